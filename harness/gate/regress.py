"""Sequential regression runs: the candidate model on a baseline run's protocol and seeds, stopped as soon as an
anytime-valid test decides (harness.analysis.sequential).

`regress(baseline_dir, model, ...)` builds the candidate's protocol from the baseline's manifest with only the
model replaced (and, with `max_episodes`, fewer episodes per task), and runs it through the run store
(`harness.run.execute`), so an interrupted regression resumes where it stopped. Jobs run round by round
(episode k of every task, then k + 1); each task's pairs feed that task's own sequential test at alpha / T
(harness.analysis.sequential.TaskwiseTest), so a task that breaks cannot hide behind one that improves. The
executor stops as soon as a task is REGRESSED, every task has decided, or the candidate errored on more than half
of a task's pairs (ERRORED whatever follows); a pair with an errored arm is counted, never tested. Episodes
already in the candidate run are counted first, so re-running the same command reproduces the decision without
new episodes. A baseline that errored on more than half of a task's episodes is refused before anything runs.

Afterwards the pairs run are compared with the fixed-size statistics (harness.analysis.compare), and the verdict
is the worse of the sequential verdict and that comparison's (`gate_verdict`): regress never exits 0 where
`compare` on the same pairs exits non-zero. A test that ends undecided while the candidate lacks baseline pairs of
its jobs is INCOMPLETE (exit 4), as in compare. `gate_on_outcomes` is the same decision on outcome dicts. The
results are typed (harness.gate.results: `RegressResult`, `RegressGridResult`; `to_json()` writes regress.json).
"""
from __future__ import annotations

import dataclasses

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator, Sequence

from harness.analysis.compare import CompareConfig, compare_runs
from harness.analysis.compare_result import Outcomes
from harness.gate.config import GateConfig
from harness.analysis.outcomes import incompleteness, outcome_tables, outcome_verdicts, overall_verdict
from harness.analysis.paired import PairedCounts, errored_most, mcnemar_exact_sample_size
from harness.analysis.provenance import summary_points
from harness.gate.results import (
    GRID_FORMAT,
    REGRESS_FORMAT,
    ConditionRegress,
    RegressGridResult,
    RegressResult,
    ReplayResult,
    SequentialSummary,
)
from harness.results import ABSENT
from harness.analysis.runs import load_run
from harness.analysis.sequential import SequentialConfig, TaskwiseTest
from harness.run.executor import EpisodeContext, SequentialExecutor
from harness.run.protocol import EpisodeJob, Protocol
from harness.run.store import EpisodeRow, RunStore
from harness.verdicts import DEFAULT_FAIL_ON, EXIT_FAIL, GateVerdict, ReplayVerdict, gate_exit_code

log = logging.getLogger(__name__)


def candidate_protocol(baseline_manifest: dict, model: str, max_episodes: int | None = None,
                       where: str = "the baseline's manifest.json", text_tokenizer: str | None = None,
                       drop_probes: bool = False) -> Protocol:
    """The baseline's protocol with the model (and the text tokenizer, when given: auto|fallback|PATH) replaced
    (fingerprints recomputed by the run); its probes inherited, or turned off with `drop_probes`."""
    from harness.run.protocol import protocol_from_manifest
    from harness.runfolder.schema import check_protocol

    data = baseline_manifest.get("protocol")
    if not data:
        raise ValueError("the baseline run has no protocol in manifest.json (made before the run store); "
                         "re-run the baseline with this octo-harness, then regress against it")
    episodes = check_protocol(data, where)["episodes"]
    if max_episodes is not None:
        if max_episodes < 1:
            raise ValueError(f"--max-episodes must be at least 1, got {max_episodes}")
        episodes = min(episodes, max_episodes)
    tokenizer = {}
    if text_tokenizer is not None:
        from harness.run.settings import text_tokenizer_choice

        tokenizer = {"text_tokenizer": text_tokenizer_choice(text_tokenizer)}
    protocol = protocol_from_manifest(baseline_manifest, where, model=model, model_fingerprint=None,
                                      goal_fingerprint=None, episodes=episodes, **tokenizer)
    if drop_probes:
        from harness.policy_config import without_probes

        protocol = dataclasses.replace(protocol, policy=without_probes(protocol.policy))
    return protocol


