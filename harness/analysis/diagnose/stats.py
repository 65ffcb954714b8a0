"""The statistics of `diagnose`, pure numpy: AUROC within strata and its seed-cluster bootstrap, seed-disjoint folds,
an L2-regularised logistic regression, the threshold at a false-alarm rate, the stall step and robust z-scores.

AUROC (`auroc`): the share of (failure, success) pairs the score orders correctly (a tie counts one half), over the
pairs of the same stratum only: with one stratum per run and task, a score that is constant within each run (the
condition alone) scores 0.5, whatever it says across conditions. One stratum over everything is the pooled AUROC.

Seed-cluster bootstrap (`cluster_draws`): whole seeds are drawn with replacement, each with every episode it has
(across runs, tasks and conditions, which share the scene's seed); an episode's weight in a resample is how often its
seed was drawn. The AUROC of a resample weighs each pair by the product of its two weights (`bootstrap_auroc`); the
same draws serve a predictor and the baseline, so their difference is paired. The interval is the percentile one;
resamples without a pair of both classes are left out, and with more than half of them left out there is none.
"""

from __future__ import annotations

import math

import numpy as np

RESAMPLES = 2000
MIN_CLASS = 5  # fewer failures or successes than this: no AUROC, a line saying so
FALSE_ALARM = 0.05
LAST_TENTH = 0.1  # a task without phases: its stall step opens the episode's last tenth
MAD_SCALE = 1.4826  # the MAD of a normal distribution times this is its standard deviation


# ------------------------------------------------------------------------------------------- AUROC


def _comparisons(fail_scores: np.ndarray, ok_scores: np.ndarray) -> np.ndarray:
    """(n_fail, n_ok): 1 where the failure scores higher, 0.5 on a tie, 0 below."""
    diff = fail_scores[:, None] - ok_scores[None, :]
    return (diff > 0) + 0.5 * (diff == 0)


def auroc(scores, failed, strata=None) -> float:
    """The AUROC of `scores` (higher: failure) for the 0/1 labels `failed`, over (failure, success) pairs of the same
    stratum (None: one stratum); nan without such a pair. nan scores are left out."""
    scores, failed = np.asarray(scores, np.float64), np.asarray(failed, bool)
    strata = np.zeros(len(scores), int) if strata is None else np.asarray(strata)
    keep = np.isfinite(scores)
    num = den = 0.0
    for stratum in np.unique(strata[keep]):
        here = keep & (strata == stratum)
        f, s = scores[here & failed], scores[here & ~failed]
        if len(f) and len(s):
            num += float(_comparisons(f, s).sum())
            den += len(f) * len(s)
    return num / den if den else math.nan


def cluster_draws(seeds, resamples: int = RESAMPLES, seed: int = 0) -> np.ndarray:
    """(resamples, episodes) float weights: how often each episode's seed was drawn when the distinct seeds are drawn
    with replacement (as many draws as seeds)."""
    seeds = np.asarray(seeds)
    unique, index = np.unique(seeds, return_inverse=True)
    rng = np.random.default_rng(seed)
    counts = np.stack([np.bincount(rng.integers(0, len(unique), len(unique)), minlength=len(unique))
                       for _ in range(resamples)]) if len(unique) else np.zeros((resamples, 0))
    return counts[:, index].astype(np.float64)


def bootstrap_auroc(scores, failed, strata, weights: np.ndarray) -> np.ndarray:
    """(resamples,) the stratified AUROC under each row of `weights` (cluster_draws; nan where a resample has no pair
    of both classes in one stratum)."""
    scores, failed, strata = np.asarray(scores, np.float64), np.asarray(failed, bool), np.asarray(strata)
    keep = np.isfinite(scores)
    num = np.zeros(len(weights))
    den = np.zeros(len(weights))
    for stratum in np.unique(strata[keep]):
        here = keep & (strata == stratum)
        fi, si = np.flatnonzero(here & failed), np.flatnonzero(here & ~failed)
        if not (len(fi) and len(si)):
            continue
        comparisons = _comparisons(scores[fi], scores[si])  # (nf, ns)
        wf, ws = weights[:, fi], weights[:, si]
        num += np.einsum("bf,fs,bs->b", wf, comparisons, ws)
        den += wf.sum(axis=1) * ws.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)


