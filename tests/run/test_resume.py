"""Runs that survive: the real CLI in a subprocess (real simulator, the tiny reference model) is killed with SIGKILL
mid-step, during MP4 finalisation and between episodes, then stopped with SIGTERM, and each time resumed; the
finished run has exactly its episodes, no temporaries, and the arrays and PNG bytes of an uninterrupted run.
A full disk (a small tmpfs, and an injected OSError) ends with one line and a consistent results.jsonl.

To stop a subprocess at an exact moment, the test starts it through a tiny wrapper that pauses (prints PAUSED and
sleeps) right after a chosen real operation: a step handed to the writer, the MP4 moved into place, a results.jsonl
line appended. Nothing is simulated: the wrapper only waits.
"""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from harness import cli

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]

PAUSING_CLI = r"""
import os, sys, time
point = os.environ["PAUSE_AT"]

def pause(tag):
    print("PAUSED " + tag, flush=True)
    time.sleep(600)

if point.startswith("step:"):
    import harness.outputs.writers as w
    n, original = int(point[5:]), w.EpisodeWriter.add_step
    def add_step(self, record):
        blocked = original(self, record)
        if record.step == n:
            # let the writer thread put this step's PNGs on disk, and ffmpeg (a process of its own, which creates its
            # output once its encoder is up: later than the PNGs under load) its temporary MP4
            deadline = time.time() + 30
            while time.time() < deadline and not (list(self.dir.glob(f"step_{n:04d}_layer_*.png"))
                                                  and list(self.dir.glob("*.tmp.*.mp4"))):
                time.sleep(0.01)
            pause(f"{self.dir.name} step {n}")
        return blocked
    w.EpisodeWriter.add_step = add_step
elif point == "mp4":
    import harness.outputs.video as v
    original = v.Mp4Writer.close
    def close(self):
        path = original(self)
        pause(f"{self.path} written")
        return path
    v.Mp4Writer.close = close
elif point == "append":
    import harness.run.store as s
    original = s.RunStore.append
    def append(self, row):
        original(self, row)
        pause(f"appended {row.directory}")
    s.RunStore.append = append

from harness import cli
sys.exit(cli.main(sys.argv[1:]))
"""

EPISODES, STEPS = 2, 3


def _args(model, out, name):
    return ["run", "--task", "Lift", "--model", model, "--episodes", str(EPISODES), "--max-steps", str(STEPS),
            "--fast-render", "--png-every", "1", "--out", str(out), "--run-name", name, "--seed", "3"]


