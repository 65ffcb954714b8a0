"""diagnose's outputs: diagnose.json (everything), diagnose.md (the tables) and failures.csv, written together (a
refused write removes all three)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from harness.analysis.diagnose.evaluate import BETTER, STEPS
from harness.analysis.diagnose.failures import FAILURE_COLUMNS
from harness.analysis.diagnose.stats import FALSE_ALARM
from harness.files import all_or_none, atomic_write_json, write_atomic

FILES = {"json": "diagnose.json", "markdown": "diagnose.md", "csv": "failures.csv"}
SHOWN_FAILURES = 40  # diagnose.md lists at most this many failed episodes a task (failures.csv has all)


def number(x, digits: int = 2) -> str:
    """A figure to `digits` places, or an em dash when there is none."""
    return "—" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _auroc(row: dict, pooled: bool = False) -> str:
    value, (low, high) = (row["pooled_auroc"], row["pooled_interval"]) if pooled else (row["auroc"], row["interval"])
    if not math.isfinite(value):
        return "—"
    text = f"{value:.2f} [{number(low)}, {number(high)}]"
    if pooled or row["verdict"] == "the baseline":
        return text
    return text + (", better" if row["verdict"] == BETTER else ", not better")


def auroc_table(cells: list[dict], labels: list[str], names: list[str], pooled: bool) -> list[str]:
    """The AUROC table's lines (a row per predictor, a column per cell) and the cells' one-line notes."""
    lines = ["| predictor | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels),
             "| failures / successes | " + " | ".join(f"{c['failures']} / {c['successes']}" for c in cells) + " |"]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(_auroc(c["predictors"][name], pooled) if name in c["predictors"]
                                                 else "—" for c in cells) + " |")
    notes = [f"- {c['where']}: {c['message']}" for c in cells if c.get("message")]
    return lines + ([""] + notes if notes else [])


def task_section(task: str, result: dict) -> list[str]:
    lines = [f"## {task}", ""]
    head = (f"{result['episodes']} episodes, {result['failures']} failed, {result['seeds']} seeds, runs: "
            f"{', '.join(result['runs'])}.")
    if "message" in result:
        return lines + [head, "", result["message"], ""]
    names = result["predictors"]
    lines += [head + f" Scores come from {result['folds']} seed-disjoint folds (a seed never on both sides).", ""]
    lines += ["### AUROC by step, within conditions", "",
              "Over the episodes still running at t; pairs of one run only. \"better\": the seed-cluster interval of "
              "its difference from time and phase lies above 0.", ""]
    lines += auroc_table(result["by_step"], [f"t = {t}" for t in STEPS], names, pooled=False) + [""]
    if result["by_phase"]:
        lines += ["### AUROC on entering each phase, within conditions", ""]
        lines += auroc_table(result["by_phase"], [c["phase"] for c in result["by_phase"]], names, pooled=False) + [""]
    else:
        lines += [result["no_phases"], ""]
    lines += ["### Lead time", "",
              f"Threshold: at most {FALSE_ALARM:.0%} of the successful training episodes flagged. Lead: steps from the "
              "first flag to the stall step (positive: before it).", ""]
    lines += lead_time_table(result)
    lines += ["", "### Pooled across conditions (not the result)", "",
              "Pairs across runs, inputs not centred per run: a perturbation that predicts failure by itself counts "
              "here.", ""]
    lines += auroc_table(result["by_step"], [f"t = {t}" for t in STEPS], names, pooled=True) + [""]
    return lines


def lead_time_table(result: dict) -> list[str]:
    """The lead-time table's lines: a row per predictor."""
    lines = ["| predictor | failures flagged | median lead (steps) | false alarms, held-out | false alarms, training |",
             "|---|---|---|---|---|"]
    for name, row in result["lead_time"].items():
        if row.get("message"):
            lines.append(f"| {name} | {row['message']} | | | |")
            continue
        lines.append(f"| {name} | {row['flagged_failures']}/{row['failures']} ({number(100 * row['flagged_share'], 0)}%)"
                     f" | {number(row['median_lead'], 1)} | {number(100 * row['false_alarm'], 0)}% of "
                     f"{row['successes']} | {number(100 * row['training_false_alarm'], 0)}% |")
    return lines


def failures_section(rows: list[dict]) -> list[str]:
    lines = ["## Why each failed episode failed", "",
             "Stall step: the first step of the furthest phase reached (no phases: the last tenth). Signals: robust "
             "z-scores against the successful episodes of the same task and condition at that phase.", "",
             "| run | task | seed | furthest phase | stall step | successes passed it (median step) | furthest "
             "signals | pre-flight |", "|---|---|---|---|---|---|---|---|"]
    for task in dict.fromkeys(r["task"] for r in rows):
        mine = [r for r in rows if r["task"] == task]
        for r in mine[:SHOWN_FAILURES]:
            phase = r["furthest_phase"] or r["stall_basis"]
            lines.append(f"| {r['run']} | {r['task']} | {r['seed']} | {phase} | {r['stall_step']} | "
                         f"{r['passed_median'] or '—'} | {r['furthest']} | {r['preflight']} |")
        if len(mine) > SHOWN_FAILURES:
            lines.append(f"| ... | {task} | | {len(mine) - SHOWN_FAILURES} more in failures.csv | | | | |")
    return lines + [""]


def markdown(diagnosis) -> str:
    lines = ["# Failure early warning", "", f"Runs: {', '.join(diagnosis.runs)}. Folds {diagnosis.settings['folds']}, "
             f"{diagnosis.settings['resamples']} seed-cluster resamples, at least {diagnosis.settings['min_class']} "
             "episodes of each class for an AUROC.", ""]
    shown = {r.get("message") for r in diagnosis.tasks.values()}  # a task's own line is in its section
    general = [line for line in diagnosis.lines if line not in shown]
    lines += [f"- {line}" for line in general] + ([""] if general else [])
    for task, result in diagnosis.tasks.items():
        lines += task_section(task, result)
    lines += failures_section(diagnosis.failures) if diagnosis.failures else ["No episode failed.", ""]
    lines += [f"- {note}" for note in diagnosis.notes]
    return "\n".join(lines).rstrip("\n") + "\n"


def failures_csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, FAILURE_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def write_outputs(diagnosis, out: Path) -> dict[str, Path]:
    paths = {kind: out / name for kind, name in FILES.items()}
    out.mkdir(parents=True, exist_ok=True)
    with all_or_none(*paths.values()):
        atomic_write_json(paths["json"], {"format": "octo-harness-diagnose/1", "runs": diagnosis.runs,
                                          "settings": diagnosis.settings, "lines": diagnosis.lines,
                                          "notes": diagnosis.notes, "tasks": diagnosis.tasks,
                                          "failures": diagnosis.failures})
        text = markdown(diagnosis).encode()
        write_atomic(paths["markdown"], lambda f: f.write(text))
        table = failures_csv(diagnosis.failures).encode()
        write_atomic(paths["csv"], lambda f: f.write(table))
    return paths
