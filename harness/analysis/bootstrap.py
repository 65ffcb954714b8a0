"""Bootstrap confidence intervals of a mean over episodes: pure numpy, seeded, vectorised over many columns.

The unit of resampling is the episode (rows); every column (a metric at a layer, head or progress bin) is
resampled with the same draws, so columns keep their joint structure. NaN marks a value an episode does
not have (e.g. a target never visible): it is left out of that column's mean, in the estimate and in each
resample alike. Method: percentile bootstrap (Efron & Tibshirani 1993, ch. 13) with multinomial resample
counts, so the resample means are one matrix product counts (resamples, n) @ values (n, columns).
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
    enough = n >= 2
    if episodes >= 2 and enough.any():
        rng = np.random.default_rng(seed)
        counts = rng.multinomial(episodes, np.full(episodes, 1.0 / episodes), size=resamples).astype(np.float64)  # (B, n)
        cols = np.flatnonzero(enough)
        sums = counts @ filled[:, cols]  # (B, m')
        weights = counts @ present[:, cols].astype(np.float64)  # (B, m') episodes drawn that have a value
        with np.errstate(invalid="ignore", divide="ignore"):
            means = sums / weights
        tail = (1.0 - confidence) / 2.0
        if np.isnan(means).any():  # some resamples drew only episodes without a value for a column
            qs = np.nanquantile(means, [tail, 1.0 - tail], axis=0)
        else:
            qs = np.quantile(means, [tail, 1.0 - tail], axis=0)
        low[cols], high[cols] = qs[0], qs[1]
        # constant columns: the interval is exactly the value (no floating-point spread from the matrix product)
        spread = np.nanmax(np.where(present[:, cols], flat[:, cols], np.nan), axis=0) - np.nanmin(
            np.where(present[:, cols], flat[:, cols], np.nan), axis=0)
        constant = spread == 0
        low[cols[constant]] = high[cols[constant]] = mean[cols[constant]]
    return mean.reshape(shape), low.reshape(shape), high.reshape(shape), n.reshape(shape)
