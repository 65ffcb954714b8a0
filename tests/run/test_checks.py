"""Checks before anything heavy: every bad input of `octo-harness run` exits 2 with one line, before the model
loads (or right after it for model-dependent ones), before any episode runs; protocol changes and concurrent
runs refuse; --overwrite starts afresh. Real model (the tiny reference fixture) and real simulator."""

import json
import os
import subprocess

import numpy as np
import pytest

import harness.octo
from harness import cli
from harness.run.store import RunStore


@pytest.fixture
def tiny(fixtures_dir):
    return str(fixtures_dir / "tiny")


@pytest.fixture
def no_model_load(monkeypatch):
    """Fail the test if the model is loaded: the check under test must come first."""
    def refuse(*args, **kwargs):
        raise AssertionError("the model was loaded before the check")

    monkeypatch.setattr(harness.octo, "load_pretrained", refuse)


def _run(capsys, *args):
    code = cli.main(["run", *map(str, args)])
    captured = capsys.readouterr()
    return code, [line for line in captured.err.splitlines() if line.startswith("error:")], captured


def _one_line_error(capsys, needle, *args):
    code, errors, captured = _run(capsys, *args)
    assert code == 2, captured.err[-2000:]
    assert len(errors) == 1 and needle in errors[0], captured.err[-2000:]
    return errors[0]


BASE = ("--task", "Lift", "--max-steps", "1", "--png-every", "0", "--no-video", "--fast-render")


@pytest.mark.parametrize("args,needle", [
    (("--task", "Lift", "--episodes", "0"), "--episodes must be at least 1"),
    (("--task", "Lift", "--max-steps", "-5"), "--max-steps must be at least 1"),
    (("--task", ""), "no task given"),
    (("--task", " , "), "no task given"),
    ((), "no task given"),
    (("--task", "Lift", "--run-name", "../../x"), "not a plain folder name"),
    (("--task", "Lift", "--run-name", "/abs/x"), "not a plain folder name"),
    (("--task", "Lift", "--ensemble-weight", "nan"), "--ensemble-weight must be a finite number"),
    (("--task", "Lift", "--camera", "image_primary=agentview"), "KEY=camera:size"),
])
def test_bad_numbers_names_and_paths_fail_before_loading(capsys, tmp_path, tiny, no_model_load, args, needle):
    base = ["--model", tiny, "--out", tmp_path / "out"]
    _one_line_error(capsys, needle, *base, *args)
    assert not list((tmp_path / "out").glob("*"))  # nothing written (no run folder)
    assert not (tmp_path / "x").exists()


def test_out_that_is_a_file_or_read_only_fails_before_loading(capsys, tmp_path, tiny, no_model_load):
    blocker = tmp_path / "file"
    blocker.write_text("")
    _one_line_error(capsys, "is a file", "--task", "Lift", "--model", tiny, "--out", blocker)
    _one_line_error(capsys, "cannot be created", "--task", "Lift", "--model", tiny, "--out", blocker / "sub")
    read_only = tmp_path / "ro"
    read_only.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(read_only)],
                             capture_output=True).returncode == 0
    if not mounted:  # not root: a folder without write permission does the same for an ordinary user
        os.chmod(read_only, 0o500)
    try:
        _one_line_error(capsys, "not writable", "--task", "Lift", "--model", tiny, "--out", read_only)
    finally:
        if mounted:
            subprocess.run(["umount", str(read_only)], check=True)


def test_unknown_mujoco_gl_names_the_valid_ones(capsys, tmp_path, tiny, no_model_load, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "vulkan")
    line = _one_line_error(capsys, "MUJOCO_GL='vulkan'", "--task", "Lift", "--model", tiny, "--out", tmp_path)
    assert all(name in line for name in ("egl", "osmesa", "glfw"))


def test_goal_image_that_does_not_decode_is_named(capsys, tmp_path, tiny, no_model_load):
    goals = tmp_path / "goals"
    goals.mkdir()
    (goals / "image_primary.png").write_bytes(b"not a png at all")
    _one_line_error(capsys, str(goals / "image_primary.png"), "--task", "Lift", "--model", tiny, "--out", tmp_path,
                    "--goal-images", goals)


