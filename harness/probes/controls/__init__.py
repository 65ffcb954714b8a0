"""The attention-controls probe (--attention-controls, --controls-every): every N-th inferred step is asked again,
open loop, with every camera's window frames blanked to their mean colour and/or mirrored left-right
(harness.measures.controls); the readout attention of each control pass is the payload.

Payload: {control: (layers, heads, readouts, keys) float32}. The control requests of one call are batched in the
compiled batch shape, each with its request's own rng key (actions discarded). Files: controls.npz (`.sink`, read
back by `.reader`); the report's Position section reads it too (harness.analysis.position).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from harness.probes import Probe, ProbeContext


class ControlsProbe(Probe):
    name = "controls"
    option = "attention_controls"
    sink = ".sink:ControlArrays"
    reader = ".reader"

    def __init__(self, context: ProbeContext):
        from harness.measures.controls import CONTROLS, parse_controls

        super().__init__(context)
        self.transforms = {name: CONTROLS[name] for name in parse_controls(context.config.attention_controls)}

    @classmethod
    def every(cls, config) -> int:
        return int(config.controls_every) if config.attention_controls is not None else 0

    def run(self, batch, context):
        by_control = self.attention([item.request for item in batch], context)
        return [{name: values[j] for name, values in by_control.items()} for j in range(len(batch))]

    def attention(self, requests: list, context: ProbeContext, transforms: dict | None = None) -> dict[str, np.ndarray]:
        """{name: (len(requests), layers, heads, readouts, keys) float32}: the requests' readout attention with every
        camera's window frames under `transforms[name]` ((..., H, W, 3) -> same; default: the probe's controls), each
        as its own forward pass of the compiled batch shape with the request's own rng key (actions discarded)."""
        out = {}
        size = context.batch_size
        for name, transform in (self.transforms if transforms is None else transforms).items():
            changed = [dataclasses.replace(r, observation={k: (transform(v) if k.startswith("image_") else v)
                                                           for k, v in r.observation.items()}) for r in requests]
            rows = []
            for i in range(0, len(changed), size):
                part = changed[i:i + size]
                _, attention = context.sample(*context.inputs(part + [part[0]] * (size - len(part))))
                rows.append(np.asarray(attention.readout, dtype=np.float32)[:len(part)])
            out[name] = np.concatenate(rows)
        return out
