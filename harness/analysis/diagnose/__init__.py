"""`octo-harness diagnose`: why an episode failed, and how early it could have been known, from finished run folders
(no episode is run). docs/diagnose.md explains the method.

`diagnose(paths, out)` reads every finished episode of the runs (a robustness grid folder: its condition runs;
`.signals`), and per task:
- predicts the final failure from what is known up to step t (`.predictors`: a linear probe on the readout features,
  action consistency, attention entropy, nuisance mass, and the time-and-phase baseline), fitted on some seeds and
  scored on the others, and evaluates the scores within conditions (`.evaluate`: AUROC by step and by phase with
  seed-cluster intervals, lead time at a 5% false-alarm rate);
- gives one row per failed episode (`.failures`): its furthest phase and stall step, the successful episodes' median
  step past that phase, the signals furthest from theirs, the run's pre-flight verdicts.
A task with fewer than MIN_CLASS successes or failures gets one line instead of its tables (the failures are still
listed). Outputs in `out` (`.outputs`): diagnose.json (everything), diagnose.md (the tables), failures.csv.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from harness.analysis.diagnose.evaluate import evaluate_task
from harness.analysis.diagnose.failures import failure_rows
from harness.analysis.diagnose.signals import load
from harness.analysis.diagnose.stats import MIN_CLASS, RESAMPLES, counted

FOLDS = 5


@dataclass
class Diagnosis:
    runs: list[str]
    tasks: dict[str, dict]  # task -> evaluate_task's tables, or {"message": ..., counts} with too few of a class
    failures: list[dict]  # failures.failure_rows
    notes: list[str] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)  # the one-line messages (too few of a class, missing signals)
    settings: dict = field(default_factory=dict)


def task_line(task: str, failures: int, successes: int) -> str | None:
    """The one line for a task with too few of a class, None when it has enough of both."""
    if min(failures, successes) >= MIN_CLASS:
        return None
    short = "successes" if successes < failures else "failures"
    return (f"{task}: too few {short} to predict failure ({counted(successes, failures)}; at least "
            f"{MIN_CLASS} of each are needed): no AUROC or lead time; failures.csv still says why each failure failed")


def diagnose(paths, folds: int = FOLDS, resamples: int = RESAMPLES, seed: int = 0) -> Diagnosis:
    episodes, records, notes = load(paths)
    if not episodes:
        raise ValueError(f"no finished episode in {', '.join(str(p) for p in paths)}; diagnose reads runs made by "
                         "octo-harness run or robustness (finish or resume them first)")
    tasks, lines = {}, []
    for task in dict.fromkeys(e.task for e in episodes):
        mine = [e for e in episodes if e.task == task]
        failures = sum(not e.success for e in mine)
        line = task_line(task, failures, len(mine) - failures)
        if line:
            lines.append(line)
            tasks[task] = {"episodes": len(mine), "failures": failures, "seeds": len({e.seed for e in mine}),
                           "runs": sorted({e.run for e in mine}), "message": line}
            continue
        tasks[task] = evaluate_task(mine, folds, resamples, seed)
        if tasks[task]["missing"]:
            lines.append(f"{task}: not evaluated, its signal was not recorded: {', '.join(tasks[task]['missing'])} "
                         "(the readout probe needs a run with --readout-features-every N; entropy and nuisance mass "
                         "a policy with attention)")
    settings = {"folds": folds, "resamples": resamples, "seed": seed, "min_class": MIN_CLASS}
    return Diagnosis([r.name for r in records], tasks, failure_rows(episodes), notes, lines, settings)


def write(diagnosis: Diagnosis, out: str | Path) -> dict[str, Path]:
    from harness.analysis.diagnose.outputs import write_outputs

    return write_outputs(diagnosis, Path(out))
