"""A pytest plugin that records every file a test process opens or lists outside the places a clone may read.

Loaded by tests/test_standalone.py in a copy of the repository with nothing beside it (`-p tests._path_audit`):
Python's audit hooks (PEP 578) report each `open`, `os.listdir`, `os.scandir` and `os.mkdir`, whatever opens it
(numpy, json, jax). A path is allowed when it lies in the repository (OCTO_AUDIT_ROOT), in the Python installation or
virtual environment that runs the tests, in the system's folders and the user's caches, or in a temporary folder that is not the
repository's parent. The offending paths, each with the test that touched it, go to OCTO_AUDIT_LOG at the end.
"""

import json
import os
import sys
import tempfile

ROOT = os.path.realpath(os.environ["OCTO_AUDIT_ROOT"])
PARENT = os.path.dirname(ROOT)
SYSTEM = ("/usr", "/lib", "/lib64", "/bin", "/sbin", "/etc", "/opt", "/proc", "/sys", "/dev", "/run", "/var/lib",
          "/var/cache")
HOME = os.path.expanduser("~")
USER = tuple(os.path.join(HOME, d) for d in (".cache", ".config", ".local", ".fonts"))  # libraries' per-user caches
# Caches the calling test process shares (the suite's XLA compilation cache): a speed-up, never an input
SHARED = tuple(p for p in os.environ.get("OCTO_AUDIT_ALLOW", "").split(os.pathsep) if p)
PYTHON = {os.path.realpath(p) for p in (sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix)}
TEMP = os.path.realpath(tempfile.gettempdir())
EVENTS = ("open", "os.listdir", "os.scandir", "os.mkdir")
_seen: dict[str, str] = {}
_busy = [False]


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip("/") + "/")


def allowed(path: str) -> bool:
    if _inside(path, ROOT):
        return True
    if _inside(path, PARENT):  # beside the repository: ../shared and every other sibling
        return False
    return any(_inside(path, p) for p in (*PYTHON, *SYSTEM, *USER, *SHARED, TEMP))


def _hook(event: str, args: tuple) -> None:
    if event not in EVENTS or _busy[0] or not args:
        return
    target = args[0]
    if isinstance(target, bytes):
        target = os.fsdecode(target)
    if not isinstance(target, str) or not target:
        return  # a file descriptor, or the current folder
    _busy[0] = True
    try:
        path = os.path.realpath(target)
        if not allowed(path) and path not in _seen:
            _seen[path] = os.environ.get("PYTEST_CURRENT_TEST", "(collection)").split(" ")[0]
    finally:
        _busy[0] = False


sys.addaudithook(_hook)


def pytest_unconfigure(config):
    _busy[0] = True
    with open(os.environ["OCTO_AUDIT_LOG"], "w") as f:
        json.dump(_seen, f, indent=1, sort_keys=True)
