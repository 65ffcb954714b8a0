"""The options of the gates (`compare`, `regress`, `replay`) as one frozen value, each declared once on its field.

`GateConfig` travels whole through regress_grid -> regress -> replay_baseline -> replay_run and hands each test the
part it reads: `compare()` (harness.analysis.compare.CompareConfig), `sequential()`
(harness.analysis.sequential.SequentialConfig), `tolerances()` (harness.analysis.equivalence.Tolerances). A grid
of conditions splits alpha with `at(alpha)`. Values are checked where they are read (the config of each test), so
every error line stays that test's own.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from harness.analysis.compare import CompareConfig
from harness.analysis.equivalence import Tolerances
from harness.analysis.sequential import SequentialConfig
from harness.options import option
from harness.verdicts import DEFAULT_FAIL_ON, FAIL_ON  # --fail-on's choices, from the gate verdicts


@dataclass(frozen=True)
class GateConfig:
    max_drop: float = option(0.1, "--max-drop", "HELD rules out a larger drop in success rate", type=float)
    alpha: float = option(0.05, "--alpha", {
        "compare": "family-wise level; intervals at 1 - alpha",
        "regress": "family-wise level; each task's sequential test runs at alpha / tasks"}, type=float)
    first_steps: int = option(10, "--first-steps", "per-step divergence over the first k steps", type=int)
    fail_on: str = option(DEFAULT_FAIL_ON, "--fail-on", {
        "compare": "mildest verdict that exits 1: REGRESSED only; also SUSPECT (a drop the interval shows, the exact "
                   "test does not confirm); also UNDERPOWERED; anything but IDENTICAL",
        "regress": "mildest verdict that exits 1, as for compare; 'changed' also fails a candidate whose numbers on the "
                   "baseline's recorded inputs are not EQUIVALENT (replay): the gate for an unchanged model, on any "
                   "machine"}, choices=FAIL_ON)
    max_episodes: int | None = option(None, "--max-episodes", "at most N episodes per task", type=int,
                                     default_text="the baseline's")
    # the candidate's text tokenizer (regress, replay): auto|fallback|PATH; None: the baseline's (the run's) choice
    text_tokenizer: str | None = option(
        None, "--text-tokenizer", "the candidate's text tokenizer (as for `run --text-tokenizer`)",
        metavar="auto|fallback|PATH", default_text="the baseline's choice")
    # regress and replay inherit the baseline's probes (its measures beside the actions); True: run without them
    drop_probes: bool = option(
        False, "--drop-probes", "run the candidate without the baseline's probes (reliance, attribution, controls...: "
        "the measures taken beside the actions); the comparison names what only the baseline measured",
        action="store_true", default_text="the baseline's probes run")
    action_tolerance: float = option(
        Tolerances.action, "--action-tolerance",
        "largest change of an action chunk, in normalised action units", type=float)
    attention_tolerance: float = option(
        Tolerances.attention_js, "--attention-tolerance",
        "largest Jensen-Shannon divergence (bits) of a layer's and head's readout attention", type=float)

    @classmethod
    def from_args(cls, args) -> "GateConfig":
        """The options a command line gave (attributes of an argparse namespace; None or absent: the default)."""
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{n: getattr(args, n) for n in names if getattr(args, n, None) is not None})

    def at(self, alpha: float) -> "GateConfig":
        return dataclasses.replace(self, alpha=alpha)

    def compare(self) -> CompareConfig:
        return CompareConfig(max_drop=self.max_drop, alpha=self.alpha, first_steps=self.first_steps)

    def sequential(self) -> SequentialConfig:
        return SequentialConfig(alpha=self.alpha, max_drop=self.max_drop)

    def tolerances(self) -> Tolerances:
        return Tolerances(action=self.action_tolerance, attention_js=self.attention_tolerance)
