"""Attention along task phases: per-phase means, event-aligned views, a paired test over episodes. Pure numpy/scipy.

Inputs are one episode's arrays as the writers store them (attention.npz: `phase` (steps,) int8 into
`phase_names`, `measures/layer/mask_mass/<cam>/<mask>` (steps, layers), `metrics/mask_area/<cam>/<mask>` (steps,)).

- `phase_lifts`: the lift (mass / area; 1 = chance) of the target, gripper and goal masks and of the background (every
  pixel in no mask: 1 - target - robot - goal, robot including the gripper) per step and layer.
- `phase_means`: an episode's mean of a measure in each phase (nan where it spent no step there).
- `onsets` / `align`: the step a phase starts (its first step) and a window of steps around it; `EVENTS` names them
  (grasp onset, lift-off, place onset, release).
- `phase_test`: does a measure change across phases? Friedman's test (scipy.stats.friedmanchisquare) on the
  per-episode phase means of the episodes that visited every compared phase (with two phases: Wilcoxon's
  signed-rank test); the compared phases are those at least `min_episodes` episodes visited, dropping the least
  visited until `min_episodes` complete episodes remain.
- `failure_contrast`: in a phase, failed against successful episodes (difference of means and a Mann-Whitney U
  p-value).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from harness.analysis.bootstrap import bootstrap_mean_ci

MASKS = ("target", "gripper", "goal")  # measured per phase (plus "background")
EVENTS = {"grasp": "grasp onset", "lift": "lift-off", "transport": "lift-off", "place": "place onset",
          "release": "release"}
MIN_EPISODES = 3


def phase_lifts(arrays: dict) -> dict[str, np.ndarray]:
    """attention.npz arrays -> {"<cam>/<mask>": (steps, layers) lift} for target, gripper, goal and background."""
    out: dict[str, np.ndarray] = {}
    cams = sorted({k.split("/")[3] for k in arrays if k.startswith("measures/layer/mask_mass/")})
    for cam in cams:
        mass = {k.split("/")[-1]: np.asarray(v, np.float64) for k, v in arrays.items()
                if k.startswith(f"measures/layer/mask_mass/{cam}/")}
        area = {k.split("/")[-1]: np.asarray(v, np.float64) for k, v in arrays.items()
                if k.startswith(f"metrics/mask_area/{cam}/")}
        for name in MASKS:
            if name in mass and name in area:
                out[f"{cam}/{name}"] = _lift(mass[name], area[name])
        parts = [n for n in ("target", "robot", "goal") if n in mass and n in area]
        if "target" in parts and "robot" in parts:  # the rest of the image: pixels of no mask
            rest_mass = 1.0 - sum(mass[n] for n in parts)
            rest_area = 1.0 - sum(area[n] for n in parts)
            out[f"{cam}/background"] = _lift(np.clip(rest_mass, 0.0, None), rest_area)
    return out


def _lift(mass: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(steps, layers) mass, (steps,) area -> (steps, layers) mass / area (nan where the area is 0 or unknown)."""
    area = np.asarray(area, np.float64)[:, None]
    ok = np.isfinite(area) & (area > 0)
    return np.divide(mass, np.where(ok, area, 1.0), out=np.full(np.broadcast_shapes(mass.shape, area.shape), np.nan),
                     where=ok & np.isfinite(mass))


def phase_means(phase: np.ndarray, values: np.ndarray, phases: int) -> np.ndarray:
    """phase (steps,) int, values (steps, ...) -> (phases, ...) nan-mean over each phase's steps (nan: none there)."""
    phase = np.asarray(phase)
    values = np.asarray(values, np.float64)
    out = np.full((phases,) + values.shape[1:], np.nan)
    for k in range(phases):
        sel = values[phase == k]
        if len(sel):
            with np.errstate(all="ignore"):
                count = np.isfinite(sel).sum(axis=0)
                total = np.where(np.isfinite(sel), sel, 0.0).sum(axis=0)
            out[k] = np.divide(total, count, out=np.full(count.shape, np.nan), where=count > 0)
    return out


