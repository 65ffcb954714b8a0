"""Demonstration recording: resumable job by job, and the LIBERO recovery bursts (reference_policies.demos,
reference_policies.libero_demos). Hand-made jobs in this process, no simulator: the recorders' own episodes are
checked in tests/libero/test_reference_policy.py."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from reference_policies.demos import record_tasks
from reference_policies.libero_demos import BurstConfig, Bursts
from reference_policies.libero_expert import CLOSED, OPEN

CALLS: list[tuple[str, int]] = []


@dataclass(frozen=True)
class _Config:
    jobs_per_task: int = 3
    tag: str = "a"  # part of the fingerprint
    jobs_dir: str = ""  # _stopping_job: where the others' saved jobs appear

    def task_seed_base(self, task: str) -> int:
        return {"t0": 100, "t1": 200}[task]


def _job(args):
    """A recorder whose episode k of seed s has s + k steps of arrays that encode the seed; seeds divisible by 7 fail."""
    task, first_seed, count, config = args
    CALLS.append((task, first_seed))
    episodes, seeds, dropped, seed = [], [], 0, first_seed
    while len(episodes) < count:
        if seed % 7 == 0:
            dropped += 1
        else:
            n = 2 + seed % 3
            episodes.append({"action": np.full((n, 7), seed, np.float32),
                             "image_primary": np.full((n, 4, 4, 3), seed % 255, np.uint8)})
            seeds.append(seed)
        seed += 1
    return episodes, seeds, dropped


def _stopping_job(args):
    """Job t0/100 waits (up to 60 s) until the four other jobs are saved, then dies as a stopped session would."""
    task, first_seed, _, config = args
    if (task, first_seed) == ("t0", 100):
        deadline = time.monotonic() + 60
        while len(list(Path(config.jobs_dir).glob("*.npz"))) < 4 and time.monotonic() < deadline:
            time.sleep(0.1)
        raise RuntimeError("stopped under way")
    return _job(args)


def _record(out, config=_Config()):
    CALLS.clear()
    return record_tasks(_job, config, {"t0": 5, "t1": 2}, out, lambda t: f"{t}.npz", workers=1, seeds_per_job=10)


def _files(out):
    return {p.name: p.read_bytes() for p in sorted(out.glob("*.npz"))}


def test_a_stopped_recording_records_only_the_jobs_it_had_not_saved(tmp_path):
    whole = tmp_path / "whole"
    _record(whole)
    assert len(CALLS) == 5  # t0: 3 jobs (2+2+1), t1: 2 jobs of one episode (the third would be empty: none)
    first = _files(whole)

    stopped = tmp_path / "stopped"
    _record(stopped)
    parts = sorted((stopped / "jobs").glob("*.npz"))
    for part in parts[1:]:  # a stop after the first job: the others never saved
        part.unlink()
    (stopped / "summary.json").unlink()
    _record(stopped)
    assert len(CALLS) == 4 and CALLS[0] != ("t0", 100)  # only the missing jobs ran again
    assert _files(stopped) == first  # byte for byte the files of the uninterrupted recording
    summary = json.loads((stopped / "summary.json").read_text())
    assert summary["t0"]["episodes"] == 5 and summary["t1"]["episodes"] == 2

    _record(stopped)
    assert CALLS == []  # everything saved: nothing runs


def test_each_job_is_saved_when_it_finishes_not_behind_a_slower_one(tmp_path):
    """Jobs finished after a slow one are on disk when it dies (spawned workers hand results back as they finish),
    so a stop loses only the jobs under way; resuming then runs the one job that died."""
    config = _Config(jobs_dir=str(tmp_path / "jobs"))
    with pytest.raises(RuntimeError, match="stopped under way"):
        record_tasks(_stopping_job, config, {"t0": 5, "t1": 2}, tmp_path, lambda t: f"{t}.npz", workers=2,
                     seeds_per_job=10)
    assert sorted(p.name for p in (tmp_path / "jobs").glob("*.npz")) == \
        ["t0_110.npz", "t0_120.npz", "t1_200.npz", "t1_210.npz"]
    CALLS.clear()
    record_tasks(_job, config, {"t0": 5, "t1": 2}, tmp_path, lambda t: f"{t}.npz", workers=1, seeds_per_job=10)
    assert CALLS == [("t0", 100)]


def test_a_saved_job_of_another_configuration_or_a_torn_file_is_recorded_again(tmp_path):
    _record(tmp_path)
    part = sorted((tmp_path / "jobs").glob("*.npz"))[0]
    part.write_bytes(part.read_bytes()[:100])  # torn
    _record(tmp_path)
    assert len(CALLS) == 1
    _record(tmp_path, _Config(tag="b"))
    assert len(CALLS) == 5  # another configuration: none of the saved jobs counts


def test_bursts_change_what_is_executed_never_the_label():
    rng = np.random.default_rng(0)
    bursts = Bursts(BurstConfig(push=0.05, gripper=0.05))
    label = np.array([0.1, -0.2, 0.3, 0, 0, 0, OPEN], np.float32)
    pushes = closes = 0
    for _ in range(2000):
        executed = bursts(label.copy(), label, rng)
        pushes += not np.allclose(executed[:2], label[:2])
        closes += executed[6] == CLOSED
        if not np.allclose(executed[:2], label[:2]):
            assert np.linalg.norm(executed[:2]) == pytest.approx(0.6, rel=1e-5)  # the push's size
    assert label[6] == OPEN and label[0] == np.float32(0.1)  # the label is never written
    # each kind starts with probability 0.05 a step when no burst runs: bursts run in a sizeable share of the steps
    assert 0.1 < pushes / 2000 < 0.5 and 0.1 < closes / 2000 < 0.6
    held = np.array([0, 0, 0, 0, 0, 0, CLOSED], np.float32)
    bursts = Bursts(BurstConfig(push=0.0, gripper=1.0))
    assert all(bursts(held.copy(), held, rng)[6] == CLOSED for _ in range(50))  # never opens a held grasp


def test_missed_grasps_are_part_of_the_recording_fingerprint_only_when_set():
    from reference_policies.demos import config_fingerprint
    from reference_policies.libero_demos import LiberoDemoConfig, MissConfig

    # unset: the fingerprint of the recordings made before missed grasps existed, so they stay reusable
    assert "miss" not in config_fingerprint(LiberoDemoConfig())["bursts"]
    set_ = LiberoDemoConfig(bursts=BurstConfig(miss=MissConfig(rate=0.5)))
    assert config_fingerprint(set_)["bursts"]["miss"] == {"rate": 0.5, "offset": 0.03, "close_steps": [6, 10]}
    for rate in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="probability"):
            MissConfig(rate=rate)


def test_bursts_are_a_function_of_the_episode_seed():
    def trace(seed):
        rng = np.random.default_rng(seed)
        bursts = Bursts(BurstConfig())
        label = np.array([0, 0, 0, 0, 0, 0, OPEN], np.float32)
        return np.stack([bursts(label.copy(), label, rng) for _ in range(300)])

    np.testing.assert_array_equal(trace(1), trace(1))
    assert not np.array_equal(trace(1), trace(2))


def test_weighted_frames_are_drawn_in_proportion_within_their_task_and_uniform_draws_are_unchanged():
    from reference_policies.train import frame_drawer

    by_task = [np.arange(0, 4), np.arange(4, 6)]
    weight = np.array([1.0, 1.0, 1.0, 3.0, 1.0, 1.0])
    draws = frame_drawer(by_task, weight)(np.zeros(60_000, int), np.random.default_rng(0))
    share = np.bincount(draws, minlength=6) / len(draws)
    np.testing.assert_allclose(share[:4], [1 / 6, 1 / 6, 1 / 6, 1 / 2], atol=0.01)  # frame 3 three times as often
    assert set(frame_drawer(by_task, weight)(np.ones(500, int), np.random.default_rng(1))) == {4, 5}
    # without weights: exactly the draws the trainer made before frame weights existed
    rng_a, rng_b = np.random.default_rng(2), np.random.default_rng(2)
    old = np.array([by_task[t][rng_a.integers(0, len(by_task[t]))] for t in [0, 1, 1, 0]])
    np.testing.assert_array_equal(frame_drawer(by_task, None)(np.array([0, 1, 1, 0]), rng_b), old)


def test_corrections_with_weights_append_to_demonstrations_that_have_none(tmp_path):
    from reference_policies.dagger import append_corrections
    from reference_policies.train import build_dataset

    def frames(n, seed):
        r = np.random.default_rng(seed)
        return {"image_primary": r.integers(0, 255, (n, 8, 8, 3), np.uint8), "proprio": r.normal(size=(n, 8)),
                "action": r.uniform(-1, 1, (n, 7)).astype(np.float32), "episode": np.zeros(n, np.int32),
                "step": np.arange(n, dtype=np.int32), "lengths": np.array([n], np.int32)}

    extra = {**frames(3, 1), "weight": np.array([3.0, 1.0, 3.0])}
    np.savez(tmp_path / "t.npz", **extra)
    merged = append_corrections({"t": frames(4, 0)}, tmp_path, "t", "t.npz")["t"]
    np.testing.assert_array_equal(merged["weight"], [1, 1, 1, 1, 3, 1, 3])
    assert merged["episode"].tolist() == [0, 0, 0, 0, 1, 1, 1]
    assert build_dataset({"t": merged}, 2).weight.tolist() == [1, 1, 1, 1, 3, 1, 3]
    assert build_dataset({"t": frames(4, 0)}, 2).weight is None
    with pytest.raises(ValueError, match="weights must be finite and > 0"):
        build_dataset({"t": {**merged, "weight": np.r_[merged["weight"][:-1], 0.0]}}, 2)


def test_the_first_recipe_still_describes_the_committed_checkpoints_demonstrations():
    """`--recipe first` must rebuild the first committed LIBERO checkpoint (models/octo-reference-libero-object-first): its recorded demonstration summary names the
    configuration it was made with, which must equal the first recipe's apart from fields added since (whose
    defaults leave the first recipe's data unchanged: bursts None, the labeller's radii unused by the timed expert)."""
    from reference_policies.demos import config_fingerprint
    from reference_policies.libero_pipeline import RECIPES
    from tests.helpers import REPO

    summary = json.loads((REPO / "models" / "octo-reference-libero-object-first" / "training_summary.json").read_text())
    recorded = summary["demonstrations"]["config"]
    first = config_fingerprint(RECIPES["first"])
    added = {"bursts", "demonstrator"}  # the committed checkpoint predates both: it used the timed expert
    assert {k: v for k, v in first.items() if k not in added and k != "expert"} == \
        {k: v for k, v in recorded.items() if k != "expert"}
    assert first["bursts"] is None and first["demonstrator"] == "timed"
    assert {k: v for k, v in first["expert"].items() if k in recorded["expert"]} == recorded["expert"]
    assert RECIPES["second"].cameras[1][2] == 128 and RECIPES["second"].bursts is not None


def test_a_killed_recording_leaves_no_worker_recording_on(tmp_path):
    """The recording pool's workers die with the process that started them (SIGKILL, no clean-up): none goes on
    recording into the demonstrations folder beside a restarted pipeline (found in session 21 after a restart)."""
    import os
    import signal
    import subprocess
    import sys

    from tests.helpers import REPO, alive, descendants

    started = [tmp_path / "0", tmp_path / "1"]  # each job marks its start, after the worker's initializer ran
    code = ("from reference_policies.demos import jobs_as_done\nfrom tests.reference.test_recording import _mark_and_sleep\n"
            f"for _ in jobs_as_done(_mark_and_sleep, {[str(p) for p in started]!r}, 2):\n    pass\n")
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 180
        while not all(p.exists() for p in started):
            assert proc.poll() is None and time.monotonic() < deadline, "the pool's jobs did not start"
            time.sleep(0.2)
        workers = {pid for pid in descendants(proc.pid) if b"spawn_main" in _cmdline(pid)}
        assert len(workers) == 2, workers
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 20
        while alive(workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not alive(workers), f"recording workers outlived their pipeline: {alive(workers)}"
    finally:
        for pid in alive(workers):
            os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()


def _mark_and_sleep(path: str) -> None:
    """A stand-in recording job (run in a spawned worker): says it started, then takes longer than the test."""
    Path(path).touch()
    time.sleep(300)


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # gone meanwhile
        return b""
