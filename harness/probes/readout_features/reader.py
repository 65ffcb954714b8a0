"""The readout-features probe's file read back: readout_features.npz -> the pooled readout embedding by step (the
probe's reader; what a failure predictor fits on)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.runs import read_npz

FILE = "readout_features.npz"


def arrays(directory: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """An episode folder's readout_features.npz -> (steps (n,) int, features (n, width) float32), None without it."""
    path = Path(directory) / FILE
    if not path.is_file():
        return None
    stored = read_npz(path)
    return np.asarray(stored["step"], int), np.asarray(stored["features"], np.float32)


def by_step(directory: str | Path) -> dict[int, dict]:
    """{step: {"features": (width,) float32}} ({} without the file); stored as float16."""
    found = arrays(directory)
    if found is None:
        return {}
    steps, features = found
    return {int(step): {"features": features[i]} for i, step in enumerate(steps)}
