"""SIGINT and SIGTERM that cannot be lost: the signal is recorded before the KeyboardInterrupt is raised.

Python raises a signal handler's exception wherever the main thread happens to be. When that is a `__del__`, a
weakref callback or a `finally` that swallows it (MuJoCo's render context is finalised while a model loads), the
KeyboardInterrupt is printed as "Exception ignored" and lost, and the command went on to exit 0 (2 of 8 Ctrl-C
during model loading). `handler` records the signal in `received` first; the run driver and the command line
`check()` it at their next safe point, so the command still ends with 128 + signum. `quiet_unraisable` keeps such a
swallowed Interrupted from printing "Exception ignored ... Traceback" above the one line (it is recorded already).

A signal that lands while a module is imported is not raised there: an exception raised inside a compiled
extension's initialisation (jaxlib's, while its enums are built) cannot unwind through it, and the process aborted
(exit -6, no line; 1 of 40 Ctrl-C at 0.2-2 s after start). `deliver` records it and returns; a watcher thread sends
the same signal again as soon as the main thread has left the import, so it is raised at the next line of Python
(docs/run-integrity.md). A second signal while the first waits is raised at once: an import that never ends cannot
hold a command.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

received: int | None = None  # the first SIGINT / SIGTERM since `reset()`
_raised = False  # an Interrupted was raised since `reset()`: a re-sent signal then has nothing left to do
_resent = False  # the signal in flight is the watcher's, not the user's
_deferred = False  # a signal landed inside an import and waits for the watcher
_watcher: threading.Thread | None = None
_stop = threading.Event()
IMPORT_FRAMES = "<frozen importlib._bootstrap"  # the import system's frames (both modules' names start so)
RESEND_POLL_S = 0.02


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
    deliver(signum, frame)


def deliver(signum: int, frame) -> None:
    """Raise Interrupted for a recorded signal, unless `frame` is inside an import: then return and have the watcher
    send the signal again once the main thread is out of it (a handler calls this last)."""
    global _resent, _raised, _deferred
    resent, _resent = _resent, False
    if resent and _raised:  # the command is ending with 128 + signum already
        return
    if _importing(frame) and not (_deferred and not resent):  # a second Ctrl-C while one waits: raised at once
        _deferred = True
        _watch(signum)
        return
    _raised, _deferred = True, False
    raise Interrupted(signum)


def _importing(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith(IMPORT_FRAMES):
            return True
        frame = frame.f_back
    return False


def _watch(signum: int) -> None:
    """Start (once) the thread that re-sends `signum` when the main thread has left every import."""
    global _watcher
    if _watcher is not None and _watcher.is_alive():
        return
    main = threading.main_thread().ident
    _stop.clear()

    def run() -> None:
        global _resent
        while not _stop.wait(RESEND_POLL_S):
            if _raised:
                return
            if not _importing(sys._current_frames().get(main)):
                _resent = True
                os.kill(os.getpid(), signum)
                return

    _watcher = threading.Thread(target=run, name="interrupt-resend", daemon=True)
    _watcher.start()


def settle(timeout: float = 1.0) -> None:
    """Stop the watcher (before a command restores the handlers it replaced), so no re-sent signal outlives them."""
    _stop.set()
    if _watcher is not None:
        _watcher.join(timeout)
        # a signal it sent may still wait for the main thread: give it the handler still installed
        deadline = time.monotonic() + 0.05
        while _resent and time.monotonic() < deadline:
            time.sleep(0.005)


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
    global _raised
    if received is not None:
        _raised = True
        raise Interrupted(received)


def reset() -> None:
    global received, _raised, _resent, _deferred
    settle()
    received, _raised, _resent, _deferred = None, False, False, False


def die_with_parent() -> None:
    """Linux: the kernel sends this process SIGKILL when its parent dies, so a worker never outlives a killed driver
    (PR_SET_PDEATHSIG; elsewhere a no-op). Call it first in a worker process, or as a pool's initializer."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
