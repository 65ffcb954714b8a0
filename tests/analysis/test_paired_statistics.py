"""Paired statistics against known answers: exact McNemar by hand, Newcombe (1998) published intervals, Holm."""

import math

import pytest

from harness.analysis.paired import (
    PairedCounts,
    decide,
    difference_interval,
    holm_adjust,
    mcnemar_exact,
    mcnemar_sample_size,
    newcombe_paired_interval,
    paired_verdict,
    pairs_to_decide,
)
from harness.verdicts import GateVerdict


@pytest.mark.parametrize(
    "baseline_only, candidate_only, expected",
    [
        (10, 2, 2 * (1 + 12 + 66) / 4096),  # 2 * P(X <= 2), X ~ Bin(12, 1/2)
        (2, 10, 2 * (1 + 12 + 66) / 4096),  # symmetric
        (5, 0, 2 / 32),
        (6, 0, 2 / 64),
        (7, 3, 2 * (1 + 10 + 45 + 120) / 1024),
        (3, 3, 1.0),
        (0, 0, 1.0),  # no discordant pairs: no evidence
    ],
)
def test_exact_mcnemar_matches_hand_computed_binomial_tails(baseline_only, candidate_only, expected):
    assert mcnemar_exact(baseline_only, candidate_only) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    "table, published",
    [
        # Newcombe (1998) Table II examples (a)-(d), method 10; (e) Altman et al. "Statistics with confidence"
        # (2000) Table 6.2, 0.011 to 0.226.
        ((36, 12, 2, 0), (0.0569, 0.3404)),
        ((18, 12, 2, 18), (0.0562, 0.3290)),
        ((53, 0, 0, 1), (-0.0729, 0.0729)),
        ((0, 30, 0, 0), (0.8395, 1.0)),
        ((14, 5, 0, 22), (0.0115, 0.2265)),
    ],
)
def test_newcombe_method_10_reproduces_published_intervals(table, published):
    low, high = newcombe_paired_interval(*table)
    assert low == pytest.approx(published[0], abs=5e-5) and high == pytest.approx(published[1], abs=5e-5)
    # swapping the arms negates the interval
    both, first, second, neither = table
    swapped = newcombe_paired_interval(both, second, first, neither)
    assert swapped == pytest.approx((-high, -low), abs=1e-12)


def test_phi_continuity_correction_is_what_separates_method_10_from_the_plain_phi():
    # (18, 12, 2, 18): A = 18*18 - 12*2 = 300 > n/2 = 25, so phi* = 275/sqrt(30*20*20*30) = 0.4583 (not 0.5);
    # the uncorrected phi would give (0.0618, 0.3239), which is not the published interval.
    low, high = newcombe_paired_interval(18, 12, 2, 18)
    assert (round(low, 4), round(high, 4)) == (0.0562, 0.3290)


def test_difference_interval_is_candidate_minus_baseline():
    counts = PairedCounts(both=36, baseline_only=2, candidate_only=12, neither=0)
    assert counts.difference == pytest.approx(0.2)
    assert difference_interval(counts) == pytest.approx(newcombe_paired_interval(36, 12, 2, 0))


