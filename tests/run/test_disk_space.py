"""What a run costs before it runs, and a disk that fills while it runs (issue 71 item 6; harness/run/space.py).

Real runs of the tiny fixture (robosuite Lift, 2 steps an episode). The small disk is a real tmpfs where this process
may mount one (root); otherwise the disk's refusal is injected where the episodes write (the PNG sink's atomic
writes, ENOSPC) and the free space where `harness.run.space.free_bytes` reads it.
"""

from __future__ import annotations

import csv
import dataclasses
import errno
import functools
import json
import os
import subprocess
from pathlib import Path

import pytest

from harness.policies import as_policy
from harness import cli
from harness.octo import load_pretrained
from harness.outputs.writers import OutputOptions
from harness.run import execute, executor as executor_module, space
from harness.run.protocol import Protocol
from harness.run.store import RunStore
from harness.run.workers import WorkersExecutor

pytestmark = pytest.mark.slow  # real runs: about 20 s each on a 2-core machine

STEPS = 2
EPISODES = 2


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny"))


def _folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "results.jsonl").read_text().splitlines()]


def _errors(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("error:")]


def _leftovers(run: Path) -> list[str]:
    """Temporaries, and episode folders without their episode.json (half-written, mistakable for finished)."""
    temporaries = [p.name for p in run.rglob("*.tmp.*")]
    incomplete = [str(p) for p in run.glob("*/episode_*") if not (p / "episode.json").is_file()]
    return temporaries + incomplete


class SmallDisk:
    """A filesystem of `size` bytes at `path`: a tmpfs when one can be mounted, else the disk's refusal injected."""

    def __init__(self, path: Path, size: int, monkeypatch):
        self.path, self.monkeypatch = path, monkeypatch
        path.mkdir()
        self.mounted = os.geteuid() == 0 and subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True).returncode == 0
        if not self.mounted:  # the writes of episode_1 onwards meet a full disk, as a 1.5-episode disk would do
            import harness.outputs.panels as panels

            real = panels.write_atomic

            def write_atomic(target, write):
                if "episode_0" not in str(target):
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))
                return real(target, write)

            monkeypatch.setattr(panels, "write_atomic", write_atomic)
            monkeypatch.setattr(space, "free_bytes", lambda path: 0)

    def free(self, needed: int) -> None:
        """Space is freed: `needed` bytes more than the disk holds now."""
        if self.mounted:
            used = int(subprocess.run(["df", "-B1", "--output=used", str(self.path)], capture_output=True, text=True,
                                      check=True).stdout.split()[-1])
            subprocess.run(["mount", "-o", f"remount,size={used + needed}", str(self.path)], check=True)
        else:
            self.monkeypatch.undo()
            self.monkeypatch.setattr(space, "free_bytes", lambda path: needed)

    def close(self) -> None:
        if self.mounted:
            subprocess.run(["umount", str(self.path)], check=False)


