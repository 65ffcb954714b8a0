"""Compare's verdict logic: the paired outcome tables of two runs and the gate verdict of each (issue 72 item 4).

`outcome_tables(details)` counts compare's (or regress's) pairs per task: a 2x2 table of the pairs in which both arms
ran to an outcome, and the pairs left out because an arm errored. `outcome_verdicts(tables, config)` gives each
table (every task, and the pooled table) its rates with Wilson intervals, the difference with Newcombe's interval,
McNemar's exact p and its Holm adjustment over the family, the gate verdict (harness.analysis.paired.paired_verdict)
and the lines that say why; `overall_verdict` is the worst of them (harness.verdicts.GateVerdict's rank), IDENTICAL
when every pair is. `incompleteness` is the note of a candidate that lacks the baseline's finished episodes
(INCOMPLETE). The verdicts, their order and exit codes are harness.verdicts'.
"""
from __future__ import annotations

from dataclasses import asdict

from harness.analysis.compare_result import CompareConfig, Incompleteness, OutcomeBlock, Outcomes, Rate
from harness.analysis.paired import (
    ErroredPairs,
    PairedCounts,
    difference_interval,
    errored_most,
    holm_adjust,
    mcnemar_exact,
    min_mcnemar_p,
    paired_verdict,
    pairs_for_regressed,
    pairs_to_decide,
    regressed_reachable,
)
from harness.measures.stats import wilson_interval
from harness.verdicts import GateVerdict

POOLED = "\0pooled"  # key of the pooled table while verdicts are computed (cannot clash with a task name)
UNDECIDED = (GateVerdict.UNDERPOWERED, GateVerdict.SUSPECT)  # more pairs could decide these: "to decide" projects them


def _rate(successes: int, n: int, confidence: float, errored: int = 0) -> dict:
    low, high = wilson_interval(successes, n, confidence)
    return {"successes": successes, "n": n, "rate": successes / n if n else None, "ci_low": low, "ci_high": high,
            "errored": errored}


def _outcome_block(counts: PairedCounts, config: CompareConfig, errored: ErroredPairs = ErroredPairs(),
                   family: int = 1) -> dict:
    """One table's numbers: n = pairs with an outcome in both arms; errored pairs counted beside it. The arms'
    Wilson intervals are at 1 - alpha; the difference's Newcombe interval at 1 - alpha / family (Bonferroni
    over the Holm family: the intervals of every task and the pooled table hold together at 1 - alpha)."""
    confidence = 1.0 - config.alpha
    low, high = difference_interval(counts, 1.0 - config.alpha / family)
    return {
        "pairs": counts.n,
        "errored_pairs": errored.pairs,
        "paired_episodes": counts.n + errored.pairs,
        "table": asdict(counts),
        "baseline": _rate(counts.baseline_successes, counts.n, confidence, errored.baseline),
        "candidate": _rate(counts.candidate_successes, counts.n, confidence, errored.candidate),
        "difference": counts.difference if counts.n else None,
        "difference_ci": [low, high],
        "difference_confidence": 1.0 - config.alpha / family,
        "mcnemar_p": mcnemar_exact(counts.baseline_only, counts.candidate_only),
    }


def _notes(label: str, block: dict, alpha: float, pooled: bool = False) -> list[str]:
    """The lines that say why a block's verdict is what it is (errors, an unreachable REGRESSED); the pooled
    table's errors are its tasks' (already said)."""
    notes = []
    n, paired = block["pairs"], block["paired_episodes"]
    for arm in ("candidate", "baseline"):
        errored = block[arm]["errored"]
        if errored_most(errored, paired) and not pooled:
            tail = ("it cannot pass the gate" if arm == "candidate" else
                    "the baseline cannot serve as the reference, so the gate cannot pass; re-run the baseline")
            notes.append(f"{GateVerdict.ERRORED}: the {arm} errored on {errored} of {paired} paired episodes in "
                         f"{label} (more than half): {tail}.")
    if block["errored_pairs"] and block["verdict"] != GateVerdict.ERRORED and not pooled:
        notes.append(f"{block['errored_pairs']} errored pair(s) in {label} left out of n = {n} (baseline errored "
                     f"{block['baseline']['errored']}, candidate {block['candidate']['errored']}): at best "
                     f"{GateVerdict.UNDERPOWERED}.")
    if not block["regressed_reachable"] and block["verdict"] != GateVerdict.ERRORED:
        factor = block["holm_factor"]
        notes.append(f"{GateVerdict.REGRESSED} is unreachable with {n} pairs in {label}: the smallest exact McNemar p "
                     f"is {min_mcnemar_p(n):.3g} (x Holm factor {factor} = {min(1.0, factor * min_mcnemar_p(n)):.3g}) "
                     f"> alpha {alpha:g}; at least {block['pairs_for_regressed']} pairs are needed.")
    return notes


