"""The Ray executor end to end (real robosuite, real JAX model, a real local Ray cluster): `--executor ray --workers 2`
gives the sequential run's episodes step for step; an env actor and then the policy replica killed mid-episode are
replaced and their episodes retried;
a node lost mid-run (a real second node of a two-node cluster on this machine) has its episodes retried on the head,
to the sequential run's files. Its own file: a local Ray cluster is several times slower while the other test
process loads both cores (measured: 120 s against 35 s alone), and its place in the order is its measured time
(tests/durations.json).

Starting Ray is much of each test's time (a local instance or a `ray start` head: 13-20 s each on 2 loaded cores),
so the module starts one head (`cluster`, before the first test that needs it) that the lost-actor test runs on, the
address test connects to and the node test joins its second node to; the two-worker run starts its own local
instance (the path without an address), as does the address test's last check."""

from __future__ import annotations

import os
import re
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from harness.policies import as_policy
from harness.run import execute
from tests.helpers import alive, descendants
from tests.run.test_parallel import (STEPS, _assert_replay_is_exact, _assert_same_episodes, _assert_same_files,
                                     _protocol, _run_while,
                                     _the_one_retried_episode, sequential, tiny)  # noqa: F401

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """One `ray start --head` for the module, as the node test needs its head (2 CPUs, the `octo_policy` resource that
    pins the policy replica there, a lean node, fast health checks): -> (process, port, temp dir, address)."""
    head, port, temp_dir = _ray_head(tmp_path_factory.mktemp("head"),
                                     extra=("--resources", '{"octo_policy": 1}', *LEAN_NODE), env=FAST_HEALTH_CHECK)
    try:
        yield SimpleNamespace(process=head, port=port, temp_dir=temp_dir, address=f"127.0.0.1:{port}")
    finally:
        _stop_head(head, temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)


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


def _ray_processes(title: bytes) -> list[int]:
    """Pids of this test's Ray processes whose title starts with `title` (descendants of this process only)."""
    pids = []
    for pid in descendants(os.getpid()):
        try:
            if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(title):
                pids.append(pid)
        except OSError:
            pass
    return pids


def _busy_ray_env_workers() -> list[int]:
    """Pids of this test's Ray env-worker actors inside `run` (Ray titles the process `ray::EnvWorker.run`
    meanwhile): descendants of this process only, since another test process may run a Ray cluster of its own."""
    return _ray_processes(b"ray::EnvWorker.run")


def test_a_lost_env_actor_and_a_lost_policy_replica_are_replaced_and_their_episodes_retried(tiny, sequential, cluster,
                                                                                            tmp_path):
    """One env actor: SIGKILLed during the first job, it is replaced, and the replacement runs the second episode;
    then the policy replica is SIGKILLed while it serves that episode, past its first step. Both episodes are
    infrastructure failures (a lost worker, a lost policy replica), the replica is started again, and both run again
    to the sequential run's files. On the module's cluster (`--ray-address`: its head has the 2 CPUs the actor and the
    replica ask for; the recovery is the executor's whichever Ray it reached), so no Ray instance is started for it;
    from a cluster the run only disconnects, so every actor must be gone by the executor's own kills."""
    import ray

    from harness.run.ray_executor import RayExecutor

    executors, killed = [], []

    def factory(context, model):  # one env actor: its replacement must run the second episode (one actor fewer to start)
        executors.append(RayExecutor(context, model, workers=1, address=cluster.address))
        return executors[-1]

    def kill_an_actor_then_the_replica():
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and not killed:
            busy = _busy_ray_env_workers()
            if busy:  # a job is under way on that actor (making its env or stepping the episode)
                os.kill(busy[0], signal.SIGKILL)
                killed.append(busy[0])
            time.sleep(0.02)
        while time.monotonic() < deadline:
            ex = executors[0]
            try:
                second = [(i, job) for i, job in list(ex.running.items()) if job.episode == 1]
                if second and ray.get(ex._served_by[second[0][0]].step_of.remote(second[0][1].key), timeout=10) >= 1:
                    (replica,) = _ray_processes(b"ray::PolicyReplica")
                    os.kill(replica, signal.SIGKILL)
                    killed.append(replica)
                    return
            except (RuntimeError, KeyError, ray.exceptions.RayError):  # the executor changed while we looked
                pass
            time.sleep(0.02)

    summary = _run_while(tiny, tmp_path, "raykill", factory, kill_an_actor_then_the_replica, episodes=2)
    assert len(killed) == 2, "the env actor and the replica were not both killed"
    assert summary.status == "complete" and all(r.status == "ok" for r in summary.rows)
    lost = {r.episode: r.retries for r in summary.rows}
    assert [a["lost"] for a in lost[0]] == ["worker"] and f"worker process died (pid {killed[0]}" in lost[0][0]["cause"]
    assert [a["lost"] for a in lost[1]] == ["policy replica"] and "policy replica lost" in lost[1][0]["cause"]
    assert summary.manifest["recovery"]["retried_after"] == {"worker": 1, "policy replica": 1}
    _assert_same_files(sequential, summary)
    assert executors[0].replacements == 1 and executors[0].replica_restarts == 1
    assert not _busy_ray_env_workers()  # every actor is gone with the run


