"""Executors: what turns episode jobs into finished episodes. The driver (harness/run/driver.py) owns the run store.

The interface (all an executor has to provide):

    class Executor:
        def run(self, jobs: Sequence[EpisodeJob], on_step=None) -> Iterator[EpisodeRow]: ...
        def close(self) -> None: ...

- `run` receives the jobs still to do (in run order) and yields exactly one `EpisodeRow` per job as each
  finishes, in any order. A job that fails (an exception in the env, the policy or the writer) yields a row
  with status "failed", its error and its kind (`failure_of`): "episode", or "infrastructure" where what ran it
  was lost (a worker, a node, a policy replica, a LIBERO server, a render context); the executor goes on with the
  other jobs. The driver wraps every executor in `Retrying`, which runs infrastructure failures again.
- Episode files are written by `EpisodeWriter` into `<run_dir>/<job.directory>` only (`run_episode` does all
  of it, and records the size and sha256 of the data files in the row, harness/runfolder/integrity.py); an executor never touches results.jsonl, results.json, summary.csv or the manifest: the driver
  appends each yielded row and rewrites the derived files, so every executor leaves the same run folder.
- Episodes are independent given (task, seed): `env.reset(seed=seed)` and `ClosedLoopPolicy.reset(..., seed=seed)`
  restore everything an episode depends on, so a job gives the same files whichever process runs it and
  whatever ran before (this is what makes resume and parallel runs equal a sequential run).
- `harness.policy.EnvMismatchError` (the model's inputs or action dimension do not fit the env: a protocol error,
  not an episode outcome) propagates out of `run` like KeyboardInterrupt; the driver stops the run with one line.
- On KeyboardInterrupt (SIGINT, or SIGTERM turned into `Interrupted`) `run` aborts the episodes in flight
  (their writers delete temporaries and never write episode.json) and lets the exception propagate; the
  driver then calls `close()` and removes the incomplete episode folders.
- `on_step(job, t, record)` (optional) is called after each control step, for progress display.

An executor is built by a factory `factory(context, model) -> Executor`; `EpisodeContext` is frozen and
picklable (protocol, run folder, model description, goal images), so worker processes can receive it.
`SequentialExecutor` is the reference: one environment at a time in this thread, the loaded model.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterator, Protocol as TypingProtocol, Sequence

import numpy as np

import envs
from envs.perturbations import instruction_for
from harness.files import atomic_write_json
from harness.policy import ClosedLoopPolicy, EnvMismatchError
from harness.policies.served import ServerLostError
from harness.records import EpisodeMeta, StepRecord
from harness.rollout import rollout
from harness.run.protocol import EpisodeJob, Protocol
from harness.run.space import DISK, disk_error
from harness.run.store import EpisodeRow
from harness.runfolder.integrity import data_digests
from harness.outputs.writers import EpisodeWriter

log = logging.getLogger(__name__)

StepCallback = Callable[[EpisodeJob, int, StepRecord], None]


@dataclass(frozen=True, eq=False)
class EpisodeContext:
    """What any process needs to run a job of this run (picklable)."""

    protocol: Protocol
    run_dir: str  # absolute path of the run folder
    run: str  # run name
    model: dict  # manifest["model"]: source, is_random, text_tokenizer, dataset_key, ...
    goals: dict[str, np.ndarray] | None  # {obs key: (height, width, 3) uint8} at the model's goal sizes
    viewer: str | None = None  # gRPC url of a live Rerun viewer every episode streams to (--rerun spawn/serve)

    def episode_dir(self, job: EpisodeJob) -> Path:
        return Path(self.run_dir) / job.directory

    def meta(self, job: EpisodeJob) -> EpisodeMeta:
        spec = envs.get_task(job.task)
        perturbations = envs.parse_perturb(self.protocol.perturb)
        return EpisodeMeta(
            run=self.run, task=job.task, episode=job.episode, seed=job.seed,
            instruction=instruction_for(spec, self.protocol.instruction or spec.instruction, job.seed, perturbations),
            model=self.model["source"], model_is_random=bool(self.model["is_random"]),
            dataset_key=self.model.get("dataset_key"), text_tokenizer=self.model.get("text_tokenizer", ""),
            execution=self.protocol.policy.describe(),
            extra={"perturb": self.protocol.perturb} if self.protocol.perturb else {},
        )


class Executor(TypingProtocol):
    def run(self, jobs: Sequence[EpisodeJob], on_step: StepCallback | None = None) -> Iterator[EpisodeRow]: ...

    def close(self) -> None: ...


def make_env(context: EpisodeContext, task: str):
    """The environment of `task` as the protocol asks for it (create and use it in one thread)."""
    return _make_env(context.protocol, task)


def _make_env(protocol: Protocol, task: str):
    return envs.make(task, protocol.env_for(task), instruction=protocol.instruction, perturb=protocol.perturb)


class CheckedEnv:
    """The first task's environment, made before the run starts to check the model against it (EnvMismatchError,
    one line). An executor that steps episodes in this thread takes it (`adopt`) for that task's episodes rather
    than making the same env again (robosuite: about 2 s; LIBERO: a server process); otherwise it is closed."""

    def __init__(self, protocol: Protocol, model, task: str):
        self.task = task
        self._env = _make_env(protocol, task)
        try:
            model.closed_loop(protocol.policy).check_env(self._env)
        except BaseException:
            self.close()
            raise

    @property
    def env(self):
        """The env, still this object's to close (the pre-flight check resets it once)."""
        return self._env

    def take(self):
        """The env, now the caller's to close (None once taken or closed)."""
        env, self._env = self._env, None
        return env

    def close(self) -> None:
        env = self.take()
        if env is not None:
            env.close()


