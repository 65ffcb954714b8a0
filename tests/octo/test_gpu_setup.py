"""GPU set-up: the cuda extra matches the jax pin; asking for a GPU where JAX finds none is one line naming the fix."""

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from harness.run.checks import check_accelerator

REPO = Path(__file__).resolve().parents[2]


def test_cuda_extra_brings_jax_cuda12_wheels_at_the_pinned_jax_version():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    [jax_pin] = [d for d in project["dependencies"] if d.startswith("jax")]
    [cuda] = project["optional-dependencies"]["cuda"]
    assert cuda == jax_pin.replace("jax", "jax[cuda12]", 1)


def test_no_gpu_asked_for_is_no_check():
    check_accelerator({})
    check_accelerator({"JAX_PLATFORMS": "cpu"})


@pytest.mark.slow
def test_gpu_asked_for_where_jax_finds_none_is_one_line(tmp_path):
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('gpu')"], capture_output=True,
                           env=dict(os.environ, JAX_PLATFORMS=""))
    if probe.returncode == 0:
        pytest.skip("this machine has a CUDA GPU: the no-GPU error cannot happen here")
    env = dict(os.environ, JAX_PLATFORMS="cuda", HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO))
    result = subprocess.run([sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--model",
                             "random:octo-small-1.5", "--out", str(tmp_path), "--run-name", "gpu"],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert result.returncode == 2 and len(errors) == 1, result.stderr[-2000:]
    assert "JAX_PLATFORMS=cuda" in errors[0] and "octo-harness[cuda]" in errors[0]
    assert "Traceback" not in result.stderr and not (tmp_path / "gpu").exists()