def _free_ports(n: int) -> list[int]:
    import socket

    probes = [socket.socket() for _ in range(n)]
    try:
        for probe in probes:
            probe.bind(("127.0.0.1", 0))
        return [probe.getsockname()[1] for probe in probes]
    finally:
        for probe in probes:
            probe.close()


def _ray_head(log_dir: Path, tries: int = 3, *, extra: tuple[str, ...] = (), env: dict | None = None,
              head_address: str | None = None, name: str = "head"):
    """`ray start --head --block` (the cluster a user starts) -> (process, port, temp dir): in a process of its own
    that stops every Ray process it started on SIGINT; token authentication off, as the test's own process has it.
    Its files go to a temp dir of its own, not /tmp/ray, where another test process's Ray would find it. On a loaded
    machine `ray start` can give up by itself ("The current node timed out during startup": Ray waits 30 s for its
    raylet, a fixed wait); then it is stopped and started again, on fresh ports and temp dir, up to `tries` times.
    With `head_address`: a node that joins that head instead (`ray start --address`), on ports of its own (its files
    go to the head's temp dir, as Ray has it; the returned temp dir is the one its command line names)."""
    import subprocess
    import tempfile

    logs = []
    for attempt in range(tries):
        port, *own = _free_ports(7)  # the head's GCS, then this node's own servers (two nodes share one machine)
        ports = [f"--{flag}={p}" for flag, p in zip(("node-manager-port", "object-manager-port", "runtime-env-agent-port",
                                                     "dashboard-agent-listen-port", "dashboard-agent-grpc-port",
                                                     "metrics-export-port"), own)]
        temp_dir = tempfile.mkdtemp(prefix=f"ray-{name}-", dir="/tmp")  # short: Ray's socket paths live under it
        log = log_dir / f"{name}{attempt}.log"
        where = [f"--address={head_address}"] if head_address else ["--head", f"--port={port}", "--include-dashboard=false",
                                                                    f"--temp-dir={temp_dir}"]
        command = [str(Path(sys.executable).with_name("ray")), "start", *where, "--block", "--num-cpus=2",
                   "--disable-usage-stats", *ports, *extra]
        head = subprocess.Popen(command, stdout=log.open("w"), stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, "RAY_AUTH_MODE": "disabled", **(env or {})})
        deadline = time.monotonic() + 150
        while "Ray runtime started" not in log.read_text() and head.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        if "Ray runtime started" in log.read_text():
            return head, port, temp_dir
        _stop_head(head, temp_dir)
        shutil.rmtree(temp_dir, ignore_errors=True)
        logs.append(log.read_text()[-1500:])
    raise AssertionError(f"ray start ({name}) failed {tries} times:\n" + "\n---\n".join(logs))


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


def test_runs_one_after_another_in_one_process_each_connect_to_the_cluster_at_the_address(tiny, cluster, tmp_path,
                                                                                          monkeypatch):
    """`--ray-address`: a robustness grid runs its cells one after another in one process. Each run's executor
    connects and, when it closes, disconnects, so the next one connects again (left connected, the second one
    failed with "cannot connect to the Ray cluster ... ray.init twice"). Without an address, a run starts its own
    instance even where RAY_ADDRESS names that cluster (ray.init joined it, and refused num_cpus for it). The cluster
    is the module's head, as a user starts it (`ray start --head`)."""
    import ray

    from harness.run.executor import EpisodeContext
    from harness.run.ray_executor import RayExecutor

    port = cluster.port
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


