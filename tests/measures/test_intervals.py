"""Binomial confidence intervals against published values (Newcombe 1998, Statistics in Medicine 17:857-872, Table I)."""
import math

import pytest

from harness.measures.stats import clopper_pearson_interval, success_summary, wilson_interval

# (successes, n, Wilson score (method 3), Clopper-Pearson exact (method 5)), 95%, 4 decimals as printed in Table I.
NEWCOMBE_TABLE_I = [
    (81, 263, (0.2553, 0.3662), (0.2527, 0.3676)),
    (15, 148, (0.0624, 0.1605), (0.0578, 0.1617)),
    (0, 20, (0.0000, 0.1611), (0.0000, 0.1684)),
    (1, 29, (0.0061, 0.1718), (0.0009, 0.1776)),
    (29, 29, (0.8830, 1.0000), (0.8806, 1.0000)),
]


@pytest.mark.parametrize("successes,n,wilson,_", NEWCOMBE_TABLE_I)
def test_wilson_matches_newcombe_table_1(successes, n, wilson, _):
    low, high = wilson_interval(successes, n)
    assert round(low, 4) == pytest.approx(wilson[0], abs=1e-9)
    assert round(high, 4) == pytest.approx(wilson[1], abs=1e-9)


@pytest.mark.parametrize("successes,n,_,exact", NEWCOMBE_TABLE_I)
def test_clopper_pearson_matches_newcombe_table_1(successes, n, _, exact):
    low, high = clopper_pearson_interval(successes, n)
    assert round(low, 4) == pytest.approx(exact[0], abs=1e-9)
    assert round(high, 4) == pytest.approx(exact[1], abs=1e-9)


def test_interval_properties():
    for n in (1, 2, 7, 50):
        for k in range(n + 1):
            w = wilson_interval(k, n)
            c = clopper_pearson_interval(k, n)
            assert 0.0 <= w[0] <= k / n <= w[1] <= 1.0
            assert 0.0 <= c[0] <= k / n <= c[1] <= 1.0
    # Higher confidence gives a wider interval; symmetric in successes <-> failures.
    assert wilson_interval(3, 10, 0.99)[0] < wilson_interval(3, 10, 0.95)[0]
    low, high = wilson_interval(3, 10)
    assert (1 - high, 1 - low) == pytest.approx(wilson_interval(7, 10))


def test_success_summary_and_empty():
    row = success_summary(1, 29)
    assert row["n"] == 29 and row["successes"] == 1 and row["method"] == "wilson"
    assert row["success_rate"] == pytest.approx(1 / 29)
    assert (round(row["ci_low"], 4), round(row["ci_high"], 4)) == (0.0061, 0.1718)
    exact = success_summary(1, 29, method="clopper-pearson")
    assert (round(exact["ci_low"], 4), round(exact["ci_high"], 4)) == (0.0009, 0.1776)
    empty = success_summary(0, 0)
    assert math.isnan(empty["success_rate"]) and (empty["ci_low"], empty["ci_high"]) == (0.0, 1.0)


@pytest.mark.parametrize("args", [(3, 2), (-1, 5), (1, -1), (1.5, 3)])
def test_bad_counts_raise(args):
    with pytest.raises(ValueError):
        wilson_interval(*args)


def test_bad_method_and_confidence_raise():
    with pytest.raises(ValueError, match="wilson"):
        success_summary(1, 2, method="wald")
    with pytest.raises(ValueError):
        clopper_pearson_interval(1, 2, confidence=1.0)
