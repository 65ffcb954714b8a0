"""The region-reliance probe (--reliance-every, --reliance-fill): every N-th inferred step, each labelled region of
every camera replaced by the fill, open loop with the step's rng, and the action chunk's change
(harness.probes.reliance.measure.RelianceProbe, sharing the attribution probe's compiled functions when both run).

Payload: {"rows": [one per camera x region], "seconds"}; it needs the env's masks at its steps. Files: reliance.jsonl
(`.sink`); read back by `.reader`; report: the Reliance section; viewer: the reliance map over each frame and each
region's share (`.viewer`).
"""

from __future__ import annotations

from dataclasses import dataclass

from harness.options import option
from harness.probes.registry import Probe, ProbeContext


@dataclass(frozen=True)
class RelianceOptions:
    """The reliance probe's options (fields of harness.policy.PolicyConfig)."""

    # region reliance (harness/probes/reliance/measure.py): each labelled region of every camera replaced by the fill, open
    # loop with the step's rng, the action chunk's change recorded in reliance.jsonl; needs the env's masks
    reliance_every: int = option(
        0, "--reliance-every", "region reliance every N-th step: each labelled region (target, gripper, goal, "
        "distractors, background...) of every camera replaced by --reliance-fill, and how much the predicted action "
        "chunk changes, in reliance.jsonl", default_text="{} = never", type=int, file=(int,), metavar="N", sparse=True)
    reliance_fill: str = option(
        "impute", "--reliance-fill", "what a replaced region becomes for --reliance-every: the frame's mean colour, a "
        "blur of the frame, or noisy linear imputation from the surrounding pixels", file=(str,),
        choices=("mean", "blur", "impute"), sparse=True)

    def check(self) -> None:
        """Validate (and complete) the fields on the assembled PolicyConfig; a ValueError names the flag."""
        if isinstance(self.reliance_every, bool) or not isinstance(self.reliance_every, int) or self.reliance_every < 0:
            raise ValueError(f"--reliance-every must be an integer >= 0 (0 = never), got {self.reliance_every!r}")
        if self.reliance_fill not in ("mean", "blur", "impute"):
            raise ValueError(f"--reliance-fill must be 'mean', 'blur' or 'impute', got {self.reliance_fill!r}")


class RelianceProbe(Probe):
    name = "reliance"
    option = "reliance_every"
    needs_masks = True
    masks_error = "--reliance-every needs the env's masks at every reliance step; drop --no-masks"
    options = RelianceOptions
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
