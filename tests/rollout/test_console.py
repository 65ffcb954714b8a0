"""The demo's console shows only the harness's own lines; --verbose shows the other libraries' too."""

import os
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
OWN_LINE = re.compile(r"^\[(harness|envs)(\.[\w.]+)?\] |^\[\d+/\d+\] ")  # our loggers, the per-episode progress line


def _demo(tmp_path, *extra):
    env = dict(os.environ, HF_HUB_OFFLINE="1")
    return subprocess.run(["bash", "scripts/demo.sh", "--out", str(tmp_path), "--max-steps", "2", "--png-every", "0",
                           "--no-video", *extra], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def test_demo_stderr_holds_only_the_harness_lines(tmp_path):
    result = _demo(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    foreign = [line for line in lines if not OWN_LINE.match(line)]
    assert foreign == [], "\n".join(foreign)
    assert any(line.startswith("[harness.run.driver] loading") for line in lines)
    for noise in ("macro file", "libtpu", "OpenGL_accelerate", "robosuite_models", "mink", "WARNING"):
        assert noise not in result.stderr


@pytest.mark.slow
def test_verbose_shows_the_other_libraries_lines(tmp_path):
    result = _demo(tmp_path, "--verbose")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "private macro file" in result.stderr and "OpenGL_accelerate" in result.stderr
    assert result.stderr.count("No private macro file found") == 1  # once: robosuite's handler, not the root's too
