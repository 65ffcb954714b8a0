"""Bootstrap confidence intervals of a mean over episodes: pure numpy, seeded, vectorised over many columns.

The unit of resampling is the episode (rows); every column (a metric at a layer, head or progress bin) is
resampled with the same draws, so columns keep their joint structure. NaN marks a value an episode does
not have (e.g. a target never visible): it is left out of that column's mean, in the estimate and in each
resample alike. Method: percentile bootstrap (Efron & Tibshirani 1993, ch. 13) with multinomial resample
counts, so the resample means are one matrix product values (columns, n) @ counts (n, resamples); the interval
ends are the order statistics floor((B-1)(1-c)/2) and ceil((B-1)(1+c)/2) of the B resample means (rounded
outward, no interpolation).
"""

from __future__ import annotations

import numpy as np

DEFAULT_RESAMPLES = 2000


def bootstrap_mean_ci(
    values: np.ndarray,
    confidence: float = 0.95,
    resamples: int = DEFAULT_RESAMPLES,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """values (episodes, ...) -> (mean, ci_low, ci_high, n), each (...).

    mean: NaN-ignoring mean over episodes; n: episodes with a value; (ci_low, ci_high): the percentile
    interval of the resampled means at `confidence`. With fewer than 2 values the interval is NaN (one
    episode says nothing about the spread), with no value the mean is NaN too. Same inputs and seed ->
    same interval; constant data -> a point interval.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be strictly between 0 and 1, got {confidence!r}")
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 0:
        raise ValueError("values must have an episode axis first: (episodes, ...)")
    episodes, shape = values.shape[0], values.shape[1:]
    flat = values.reshape(episodes, -1)  # (n, m)
    present = np.isfinite(flat)
    filled = np.where(present, flat, 0.0)
    n = present.sum(axis=0)  # (m,)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = filled.sum(axis=0) / n
    low = np.full(mean.shape, np.nan)
    high = np.full(mean.shape, np.nan)
    cols = np.flatnonzero(n >= 2)
    if cols.size:
        rng = np.random.default_rng(seed)
        counts32 = rng.multinomial(episodes, np.full(episodes, 1.0 / episodes), size=resamples).T.astype(np.float32)  # (n, B)
        full = cols[n[cols] == episodes]  # columns every episode has: means = values @ counts / n
        part = cols[n[cols] < episodes]
        k_low = int(np.floor((resamples - 1) * (1.0 - confidence) / 2.0))  # order statistics, rounded outward
        k_high = int(np.ceil((resamples - 1) * (1.0 + confidence) / 2.0))
        for block in (full, part):
            if not block.size:
                continue
            # (m', B) resample means in float32: ample for interval ends, half the memory traffic of the partition
            sums = filled[:, block].T.astype(np.float32) @ counts32
            if block is full:
                means = sums / np.float32(episodes)
            else:  # a resample may draw only episodes without a value: those resamples are left out of that column
                with np.errstate(invalid="ignore", divide="ignore"):
                    means = sums / (present[:, block].T.astype(np.float32) @ counts32)
            if np.isnan(means).any():
                qs = np.nanquantile(means, [k_low / (resamples - 1), k_high / (resamples - 1)], axis=1,
                                    method="nearest") if resamples > 1 else np.stack([means[:, 0]] * 2)
                low[block], high[block] = qs[0], qs[1]
            else:
                ordered = np.partition(means, sorted({k_low, k_high}), axis=1)
                low[block], high[block] = ordered[:, k_low], ordered[:, k_high]
        # constant columns: the interval is exactly the value (no floating-point spread from the matrix product)
        values_c = flat[:, cols]
        spread = np.where(present[:, cols], values_c, -np.inf).max(axis=0) - np.where(present[:, cols], values_c, np.inf).min(axis=0)
        constant = cols[spread == 0]
        low[constant] = high[constant] = mean[constant]
        inside = np.isfinite(low)  # float32 rounding must not put an interval end beyond the mean
        low[inside] = np.minimum(low[inside], mean[inside])
        high[inside] = np.maximum(high[inside], mean[inside])
    return mean.reshape(shape), low.reshape(shape), high.reshape(shape), n.reshape(shape)
