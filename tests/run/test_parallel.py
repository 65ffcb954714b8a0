"""Parallel execution end to end (real robosuite, real JAX model: the tiny reference fixture, 64/32 px cameras):
`--workers 2` and `--executor ray --workers 2` give the sequential run's episodes step for step; batched inference
neither recompiles after warm-up nor lets an episode's actions depend on its batch; faults stay contained."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import envs
from harness.policies import as_policy
from harness.octo import load_pretrained
from harness.policy import PolicyConfig, TaskPrompt
from harness.run import execute
from harness.run.protocol import Protocol
from harness.run.execution import executor_factory
from harness.run.workers import WorkersExecutor, max_workers, warmup_request, PolicyShape
from harness.outputs.writers import OutputOptions
from tests.helpers import alive, descendants

STEPS = 8
CAMERAS = (("image_primary", "agentview", 64), ("image_wrist", "robot0_eye_in_hand", 32))  # the tiny model's sizes
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny(fixtures_dir):
    return load_pretrained(str(fixtures_dir / "tiny"))


def _protocol(model, episodes: int = 2, **kw) -> Protocol:
    return Protocol(model=model.source, tasks=("Lift",), episodes=episodes, seed=3, max_steps=STEPS,
                    env=envs.EnvOptions(masks=True, fast_render=True, cameras=CAMERAS),
                    outputs=OutputOptions(png_every=0, video=False, record_inputs=True), **kw)


def _actions(summary, row) -> np.ndarray:
    with np.load(summary.episode_dir(row) / "actions.npz") as z:
        return z["executed"]  # (steps, action_dim)


def _no_temporaries(run_dir: Path) -> bool:
    return not [p for p in run_dir.rglob("*.tmp.*")]


def _counting_envs(monkeypatch) -> list[list]:
    """[env, closed] for each env that `envs.make` builds in this process from now on."""
    made, original = [], envs.make

    def make(*args, **kwargs):
        entry = [original(*args, **kwargs), False]
        close = entry[0].close

        def counted_close():
            entry[1] = True
            return close()

        entry[0].close = counted_close
        made.append(entry)
        return entry[0]

    monkeypatch.setattr(envs, "make", make)
    return made


SEQUENTIAL_ENVS: list[list] = []


@pytest.fixture(scope="module")
def sequential(tiny, tmp_path_factory):
    with pytest.MonkeyPatch.context() as monkeypatch:
        SEQUENTIAL_ENVS[:] = made = _counting_envs(monkeypatch)
        summary = execute(_protocol(tiny), tmp_path_factory.mktemp("seq"), "seq", model=tiny, progress=False)
    SEQUENTIAL_ENVS[:] = made
    return summary


def test_a_sequential_run_steps_its_episodes_in_the_env_that_checked_the_model(sequential):
    """The driver makes the first task's env to check the model against it; the sequential executor runs the
    episodes in that env rather than building the same one again, and it is closed at the end."""
    assert sequential.status == "complete" and len(sequential.rows) == 2
    assert [closed for _, closed in SEQUENTIAL_ENVS] == [True]


def test_the_run_records_its_preflight_where_the_tiny_fixtures_blank_frames_are_inconclusive(sequential):
    """The pre-flight check reset that env once before the episodes (which the parallel runs below, whose workers
    make their own envs, must still match bit for bit); the manifest records its findings outside the protocol."""
    block = sequential.manifest["preflight"]
    assert block["mode"] == "warn" and block["task"] == "Lift" and "preflight" not in sequential.manifest["protocol"]
    images = [f for f in block["findings"] if f["check"].startswith("image:")]
    assert len(images) == 2 and all(f["reason"] == "blank example frame" for f in images)


def _assert_same_episodes(reference, other) -> None:
    assert other.status == "complete" and len(other.rows) == len(reference.rows)
    for a, b in zip(reference.rows, other.rows):
        assert (b.task, b.episode, b.seed, b.status) == (a.task, a.episode, a.seed, "ok")
        assert (b.success, b.steps) == (a.success, a.steps)
        # bit-identical: one fixed inference shape, per-example rng (not "close": the numbers must not depend on
        # the executor, the worker count or the load)
        np.testing.assert_array_equal(_actions(other, b), _actions(reference, a))
        with np.load(reference.episode_dir(a) / "attention.npz") as za, np.load(other.episode_dir(b) / "attention.npz") as zb:
            np.testing.assert_array_equal(zb["readout_attention"], za["readout_attention"])


def _assert_replay_is_exact(summary, model) -> None:
    """Replay of a run on its own recorded inputs, with its own model on this machine: EQUIVALENT, and exactly 0."""
    from harness.gate.replay import replay_run

    result = replay_run(summary.run_dir, loaded_model=model)
    assert result.verdict == "EQUIVALENT" and result.steps_compared == sum(r.steps for r in summary.rows)
    assert result.action_change_max == 0.0 and result.attention_js_max == 0.0


def _run_while(tiny, tmp_path, name, factory, killer, episodes: int = 3):
    """Run 3 (or `episodes`) episodes with `factory` while `killer` (a thread) kills a worker."""
    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    summary = execute(_protocol(tiny, episodes=episodes), tmp_path, name, model=tiny, executor=factory, progress=False)
    thread.join()
    return summary


def _assert_same_files(reference, summary) -> None:
    """Each episode both runs ran has the same data files: byte for byte (the sizes and sha256 their rows record), but
    metrics.jsonl, whose lines also hold the run's name and wall-clock timings: equal without those."""
    ours = {r.key: r for r in summary.rows}
    for a in reference.rows:
        b = ours[a.key]
        assert (b.seed, set(b.files)) == (a.seed, set(a.files))
        for name in a.files:
            if name != "metrics.jsonl":
                assert b.files[name] == a.files[name], (a.directory, name)
        lines = [[_untimed(json.loads(line)) for line in (run.episode_dir(row) / "metrics.jsonl").read_text().splitlines()]
                 for run, row in ((reference, a), (summary, b))]
        assert lines[0] == lines[1], a.directory


