"""Local parallel executor: N spawned env-worker processes, batched inference in the driver process.

    driver process                                   env worker k (spawned; one per --workers)
    ───────────────────────────────────────────     ─────────────────────────────────────────
    run store (results.jsonl, results.json)          one env (its own GL context), remade per task
    InferenceServer: policy.inference()      <─obs── EpisodeState (history, chunks, seed/t, task)
      one sample_actions call over all        ─act─> rollout() -> EpisodeWriter (background thread,
      waiting workers, padded to a fixed size        PNG pool, MP4) writes the episode folder
    jobs out, finished rows in               <─row─

Where inference runs, and why: in the driver. The driver has already loaded (and checked) the model;
one process holding the model means one copy of the weights, one set of compiled functions and one
XLA thread pool. The driver's other work (appending a row to results.jsonl and rewriting the derived
files once per episode) is small and happens between batches.

Batching: whenever the model is free, up to `policy.inference_batch` waiting requests go into one call,
padded to exactly that size (the one shape compiled during warm-up; nothing compiles during the run).
The batch shape is part of the protocol, not a timing decision: XLA's numbers depend on the batch shape,
so a fixed shape makes every episode's actions and attention bit-identical to a sequential run of the
same protocol, whatever the worker count, the arrival order or the load (each example also has its own
rng key and task, see harness/policy.py). With the default of 1 (right on a CPU, where one inference
already uses every core) requests are served one at a time, first come first served, and the workers
fall out of step: one worker's inference runs while the others simulate (benchmarks/bench_parallel.py
on 2 cores with octo-small: 2 workers 1.15x sequential). On a GPU a larger --inference-batch pays.

Where the writers run, and why: in each env worker, in EpisodeWriter's background thread (and its
PNG thread pool). The frames and masks are already in that process; only the resized observation
window travels to the driver and only the action chunk and attention rows travel back. A worker
only enqueues a step (it waits only if its writer falls `queue_size` steps behind), and encoding
never runs in the driver, so it never stalls inference.

Faults: a worker that dies (SIGKILL, a segfault, an OOM kill) has its current episode recorded as
failed with the cause ("worker process died: signal 9 (SIGKILL)"), an infrastructure failure at the step of
its last inference request (harness.run.executor.Retrying runs it again), and is replaced; a worker whose
episode lost its env (a LIBERO server that died) makes a new one for its next job; an exception in
inference fails the episodes of that batch only, as episode failures (their workers raise it inside the
episode, which records the failure and goes on). Ctrl-C / SIGTERM in the driver: workers (which ignore SIGINT, so a
terminal's Ctrl-C reaches them only through the driver) are told to stop, abort their episode
writers (no temporary files left) and exit; stragglers are terminated, then killed. Workers also exit
when the driver's end of their pipe closes, and get SIGKILL from the kernel if the driver dies
(PR_SET_PDEATHSIG), so no process outlives a run.
"""

from __future__ import annotations

import collections
import functools
import logging
import multiprocessing
import os
import shutil
import signal
import time
import traceback
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from harness.interrupts import die_with_parent
from harness.policy import ClosedLoopPolicy, InferenceRequest, InferenceResult, PolicyConfig, TaskPrompt
from harness.policies.served import ServerLostError
from harness.run.executor import EpisodeContext, InfrastructureError, make_env, record_failure, run_episode
from harness.run.protocol import EpisodeJob
from harness.run.store import EpisodeRow

log = logging.getLogger(__name__)

STOP_TIMEOUT_S = 10.0  # how long stopping workers may take before they are terminated
LIVENESS_S = 0.5  # the longest the pool waits for a message before it checks that its workers still live


@dataclass(frozen=True)
class PolicyShape:
    """What the env side of a policy needs to know about the model (picklable, no weights)."""

    image_sizes: dict  # obs key -> (height, width)
    window_size: int
    action_horizon: int
    dataset_key: str | None
    lowdim_sizes: dict = field(default_factory=dict)  # low-dim obs key -> dims (e.g. {"proprio": 8})

    @classmethod
    def of(cls, model, dataset_key: str | None) -> "PolicyShape":
        return cls(image_sizes=dict(model.image_sizes), window_size=int(model.window_size),
                   action_horizon=int(model.action_horizon), dataset_key=dataset_key,
                   lowdim_sizes=dict(getattr(model, "lowdim_sizes", None) or {}))


