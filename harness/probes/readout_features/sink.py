"""The readout-features probe's file: readout_features.npz, the pooled readout embedding at its steps (the sink of
harness.probes.readout_features)."""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.files import write_atomic
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink

FILE = "readout_features.npz"


class ReadoutArrays(Sink):
    """readout_features.npz (--readout-features-every): step (n,) int32, features (n, width) float16 at the probed
    steps; not written when no step carries features. Every step's features must have the first one's width."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.rows: list[tuple[int, np.ndarray]] = []

    def add(self, step: FinishedStep) -> None:
        payload = step.record.probes.get("readout_features")
        if payload is None:
            return
        features = np.asarray(payload["features"], np.float32).reshape(-1)
        if self.rows and features.shape != self.rows[0][1].shape:
            raise ValueError(f"step {step.step}: readout features have {features.size} values, the episode started "
                             f"with {self.rows[0][1].size}")
        self.rows.append((step.step, features.astype(np.float16)))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        if not self.rows:
            return {}
        arrays = {"step": np.asarray([s for s, _ in self.rows], np.int32),
                  "features": np.stack([f for _, f in self.rows])}
        write_atomic(self.dir / FILE, lambda f: np.savez(f, **arrays))
        return {"readout_features": FILE}