def _untimed(value):
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if k != "run" and not re.search(r"time|timing|seconds", k)}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def _the_one_retried_episode(summary, reference, episodes: int = 3):
    """A run of `episodes` that lost one worker: complete, every episode ok, exactly one retried (after a lost
    worker, counted in the manifest and the summary); each episode that `reference` (a sequential run) also ran has
    its data files byte for byte; no temporaries. Returns the retried row."""
    assert summary.status == "complete" and len(summary.rows) == episodes
    assert all(r.status == "ok" and r.steps == STEPS and r.failure is None for r in summary.rows)
    retried = [r for r in summary.rows if r.retries]
    assert len(retried) == 1
    assert summary.manifest["recovery"]["episodes_retried"] == 1 and summary.manifest["recovery"]["lost"] == []
    results = json.loads((summary.run_dir / "results.json").read_text())
    assert results["recovery"]["retried_after"] == {retried[0].retries[-1]["lost"]: 1}
    assert f"1 episode retried after a lost {retried[0].retries[-1]['lost']}" in summary.table()
    _assert_same_files(reference, summary)
    assert retried[0].episode in {a.episode for a in reference.rows}
    assert _no_temporaries(summary.run_dir)
    return retried[0]


@pytest.mark.slow
def test_two_worker_processes_give_the_sequential_episodes_without_recompiling(tiny, sequential, tmp_path):
    executors = []

    def factory(context, model):
        executors.append(WorkersExecutor(context, as_policy(model), workers=2))
        return executors[-1]

    with pytest.MonkeyPatch.context() as monkeypatch:
        made = _counting_envs(monkeypatch)
        summary = execute(_protocol(tiny), tmp_path, "w2", model=tiny, executor=factory, progress=False)
    assert [closed for _, closed in made] == [True]  # the check's env: the workers make their own, it is closed
    _assert_same_episodes(sequential, summary)
    _assert_replay_is_exact(sequential, tiny)
    _assert_replay_is_exact(summary, tiny)
    # one inference shape (the protocol's inference_batch 1, shared with the sequential run), compiled once
    assert tiny.sample_cache_size == 1
    pool = executors[0].pool
    assert sum(pool.batches) == 2 * STEPS and set(pool.batches) == {1} and pool.max_batch == 1 and pool.replacements == 0
    rows = [json.loads(line) for line in (summary.run_dir / "results.jsonl").read_text().splitlines()]
    assert sorted((r["task"], r["episode"]) for r in rows) == [("Lift", 0), ("Lift", 1)]
    assert _no_temporaries(summary.run_dir)


