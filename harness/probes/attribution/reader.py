"""The attribution probe's files read back: attribution.npz -> {step: {"maps": {method: {obs key: (rows, cols)}}}},
as a step record carries them (`view`'s rebuild of a recording from a run's files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.runs import read_npz

FILE = "attribution.npz"


def by_step(directory: str | Path) -> dict[int, dict]:
    """An episode folder's attribution.npz -> {step: {"maps": {method: {obs key: (rows, cols) float32}}}} ({} without
    the file)."""
    path = Path(directory) / FILE
    if not path.is_file():
        return {}
    arrays = read_npz(path)
    out: dict[int, dict] = {}
    for i, step in enumerate(np.asarray(arrays.get("step", []), int)):
        maps: dict[str, dict[str, np.ndarray]] = {}
        for name, value in arrays.items():
            if name.startswith("map/"):
                _, method, key = name.split("/", 2)
                maps.setdefault(method, {})[key] = value[i]
        out[int(step)] = {"maps": maps}
    return out
