"""Helpers the test files share: the repository root, headless Chromium, the LIBERO-environment guard, and the
processes a command leaves."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REFERENCE_MODEL = REPO / "models" / "octo-reference-robosuite"


def chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        if shutil.which(name):
            return shutil.which(name)
    raise FileNotFoundError("chromium not found: install Debian's chromium (apt-get install --no-install-recommends "
                            "chromium; scripts/test.sh does it)")


def browser(html: Path, tmp: Path, *args: str) -> subprocess.CompletedProcess:
    """Headless Chromium on a local page, with the flags that keep it off this machine's closed network."""
    command = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               f"--user-data-dir={tmp / 'chromium-profile'}", "--hide-scrollbars", *args, html.as_uri()]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=True)


def needs_libero() -> None:
    """Skips outside CI, fails under CI=true, when LIBERO's environment (scripts/setup_libero.sh) is missing."""
    from envs.libero_env import LiberoEnvironmentMissing, libero_python

    try:
        libero_python()
    except LiberoEnvironmentMissing as exc:
        if os.environ.get("CI", "").strip().lower() in ("1", "true", "yes"):
            pytest.fail(f"CI=true and {exc}")
        pytest.skip(str(exc))


def descendants(pid: int) -> set[int]:
    """Every descendant process of `pid` (from /proc)."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - found
        found |= frontier
    return found


def alive(pids: set[int]) -> set[int]:
    """Those of `pids` still running (not gone, not zombies)."""
    running = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            running.add(pid)
    return running
