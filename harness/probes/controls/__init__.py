"""The attention-controls probe (--attention-controls, --controls-every): every N-th inferred step is asked again,
open loop, with every camera's window frames blanked to their mean colour and/or mirrored left-right
(harness.measures.controls); the readout attention of each control pass is the payload.

Payload: {control: (layers, heads, readouts, keys) float32}. The control requests of one call are batched in the
compiled batch shape, each with its request's own rng key (actions discarded). Files: controls.npz (`.sink`, read
back by `.reader`); the report's Position section reads it too (harness.analysis.position).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from harness.options import joined, option
from harness.probes.registry import Probe, ProbeContext


@dataclass(frozen=True)
class ControlsOptions:
    """The attention-controls probe's options (fields of harness.policy.PolicyConfig)."""

    # position-against-content controls (harness/measures/controls.py): every `controls_every`-th inference step is
    # asked again, open loop, with every camera's frames blanked to their mean colour / mirrored left-right; the
    # control attention goes to controls.npz. They do not change actions
    attention_controls: str | None = option(
        None, "--attention-controls", "position-against-content controls: ask the model each control step again with "
        "every camera's frames blanked to their mean colour and/or mirrored left-right; attention in controls.npz "
        "(docs/phases-and-position.md)", file=(str, list), metavar="blank,mirror", convert=joined, sparse=True)
    controls_every: int | None = option(  # None: 1 with --attention-controls, unset without
        None, "--controls-every", "run the attention controls at every N-th inference step",
        default_text="1 with --attention-controls", type=int, file=(int,), metavar="N", sparse=True)

    def check(self) -> None:
        """Validate (and complete) the fields on the assembled PolicyConfig; a ValueError names the flag."""
        if self.controls_every is not None and (isinstance(self.controls_every, bool) or
                                                not isinstance(self.controls_every, int) or self.controls_every < 1):
            raise ValueError(f"--controls-every must be an integer >= 1 (1: every inference step), got "
                             f"{self.controls_every!r}")
        if self.attention_controls is not None:
            from harness.measures.controls import parse_controls

            object.__setattr__(self, "attention_controls", ",".join(parse_controls(self.attention_controls)))
            if self.controls_every is None:
                object.__setattr__(self, "controls_every", 1)
        elif self.controls_every is not None:
            raise ValueError("--controls-every needs --attention-controls (e.g. --attention-controls blank,mirror)")


class ControlsProbe(Probe):
    name = "controls"
    option = "attention_controls"
    options = ControlsOptions
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