def test_holm_matches_the_textbook_example():
    # m = 4: sorted 0.005*4 = 0.02, 0.01*3 = 0.03, 0.03*2 = 0.06, 0.04*1 = 0.04 -> max(0.06, 0.04) = 0.06
    assert holm_adjust([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjust([0.5]) == [0.5]
    assert holm_adjust([0.6, 0.9]) == [1.0, 1.0]  # capped at 1
    assert holm_adjust([]) == []


def test_counts_from_outcomes():
    counts = PairedCounts.from_outcomes([True, True, False, False, True], [True, False, True, False, False])
    assert counts == PairedCounts(both=1, baseline_only=2, candidate_only=1, neither=1)
    with pytest.raises(ValueError):
        PairedCounts.from_outcomes([True], [])


def test_verdict_rules():
    drop = PairedCounts(both=5, baseline_only=10, candidate_only=0, neither=5)  # p = 2/1024
    assert decide(drop, max_drop=0.1, alpha=0.05) == "REGRESSED"
    gain = PairedCounts(both=5, baseline_only=0, candidate_only=10, neither=5)
    assert decide(gain, max_drop=0.1, alpha=0.05) == "IMPROVED"
    same = PairedCounts(both=100, neither=100)  # 200 concordant pairs: lower limit about -0.01
    assert difference_interval(same)[0] > -0.1
    assert decide(same, max_drop=0.1, alpha=0.05) == "HELD"
    assert decide(PairedCounts(both=2, neither=2), max_drop=0.1, alpha=0.05) == "UNDERPOWERED"
    assert decide(PairedCounts(), max_drop=0.1, alpha=0.05) == "UNDERPOWERED"
    # significant alone (p = 2/64 = 0.031) but not after a Holm factor of 2 (0.0625): no longer REGRESSED, but
    # its interval still lies below 0, so SUSPECT (never UNDERPOWERED or HELD under an interval showing a drop)
    six = PairedCounts(baseline_only=6, both=10, neither=10)
    assert difference_interval(six)[1] < 0
    assert decide(six, 0.1, 0.05) == "REGRESSED" and decide(six, 0.1, 0.05, multiplier=2) == "SUSPECT"
    # the interval rules: HELD needs the lower limit >= -max_drop
    assert paired_verdict(same, 1.0, (-0.1, 0.2), 0.1, 0.05) == "HELD"
    assert paired_verdict(same, 1.0, (-0.1001, 0.2), 0.1, 0.05) == "UNDERPOWERED"


def test_pairs_to_decide_is_the_smallest_scaled_table_with_a_verdict():
    counts = PairedCounts(both=2, baseline_only=1, candidate_only=0, neither=2)  # 5 pairs, UNDERPOWERED
    assert decide(counts, 0.1, 0.05) == "UNDERPOWERED"
    n = pairs_to_decide(counts, 0.1, 0.05)
    assert n is not None and n > counts.n
    from harness.analysis.paired import _scaled

    assert _scaled(counts, n).n == n
    assert decide(_scaled(counts, n), 0.1, 0.05) in ("REGRESSED", "IMPROVED", "HELD")
    assert decide(_scaled(counts, n - 1), 0.1, 0.05) in ("UNDERPOWERED", "SUSPECT")  # SUSPECT: not yet decided
    decided = PairedCounts(both=5, baseline_only=10, neither=5)
    assert pairs_to_decide(decided, 0.1, 0.05) == decided.n
    assert pairs_to_decide(PairedCounts(), 0.1, 0.05) is None


def test_connor_sample_size_by_hand():
    # psi = 0.5, delta = 0.3: (1.959964 * sqrt(0.5) + 0.841621 * sqrt(0.41))^2 / 0.09 = 41.17 -> 42
    expected = (1.959964 * math.sqrt(0.5) + 0.841621 * math.sqrt(0.41)) ** 2 / 0.09
    assert mcnemar_sample_size(0.4, 0.1) == math.ceil(expected) == 42
    assert mcnemar_sample_size(0.2, 0.2) is None


def test_a_grid_with_an_incomplete_condition_is_incomplete_unless_another_failed_outright():
    """regress over a robustness grid takes the worst of its conditions: INCOMPLETE used to be outside the gate's
    order, so a grid with one unfinished condition raised (exit 5) instead of giving a verdict."""
    assert GateVerdict.worst([GateVerdict.HELD, GateVerdict.INCOMPLETE, GateVerdict.IDENTICAL]) == GateVerdict.INCOMPLETE
    assert GateVerdict.worst([GateVerdict.SUSPECT, GateVerdict.INCOMPLETE]) == GateVerdict.INCOMPLETE
    assert GateVerdict.worst([GateVerdict.INCOMPLETE, GateVerdict.REGRESSED]) == GateVerdict.REGRESSED
    assert GateVerdict.worst([GateVerdict.ERRORED, GateVerdict.INCOMPLETE]) == GateVerdict.ERRORED
    assert GateVerdict.worst([]) == GateVerdict.IDENTICAL
