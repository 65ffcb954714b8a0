"""Paired success statistics: two policies run on the same seeds, compared pair by pair (pure functions).

A pair is one (task, seed) episode run by both arms. Its outcomes fall into a 2x2 table:

    both        both arms succeeded          baseline_only   only the baseline succeeded
    neither     both failed                  candidate_only  only the candidate succeeded

Only the discordant pairs (baseline_only, candidate_only) carry information about a difference.

- `mcnemar_exact`: two-sided exact McNemar p-value (binomial test of candidate_only out of the discordant
  pairs against 1/2).
- `newcombe_paired_interval`: interval for the difference of paired proportions, Newcombe (1998,
  Statistics in Medicine 17:2635, method 10: Wilson score limits of both margins combined with the
  continuity-corrected phi coefficient).
- `holm_adjust`: Holm's (1979) step-down adjusted p-values.
- `paired_verdict`: ERRORED / REGRESSED / SUSPECT / IMPROVED / HELD / UNDERPOWERED from the rules below.
- `equivalent`: the HELD rule's equivalence test alone (a drop larger than max_drop ruled out); compare's HELD and
  the robustness grid's HOLDS are this one function.
- `detectable_loss` / `detectable_phrase`: the smallest drop (lost pairs, none gained) the exact test can declare
  at n pairs, alpha and a multiplicity: what a null statement ("breaks nothing") could have detected.
- `regressed_reachable` / `pairs_for_regressed`: whether n pairs can give REGRESSED at all (exact test).
- `pairs_to_decide`: how many pairs the current rates would need for a verdict other than UNDERPOWERED.
- `mcnemar_sample_size`: fixed-size number of pairs for a given power (Connor 1987, asymptotic);
  `mcnemar_exact_sample_size`: the same for the exact conditional McNemar test that `compare` runs.

Only pairs in which both arms ran to an outcome are counted (n). A pair in which either arm errored (the
episode raised: no outcome) is an "errored pair": it is left out of the 2x2 table and counted separately.

Decision rules (difference = candidate rate - baseline rate; interval at confidence 1 - alpha / m over a family
of m tables, Bonferroni-simultaneous, so that SUSPECT's family-wise false alarm is <= alpha / 2 like REGRESSED's):
  ERRORED       an arm errored on more than half of its paired episodes (no outcome to compare)
  REGRESSED     Holm-adjusted McNemar p <= alpha and candidate_only < baseline_only
  IMPROVED      Holm-adjusted McNemar p <= alpha and candidate_only > baseline_only
  SUSPECT       neither, but the interval's upper limit < 0 (the printed interval shows a drop the exact test,
                after Holm, does not confirm: the verdict never contradicts its interval)
  HELD          none of these, no errored pair, the interval's lower limit >= -max_drop and the exact
                unconditional test of "a drop >= max_drop" (`held_pvalue`) rejects at alpha / 2: a drop larger
                than max_drop is ruled out (the exact test keeps the error of HELD <= alpha / 2, which Newcombe's
                interval alone exceeds at small n: up to 9% at 20 pairs; tests/gate/test_decisions.py)
  UNDERPOWERED  none of the above (or no pairs, or HELD but with errored pairs)
Gate order (worst first, harness.verdicts.GateVerdict's rank; an overall verdict is the worst of its parts):
ERRORED > REGRESSED > INCOMPLETE > SUSPECT > UNDERPOWERED > HELD > IMPROVED > IDENTICAL.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import beta, binom, binomtest, norm

from harness.measures.stats import wilson_interval
from harness.verdicts import GateVerdict


# the verdicts that decide a table (pairs_to_decide's aim; every other verdict of paired_verdict leaves it open)
DECIDED = (GateVerdict.REGRESSED, GateVerdict.IMPROVED, GateVerdict.HELD)


def errored_most(errored: int, paired_episodes: int) -> bool:
    """An arm errored on more than half of its paired episodes (the ERRORED rule)."""
    return paired_episodes > 0 and 2 * errored > paired_episodes


@dataclass(frozen=True)
class PairedCounts:
    """The 2x2 table of paired outcomes (counts of pairs)."""

    both: int = 0
    baseline_only: int = 0
    candidate_only: int = 0
    neither: int = 0

    @classmethod
    def from_outcomes(cls, baseline: list[bool], candidate: list[bool]) -> "PairedCounts":
        """Two equally long sequences of success flags, aligned pair by pair."""
        if len(baseline) != len(candidate):
            raise ValueError(f"paired outcomes need equal lengths, got {len(baseline)} and {len(candidate)}")
        pairs = [(bool(b), bool(c)) for b, c in zip(baseline, candidate)]
        return cls(pairs.count((True, True)), pairs.count((True, False)), pairs.count((False, True)),
                   pairs.count((False, False)))

    def __add__(self, other: "PairedCounts") -> "PairedCounts":
        return PairedCounts(self.both + other.both, self.baseline_only + other.baseline_only,
                            self.candidate_only + other.candidate_only, self.neither + other.neither)

    @property
    def n(self) -> int:
        return self.both + self.baseline_only + self.candidate_only + self.neither

    @property
    def discordant(self) -> int:
        return self.baseline_only + self.candidate_only

    @property
    def baseline_successes(self) -> int:
        return self.both + self.baseline_only

    @property
    def candidate_successes(self) -> int:
        return self.both + self.candidate_only

    @property
    def difference(self) -> float:
        """Candidate success rate minus baseline success rate (NaN without pairs)."""
        return (self.candidate_only - self.baseline_only) / self.n if self.n else float("nan")


@dataclass(frozen=True)
class ErroredPairs:
    """Pairs left out of the 2x2 table because an arm errored (status "failed": the episode raised)."""

    baseline: int = 0  # pairs whose baseline episode errored
    candidate: int = 0  # pairs whose candidate episode errored
    pairs: int = 0  # pairs with either arm errored

    @classmethod
    def from_statuses(cls, baseline_ok: list[bool], candidate_ok: list[bool]) -> "ErroredPairs":
        """Per pair, whether each arm ran to an outcome."""
        flags = list(zip(baseline_ok, candidate_ok))
        return cls(sum(not b for b, _ in flags), sum(not c for _, c in flags), sum(not (b and c) for b, c in flags))

    def __add__(self, other: "ErroredPairs") -> "ErroredPairs":
        return ErroredPairs(self.baseline + other.baseline, self.candidate + other.candidate, self.pairs + other.pairs)


def mcnemar_exact(baseline_only: int, candidate_only: int) -> float:
    """Two-sided exact McNemar p-value: binomial test of candidate_only ~ Bin(discordant, 1/2).

    1.0 when there are no discordant pairs.
    """
    if baseline_only < 0 or candidate_only < 0:
        raise ValueError(f"discordant counts must be >= 0, got {baseline_only}, {candidate_only}")
    discordant = baseline_only + candidate_only
    if discordant == 0:
        return 1.0
    return float(binomtest(candidate_only, discordant, 0.5, alternative="two-sided").pvalue)


def newcombe_paired_interval(both: int, first_only: int, second_only: int, neither: int,
                             confidence: float = 0.95) -> tuple[float, float]:
    """Newcombe (1998) method 10 interval for p_first - p_second from paired counts.

    p_first = (both + first_only) / n, p_second = (both + second_only) / n. With Wilson limits (l1, u1) of
    p_first and (l2, u2) of p_second and the difference d = (first_only - second_only) / n:
        lower = d - sqrt((p1 - l1)^2 - 2 phi (p1 - l1)(u2 - p2) + (u2 - p2)^2)
        upper = d + sqrt((u1 - p1)^2 - 2 phi (u1 - p1)(p2 - l2) + (p2 - l2)^2)
    phi is the correlation of the 2x2 table with Newcombe's continuity correction:
    A = both * neither - first_only * second_only; phi = max(A - n/2, 0) / sqrt(margins) if A > 0,
    A / sqrt(margins) if A <= 0, and 0 when a margin is empty. Returns (-1, 1) when n == 0.
    """
    counts = (both, first_only, second_only, neither)
    if any(c < 0 for c in counts):
        raise ValueError(f"paired counts must be >= 0, got {counts}")
    n = sum(counts)
    if n == 0:
        return -1.0, 1.0
    p1, p2 = (both + first_only) / n, (both + second_only) / n
    l1, u1 = wilson_interval(both + first_only, n, confidence)
    l2, u2 = wilson_interval(both + second_only, n, confidence)
    margins = (both + first_only) * (second_only + neither) * (both + second_only) * (first_only + neither)
    cross = both * neither - first_only * second_only
    if margins == 0:
        phi = 0.0
    elif cross > 0:
        phi = max(cross - n / 2.0, 0.0) / math.sqrt(margins)
    else:
        phi = cross / math.sqrt(margins)
    d = (first_only - second_only) / n
    lower = d - math.sqrt(max((p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2, 0.0))
    upper = d + math.sqrt(max((u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2, 0.0))
    return max(-1.0, lower), min(1.0, upper)


def held_pvalue(baseline_only: int, candidate_only: int, n: int, max_drop: float, grid: int = 256,
                gamma: float = 0.001) -> float:
    """Exact unconditional p-value of H0 "the candidate's rate is lower by max_drop or more" (one-sided), with
    Berger & Boos's (1994, JASA 89:1012) confidence-set restriction of the nuisance parameter.

    With D = baseline_only - candidate_only, small D is evidence against H0. On H0's boundary
    p_b = p_c + max_drop (moving mass to p_b only makes D larger, so the boundary is the worst case) the
    discordant cells are trinomial and, with psi = p_b + p_c the discordance rate,
        P(D <= d) = sum_m Bin(m; n, psi) P(Bin(m, p_b / psi) <= (m + d) / 2).
    p = gamma + the largest P(D <= d) over psi in the (1 - gamma) Clopper-Pearson interval of the observed
    discordance (m = baseline_only + candidate_only out of n), on a grid of `grid` values; p = gamma when that
    interval holds no psi >= max_drop the null allows. Valid at every level (Berger & Boos). 1.0 without pairs.
    """
    if n <= 0:
        return 1.0
    d, m_obs = baseline_only - candidate_only, baseline_only + candidate_only
    low = beta.ppf(gamma / 2, m_obs, n - m_obs + 1) if m_obs > 0 else 0.0
    high = beta.ppf(1 - gamma / 2, m_obs + 1, n - m_obs) if m_obs < n else 1.0
    low, high = max(low, max_drop), min(high, 1.0)
    if low > high:
        return gamma
    psi = np.linspace(low, high, grid)[:, None]  # (grid, 1) discordance rates on the null's boundary
    share = (psi + max_drop) / (2 * psi)  # p_b / psi with p_b = (psi + max_drop) / 2
    # discordant counts within 9 standard deviations of every psi on the grid (the rest weighs < 1e-18)
    spread = 9 * math.sqrt(n * 0.25) + 1
    m = np.arange(max(0, math.floor(n * low - spread)), min(n, math.ceil(n * high + spread)) + 1)[None, :]  # (1, k)
    inside = binom.cdf(np.floor((m + d) / 2.0), m, share)  # (grid, k) P(b - c <= d | m)
    tail = (binom.pmf(m, n, psi) * inside).sum(axis=1)  # (grid,)
    return float(min(1.0, tail.max() + gamma))


def difference_interval(counts: PairedCounts, confidence: float = 0.95) -> tuple[float, float]:
    """Interval for candidate rate - baseline rate (Newcombe method 10)."""
    return newcombe_paired_interval(counts.both, counts.candidate_only, counts.baseline_only, counts.neither, confidence)


def holm_adjust(pvalues: list[float]) -> list[float]:
    """Holm (1979) step-down adjusted p-values, in the input order.

    Sorted ascending p_(1) <= ... <= p_(m): adjusted p_(i) = max_{j <= i} min(1, (m - j + 1) p_(j)).
    Rejecting every hypothesis whose adjusted p <= alpha controls the family-wise error at alpha.
    """
    m = len(pvalues)
    order = sorted(range(m), key=lambda i: pvalues[i])
    adjusted = [0.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvalues[i]))
        adjusted[i] = running
    return adjusted


def paired_verdict(counts: PairedCounts, p_adjusted: float, interval: tuple[float, float],
                   max_drop: float, alpha: float, errored: "ErroredPairs | None" = None) -> GateVerdict:
    """Verdict of one table by the rules in the module docstring.

    errored: the pairs left out of `counts` because an arm errored; paired episodes = counts.n + errored.pairs.
    """
    errored = errored or ErroredPairs()
    errored_pairs = errored.pairs
    paired_episodes = counts.n + errored_pairs
    if errored_most(errored.baseline, paired_episodes) or errored_most(errored.candidate, paired_episodes):
        return GateVerdict.ERRORED
    if counts.n == 0:
        return GateVerdict.UNDERPOWERED
    if p_adjusted <= alpha and counts.candidate_only != counts.baseline_only:
        return GateVerdict.REGRESSED if counts.candidate_only < counts.baseline_only else GateVerdict.IMPROVED
    if interval[1] < 0:
        return GateVerdict.SUSPECT
    if not errored_pairs and equivalent(counts, interval, max_drop, alpha):
        return GateVerdict.HELD
    return GateVerdict.UNDERPOWERED


def equivalent(counts: PairedCounts, interval: tuple[float, float], max_drop: float, alpha: float) -> bool:
    """Whether a drop (baseline rate - candidate rate) larger than `max_drop` is ruled out: the interval's lower limit
    (candidate - baseline) >= -max_drop, i.e. the upper confidence bound of the drop is within the margin, and the
    exact unconditional test of "a drop >= max_drop" (`held_pvalue`) rejects at alpha / 2. False without pairs."""
    return bool(counts.n and interval[0] >= -max_drop
                and held_pvalue(counts.baseline_only, counts.candidate_only, counts.n, max_drop) <= alpha / 2)


def detectable_loss(pairs: int, alpha: float, cells: int = 1) -> int | None:
    """Fewest lost pairs (none gained) whose exact McNemar p, times `cells` (Holm's first factor over a family of
    `cells` tables: the bound that holds whatever the other cells show), is <= alpha; None when `pairs` pairs
    cannot reach it. E.g. 6 at alpha 0.05 alone (2 * 0.5**6 = 0.031), 10 over 21 cells (21 * 2 * 0.5**10 = 0.041)."""
    if pairs <= 0:
        return None
    needed = pairs_for_regressed(alpha, cells)
    return needed if needed <= pairs else None


def detectable_phrase(pairs: int, alpha: float = 0.05, cells: int = 1) -> str:
    """A null statement's power in words: "no drop of 50 points or more at 20 pairs (Holm over 21 cells)"."""
    family = f"Holm over {cells} cells" if cells > 1 else f"alpha {alpha:g}"
    loss = detectable_loss(pairs, alpha, cells)
    if loss is None:
        return f"no drop at all is detectable at {pairs} pairs ({family})"
    return f"no drop of {round(100 * loss / pairs)} points or more at {pairs} pairs ({family})"