def percentile_interval(draws: np.ndarray, confidence: float = 0.95) -> tuple[float, float]:
    """The percentile interval of the finite draws; (nan, nan) when fewer than half of them are finite."""
    draws = np.asarray(draws, np.float64)
    finite = draws[np.isfinite(draws)]
    if len(finite) < max(1, len(draws) // 2):
        return (math.nan, math.nan)
    low, high = np.quantile(finite, [(1 - confidence) / 2, (1 + confidence) / 2])
    return (float(low), float(high))


# ------------------------------------------------------------------------------------------- folds and the model


def seed_folds(seeds, folds: int = 5, seed: int = 0) -> np.ndarray:
    """(episodes,) fold index 0..k-1 by seed: every episode of a seed (in any run, task or condition) is in the same
    fold, so a model fitted on the other folds has never seen that seed. k = min(folds, distinct seeds)."""
    seeds = np.asarray(seeds)
    unique = np.unique(seeds)
    k = max(1, min(int(folds), len(unique)))
    order = np.random.default_rng(seed).permutation(len(unique))
    fold_of = {unique[i]: n % k for n, i in enumerate(order)}
    return np.asarray([fold_of[s] for s in seeds], int)


class Logistic:
    """L2-regularised logistic regression on standardised inputs (the mean and standard deviation of the training
    rows), fitted by Newton's method (iteratively reweighted least squares); `l2` is the penalty on the weights of
    the standardised inputs (not on the intercept), `weights` weigh the rows (e.g. 1 / steps, so that every episode
    counts once: the penalty then weighs against the number of episodes). Higher `score`: more likely failure."""

    def __init__(self, l2: float = 1.0, iterations: int = 50):
        self.l2, self.iterations = float(l2), int(iterations)

    def fit(self, x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None) -> "Logistic":
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        w = np.ones(len(y)) if weights is None else np.asarray(weights, np.float64)
        self.mean = np.average(x, axis=0, weights=w)
        std = np.sqrt(np.average((x - self.mean) ** 2, axis=0, weights=w))
        self.std = np.where(std > 1e-12, std, 1.0)
        z = np.column_stack([np.ones(len(x)), (x - self.mean) / self.std])
        beta = np.zeros(z.shape[1])
        penalty = np.full(z.shape[1], self.l2)
        penalty[0] = 0.0
        for _ in range(self.iterations):
            p = 1 / (1 + np.exp(-np.clip(z @ beta, -30, 30)))
            gradient = z.T @ (w * (p - y)) + penalty * beta
            hessian = (z * (w * p * (1 - p))[:, None]).T @ z + np.diag(penalty + 1e-9)
            step = np.linalg.solve(hessian, gradient)
            beta -= step
            if np.max(np.abs(step)) < 1e-8:
                break
        self.beta = beta
        return self

    def score(self, x: np.ndarray) -> np.ndarray:
        """The log-odds of failure of each row (a monotone score; nan rows stay nan)."""
        x = np.asarray(x, np.float64)
        return self.beta[0] + ((x - self.mean) / self.std) @ self.beta[1:]


# ------------------------------------------------------------------------------------------- thresholds and steps


def calibrate(success_peaks, rate: float = FALSE_ALARM) -> float:
    """The threshold over which at most `rate` of the successful training episodes' peak scores lie (strictly): an
    episode is flagged at its first step with a score above it. inf without successes (nothing is flagged)."""
    peaks = np.sort(np.asarray([p for p in success_peaks if np.isfinite(p)], np.float64))[::-1]
    if not len(peaks):
        return math.inf
    allowed = int(math.floor(rate * len(peaks) + 1e-9))
    return float(peaks[allowed]) if allowed < len(peaks) else -math.inf


def first_flag(scores, threshold: float) -> int | None:
    """The index of the first score above `threshold`, None when none is."""
    above = np.flatnonzero(np.asarray(scores, np.float64) > threshold)
    return int(above[0]) if len(above) else None


def stall_step(phase, steps: int | None = None) -> int:
    """The step after which the episode made no more progress: the first step of the furthest phase it reached
    (phase indices by step, -1 for unknown). Without phases (None or no known index), the first step of the
    episode's last tenth."""
    phase = None if phase is None else np.asarray(phase, int)
    if phase is None or not len(phase) or (phase < 0).all():
        n = int(steps if steps is not None else (0 if phase is None else len(phase)))
        return int(math.floor(n * (1 - LAST_TENTH)))
    return int(np.flatnonzero(phase == phase.max())[0])


def robust_z(value: float, reference) -> float:
    """(value - median) / (MAD_SCALE * MAD) of the finite reference values; nan with fewer than 3 of them or no
    spread (a MAD of 0)."""
    ref = np.asarray([r for r in reference if np.isfinite(r)], np.float64)
    if len(ref) < 3 or not np.isfinite(value):
        return math.nan
    median = float(np.median(ref))
    mad = float(np.median(np.abs(ref - median))) * MAD_SCALE
    return (float(value) - median) / mad if mad > 0 else math.nan


def counted(successes: int, failures: int) -> str:
    """"7 successes, 1 failure": the two classes' counts in words."""
    return (f"{successes} success{'es' if successes != 1 else ''}, "
            f"{failures} failure{'s' if failures != 1 else ''}")
