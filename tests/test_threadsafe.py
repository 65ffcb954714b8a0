"""Array headers read from many threads at once (harness/threadsafe.py, issue 66): CPython 3.11's AST constructor
is not thread-safe (gh-106905), and numpy parses every .npy header with it.

The interpreter switches threads in the middle of a parse when a garbage collection runs a finaliser written in
Python (numpy's NpzFile has one, matplotlib's objects too). A real command makes such garbage now and then; this test
makes it on purpose and collects often, so that a few thousand parses meet the race. Without the lock
(`ast.parse.__wrapped__` put back) the same workload failed in 29 of 30 tries on CPython 3.11.7 here (up to 6 of
its 8 threads raised SystemError in a try); with it, in 0 of 30.
"""

from __future__ import annotations

import ast
import gc
import os
import signal
import sys
import threading

import numpy as np
import pytest

import harness  # noqa: F401 - installs the lock, as every command does
from harness.bounded import npz_headers, open_npz, read_npz

THREADS = 8
ROUNDS = 60  # per thread: 8 x 60 x 12 members = 5760 header parses
MEMBERS = 12


class _Cycle:
    """Garbage that only the cycle collector frees, with a finaliser that runs Python code."""

    def __init__(self):
        self.me = self

    def __del__(self):
        sum(range(20))


def make_arrays(folder) -> list[str]:
    paths = []
    for i in range(6):
        path = os.path.join(folder, f"episode_{i}.npz")
        np.savez(path, **{f"member_{j}": np.full((2, j + 1), i, np.float32) for j in range(MEMBERS)})
        paths.append(path)
    return paths


def hammer(paths: list[str], threads: int = THREADS, rounds: int = ROUNDS) -> list[str]:
    """Each thread reads headers every way a command does (harness.bounded's own check, np.load through read_npz,
    a lazy NpzFile indexed member by member) while making cyclic garbage; the errors raised, one per thread at most."""
    errors: list[str] = []

    def work(k: int) -> None:
        try:
            for r in range(rounds):
                garbage = [_Cycle() for _ in range(20)]  # noqa: F841 - collected mid-parse, in some other thread
                path = paths[(k + r) % len(paths)]
                if r % 3 == 0:
                    assert len(npz_headers(path)) == MEMBERS
                elif r % 3 == 1:
                    assert read_npz(path)["member_0"].shape == (2, 1)
                else:
                    with open_npz(path) as z:
                        assert all(z[name].dtype == np.float32 for name in z.files)
        except Exception as exc:  # noqa: BLE001 - every kind counts
            errors.append(f"{type(exc).__name__}: {exc}")

    interval, thresholds = sys.getswitchinterval(), gc.get_threshold()
    sys.setswitchinterval(1e-6)  # switch threads as often as the interpreter can
    gc.set_threshold(5, 5, 5)  # and collect cycles every few allocations
    try:
        workers = [threading.Thread(target=work, args=(k,)) for k in range(threads)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    finally:
        sys.setswitchinterval(interval)
        gc.set_threshold(*thresholds)
    return errors


def test_the_harness_package_locks_the_parse():
    assert getattr(ast.parse, "__wrapped_by_harness__", False)
    assert ast.literal_eval("{'descr': '<f4', 'shape': (2, 3)}") == {"descr": "<f4", "shape": (2, 3)}
    assert np.lib.format.read_array_header_1_0 is not None  # numpy's parse reaches ast.parse through literal_eval


def test_many_threads_read_many_arrays_at_once(tmp_path):
    errors = hammer(make_arrays(tmp_path))
    assert errors == []


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork here")
def test_a_child_forked_while_a_thread_holds_the_lock_can_parse():
    from harness import threadsafe

    held, release = threading.Event(), threading.Event()

    def hold():
        with threadsafe._LOCK:
            held.set()
            release.wait(10)

    thread = threading.Thread(target=hold)
    thread.start()
    held.wait(10)
    try:
        pid = os.fork()
        if pid == 0:  # the child: a parse that would wait forever on the parent's held lock
            signal.alarm(10)
            ast.parse("x = 1")
            os._exit(0)
    finally:
        release.set()
        thread.join()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