# a lost node is declared dead within about 5 to 10 s (GCS defaults: a 3 s period, 5 misses), set on the head's GCS;
# shorter (0.5 s, 3 misses) declared a live node dead on a loaded machine (load average 20 on 2 cores)
FAST_HEALTH_CHECK = {"RAY_health_check_period_ms": "1000", "RAY_health_check_timeout_ms": "2000",
                     "RAY_health_check_failure_threshold": "5", "RAY_health_check_initial_delay_ms": "1000"}
# fewer processes and a small object store: a node starts sooner on a loaded machine (Ray gives its raylet a fixed 30 s)
LEAN_NODE = ("--include-log-monitor=false", "--object-store-memory=100000000")
NODE_TEST_LIMIT_S = 170  # past it the cluster is stopped, so a run that hangs fails instead of waiting


def _sequential_episodes(model, summary, rows, run_dir: Path):
    """The jobs of `rows` run again by the sequential executor into `run_dir` (a stand-in for a sequential run's
    summary: `rows`, `episode_dir`), with the run's protocol and model."""
    from types import SimpleNamespace

    from harness.run.executor import EpisodeContext, SequentialExecutor
    from harness.run.jobs import EpisodeJob

    context = EpisodeContext(protocol=_protocol(model, episodes=len(summary.rows)), run_dir=str(run_dir), run="seq",
                             model=summary.manifest["model"], goals=None)
    executor = SequentialExecutor(context, as_policy(model))
    try:
        done = list(executor.run([EpisodeJob(r.task, r.episode, r.seed) for r in rows]))
    finally:
        executor.close()
    return SimpleNamespace(rows=done, episode_dir=lambda row: run_dir / row.directory)


