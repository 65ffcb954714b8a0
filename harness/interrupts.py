"""SIGINT and SIGTERM that cannot be lost: the signal is recorded before the KeyboardInterrupt is raised.

Python raises a signal handler's exception wherever the main thread happens to be. When that is a `__del__`, a
weakref callback or a `finally` that swallows it (MuJoCo's render context is finalised while a model loads), the
KeyboardInterrupt is printed as "Exception ignored" and lost, and the command went on to exit 0 (2 of 8 Ctrl-C
during model loading). `handler` records the signal in `received` first; the run driver and the command line
`check()` it at their next safe point, so the command still ends with 128 + signum. `quiet_unraisable` keeps such a
swallowed Interrupted from printing "Exception ignored ... Traceback" above the one line (it is recorded already).
"""

from __future__ import annotations

import ctypes
import signal

received: int | None = None  # the first SIGINT / SIGTERM since `reset()`


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; `signum` says which (exit code 128 + signum)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def record(signum: int) -> None:
    global received
    if received is None:
        received = signum


def handler(signum, frame) -> None:
    record(signum)
    raise Interrupted(signum)


def quiet_unraisable(previous):
    """A `sys.unraisablehook` that, once a signal is recorded, drops what Python can only ignore: an Interrupted
    raised in a gc callback or a `__del__` (every Interrupted is raised after `record`, and `check()` ends the command
    with the one line), and the error of an object the interrupt left half-built failing in its `__del__`
    (robosuite's render context, stopped before its `con` was set: AttributeError); the command is ending with
    128 + signum anyway. Before a signal everything goes to `previous`."""

    def hook(unraisable) -> None:
        if received is not None:
            return
        previous(unraisable)

    return hook


def check() -> None:
    """Raise Interrupted when a signal arrived whose KeyboardInterrupt may have been swallowed."""
    if received is not None:
        raise Interrupted(received)


def reset() -> None:
    global received
    received = None


def die_with_parent() -> None:
    """Linux: the kernel sends this process SIGKILL when its parent dies, so a worker never outlives a killed driver
    (PR_SET_PDEATHSIG; elsewhere a no-op). Call it first in a worker process, or as a pool's initializer."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