def round_order(jobs: Sequence[EpisodeJob], tasks: Sequence[str]) -> list[EpisodeJob]:
    """Jobs round by round: episode 0 of every task (in protocol order), then episode 1, ..."""
    rank = {t: i for i, t in enumerate(tasks)}
    return sorted(jobs, key=lambda j: (j.episode, rank.get(j.task, len(rank))))


def sequential_state(baseline: dict[tuple[str, int], bool | None], candidate: dict[tuple[str, int], bool | None],
                     jobs: Sequence[EpisodeJob], tasks: Sequence[str], config: SequentialConfig) -> TaskwiseTest:
    """Feed complete rounds in order into a fresh per-task test (stops at the family's first decision).

    baseline / candidate: {(task, seed): success, None if the episode errored}. A round is complete when every
    task that has a baseline episode for that round's seed has a candidate episode too; rounds without any
    pair are skipped. Each task's pair goes to that task's own test; a pair with an errored arm is counted,
    not tested.
    """
    test = TaskwiseTest(tuple(tasks), config)
    for paired in _rounds(baseline, jobs, tasks):
        if any((j.task, j.seed) not in candidate for j in paired):
            break  # the next round is not finished yet
        if test.add_round({j.task: (baseline[(j.task, j.seed)], candidate[(j.task, j.seed)]) for j in paired}):
            break
    return test


def _rounds(baseline: dict, jobs: Sequence[EpisodeJob], tasks: Sequence[str]) -> list[list[EpisodeJob]]:
    """Jobs with a baseline episode, grouped round by round (empty rounds dropped)."""
    rounds: dict[int, list[EpisodeJob]] = {}
    for job in round_order(jobs, tasks):
        rounds.setdefault(job.episode, []).append(job)
    paired = ([j for j in rounds[episode] if (j.task, j.seed) in baseline] for episode in sorted(rounds))
    return [group for group in paired if group]


def errored_tasks(baseline: dict, candidate: dict, jobs: Sequence[EpisodeJob]) -> list[str]:
    """Tasks whose candidate errored on more than half of the task's baseline pairs: ERRORED whatever follows."""
    planned: dict[str, int] = {}
    errored: dict[str, int] = {}
    for j in jobs:
        if (j.task, j.seed) in baseline:
            planned[j.task] = planned.get(j.task, 0) + 1
            failed = (j.task, j.seed) in candidate and candidate[(j.task, j.seed)] is None
            errored[j.task] = errored.get(j.task, 0) + failed
    return [t for t in planned if errored_most(errored[t], planned[t])]


def gate_verdict(sequential: GateVerdict, compared: GateVerdict) -> GateVerdict:
    """regress's verdict: the worse of the sequential verdict and compare's verdict on the pairs run, so regress
    never passes what `compare` on the same pairs fails (IDENTICAL pairs: IDENTICAL, nothing changed)."""
    return GateVerdict.IDENTICAL if compared == GateVerdict.IDENTICAL else GateVerdict.worst([sequential, compared])


@dataclass(frozen=True)
class GateDecision:
    """regress's decision on outcome dicts (`gate_on_outcomes`): no files, the test itself kept."""

    verdict: GateVerdict
    sequential_verdict: GateVerdict
    compare_verdict: GateVerdict
    rounds: int
    pairs: int
    test: TaskwiseTest
    outcomes: Outcomes


def gate_on_outcomes(baseline: dict, candidate: dict, jobs: Sequence[EpisodeJob], tasks: Sequence[str],
                     alpha: float = 0.05, max_drop: float = 0.1) -> GateDecision:
    """The whole decision of `regress` on outcome dicts (no episodes run, no files): the per-task sequential
    test over the complete rounds, compare's outcome verdict on the same pairs, and the gate verdict.

    baseline / candidate: {(task, seed): success, None if errored}. Pairs are those of the rounds the
    sequential test consumed (all complete rounds when it stops on errors or runs out).
    """
    test = sequential_state(baseline, candidate, jobs, tasks, SequentialConfig(alpha=alpha, max_drop=max_drop))
    rounds = _rounds(baseline, jobs, tasks)[: test.rounds]
    details = [{"task": j.task, "baseline_success": baseline[(j.task, j.seed)],
                "candidate_success": candidate[(j.task, j.seed)],
                "baseline_status": "failed" if baseline[(j.task, j.seed)] is None else "ok",
                "candidate_status": "failed" if candidate[(j.task, j.seed)] is None else "ok"}
               for paired in rounds for j in paired]
    tables, errored = outcome_tables(details)
    outcomes = outcome_verdicts(tables, CompareConfig(max_drop=max_drop, alpha=alpha), errored, project=False)
    compared = overall_verdict(outcomes)
    sequential = GateVerdict(test.verdict or GateVerdict.UNDERPOWERED)
    return GateDecision(verdict=gate_verdict(sequential, compared), sequential_verdict=sequential,
                        compare_verdict=compared, rounds=test.rounds, pairs=len(details), test=test, outcomes=outcomes)


