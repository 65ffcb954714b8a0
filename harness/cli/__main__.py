"""`python -m harness.cli ...`: the same as the `octo-harness` console script."""

import sys

from harness.cli import main

if __name__ == "__main__":
    sys.exit(main())