def min_mcnemar_p(pairs: int) -> float:
    """Smallest two-sided exact McNemar p-value `pairs` pairs can give (all of them discordant one way)."""
    return min(1.0, 2.0 * 0.5 ** pairs)


def regressed_reachable(pairs: int, alpha: float, multiplier: float = 1.0) -> bool:
    """Whether any table of `pairs` pairs can be REGRESSED: multiplier x smallest exact p <= alpha."""
    return multiplier * min_mcnemar_p(pairs) <= alpha


def pairs_for_regressed(alpha: float, multiplier: float = 1.0) -> int:
    """Fewest pairs with which REGRESSED is reachable (every pair discordant towards the baseline)."""
    n = 1
    while not regressed_reachable(n, alpha, multiplier):
        n += 1
    return n


def decide(counts: PairedCounts, max_drop: float, alpha: float, multiplier: float = 1.0,
           errored: ErroredPairs | None = None) -> str:
    """Verdict for one table on its own; `multiplier` scales its McNemar p (e.g. its Holm factor) and widens its
    interval to confidence 1 - alpha / multiplier (Bonferroni), as `compare` does over a family of that size."""
    p = min(1.0, multiplier * mcnemar_exact(counts.baseline_only, counts.candidate_only))
    return paired_verdict(counts, p, difference_interval(counts, 1.0 - alpha / multiplier), max_drop, alpha, errored)


