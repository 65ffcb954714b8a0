"""The typed results of the gate commands `regress` and `replay`: what regress.json and replay.json hold.

Each is a frozen dataclass whose fields are its file's keys (harness.results: `to_json()` writes today's schema,
`from_json(data)` reads a stored file back). `RegressResult` holds the comparison of the pairs run
(harness.analysis.compare_result.CompareResult, written beside it as compare.json) and the candidate's replay of the
baseline's recorded inputs (`ReplayResult`, without its episode details). Compare and regress verdicts are
`harness.verdicts.GateVerdict`; replay's are `harness.verdicts.ReplayVerdict`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from harness.analysis.compare_result import CompareResult, Incompleteness
from harness.analysis.equivalence import Tolerances
from harness.analysis.paired import PairedCounts
from harness.results import ABSENT, Result
from harness.verdicts import GateVerdict, ReplayVerdict

REPLAY_FORMAT = "octo-harness-replay/1"
REGRESS_FORMAT = "octo-harness-regress/2"
GRID_FORMAT = "octo-harness-regress-grid/1"  # regress_grid's result


@dataclass(frozen=True)
class ChangeAt(Result):
    """The change at an episode's first step beyond the tolerances."""

    action: float
    attention_js: float | None  # None: the replayed policy gives no attention


@dataclass(frozen=True)
class EpisodeReplay(Result):
    """One replayed episode; the keys after `attention_js_max` are in replay.json only where they were measured."""

    task: str
    episode: int
    seed: int
    steps: int
    compared_steps: int
    verdict: ReplayVerdict
    first_changed_step: int | None
    action_change_max: float | None
    attention_js_max: float | None
    action_change_step0: float = ABSENT
    attention_js_step0: float = ABSENT
    action_change_per_step: tuple[float, ...] = ABSENT
    attention_js_per_step: tuple[float, ...] = ABSENT
    change_at_first: ChangeAt = ABSENT
    note: str = ABSENT


@dataclass(frozen=True)
class FirstChange(Result):
    """The changed episode whose change comes first."""

    task: str
    episode: int
    first_changed_step: int | None
    change_at_first: ChangeAt | None
    note: str | None


@dataclass(frozen=True)
class ReplayResult(Result):
    """replay.json (harness.gate.replay.replay_run)."""

    format: str
    verdict: ReplayVerdict
    run: str
    recorded_model: Any
    recorded_model_fingerprint: Any
    model: str
    tolerances: Tolerances
    units: dict[str, str]
    platform_recorded: Any
    episodes: int
    episodes_changed: int
    steps_compared: int
    action_change_max: float | None
    attention_js_max: float | None
    first_change: FirstChange | None
    episode_details: tuple[EpisodeReplay, ...] = ABSENT  # left out where regress keeps the replay


@dataclass(frozen=True)
class EValues(Result):
    """The e-values of a task's three sequential tests."""

    regression: float
    improvement: float
    held: float


@dataclass(frozen=True)
class TaskSequential(Result):
    """One task's sequential test (harness.analysis.sequential.SequentialTest.summary, with its errored pairs)."""

    units: int
    verdict: GateVerdict
    decided: bool
    threshold: float
    e_values: EValues
    alpha: float
    max_drop: float
    errored_pairs: int


@dataclass(frozen=True)
class SequentialSummary(Result):
    """The per-task sequential test of a regress run (harness.analysis.sequential.TaskwiseTest.summary)."""

    verdict: GateVerdict
    decided: bool
    rounds: int
    alpha: float
    task_alpha: float
    max_drop: float
    threshold: float
    tasks: dict[str, TaskSequential]
    errored_tasks: tuple[str, ...] = ABSENT  # tasks whose candidate errored on more than half of its pairs


@dataclass(frozen=True)
class RegressResult(Result):
    """regress.json (harness.gate.regress.regress); `compare` is written beside it as compare.json."""

    format: str
    verdict: GateVerdict
    incomplete: Incompleteness | None
    sequential_verdict: GateVerdict
    compare_verdict: GateVerdict
    sequential: SequentialSummary
    pairs_used: int
    errored_pairs: int
    rounds_used: int
    baseline_pairs: int
    fixed_size_pairs_80_power: int | None
    fixed_size_pairs_80_power_tasks: dict[str, int | None]
    fixed_size_note: str
    table: PairedCounts
    baseline_run: str
    candidate_run: str
    candidate_status: str
    replay: ReplayResult | None
    compare: CompareResult = ABSENT  # in memory; regress.json names its file instead (compare_json)
    exit_code: int = ABSENT
    compare_json: str = ABSENT


@dataclass(frozen=True)
class ConditionRegress(Result):
    """One condition of a grid regression."""

    verdict: GateVerdict
    sequential_verdict: GateVerdict
    compare_verdict: GateVerdict
    pairs_used: int
    candidate_run: str
    alpha: float


@dataclass(frozen=True)
class RegressGridResult(Result):
    """regress.json of a grid regression (harness.gate.regress.regress_grid)."""

    format: str
    verdict: GateVerdict
    conditions: dict[str, ConditionRegress]
    compare_verdict: GateVerdict
    baseline_grid: str
    candidate_run: str
    compare: CompareResult = ABSENT
    exit_code: int = ABSENT
    compare_json: str = ABSENT