@dataclass(frozen=True)
class WorkerSpec:
    """Everything an env worker needs, picklable (module-level functions or functools.partial of them).

    make_env(task) -> env; run_episode(env, policy, job) -> row (records its own failures as failed rows);
    failed_row(job, exc, trace) -> row of an episode whose env could not be made (called in the worker);
    died_row(job, cause, steps) -> row of an episode whose worker died after `steps` (called in the driver).
    """

    make_env: Callable[[str], Any]
    run_episode: Callable[[Any, ClosedLoopPolicy, Any], Any]
    failed_row: Callable[[Any, BaseException, str], Any]
    died_row: Callable[[Any, str, int], Any]
    policy: PolicyConfig
    shape: PolicyShape


def max_workers(cpus: int | None = None, memory_bytes: int | None = None) -> int:
    """The most env workers this machine can use: 4 per CPU core (rendering and physics are CPU-bound; more only
    queue) and one per WORKER_MEMORY of physical memory (each holds an env, a GL context and a writer)."""
    cpus = cpus if cpus is not None else (os.cpu_count() or 1)
    if memory_bytes is None:
        try:
            memory_bytes = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            memory_bytes = 0
    by_memory = memory_bytes // WORKER_MEMORY if memory_bytes > 0 else 4 * cpus
    return max(1, min(4 * cpus, by_memory))


WORKER_MEMORY = 1 << 30  # bytes one env worker may take (measured ~0.4-0.6 GB: robosuite, MuJoCo, GL, writer)


def death_cause(exitcode: int | None) -> str:
    """A worker's exit code -> the error recorded for its episode."""
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = "unknown signal"
        return f"worker process died: signal {-exitcode} ({name})"
    return f"worker process exited unexpectedly with code {exitcode}"


def warmup_request(shape: PolicyShape, task: TaskPrompt) -> InferenceRequest:
    """A zero observation window of the model's sizes (compilation depends on shapes only)."""
    window = shape.window_size
    obs: dict = {k: np.zeros((window, h, w, 3), np.uint8) for k, (h, w) in shape.image_sizes.items()}
    obs.update({k: np.zeros((window, n), np.float32) for k, n in shape.lowdim_sizes.items()})
    obs["timestep_pad_mask"] = np.ones((window,), bool)
    obs["pad_mask_dict"] = {k: np.ones((window,), bool) for k in [*shape.image_sizes, *shape.lowdim_sizes]}
    return InferenceRequest(observation=obs, task=task, seed=0, step=0)


# ---------------------------------------------------------------------------------------------- env worker side


class _Stop(KeyboardInterrupt):
    """The driver asked this worker to stop (or went away): abort the episode like Ctrl-C, write nothing more."""


class PolicyError(RuntimeError):
    """Inference failed for the batch holding this episode's request."""


class PipeInference:
    """Env-worker side of the inference server: `[request] -> [result]` over the worker's pipe."""

    def __init__(self, conn: Connection, dataset_key: str | None):
        self.conn = conn
        self.dataset_key = dataset_key

    def __call__(self, requests: list[InferenceRequest]) -> list[InferenceResult]:
        (request,) = requests
        try:
            self.conn.send(("infer", request))
            kind, payload = self.conn.recv()
        except (EOFError, OSError) as exc:
            raise _Stop("driver went away") from exc
        if kind == "result":
            return [payload]
        if kind == "error":
            raise PolicyError(payload)
        if kind == "lost":
            raise InfrastructureError(payload, ServerLostError.lost)
        raise _Stop("stopped by the driver")