class _StoppingExecutor:
    """Runs jobs round by round with an inner executor and stops once the sequential test has decided."""

    def __init__(self, inner, baseline: dict, done: dict, jobs: Sequence[EpisodeJob], tasks: Sequence[str],
                 config: SequentialConfig):
        self.inner, self.baseline, self.done = inner, baseline, dict(done)
        self.jobs, self.tasks, self.config = list(jobs), list(tasks), config

    def decided(self) -> bool:
        return (sequential_state(self.baseline, self.done, self.jobs, self.tasks, self.config).verdict is not None
                or bool(errored_tasks(self.baseline, self.done, self.jobs)))

    def run(self, jobs: Sequence[EpisodeJob], on_step=None) -> Iterator[EpisodeRow]:
        if self.decided():
            return
        for row in self.inner.run(round_order(jobs, self.tasks), on_step=on_step):
            self.done[(row.task, row.seed)] = bool(row.success) if row.status == "ok" else None
            yield row
            if self.decided():
                log.info("sequential test decided after %d candidate episodes; stopping", len(self.done))
                return

    def adopt(self, checked) -> None:
        """The driver's pre-flight env (harness.run.executor.CheckedEnv), to the inner executor where it takes one
        (else the driver closes it)."""
        adopt = getattr(self.inner, "adopt", None)
        if adopt is not None:
            adopt(checked)

    def close(self) -> None:
        self.inner.close()


def _outcomes(run) -> dict[tuple[str, int], bool | None]:
    """{(task, seed): success, None for an episode that errored}."""
    return {(e.task, e.seed): bool(e.success) if e.ok else None for e in run.episodes if e.seed is not None}


def _check_baseline(baseline: dict, jobs: Sequence[EpisodeJob], path) -> None:
    """A baseline that errored on more than half of a task's episodes cannot be the reference (one line)."""
    for task in dict.fromkeys(j.task for j in jobs):
        outcomes = [baseline[(j.task, j.seed)] for j in jobs if j.task == task and (j.task, j.seed) in baseline]
        errored = sum(o is None for o in outcomes)
        if errored_most(errored, len(outcomes)):
            raise ValueError(f"the baseline {path} errored on {errored} of {len(outcomes)} episodes of {task} (more "
                             "than half): it cannot serve as the reference; re-run it "
                             "(octo-harness run --retry-failed)")


def _run_candidate(protocol, out, run_name, loaded_model, executor, progress, base_outcomes, config):
    """The candidate's episodes, stopped once the sequential test decides -> (the run's summary, the policy to
    replay the baseline with: the one the run loaded, so it is not loaded and compiled a second time)."""
    from harness.run import execute

    jobs = protocol.jobs()
    run_model = loaded_model  # the candidate policy the run used (the driver loads it and gives it to the factory)

    def factory(context: EpisodeContext, model_):
        nonlocal run_model
        run_model = model_
        existing = {(r.task, r.seed): bool(r.success) if r.status == "ok" else None
                    for r in RunStore(context.run_dir).load_rows().values()}
        inner = (executor or SequentialExecutor)(context, model_)
        return _StoppingExecutor(inner, base_outcomes, existing, jobs, protocol.tasks, config)

    summary = execute(protocol, out, run_name, model=loaded_model, executor=factory, progress=progress)
    return summary, run_model


