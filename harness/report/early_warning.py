"""The "Failure early warning" section of a model's EVAL.md, from `octo-harness diagnose` over run folders.

    python -m harness.report.early_warning RUN... [--eval-md EVAL.md] [--note TEXT] [--command TEXT]
        [--folds N] [--resamples N]

Per task, in the short form every generated section has (no prose paragraph over 120 words):
- the AUROC table by step, within conditions, each cell with its seed-cluster interval and its verdict against time
  and phase;
- the smallest AUROC difference from time and phase each cell could resolve: half the width of the paired interval
  of the difference, so a null result says what it could have detected;
- lead times and false alarms at the threshold calibrated on successful training episodes (5% false alarms);
- the per-phase stall table: where the failed episodes stalled, when, and when the successes passed that phase.
The figures go to `figures/failure-early-warning.json` beside the EVAL.md and the section is rendered from it
(harness/report/eval_md.py). The method is docs/diagnose.md's.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from harness.analysis.diagnose import FOLDS, diagnose
from harness.analysis.diagnose.evaluate import BETTER, STEPS
from harness.analysis.diagnose.stats import FALSE_ALARM, RESAMPLES
from harness.analysis.diagnose.outputs import auroc_table, lead_time_table, number
from harness.analysis.diagnose.predictors import BASELINE
from harness.report.figures_file import markdown_table

SECTION = "## Failure early warning"


def resolvable(row: dict) -> float:
    """Half the width of the paired interval of a predictor's AUROC difference from time and phase: the smallest
    difference these episodes could tell from none (nan without an interval or with one of width 0)."""
    low, high = row.get("difference_interval", (math.nan, math.nan))
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return math.nan  # no interval, or every resample gave one difference (too few pairs to tell): no resolution
    return (high - low) / 2


def resolvable_table(result: dict) -> list[str]:
    names = [n for n in result["predictors"] if n != BASELINE]
    rows = []
    for name in names:
        cells = [c["predictors"].get(name) for c in result["by_step"]]
        rows.append([name, *(f"±{resolvable(c):.2f}" if c and math.isfinite(resolvable(c)) else "—" for c in cells)])
    return markdown_table(["predictor", *(f"t = {t}" for t in STEPS)], rows)


def verdict_line(task: str, result: dict) -> str:
    """One line: which predictors beat time and phase where, or the null result with what it could have resolved."""
    better, narrowest = [], None
    for cell in result["by_step"] + result["by_phase"]:
        for name, row in cell["predictors"].items():
            if row.get("verdict") == BETTER:
                low, high = row["difference_interval"]
                better.append(f"{name} {cell['where']} ({row['difference']:+.2f} [{low:+.2f}, {high:+.2f}])")
            width = resolvable(row) if name != BASELINE else math.nan
            if math.isfinite(width) and (narrowest is None or width < narrowest[0]):
                narrowest = (width, name, cell["where"])
    if better:
        return f"{task}: better than time and phase: " + "; ".join(better) + "."
    if narrowest is None:
        return f"{task}: no cell had enough failures and successes within a run to compare with time and phase."
    width, name, where = narrowest
    return (f"{task}: no predictor is better than time and phase at any step or phase. The smallest AUROC difference "
            f"these episodes could have resolved is ±{width:.2f} ({name}, {where}); a smaller gain would go unseen.")


def stall_table(failures: list[dict], task: str, phases: list[str]) -> list[str]:
    """Per phase: the failures that stalled there, their median stall step, the successes' median step past it, and
    the signal most often furthest from the successes'."""
    mine = [r for r in failures if r["task"] == task]
    order = list(phases) + sorted({r["furthest_phase"] or r["stall_basis"] for r in mine} - set(phases))
    rows = []
    for phase in order:
        here = [r for r in mine if (r["furthest_phase"] or r["stall_basis"]) == phase]
        if not here:
            continue
        passed = [float(r["passed_median"]) for r in here if r["passed_median"]]
        signals = Counter(r["furthest"].split(" ")[0] for r in here if r["furthest"] and r["furthest"][0] != "n")
        top = ", ".join(f"{s} ({n})" for s, n in signals.most_common(2)) or "—"
        rows.append([phase, len(here), number(float(np.median([r["stall_step"] for r in here])), 0),
                     number(float(np.median(passed)), 0) if passed else "—", top])
    return markdown_table(["stalled in phase", "failed episodes", "median stall step",
                           "successes passed it (median step)", "signal furthest from the successes (episodes)"], rows)


