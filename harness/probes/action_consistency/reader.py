"""The action-consistency probe's file read back: action_consistency.npz by step; and the same measure computed from
any episode's actions.npz (`from_actions`), for runs made without the probe (served policies included)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from harness.analysis.runs import read_npz
from harness.probes.action_consistency.measure import episode

FILE = "action_consistency.npz"


def arrays(directory: str | Path) -> dict[str, np.ndarray] | None:
    """An episode folder's action_consistency.npz as {name: array} (the sink's fields), None without it."""
    path = Path(directory) / FILE
    return read_npz(path) if path.is_file() else None


def by_step(directory: str | Path) -> dict[int, dict]:
    """{step: {"disagreement": float, "dims": (d,), "by_age": (H - 1,), and translation / rotation / gripper, samples
    / spread / spread_dims where stored}} ({} without the file)."""
    stored = arrays(directory)
    if stored is None:
        return {}
    names = [name for name in stored if name != "step"]
    out = {}
    for i, step in enumerate(np.asarray(stored["step"], int)):
        row = {name: stored[name][i] for name in names}
        out[int(step)] = {k: (float(v) if np.ndim(v) == 0 and k != "samples" else int(v) if k == "samples" else v)
                          for k, v in row.items()}
    return out


def from_actions(directory: str | Path) -> dict[str, np.ndarray]:
    """The disagreement at every inferred step of an episode from its actions.npz (measure.episode: step,
    disagreement, dims, by_age), whether or not the run had --action-consistency."""
    stored = read_npz(Path(directory) / "actions.npz", "step", "predicted", "inferred")
    return episode(np.asarray(stored["step"], int), stored["predicted"], stored.get("inferred"))