def regress(baseline_dir: str | Path, model: str, gate: GateConfig | None = None, *, out: str | Path = "results/runs",
            run_name: str | None = None, loaded_model=None, executor=None, progress: bool = True) -> RegressResult:
    """Run the sequential regression (see the module docstring); returns regress.json's content (and the comparison).

    gate: alpha, max_drop, max_episodes, the candidate's text_tokenizer and the replay tolerances (default GateConfig()).
    executor: factory(context, model) -> Executor for the candidate's episodes (default SequentialExecutor).
    """
    gate = gate if gate is not None else GateConfig()
    alpha = gate.alpha
    baseline = load_run(baseline_dir, legacy=False)
    protocol = candidate_protocol(baseline.manifest, model, gate.max_episodes, str(baseline.path / "manifest.json"),
                                  gate.text_tokenizer, gate.drop_probes)
    config = gate.sequential()
    compare_config = gate.compare()
    base_outcomes = _outcomes(baseline)
    jobs = protocol.jobs()
    if not any((j.task, j.seed) in base_outcomes for j in jobs):
        raise ValueError(f"the baseline {baseline.path} has no finished episode to pair with; finish the baseline first")
    _check_baseline(base_outcomes, jobs, baseline.path)

    summary, replay_model = _run_candidate(protocol, out, run_name, loaded_model, executor, progress, base_outcomes,
                                           config)
    candidate = load_run(summary.run_dir)
    cand = _outcomes(candidate)
    decision = gate_on_outcomes(base_outcomes, cand, jobs, protocol.tasks, alpha, gate.max_drop)
    test = decision.test
    used = [(j.task, j.seed) for paired in _rounds(base_outcomes, jobs, protocol.tasks)[: test.rounds] for j in paired]
    outcome_pairs = [k for k in used if base_outcomes[k] is not None and cand[k] is not None]
    counts = PairedCounts.from_outcomes([base_outcomes[k] for k in outcome_pairs], [cand[k] for k in outcome_pairs])
    comparison = compare_runs(baseline.path, candidate.path, compare_config, require_complete=False)
    replay = replay_baseline(baseline, model, replace(gate, text_tokenizer=protocol.text_tokenizer), replay_model)
    tested = test.summary()
    stopped_errored = errored_tasks(base_outcomes, cand, jobs)
    if stopped_errored:
        tested["errored_tasks"] = stopped_errored
    sequential = SequentialSummary.from_json(tested)
    verdict = gate_verdict(sequential.verdict, comparison.verdict)
    # the test stopped undecided although the candidate lacks baseline pairs of its jobs: it did not run them all
    lacking = [[j.task, j.seed] for j in jobs if (j.task, j.seed) in base_outcomes and (j.task, j.seed) not in cand]
    incomplete = incompleteness(lacking, baseline.path, candidate.path) if not sequential.decided else None
    if incomplete is not None:
        notes = (incomplete.note, *comparison.outcomes.notes)
        comparison = replace(comparison, outcomes=replace(comparison.outcomes, notes=notes))
        verdict = GateVerdict.worst([verdict, GateVerdict.INCOMPLETE])  # ERRORED and REGRESSED stand
    return RegressResult(
        format=REGRESS_FORMAT,
        verdict=verdict,
        incomplete=incomplete,
        sequential_verdict=sequential.verdict,
        compare_verdict=comparison.verdict,
        sequential=sequential,
        pairs_used=counts.n,
        errored_pairs=len(used) - len(outcome_pairs),
        rounds_used=test.rounds,
        baseline_pairs=sum((j.task, j.seed) in base_outcomes for j in jobs),
        fixed_size_pairs_80_power=_fixed_size(counts, alpha),
        fixed_size_pairs_80_power_tasks={
            task: _fixed_size(PairedCounts.from_outcomes([base_outcomes[k] for k in outcome_pairs if k[0] == task],
                                                         [cand[k] for k in outcome_pairs if k[0] == task]), alpha)
            for task in protocol.tasks},
        fixed_size_note="pairs a fixed-size exact two-sided McNemar test at the same alpha needs for 80% power at "
                        "the observed discordance rates (exact unconditional power); null when no difference was "
                        "observed",
        table=counts,
        baseline_run=str(baseline.path),
        candidate_run=str(candidate.path),
        candidate_status=candidate.status,
        replay=replay,
        compare=comparison,
    )


def replay_baseline(baseline, model: str, gate: GateConfig, loaded_model=None) -> ReplayResult | None:
    """The candidate on the baseline's recorded inputs (harness/gate/replay.py): its model numerics, isolated from
    the simulator and the platform, within the gate's tolerances; None when the baseline recorded no inputs."""
    from harness.gate.replay import INPUTS, replay_run

    if not all((e.directory / INPUTS).is_file() for e in baseline.episodes if e.ok):
        return None
    result = replay_run(baseline.path, model, gate, loaded_model=loaded_model)
    return replace(result, episode_details=ABSENT)


