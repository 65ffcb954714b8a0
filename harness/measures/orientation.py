"""How well a rendered frame matches a checkpoint's example frame under each image convention (pure array maths).

The pre-flight check (harness/run/preflight.py) compares the first frame a run feeds a camera with the
checkpoint's example frame of that camera. The scene state differs (objects elsewhere, the arm in another pose),
so the measure must see the layout of the picture, not its details. Two measures are offered; the check uses
`MEASURE`, chosen from the margins measured on the reference checkpoints (scripts/preflight_margins.py):

- "grey": the Pearson correlation of heavily blurred grey images (area-averaged to `GREY_SIDE` px a side);
- "hog": the Pearson correlation of gradient-orientation histograms (signed orientation, magnitude-weighted,
  `HOG_CELLS` x `HOG_CELLS` cells of a grey image area-averaged to `HOG_SIDE` px).

Relative to upright, "opengl" reverses the rows and "rot180" the columns (envs.options.to_convention), so a
frame's orientations are three flips of one upright picture.
"""

from __future__ import annotations

import numpy as np

from envs.options import IMAGE_CONVENTIONS, to_convention

GREY_SIDE = 16
HOG_SIDE = 32
HOG_CELLS = 4
HOG_BINS = 8
MEASURES = ("grey", "hog")
MEASURE = "grey"
FLAT = 1.0  # grey-level std (0-255) under which a frame holds no picture (all zeros, one colour)


def grey(frame: np.ndarray) -> np.ndarray:
    """(height, width, 3) or (height, width) pixels -> (height, width) float64 luma (0-255)."""
    frame = np.asarray(frame, np.float64)
    return frame if frame.ndim == 2 else frame[..., :3] @ np.array([0.299, 0.587, 0.114])


def area_resize(image: np.ndarray, side: int) -> np.ndarray:
    """(height, width) -> (side, side), each output pixel the mean of the input pixels its area covers (a box
    filter; exact when the sizes divide, else by nearest bin edges)."""
    image = np.asarray(image, np.float64)
    rows = np.linspace(0, image.shape[0], side + 1).round().astype(int)
    cols = np.linspace(0, image.shape[1], side + 1).round().astype(int)
    summed = np.add.reduceat(np.add.reduceat(image, rows[:-1], axis=0), cols[:-1], axis=1)
    return summed / np.outer(np.diff(rows), np.diff(cols))


def is_flat(frame: np.ndarray) -> bool:
    """Whether a frame holds no picture: all zeros or one colour (a synthetic example batch)."""
    return float(np.std(grey(frame))) < FLAT


def grey_features(frame: np.ndarray) -> np.ndarray:
    """(height, width, 3) -> (GREY_SIDE**2,) blurred grey image."""
    return area_resize(grey(frame), GREY_SIDE).ravel()


def hog_features(frame: np.ndarray) -> np.ndarray:
    """(height, width, 3) -> (HOG_CELLS**2 * HOG_BINS,) magnitude-weighted histograms of signed gradient
    orientation per cell of the grey image at HOG_SIDE px."""
    image = area_resize(grey(frame), HOG_SIDE)
    gy, gx = np.gradient(image)
    magnitude = np.hypot(gx, gy)
    bins = ((np.arctan2(gy, gx) + np.pi) / (2 * np.pi) * HOG_BINS).astype(int) % HOG_BINS
    cell = HOG_SIDE // HOG_CELLS
    cells = (np.arange(HOG_SIDE) // cell)
    index = (cells[:, None] * HOG_CELLS + cells[None, :]) * HOG_BINS + bins
    return np.bincount(index.ravel(), magnitude.ravel(), HOG_CELLS * HOG_CELLS * HOG_BINS)


FEATURES = {"grey": grey_features, "hog": hog_features}


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equal-length vectors; 0.0 when either is constant."""
    a, b = np.asarray(a, np.float64) - np.mean(a), np.asarray(b, np.float64) - np.mean(b)
    norm = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b / norm) if norm > 0 else 0.0


def orientation_scores(example: np.ndarray, upright: np.ndarray, measure: str = MEASURE) -> dict[str, float]:
    """{convention: similarity of `example` (H, W, 3) to `upright` (h, w, 3) turned into that convention} for each
    of the harness's image conventions; sizes may differ (both are reduced to the measure's own size)."""
    features = FEATURES[measure]
    reference = features(example)
    return {c: correlation(reference, features(to_convention(upright, c))) for c in IMAGE_CONVENTIONS}
