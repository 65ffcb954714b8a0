"""The typed result of `compare` (harness.analysis.compare): what compare.json holds, read by attribute.

`CompareResult` is a frozen dataclass whose fields are compare.json's keys, with nested dataclasses for its blocks:
the arms (`Arm`), the IDENTICAL check (`IdenticalCheck`), the outcome tables (`Outcomes` of `OutcomeBlock`s, each arm's
`Rate`), the drift (`Drift`), what the protocols differ in (`Differs`), the provenance line (`Provenance`) and the
pairs (`PairDetail`); a grid comparison's folders (`GridInfo`) and a grid's own file (`RobustnessGrid`). `to_json()`
writes today's schema and `CompareResult.from_json(data)` reads a stored
compare.json back (harness.results). Verdicts are `harness.verdicts.GateVerdict`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from harness.analysis.paired import PairedCounts
from harness.results import ABSENT, Result
from harness.verdicts import GateVerdict

FORMAT = "octo-harness-compare/1"


@dataclass(frozen=True)
class CompareConfig(Result):
    max_drop: float = 0.1  # HELD needs the interval to rule out a drop larger than this
    alpha: float = 0.05  # family-wise level of the McNemar tests; intervals at 1 - alpha
    first_steps: int = 10  # per-step divergence over steps 0..first_steps-1
    atol: float = 0.0  # IDENTICAL: every paired array equal within this (0: bit-level)

    def __post_init__(self):
        if not 0 < self.alpha < 1:
            raise ValueError(f"--alpha must be in (0, 1), got {self.alpha}")
        if not 0 <= self.max_drop < 1:
            raise ValueError(f"--max-drop must be in [0, 1), got {self.max_drop}")
        if self.first_steps < 1:
            raise ValueError(f"--first-steps must be at least 1, got {self.first_steps}")


@dataclass(frozen=True)
class Rate(Result):
    """One arm's success rate over the pairs with an outcome in both arms, its Wilson interval, its errored episodes."""

    successes: int
    n: int
    rate: float | None
    ci_low: float | None
    ci_high: float | None
    errored: int = 0


@dataclass(frozen=True)
class OutcomeBlock(Result):
    """One outcome table (a task, or the pooled table): counts, intervals, tests and its verdict."""

    pairs: int  # pairs in which both arms ran to an outcome (n)
    errored_pairs: int
    paired_episodes: int
    table: PairedCounts
    baseline: Rate
    candidate: Rate
    difference: float | None  # candidate - baseline
    difference_ci: tuple[float | None, ...]
    difference_confidence: float
    mcnemar_p: float
    mcnemar_p_holm: float
    verdict: GateVerdict
    pairs_to_decide: int | None
    more_pairs_needed: int | None
    holm_factor: int
    regressed_reachable: bool
    pairs_for_regressed: int | None
    notes: tuple[str, ...]
    paired_verdict: GateVerdict = ABSENT  # the paired statistics' verdict before IDENTICAL (compare's result only)


@dataclass(frozen=True)
class Outcomes(Result):
    tasks: dict[str, OutcomeBlock]
    overall: OutcomeBlock  # the pooled table
    holm_family: int
    notes: tuple[str, ...]


@dataclass(frozen=True)
class Arm(Result):
    """One run of the comparison."""

    run: str
    path: str
    model: Any
    random_weights: bool
    status: str
    episodes: int
    missing_jobs: Any
    errors: int
    git_commit: str | None
    unverified: int
    arrays: str


@dataclass(frozen=True)
class MissingPairs(Result):
    """[task, seed] pairs finished by one arm only."""

    candidate: tuple[tuple, ...]  # run by the baseline only
    baseline: tuple[tuple, ...]  # run by the candidate only


@dataclass(frozen=True)
class OneSideMeasures(Result):
    """The probes (measures beside the actions) only one run took, by name: the other run cannot be compared on them."""

    baseline: tuple[str, ...]  # only the baseline measured these
    candidate: tuple[str, ...]  # only the candidate measured these


@dataclass(frozen=True)
class Incompleteness(Result):
    pairs: int
    tasks: dict[str, int]
    note: str


@dataclass(frozen=True)
class DerivedMeasures(Result):
    """Identical trajectories whose derived measures differ because their definition changed."""

    baseline_version: Any
    candidate_version: Any
    pairs: int
    first_difference: str
    note: str