def _fixed_size(counts: PairedCounts, alpha: float) -> int | None:
    if not counts.n:
        return None
    return mcnemar_exact_sample_size(counts.baseline_only / counts.n, counts.candidate_only / counts.n, alpha, 0.8)


def exit_code(result: RegressResult | RegressGridResult, fail_on: str = DEFAULT_FAIL_ON) -> int:
    """The gate verdict's exit code, as for compare: 0 pass, 1 REGRESSED/SUSPECT (or what --fail-on adds),
    3 ERRORED, 4 INCOMPLETE. fail_on="changed" (the model must not change) also fails unless the outcomes are IDENTICAL or the
    candidate's numbers on the baseline's recorded inputs are EQUIVALENT (replay): on another platform an unchanged
    model passes, a changed one fails whatever its outcomes."""
    if fail_on != "changed":
        return gate_exit_code(result.verdict, fail_on)
    code = gate_exit_code(result.verdict, "suspect")
    if code or result.verdict == GateVerdict.IDENTICAL:
        return code
    replay = getattr(result, "replay", None)  # a grid's result has none
    return ReplayVerdict(replay.verdict).exit_code if replay is not None else EXIT_FAIL


def summary_text(result: RegressResult, code: int) -> str:
    """A few lines for the terminal / CI log."""
    seq = result.sequential
    lines = [
        f"regress: {result.verdict} after {result.pairs_used} pairs ({result.rounds_used} rounds"
        + (f", {result.errored_pairs} errored pairs left out" if result.errored_pairs else "")
        + f") of {result.baseline_pairs} in the baseline",
        f"  sequential test per task (alpha {seq.alpha:g} / {len(seq.tasks)} task(s) = "
        f"{seq.task_alpha:.3g} each, "
        f"max drop {seq.max_drop:g}, reject at e-value {seq.threshold:g}): {result.sequential_verdict}",
    ]
    for task, t in seq.tasks.items():
        e = t.e_values
        lines.append(f"    {task}: {t.verdict} after {t.units} pairs ({t.errored_pairs} errored); e-values "
                     f"regression {e.regression:.3g}, improvement {e.improvement:.3g}, held {e.held:.3g}")
    for task in seq.errored_tasks or ():
        lines.append(f"    {task}: the candidate errored on more than half of its pairs: {GateVerdict.ERRORED}")
    lines += [
        f"  fixed-size comparison of the pairs run: {result.compare_verdict}"
        + "".join(f"\n    {note}" for note in result.compare.outcomes.notes),
        "  an exact fixed-size McNemar test would need " + (
            f"{result.fixed_size_pairs_80_power} pairs for 80% power at the observed discordance"
            if result.fixed_size_pairs_80_power else "n/a pairs (no difference observed, or more than 20000)"),
        f"  verdict = worse of sequential and fixed-size: {result.verdict}",
        "  " + _numerics_line(result.replay),
        "  provenance of the outcomes:",
        *(f"    - {point}" for point in summary_points(result.compare.provenance.summary)),
        f"exit code {code}",
    ]
    return "\n".join(lines)


def _numerics_line(replay: ReplayResult | None) -> str:
    if replay is None:
        return "model numerics: not replayed (the baseline recorded no inputs; make it with --record-inputs)"
    from harness.gate.replay import summary_text as replay_summary

    lines = replay_summary(replay).splitlines()
    return "model numerics: " + lines[0].removeprefix("replay: ") + "".join(f"\n  {line}" for line in lines[1:])


def write_regress(result: RegressResult | RegressGridResult, code: int, write_comparison) -> dict:
    """regress.json and the comparison outputs into <candidate run>/regress/ (a grid's: <candidate grid>/regress/),
    all or none; returns paths and the summary text (a `regress` or a `regress_grid` result)."""
    from harness.files import all_or_none, atomic_write_json

    out = Path(result.candidate_run) / "regress"
    with all_or_none(out / "regress.json", out / "compare.json", out / "compare.md", out / "compare.html"):
        paths = write_comparison(result.compare, out, None, None)
        written = replace(result, compare=ABSENT, exit_code=code, compare_json=str(paths["json"]))
        atomic_write_json(out / "regress.json", written.to_json())
    summary = grid_summary_text if isinstance(result, RegressGridResult) else summary_text
    return {"json": out / "regress.json", "html": paths["html"], "summary": summary(result, code)}


