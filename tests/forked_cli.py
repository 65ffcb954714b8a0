"""`octo-harness ARGV` in a process of its own, without paying the interpreter's imports each time.

A forkserver imports the command line and builds its parser once (which imports JAX, MuJoCo and the simulators:
2.5-3.5 s a process on 2 cores); each command is a child forked from that server, so it starts with the server's
modules and nothing else: no JAX backend, no GL context and no thread of the server's (the server never ran any).
The child caps its address space, takes its environment, writes stdout and stderr to files (the C libraries' writes
too) and runs `harness.cli.main(argv)`: the real command, in a process of its own, with its own exit code.
"""

from __future__ import annotations

import multiprocessing
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PRELOAD = "tests._cli_preload"  # imports harness.cli and builds its parser in the server


def _child(argv: list[str], env: dict, cap: int | None, out: str, err: str) -> None:
    if cap:
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    os.environ.update(env)
    os.chdir(REPO)
    for fd, path in ((1, out), (2, err)):
        target = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(target, fd)
        os.close(target)
    from harness.cli import main

    sys.exit(main(argv))  # Process flushes stdout and stderr and turns SystemExit into the exit code


def _context():
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([PRELOAD])
    return context


def run(argv: list[str], env: dict | None = None, cap: int | None = None, timeout: float = 60
        ) -> tuple[int, str, str, float] | None:
    """(exit code, stdout, stderr, seconds), or None when the command did not end within `timeout` (killed)."""
    with tempfile.TemporaryDirectory(prefix="forked-cli-") as tmp:
        out, err = os.path.join(tmp, "out"), os.path.join(tmp, "err")
        start = time.perf_counter()
        process = _context().Process(target=_child, args=(list(argv), dict(env or {}), cap, out, err))
        process.start()
        process.join(timeout)
        seconds = time.perf_counter() - start
        if process.exitcode is None:
            process.kill()
            process.join()
            return None
        read = lambda path: Path(path).read_text(errors="replace") if os.path.exists(path) else ""  # noqa: E731
        return process.exitcode, read(out), read(err), seconds