def test_protocol_file_with_unknown_key_is_one_line(capsys, tmp_path, no_model_load):
    path = tmp_path / "eval.toml"
    path.write_text('task = "Lift"\nepisodes = 2\nmax_step = 3\n')
    _one_line_error(capsys, "max_step", "--protocol", path)


def test_concurrent_run_refuses_naming_the_holder(capsys, tmp_path, tiny, no_model_load):
    holder = RunStore(tmp_path / "busy")
    holder.lock()
    try:
        _one_line_error(capsys, f"in use by process {os.getpid()}", *BASE, "--model", tiny, "--out", tmp_path,
                        "--run-name", "busy")
    finally:
        holder.unlock()


@pytest.mark.slow
@pytest.mark.parametrize("args,needle", [
    (("--layers", "0,99"), "--layers 99 is out of range"),
    (("--video-attention", "50"), "--video-attention 50 is out of range"),
    (("--execution", "receding_horizon", "--receding-steps", "99"), "--receding-steps 99 exceeds the action horizon"),
    (("--dataset-key", "nope"), "unknown dataset key"),
    (("--camera", "image_primary=agentview:64"), "image_wrist"),  # the model also needs a wrist camera
])
def test_model_dependent_checks_fail_before_any_episode(capsys, tmp_path, tiny, args, needle):
    _one_line_error(capsys, needle, *BASE, "--model", tiny, "--out", tmp_path, "--run-name", "r", *args)
    assert not (tmp_path / "r").exists()  # no episode ran, no run folder is left behind


@pytest.mark.slow
def test_language_model_with_goal_images_gets_both(capsys, tmp_path, tiny):
    goals = tmp_path / "goals"
    goals.mkdir()
    rng = np.random.default_rng(0)
    import imageio.v3 as iio

    iio.imwrite(goals / "image_primary.png", rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    iio.imwrite(goals / "image_wrist.png", rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
    actions = []
    for name, instruction in (("a", "pick up the red cube"), ("b", "open the door")):
        code, _, captured = _run(capsys, *BASE, "--model", tiny, "--out", tmp_path, "--run-name", name,
                                 "--goal-images", goals, "--instruction", instruction)
        assert code == 0, captured.err[-2000:]
        manifest = json.loads((tmp_path / name / "manifest.json").read_text())
        assert manifest["task_inputs"] == ["language", "goal"]
        assert manifest["goal_images"] == str(goals.resolve()) and manifest["protocol"]["goal_fingerprint"]
        with np.load(tmp_path / name / "Lift" / "episode_0" / "actions.npz") as z:
            actions.append(z["predicted"])
    assert not np.array_equal(*actions)  # the instruction still reaches the model when goals are given


@pytest.mark.slow
def test_different_protocol_refuses_and_overwrite_starts_afresh(capsys, tmp_path, tiny):
    args = [*BASE, "--model", tiny, "--out", tmp_path, "--run-name", "m"]
    assert _run(capsys, *args)[0] == 0
    line = _one_line_error(capsys, "differs: max_steps, seed", *args, "--max-steps", "2", "--seed", "5")
    assert "--overwrite" in line
    code, _, captured = _run(capsys, *args, "--max-steps", "2", "--overwrite")
    assert code == 0, captured.err[-2000:]
    results = json.loads((tmp_path / "m" / "results.json").read_text())
    assert results["manifest"]["protocol"]["max_steps"] == 2 and [e["steps"] for e in results["episodes"]] == [2]
    assert len((tmp_path / "m" / "results.jsonl").read_text().splitlines()) == 1  # the old run's record is gone
    # the same command again: nothing to do, the complete run is reported
    code, _, captured = _run(capsys, *args, "--max-steps", "2")
    assert code == 0 and "1 of 1 episodes were already finished" in captured.out
    code, _, captured = _run(capsys, "--resume", tmp_path / "m")
    assert code == 0 and "already finished" in captured.out
