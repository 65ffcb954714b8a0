"""A Ctrl-C that lands while a module is imported is raised after the import, never inside it (harness/interrupts.py).

Raised inside a compiled extension's initialisation (jaxlib builds its enums in Python while its module is created),
the exception cannot unwind and the process aborts (exit -6, no line; CI, 0.5 s after start). A module whose own body
sends the signal stands in for that moment: it lands inside the import every time."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SLOW_MODULE = """
import os, signal, time
os.kill(os.getpid(), signal.SIG{name})
end = time.monotonic() + 0.3
while time.monotonic() < end:  # Python lines run here after the signal: the handler is called inside the import
    pass
FINISHED = time.monotonic()
"""

DRIVER = """
import signal, sys, time
sys.path.insert(0, sys.argv[1])
from harness.cli import _interrupt
from harness import interrupts
signal.signal(signal.SIGINT, _interrupt)
signal.signal(signal.SIGTERM, _interrupt)
finished = None
try:
    import slow_module
    finished = slow_module.FINISHED
    end = time.monotonic() + 10
    while time.monotonic() < end:
        pass
    print("not interrupted")
except interrupts.Interrupted as exc:
    print("interrupted", exc.signum, finished is not None, round(time.monotonic() - finished, 3) if finished else None)
"""


def _run(tmp_path: Path, module: str) -> list[str]:
    """What DRIVER printed after importing `module`'s text as slow_module."""
    (tmp_path / "slow_module.py").write_text(module)
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(DRIVER), str(tmp_path)], capture_output=True, text=True,
                          timeout=120, cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.split()


def test_a_sigint_inside_an_import_is_raised_once_the_import_has_finished(tmp_path):
    interrupted, signum, finished, after = _run(tmp_path, SLOW_MODULE.format(name="INT"))
    assert (interrupted, signum, finished) == ("interrupted", "2", "True")  # the module's body ran to its end
    assert float(after) < 1.0  # then the signal was raised at once, not after the 10 s loop


def test_a_sigterm_inside_an_import_is_raised_once_the_import_has_finished(tmp_path):
    interrupted, signum, finished, after = _run(tmp_path, SLOW_MODULE.format(name="TERM"))
    assert (interrupted, signum, finished) == ("interrupted", "15", "True")
    assert float(after) < 1.0


HANGING_MODULE = """
import os, signal, time
os.kill(os.getpid(), signal.SIGINT)
end = time.monotonic() + 0.3
while time.monotonic() < end:
    pass
os.kill(os.getpid(), signal.SIGINT)  # the user presses Ctrl-C again: an import that never ends
while True:
    pass
"""


def test_a_second_sigint_while_the_first_waits_for_an_import_is_raised_at_once(tmp_path):
    assert _run(tmp_path, HANGING_MODULE)[:3] == ["interrupted", "2", "False"]  # raised inside the import that never ends