def outcome_verdicts(tables: dict[str, PairedCounts], config: CompareConfig,
                     errored: dict[str, ErroredPairs] | None = None, project: bool = True) -> Outcomes:
    """{task: counts} -> Outcomes (tasks: {task: OutcomeBlock}, overall: the pooled block, holm_family, notes), each
    block with its Holm-adjusted p and verdict.

    errored: {task: pairs left out because an arm errored} (none when absent). The Holm family is every task
    plus the pooled table (the pooled table alone when there is one task); the difference intervals are
    simultaneous over it (1 - alpha / family), so SUSPECT's family-wise false alarm stays <= alpha / 2 as
    REGRESSED's does. For an UNDERPOWERED or SUSPECT block,
    `pairs_to_decide` projects its table with the family size as the p-value factor (the largest Holm factor,
    so the estimate errs towards more pairs); `regressed_reachable` says whether its n pairs could give
    REGRESSED at all with that factor (project=False skips the projection: simulations). The overall block's
    verdict is the pooled table's; the overall verdict of a comparison is `overall_verdict`.
    """
    errored = errored or {}
    named = dict(tables)
    named[POOLED] = sum(tables.values(), PairedCounts())
    named_errored = {name: errored.get(name, ErroredPairs()) for name in tables}
    named_errored[POOLED] = sum(named_errored.values(), ErroredPairs())
    family = list(named) if len(tables) > 1 else [POOLED]
    blocks = {name: _outcome_block(counts, config, named_errored[name], len(family)) for name, counts in named.items()}
    for name, p in zip(family, holm_adjust([blocks[name]["mcnemar_p"] for name in family])):
        blocks[name]["mcnemar_p_holm"] = p
    if len(tables) == 1:  # one task: its table is the pooled one
        blocks[next(iter(tables))]["mcnemar_p_holm"] = blocks[POOLED]["mcnemar_p_holm"]
    factor = len(family)
    notes = []
    for name, counts in named.items():
        block = blocks[name]
        block["verdict"] = paired_verdict(counts, block["mcnemar_p_holm"], tuple(block["difference_ci"]),
                                          config.max_drop, config.alpha, named_errored[name])
        needed = None
        if project and block["verdict"] in UNDECIDED:
            needed = pairs_to_decide(counts, config.max_drop, config.alpha, multiplier=factor)
        block["pairs_to_decide"] = needed
        block["more_pairs_needed"] = None if needed is None else needed - counts.n
        block["holm_factor"] = factor
        block["regressed_reachable"] = regressed_reachable(counts.n, config.alpha, factor)
        block["pairs_for_regressed"] = pairs_for_regressed(config.alpha, factor)
        block["notes"] = ([] if name == POOLED and len(tables) == 1 else
                          _notes("pooled" if name == POOLED else name, block, config.alpha, pooled=name == POOLED))
        notes += block["notes"]
    pooled = blocks.pop(POOLED)
    return Outcomes(tasks={name: _typed_block(block) for name, block in blocks.items()}, overall=_typed_block(pooled),
                    holm_family=factor, notes=tuple(notes))


def _typed_block(block: dict) -> OutcomeBlock:
    """An outcome table's dict (as `_outcome_block` and `outcome_verdicts` fill it) as an OutcomeBlock."""
    return OutcomeBlock(**{**block, "table": PairedCounts(**block["table"]), "baseline": Rate(**block["baseline"]),
                           "candidate": Rate(**block["candidate"]), "difference_ci": tuple(block["difference_ci"]),
                           "notes": tuple(block["notes"])})


def overall_verdict(outcomes: Outcomes, identical: bool = False) -> GateVerdict:
    """IDENTICAL when every pair is identical, else the worst verdict of the tasks and the pooled table."""
    if identical:
        return GateVerdict.IDENTICAL
    return GateVerdict.worst([b.verdict for b in outcomes.tasks.values()] + [outcomes.overall.verdict])


def outcome_tables(details: list[dict]) -> tuple[dict[str, PairedCounts], dict[str, ErroredPairs]]:
    """Pairs (task, baseline/candidate success and status) -> ({task: 2x2 table of the pairs in which both
    arms ran to an outcome}, {task: pairs left out because an arm errored}), tasks in order of appearance."""
    tables: dict[str, PairedCounts] = {}
    errored: dict[str, ErroredPairs] = {}
    for d in details:
        task = d["task"]
        base_ok, cand_ok = d["baseline_status"] == "ok", d["candidate_status"] == "ok"
        tables.setdefault(task, PairedCounts())
        errored[task] = errored.get(task, ErroredPairs()) + ErroredPairs.from_statuses([base_ok], [cand_ok])
        if base_ok and cand_ok:
            one = PairedCounts.from_outcomes([bool(d["baseline_success"])], [bool(d["candidate_success"])])
            tables[task] = tables[task] + one
    return tables, errored


def incompleteness(lacking: list, baseline_path, candidate_path) -> Incompleteness | None:
    """[[task, seed]] the baseline finished and the candidate did not -> Incompleteness (pairs, tasks: {task: count},
    note), or None when it lacks none."""
    if not lacking:
        return None
    tasks: dict[str, int] = {}
    for task, _ in lacking:
        tasks[task] = tasks.get(task, 0) + 1
    listed = ", ".join(f"{task} {count}" for task, count in tasks.items())
    return Incompleteness(
        pairs=len(lacking), tasks=tasks,
        note=f"{GateVerdict.INCOMPLETE}: the candidate {candidate_path} lacks {len(lacking)} finished episode(s) "
             f"the baseline {baseline_path} has ({listed}); it cannot pass the gate until it runs them (the "
             "baseline's tasks and seeds: `octo-harness run --resume` on the candidate, or `octo-harness regress`).")
