"""The region-reliance probe (--reliance-every, --reliance-fill): every N-th inferred step, each labelled region of
every camera replaced by the fill, open loop with the step's rng, and the action chunk's change
(harness.probes.reliance.measure.RelianceProbe, sharing the attribution probe's compiled functions when both run).

Payload: {"rows": [one per camera x region], "seconds"}; it needs the env's masks at its steps. Files: reliance.jsonl
(`.sink`); read back by `.reader`; report: the Reliance section; viewer: the reliance map over each frame and each
region's share (`.viewer`).
"""

from __future__ import annotations

from harness.probes import Probe, ProbeContext


class RelianceProbe(Probe):
    name = "reliance"
    option = "reliance_every"
    needs_masks = True
    masks_error = "--reliance-every needs the env's masks at every reliance step; drop --no-masks"
    sink = ".sink:RelianceLines"
    reader = ".reader"
    section = ".report:Section"
    layer = ".viewer:RelianceLayer"

    def __init__(self, context: ProbeContext):
        from harness.probes.reliance.measure import RelianceProbe as Regions

        super().__init__(context)
        config = context.config
        self.regions = Regions(context.model, config.reliance_every, config.reliance_fill,
                               context.shared.get("functions"))

    @classmethod
    def every(cls, config) -> int:
        return int(config.reliance_every)

    def run(self, batch, context):
        out = []
        for request in (item.request for item in batch):
            if request.masks is None:  # a warm-up request has none
                out.append(None)
                continue
            observations, tasks, keys = context.inputs([request])
            out.append(self.regions(observations, tasks, keys[0], request.seed, request.step, request.masks))
        return out