@dataclass(frozen=True)
class IdenticalCheck(Result):
    identical: bool
    pairs_identical: int
    first_difference: str | None
    atol: float
    steps_compared: str
    derived_measures: DerivedMeasures | None


@dataclass(frozen=True)
class DriftBlock(Result):
    """Step-0 drift over a group of pairs (arrays stay numpy until written)."""

    pairs: int
    action_l2: float | None
    action_max_abs: float | None
    js_layer_head: Any  # (layers, heads) or None
    js_layer: Any  # (layers,) or None
    js_mean: float | None
    target_lift_change: dict[str, Any]  # {obs key: (layers,)}


@dataclass(frozen=True)
class Step0Drift(Result):
    tasks: dict[str, DriftBlock]
    overall: DriftBlock


@dataclass(frozen=True)
class StepDrift(Result):
    step: int
    pairs: int
    action_l2: float | None
    js_mean: float | None


@dataclass(frozen=True)
class WholeEpisodeDrift(Result):
    confounded: bool
    note: str
    action_l2: float | None
    js_mean: float | None
    pairs: int


@dataclass(frozen=True)
class Drift(Result):
    step0: Step0Drift
    first_steps: tuple[StepDrift, ...]
    whole_episode: WholeEpisodeDrift


@dataclass(frozen=True)
class DifferingField(Result):
    field: str
    baseline: Any
    candidate: Any


@dataclass(frozen=True)
class Differs(Result):
    """What the protocols of two comparable runs differ in (harness.analysis.compare.what_differs)."""

    model: bool
    other: tuple[DifferingField, ...]
    cause: str
    drift_label: str


@dataclass(frozen=True)
class Provenance(Result):
    """harness.analysis.provenance.provenance: platforms, inputs, step-0 numerics and the sentence a report leads with."""

    platform: dict
    inputs: dict
    step0_numerics: dict
    summary: str


@dataclass(frozen=True)
class PairDetail(Result):
    """One (task, seed) pair; the keys after `step0_js_mean` are in compare.json only where they were measured."""

    task: str
    seed: Any
    baseline_dir: str
    candidate_dir: str
    baseline_success: Any
    candidate_success: Any
    baseline_steps: Any
    candidate_steps: Any
    baseline_status: str
    candidate_status: str
    identical: bool
    difference: str | None
    step0_action_l2: float | None
    step0_js_mean: float | None
    compared_steps: int = ABSENT
    inputs: dict = ABSENT
    derived_difference: str | None = ABSENT
    action_max_abs_step0: float = ABSENT
    js_step0_max: float = ABSENT
    attention_note: str = ABSENT
    condition: str = ABSENT  # a grid comparison's condition


@dataclass(frozen=True)
class RobustnessGrid(Result):
    """A robustness grid's robustness.json (harness.gate.robustness writes it; compare and regress read it): {run
    folder name: --perturb or None (nominal)}, and what made it (absent from older or hand-made grid files)."""

    runs: dict[str, str | None]
    format: str = ABSENT
    conditions: tuple[str, ...] = ABSENT
    levels: tuple[int, ...] = ABSENT
    tasks: tuple[str, ...] = ABSENT
    regress_of: str = ABSENT  # a candidate grid made by regress: the baseline grid


@dataclass(frozen=True)
class GridInfo(Result):
    """A grid comparison's folders and conditions."""

    baseline: str
    candidate: str
    conditions: tuple[str, ...]
    cells: int
    perturb: dict[str, str | None]


@dataclass(frozen=True)
class CompareResult(Result):
    """compare.json (see harness.analysis.compare)."""

    format: str
    verdict: GateVerdict
    config: CompareConfig
    baseline: Arm
    candidate: Arm
    env: dict | None
    perturb: str | None
    pairs: int
    missing_pairs: MissingPairs
    incomplete: Incompleteness | None
    identical: IdenticalCheck
    outcomes: Outcomes
    drift: Drift
    differs: Differs
    provenance: Provenance
    pair_details: tuple[PairDetail, ...]
    grid: GridInfo = ABSENT  # compare_grids only
    one_side_measures: OneSideMeasures = ABSENT  # present when one run took measures the other did not
    exit_code: int | None = ABSENT  # written beside the result (harness.report.compare_html.write_comparison)
