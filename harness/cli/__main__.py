"""`python -m harness.cli ...`: the same as the `octo-harness` console script."""

import sys

from harness.cli import main

sys.exit(main())
