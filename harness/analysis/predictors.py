"""Which measure predicts failure over a robustness grid: nuisance attention (where the policy looks: the raw map,
and the content-only map where runs have blank controls) or nuisance reliance (what its action depends on:
`--reliance-every`, harness.probes.reliance.reader).

Each measure is taken within conditions: an episode's value minus the mean of its run (one condition and level), so
that a perturbation which moves both the measure and success cannot make the association by itself. Its association
with success is the point-biserial r; a measure predicts failure when r's seed-cluster 95% interval lies below 0.
The comparison is paired: on the episodes where both measures exist, the same resamples of whole seeds (every
episode of a seed, across conditions) give both r's, and the percentile interval of their difference
(r_reliance - r_attention) says which goes with failure more strongly. When the interval holds 0, neither is shown
to predict better, and its half-width is the smallest difference that this grid could have resolved.

`predictor_rows(rows)` -> PREDICTOR_COLUMNS rows, one per task and attention map; `predictor_table(task, rows)` ->
one task's table cells (PREDICTOR_HEADER).
"""

from __future__ import annotations

import math

import numpy as np

from harness.analysis.robustness import CLUSTER_RESAMPLES, MIN_CLASS, EpisodeRow, centred_per_run, has_content

PREDICTOR_COLUMNS = ("task", "attention_map", "episodes", "seeds", "failures", "reliance_r", "reliance_ci_low",
                     "reliance_ci_high", "attention_r", "attention_ci_low", "attention_ci_high", "difference",
                     "difference_ci_low", "difference_ci_high", "verdict")
MAP_WORDS = {"raw": "nuisance attention (raw map)", "content": "nuisance attention (content-only map)"}


def _r(success: np.ndarray, values: np.ndarray) -> float:
    if success.std() == 0 or values.std() == 0:
        return math.nan
    return float(np.corrcoef(success, values)[0, 1])


def paired_difference(seeds, success, first, second, confidence: float = 0.95, resamples: int = CLUSTER_RESAMPLES,
                      seed: int = 0) -> tuple[float, float, float, float, float, float, float, float, float]:
    """(r_first, low, high, r_second, low, high, r_first - r_second, low, high): each point-biserial r with success,
    and their difference, with seed-cluster percentile intervals from the same resamples (a paired comparison).
    Intervals are nan with fewer than 4 seeds or fewer than MIN_CLASS successes or failures."""
    seeds, s = np.asarray(seeds), np.asarray(success, np.float64)
    a, b = np.asarray(first, np.float64), np.asarray(second, np.float64)
    point = (_r(s, a), _r(s, b))
    nan2 = (math.nan, math.nan)
    groups = [np.flatnonzero(seeds == k) for k in np.unique(seeds)]
    if len(groups) < 4 or min(int(s.sum()), int(s.size - s.sum())) < MIN_CLASS:
        return (point[0], *nan2, point[1], *nan2, point[0] - point[1], *nan2)
    draws = []
    for draw in np.random.default_rng(seed).integers(0, len(groups), size=(resamples, len(groups))):
        idx = np.concatenate([groups[g] for g in draw])
        ra, rb = _r(s[idx], a[idx]), _r(s[idx], b[idx])
        if math.isfinite(ra) and math.isfinite(rb):
            draws.append((ra, rb, ra - rb))
    if len(draws) < resamples // 2:
        return (point[0], *nan2, point[1], *nan2, point[0] - point[1], *nan2)
    q = np.quantile(np.asarray(draws), [(1 - confidence) / 2, (1 + confidence) / 2], axis=0)
    return (point[0], float(q[0, 0]), float(q[1, 0]), point[1], float(q[0, 1]), float(q[1, 1]),
            point[0] - point[1], float(q[0, 2]), float(q[1, 2]))


def verdict(result: tuple, attention_map: str) -> str:
    """Which measure is the better predictor of failure, from the interval of r_reliance - r_attention (`result`:
    paired_difference's tuple), and whether the better one predicts failure by itself (its own interval below 0)."""
    low, high = result[7], result[8]
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"too few seeds, successes or failures (< {MIN_CLASS}) to compare"
    if low <= 0 <= high:
        return (f"neither is shown to predict failure better (the interval of the difference holds 0; the smallest "
                f"difference in r it could resolve is about {(high - low) / 2:.2f})")
    better, own_high = ("nuisance reliance", result[2]) if high < 0 else (MAP_WORDS[attention_map], result[5])
    alone = ("and it predicts failure by itself (its own interval lies below 0)" if own_high < 0 else
             "though its own interval does not lie below 0: it does not predict failure by itself here")
    return f"{better} is the better predictor of failure (its r is lower), {alone}"


def predictor_rows(rows: list[EpisodeRow]) -> list[tuple]:
    """Per task and attention map (raw; content-only where runs have controls): reliance against attention, within
    conditions, on the finished episodes that have both. Empty when no episode has nuisance reliance."""
    if not any(math.isfinite(r.nuisance_reliance) for r in rows):
        return []
    out = []
    maps = ("raw", "content") if has_content(rows) else ("raw",)
    for task in dict.fromkeys(r.task for r in rows):
        ok = [r for r in rows if r.task == task and r.status == "ok"]
        for map_ in maps:
            both = [r for r in ok if math.isfinite(r.nuisance("reliance")[0]) and math.isfinite(r.nuisance(map_)[0])]
            if not both:
                continue
            success = [float(r.success) for r in both]
            result = paired_difference([r.seed for r in both], success, centred_per_run(both, "reliance"),
                                       centred_per_run(both, map_))
            out.append((task, map_, len(both), len({r.seed for r in both}), int(len(both) - sum(success)), *result,
                        verdict(result, map_)))
    return out


def _r_text(r: float, low: float, high: float) -> str:
    interval = f" [{low:+.2f}, {high:+.2f}]" if math.isfinite(low) and math.isfinite(high) else " (no interval)"
    return ("r n/a" if not math.isfinite(r) else f"r {r:+.2f}") + interval


PREDICTOR_HEADER = ("map", "nuisance reliance: r [95%]", "nuisance attention: r [95%]", "difference [95%]",
                    "smallest difference it resolves", "better predictor of failure", "episodes", "seeds", "failed")
PREDICTOR_CAPTION = ("which predicts failure within conditions (point-biserial r with success, centred per run, "
                     "seed-cluster 95%)")


def _better(row: tuple) -> str:
    """The verdict column in a few words (the full sentence is the CSV's `verdict`)."""
    low, high = row[12], row[13]
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"too few (< {MIN_CLASS})"
    if low <= 0 <= high:
        return "neither shown"
    better, own_high = ("nuisance reliance", row[7]) if high < 0 else ("nuisance attention", row[10])
    return f"{better}, " + ("which predicts failure alone" if own_high < 0 else "not alone")


def predictor_table(task: str, rows: list[tuple]) -> list[tuple[str, ...]]:
    """'Which predicts failure' for one task as table cells (PREDICTOR_HEADER), one row per attention map ([] when the
    grid has no reliance)."""
    out = []
    for row in (p for p in rows if p[0] == task):
        low, high = row[12], row[13]
        resolves = f"{(high - low) / 2:.2f}" if math.isfinite(low) and math.isfinite(high) and low <= 0 <= high else "-"
        out.append((MAP_WORDS[row[1]].removeprefix("nuisance attention ").strip("()"), _r_text(*row[5:8]),
                    _r_text(*row[8:11]), _r_text(*row[11:14]).replace("r ", "", 1), resolves, _better(row),
                    str(row[2]), str(row[3]), str(row[4])))
    return out
