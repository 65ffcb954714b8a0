"""Anytime-valid sequential test on paired outcomes: stop a regression run as soon as the evidence decides.

Pure functions and a small accumulator; nothing here runs episodes. Written from the published
descriptions of testing by betting (Shafer 2021, J. R. Stat. Soc. A 184:407; Waudby-Smith & Ramdas 2024,
J. R. Stat. Soc. B 86:1) and of mixture sequential probability ratio tests (Robbins 1970).

Data: a stream of units y_i in [-1, 1], the candidate's success minus the baseline's on one pair
(+1 candidate-only success, -1 baseline-only success, 0 concordant), or the mean of that over one round of
pairs (one seed of every task), so that several tasks weigh equally. mu = E[y] is the difference of
success rates (candidate - baseline).

Three one-sided nulls, each tested by a bettor whose wealth starts at 1 and is multiplied after every
unit by 1 + lambda * z_i with a fixed bet lambda >= 0:

    regression   H0: mu >= 0          z = -y           lambda in (0, 1)
    improvement  H0: mu <= 0          z = y            lambda in (0, 1)
    held         H0: mu <= -max_drop  z = y + max_drop lambda in (0, 1 / (1 - max_drop))

Under its null each factor has expectation 1 + lambda E[z] <= 1, so the wealth is a nonnegative
supermartingale, and so is the average of the wealths over a grid of bets (a discrete uniform prior on
lambda; for y in {-1, 0, 1} the regression and improvement mixtures are exactly mixture likelihood ratios of
the discordant pairs against Bernoulli(1/2)). Ville's inequality gives P(sup_t wealth_t >= 1/a) <= a, so
stopping the first time a mixture wealth reaches 2/alpha rejects that null with error <= alpha/2 at any
stopping time: REGRESSED, IMPROVED or HELD (a drop larger than max_drop ruled out). The two directional
tests together have a two-sided level alpha, matching the fixed-size McNemar test, and HELD matches the
lower limit of a two-sided (1 - alpha) interval. When several cross at the same unit, one rule (`PRIORITY`,
used by both `first_decisions` and `SequentialTest.add`) picks REGRESSED > IMPROVED > HELD. A stream that ends
undecided is UNDERPOWERED.

Several tasks (`TaskwiseTest`, `taskwise_decisions`): one test per task on that task's own pairs, each at
alpha / T (Bonferroni over T tasks, so the family-wise error of a false REGRESSED stays <= alpha / 2 and of a
false HELD <= alpha / 2). A mean over tasks would let a task that breaks hide behind one that improves. The
family is REGRESSED as soon as any task is; it stops when a task regressed or every task decided, and is
then the worst task verdict (HELD unless every task IMPROVED); undecided at the end: UNDERPOWERED.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import logsumexp

from harness.verdicts import GateVerdict

TESTS = ("regression", "improvement", "held")
VERDICT_OF = {"regression": GateVerdict.REGRESSED, "improvement": GateVerdict.IMPROVED, "held": GateVerdict.HELD}
PRIORITY = ("regression", "improvement", "held")  # the one tie rule: REGRESSED > IMPROVED > HELD
_MAX_BET = 0.99  # fraction of the largest bet that keeps every factor positive


@dataclass(frozen=True)
class SequentialConfig:
    alpha: float = 0.05
    max_drop: float = 0.1
    grid: int = 64  # bets in each mixture

    def __post_init__(self):
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if not 0 < self.max_drop < 1:
            raise ValueError(f"max_drop must be in (0, 1), got {self.max_drop}")
        if self.grid < 1:
            raise ValueError(f"grid must be >= 1, got {self.grid}")

    @property
    def threshold(self) -> float:
        """Wealth at which a null is rejected: 2 / alpha (each one-sided test at alpha / 2)."""
        return 2.0 / self.alpha

    def bets(self, test: str) -> np.ndarray:
        """(grid,) bets lambda: midpoints of a uniform grid on (0, largest safe bet)."""
        largest = 1.0 / (1.0 - self.max_drop) if test == "held" else 1.0
        return (np.arange(self.grid) + 0.5) / self.grid * largest * _MAX_BET

    def shift(self, test: str, y: np.ndarray) -> np.ndarray:
        """z for the test's null from units y."""
        if test == "regression":
            return -y
        if test == "improvement":
            return y
        if test == "held":
            return y + self.max_drop
        raise ValueError(f"unknown test {test!r}; use one of {TESTS}")