def run_episode(context: EpisodeContext, job: EpisodeJob, env, policy: ClosedLoopPolicy, tokens=None,
                on_step: StepCallback | None = None) -> EpisodeRow:
    """Roll out one job with `env` and `policy` and write its episode folder; a failure gives a "failed" row."""
    episode_dir = context.episode_dir(job)
    meta = context.meta(job)
    extra = {"control_hz": (getattr(env, "metadata", None) or {}).get("render_fps"),  # the recording's sim_time
             "intervention": context.protocol.policy.intervention}
    meta = dataclasses.replace(meta, extra={**meta.extra, **{k: v for k, v in extra.items() if v is not None}})
    writer = None
    steps = 0  # steps that ran, for the failed row when the episode fails after some (e.g. finishing its files)

    def step_cb(t, record):
        nonlocal steps
        steps = t + 1
        if on_step is not None:
            on_step(job, t, record)

    try:
        writer = EpisodeWriter(episode_dir, tokens, meta, context.protocol.outputs, viewer=context.viewer)
        result = rollout(env, policy, writer.add_step, seed=job.seed, instruction=meta.instruction, goals=context.goals,
                         max_steps=context.protocol.max_steps, on_step=step_cb)
        drawn = getattr(getattr(env, "unwrapped", env), "perturbation_record", None) if context.protocol.perturb else None
        written = writer.finish({"success": result.success, "steps": result.steps, "total_reward": result.total_reward,
                                 "actions_clipped": result.actions_clipped, "timings": result.timings,
                                 **({"phases": result.phases} if result.phases is not None else {}),
                                 **({"outcome": result.outcome} if result.outcome is not None else {}),
                                 **({"perturbation": drawn} if drawn is not None else {})})
        files = data_digests(episode_dir, (Path(p).name for p in written["paths"].values()))  # size and sha256
    except (KeyboardInterrupt, EnvMismatchError):  # a model/env mismatch is the protocol's error: refuse the run
        if writer is not None:
            writer.abort()
        raise
    except Exception as exc:  # a failing episode is recorded and the run goes on
        if writer is not None:
            writer.abort()
        return record_failure(context, job, exc, traceback.format_exc(), steps)
    n = max(result.steps, 1)
    step = result.timings["step"] / n
    sim = result.timings["simulation"] / n
    inf = result.timings["inference"] / n
    return EpisodeRow(run=context.run, task=job.task, episode=job.episode, seed=job.seed, status="ok",
                      success=bool(result.success), steps=result.steps, total_return=float(result.total_reward),
                      seconds_per_step=step, simulation_per_step=sim, inference_per_step=inf,
                      overhead_fraction=(step - sim - inf) / step if step > 0 else 0.0, directory=job.directory,
                      files=files, furthest_phase=(result.phases or {}).get("furthest"))


class InfrastructureError(RuntimeError):
    """What ran the episode was lost, not the episode itself (`lost`: "worker", "node", "policy replica", ...): its job
    is retried elsewhere (`Retrying`)."""

    def __init__(self, message: str, lost: str = "worker"):
        super().__init__(message)
        self.lost = lost

    def __reduce__(self):  # keeps `lost` across a process boundary (Ray sends a replica's exception back pickled)
        return type(self), (str(self), self.lost)


def failure_of(exc: BaseException) -> tuple[str, str | None]:
    """An episode's exception -> (failure kind, the lost part or None): "infrastructure" for a lost worker, node or
    policy replica (InfrastructureError), a policy server that refused, dropped or stopped answering the connection
    (harness.policies.served.ServerLostError: the retry reconnects), what a suite says its env lost (envs.suites.Suite.lost: a LIBERO server that
    died or stopped answering), a render context that OpenGL lost, or a disk that filled ("disk": the driver stops the run, harness/run/space.py); "episode" for
    anything else (the policy, the env, the physics, a non-finite action)."""
    if disk_error(exc) is not None:
        return "infrastructure", DISK
    if isinstance(exc, (InfrastructureError, ServerLostError)):
        return "infrastructure", exc.lost
    lost = envs.suites.lost(exc)
    if lost is not None:
        return "infrastructure", lost
    if type(exc).__module__.split(".")[0] == "OpenGL":  # OpenGL.error.GLError: the GL context is gone
        return "infrastructure", "render context"
    return "episode", None