def _freeze_and_kill(pids: set[int]) -> None:
    """SIGSTOP every process (none starts another meanwhile), then SIGKILL each: a node lost at once."""
    for sig in (signal.SIGSTOP, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass


class _ClusterDidNotStart(Exception):
    """The run stopped before the node was killed: the cluster did not come up (not what the test measures)."""


def test_a_node_lost_mid_run_has_its_episodes_retried_on_the_surviving_node_to_the_sequential_files(tiny, cluster,
                                                                                                   tmp_path):
    """The scenario below, first with the module's head (started as this test needs it) and a second node joined to
    it, then on a fresh head and node and fresh ports once more where the cluster itself did not come up before any
    node was killed, as the nodes' own start-up is retried; Ray's own log lines are printed then. A failure after the
    kill is never retried. (The replica's warm-up cancelled before the kill, in two fresh-clone CI runs, was Ray's
    token-authentication mode, which it reads once per process: tests/conftest.py sets one for every test.)"""
    for attempt in range(2):
        try:
            return _node_lost_mid_run(tiny, tmp_path / f"cluster{attempt}", cluster if attempt == 0 else None)
        except _ClusterDidNotStart as exc:
            if attempt:
                raise AssertionError(f"the two-node cluster did not come up twice: {exc}") from None
            print(f"node test: the cluster did not come up ({exc}); fresh nodes")


def _node_lost_mid_run(tiny, tmp_path, cluster=None):
    """Two Ray nodes on this machine (the head: `cluster`'s, or one started here and stopped at the end): a head of 2 CPUs holding the policy replica (its `octo_policy` resource pins it)
    and a second node of 2 CPUs joined with `ray start --address`, on ports of its own. A run of 4 episodes with 2 env
    workers (one at least on the second node: the head has room for one) loses the second node (its raylet and
    every process of it, SIGKILL) while an env worker there runs an episode. The run completes: every episode ok, the
    lost ones retried on the head and counted, the data files byte for byte those of a sequential run, and no process
    of the lost node left."""
    from harness.run.ray_executor import RayExecutor, RayExecutorError

    tmp_path.mkdir(parents=True, exist_ok=True)
    done = threading.Event()  # the killer's loop ends with the run
    started = time.monotonic()
    if cluster is not None:
        head, port, head_dir = cluster.process, cluster.port, cluster.temp_dir
    else:
        head, port, head_dir = _ray_head(tmp_path, extra=("--resources", '{"octo_policy": 1}', *LEAN_NODE),
                                         env=FAST_HEALTH_CHECK)
    node, node_dir, watchdog = None, None, None
    try:
        node, _, node_dir = _ray_head(tmp_path, head_address=f"127.0.0.1:{port}", name="node", extra=LEAN_NODE,
                                      env=FAST_HEALTH_CHECK)
        cluster = time.monotonic()
        watchdog = threading.Timer(max(NODE_TEST_LIMIT_S - (time.monotonic() - started), 30),
                                   lambda: [_stop_head(head, head_dir), _stop_head(node, node_dir)])
        watchdog.start()
        executors, lost = [], set()

        def factory(context, model):
            executors.append(RayExecutor(context, model, workers=2, address=f"127.0.0.1:{port}"))
            return executors[-1]

        def kill_the_node():
            """Once an env worker of the second node is past the first step of its episode (its replica has served
            it), the node goes: its raylet, its workers and `ray start` itself."""
            import ray

            deadline = time.monotonic() + NODE_TEST_LIMIT_S
            while time.monotonic() < deadline and not done.is_set():
                ex = executors[0] if executors else None
                ours = descendants(node.pid)
                try:
                    there = [(i, job) for i, job in list(ex.running.items()) if ex.started_on.get(i, (0, 0))[1] in ours] \
                        if ex is not None else []
                    if any(ray.get(ex._served_by[i].step_of.remote(job.key), timeout=10) >= 1 for i, job in there):
                        lost.update(descendants(node.pid) | {node.pid})
                        _freeze_and_kill(lost)
                        return
                except (RuntimeError, KeyError, ray.exceptions.RayError):  # the executor changed while we looked
                    pass
                time.sleep(0.05)

        try:
            summary = _run_while(tiny, tmp_path, "node2", factory, kill_the_node, episodes=4)
        except RayExecutorError as exc:
            if lost:
                raise
            for log in sorted(Path(head_dir).glob("session_latest/logs/*")):  # what Ray said (the failure's cause)
                if log.suffix in (".out", ".err", ".log") and log.stat().st_size:
                    tail = [line for line in log.read_text(errors="replace").splitlines()
                            if re.search(r"\b(E|W)\d{4}|ERROR|WARNING|dead|cancel", line)][-8:]
                    if tail:
                        print(f"--- {log.name}\n" + "\n".join(tail))
            raise _ClusterDidNotStart(str(exc)) from None
        finally:
            done.set()
        assert lost, "no env worker ran on the second node"
        time.sleep(1.0)
        assert not alive(lost), f"processes of the lost node left behind: {alive(lost)}"
        retried = [r for r in summary.rows if r.retries]
        assert summary.status == "complete" and len(summary.rows) == 4
        assert all(r.status == "ok" and r.steps == STEPS for r in summary.rows)
        assert retried and all([a["lost"] for a in r.retries] == ["node"] for r in retried)
        assert any(a["step"] >= 1 and "its node died" in a["cause"] for r in retried for a in r.retries)
        assert summary.manifest["recovery"]["episodes_retried"] == len(retried)
        assert f"retried after a lost {retried[0].retries[-1]['lost']}" in summary.table()
        ran = time.monotonic()
        _assert_same_files(_sequential_episodes(tiny, summary, retried, tmp_path / "seq"), summary)
        assert executors[0].replacements >= 1
        print(f"node test: cluster up {cluster - started:.1f} s, run {ran - cluster:.1f} s, all "
              f"{time.monotonic() - started:.1f} s; retried {[(r.episode, r.retries) for r in retried]}")
    finally:
        if watchdog is not None:
            watchdog.cancel()
        if node is not None:
            _stop_head(node, node_dir)
            shutil.rmtree(node_dir, ignore_errors=True)
        if cluster is None:  # the module's head is stopped by its fixture
            _stop_head(head, head_dir)
            shutil.rmtree(head_dir, ignore_errors=True)
