"""Sequential (anytime-valid) test on paired outcomes: closed-form wealth, type-I error, power and early stopping."""

import time

import numpy as np
import pytest

from harness.analysis.paired import mcnemar_sample_size
from harness.analysis.sequential import (
    SequentialConfig,
    SequentialTest,
    first_decisions,
    log_wealth_paths,
    simulate_pairs,
)

CONFIG = SequentialConfig(alpha=0.05, max_drop=0.1)


def _first_crossing(factor_of_bet: np.ndarray, threshold: float) -> int:
    """Smallest k with mean_j factor_j^k >= threshold (a closed form for constant streams)."""
    k = 1
    while np.mean(factor_of_bet ** k) < threshold:
        k += 1
    return k


def test_wealth_of_constant_streams_has_its_closed_form():
    bets = CONFIG.bets("regression")
    assert bets.min() > 0 and bets.max() < 1
    paths = log_wealth_paths(np.full(10, -1.0), CONFIG)  # baseline-only success every pair
    k = np.arange(1, 11)[:, None]
    np.testing.assert_allclose(np.exp(paths["regression"]), np.mean((1 + bets) ** k, axis=1), rtol=1e-12)
    np.testing.assert_allclose(np.exp(paths["improvement"]), np.mean((1 - bets) ** k, axis=1), rtol=1e-12)
    held_bets = CONFIG.bets("held")
    assert held_bets.max() < 1 / (1 - CONFIG.max_drop)
    np.testing.assert_allclose(np.exp(paths["held"]), np.mean((1 - held_bets * 0.9) ** k, axis=1), rtol=1e-12)


def test_decision_times_of_constant_streams():
    threshold = CONFIG.threshold
    assert threshold == pytest.approx(40.0)
    verdict, used = first_decisions(np.full(100, -1.0), CONFIG)
    assert verdict == "REGRESSED" and used == _first_crossing(1 + CONFIG.bets("regression"), threshold)
    verdict, used = first_decisions(np.full(100, 1.0), CONFIG)  # both IMPROVED and HELD cross; held is faster
    held_k = _first_crossing(1 + CONFIG.bets("held") * 1.1, threshold)
    assert used == min(held_k, _first_crossing(1 + CONFIG.bets("improvement"), threshold))
    verdict, used = first_decisions(np.zeros(200), CONFIG)  # identical outcomes: only HELD can be shown
    assert verdict == "HELD" and used == _first_crossing(1 + CONFIG.bets("held") * 0.1, threshold)
    verdict, used = first_decisions(np.zeros(5), CONFIG)
    assert verdict == "UNDERPOWERED" and used == 5


def test_incremental_test_agrees_with_the_vectorised_paths():
    rng = np.random.default_rng(3)
    for y in simulate_pairs(0.7, 0.5, 150, 5, rng):
        verdict, used = first_decisions(y, CONFIG)
        test = SequentialTest(CONFIG)
        for value in y:
            if test.add(float(value)) is not None:
                break
        assert (test.verdict or "UNDERPOWERED") == verdict and test.units == used
        log_regression = log_wealth_paths(y[:used], CONFIG)["regression"][-1]
        assert test.wealth("regression") == pytest.approx(np.exp(log_regression), rel=1e-9)


def test_simulated_outcomes_have_the_requested_rates():
    y = simulate_pairs(0.8, 0.5, 1000, 200, np.random.default_rng(0), correlation=0.5)
    assert y.mean() == pytest.approx(-0.3, abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("rate, correlation", [(0.5, 0.0), (0.8, 0.5)])
def test_type_one_error_on_equal_policies_is_at_most_alpha(rate, correlation):
    start = time.perf_counter()
    y = simulate_pairs(rate, rate, pairs=200, runs=2000, rng=np.random.default_rng(11), correlation=correlation)
    verdict, used = first_decisions(y, CONFIG)
    false_difference = np.mean((verdict == "REGRESSED") | (verdict == "IMPROVED"))
    print(f"equal policies p={rate} corr={correlation}: false REGRESSED/IMPROVED {false_difference:.4f}, "
          f"HELD {np.mean(verdict == 'HELD'):.3f}, mean pairs {used.mean():.1f}")
    assert false_difference <= CONFIG.alpha
    assert time.perf_counter() - start < 20


@pytest.mark.slow
def test_power_on_a_30_point_drop_and_early_stopping():
    start = time.perf_counter()
    y = simulate_pairs(0.8, 0.5, pairs=200, runs=2000, rng=np.random.default_rng(12))
    verdict, used = first_decisions(y, CONFIG)
    power = np.mean(verdict == "REGRESSED")
    # the fixed-size McNemar test on independent arms: discordance rates 0.8*0.5 = 0.4 and 0.2*0.5 = 0.1
    fixed_80, fixed_95 = mcnemar_sample_size(0.4, 0.1, 0.05, 0.8), mcnemar_sample_size(0.4, 0.1, 0.05, 0.95)
    print(f"30-point drop: power {power:.4f}, pairs used mean {used.mean():.1f} median {np.median(used):.0f}, "
          f"fixed-size McNemar {fixed_80} (80% power) / {fixed_95} (95% power)")
    assert power >= 0.95
    assert used.mean() < fixed_95  # stops earlier on average than a fixed test of comparable power
    assert time.perf_counter() - start < 20
