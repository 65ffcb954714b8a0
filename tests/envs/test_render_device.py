"""--render-device cpu|gpu|N (OCTO_HARNESS_RENDER_DEVICE): where MuJoCo renders, whatever device JAX computes on, set
up before MuJoCo loads and recorded in the manifest's platform.gl. No GPU is lent to this machine: the GPU choices
are tested for the variables they set and the errors they give; the CPU choice renders for real (Mesa llvmpipe)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from envs.gl import HeadlessGLError, render_device_settings

REPO = Path(__file__).resolve().parents[2]


def test_cpu_renders_with_mesa_egl_only_else_osmesa(tmp_path):
    vendor = tmp_path / "50_mesa.json"
    vendor.write_text("{}")
    assert render_device_settings("cpu", {}, mesa_vendor=str(vendor)) == {
        "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl", "__EGL_VENDOR_LIBRARY_FILENAMES": str(vendor),
        "LIBGL_ALWAYS_SOFTWARE": "1"}
    assert render_device_settings("cpu", {"MUJOCO_GL": "osmesa"}, mesa_vendor=str(vendor))["MUJOCO_GL"] == "osmesa"
    missing = str(tmp_path / "none.json")
    assert render_device_settings("cpu", {}, mesa_vendor=missing, osmesa_found=lambda: True)["MUJOCO_GL"] == "osmesa"
    with pytest.raises(HeadlessGLError, match=r"needs Mesa's EGL .* or OSMesa; fix: `apt-get install -y libegl-mesa0`"):
        render_device_settings("cpu", {}, mesa_vendor=missing, osmesa_found=lambda: False)
    with pytest.raises(HeadlessGLError, match="MUJOCO_GL=glfw is set; unset MUJOCO_GL"):
        render_device_settings("cpu", {"MUJOCO_GL": "glfw"}, mesa_vendor=str(vendor))


def test_gpu_and_a_device_number_render_with_egl():
    assert render_device_settings("gpu", {}) == {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
    assert render_device_settings("1", {"MUJOCO_GL": "egl"})["MUJOCO_EGL_DEVICE_ID"] == "1"
    with pytest.raises(HeadlessGLError, match="MUJOCO_GL=osmesa is set"):
        render_device_settings("gpu", {"MUJOCO_GL": "osmesa"})
    with pytest.raises(HeadlessGLError, match="MUJOCO_EGL_DEVICE_ID=0 is set; keep one of them"):
        render_device_settings("1", {"MUJOCO_EGL_DEVICE_ID": "0"})
    with pytest.raises(HeadlessGLError, match="use cpu, gpu or an EGL device number"):
        render_device_settings("tpu", {})


def _cli(args, tmp_path, **env):
    environ = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    environ.update(HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO), **env)
    return subprocess.run([sys.executable, "-m", "harness.cli", *args], cwd=REPO, env=environ, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.slow
def test_a_render_device_that_conflicts_is_one_line_before_anything_runs(tmp_path, fixtures_dir):
    done = _cli(["run", "--render-device", "gpu", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out",
                 str(tmp_path), "--run-name", "r"], tmp_path, MUJOCO_GL="osmesa")
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(errors) == 1 and "--render-device gpu renders with EGL" in errors[0], done.stderr
    assert not (tmp_path / "r").exists()
    done = _cli(["run", "--render-device", "first", "--task", "Lift"], tmp_path)
    assert done.returncode == 2 and "--render-device takes cpu, gpu or an EGL device number" in done.stderr


@pytest.mark.slow
def test_render_device_cpu_renders_with_llvmpipe_and_is_recorded(tmp_path, fixtures_dir):
    done = _cli(["run", "--render-device", "cpu", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--episodes",
                 "1", "--max-steps", "1", "--png-every", "0", "--no-video", "--fast-render", "--out", str(tmp_path),
                 "--run-name", "r"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    gl = json.loads((tmp_path / "r" / "manifest.json").read_text())["platform"]["gl"]
    assert gl["render_device"] == "cpu" and gl["egl_device_id"] is None
    assert "llvmpipe" in gl["renderer"] or gl["backend"] == "osmesa", gl