def markdown(records, note: str, folds: int = FOLDS, resamples: int = RESAMPLES) -> str:
    """section_main's `markdown`: diagnose the runs, then `section_text`."""
    try:
        result = diagnose([r.path for r in records], folds=folds, resamples=resamples)
    except ValueError as exc:  # no finished episode: section_main prints the one line, EVAL.md untouched
        raise ValueError(f"no Failure early warning section: {exc}") from None
    unfinished = [f"{r.name} ({len(r.episodes)} of {len(r.jobs)} episodes)" for r in records if r.missing]
    return section_text(result, note, unfinished)


def section_text(result, note: str = "", unfinished: list[str] | None = None) -> str:
    """The section's Markdown from a diagnose.Diagnosis; `unfinished` names runs with episodes still to run."""
    folds, resamples = result.settings["folds"], result.settings["resamples"]
    parts = [SECTION, note,
             *([f"- Not finished, so these figures are interim: {', '.join(unfinished)}."] if unfinished else []),
             f"- Method: docs/diagnose.md. Each predictor is fitted on {folds - 1} of {folds} seed-disjoint folds and "
             "scored on the held-out one. An AUROC compares a failure and a success of one run (one condition), "
             f"with a seed-cluster 95% interval ({resamples} resamples).",
             "- \"better\": the paired interval of the difference from time and phase lies above 0. \"Resolvable\": "
             "half that interval's width, the smallest difference these episodes could tell from none.",
             f"- Lead time: the threshold flags at most {FALSE_ALARM:.0%} of the successful training episodes. Lead is "
             "the steps from the first flag to the stall step (positive: before it)."]
    for task, res in result.tasks.items():
        parts.append(f"### {task}")
        if "message" in res:
            parts.append(res["message"])
        else:
            runs = len(res["runs"])
            parts.append(f"{res['episodes']} episodes ({res['failures']} failed) of {res['seeds']} seeds in "
                         f"{runs} run{'s' if runs != 1 else ''}.")
            parts.append("\n".join(auroc_table(res["by_step"], [f"t = {t}" for t in STEPS], res["predictors"],
                                               pooled=False)))
            parts.append("Resolvable AUROC difference from time and phase, by step:")
            parts.append("\n".join(resolvable_table(res)))
            parts.append(verdict_line(task, res))
            parts.append("\n".join(lead_time_table(res)))
        if any(r["task"] == task for r in result.failures):
            parts.append(f"Where {task}'s failed episodes stalled:")
            parts.append("\n".join(stall_table(result.failures, task, res.get("phases", []))))
    return "\n\n".join(p.strip("\n") for p in parts if p.strip()) + "\n"


def main(argv=None) -> int:
    import argparse
    import functools

    from harness.report.eval_md import section_main

    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--folds", type=int, default=FOLDS)
    parser.add_argument("--resamples", type=int, default=RESAMPLES)
    known, rest = parser.parse_known_args(argv)
    options = (("--folds", str(known.folds)) if known.folds != FOLDS else ()) + \
        (("--resamples", str(known.resamples)) if known.resamples != RESAMPLES else ())
    return section_main(rest, "python -m harness.report.early_warning", "Write the Failure early warning section of "
                        "an EVAL.md from run folders (octo-harness diagnose's tables; docs/diagnose.md)",
                        functools.partial(markdown, folds=known.folds, resamples=known.resamples), options)


if __name__ == "__main__":
    raise SystemExit(main())
