"""Ray executor (`--executor ray [--ray-address ADDR]`): env workers and policy replicas as Ray actors.

    driver (this process)                 EnvWorker actor k (1 CPU)               PolicyReplica actor r
    ──────────────────────────────        ──────────────────────────────        ─────────────────────────────
    run store: every write to             one env + GL context; runs an          the model (1 GPU where the
    results.jsonl / results.json   <─row─ episode per call: EpisodeState  ─obs─> cluster has GPUs); batches all
    jobs out ─────────────────────job─>   -> rollout -> EpisodeWriter    <─act─  requests waiting when it is free
                                          (writes the episode folder)            (policy.inference(), one fixed shape)

The driver owns the run store, so resume, statistics and the files of a run are the same as with the
local executor (harness/run/workers.py): env workers run the same episode function and write the
episode folder under `--out`, which therefore must be a filesystem every node sees (NFS, a shared
volume). That is checked before any episode: the driver writes a marker file into the run folder and
every env-worker actor reads it when it starts; a worker that cannot gives one line naming the node.

Env worker k uses replica k % R. A replica is an async actor: requests accumulate while a batch runs
(in a worker thread, off the event loop) and the next batch takes up to `policy.inference_batch` of them,
padded to exactly that size (the protocol's shape: actions bit-identical to a sequential run).

Without an address a local Ray instance is started for this run (no dashboard) and shut down at the
end. Its logical CPUs are max(os.cpu_count(), workers + replicas): each actor asks for one CPU, so
2 workers + 1 replica on a 2-core machine oversubscribe the cores exactly as the local executor does.

Faults: an env-worker actor that dies (SIGKILL, segfault, OOM, its node lost) fails its episode as an infrastructure
failure at the step its replica last served (executor.Retrying runs it again) and is started again; jobs go only
to started workers, so a replacement with no room (its node gone) holds nothing up. A lost replica fails its
episodes the same way, and is started again for its workers. A policy error fails its batch's episodes (episode
failures). Replicas ask for the custom resource `octo_policy` where the cluster offers it (a head that survives).
Ctrl-C kills every actor and, for a local instance, stops Ray (no processes left behind). At the end of a run
the driver disconnects from a cluster too, so that the next run in the same process (a robustness grid's next
cell) connects again.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import os
import socket
import time
import traceback
import uuid
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterable, Iterator

from harness.policy import ClosedLoopPolicy, InferenceRequest, InferenceResult, PolicyConfig, TaskPrompt
from harness.policies.served import ServerLostError
from harness.run.protocol import policy_options
from harness.run.executor import EpisodeContext, InfrastructureError
from harness.run.ray_errors import actor_death_cause, actor_error, last_line, lost_part
from harness.run.workers import PolicyError, WorkerSpec, warmup_request, warmup_task, worker_spec

log = logging.getLogger(__name__)

FORWARDED_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "HF_HUB_OFFLINE", "HF_HOME", "JAX_PLATFORMS")
MARKER_PREFIX = ".octo-harness-shared-check-"
POLICY_RESOURCE = "octo_policy"  # a custom resource that, where the cluster offers it, holds the policy replicas
START_TIMEOUT_S = 300.0  # how long jobs may wait, after a loss, with no env worker started before the run stops
START_TRIES = 3  # times one worker slot is started again in a row before it is given up


class RayExecutorError(ValueError):
    """A user-facing problem with the Ray set-up (one line: what and how to fix it; the CLI prints it, exit 2)."""


def import_ray():
    try:
        import ray
    except ImportError:
        raise RayExecutorError("--executor ray needs Ray: pip install 'octo-harness[ray]' (or pip install 'ray>=2.9')") from None
    return ray


# ---------------------------------------------------------------------------------------------- actors


class PolicyReplica:
    """A model replica serving batched inference requests from many env workers (an async Ray actor)."""

    def __init__(self, model_source: str, config: PolicyConfig, options: dict | None = None):
        from harness.policies import load_policy

        self.model = load_policy(model_source, **(options or {}))  # options: harness.run.protocol.policy_options
        self.inference = self.model.inference(config)
        self._pending: list[tuple[InferenceRequest, asyncio.Future]] = []
        self._running = False
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inference")
        self.batches: list[int] = []
        self.progress: dict = {}  # job key -> the step of its last request (the step a lost worker is recorded at)

    def warm_up(self, request: InferenceRequest) -> int:
        """Compile the one inference shape; returns the number of compiled sampler variants."""
        self.inference.warm_up(request)
        return self.model.sample_cache_size

    def stats(self) -> dict:
        return {"batches": list(self.batches), "sample_cache_size": self.model.sample_cache_size}

    def step_of(self, key) -> int:
        return self.progress.get(key, 0)

    async def infer(self, request: InferenceRequest, key=None) -> InferenceResult:
        if key is not None:
            self.progress[key] = request.step
        future = asyncio.get_running_loop().create_future()
        self._pending.append((request, future))
        if not self._running:
            self._running = True
            asyncio.get_running_loop().create_task(self._serve())
        return await future

    async def _serve(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            while self._pending:
                size = self.inference.batch_size  # the protocol's fixed shape: same numbers as a sequential run
                batch, self._pending = self._pending[:size], self._pending[size:]
                self.batches.append(len(batch))
                try:
                    results = await loop.run_in_executor(self._thread, self.inference, [r for r, _ in batch])
                except ServerLostError as exc:  # the policy server went away: an infrastructure failure, retried
                    for _, future in batch:
                        future.set_exception(InfrastructureError(str(exc), ServerLostError.lost))
                except Exception as exc:  # a policy error fails the episodes of this batch only
                    for _, future in batch:
                        future.set_exception(PolicyError(f"{type(exc).__name__}: {exc}"))
                else:
                    for (_, future), result in zip(batch, results):
                        future.set_result(result)
        finally:
            self._running = False


class RayInference:
    """Env-worker side: `[request] -> [result]` through a PolicyReplica actor."""

    def __init__(self, replica, dataset_key: str | None):
        self.replica = replica
        self.dataset_key = dataset_key
        self.key = None  # the job under way (the replica records its steps)

    def __call__(self, requests: list[InferenceRequest]) -> list[InferenceResult]:
        import ray

        (request,) = requests
        try:
            return [ray.get(self.replica.infer.remote(request, self.key))]
        except ray.exceptions.RayTaskError as exc:  # the replica's PolicyError (this batch failed)
            cause = getattr(exc, "cause", None)
            if isinstance(cause, InfrastructureError):  # the replica lost its policy server
                raise InfrastructureError(str(cause), cause.lost) from None
            raise PolicyError(str(cause) if cause is not None else last_line(exc)) from None
        except ray.exceptions.RayActorError as exc:  # the replica (or its node) was lost: not the episode's doing
            raise InfrastructureError(f"policy replica lost: {str(exc).splitlines()[0]}", "policy replica") from None


class EnvWorker:
    """One env (and GL context) on some node; `run(job)` runs one episode and returns its row."""

    def __init__(self, spec: WorkerSpec, replica, marker: tuple[str, str]):
        path, token = marker
        try:
            seen = Path(path).read_text()
        except OSError:
            seen = None
        if seen != token:
            raise RayExecutorError(f"--out is not visible from node {socket.gethostname()} ({path} is missing there or not this run's); "
                                   "put --out on a filesystem every Ray node mounts at the same path (NFS, shared volume)")
        self.spec = spec
        self.infer = RayInference(replica, spec.shape.dataset_key)
        self.policy = ClosedLoopPolicy(spec.shape, spec.policy, self.infer)
        self.env, self.env_task = None, None

    def ready(self) -> tuple[str, int, str]:
        import ray

        return socket.gethostname(), os.getpid(), ray.get_runtime_context().get_node_id()

    def use_replica(self, replica) -> None:
        """Serve the next episodes from `replica` (the restarted one)."""
        self.infer.replica = replica

    def run(self, job) -> Any:
        self.infer.key = job.key
        row = self._run(job)
        if getattr(row, "failure", None) == "infrastructure" and self.env is not None:  # its env was lost
            try:
                self.env.close()
            except Exception:  # closing what was lost must not hide the episode's row
                log.debug("closing a lost env failed: %s", traceback.format_exc())
            self.env, self.env_task = None, None
        return row

    def _run(self, job) -> Any:
        if self.env_task != job.task:
            if self.env is not None:
                self.env.close()
            self.env, self.env_task = None, None
            try:
                self.env = self.spec.make_env(job.task)
            except Exception as exc:  # the env could not be made: this episode fails, the worker stays
                return self.spec.failed_row(job, exc, traceback.format_exc())
            self.env_task = job.task
        return self.spec.run_episode(self.env, self.policy, job)


# ---------------------------------------------------------------------------------------------- driver


class RayExecutor:
    """Runs episode jobs on env-worker actors with inference on policy-replica actors; rows come back to the driver.

        factory = functools.partial(RayExecutor, workers=2, address=None)   # factory(context, model)
        for row in factory(context, model).run(jobs): ...                  # the driver appends each row
    """

    def __init__(self, context: EpisodeContext, model, *, workers: int | None, address: str | None = None,
                 replicas: int = 1):
        """workers None: os.cpu_count() on a local instance, the cluster's CPUs minus one per replica on a cluster."""
        if (workers is not None and workers < 1) or replicas < 1:
            raise ValueError(f"--workers and --policy-replicas must be >= 1; got {workers} and {replicas}")
        import_ray()  # not installed: one line before anything starts
        self.context = context
        self.spec = worker_spec(context, model)
        self.model_source = model.source
        self.workers = workers
        self.replicas = replicas
        self.run_dir = Path(context.run_dir)
        self.address = address
        self.replacements = 0
        self.replica_stats: list[dict] = []
        self._ray = None
        self._connected = False  # this executor called ray.init (a local instance, or a connection to `address`)
        self._actors: dict = {}
        self._replicas: list = []
        self._replica_cls = None
        self._replica_resources: dict = {}
        self._warmup: TaskPrompt | None = None
        self._served_by: dict = {}  # worker index -> the replica handle it was given
        self._idle: collections.deque = collections.deque()  # started workers without a job
        self._starting: dict = {}  # ready() ref -> worker index, for workers (re)starting
        self._start_failures: dict = {}
        self._node_of: dict = {}  # worker index -> the Ray node id it started on
        self.started_on: dict = {}  # worker index -> (host, pid, node id) of its actor (statistics, tests)
        self.running: dict = {}  # worker index -> the job it runs (read-only outside: statistics, tests)
        self.replica_restarts = 0
        self._marker: Path | None = None
        self._token = ""
        self._worker_cls = None

    def _init(self):
        ray = import_ray()
        env_vars = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
        if self.address:
            try:
                ray.init(address=self.address, runtime_env={"env_vars": env_vars}, log_to_driver=True)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise RayExecutorError(f"cannot connect to the Ray cluster at {self.address}: {str(exc).splitlines()[0]}; "
                                       "check `ray status` on the head node") from None
            self._connected = True
        else:
            with warnings.catch_warnings():  # Ray starts its daemons with fork+exec, which JAX's fork warning flags
                warnings.simplefilter("ignore", RuntimeWarning)
                if self.workers is None:
                    self.workers = os.cpu_count() or 1
                # "local": a new instance of this run's own, even where RAY_ADDRESS or /tmp/ray names a running
                # cluster (ray.init would join it, and refuse num_cpus for it)
                ray.init(address="local", num_cpus=max(os.cpu_count() or 1, self.workers + self.replicas),
                         include_dashboard=False,
                         runtime_env={"env_vars": env_vars}, configure_logging=False, log_to_driver=True)
            self._connected = True
        self._ray = ray
        return ray

    def _check_resources(self, ray) -> float:
        """Returns GPUs per replica (1 where the cluster has enough GPUs, else 0); one line when CPUs cannot fit the actors."""
        resources = ray.cluster_resources()
        cpus, gpus = resources.get("CPU", 0), resources.get("GPU", 0)
        if self.workers is None:
            self.workers = max(1, int(cpus) - self.replicas)
        if cpus < self.workers + self.replicas:
            raise RayExecutorError(f"the Ray cluster has {cpus:g} CPUs; {self.workers} env workers + {self.replicas} policy "
                                   f"replica(s) need {self.workers + self.replicas}: lower --workers or add nodes")
        held = resources.get(POLICY_RESOURCE, 0)  # the nodes that hold the replicas (a head that survives)
        self._replica_resources = {POLICY_RESOURCE: held / self.replicas} if held else {}
        return 1.0 if gpus >= self.replicas else 0.0

    def _start(self, warmup: TaskPrompt | None) -> None:
        """Start Ray, the policy replicas and the env-worker actors; check the shared folder and warm up."""
        ray = self._init()
        gpus = self._check_resources(ray)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._marker = self.run_dir / f"{MARKER_PREFIX}{uuid.uuid4().hex}"
        self._token = uuid.uuid4().hex
        self._marker.write_text(self._token)
        self._replica_cls = ray.remote(num_cpus=1, num_gpus=gpus, resources=self._replica_resources)(PolicyReplica)
        self._worker_cls = ray.remote(num_cpus=1, max_restarts=0)(EnvWorker)
        self._warmup = warmup
        self._replicas = [self._new_replica() for _ in range(self.replicas)]
        warming = [r.warm_up.remote(warmup_request(self.spec.shape, warmup)) for r in self._replicas] if warmup else []
        for i in range(self.workers):
            self._start_worker(i)
        try:  # the replicas load the model and compile while the env workers start (`_started`: each takes jobs then)
            ray.get(warming)
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as exc:
            if isinstance(exc, ray.exceptions.RayTaskError) or exc.actor_init_failed:  # the model did not load there
                raise RayExecutorError(last_line(exc)) from None
            raise RayExecutorError(f"the policy replica did not start: {actor_error(exc)}") from None

    def _new_replica(self):
        protocol = self.context.protocol
        return self._replica_cls.remote(self.model_source, self.spec.policy,
                                        policy_options(protocol.text_tokenizer, protocol.served_conventions))

    def _start_worker(self, i: int):
        """Start env worker `i` (again); it takes jobs once its `ready` answers (`_started`)."""
        replica = self._replicas[i % self.replicas]
        self._actors[i] = self._worker_cls.remote(self.spec, replica, (str(self._marker), self._token))
        self._served_by[i] = replica
        self._starting[self._actors[i].ready.remote()] = i
        return self._actors[i]

    def _started(self, ref) -> None:
        """A worker's `ready` answered: it takes jobs; one that died starting is started again (START_TRIES in a
        row, then its slot is given up: the other workers take its jobs)."""
        ray = self._ray
        i = self._starting.pop(ref)
        try:
            self.started_on[i] = ray.get(ref)
            self._node_of[i] = self.started_on[i][2]
        except (ray.exceptions.RayActorError, ray.exceptions.RayTaskError) as exc:
            if "RayExecutorError" in str(exc):  # its own one-line refusal (--out not visible there): the run stops
                raise RayExecutorError(last_line(exc)) from None
            self._start_failures[i] = self._start_failures.get(i, 0) + 1
            log.error("env worker %d could not start (%d of %d): %s", i, self._start_failures[i], START_TRIES,
                      last_line(exc))
            if self._start_failures[i] < START_TRIES:
                self._start_worker(i)
            return
        self._start_failures.pop(i, None)
        self._idle.append(i)

    def _lost_worker(self, i: int, job, exc) -> Any:
        """Env worker `i` died running `job`: its (infrastructure) row, at the step its replica last served it; the
        worker is started again (it takes jobs once it has started, wherever the cluster has room)."""
        ray = self._ray
        node = self._node_of.get(i)

        def node_alive():
            try:
                return any(n["NodeID"] == node and n["Alive"] for n in ray.nodes())
            except Exception:  # the GCS does not answer now
                return None

        lost = lost_part(exc, node_alive if node else None)
        cause = actor_death_cause(exc, lost)
        log.error("env worker %d died running %s (%s lost): %s", i, job, lost, cause)
        try:
            steps = int(ray.get(self._served_by[i].step_of.remote(job.key), timeout=30))
        except Exception:  # the replica is gone too, or does not answer: the step is not known
            steps = 0
        row = self.spec.died_row(job, cause, steps, lost)
        try:
            ray.kill(self._actors[i], no_restart=True)
        except Exception:  # already gone with its node
            pass
        self.replacements += 1
        self._start_worker(i)
        return row

    def _lost_replica(self, i: int) -> None:
        """Worker `i`'s episode lost its policy replica: start the replica again (once, whichever of its workers says
        so first) and switch its workers to it (after the episode each runs now: actor calls run in order)."""
        ray = self._ray
        r = i % self.replicas
        if self._served_by.get(i) is self._replicas[r]:
            log.error("policy replica %d was lost; starting it again", r)
            try:
                ray.kill(self._replicas[r], no_restart=True)
            except Exception:  # already gone
                pass
            self._replicas[r] = self._new_replica()
            self.replica_restarts += 1
            if self._warmup is not None:
                ray.get(self._replicas[r].warm_up.remote(warmup_request(self.spec.shape, self._warmup)))
        for j, actor in self._actors.items():
            if j % self.replicas == r and self._served_by.get(j) is not self._replicas[r]:
                actor.use_replica.remote(self._replicas[r])
                self._served_by[j] = self._replicas[r]

    def run(self, jobs: Iterable[Any], on_step=None) -> Iterator[Any]:
        """Yield one row per job as each finishes (on_step is not forwarded: steps happen on other processes).

        The actors stay for the next `run` until `close()`; an exception (Ctrl-C) stops everything at once."""
        jobs = list(jobs)
        queue = collections.deque(jobs)
        if not queue:
            return
        completed = False
        try:
            if self._ray is None:
                self._start(warmup_task(self.context, jobs))
            ray = self._ray
            in_flight: dict = {}
            waiting_since = None
            while queue or in_flight:
                while queue and self._idle:
                    i = self._idle.popleft()
                    job = queue.popleft()
                    in_flight[self._actors[i].run.remote(job)] = (i, job)
                    self.running[i] = job
                if not in_flight and not self._starting:
                    raise RayExecutorError("no env worker can start on the Ray cluster (its nodes were lost); add "
                                           "nodes, then `run --resume` the run folder")
                if not in_flight and self.replacements:  # jobs wait for a worker to start after a loss
                    waiting_since = waiting_since or time.monotonic()
                    if time.monotonic() - waiting_since > START_TIMEOUT_S:
                        raise RayExecutorError(f"no env worker started on the Ray cluster within {START_TIMEOUT_S:.0f} s "
                                               "(its nodes were lost: no room for one); add nodes, then `run --resume` "
                                               "the run folder")
                else:
                    waiting_since = None
                ready, _ = ray.wait([*in_flight, *self._starting], num_returns=1, timeout=5.0)
                if not ready:
                    continue
                (ref,) = ready
                if ref in self._starting:
                    self._started(ref)
                    continue
                i, job = in_flight.pop(ref)
                self.running.pop(i, None)
                try:
                    row = ray.get(ref)
                except ray.exceptions.RayActorError as exc:
                    yield self._lost_worker(i, job, exc)
                    continue
                except ray.exceptions.RayTaskError as exc:  # a bug in the episode function itself
                    row = self.spec.failed_row(job, RuntimeError(last_line(exc)), str(exc))
                if getattr(row, "lost", None) == "policy replica":
                    self._lost_replica(i)
                self._idle.append(i)
                yield row
            self.replica_stats = ray.get([r.stats.remote() for r in self._replicas])
            completed = True
        finally:
            if not completed:
                self.close()

    def close(self) -> None:
        """Kill every actor, remove the marker and stop a Ray instance started here (idempotent)."""
        ray = self._ray
        if ray is None:
            return
        for actor in list(self._actors.values()) + self._replicas:
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # already dead
                pass
        self._actors, self._replicas = {}, []
        self._idle.clear()
        self._starting.clear()
        self._served_by.clear()
        if self._marker is not None:
            self._marker.unlink(missing_ok=True)
        if self._connected:  # stops a local instance; from a cluster, only disconnects (the next run connects again)
            ray.shutdown()
            self._connected = False
        self._ray = None
