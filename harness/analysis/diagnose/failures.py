"""Why each failed episode failed: one row per failed episode (failures.csv, FAILURE_COLUMNS).

- furthest phase and stall step (stats.stall_step): the first step of the furthest phase it reached, after which it
  made no more progress; a task without phases (Door, LIBERO) says so and uses the first step of the last tenth;
- `passed_median`: the median step at which the successful episodes of the same task and condition passed that phase
  (their first step beyond it; the last phase: their last step); without phases, their median length;
- the signals at the stall against the successful episodes' at the same phase: each signal's mean over the failed
  episode's steps in its furthest phase (without phases: its last tenth) as a robust z-score (stats.robust_z: median
  and MAD) against the successful episodes' means over their steps in that phase (their last tenth); `furthest`
  names the largest by size. Signals: attention on the target, gripper and nuisance regions, nuisance reliance
  where measured, action consistency;
- the run's pre-flight verdicts (manifest "preflight").
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from harness.analysis.diagnose.signals import EpisodeSignals
from harness.analysis.diagnose.stats import LAST_TENTH, robust_z, stall_step

Z_SIGNALS = ("target", "gripper", "nuisance", "reliance", "consistency")
Z_SIGNALS_TEXT = ("attention on the target, gripper and nuisance regions, nuisance reliance where measured, action "
                  "consistency")  # what Z_SIGNALS are, in words (the report's Failures section quotes it)
FAILURE_COLUMNS = ("run", "task", "condition", "seed", "episode", "steps", "furthest_phase", "stall_step", "stall_basis",
                   "passed_median", "successes", *(f"z_{s}" for s in Z_SIGNALS), "furthest", "preflight")
NO_PHASES = "no phases: last tenth"


def _window(episode: EpisodeSignals, phase: int | None) -> np.ndarray:
    """The steps an episode spent in `phase` (None: its last tenth)."""
    if phase is None or not episode.has_phases:
        return np.arange(int(math.floor(episode.steps * (1 - LAST_TENTH))), episode.steps)
    return np.flatnonzero(episode.phase == phase)


def _mean(values: np.ndarray, steps: np.ndarray) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmean(values[steps])) if len(steps) else math.nan


def passed(episode: EpisodeSignals, phase: int) -> int:
    """The first step a (successful) episode was beyond `phase`; its last step when it never was."""
    beyond = np.flatnonzero(episode.phase > phase)
    return int(beyond[0]) if len(beyond) else episode.steps - 1


def _cell(value: float, digits: int = 2) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def failure_rows(episodes: list[EpisodeSignals]) -> list[dict]:
    """FAILURE_COLUMNS dicts, one per failed episode, in run, task, seed order."""
    out = []
    for episode in episodes:
        if episode.success:
            continue
        peers = [e for e in episodes if e.success and e.task == episode.task and e.condition == episode.condition]
        if episode.has_phases:
            furthest = int(episode.phase.max())
            name = episode.phase_names[furthest] if furthest < len(episode.phase_names) else str(furthest)
            basis = "phases"
            marks = [passed(e, furthest) for e in peers if e.has_phases and e.phase.max() >= furthest]
            reference = [e for e in peers if e.has_phases and (e.phase == furthest).any()]
        else:
            furthest, name, basis = None, "", NO_PHASES
            marks = [e.steps for e in peers]
            reference = peers
        stall = stall_step(episode.phase if episode.has_phases else None, episode.steps)
        own = _window(episode, furthest)
        z = {}
        for signal in Z_SIGNALS:
            value = _mean(episode.signals[signal], own)
            z[signal] = robust_z(value, [_mean(e.signals[signal], _window(e, furthest)) for e in reference])
        ranked = sorted((s for s in Z_SIGNALS if math.isfinite(z[s])), key=lambda s: -abs(z[s]))
        out.append({"run": episode.run, "task": episode.task, "condition": episode.condition, "seed": episode.seed,
                    "episode": episode.episode, "steps": episode.steps, "furthest_phase": name, "stall_step": stall,
                    "stall_basis": basis, "passed_median": _cell(float(np.median(marks)) if marks else math.nan, 1),
                    "successes": len(reference),
                    **{f"z_{s}": _cell(z[s]) for s in Z_SIGNALS},
                    "furthest": "; ".join(f"{s} {z[s]:+.1f}" for s in ranked[:3]) or
                                f"no z-score (fewer than 3 successful episodes of {episode.task} in {episode.condition})",
                    "preflight": episode.preflight})
    return sorted(out, key=lambda r: (r["run"], r["task"], r["seed"], r["episode"]))
