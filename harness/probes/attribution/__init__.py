"""The attribution probe (--attribution, --faithfulness-every): attribution maps of every method at every inferred
step, and open-loop faithfulness every k-th step (harness.measures.attribution.Probe, harness.measures.faithfulness).

Payload: {"maps": {method: {obs key: (rows, cols) float32}}, "faithfulness": [rows], "seconds"}. Its compiled
functions (`shared["functions"]`) are lent to the reliance probe of the same inference. Files: attribution.npz and
faithfulness.jsonl (`.sink`); report: the Faithfulness section; viewer: a map per method over each frame.
"""

from __future__ import annotations

from harness.probes import Probe, ProbeContext


class AttributionProbe(Probe):
    name = "attribution"
    option = "attribution"
    sink = ".sink:AttributionFiles"
    reader = ".reader"
    section = "harness.report.sections:Faithfulness"
    layer = ".viewer:AttributionLayer"

    def __init__(self, context: ProbeContext):
        from harness.measures.attribution import Probe as Maps

        super().__init__(context)
        config = context.config
        self.maps = Maps(context.model, config.attribution, config.faithfulness_every, config.faithfulness_fill)
        context.shared.setdefault("functions", self.maps.functions)

    def run(self, batch, context):
        out = []
        for request in (item.request for item in batch):
            observations, tasks, keys = context.inputs([request])
            out.append(self.maps(observations, tasks, keys[0], request.seed, request.step))
        return out

    @staticmethod
    def upright(payload, flip):
        maps = {m: {k: flip(k, v) for k, v in by.items()} for m, by in payload["maps"].items()}
        return {**payload, "maps": maps}