def worker_main(index: int, conn: Connection, spec: WorkerSpec) -> None:
    """Env worker process: take episode jobs, run each with a policy whose inference is the driver's server."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is handled by the driver, which tells us to stop
    die_with_parent()
    os.environ["OCTO_HARNESS_WORKER"] = str(index)
    infer = PipeInference(conn, spec.shape.dataset_key)
    policy = ClosedLoopPolicy(spec.shape, spec.policy, infer)
    env, env_task = None, None
    try:
        conn.send(("ready", None))
        while True:
            try:
                kind, job = conn.recv()
            except (EOFError, OSError):
                return
            if kind != "job":
                return
            try:
                if env_task != job.task:
                    if env is not None:
                        env.close()
                    env, env_task = None, None
                    env = spec.make_env(job.task)
                    env_task = job.task
            except Exception as exc:  # the env could not be made: this episode fails, the worker stays
                row = spec.failed_row(job, exc, traceback.format_exc())
            else:
                row = spec.run_episode(env, policy, job)
                if getattr(row, "failure", None) == "infrastructure" and env is not None:  # its env was lost
                    _close_quietly(env, index)
                    env, env_task = None, None
            conn.send(("done", row))
    except (_Stop, EOFError, BrokenPipeError):
        return
    finally:
        if env is not None:
            _close_quietly(env, index)


def _close_quietly(env, index: int) -> None:
    try:
        env.close()
    except Exception:  # closing a broken env must not hide why the worker stops
        log.debug("env.close failed in worker %d: %s", index, traceback.format_exc())


# ---------------------------------------------------------------------------------------------- driver side


@dataclass(eq=False)
class _Worker:
    index: int
    process: multiprocessing.process.BaseProcess
    conn: Connection
    job: Any = None  # the episode job it is running, None when idle
    ready: bool = False
    step: int = 0  # the step of its job's last inference request (the step a death is recorded at)


class WorkerPool:
    """Runs episode jobs on N env-worker processes; inference for all of them in this (the driver) process.

        pool = WorkerPool(spec, model, workers=2)
        for row in pool.run(jobs): ...   # one row per job, in finishing order, in the driver

    The driver appends each row to the run store. Rows of episodes whose worker died come from
    spec.died_row(job, cause, steps), called in the driver.
    """

    def __init__(self, spec: WorkerSpec, model, workers: int, *, context: str = "spawn"):
        if workers < 1:
            raise ValueError(f"--workers must be >= 1; got {workers}")
        self.spec = spec
        self.workers = workers
        self.inference = model.inference(spec.policy)
        self.ctx = multiprocessing.get_context(context)
        self._pool: dict[int, _Worker] = {}
        self._next_index = 0
        self.replacements = 0
        self.late_sentinels = 0  # deaths seen by waitpid before their sentinel was readable (statistics, tests)
        self.queued: collections.deque = collections.deque()
        self._warm = False
        self.batches: list[int] = []  # number of real requests in each inference call (for statistics/tests)
        self.max_batch = spec.policy.inference_batch  # requests per inference call (see the module docstring)

    # -------------------------------------------------------------- lifecycle

    def _start_worker(self) -> _Worker:
        parent, child = self.ctx.Pipe(duplex=True)
        index = self._next_index
        self._next_index += 1
        process = self.ctx.Process(target=worker_main, args=(index, child, self.spec), name=f"octo-env-worker-{index}",
                                   daemon=True)
        process.start()
        child.close()
        worker = _Worker(index=index, process=process, conn=parent)
        self._pool[index] = worker
        return worker

    def shutdown(self) -> None:
        """Stop every worker: ask, wait up to STOP_TIMEOUT_S, then terminate and kill; reap all of them."""
        for w in self._pool.values():
            try:
                w.conn.send(("stop", None))
            except (OSError, ValueError):
                pass
        deadline = time.monotonic() + STOP_TIMEOUT_S
        live = list(self._pool.values())
        while live and time.monotonic() < deadline:
            for w in live:  # drain what they still send (a worker blocked sending a request then sees the stop)
                try:
                    while w.conn.poll():
                        w.conn.recv()
                except (EOFError, OSError):
                    pass
            wait([w.process.sentinel for w in live], timeout=0.05)
            live = [w for w in live if w.process.is_alive()]
        for w in self._pool.values():
            if w.process.is_alive():
                w.process.terminate()
                w.process.join(2.0)
            if w.process.is_alive():
                w.process.kill()
                w.process.join()
            w.conn.close()
        self._pool.clear()

    def warm_up(self, task: TaskPrompt) -> None:
        """Compile the one inference shape (and build the first task)."""
        self.inference.warm_up(warmup_request(self.spec.shape, task))
        self._warm = True

    # -------------------------------------------------------------- the loop

    def run(self, jobs: Iterable[Any], *, warmup_task: TaskPrompt | None = None) -> Iterator[Any]:
        """Yield one row per job as each finishes. The workers stay for the next `run` until `shutdown()`;
        Ctrl-C (or closing the generator early) stops them at once, leaving no process behind."""
        queue = collections.deque(jobs)
        self.queued = queue  # the jobs not yet handed to a worker (read-only outside: statistics, tests)
        if not queue:
            return
        finished: list = []
        completed = False
        try:
            idle = [w for w in self._pool.values() if w.job is None]
            for _ in range(min(self.workers - len(self._pool), len(queue))):
                self._assign(self._start_worker(), queue)  # new workers make their envs while the model compiles
            for w in idle:
                self._assign(w, queue)
            if warmup_task is not None and not self._warm:
                self.warm_up(warmup_task)
            waiting: list[tuple[_Worker, InferenceRequest]] = []
            while True:
                while finished:
                    yield finished.pop(0)
                if not (queue or any(w.job is not None for w in self._pool.values())):
                    break
                self._poll(queue, waiting, finished.append, block=not waiting)
                if waiting:  # first come, first served
                    batch, waiting[:] = waiting[:self.max_batch], waiting[self.max_batch:]
                    self._serve(batch)
            completed = True
        finally:
            if not completed:
                self.shutdown()

    def _poll(self, queue, waiting, on_row, *, block: bool) -> None:
        """Handle every message (and worker death) that is ready; wait for one when `block`."""
        handles = {}
        for w in self._pool.values():
            handles[w.conn] = w
            handles[w.process.sentinel] = w
        ready = wait(list(handles), timeout=LIVENESS_S if block else 0)
        dead = []
        for handle in ready:
            w = handles[handle]
            if handle is w.process.sentinel:
                dead.append(w)
                continue
            self._receive(w, queue, waiting, on_row)
        for w in self._pool.values():  # a death whose sentinel is not readable yet: the kernel's word (waitpid) first
            if w not in dead and not w.process.is_alive():
                log.info("env worker %d: death seen by waitpid before its sentinel", w.index)
                self.late_sentinels += 1
                dead.append(w)
        for w in dict.fromkeys(dead):
            if w.index not in self._pool:
                continue
            while w.conn.poll():  # messages sent before it died still count (e.g. its last "done")
                try:
                    self._receive(w, queue, waiting, on_row, drain=True)
                except (EOFError, OSError):
                    break
            self._bury(w, queue, waiting, on_row)

    def _receive(self, w: _Worker, queue, waiting, on_row, drain: bool = False) -> None:
        try:
            kind, payload = w.conn.recv()
        except (EOFError, OSError):
            if drain:
                raise
            return  # the sentinel reports the death
        if kind == "infer":
            w.step = payload.step
            waiting.append((w, payload))
            return
        if kind == "ready":
            w.ready = True
        if kind == "done":
            w.job = None
            on_row(payload)
            if not drain:
                self._assign(w, queue)

    @staticmethod
    def _assign(w: _Worker, queue) -> None:
        if queue:
            w.job, w.step = queue.popleft(), 0
            try:
                w.conn.send(("job", w.job))
            except (OSError, ValueError):
                pass  # it died; its sentinel reports it and the job is recorded as failed

    def _bury(self, w: _Worker, queue, waiting, on_row) -> None:
        """A worker died: fail its episode with the cause, drop its request, start a replacement if work remains."""
        w.process.join()
        cause = death_cause(w.process.exitcode)
        del self._pool[w.index]
        w.conn.close()
        waiting[:] = [(x, r) for x, r in waiting if x is not w]
        if w.job is not None:
            log.error("env worker %d died running %s: %s", w.index, w.job, cause)
            on_row(self.spec.died_row(w.job, cause, w.step))
        else:
            log.error("env worker %d died: %s", w.index, cause)
        if queue:
            self.replacements += 1
            self._assign(self._start_worker(), queue)

    def _serve(self, waiting: list[tuple[_Worker, InferenceRequest]]) -> None:
        """One batched inference over every waiting request; results (or the error) go back to their workers."""
        self.batches.append(len(waiting))
        try:
            results = self.inference([r for _, r in waiting])
            replies = [("result", res) for res in results]
        except ServerLostError as exc:  # the policy server went away: not the episodes' doing, retried
            log.error("inference lost its policy server for a batch of %d: %s", len(waiting), exc)
            replies = [("lost", str(exc))] * len(waiting)
        except Exception as exc:  # a policy error fails the episodes of this batch only
            log.error("inference failed for a batch of %d: %s", len(waiting), exc)
            replies = [("error", f"{type(exc).__name__}: {exc}")] * len(waiting)
        for (w, _), reply in zip(waiting, replies):
            try:
                w.conn.send(reply)
            except (OSError, ValueError):
                pass  # it died meanwhile; its sentinel reports it


# ---------------------------------------------------------------------------------------------- the run store's executor


class WorkerDied(InfrastructureError):
    """The env-worker process running an episode died (signal, OOM kill, segfault, its node lost)."""


def _run_job(context: EpisodeContext, tokens, env, policy: ClosedLoopPolicy, job: EpisodeJob) -> EpisodeRow:
    return run_episode(context, job, env, policy, tokens)


def _failed_row(context: EpisodeContext, job: EpisodeJob, exc: BaseException, trace: str) -> EpisodeRow:
    return record_failure(context, job, exc, trace)


def _died_row(context: EpisodeContext, job: EpisodeJob, cause: str, steps: int = 0, lost: str = "worker") -> EpisodeRow:
    """The dead process could not clean up: drop its partial episode folder, then record the (infrastructure)
    failure there, at `steps`."""
    shutil.rmtree(context.episode_dir(job), ignore_errors=True)
    return record_failure(context, job, WorkerDied(cause, lost), steps=steps)


def worker_spec(context: EpisodeContext, model) -> WorkerSpec:
    """The WorkerSpec of a run: the sequential executor's env and episode functions, bound to this run's context."""
    return WorkerSpec(
        make_env=functools.partial(make_env, context),
        run_episode=functools.partial(_run_job, context, model.token_map()),
        failed_row=functools.partial(_failed_row, context),
        died_row=functools.partial(_died_row, context),
        policy=context.protocol.policy,
        shape=PolicyShape.of(model, context.model.get("dataset_key")),
    )


def warmup_task(context: EpisodeContext, jobs: Sequence[EpisodeJob]) -> TaskPrompt | None:
    """The first job's task (compiling with it also builds it: the first episodes find it cached)."""
    return TaskPrompt.of(context.meta(jobs[0]).instruction, context.goals) if jobs else None


class WorkersExecutor:
    """`--workers N`: the run store's executor over a WorkerPool (factory: functools.partial(WorkersExecutor, workers=N)).

    on_step is not forwarded (the steps happen in other processes); progress is reported per episode.
    """

    def __init__(self, context: EpisodeContext, model, *, workers: int):
        self.context = context
        self.workers = workers
        self.pool = WorkerPool(worker_spec(context, model), model, workers)

    def run(self, jobs: Sequence[EpisodeJob], on_step=None) -> Iterator[EpisodeRow]:
        yield from self.pool.run(jobs, warmup_task=warmup_task(self.context, jobs))

    def close(self) -> None:
        self.pool.shutdown()
