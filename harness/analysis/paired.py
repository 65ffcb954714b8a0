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
- `paired_verdict`: REGRESSED / IMPROVED / HELD / UNDERPOWERED from the rules below.
- `pairs_to_decide`: how many pairs the current rates would need for a verdict other than UNDERPOWERED.
- `mcnemar_sample_size`: fixed-size number of pairs for a given power (Connor 1987).

Decision rules (difference = candidate rate - baseline rate, interval at confidence 1 - alpha):
  REGRESSED     Holm-adjusted McNemar p <= alpha and candidate_only < baseline_only
  IMPROVED      Holm-adjusted McNemar p <= alpha and candidate_only > baseline_only
  HELD          neither, and the interval's lower limit >= -max_drop (a drop larger than max_drop is ruled out)
  UNDERPOWERED  none of the above (or no pairs)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from scipy.stats import binomtest, norm

from harness.analysis.stats import wilson_interval

VERDICTS = ("REGRESSED", "IMPROVED", "HELD", "UNDERPOWERED")


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
                   max_drop: float, alpha: float) -> str:
    """REGRESSED / IMPROVED / HELD / UNDERPOWERED by the rules in the module docstring."""
    if counts.n == 0:
        return "UNDERPOWERED"
    if p_adjusted <= alpha and counts.candidate_only != counts.baseline_only:
        return "REGRESSED" if counts.candidate_only < counts.baseline_only else "IMPROVED"
    if interval[0] >= -max_drop:
        return "HELD"
    return "UNDERPOWERED"


def decide(counts: PairedCounts, max_drop: float, alpha: float, multiplier: float = 1.0) -> str:
    """Verdict for one table on its own; `multiplier` scales its McNemar p (e.g. its Holm factor)."""
    p = min(1.0, multiplier * mcnemar_exact(counts.baseline_only, counts.candidate_only))
    return paired_verdict(counts, p, difference_interval(counts, 1.0 - alpha), max_drop, alpha)


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
    """Total pairs at which a table with the current proportions would no longer be UNDERPOWERED.

    A plug-in estimate: the observed 2x2 proportions are held fixed and scaled to N pairs; the smallest
    such N (found by doubling, then bisection) whose verdict under `decide` is REGRESSED, IMPROVED or HELD
    is returned. Because the proportions are estimates, N is where a decision becomes about as likely as
    not, not a guarantee. None when there are no pairs or N would exceed `limit`. Returns counts.n when the
    current table is already decided.
    """
    if counts.n == 0:
        return None

    def decided(n: int) -> bool:
        return decide(_scaled(counts, n), max_drop, alpha, multiplier) != "UNDERPOWERED"

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
