"""The controls probe's file read back: controls.npz -> {step: {control: (layers, heads, readouts, keys) float32}}, as
a step record carries them (the probe's reader; the report's Position section reads the file with its own
measures, harness.analysis.position)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.runs import read_npz

FILE = "controls.npz"


def by_step(directory: str | Path) -> dict[int, dict]:
    """An episode folder's controls.npz -> {step: {control: (layers, heads, readouts, keys) float32}} ({} without the
    file); the arrays are stored as float16."""
    path = Path(directory) / FILE
    if not path.is_file():
        return {}
    arrays = read_npz(path)
    names = [name for name in arrays if name != "step"]
    return {int(step): {name: np.asarray(arrays[name][i], np.float32) for name in names}
            for i, step in enumerate(np.asarray(arrays.get("step", []), int))}
