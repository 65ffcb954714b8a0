"""Python's `ast` made safe to call from several threads at once, for every module of the process.

CPython 3.11 (3.11.7 here) keeps the AST constructor's recursion depth in one counter per interpreter. Two threads
that build syntax trees at once corrupt it, and one of them fails with `SystemError: AST constructor recursion depth
mismatch` (CPython gh-106905). numpy parses every `.npy` header with `ast.literal_eval`: in `np.load`, in a lazy
`NpzFile`'s indexing and in harness.bounded's own header check. So a command that reads arrays from two threads
(`report` does, from its overlay pool) fails at random.

`install()` wraps `ast.parse`, through which `ast.literal_eval` and numpy's header parse go, in one process-wide
lock. It runs once, when the `harness` package is imported, so every command and every worker process that imports
any harness module has it. A header's parse takes about 60 us here and the lock adds under 1 us to it (the least of
10 timings each). A forked child gets a fresh lock (a thread of the parent may have held it at the fork).
"""

from __future__ import annotations

import ast
import functools
import os
import threading

_LOCK = threading.RLock()  # reentrant: a finaliser that parses while this thread holds it does not deadlock


def _fresh_lock() -> None:
    global _LOCK
    _LOCK = threading.RLock()


def install() -> None:
    """Wrap `ast.parse` in the process-wide lock (idempotent)."""
    if getattr(ast.parse, "__wrapped_by_harness__", False):
        return
    parse = ast.parse

    @functools.wraps(parse)
    def locked_parse(*args, **kwargs):
        with _LOCK:
            return parse(*args, **kwargs)

    locked_parse.__wrapped_by_harness__ = True
    ast.parse = locked_parse
    os.register_at_fork(after_in_child=_fresh_lock)