def test_workers_are_bounded_by_the_machine_before_anything_compiles():
    assert max_workers(cpus=2, memory_bytes=24 << 30) == 8  # 4 per core
    assert max_workers(cpus=64, memory_bytes=8 << 30) == 8  # one per GB of memory
    assert max_workers(cpus=1, memory_bytes=0) == 4  # memory unknown: the core bound alone
    with pytest.raises(ValueError, match=r"^--workers 100000 is more than this machine can use .*use --workers \d+ or fewer$"):
        executor_factory(100000)
    assert executor_factory(max_workers()) is not None
    assert executor_factory(100000, "ray", "head-node:6379") is not None  # a cluster's CPUs are checked when joined
    with pytest.raises(ValueError, match=r"^--workers 100000 is more than this machine can use"):
        executor_factory(100000, "ray")  # a local Ray instance runs on this machine


@pytest.mark.slow
def test_an_episode_gets_the_same_bits_whatever_shares_its_inference_call(tiny):
    """inference_batch 4: alone (padded to 4) or with others (3 in one call, or 2 in another order), each example's
    chunk and attention are bit-identical; one shape is compiled; per-example rng."""
    shape = PolicyShape.of(tiny, None)
    inference = as_policy(tiny).inference(PolicyConfig(inference_batch=4))
    rng = np.random.default_rng(0)
    requests = []
    for i, text in enumerate(["lift the red cube", "open the door", "lift the red cube"]):
        base = warmup_request(shape, TaskPrompt.of(text))
        obs = {k: (rng.integers(0, 256, v.shape, dtype=np.uint8) if k.startswith("image_") else v)
               for k, v in base.observation.items()}
        requests.append(type(base)(obs, base.task, seed=10 + i, step=i))
    inference.warm_up(requests[0])
    compiled = tiny.sample_cache_size
    alone = [inference([r])[0] for r in requests]
    together = inference(requests)  # batch of 3, padded to 4
    pairs = inference([requests[2], requests[0]])  # other neighbours and positions
    assert tiny.sample_cache_size == compiled  # no recompilation after warm-up
    for got, want in list(zip(together, alone)) + list(zip(pairs, [alone[2], alone[0]])):
        np.testing.assert_array_equal(got.chunk, want.chunk)
        np.testing.assert_array_equal(got.readout_attention, want.readout_attention)
    assert not np.allclose(alone[0].chunk, alone[2].chunk)  # different seeds/observations -> different actions
    assert len(inference._tasks) == 2  # one task per distinct instruction


@pytest.mark.slow
def test_a_policy_error_fails_only_the_episodes_of_its_batch(tiny, tmp_path):
    executors = []

    def factory(context, model):
        executor = WorkersExecutor(context, as_policy(model), workers=2)
        real, calls = executor.pool.inference, []

        class FailingThirdBatch:  # fault injection around the real inference: the third call after warm-up raises
            warm_up = real.warm_up

            def __call__(self, requests):
                calls.append(len(requests))
                if len(calls) == 3:
                    raise FloatingPointError("injected policy failure")
                return real(requests)

        executor.pool.inference = FailingThirdBatch()
        executors.append((executor, calls))
        return executor

    summary = execute(_protocol(tiny, episodes=3), tmp_path, "perr", model=tiny, executor=factory, progress=False)
    _, calls = executors[0]
    failed = [r for r in summary.rows if r.status == "failed"]
    assert summary.status == "complete" and len(summary.rows) == 3
    assert len(failed) == calls[2] and all("injected policy failure" in r.error for r in failed)
    # the policy's own failure: an episode failure, in the statistics' failed count, never retried
    assert all(r.failure == "episode" and not r.retries for r in failed)
    assert summary.statistics["overall"]["failed"] == len(failed) and "recovery" not in summary.manifest
    assert all(r.steps == STEPS for r in summary.rows if r.status == "ok")
    for row in failed:
        meta = json.loads((summary.episode_dir(row) / "episode.json").read_text())
        assert meta["status"] == "failed" and "injected policy failure" in meta["error"]
    assert _no_temporaries(summary.run_dir)