def log_wealth_paths(y: np.ndarray, config: SequentialConfig) -> dict[str, np.ndarray]:
    """y (..., units) in [-1, 1] -> {test: (..., units)} log of each mixture wealth after every unit."""
    y = np.asarray(y, dtype=np.float64)
    if y.size and (y.min() < -1 or y.max() > 1):
        raise ValueError("units must lie in [-1, 1] (candidate minus baseline success)")
    out = {}
    for test in TESTS:
        z = config.shift(test, y)
        acc = None
        for bet in config.bets(test):
            path = np.cumsum(np.log1p(bet * z), axis=-1)
            acc = path if acc is None else np.logaddexp(acc, path)
        out[test] = acc - np.log(config.grid)
    return out


def first_decisions(y: np.ndarray, config: SequentialConfig) -> tuple[np.ndarray, np.ndarray]:
    """y (..., units) -> (verdicts (...) str, units used (...) int).

    Units used is the 1-based index of the deciding unit, or the number of units when undecided.
    """
    y = np.asarray(y, dtype=np.float64)
    units = y.shape[-1]
    paths = log_wealth_paths(y, config)
    level = np.log(config.threshold)
    index = np.arange(units)
    first = {t: np.where(paths[t] >= level, index, units).min(axis=-1) for t in TESTS}  # (...) first crossing
    stop = np.minimum.reduce([first[t] for t in TESTS])
    verdict = np.full(stop.shape, GateVerdict.UNDERPOWERED, dtype=object)
    for test in reversed(PRIORITY):  # later assignments win ties: PRIORITY[0] last
        verdict = np.where((first[test] == stop) & (stop < units), VERDICT_OF[test], verdict)
    used = np.where(stop < units, stop + 1, units)
    return verdict, used


@dataclass
class SequentialTest:
    """Accumulates units one at a time; `verdict` is None until a null is rejected."""

    config: SequentialConfig = field(default_factory=SequentialConfig)
    units: int = 0
    verdict: GateVerdict | None = None
    _log_wealth: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def __post_init__(self):
        self._log_wealth = {t: np.zeros(self.config.grid) for t in TESTS}

    def add(self, y: float) -> GateVerdict | None:
        """Add one unit (candidate minus baseline success, or its mean over a round); returns the verdict."""
        if not -1.0 <= y <= 1.0:
            raise ValueError(f"a unit must lie in [-1, 1], got {y}")
        if self.verdict is not None:
            return self.verdict
        self.units += 1
        for test in TESTS:
            z = float(self.config.shift(test, np.float64(y)))
            self._log_wealth[test] = self._log_wealth[test] + np.log1p(self.config.bets(test) * z)
        crossed = [t for t in TESTS if self.wealth(t) >= self.config.threshold]
        if crossed:
            self.verdict = VERDICT_OF[next(t for t in PRIORITY if t in crossed)]
        return self.verdict

    def wealth(self, test: str) -> float:
        """Current mixture wealth (the e-value) of one test."""
        return float(np.exp(logsumexp(self._log_wealth[test]) - np.log(self.config.grid)))

    def summary(self) -> dict:
        return {
            "units": self.units,
            "verdict": self.verdict or GateVerdict.UNDERPOWERED,
            "decided": self.verdict is not None,
            "threshold": self.config.threshold,
            "e_values": {t: self.wealth(t) for t in TESTS},
            "alpha": self.config.alpha,
            "max_drop": self.config.max_drop,
        }


def combine_tasks(verdicts: list[GateVerdict | None]) -> GateVerdict | None:
    """The family's verdict from its tasks' (None = undecided): REGRESSED if any task is, else None while a
    task is undecided, else HELD unless every task IMPROVED."""
    if GateVerdict.REGRESSED in verdicts:
        return GateVerdict.REGRESSED
    if any(v is None or v == GateVerdict.UNDERPOWERED for v in verdicts) or not verdicts:
        return None
    return GateVerdict.IMPROVED if all(v == GateVerdict.IMPROVED for v in verdicts) else GateVerdict.HELD


