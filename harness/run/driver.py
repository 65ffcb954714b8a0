"""The run driver: checks -> lock -> protocol comparison -> model -> manifest -> executor loop -> results.

`execute(protocol, out)` is the whole pipeline of `octo-harness run`. It owns every write to the run store:
each row the executor yields is appended to results.jsonl (fsynced), then results.json / summary.csv /
statistics.csv are rewritten. Running it again with the same protocol resumes (finished jobs are skipped,
unless their files are missing or differ from the sizes and digests their rows record; leftover temporaries
and incomplete episode folders are deleted first); a different protocol under the same
run name raises `ProtocolMismatchError` naming the differing fields unless `overwrite`. SIGINT and SIGTERM
raise `Interrupted` (a KeyboardInterrupt) outside the store's critical sections; the results then say
"interrupted".
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from harness.measures.attention import MEASURES_VERSION
from harness.policies import as_policy, family_of
from harness import interrupts
from harness.run import checks, space
from harness.run.protocol import protocol_from_manifest
from harness.runfolder.platform import (git_commit, platform_differences, platform_fingerprint, platform_info,
                                        suite_platforms)
from harness.run.executor import CheckedEnv, EpisodeContext, Executor, Retrying, SequentialExecutor, StepCallback
from harness.run.preflight import check_run
from harness.run.progress import Progress
from harness.run.protocol import (FORMAT, EpisodeJob, Protocol, Recovery, diff, goal_fingerprint,
                                  load_protocol_policy, model_fingerprint)
from harness.outputs.writers import recorded_presentation
from harness.run.store import MANIFEST, EpisodeRow, RunStore, now_utc, recovery, recovery_lines, statistics

log = logging.getLogger(__name__)

ExecutorFactory = Callable[[EpisodeContext, object], Executor]
CI_METHODS = ("wilson", "clopper-pearson")


class ProtocolMismatchError(ValueError):
    """An existing run folder holds a different protocol."""


Interrupted = interrupts.Interrupted  # SIGINT or SIGTERM arrived; `signum` says which (exit code 128 + signum)


@dataclass(frozen=True)
class RunSummary:
    run_dir: Path
    rows: tuple[EpisodeRow, ...]  # finished episodes in job order (directory relative to run_dir)
    manifest: dict
    status: str  # "complete" | "interrupted"
    statistics: dict
    skipped: int = 0  # jobs already finished before this call (resume)

    def episode_dir(self, row: EpisodeRow) -> Path:
        return self.run_dir / row.directory

    def table(self) -> str:
        """Per-task table with success rate and its confidence interval (plain text)."""
        header = (f"{'task':<18} {'done':>5} {'failed':>6} {'success':>8} {'rate':>6} {'95% CI':>15} {'steps':>6} "
                  f"{'s/step':>7} {'infer':>6} {'sim':>6} {'overhead':>8}")
        lines = [header, "-" * len(header)]
        groups = {t: [r for r in self.rows if r.task == t] for t in self.statistics["tasks"]}
        groups["overall"] = list(self.rows)
        for task, rows in groups.items():
            s = self.statistics["overall"] if task == "overall" else self.statistics["tasks"][task]
            ok = [r for r in rows if r.status == "ok"]
            rate = f"{s['success_rate']:.0%}" if s["n"] else "-"
            ci = f"[{s['ci_low']:.2f}, {s['ci_high']:.2f}]" if s["n"] else "-"
            lines.append(f"{task:<18} {len(rows):>5} {s['failed']:>6} {s['successes']:>4}/{s['n']:<3} {rate:>6} "
                         f"{ci:>15} {_mean([r.steps for r in ok]):>6.1f} {_mean([r.seconds_per_step for r in ok]):>7.3f} "
                         f"{_mean([r.inference_per_step for r in ok]):>6.3f} {_mean([r.simulation_per_step for r in ok]):>6.3f} "
                         f"{_mean([r.overhead_fraction for r in ok]):>8.1%}")
            if task != "overall" and len(groups) == 2:
                break  # one task: the overall row would repeat it
        method = self.statistics["overall"]["method"]
        lines.append(f"success interval: {method} {self.statistics['overall']['confidence']:.0%}; "
                     "failed episodes (errors) are not counted in n")
        return "\n".join(lines + recovery_lines(recovery(self.rows)))


def _mean(values) -> float:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else float("nan")


def default_run_name(protocol: Protocol) -> str:
    """<model short name>_<first 10 hex digits of the protocol hash>: the same command resumes the same run."""
    return f"{family_of(protocol.model).run_label(protocol.model)}_{protocol.hash()[:10]}"


# ---- signals ---------------------------------------------------------------------------------------

class _SignalGuard:
    """SIGINT/SIGTERM -> Interrupted, deferred while inside `critical()` (appending and deriving results)."""

    def __init__(self):
        self.depth = 0
        self.pending: int | None = None

    def handler(self, signum, frame) -> None:
        interrupts.record(signum)  # kept even if the KeyboardInterrupt below is swallowed (a __del__)
        if self.depth:
            self.pending = signum
            return
        interrupts.deliver(signum, frame)  # raises, unless the main thread is inside an import (then soon after)

    @contextmanager
    def critical(self):
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1
        if not self.depth and self.pending is not None:
            signum, self.pending = self.pending, None
            interrupts.deliver(signum, None)  # raises (marked raised: no re-sent signal follows)

    @contextmanager
    def installed(self):
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        previous = {s: signal.signal(s, self.handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            interrupts.check()  # a signal that arrived before (loading the model) and was swallowed
            yield self
        finally:
            for s, h in previous.items():
                signal.signal(s, h)


# ---- the pipeline ----------------------------------------------------------------------------------

def _tokenizer_label(tokenizer) -> str:
    if tokenizer is None:
        return "none (goal-conditioned model)"
    return tokenizer.label() if hasattr(tokenizer, "label") else str(tokenizer.name)


def _model_info(model, policy_dataset_key, fingerprint: dict) -> dict:
    return {
        "source": model.source,
        "is_random": bool(model.is_random),
        "note": "RANDOM WEIGHTS - actions and attention are not Octo's" if model.is_random else "",
        "text_tokenizer": _tokenizer_label(getattr(model, "text_tokenizer", None)),
        "tokenizer": fingerprint.get("tokenizer"),  # kind, name, vocab_size, max_length, sha256, path
        "dataset_key": policy_dataset_key,
        "layers": model.attention_shape.layers if model.attention_shape is not None else None,
        "action_horizon": int(model.action_horizon),
        "window": int(model.window_size),
        "image_sizes": {k: list(v) for k, v in model.image_sizes.items()},
        "goal_image_sizes": {k: list(v) for k, v in model.goal_image_sizes.items()},
        "fingerprint": fingerprint,
        **model.describe(),  # what the policy adds of itself (a server's metadata)
    }


def execute(
    protocol: Protocol,
    out: str | Path,
    run_name: str | None = None,
    *,
    overwrite: bool = False,
    retry_failed: bool = False,
    model=None,
    executor: ExecutorFactory | None = None,
    on_step: StepCallback | None = None,
    progress: bool = True,
    ci_method: str | None = None,
    viewer: str | None = None,
    retries: int | None = None,
    preflight: str = "warn",
    space_check: bool = True,
) -> RunSummary:
    """Run (or resume) the protocol's episodes into `<out>/<run_name>` and return the summary.

    model: an already loaded policy of `protocol.model` (a harness.policies.Policy, or an Octo model: it is wrapped;
    else it is loaded by the factory after the cheap checks).
    executor: factory(context, model) -> Executor (default SequentialExecutor).
    viewer: gRPC url of a live Rerun viewer every episode streams to (harness.outputs.rerun_viewer.start_viewer).
    ci_method: the success intervals of the derived files (wilson, clopper-pearson); recorded in the manifest
    ("statistics", outside the protocol and its hash), so a resume writes them as the run began; None: the recorded
    one, else wilson. A different one for a run that records its own is refused (one line).
    retries: times a lost job runs again (executor.Retrying); None: the run's recorded number, else Recovery's default.
    preflight: warn | strict | off, the checks of frames and action space before the first episode (run/preflight.py).
    space_check: refuse to start when the files of the jobs left would not fit where the run writes (run/space.py).
    """
    model = as_policy(model) if model is not None else None
    protocol, out, name, goal_images, fingerprint_details = _checked_inputs(protocol, out, run_name, ci_method, viewer,
                                                                            model)
    store = RunStore(out / name)
    jobs = protocol.jobs()
    created = not store.dir.exists()
    with store:
        try:
            opened = _open_run(store, protocol, jobs, name, goal_images, fingerprint_details, overwrite=overwrite,
                               retry_failed=retry_failed, model=model, ci_method=ci_method, preflight=preflight,
                               space_check=space_check)
        except BaseException:
            if created and not (store.dir / MANIFEST).exists():  # a check failed: leave no empty run folder behind
                shutil.rmtree(store.dir, ignore_errors=True)
            raise
        protocol = _with_presentation(protocol, opened.manifest)  # a resume draws as the run began
        try:
            if len(opened.pending) < len(jobs):
                log.info("resuming run %s: %d of %d episodes already finished", name, len(jobs) - len(opened.pending),
                         len(jobs))
            context = EpisodeContext(protocol=protocol, run_dir=str(store.dir.resolve()), run=name,
                                     model=opened.manifest["model"], goals=opened.goals, viewer=viewer)
            retries = (opened.manifest.get("recovery") or {}).get("retries", Recovery.retries) if retries is None else retries
            status = _run_pending(store, protocol, jobs, opened, context, executor, on_step, progress, retries)
        finally:
            if opened.checked is not None:
                opened.checked.close()  # unless an executor took it
        rows = opened.rows
        ordered = tuple(rows[j.key] for j in jobs if j.key in rows)
        return RunSummary(run_dir=store.dir, rows=ordered, manifest=opened.manifest, status=status,
                          statistics=statistics(ordered, protocol.tasks, method=opened.ci_method),
                          skipped=len(jobs) - len(opened.pending))


def _checked_inputs(protocol: Protocol, out: str | Path, run_name: str | None, ci_method: str | None,
                    viewer: str | None, model=None) -> tuple[Protocol, Path, str, dict | None, dict]:
    """The checks that need no run folder and no model, in order, then the fingerprints; returns (protocol with its
    model and goal fingerprints, destination, run name, decoded goal images, the model fingerprint's details)."""
    if ci_method not in (None, *CI_METHODS):
        raise ValueError(f"ci_method must be one of {', '.join(CI_METHODS)}, got {ci_method!r}")
    checks.check_environment()
    checks.check_suites(protocol)
    if protocol.outputs.rerun or viewer is not None:
        from harness.outputs.rerun_sink import import_rerun

        import_rerun()  # the optional viewer extra: one line naming the install command, before anything heavy
    checks.check_perturbations(protocol)
    out = checks.check_destination(Path(out))
    if run_name is not None:
        checks.check_run_name(run_name)  # before hashing the checkpoint
    identity = model.identity() if model is not None else None  # a policy object of the caller's says who it is
    fingerprint, fingerprint_details = identity or model_fingerprint(protocol.model, protocol.text_tokenizer,
                                                                     protocol.served_conventions)
    goals_fp = goal_fingerprint(protocol.goal_images) if protocol.goal_images else None
    protocol = protocol.replace(model_fingerprint=fingerprint, goal_fingerprint=goals_fp)
    goal_images = checks.decode_goal_images(protocol.goal_images) if protocol.goal_images else None
    name = checks.check_run_name(run_name) if run_name is not None else default_run_name(protocol)
    return protocol, out, name, goal_images, fingerprint_details


@dataclass
class _OpenedRun:
    """A run folder past its checks: its manifest (recorded or just written), its rows (by job key), the jobs that
    stand, the jobs left to run, the model and goal images they need, the success interval method and the platform."""
    manifest: dict
    rows: dict
    done: set
    pending: list
    model: object
    goals: dict | None
    ci_method: str
    platform_fp: str
    checked: CheckedEnv | None = None  # the first task's env, checked against the model; closed unless adopted


def _open_run(store: RunStore, protocol: Protocol, jobs: list[EpisodeJob], name: str, goal_images: dict | None,
              fingerprint_details: dict, *, overwrite: bool, retry_failed: bool, model, ci_method: str | None,
              preflight: str = "warn", space_check: bool = True) -> _OpenedRun:
    """Inside the store's lock: compare with what the folder holds, load the model if any job is left (or the run is
    new), check it against the protocol and the first env, write a new run's manifest and clear leftovers."""
    protocol_dict = protocol.to_dict()
    manifest = _recorded_manifest(store, protocol, protocol_dict, overwrite)
    ci_method = _recorded_ci_method(store, manifest, ci_method)
    platform_now = platform_info(sides=suite_platforms(protocol.tasks))
    platform_fp = platform_fingerprint(platform_now)
    if manifest is not None and manifest.get("platform_fingerprint") not in (None, platform_fp):
        log.warning("resuming run %s on another platform (differs: %s); its episodes record where they ran",
                    name, ", ".join(platform_differences(manifest.get("platform"), platform_now)) or "unknown")
    rows = store.load_rows({j.key: j.seed for j in jobs}) if manifest is not None else {}
    if manifest is not None and manifest.get("run") != name:  # a copied or renamed run folder
        rows = _rename_run(store, manifest, rows, name)
        manifest = store.read_manifest()
    done = store.standing_jobs(rows, retry_failed, manifest)
    pending = [j for j in jobs if j.key not in done]
    goals = None
    if model is None and (pending or manifest is None):  # a finished run needs no model
        log.info("loading %s", protocol.model)
        model = load_protocol_policy(protocol)
        interrupts.check()  # Ctrl-C while loading, its KeyboardInterrupt swallowed by a finaliser
    if model is not None:
        task_inputs, goals, dataset_key = _check_model(protocol, model, goal_images)
        if space_check:  # before any env is made: what the jobs left write against the free space
            space.check_space(protocol, model, pending, store.dir)
    checked = CheckedEnv(protocol, model, pending[0].task) if model is not None and pending else None
    try:
        found = check_run(preflight, protocol, model, checked.env, pending[0].seed, dataset_key) if checked else None
        if overwrite:
            store.clear()  # only now: every check has passed
        if manifest is None:
            manifest = _new_manifest(protocol, protocol_dict, jobs, name,
                                     _model_info(model, dataset_key, fingerprint_details), task_inputs, platform_now,
                                     platform_fp, ci_method) | ({"preflight": found} if found else {})
            store.write_manifest(manifest)
        for line in _default_lines(protocol):
            log.info("%s", line)
        store.remove_temporaries()
        store.remove_incomplete(protocol.tasks, keep=done)
    except BaseException:
        if checked is not None:
            checked.close()
        raise
    return _OpenedRun(manifest, rows, done, pending, model, goals, ci_method, platform_fp, checked)


def _recorded_manifest(store: RunStore, protocol: Protocol, protocol_dict: dict, overwrite: bool) -> dict | None:
    """The manifest the run folder holds (None for a new run, or with `overwrite`); refuses a folder that is not a
    run, and a run of another protocol (ProtocolMismatchError naming the differing fields)."""
    foreign = store.foreign_content(protocol.tasks)
    if foreign:
        raise ValueError(f"{store.dir} exists and is not an octo-harness run (holds {', '.join(foreign[:3])}); "
                         "choose another --run-name")
    manifest = None if overwrite else store.read_manifest()
    if manifest is not None:
        # through Protocol, so a field added since the run started compares at its default
        recorded = protocol_from_manifest(manifest, store.dir / MANIFEST).to_dict()
        differs = diff(recorded, protocol_dict)
        if differs:
            raise ProtocolMismatchError(
                f"run {store.dir} was started with a different protocol (differs: {', '.join(differs)}); "
                "run the same command to resume it, --overwrite to start it afresh, or choose another --run-name")
    return manifest


def _recorded_ci_method(store: RunStore, manifest: dict | None, ci_method: str | None) -> str:
    """The success interval method: the one asked for, else the run's recorded one, else wilson; a different one than
    the run records is refused."""
    recorded_method = ((manifest or {}).get("statistics") or {}).get("ci_method")
    if ci_method is not None and recorded_method is not None and ci_method != recorded_method:
        raise ProtocolMismatchError(
            f"run {store.dir} writes its success intervals with {recorded_method} (manifest.json statistics."
            f"ci_method); drop --ci-method or pass --ci-method {recorded_method} to resume it, --overwrite to "
            "start it afresh")
    return ci_method or recorded_method or "wilson"


def _new_manifest(protocol: Protocol, protocol_dict: dict, jobs: list[EpisodeJob], name: str, model_info: dict,
                  task_inputs: list[str], platform_now: dict, platform_fp: str, ci_method: str) -> dict:
    """manifest.json of a new run: its protocol and jobs, the model, where and with what it runs."""
    return {
        "format": FORMAT, "run": name, "created": now_utc(), "protocol": protocol_dict,
        "protocol_hash": protocol.hash(), "jobs": [[j.task, j.episode, j.seed] for j in jobs],
        "model": model_info, "task_inputs": task_inputs,
        "goal_images": protocol.goal_images, "git_commit": git_commit(),
        "versions": {"jax": platform_now["jax"]["version"], **platform_now["versions"]},
        "platform": platform_now, "platform_fingerprint": platform_fp,
        "measures_version": MEASURES_VERSION,
        # where each env convention came from, per task family (flag, checkpoint, default:<family>)
        **({"conventions": protocol.convention_sources} if protocol.convention_sources else {}),
        # what the derived files' statistics use: not part of the protocol (the episodes are the same)
        "statistics": {"ci_method": ci_method, "confidence": 0.95},
        # how the overlays are drawn (the colour map): outside the protocol and its hash (the episodes are the same)
        "presentation": protocol.outputs.presentation(),
    }


def _with_presentation(protocol: Protocol, manifest: dict) -> Protocol:
    """The protocol drawing with the run's recorded presentation (a run made with jet keeps drawing with jet)."""
    known = protocol.outputs.presentation()
    recorded = {k: v for k, v in recorded_presentation(manifest).items() if k in known}
    if not recorded or all(getattr(protocol.outputs, k, None) == v for k, v in recorded.items()):
        return protocol
    return protocol.replace(outputs=dataclasses.replace(protocol.outputs, **recorded))


def _run_pending(store: RunStore, protocol: Protocol, jobs: list[EpisodeJob], opened: _OpenedRun,
                 context: EpisodeContext, executor: ExecutorFactory | None, on_step: StepCallback | None,
                 progress: bool, retries: int = Recovery.retries) -> str:
    """The executor loop: each finished row is appended and the derived files rewritten, inside the signal guard's
    critical sections; returns "complete" or "interrupted" (then leftovers are removed). `opened.rows` and
    `opened.done` grow with the rows."""
    manifest, rows, done, method = opened.manifest, opened.rows, opened.done, opened.ci_method
    status = "interrupted"
    bar = Progress(len(jobs), done=len(done), successes=sum(rows[k].status == "ok" and bool(rows[k].success)
                                                            for k in done)) if progress else None

    def step(job, t, record):
        if bar is not None:
            bar.step(job, t, record)
        if on_step is not None:
            on_step(job, t, record)

    guard = _SignalGuard()
    with guard.installed():
        runner = None
        try:
            with guard.critical():
                _derive(store, manifest, jobs, rows, "running", method)
                runner = (executor or SequentialExecutor)(context, opened.model) if opened.pending else None
                if opened.checked is not None and hasattr(runner, "adopt"):
                    runner.adopt(opened.checked)
                if runner is not None:
                    runner = Retrying(runner, retries, context.run_dir)
                store.record_recovery(manifest, rows, retries, Recovery.retries)
            for row in (runner.run(opened.pending, on_step=step) if runner is not None else ()):
                row = dataclasses.replace(row, platform=opened.platform_fp)  # where this episode's numbers came from
                with guard.critical(), space.stops_when_full(store.dir, protocol, opened.model, jobs, done, row):
                    store.append(row)
                    rows[row.key] = row
                    if not row.lost_infrastructure:  # a job lost after its retries stays to do (resume)
                        done.add(row.key)
                    store.record_recovery(manifest, rows, retries, Recovery.retries)
                    _derive(store, manifest, jobs, rows, "running", method)
                if bar is not None:
                    bar.episode(row)
                interrupts.check()
            status = "complete" if all(j.key in rows for j in jobs) else "interrupted"
        finally:
            if bar is not None:
                bar.close()
            try:
                if runner is not None:
                    runner.close()
            finally:
                if status != "complete":  # nothing half-written stays behind
                    store.remove_temporaries()
                    store.remove_incomplete(protocol.tasks, keep=done)
                _derive(store, manifest, jobs, rows, status, method)
    return status


def _rename_run(store: RunStore, manifest: dict, rows: dict, name: str) -> dict:
    """A run folder copied or moved to `name`: the manifest and every results.jsonl row take the folder's name (atomic
    rewrites; the old name is kept as manifest["renamed_from"]), so the records never mix two names."""
    old = manifest.get("run")
    log.info("run folder %s was made as run %r; its records now name it %r", store.dir, old, name)
    rows = {key: dataclasses.replace(row, run=name) for key, row in rows.items()}
    store.rewrite_rows(rows.values())
    store.write_manifest({**manifest, "run": name, "renamed_from": old})
    return rows


def _check_model(protocol: Protocol, model, goal_images) -> tuple[list[str], dict | None, str | None]:
    """Model-dependent checks; returns (task inputs, goal images at the model's sizes, dataset key)."""
    if model.is_random:
        log.warning("model %s has RANDOM weights: actions and attention are not Octo's", model.source)
    task_inputs = checks.check_model(protocol, model, goal_images)
    goals = None
    if goal_images is not None:
        from harness.policy import resize_frame

        goals = {k: resize_frame(v, model.goal_image_sizes[k]) for k, v in goal_images.items() if k in model.goal_image_sizes}
    dataset_key = model.inference(protocol.policy).dataset_key  # an unknown key fails here, before any episode
    return task_inputs, goals, dataset_key


def _default_lines(protocol: Protocol) -> list[str]:
    """The console lines naming each family's default conventions where a run uses them (harness.conventions)."""
    if not protocol.convention_sources:
        return []
    from harness.conventions import CONVENTIONS_FILE, default_lines, task_family
    from harness.run.settings import _model_folder

    folder = _model_folder(protocol.model)
    has_file = folder is not None and (folder / CONVENTIONS_FILE).is_file()
    options = {task_family(t): protocol.env_for(t) for t in protocol.tasks}
    label = Path(protocol.model).name if not protocol.model.startswith(("hf://", "random:")) else protocol.model
    return default_lines(protocol.convention_sources, options, protocol.tasks, label, has_file)


def _derive(store: RunStore, manifest, jobs, rows, status, method) -> None:
    """Rewrite the derived files; a failure there (disk full) is logged, results.jsonl stays the record."""
    try:
        store.write_derived(manifest, jobs, rows, status, method)
    except OSError as e:
        log.error("could not rewrite results.json/summary.csv in %s: %s (results.jsonl is intact)", store.dir, e)