def _scaled(counts: PairedCounts, n: int) -> PairedCounts:
    """The table with `n` pairs in the same proportions (cells rounded; n is kept exactly)."""
    cells = [counts.both, counts.baseline_only, counts.candidate_only, counts.neither]
    raw = [c * n / counts.n for c in cells]
    out = [math.floor(x) for x in raw]
    for i in sorted(range(4), key=lambda i: raw[i] - out[i], reverse=True)[: n - sum(out)]:
        out[i] += 1  # largest remainders first
    return PairedCounts(*out)


def pairs_to_decide(counts: PairedCounts, max_drop: float, alpha: float, multiplier: float = 1.0,
                    limit: int = 100_000) -> int | None:
    """Total pairs at which a table with the current proportions would be REGRESSED, IMPROVED or HELD
    (no longer UNDERPOWERED or SUSPECT).

    A plug-in estimate: the observed 2x2 proportions are held fixed and scaled to N pairs; the smallest
    such N (found by doubling, then bisection) whose verdict under `decide` is REGRESSED, IMPROVED or HELD
    is returned. Because the proportions are estimates, N is where a decision becomes about as likely as
    not, not a guarantee. None when there are no pairs or N would exceed `limit`. Returns counts.n when the
    current table is already decided.
    """
    if counts.n == 0:
        return None

    def decided(n: int) -> bool:
        return decide(_scaled(counts, n), max_drop, alpha, multiplier) in DECIDED

    if decided(counts.n):
        return counts.n
    low, high = counts.n, counts.n
    while not decided(high):
        low, high = high, high * 2
        if high > limit:
            return None if not decided(limit) else _bisect(decided, low, limit)
    return _bisect(decided, low, high)


