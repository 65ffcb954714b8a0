"""The action-consistency probe's file: action_consistency.npz, computed here from the chunks the step records carry
(the sink of harness.probes.action_consistency; why here: the probe's docstring)."""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.files import write_atomic
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink
from harness.probes.action_consistency.measure import PARTS, ChunkHistory

FILE = "action_consistency.npz"


class ConsistencyArrays(Sink):
    """action_consistency.npz (--action-consistency), at the probed steps (n): step (n,) int32; disagreement (n,),
    dims (n, d), by_age (n, H - 1) float32 (nan without an overlapping earlier chunk; measure.disagreement); for 7-D
    actions translation, rotation, gripper (n,) float32; with --action-samples, samples (n,) int32, spread (n,) and
    spread_dims (n, d) float32. Every inferred chunk is kept (the last H - 1 steps'), probed or not; nothing is written
    when no step is probed."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.history = ChunkHistory()
        self.rows: list[dict] = []

    def add(self, step: FinishedStep) -> None:
        record = step.record
        if not record.inferred:  # a receding-horizon step executing a stored chunk: no new plan
            return
        self.history.add(step.step, record.actions_predicted)
        payload = record.probes.get("action_consistency")
        if payload is None:
            return
        row = {"step": step.step, **self.history.at(step.step)}
        if payload.get("samples"):
            row.update(samples=int(payload["samples"]), spread=float(payload["spread"]),
                       spread_dims=np.asarray(payload["spread_dims"], np.float32))
        self.rows.append(row)

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        if not self.rows:
            return {}
        rows = self.rows
        arrays = {"step": np.asarray([r["step"] for r in rows], np.int32),
                  "disagreement": np.asarray([r["disagreement"] for r in rows], np.float32),
                  "dims": np.stack([r["dims"] for r in rows]).astype(np.float32),
                  "by_age": np.stack([r["by_age"] for r in rows]).astype(np.float32)}
        if arrays["dims"].shape[1] == 7:
            for name, where in PARTS.items():
                arrays[name] = arrays["dims"][:, where].mean(axis=1)
        if any("samples" in r for r in rows):
            dim = arrays["dims"].shape[1]
            arrays["samples"] = np.asarray([r.get("samples", 0) for r in rows], np.int32)
            arrays["spread"] = np.asarray([r.get("spread", np.nan) for r in rows], np.float32)
            arrays["spread_dims"] = np.stack([r.get("spread_dims", np.full(dim, np.nan, np.float32))
                                              for r in rows]).astype(np.float32)
        write_atomic(self.dir / FILE, lambda f: np.savez(f, **arrays))
        return {"action_consistency": FILE}