@pytest.mark.slow
def test_a_worker_killed_mid_episode_is_replaced_and_its_episode_retried_to_the_sequential_files(tiny, sequential,
                                                                                                  tmp_path):
    executors = []

    def factory(context, model):
        executors.append(WorkersExecutor(context, as_policy(model), workers=2))
        return executors[-1]

    killed = []

    def kill_a_busy_worker():
        """Kills a worker while both workers run the first two of four episodes and two are queued. The other
        worker is stopped (SIGSTOP) from before the kill until the pool has buried the killed one, so it cannot take
        the queued jobs meanwhile: a SIGKILL takes effect only when the process leaves the kernel (a worker in an
        fsync under load dies seconds later), and then the queue may have emptied. With the other worker held, the
        pool must start a replacement, however slowly the machine runs."""
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not killed:
            pool = executors[0].pool if executors else None
            if pool is not None and pool.batches:  # past warm-up: the workers have asked for actions
                try:
                    busy = [w for w in list(pool._pool.values()) if w.job is not None and w.process.pid]
                except RuntimeError:  # the pool changed while we looked
                    continue
                if len(busy) == 2 and {w.job.episode for w in busy} == {0, 1} and len(pool.queued) == 2:
                    victim, other = busy
                    os.kill(other.process.pid, signal.SIGSTOP)
                    try:
                        if victim.job is None or len(pool.queued) != 2:  # it moved on meanwhile: look again
                            continue
                        killed.append(victim.job)
                        os.kill(victim.process.pid, signal.SIGKILL)
                        while victim.index in pool._pool and time.monotonic() < deadline:
                            time.sleep(0.005)  # until the pool has buried it
                    finally:
                        os.kill(other.process.pid, signal.SIGCONT)
                    return
            time.sleep(0.001)

    summary = _run_while(tiny, tmp_path, "kill", factory, kill_a_busy_worker, episodes=4)
    assert killed, "no worker was killed"
    retried = _the_one_retried_episode(summary, sequential, episodes=4)
    assert (retried.task, retried.episode) == (killed[0].task, killed[0].episode)
    (attempt,) = retried.retries
    assert attempt["lost"] == "worker" and "worker process died: signal 9" in attempt["cause"] and attempt["step"] >= 0
    assert executors[0].pool.replacements == 1


def test_an_env_worker_that_cannot_see_the_run_folder_names_its_node_and_the_fix(tmp_path):
    from harness.run.ray_executor import EnvWorker, RayExecutorError

    (tmp_path / "marker").write_text("token")
    with pytest.raises(RayExecutorError, match=r"not visible from node .*filesystem every Ray node mounts"):
        EnvWorker(None, None, (str(tmp_path / "elsewhere"), "token"))
    with pytest.raises(RayExecutorError, match="not visible"):
        EnvWorker(None, None, (str(tmp_path / "marker"), "another run's token"))


def test_a_replica_that_never_started_is_one_line_with_rays_reason():
    """Ray's actor error -> the line a run stops with: Ray's reason and whether the actor ever ran, without its generic
    first line and ids (before, only "The actor never ran - it was cancelled before it started running." was left)."""
    from ray.core.generated.common_pb2 import ActorDiedErrorContext
    from ray.exceptions import ActorDiedError

    from harness.run.ray_errors import actor_error

    exc = ActorDiedError(ActorDiedErrorContext(class_name="PolicyReplica", actor_id=b"x" * 16, pid=7, node_ip_address="10.0.0.2",
                                               error_message="The actor is dead because its node died.", never_started=True))
    assert actor_error(exc) == ("The actor is dead because its node died. "
                                 "The actor never ran - it was cancelled before it started running.")


@pytest.mark.parametrize("flags, message", [
    (["--workers", "0"], "--workers must be at least 1"),
    (["--ray-address", "auto"], "need --executor ray"),
    (["--executor", "ray", "--policy-replicas", "0"], "--policy-replicas must be at least 1"),
])
def test_impossible_execution_options_are_one_line_before_anything_loads(fixtures_dir, tmp_path, capsys, flags, message):
    from harness import cli

    code = cli.main(["run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"), "--out", str(tmp_path), *flags])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.slow