def _bisect(decided, low: int, high: int) -> int:
    """Smallest n in (low, high] with decided(n), assuming decided(high) and not decided(low)."""
    while high - low > 1:
        mid = (low + high) // 2
        if decided(mid):
            high = mid
        else:
            low = mid
    return high


def mcnemar_sample_size(baseline_only_rate: float, candidate_only_rate: float, alpha: float = 0.05,
                        power: float = 0.8) -> int | None:
    """Pairs a fixed-size two-sided McNemar test needs to detect the given discordance rates (Connor 1987).

    With psi = p_b + p_c (probability of a discordant pair) and delta = p_b - p_c:
        n = (z_{1-alpha/2} sqrt(psi) + z_{power} sqrt(psi - delta^2))^2 / delta^2, rounded up.
    None when the rates are equal (no difference to detect).
    """
    psi = baseline_only_rate + candidate_only_rate
    delta = baseline_only_rate - candidate_only_rate
    if delta == 0:
        return None
    z_a, z_b = norm.ppf(1 - alpha / 2), norm.ppf(power)
    return math.ceil((z_a * math.sqrt(psi) + z_b * math.sqrt(max(psi - delta * delta, 0.0))) ** 2 / delta ** 2)


def exact_rejection_probability(discordant: np.ndarray, candidate_share: float, alpha: float) -> np.ndarray:
    """P(the exact two-sided McNemar test rejects at alpha | D discordant pairs), D (k,) -> (k,).

    Given D, the candidate-only count is Bin(D, q) with q = p_c / (p_b + p_c). The test rejects when
    2 P(Bin(D, 1/2) <= min(x, D - x)) <= alpha, i.e. x <= k or x >= D - k with k the largest count whose
    lower tail is <= alpha / 2 (k = -1: no rejection possible at this D).
    """
    d = np.asarray(discordant, dtype=np.int64)
    k = binom.ppf(alpha / 2, d, 0.5)  # smallest k with cdf >= alpha/2
    k = np.where(binom.cdf(k, d, 0.5) <= alpha / 2 * (1 + 1e-12), k, k - 1)  # largest with cdf <= alpha/2
    lower = np.where(k >= 0, binom.cdf(k, d, candidate_share), 0.0)
    upper = np.where(k >= 0, binom.sf(d - k - 1, d, candidate_share), 0.0)
    return lower + upper