# a grid's conditions are not replayed on recorded inputs, so "changed" (which passes an EQUIVALENT replay) is gated as
# "suspect" there, and the command says so in one line
GRID_FAIL_ON_CHANGED = ("regress: --fail-on changed gates a grid baseline as --fail-on suspect: a grid's conditions are "
                        "not replayed on recorded inputs, so no model-numerics verdict is made")


def grid_fail_on(fail_on: str) -> tuple[str, str | None]:
    """The --fail-on a grid baseline is gated with, and the line that says so where it is not the one given."""
    return ("suspect", GRID_FAIL_ON_CHANGED) if fail_on == "changed" else (fail_on, None)


def regress_grid(baseline_grid: str | Path, model: str, gate: GateConfig | None = None, *,
                 out: str | Path = "results/runs", run_name: str | None = None, executor=None,
                 progress: bool = True) -> RegressGridResult:
    """`regress` condition by condition over a robustness grid (octo-harness robustness): each condition's
    sequential test runs at alpha / conditions (and, inside it, alpha / conditions / tasks per task), so the family
    of every (task, condition) cell holds alpha; then the pairs run are compared as a grid (compare_grids: Holm over
    every cell). The candidate grid goes to <out>/<run_name> (default <model>_<baseline grid name>)."""
    from harness.analysis.compare import GRID_FILE, compare_grids, read_grid
    from harness.files import atomic_write_json
    from harness.run.protocol import load_protocol_policy

    gate = gate if gate is not None else GateConfig()
    alpha = gate.alpha
    baseline_grid = Path(baseline_grid)
    grid = read_grid(baseline_grid)
    names = list(grid.runs)
    first = load_run(baseline_grid / names[0], legacy=False)  # the candidate as every condition's run will load it
    candidate = candidate_protocol(first.manifest, model, gate.max_episodes, str(first.path / "manifest.json"),
                                   gate.text_tokenizer, gate.drop_probes)
    short = model.rstrip("/").replace("hf://", "").replace("random:", "random-").split("/")[-1].replace(":", "-")
    folder = Path(out) / (run_name or f"{short}_{baseline_grid.resolve().name}")
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / GRID_FILE, replace(grid, regress_of=str(baseline_grid.resolve())).to_json())
    loaded = load_protocol_policy(candidate)
    per_condition = {}
    for name in names:
        log.info("regress: condition %s at alpha %.3g", name, alpha / len(names))
        per_condition[name] = regress(baseline_grid / name, model, gate.at(alpha / len(names)), out=folder,
                                      run_name=name, loaded_model=loaded, executor=executor, progress=progress)
    comparison = compare_grids(baseline_grid, folder, gate.compare(),
                               require_complete=False)  # the sequential test may stop a condition early
    verdicts = [r.verdict for r in per_condition.values()] + [comparison.verdict]
    return RegressGridResult(
        format=GRID_FORMAT,
        verdict=GateVerdict.worst(verdicts),
        conditions={name: ConditionRegress(verdict=r.verdict, sequential_verdict=r.sequential_verdict,
                                           compare_verdict=r.compare_verdict, pairs_used=r.pairs_used,
                                           candidate_run=r.candidate_run, alpha=alpha / len(names))
                    for name, r in per_condition.items()},
        compare_verdict=comparison.verdict,
        baseline_grid=str(baseline_grid.resolve()),
        candidate_run=str(folder.resolve()),
        compare=comparison,
    )


def grid_summary_text(result: RegressGridResult, code: int) -> str:
    lines = [f"regress (grid): {result.verdict} over {len(result.conditions)} condition(s)"]
    for name, c in result.conditions.items():
        lines.append(f"  {name}: {c.verdict} (sequential {c.sequential_verdict} at alpha {c.alpha:.3g}, "
                     f"fixed-size {c.compare_verdict}, {c.pairs_used} pairs)")
    lines.append(f"  grid comparison (Holm over every task x condition): {result.compare_verdict}")
    lines += [f"    {note}" for note in result.compare.outcomes.notes]
    lines.append(f"exit code {code}")
    return "\n".join(lines)