def test_regress_with_two_workers_pairs_the_sequential_episodes(tiny, sequential, tmp_path, capsys):
    """`regress --workers 2`: the candidate's episodes run in env workers and still pair step for step."""
    from harness import cli
    from harness.analysis.runs import load_run

    args = ["regress", "--baseline", str(sequential.run_dir), "--model", tiny.source, "--workers", "2",
            "--out", str(tmp_path), "--run-name", "cand"]
    assert cli.main(args) == 0  # same model, same seeds: no regression
    result = json.loads((tmp_path / "cand" / "regress" / "regress.json").read_text())
    assert result["pairs_used"] == result["baseline_pairs"] == 2
    candidate = load_run(tmp_path / "cand")
    assert candidate.status == "complete" and len(candidate.episodes) == 2
    for base, cand in zip(sequential.rows, sorted(candidate.episodes, key=lambda e: e.episode)):
        assert (cand.seed, cand.success, cand.steps) == (base.seed, base.success, base.steps)
        with np.load(cand.directory / "actions.npz") as z:
            np.testing.assert_allclose(z["executed"], _actions(sequential, base), rtol=0, atol=1e-4)


# ---------------------------------------------------------------------------------------------- the command line


def _cli(fixtures_dir, out: Path, name: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "harness.cli", "run", "--task", "Lift", "--model", str(fixtures_dir / "tiny"),
            "--episodes", "3", "--max-steps", str(STEPS), "--seed", "3", "--fast-render", "--png-every", "0",
            "--camera", "image_primary=agentview:64", "--camera", "image_wrist=robot0_eye_in_hand:32",
            "--out", str(out), "--run-name", name, *extra]


def _env() -> dict:
    return {**os.environ, "HF_HUB_OFFLINE": "1", "PYTHONPATH": str(REPO)}


def _wait_for(predicate, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("timed out waiting")
        time.sleep(0.1)


@pytest.mark.slow
def test_ctrl_c_stops_every_worker_and_leaves_no_process_or_temporary(fixtures_dir, tmp_path):
    proc = subprocess.Popen(_cli(fixtures_dir, tmp_path, "int", "--workers", "2"), env=_env(), cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        workers: set[int] = set()

        def two_workers_running():
            workers.update(descendants(proc.pid))
            return len(alive(workers)) >= 2 and any((tmp_path / "int" / "Lift").glob("episode_*"))

        _wait_for(two_workers_running)
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    time.sleep(0.5)
    assert not alive(workers), f"processes left behind: {alive(workers)}"
    assert _no_temporaries(tmp_path / "int")
    results = json.loads((tmp_path / "int" / "results.json").read_text())
    assert results["status"] == "interrupted"


@pytest.mark.slow
def test_a_killed_parallel_run_resumes_to_exactly_n_episodes(fixtures_dir, tmp_path):
    command = _cli(fixtures_dir, tmp_path, "resume", "--workers", "2")
    jsonl = tmp_path / "resume" / "results.jsonl"
    proc = subprocess.Popen(command, env=_env(), cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: set[int] = set()
    try:
        def one_episode_done():
            workers.update(descendants(proc.pid))
            return jsonl.exists() and jsonl.read_text().count("\n") >= 1

        _wait_for(one_episode_done)
        proc.kill()  # SIGKILL: no clean-up in the driver
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert jsonl.read_text().count("\n") < 3
    _wait_for(lambda: not alive(workers), timeout=20)  # workers die with their driver (no orphans)
    done = subprocess.run(command, env=_env(), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
    assert sorted((r["task"], r["episode"]) for r in lines) == [("Lift", 0), ("Lift", 1), ("Lift", 2)]
    results = json.loads((tmp_path / "resume" / "results.json").read_text())
    assert results["status"] == "complete" and [e["status"] for e in results["episodes"]] == ["ok"] * 3
    assert _no_temporaries(tmp_path / "resume")
    for k in range(3):
        assert (tmp_path / "resume" / "Lift" / f"episode_{k}" / "episode.json").is_file()