def mcnemar_exact_power(n: int, baseline_only_rate: float, candidate_only_rate: float, alpha: float = 0.05) -> float:
    """Unconditional power of the exact conditional McNemar test with n pairs:
    sum over D ~ Bin(n, psi) of P(D) P(reject | D), psi = p_b + p_c."""
    psi = baseline_only_rate + candidate_only_rate
    if psi <= 0:
        return 0.0
    d = np.arange(n + 1)
    share = candidate_only_rate / psi
    return float(np.sum(binom.pmf(d, n, psi) * exact_rejection_probability(d, share, alpha)))


def mcnemar_exact_sample_size(baseline_only_rate: float, candidate_only_rate: float, alpha: float = 0.05,
                              power: float = 0.8, limit: int = 20_000) -> int | None:
    """Smallest n whose exact McNemar power (`mcnemar_exact_power`) reaches `power`.

    Exact power is a saw-tooth in n (the discrete test's level jumps), so n is searched upwards from 1 rather
    than solved; P(reject | D) does not depend on n and is computed once. None when the rates are equal or
    n would exceed `limit`.
    """
    psi = baseline_only_rate + candidate_only_rate
    if baseline_only_rate == candidate_only_rate or psi <= 0:
        return None
    reject = exact_rejection_probability(np.arange(limit + 1), candidate_only_rate / psi, alpha)  # (limit + 1,)
    for n in range(1, limit + 1):
        d = np.arange(n + 1)
        if float(np.sum(binom.pmf(d, n, psi) * reject[: n + 1])) >= power:
            return n
    return None
