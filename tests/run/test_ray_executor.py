"""The Ray executor end to end (real robosuite, real JAX model, a real local Ray cluster): `--executor ray --workers 2`
gives the sequential run's episodes step for step, and an env actor killed mid-job fails that episode only, is
replaced, and the run completes. Its own file: a local Ray cluster is several times slower while the other test
process loads both cores (measured: 120 s against 35 s alone), and its place in the order is its measured time
(tests/durations.json)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from harness.run import execute
from tests.run.test_parallel import (STEPS, _assert_replay_is_exact, _assert_same_episodes, _children,
                                     _protocol, _run_while, _the_one_failed_episode, sequential, tiny)  # noqa: F401

pytestmark = pytest.mark.slow


def test_ray_executor_with_two_workers_gives_the_sequential_episodes(tiny, sequential, tmp_path):
    from harness.run.ray_executor import RayExecutor

    executors = []

    def factory(context, model):
        executors.append(RayExecutor(context, model, workers=2))
        return executors[-1]

    summary = execute(_protocol(tiny), tmp_path, "ray2", model=tiny, executor=factory, progress=False)
    _assert_same_episodes(sequential, summary)
    _assert_replay_is_exact(summary, tiny)
    (stats,) = executors[0].replica_stats
    assert stats["sample_cache_size"] == 1  # the replica compiled its one shape during warm-up only
    assert sum(stats["batches"]) == 2 * STEPS
    assert not list(Path(summary.run_dir).glob(".octo-harness-shared-check-*"))  # the marker is removed


def _busy_ray_env_workers() -> list[int]:
    """Pids of this test's Ray env-worker actors inside `run` (Ray titles the process `ray::EnvWorker.run`
    meanwhile): descendants of this process only, since another test process may run a Ray cluster of its own."""
    pids = []
    ours = _children(os.getpid())
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) in ours:
            try:
                if (entry / "cmdline").read_bytes().startswith(b"ray::EnvWorker.run"):
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


def test_a_ray_env_worker_killed_during_a_job_fails_that_episode_is_replaced_and_the_run_completes(tiny, tmp_path):
    from harness.run.ray_executor import RayExecutor

    executors, killed = [], []

    def factory(context, model):
        executors.append(RayExecutor(context, model, workers=2))
        return executors[-1]

    def kill_a_busy_actor():
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            busy = _busy_ray_env_workers()
            if busy:  # a job is under way on that actor (making its env or stepping the episode)
                os.kill(busy[0], signal.SIGKILL)
                killed.append(busy[0])
                return
            time.sleep(0.02)

    summary = _run_while(tiny, tmp_path, "raykill", factory, kill_a_busy_actor)
    assert killed, "no Ray env worker was killed"
    failed = _the_one_failed_episode(summary)
    assert f"worker process died (pid {killed[0]}" in failed.error
    assert executors[0].replacements == 1
    assert not _busy_ray_env_workers()  # every actor is gone with the run
