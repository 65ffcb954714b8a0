"""Normalisation of low-dimensional observations (proprio) with a checkpoint's dataset statistics, as pure numpy.

Octo normalises proprio the way it normalises actions (octo.data.utils.data_utils and the
NormalizeProprio gym wrapper), honouring the statistics' `mask` (False = leave that dimension raw):
  "normal": (x - mean) / (std + 1e-8)
  "bounds": clip(2 (x - p01) / (p99 - p01 + 1e-8) - 1, -1, 1)
  "none":   x unchanged (a model trained on raw values)
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

NORMALIZATIONS = ("normal", "bounds", "none")
EPS = 1e-8


class NormalizationError(ValueError):
    """Statistics that cannot normalise the given values (message: one line naming the fix)."""


def normalize(x: np.ndarray, statistics: Mapping | None, kind: str = "normal", name: str = "proprio") -> np.ndarray:
    """x (..., dims) -> (..., dims) float32 normalised with `statistics` {mean, std | p01, p99, mask?} by `kind`."""
    if kind not in NORMALIZATIONS:
        raise NormalizationError(f"{name} normalization {kind!r} unknown; use one of {', '.join(NORMALIZATIONS)}")
    x = np.asarray(x, dtype=np.float32)
    if kind == "none":
        return x
    if statistics is None:
        raise NormalizationError(f"no dataset statistics for {name!r}; choose --dataset-key with {name} statistics "
                                 f"or proprio_normalization='none'")
    needed = ("mean", "std") if kind == "normal" else ("p01", "p99")
    missing = [k for k in needed if k not in statistics]
    if missing:
        raise NormalizationError(f"{name} statistics lack {missing} needed for {kind!r} normalization; "
                                 f"use the other normalization or add them to dataset_statistics.json")
    a, b = (np.asarray(statistics[k], dtype=np.float32) for k in needed)
    mask = np.asarray(statistics.get("mask", np.ones(a.shape, bool)), dtype=bool)
    if a.shape != (x.shape[-1],) or b.shape != a.shape or mask.shape != a.shape:
        raise NormalizationError(f"{name} has {x.shape[-1]} dims but its statistics have {a.shape[0] if a.ndim else 0}; "
                                 "the env's and the checkpoint's low-dim layouts differ")
    if kind == "normal":
        scaled = (x - a) / (b + EPS)
    else:
        scaled = np.clip(2 * (x - a) / (b - a + EPS) - 1, -1, 1)
    return np.where(mask, scaled, x).astype(np.float32)
