"""Position against content: is a hot patch about the scene at all? Pure numpy, no files.

A run with `--attention-controls blank,mirror --controls-every N` asks the model the same step again, open loop
on that step's own inputs (same rng, same batch shape), with every camera's frames changed
(harness.measures.controls):

  blank    each frame of the window replaced by its own mean colour (no content at all)
  mirror   each frame of the window mirrored left-right (the content moves to the mirror-image patch)

and stores the readout attention of those passes (controls.npz). From the attention maps of a camera (readout
rows averaged; per head and head mean), averaged over the control steps (`patch_means`):

  real       the attention a patch gets on the real frames
  blank      what it gets on the blank frames
  mirrored   what the same patch (same position) gets on the mirrored frames
  followed   what the mirror-image patch (row, cols-1-col) gets on the mirrored frames: where content-bound
             attention goes

The flag rule (`flag_position_bound`): a patch is position-bound when it is hot (real >= HOT x the camera's mean
patch attention), at least KEEP of its attention remains without content (blank >= KEEP x real) and at least
KEEP of it stays in place when the content is mirrored (mirrored >= KEEP x real). Attention that follows the
content fails the second test (the blank frame has nothing to follow) or the third (it moves to the mirror-image
patch). `remaining_share` is the share of a camera's attention that remains without content,
sum min(blank, real) / sum real; `content_only` removes the positional part from a map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HOT = 2.0  # a patch is hot when its attention is at least this multiple of the camera's mean patch attention
KEEP = 0.5  # ... and position-bound when at least this share of it remains blank and stays under the mirror


@dataclass(frozen=True)
class PatchMeans:
    """Per camera: (layers, heads + 1, rows, cols) mean attention over control steps; head index `heads` = head mean."""

    real: np.ndarray
    blank: np.ndarray
    mirrored: np.ndarray
    followed: np.ndarray
    steps: int


def with_head_mean(maps: np.ndarray) -> np.ndarray:
    """(..., layers, heads, rows, cols) -> (..., layers, heads + 1, rows, cols): the head mean appended last."""
    return np.concatenate([maps, maps.mean(axis=-3, keepdims=True)], axis=-3)


def patch_means(real: np.ndarray, blank: np.ndarray, mirror: np.ndarray) -> PatchMeans:
    """Camera maps (steps, layers, heads, rows, cols) of the real, blank and mirrored passes -> PatchMeans.

    Steps are the control steps (of one or many episodes); maps are raw readout attention (readouts averaged).
    """
    real, blank, mirror = (np.asarray(x, np.float64) for x in (real, blank, mirror))
    if not real.shape == blank.shape == mirror.shape or real.ndim != 5:
        raise ValueError(f"maps must be (steps, layers, heads, rows, cols) of one shape; got {real.shape}, "
                         f"{blank.shape}, {mirror.shape}")
    mean = lambda x: with_head_mean(x.mean(axis=0))  # noqa: E731
    return PatchMeans(mean(real), mean(blank), mean(mirror), mean(mirror[..., ::-1]), int(real.shape[0]))


def flag_position_bound(real: np.ndarray, blank: np.ndarray, mirrored: np.ndarray, hot: float = HOT,
                        keep: float = KEEP) -> np.ndarray:
    """(..., rows, cols) mean maps -> (..., rows, cols) bool: hot, remains blank and stays under the mirror."""
    real, blank, mirrored = (np.asarray(x, np.float64) for x in (real, blank, mirrored))
    mean_patch = real.mean(axis=(-2, -1), keepdims=True)
    is_hot = (real > 0) & (real >= hot * mean_patch)
    return is_hot & (blank >= keep * real) & (mirrored >= keep * real)


def remaining_share(real: np.ndarray, blank: np.ndarray) -> np.ndarray:
    """(..., rows, cols) -> (...): sum_p min(blank_p, real_p) / sum_p real_p (nan without attention)."""
    real, blank = np.asarray(real, np.float64), np.asarray(blank, np.float64)
    total = real.sum(axis=(-2, -1))
    kept = np.minimum(real, blank).sum(axis=(-2, -1))
    return np.divide(kept, total, out=np.full_like(total, np.nan), where=total > 0)


def flagged_share(real: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """(..., rows, cols) -> (...): the share of the camera's real attention on flagged patches."""
    real = np.asarray(real, np.float64)
    total = real.sum(axis=(-2, -1))
    return np.divide((real * flags).sum(axis=(-2, -1)), total, out=np.full_like(total, np.nan), where=total > 0)


def content_only(real: np.ndarray, blank: np.ndarray) -> np.ndarray:
    """(..., rows, cols) -> the content-only view: max(real - blank, 0), renormalised to the real map's camera mass
    (all zero where nothing is left)."""
    real, blank = np.asarray(real, np.float64), np.asarray(blank, np.float64)
    rest = np.clip(real - blank, 0.0, None)
    scale = np.divide(real.sum(axis=(-2, -1), keepdims=True), rest.sum(axis=(-2, -1), keepdims=True),
                      out=np.zeros(real.shape[:-2] + (1, 1)), where=rest.sum(axis=(-2, -1), keepdims=True) > 0)
    return rest * scale


def mask_lift(maps: np.ndarray, fraction: np.ndarray) -> np.ndarray:
    """maps (..., rows, cols), fraction (..., rows, cols) patch coverage of a mask -> (...) mass inside / area
    (area: the mean coverage; nan without attention, without mask pixels or where coverage is nan)."""
    maps, fraction = np.asarray(maps, np.float64), np.asarray(fraction, np.float64)
    total = maps.sum(axis=(-2, -1))
    area = fraction.mean(axis=(-2, -1))
    inside = (maps * fraction).sum(axis=(-2, -1))
    ok = (total > 0) & (area > 0) & np.isfinite(area)
    return np.divide(inside, total * np.where(ok, area, 1.0), out=np.full(np.broadcast_shapes(total.shape, area.shape),
                                                                          np.nan), where=ok)