def record_failure(context: EpisodeContext, job: EpisodeJob, exc: BaseException, trace: str = "",
                   steps: int = 0) -> EpisodeRow:
    """Write the failed episode's episode.json where possible and return its "failed" row (`steps` that ran), with
    the failure's kind (`failure_of`). A full disk leaves nothing of the episode: it runs again on resume."""
    error = f"{type(exc).__name__}: {exc}".splitlines()[0]
    failure, lost = failure_of(exc)
    log.error("episode %s failed (%s): %s", job.directory, failure, error)
    if lost == DISK:
        shutil.rmtree(context.episode_dir(job), ignore_errors=True)
        return EpisodeRow.failed(context.run, job, error, steps=steps, failure=failure, lost=lost)
    try:
        atomic_write_json(context.episode_dir(job) / "episode.json",
                          {**asdict(context.meta(job)), "status": "failed", "success": False, "steps": steps,
                           "error": error, "failure": failure, "traceback": trace})
    except OSError as write_error:  # the folder itself may be what failed; results.jsonl still records it
        log.error("could not write %s: %s", context.episode_dir(job) / "episode.json", write_error)
    return EpisodeRow.failed(context.run, job, error, steps=steps, failure=failure, lost=lost)


class SequentialExecutor:
    """The reference executor: jobs one after another in this thread, one environment open at a time."""

    def __init__(self, context: EpisodeContext, model):
        self.context = context
        self.policy = model.closed_loop(context.protocol.policy)
        self.tokens = model.token_map()
        self._env = None
        self._env_task: str | None = None

    def _environment(self, task: str):
        if self._env_task != task:
            self.close()
            self._env = make_env(self.context, task)
            self._env_task = task
            self.policy.check_env(self._env)  # EnvMismatchError: one line, the run stops before this task's episodes
        return self._env

    def adopt(self, checked: CheckedEnv) -> None:
        """Run `checked.task`'s episodes in the env the driver made (and checked) with the same arguments: an
        episode depends on (task, seed) only, not on what the env did before (see the module docstring)."""
        if self._env is None:
            self._env_task, self._env = checked.task, checked.take()

    def run(self, jobs: Sequence[EpisodeJob], on_step: StepCallback | None = None) -> Iterator[EpisodeRow]:
        for job in jobs:
            try:
                env = self._environment(job.task)
            except EnvMismatchError:
                raise
            except Exception as exc:  # e.g. a camera the task lacks: this job fails, the next one tries again
                yield record_failure(self.context, job, exc, traceback.format_exc())
                continue
            row = run_episode(self.context, job, env, self.policy, self.tokens, on_step)
            if row.failure == "infrastructure":  # its env (a LIBERO server, a GL context) is gone: the next job makes one
                self._drop_env()
            yield row

    def _drop_env(self) -> None:
        try:
            self.close()
        except Exception:  # closing what was lost must not hide the episode's row
            log.debug("closing a lost env failed: %s", traceback.format_exc())
        self._env, self._env_task = None, None

    def close(self) -> None:
        env, self._env, self._env_task = self._env, None, None
        if env is not None:
            env.close()


class Retrying:
    """Any executor with its infrastructure failures retried (`--retries N`, the driver wraps every executor in it).

    A job whose row is an infrastructure failure (`failure_of`) goes back to the executor, its folder emptied, up to
    `retries` times; the executor's replacement (or any other) worker runs it, and since an episode depends on
    (task, seed) only, it writes the files an uninterrupted run writes. Episode failures are never retried. A loss
    that recurs at the same step (after at least one) is the episode's own doing (a simulator crash or hang its
    actions cause): it becomes an episode failure. After `retries` retries the job stays an infrastructure failure.
    A full disk (lost part "disk") is never retried: the driver stops the run at its row.
    The row finally yielded lists the lost attempts in `retries`. Retries run once the jobs given have finished.
    """

    def __init__(self, executor: Executor, retries: int, run_dir: str | Path):
        self.executor = executor
        self.retries = retries
        self.run_dir = Path(run_dir)

    def run(self, jobs: Sequence[EpisodeJob], on_step: StepCallback | None = None) -> Iterator[EpisodeRow]:
        by_key = {job.key: job for job in jobs}
        lost: dict[tuple[str, int], list[dict]] = {}
        pending = list(jobs)
        while pending:
            again = []
            for row in self.executor.run(pending, on_step=on_step):
                attempts = lost.setdefault(row.key, [])
                if row.failure == "infrastructure" and row.lost != DISK:
                    if attempts and row.steps > 0 and attempts[-1]["step"] == row.steps:
                        row = dataclasses.replace(row, failure="episode", lost=None,
                                                  error=f"{row.error} (again at step {row.steps} on a retry: the "
                                                        "episode's own failure)")
                    elif len(attempts) < self.retries:
                        attempts.append({"lost": row.lost or "worker", "cause": row.error, "step": row.steps})
                        log.warning("episode %s lost its %s at step %d; retrying it (%d of %d)", row.directory,
                                    row.lost or "worker", row.steps, len(attempts), self.retries)
                        shutil.rmtree(self.run_dir / row.directory, ignore_errors=True)
                        again.append(by_key[row.key])
                        continue
                if attempts:
                    row = dataclasses.replace(row, retries=tuple(attempts))
                yield row
            pending = sorted(again)

    def close(self) -> None:
        self.executor.close()