def test_a_full_disk_stops_the_run_and_a_plain_resume_finishes_it(tiny, fixtures_dir, tmp_path, capsys, monkeypatch):
    protocol = Protocol(model=tiny.source, tasks=("Lift",), episodes=EPISODES, max_steps=STEPS)
    shape = space.ModelShape.of(as_policy(tiny))
    one = space.estimate(protocol, shape, protocol.jobs()[:1]).total
    disk = SmallDisk(tmp_path / "disk", int(1.6 * one), monkeypatch)
    made = []
    real_make = executor_module._make_env
    monkeypatch.setattr(executor_module, "_make_env", lambda *a, **k: made.append(a[1]) or real_make(*a, **k))
    args = ["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--episodes", str(EPISODES), "--max-steps",
            str(STEPS), "--out", str(disk.path), "--run-name", "r"]
    run = disk.path / "r"
    try:
        # the whole run would not fit: refused before any env is made, one line naming the cheaper flags
        assert cli.main(args) == 2
        (line,) = _errors(capsys.readouterr().err)
        assert "--png-every 0" in line and "--no-video" in line and "--no-space-check" in line
        assert made == [] and not run.exists()
        # started anyway, it stops at the first write the disk refuses: one line naming the folder, exit 2
        assert cli.main([*args, "--no-space-check"]) == 2
        (line,) = _errors(capsys.readouterr().err)
        assert f"the disk under {run} is full" in line and f"{EPISODES - 1} episode(s) left, which need up to" in line
        rows = _rows(run)
        assert [(r["episode"], r["status"], r.get("failure"), r.get("lost")) for r in rows] == [
            (0, "ok", None, None), (1, "failed", "infrastructure", "disk")]
        assert "No space left on device" in rows[1]["error"]
        assert _leftovers(run) == [] and not (run / "Lift" / "episode_1").exists()
        kept = {p.name: p.read_bytes() for p in (run / "Lift" / "episode_0").iterdir()}
        assert json.loads((run / "results.json").read_text())["statistics"]["overall"]["n"] == 1
        # still full: the plain resume is refused, what is left named, nothing made
        made.clear()
        assert cli.main(args) == 2 and made == []
        assert f"the {EPISODES - 1} episode(s) to run need up to" in _errors(capsys.readouterr().err)[0]
        # space freed for what is left (less than the whole run would need): a plain resume finishes every episode
        left = space.estimate(protocol, shape, protocol.jobs()[1:]).total
        disk.free(int(1.25 * left))
        assert space.estimate(protocol, shape, protocol.jobs()).total > space.free_bytes(run)
        assert cli.main(args) == 0
        capsys.readouterr()
        statistics = json.loads((run / "results.json").read_text())["statistics"]["overall"]
        assert (statistics["n"], statistics["failed"]) == (EPISODES, 0)
        with open(run / "summary.csv") as f:
            assert [(r["episode"], r["status"]) for r in csv.DictReader(f)] == [(str(k), "ok") for k in range(EPISODES)]
        assert {p.name: p.read_bytes() for p in (run / "Lift" / "episode_0").iterdir()} == kept
        assert _leftovers(run) == []
        # the estimate of the whole run (PNG every step, MP4, arrays) within a factor of 2 of what it wrote
        ratio = space.estimate(protocol, shape, protocol.jobs(), steps=STEPS).total / _folder_bytes(run)
        assert 0.5 < ratio < 2, ratio
    finally:
        disk.close()


def _fills_from_episode_1(run_job, env, policy, job):
    """In the env worker: the episode's arrays meet a full disk (episode 1 and later)."""
    import harness.outputs.data_files as data_files

    real = data_files.write_atomic

    def write_atomic(path, write):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    data_files.write_atomic = write_atomic if job.episode >= 1 else real
    try:
        return run_job(env, policy, job)
    finally:
        data_files.write_atomic = real


def test_a_workers_full_disk_stops_the_run_and_loses_at_most_the_episodes_in_flight(tiny, tmp_path):
    protocol = Protocol(model=tiny.source, tasks=("Lift",), episodes=EPISODES, max_steps=STEPS,
                        outputs=OutputOptions(png_every=0, video=False))

    def factory(context, model):
        made = WorkersExecutor(context, as_policy(model), workers=1)  # one env-worker process (spawning one costs ~10 s)
        spec = made.pool.spec
        made.pool.spec = dataclasses.replace(spec, run_episode=functools.partial(_fills_from_episode_1, spec.run_episode))
        return made

    with pytest.raises(space.DiskFullError, match=f"the disk under {tmp_path / 'w'} is full"):
        execute(protocol, tmp_path, "w", model=tiny, executor=factory, progress=False)
    run = tmp_path / "w"
    rows = RunStore(run).load_rows()
    assert any(r.lost == "disk" and r.failure == "infrastructure" for r in rows.values())
    assert all(r.status == "ok" for r in rows.values() if r.lost != "disk")  # no episode counted as failed
    assert _leftovers(run) == []
    summary = execute(protocol, tmp_path, "w", model=tiny, progress=False)  # space freed: a plain resume
    assert summary.status == "complete" and [r.status for r in summary.rows] == ["ok"] * EPISODES
    assert (summary.statistics["overall"]["n"], summary.statistics["overall"]["failed"]) == (EPISODES, 0)
    # the estimate without PNG and video (arrays and lines) within a factor of 2 of what the run wrote
    ratio = space.estimate(protocol, space.ModelShape.of(as_policy(tiny)), protocol.jobs(), steps=STEPS).total / _folder_bytes(run)
    assert 0.5 < ratio < 2, ratio
