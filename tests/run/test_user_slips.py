"""Small things a new user tripped on: a protocol file key given twice, a run name with a newline, a copied run folder,
the steps of an episode that failed while finishing its files, SIGTERM while the model loads, one error prefix."""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from harness import cli
from harness.run.checks import check_run_name
from harness.run.settings import read_protocol_file

REPO = Path(__file__).resolve().parents[2]


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines()]


def test_protocol_file_with_a_key_given_twice_is_refused(tmp_path):
    path = tmp_path / "eval.toml"
    path.write_text('task = "Lift"\nmax_steps = 2\nmax-steps = 3\n')
    with pytest.raises(ValueError, match="max_steps given twice"):
        read_protocol_file(path)


@pytest.mark.parametrize("name", ["a\nb", "tab\there", "trailing ", "bell\x07"])
def test_run_name_with_control_characters_is_refused(name, tmp_path, capsys):
    with pytest.raises(ValueError, match="control characters"):
        check_run_name(name)
    code = cli.main(["run", "--task", "Lift", "--model", "random:octo-small-1.5", "--out", str(tmp_path),
                     "--run-name", name])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --run-name") and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_one_error_prefix_for_every_user_error():
    from envs.gl import HeadlessGLError
    from harness.octo.errors import OctoError
    from harness.run.store import RunLockedError

    assert {HeadlessGLError, OctoError, RunLockedError, ValueError, FileNotFoundError} <= set(cli._user_errors())
    source = "".join(p.read_text() for p in (REPO / "harness").rglob("*.py"))
    assert 'print(f"Error' not in source and "print('Error" not in source


@pytest.mark.slow
def test_headless_gl_failure_is_one_error_line_not_a_traceback(tmp_path):
    """PyOpenGL told another platform than MuJoCo's EGL: the GL check's message, as every user error, exit 2."""
    env = dict(os.environ, HF_HUB_OFFLINE="1", MUJOCO_GL="egl", PYOPENGL_PLATFORM="glfw", PYTHONPATH=str(REPO))
    result = subprocess.run([sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--model",
                             str(REPO / "models" / "octo-reference-robosuite"), "--max-steps", "1", "--out",
                             str(tmp_path), "--run-name", "gl"], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=300)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert lines[-1].startswith("error: headless OpenGL unavailable") and "apt-get install" in lines[-1]


@pytest.mark.slow
def test_copied_run_folder_takes_its_new_name_in_every_record(fixtures_dir, tmp_path, capsys):
    args = ["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--episodes", "2", "--max-steps", "1",
            "--png-every", "0", "--no-video", "--fast-render", "--out", str(tmp_path)]
    assert cli.main([*args, "--run-name", "a"]) == 0
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    b = tmp_path / "b"
    lines = (b / "results.jsonl").read_text().splitlines()
    (b / "results.jsonl").write_text(lines[0] + "\n")  # the copy is of a run that had one episode left to run
    shutil.rmtree(b / "Lift" / "episode_1")
    assert cli.main([*args, "--run-name", "b"]) == 0
    capsys.readouterr()
    manifest = json.loads((b / "manifest.json").read_text())
    assert manifest["run"] == "b" and manifest["renamed_from"] == "a"
    assert [r["run"] for r in _rows(b)] == ["b", "b"]
    assert {e["run"] for e in json.loads((b / "results.json").read_text())["episodes"]} == {"b"}
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["run"] == "a"  # the original is untouched


@pytest.mark.slow
def test_episode_failing_while_finishing_its_files_records_the_steps_that_ran(fixtures_dir, tmp_path, capsys,
                                                                             monkeypatch):
    import harness.files
    import harness.outputs.data_files

    original = harness.files.write_atomic

    def write_atomic(path, write):  # the episode's arrays meet a failing device when the episode is finished (a full
        if Path(path).name == "attention.npz":  # disk stops the run instead: tests/run/test_disk_space.py)
            raise OSError(errno.EIO, os.strerror(errno.EIO), str(path))
        return original(path, write)

    monkeypatch.setattr(harness.outputs.data_files, "write_atomic", write_atomic)  # the npz and jsonl sinks
    code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--max-steps", "3",
                     "--png-every", "0", "--fast-render", "--out", str(tmp_path), "--run-name", "full"])
    capsys.readouterr()
    [row] = _rows(tmp_path / "full")
    assert code == 1 and row["status"] == "failed" and os.strerror(errno.EIO) in row["error"]
    assert row["steps"] == 3
    episode = json.loads((tmp_path / "full" / "Lift" / "episode_0" / "episode.json").read_text())
    assert episode["status"] == "failed" and episode["steps"] == 3


@pytest.mark.slow
def test_sigterm_while_the_model_loads_exits_143_with_a_message(tmp_path):
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--model",
                             "random:octo-base-1.5", "--out", str(tmp_path), "--run-name", "t"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = []
    for line in proc.stderr:  # the driver says when loading starts
        seen.append(line)
        if "loading random:octo-base-1.5" in line:
            break
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 143, "".join(seen) + err
    assert "interrupted (SIGTERM)" in err
    assert not (tmp_path / "t").exists()  # nothing was started: no run folder left behind
