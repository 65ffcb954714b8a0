"""Sequential regression runs: the candidate model on a baseline run's protocol and seeds, stopped as soon as an
anytime-valid test decides (harness.analysis.sequential).

`regress(baseline_dir, model, ...)` builds the candidate's protocol from the baseline's manifest with only the
model replaced (and, with `max_episodes`, fewer episodes per task), and runs it through the run store
(`harness.run.execute`), so an interrupted regression resumes where it stopped. Jobs run round by round
(episode k of every task, then k + 1), and each complete round is one unit of the sequential test: the mean
over the round's tasks of (candidate success - baseline success) on the same seed. The executor stops as soon
as the test decides; episodes already in the candidate run are counted first, so re-running the same command
reproduces the decision without new episodes. Afterwards the pairs are compared with the fixed-size
statistics (harness.analysis.compare), and the result says how many pairs were used against what a fixed-size
McNemar test would need.
"""
from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path
from typing import Iterator, Sequence

from harness.analysis.compare import CompareConfig, compare_runs
from harness.analysis.paired import PairedCounts, mcnemar_sample_size
from harness.analysis.runs import load_run
from harness.analysis.sequential import SequentialConfig, SequentialTest
from harness.run.executor import EpisodeContext, SequentialExecutor
from harness.run.protocol import EpisodeJob, Protocol
from harness.run.store import EpisodeRow, RunStore

log = logging.getLogger(__name__)


def candidate_protocol(baseline_manifest: dict, model: str, max_episodes: int | None = None) -> Protocol:
    """The baseline's protocol with the model replaced (fingerprints recomputed by the run)."""
    data = dict(baseline_manifest.get("protocol") or {})
    if not data:
        raise ValueError("the baseline run has no protocol in manifest.json (made before the run store); "
                         "re-run the baseline with this octo-harness, then regress against it")
    episodes = int(data.get("episodes") or 1)
    if max_episodes is not None:
        if max_episodes < 1:
            raise ValueError(f"--max-episodes must be at least 1, got {max_episodes}")
        episodes = min(episodes, max_episodes)
    data.update(model=model, model_fingerprint=None, goal_fingerprint=None, episodes=episodes)
    return Protocol.from_dict(data)


def round_order(jobs: Sequence[EpisodeJob], tasks: Sequence[str]) -> list[EpisodeJob]:
    """Jobs round by round: episode 0 of every task (in protocol order), then episode 1, ..."""
    rank = {t: i for i, t in enumerate(tasks)}
    return sorted(jobs, key=lambda j: (j.episode, rank.get(j.task, len(rank))))


def sequential_state(baseline: dict[tuple[str, int], bool], candidate: dict[tuple[str, int], bool],
                     jobs: Sequence[EpisodeJob], tasks: Sequence[str], config: SequentialConfig) -> SequentialTest:
    """Feed complete rounds in order into a fresh test (stops at the first decision).

    baseline / candidate: {(task, seed): success}. A round is complete when every task that has a baseline
    episode for that round's seed has a candidate episode too; rounds without any pair are skipped.
    """
    test = SequentialTest(config)
    rounds: dict[int, list[EpisodeJob]] = {}
    for job in round_order(jobs, tasks):
        rounds.setdefault(job.episode, []).append(job)
    for episode in sorted(rounds):
        paired = [j for j in rounds[episode] if (j.task, j.seed) in baseline]
        if not paired:
            continue
        if any((j.task, j.seed) not in candidate for j in paired):
            break  # the next round is not finished yet
        y = sum(float(candidate[(j.task, j.seed)]) - float(baseline[(j.task, j.seed)]) for j in paired) / len(paired)
        if test.add(y) is not None:
            break
    return test


class _StoppingExecutor:
    """Runs jobs round by round with an inner executor and stops once the sequential test has decided."""

    def __init__(self, inner, baseline: dict, done: dict, jobs: Sequence[EpisodeJob], tasks: Sequence[str],
                 config: SequentialConfig):
        self.inner, self.baseline, self.done = inner, baseline, dict(done)
        self.jobs, self.tasks, self.config = list(jobs), list(tasks), config

    def decided(self) -> bool:
        return sequential_state(self.baseline, self.done, self.jobs, self.tasks, self.config).verdict is not None

    def run(self, jobs: Sequence[EpisodeJob], on_step=None) -> Iterator[EpisodeRow]:
        if self.decided():
            return
        for row in self.inner.run(round_order(jobs, self.tasks), on_step=on_step):
            self.done[(row.task, row.seed)] = bool(row.success) and row.status == "ok"
            yield row
            if self.decided():
                log.info("sequential test decided after %d candidate episodes; stopping", len(self.done))
                return

    def close(self) -> None:
        self.inner.close()


def _outcomes(run) -> dict[tuple[str, int], bool]:
    return {(e.task, e.seed): bool(e.success) and e.ok for e in run.episodes if e.seed is not None}