def onsets(phase: np.ndarray, names: tuple[str, ...]) -> dict[str, int]:
    """{event name: first step of the phase} for every phase after the first that the episode entered."""
    phase = np.asarray(phase)
    out = {}
    for k, name in enumerate(names):
        if k == 0 or name not in EVENTS:
            continue
        hits = np.flatnonzero(phase == k)
        if len(hits):
            out[EVENTS[name]] = int(hits[0])
    return out


def align(values: np.ndarray, onset: int, window: int) -> np.ndarray:
    """values (steps, ...) -> (2 window + 1, ...): steps onset-window .. onset+window (nan outside the episode)."""
    values = np.asarray(values, np.float64)
    out = np.full((2 * window + 1,) + values.shape[1:], np.nan)
    lo, hi = max(0, onset - window), min(len(values), onset + window + 1)
    out[lo - (onset - window):hi - (onset - window)] = values[lo:hi]
    return out


def aligned_band(rows: list[np.ndarray], resamples: int = 2000, seed: int = 0, confidence: float = 0.95):
    """[(2w+1, ...) per episode] -> (mean, ci_low, ci_high, n) over episodes, each (2w+1, ...): percentile bootstrap."""
    return bootstrap_mean_ci(np.stack(rows), confidence=confidence, resamples=resamples, seed=seed)


@dataclass(frozen=True)
class PhaseTest:
    test: str  # "friedman", "wilcoxon" or "none"
    statistic: float
    p: float
    episodes: int  # complete episodes compared
    phases: tuple[int, ...]  # phase indices compared
    means: tuple[float, ...]  # mean over those episodes per compared phase


def phase_test(means: np.ndarray, min_episodes: int = MIN_EPISODES) -> PhaseTest:
    """means (episodes, phases) per-episode phase means (nan: not visited) -> the paired test across phases."""
    from scipy import stats

    means = np.asarray(means, np.float64)
    keep = [k for k in range(means.shape[1]) if np.isfinite(means[:, k]).sum() >= min_episodes]
    while len(keep) >= 2:
        complete = np.all(np.isfinite(means[:, keep]), axis=1)
        if complete.sum() >= min_episodes:
            break
        keep.remove(min(keep, key=lambda k: np.isfinite(means[:, k]).sum()))
    if len(keep) < 2:
        return PhaseTest("none", math.nan, math.nan, 0, tuple(keep), ())
    block = means[complete][:, keep]
    avg = tuple(float(v) for v in block.mean(axis=0))
    if np.ptp(block, axis=1).max() == 0:  # every episode the same in every phase: nothing changes
        return PhaseTest("friedman" if len(keep) > 2 else "wilcoxon", 0.0, 1.0, len(block), tuple(keep), avg)
    if len(keep) == 2:
        result = stats.wilcoxon(block[:, 0], block[:, 1])
        return PhaseTest("wilcoxon", float(result.statistic), float(result.pvalue), len(block), tuple(keep), avg)
    result = stats.friedmanchisquare(*block.T)
    return PhaseTest("friedman", float(result.statistic), float(result.pvalue), len(block), tuple(keep), avg)


def failure_contrast(failed: np.ndarray, succeeded: np.ndarray) -> tuple[float, float, float, int, int]:
    """(failed episodes' values, successful episodes' values) in one phase -> (failed mean, successful mean,
    Mann-Whitney U two-sided p (nan with fewer than 2 on a side), n failed, n successful); nan values are left out."""
    from scipy import stats

    a = np.asarray(failed, np.float64)
    b = np.asarray(succeeded, np.float64)
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    p = float(stats.mannwhitneyu(a, b, alternative="two-sided").pvalue) if len(a) >= 2 and len(b) >= 2 else math.nan
    return (float(a.mean()) if len(a) else math.nan, float(b.mean()) if len(b) else math.nan, p, len(a), len(b))
