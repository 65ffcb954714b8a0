"""The controls probe's file: controls.npz, the attention of the control inferences (--attention-controls) at their
steps (the sink of harness.probes.controls)."""

from __future__ import annotations

from typing import Any

import numpy as np

from harness.files import write_atomic
from harness.outputs.steps import EpisodeEnd, FinishedStep, Sink


class ControlArrays(Sink):
    """controls.npz (--attention-controls): step (n,), <control> (n, layers, heads, readouts, keys) float16 at the
    control steps; a control's attention must have the step's shape and be present at every control step."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.controls: list[tuple[int, dict]] = []  # (step, {control: (layers, heads, readouts, keys)})

    def add(self, step: FinishedStep) -> None:
        record = step.record
        controls = record.probes.get("controls")
        if not controls:
            return
        for name, value in controls.items():
            if np.shape(value) != step.attention.shape:
                raise ValueError(f"step {record.step}: control {name!r} attention has shape {np.shape(value)}, "
                                 f"the step's attention {step.attention.shape}")
        self.controls.append((record.step, {k: np.asarray(v, np.float32).astype(np.float16)
                                            for k, v in controls.items()}))

    def close(self, end: EpisodeEnd) -> dict[str, Any]:
        if not self.controls:
            return {}
        controls = {"step": np.asarray([s for s, _ in self.controls], np.int32)}
        for name in dict.fromkeys(k for _, c in self.controls for k in c):
            if any(name not in c for _, c in self.controls):
                raise ValueError(f"control {name!r} is missing at some control steps")
            controls[name] = np.stack([c[name] for _, c in self.controls])
        write_atomic(self.dir / "controls.npz", lambda f: np.savez(f, **controls))
        return {"controls": "controls.npz"}
