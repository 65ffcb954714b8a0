"""The Ray executor end to end (real robosuite, real JAX model, a real local Ray cluster): `--executor ray --workers 2`
gives the sequential run's episodes step for step, and an env actor killed mid-job fails that episode only, is
replaced, and the run completes. Its own file: a local Ray cluster is several times slower while the other test
process loads both cores (measured: 120 s against 35 s alone), and its place in the order is its measured time
(tests/durations.json)."""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time
from pathlib import Path

import pytest

from harness.run import execute
from tests.helpers import descendants
from tests.run.test_parallel import (STEPS, _assert_replay_is_exact, _assert_same_episodes, _protocol, _run_while,
                                     _the_one_failed_episode, sequential, tiny)  # noqa: F401

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
    ours = descendants(os.getpid())
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

    def factory(context, model):  # one env actor: its replacement must run the second episode (one actor fewer to start)
        executors.append(RayExecutor(context, model, workers=1))
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

    summary = _run_while(tiny, tmp_path, "raykill", factory, kill_a_busy_actor, episodes=2)
    assert killed, "no Ray env worker was killed"
    failed = _the_one_failed_episode(summary, episodes=2)
    assert failed.episode == 0  # the first job, on the first actor; the second ran on its replacement
    assert f"worker process died (pid {killed[0]}" in failed.error
    assert executors[0].replacements == 1
    assert not _busy_ray_env_workers()  # every actor is gone with the run



def _ray_head(log_dir: Path, tries: int = 3):
    """`ray start --head --block` (the cluster a user starts) -> (process, port, temp dir): in a process of its own
    that stops every Ray process it started on SIGINT; token authentication off, as the test's own process has it.
    Its files go to a temp dir of its own, not /tmp/ray, where another test process's Ray would find it. On a loaded
    machine `ray start` can give up by itself ("The current node timed out during startup": Ray waits 30 s for its
    raylet, a fixed wait); then it is stopped and started again, on a fresh port and temp dir, up to `tries` times."""
    import socket
    import subprocess
    import tempfile

    logs = []
    for attempt in range(tries):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        temp_dir = tempfile.mkdtemp(prefix="ray-head-", dir="/tmp")  # short: Ray's socket paths live under it
        log = log_dir / f"head{attempt}.log"
        command = [str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", f"--port={port}",
                   "--num-cpus=2", "--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={temp_dir}"]
        head = subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "RAY_AUTH_MODE": "disabled"})
        deadline = time.monotonic() + 150
        while "Ray runtime started" not in log.read_text() and head.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        if "Ray runtime started" in log.read_text():
            return head, port, temp_dir
        _stop_head(head, temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)
        logs.append(log.read_text()[-1500:])
    raise AssertionError(f"ray start --head failed {tries} times:\n" + "\n---\n".join(logs))


def _stop_head(head, temp_dir: str) -> None:
    """SIGINT (`ray start --block` then stops what it started); where that takes over 10 s (a loaded machine: it
    took over 120 s once), SIGKILL to its session and to every process whose command line names its temp dir."""
    import subprocess

    head.send_signal(signal.SIGINT)
    try:
        head.wait(timeout=10)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(head.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        head.wait(timeout=30)
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and temp_dir.encode() in (entry / "cmdline").read_bytes():
                os.kill(int(entry.name), signal.SIGKILL)
        except OSError:
            pass


def test_runs_one_after_another_in_one_process_each_connect_to_the_cluster_at_the_address(tiny, tmp_path,
                                                                                          monkeypatch):
    """`--ray-address`: a robustness grid runs its cells one after another in one process. Each run's executor
    connects and, when it closes, disconnects, so the next one connects again (left connected, the second one
    failed with "cannot connect to the Ray cluster ... ray.init twice"). Without an address, a run starts its own
    instance even where RAY_ADDRESS names that cluster (ray.init joined it, and refused num_cpus for it)."""
    import ray

    from harness.run.executor import EpisodeContext
    from harness.run.ray_executor import RayExecutor

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    head, port, temp_dir = _ray_head(tmp_path)
    try:
        context = EpisodeContext(protocol=_protocol(tiny), run_dir=str(tmp_path), run="cell",
                                 model={"source": tiny.source, "is_random": False}, goals=None)
        for _ in range(2):
            executor = RayExecutor(context, tiny, workers=1, address=f"127.0.0.1:{port}")
            executor._init()  # what a run does first (the actors are the other tests')
            assert ray.is_initialized() and ray.get_runtime_context().gcs_address.endswith(f":{port}")
            executor.close()
            assert not ray.is_initialized()  # disconnected: the next run's ray.init may connect
        monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")
        executor = RayExecutor(context, tiny, workers=1)
        executor._init()
        assert not ray.get_runtime_context().gcs_address.endswith(f":{port}")  # its own instance
        executor.close()
        assert not ray.is_initialized()
    finally:
        _stop_head(head, temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)
