"""The attribution probe (--attribution, --faithfulness-every): attribution maps of every method at every inferred
step, and open-loop faithfulness every k-th step (harness.measures.attribution.Probe, harness.measures.faithfulness).

Payload: {"maps": {method: {obs key: (rows, cols) float32}}, "faithfulness": [rows], "seconds"}. Its compiled
functions (`shared["functions"]`) are lent to the reliance probe of the same inference. Files: attribution.npz and
faithfulness.jsonl (`.sink`); report: the Faithfulness section; viewer: a map per method over each frame.
"""

from __future__ import annotations

from dataclasses import dataclass

from harness.options import joined, option
from harness.probes.registry import Probe, ProbeContext


@dataclass(frozen=True)
class AttributionOptions:
    """The attribution probe's options (fields of harness.policy.PolicyConfig)."""

    # attribution maps at every inference step (harness/measures/attribution.py: "attention,rollout,grad-attention,
    # saliency"; random is always added) and open-loop faithfulness every k-th step (0 = never), deleted patches
    # filled with "mean", "blur" or "impute" (ROAD's noisy linear imputation). They do not change actions
    attribution: str | None = option(
        None, "--attribution", "store attribution maps at every inference step in attribution.npz: comma-separated "
        "attention (every layer; attention:L one), rollout, grad-attention, saliency; random is always added",
        file=(str, list), metavar="METHODS", convert=joined, sparse=True)
    faithfulness_every: int = option(
        0, "--faithfulness-every", "open-loop faithfulness (deletion/insertion curves, top/random/bottom-k) of every "
        "attribution method every K-th step, in faithfulness.jsonl", default_text="{} = never; methods default to all",
        type=int, file=(int,), metavar="K", sparse=True)
    faithfulness_fill: str = option(
        "mean", "--faithfulness-fill", "what a deleted patch becomes in the faithfulness curves: the frame's mean "
        "colour, a blur of the frame, or noisy linear imputation from the surrounding pixels (ROAD; in distribution, "
        "no shape leak)", file=(str,), choices=("mean", "blur", "impute"), sparse=True)

    def check(self) -> None:
        """Validate (and complete) the fields on the assembled PolicyConfig; a ValueError names the flag."""
        if isinstance(self.faithfulness_every, bool) or not isinstance(self.faithfulness_every, int) \
                or self.faithfulness_every < 0:
            raise ValueError(f"--faithfulness-every must be an integer >= 0 (0 = never), got {self.faithfulness_every!r}")
        if self.faithfulness_fill not in ("mean", "blur", "impute"):
            raise ValueError(f"--faithfulness-fill must be 'mean', 'blur' or 'impute', got {self.faithfulness_fill!r}")
        if self.faithfulness_every and self.attribution is None:
            from harness.measures.attribution import DEFAULT_METHODS

            object.__setattr__(self, "attribution", DEFAULT_METHODS)
        if self.attribution is not None:
            from harness.measures.attribution import parse_methods

            parse_methods(self.attribution, 1 << 16)  # names checked here; layers against the model at start


class AttributionProbe(Probe):
    name = "attribution"
    option = "attribution"
    options = AttributionOptions
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