@dataclass
class TaskwiseTest:
    """One SequentialTest per task at alpha / T; `config` holds the family's alpha (see module docstring)."""

    tasks: tuple[str, ...]
    config: SequentialConfig = field(default_factory=SequentialConfig)
    tests: dict[str, SequentialTest] = field(default_factory=dict)
    errored: dict[str, int] = field(default_factory=dict)  # pairs left out because an arm errored
    rounds: int = 0

    def __post_init__(self):
        if not self.tasks:
            raise ValueError("a taskwise test needs at least one task")
        task_config = SequentialConfig(alpha=self.task_alpha, max_drop=self.config.max_drop, grid=self.config.grid)
        self.tests = {t: SequentialTest(task_config) for t in self.tasks}
        self.errored = {t: 0 for t in self.tasks}

    @property
    def task_alpha(self) -> float:
        return self.config.alpha / len(self.tasks)

    def add_round(self, outcomes: dict[str, tuple[bool | None, bool | None]]) -> GateVerdict | None:
        """One round: {task: (baseline success, candidate success)}, None for an arm that errored (the pair is
        counted in `errored`, not tested). Tasks already decided ignore their pair. Returns the verdict."""
        if self.verdict is not None:
            return self.verdict
        self.rounds += 1
        for task, (base, cand) in outcomes.items():
            if base is None or cand is None:
                self.errored[task] += 1
            elif self.tests[task].verdict is None:
                self.tests[task].add(float(cand) - float(base))
        return self.verdict

    @property
    def verdict(self) -> GateVerdict | None:
        return combine_tasks([self.tests[t].verdict for t in self.tasks])

    def summary(self) -> dict:
        return {
            "verdict": self.verdict or GateVerdict.UNDERPOWERED,
            "decided": self.verdict is not None,
            "rounds": self.rounds,
            "alpha": self.config.alpha,
            "task_alpha": self.task_alpha,
            "max_drop": self.config.max_drop,
            "threshold": self.tests[self.tasks[0]].config.threshold,
            "tasks": {t: {**self.tests[t].summary(), "errored_pairs": self.errored[t]} for t in self.tasks},
        }


def taskwise_decisions(y: np.ndarray, config: SequentialConfig) -> tuple[np.ndarray, np.ndarray]:
    """y (tasks, ..., rounds) units per task and round -> (family verdicts (...), rounds used (...)).

    The vectorised `TaskwiseTest` (no errored pairs): each task at alpha / T; stops at the first REGRESSED
    task, else when the last task decides.
    """
    y = np.asarray(y, dtype=np.float64)
    tasks, rounds = y.shape[0], y.shape[-1]
    task_config = SequentialConfig(alpha=config.alpha / tasks, max_drop=config.max_drop, grid=config.grid)
    verdicts, used = zip(*(first_decisions(y[t], task_config) for t in range(tasks)))
    verdicts, used = np.stack(verdicts), np.stack(used)  # (tasks, ...)
    regressed = verdicts == GateVerdict.REGRESSED
    decided = verdicts != GateVerdict.UNDERPOWERED
    first_regressed = np.where(regressed, used, rounds + 1).min(axis=0)
    all_improved = (verdicts == GateVerdict.IMPROVED).all(axis=0)
    out = np.where(decided.all(axis=0), np.where(all_improved, GateVerdict.IMPROVED, GateVerdict.HELD),
                   GateVerdict.UNDERPOWERED).astype(object)
    out = np.where(regressed.any(axis=0), GateVerdict.REGRESSED, out)
    stop = np.where(regressed.any(axis=0), first_regressed, np.where(decided.all(axis=0), used.max(axis=0), rounds))
    return out, stop


def simulate_pairs(baseline_rate: float, candidate_rate: float, pairs: int, runs: int,
                   rng: np.random.Generator, correlation: float = 0.0) -> np.ndarray:
    """(runs, pairs) units y = candidate - baseline for simulated paired Bernoulli outcomes.

    With `correlation` c in [0, 1), both arms share the seed's uniform draw with probability c (a seed that is
    easy for one is easy for the other), else draw independently; the marginal rates are exact either way.
    """
    shared = rng.random((runs, pairs))
    own_b, own_c = rng.random((runs, pairs)), rng.random((runs, pairs))
    tie = rng.random((runs, pairs)) < correlation
    base = np.where(tie, shared, own_b) < baseline_rate
    cand = np.where(tie, shared, own_c) < candidate_rate
    return cand.astype(np.int8) - base.astype(np.int8)
