"""The console of the command line: the harness's own lines on stderr, other libraries' chatter kept out of it.

By default stderr shows the `harness` and `envs` loggers from INFO up and other libraries from WARNING up, and the
known start-up noise of the libraries we use is dropped where it is logged (robosuite's private-macro-file,
robosuite_models and mink IK warnings: see `envs.robosuite_env`; JAX's TPU probe and PyOpenGL's
OpenGL_accelerate note are INFO lines, below that level). `--verbose` (or OCTO_HARNESS_VERBOSE=1, which spawned
env workers inherit) shows everything at INFO, that noise included.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import MutableMapping

VERBOSE_ENV = "OCTO_HARNESS_VERBOSE"
OWN_LOGGERS = ("harness", "envs")
FORMAT = "[%(name)s] %(message)s"


def is_verbose(environ: MutableMapping[str, str] | None = None) -> bool:
    return (os.environ if environ is None else environ).get(VERBOSE_ENV, "") not in ("", "0")


def configure(verbose: bool, environ: MutableMapping[str, str] | None = None) -> None:
    """One stderr handler on the root logger (unless it has handlers already, as logging.basicConfig: e.g. under
    pytest, which captures records itself): our loggers at INFO, the others at WARNING (INFO when `verbose`).

    Sets OCTO_HARNESS_VERBOSE in `environ` (default os.environ) so worker processes follow the same choice.
    """
    environ = os.environ if environ is None else environ
    if verbose:
        environ[VERBOSE_ENV] = "1"
    verbose = is_verbose(environ)
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(FORMAT))
        root.addHandler(handler)
    root.setLevel(logging.INFO if verbose else logging.WARNING)
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO)