def _env():
    """The suite's environment (its XLA compilation cache included: tests/conftest.py), offline, headless."""
    return dict(os.environ, HF_HUB_OFFLINE="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), PYTHONPATH=str(REPO))


def _start(args, env, pause_at=None):
    command = [sys.executable, "-c", PAUSING_CLI, *args] if pause_at else [sys.executable, "-m", "harness.cli", *args]
    return subprocess.Popen(command, cwd=REPO, env=dict(env, PAUSE_AT=pause_at or ""), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_paused(proc, timeout=240):
    deadline = time.time() + timeout
    while time.time() < deadline:
        line = proc.stdout.readline()
        if line.startswith("PAUSED"):
            return line.strip()
        if not line and proc.poll() is not None:
            break
    proc.kill()
    raise AssertionError(f"never paused; exit {proc.poll()}; stderr: {proc.stderr.read()[-3000:]}")


def _kill(proc, sig=signal.SIGKILL):
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    return proc.returncode, err


def _temporaries(run):
    return sorted(str(p.relative_to(run)) for p in run.rglob("*.tmp.*"))


def _jsonl(run):
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines()] \
        if (run / "results.jsonl").exists() else []


@pytest.mark.slow
def test_killed_runs_resume_to_the_files_of_an_uninterrupted_run(fixtures_dir, tmp_path, capsys):
    model = str(fixtures_dir / "tiny")
    env = _env()
    run = tmp_path / "out" / "k"
    args = _args(model, tmp_path / "out", "k")

    # 1. SIGKILL mid-step: step 1 of episode 0 handed to the writer, its PNGs on disk, the MP4 still a temp file
    proc = _start(args, env, "step:1")
    _wait_paused(proc)
    episode0 = run / "Lift" / "episode_0"
    assert (episode0 / "step_0000_layer_00.png").exists() and not (episode0 / "episode.json").exists()
    assert any(".tmp." in p.name and p.suffix == ".mp4" for p in episode0.iterdir())
    # ... while it runs, a second run into the same folder refuses, naming the holder
    second = subprocess.run([sys.executable, "-m", "harness.cli", *args], cwd=REPO, env=env, capture_output=True,
                            text=True, timeout=240)
    errors = [line for line in second.stderr.splitlines() if line.startswith("error:")]
    assert second.returncode == 2 and len(errors) == 1 and f"in use by process {proc.pid}" in errors[0], second.stderr
    _kill(proc)

    # 2. SIGKILL during MP4 finalisation: rollout.mp4 in place, arrays and episode.json not yet written
    proc = _start(args, env, "mp4")
    _wait_paused(proc)
    assert (episode0 / "rollout.mp4").exists() and not (episode0 / "episode.json").exists()
    assert not (episode0 / "attention.npz").exists()
    _kill(proc)

    # 3. SIGKILL between episodes: episode 0's line is in results.jsonl, the derived files not yet rewritten
    proc = _start(args, env, "append")
    _wait_paused(proc)
    assert [(r["task"], r["episode"]) for r in _jsonl(run)] == [("Lift", 0)]
    _kill(proc)

    # 4. SIGTERM mid-step of episode 1: handled like Ctrl-C, results say "interrupted", nothing half-written stays
    proc = _start(args, env, "step:1")
    assert "episode_1" in _wait_paused(proc)
    code, err = _kill(proc, signal.SIGTERM)
    assert code == 143, err[-3000:]
    results = json.loads((run / "results.json").read_text())
    assert results["status"] == "interrupted" and results["missing"] == 1 and len(results["episodes"]) == 1
    assert not (run / "Lift" / "episode_1").exists() and _temporaries(run) == []

    # 5. the same command finishes the run
    done = subprocess.run([sys.executable, "-m", "harness.cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "1 of 2 episodes were already finished" in done.stdout

    rows = _jsonl(run)
    assert sorted((r["task"], r["episode"]) for r in rows) == [("Lift", 0), ("Lift", 1)]  # exactly N, none twice
    assert all(r["status"] == "ok" and r["steps"] == STEPS for r in rows)
    results = json.loads((run / "results.json").read_text())
    assert results["status"] == "complete" and results["missing"] == 0
    assert _temporaries(run) == [] and sorted(p.name for p in (run / "Lift").iterdir()) == ["episode_0", "episode_1"]

    # an uninterrupted run of the same command (in this process) gives the same arrays and PNG bytes
    assert cli.main(_args(model, tmp_path / "out", "reference")) == 0
    capsys.readouterr()
    reference = tmp_path / "out" / "reference"
    for k in range(EPISODES):
        a, b = run / "Lift" / f"episode_{k}", reference / "Lift" / f"episode_{k}"
        assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
        for name in ("actions.npz", "attention.npz"):
            with np.load(a / name) as za, np.load(b / name) as zb:
                assert za.files == zb.files
                for key in za.files:
                    np.testing.assert_array_equal(za[key], zb[key], err_msg=f"episode {k} {name}:{key}")
        pngs = sorted(a.glob("step_*.png"))
        assert len(pngs) == STEPS * 2
        for png in pngs:
            assert png.read_bytes() == (b / png.name).read_bytes(), f"episode {k} {png.name}"
        assert (a / "rollout.mp4").read_bytes() == (b / "rollout.mp4").read_bytes()
        metrics = [json.loads(line) for line in (a / "metrics.jsonl").read_text().splitlines()]
        assert [(m["run"], m["task"], m["episode"], m["step"]) for m in metrics] == [("k", "Lift", k, t) for t in range(STEPS)]
        assert len({tuple(sorted(m)) for m in metrics}) == 1  # the same keys in every row


def test_a_results_append_the_disk_refuses_stops_with_one_line_and_a_plain_resume_finishes(fixtures_dir, tmp_path,
                                                                                             capsys, monkeypatch):
    model = str(fixtures_dir / "tiny")
    args = ["run", "--task", "Lift", "--model", model, "--episodes", "2", "--max-steps", "1", "--png-every", "0",
            "--no-video", "--fast-render", "--out", str(tmp_path), "--run-name", "full"]
    appends = []
    real_write = os.write

    def write(fd, data):  # the second line cannot be appended to results.jsonl: the disk is full
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            target = ""
        if target.endswith("results.jsonl"):
            appends.append(fd)
            if len(appends) == 2:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", write)
    code = cli.main(args)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    run = tmp_path / "full"
    assert code == 2 and len(errors) == 1 and f"the disk under {run} is full" in errors[0]
    assert "results.jsonl" in errors[0] and "No space left" in errors[0] and "1 episode(s) left" in errors[0]
    rows = _jsonl(run)
    assert [(r["episode"], r["status"]) for r in rows] == [(0, "ok")]  # consistent: whole lines only
    assert json.loads((run / "results.json").read_text())["status"] == "interrupted"
    assert not (run / "Lift" / "episode_1").exists() and _temporaries(run) == []
    monkeypatch.undo()
    # space is back: a plain resume (no --retry-failed) runs the episode whose row could not be recorded
    assert cli.main(args) == 0
    rows = _jsonl(run)
    assert [(r["episode"], r["status"]) for r in rows] == [(0, "ok"), (1, "ok")]


def test_a_real_full_disk_ends_with_one_line_and_consistent_results(fixtures_dir, tmp_path, capsys):
    mount = tmp_path / "small"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mount)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root); the injected-OSError test covers this path")
    try:
        code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--episodes", "4",
                         "--max-steps", "2", "--fast-render", "--out", str(mount), "--run-name", "d",
                         "--no-space-check"])  # its estimate exceeds the disk: started anyway, it fills it
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if line.startswith("error:")]
        assert code == 2 and len(errors) == 1 and f"the disk under {mount / 'd'} is full" in errors[0]
        rows = _jsonl(mount / "d") if (mount / "d" / "results.jsonl").exists() else []  # every line parses, no job twice
        assert len({(r["task"], r["episode"]) for r in rows}) == len(rows)
        assert all(r["status"] == "ok" or r.get("lost") == "disk" for r in rows)  # no episode failure recorded
        assert _temporaries(mount / "d") == []
    finally:
        subprocess.run(["umount", str(mount)], check=True)