def regress(baseline_dir: str | Path, model: str, *, max_episodes: int | None = None, out: str | Path = "results/runs",
            run_name: str | None = None, alpha: float = 0.05, max_drop: float = 0.1, loaded_model=None,
            executor=None, progress: bool = True) -> dict:
    """Run the sequential regression (see the module docstring); returns the result dict (regress.json).

    executor: factory(context, model) -> Executor for the candidate's episodes (default SequentialExecutor).
    """
    from harness.run import execute

    baseline = load_run(baseline_dir)
    protocol = candidate_protocol(baseline.manifest, model, max_episodes)
    config = SequentialConfig(alpha=alpha, max_drop=max_drop)
    compare_config = CompareConfig(max_drop=max_drop, alpha=alpha)
    base_outcomes = _outcomes(baseline)
    jobs = protocol.jobs()
    if not any((j.task, j.seed) in base_outcomes for j in jobs):
        raise ValueError(f"the baseline {baseline.path} has no finished episode to pair with; finish the baseline first")

    def factory(context: EpisodeContext, model_):
        existing = {(r.task, r.seed): bool(r.success) and r.status == "ok"
                    for r in RunStore(context.run_dir).load_rows().values()}
        inner = (executor or SequentialExecutor)(context, model_)
        return _StoppingExecutor(inner, base_outcomes, existing, jobs, protocol.tasks, config)

    summary = execute(protocol, out, run_name, model=loaded_model, executor=factory, progress=progress)
    candidate = load_run(summary.run_dir)
    test = sequential_state(base_outcomes, _outcomes(candidate), jobs, protocol.tasks, config)
    used_rounds = test.units
    rounds = round_order(jobs, protocol.tasks)
    used_jobs = [j for j in rounds if j.episode < _round_limit(rounds, used_rounds, base_outcomes)]
    cand = _outcomes(candidate)
    paired = [(j.task, j.seed) for j in used_jobs if (j.task, j.seed) in base_outcomes and (j.task, j.seed) in cand]
    counts = PairedCounts.from_outcomes([base_outcomes[k] for k in paired], [cand[k] for k in paired])
    fixed = None
    if counts.n:
        fixed = mcnemar_sample_size(counts.baseline_only / counts.n, counts.candidate_only / counts.n, alpha, 0.8)
    comparison = compare_runs(baseline.path, candidate.path, compare_config)
    return {
        "format": "octo-harness-regress/1",
        "verdict": test.summary()["verdict"],
        "sequential": test.summary(),
        "pairs_used": counts.n,
        "rounds_used": used_rounds,
        "baseline_pairs": sum((j.task, j.seed) in base_outcomes for j in jobs),
        "fixed_size_pairs_80_power": fixed,
        "fixed_size_note": "pairs a fixed-size two-sided McNemar test at the same alpha needs for 80% power at the "
                           "observed discordance rates (Connor 1987); null when no difference was observed",
        "table": asdict(counts),
        "baseline_run": str(baseline.path),
        "candidate_run": str(candidate.path),
        "candidate_status": candidate.status,
        "compare": comparison,
    }


def _round_limit(rounds: list[EpisodeJob], used_rounds: int, baseline: dict) -> int:
    """Episode index after the last round the test consumed (rounds without pairs do not count)."""
    counted, limit = 0, 0
    for episode in sorted({j.episode for j in rounds}):
        if counted >= used_rounds:
            break
        limit = episode + 1
        if any(j.episode == episode and (j.task, j.seed) in baseline for j in rounds):
            counted += 1
    return limit


def exit_code(result: dict, fail_on: str = "regressed") -> int:
    """0 no regression, 1 REGRESSED (or UNDERPOWERED with fail_on="underpowered")."""
    verdict = result["verdict"]
    if verdict == "REGRESSED":
        return 1
    if fail_on == "underpowered" and verdict == "UNDERPOWERED":
        return 1
    return 0


def summary_text(result: dict, code: int) -> str:
    """A few lines for the terminal / CI log."""
    seq = result["sequential"]
    e = seq["e_values"]
    lines = [
        f"regress: {result['verdict']} after {result['pairs_used']} pairs ({result['rounds_used']} rounds) of "
        f"{result['baseline_pairs']} in the baseline; sequential test at alpha {seq['alpha']:g}, max drop {seq['max_drop']:g}",
        f"  e-values (reject at {seq['threshold']:g}): regression {e['regression']:.3g}, improvement "
        f"{e['improvement']:.3g}, held {e['held']:.3g}",
        f"  a fixed-size McNemar test would need {result['fixed_size_pairs_80_power'] or 'n/a (no difference observed)'} "
        f"pairs for 80% power at the observed discordance",
        f"  fixed-size comparison of the pairs run: {result['compare']['verdict']}",
        f"exit code {code}",
    ]
    return "\n".join(lines)


def write_regress(result: dict, code: int, write_comparison) -> dict:
    """regress.json and the comparison outputs into <candidate run>/regress/; returns paths and the summary text."""
    from harness.files import atomic_write_json

    out = Path(result["candidate_run"]) / "regress"
    paths = write_comparison(result["compare"], out, None, None)
    atomic_write_json(out / "regress.json", {**{k: v for k, v in result.items() if k != "compare"}, "exit_code": code,
                                             "compare_json": str(paths["json"])})
    return {"json": out / "regress.json", "html": paths["html"], "summary": summary_text(result, code)}
