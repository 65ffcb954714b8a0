"""Success-rate statistics: binomial confidence intervals as pure functions.

Every function takes counts (successes out of n episodes) and returns plain floats; nothing here reads files or
knows about runs. Methods:

- Wilson score interval (Wilson 1927; Newcombe 1998, method 3): the default. Good coverage at small n and near
  0 or 1, never leaves [0, 1].
- Clopper–Pearson "exact" interval (Clopper & Pearson 1934; Newcombe 1998, method 5): from beta quantiles;
  conservative (coverage >= the nominal level), wider than Wilson.

With n = 0 nothing is known: the success rate is NaN and the interval is the whole range [0, 1].
"""
from __future__ import annotations

import math

from scipy.stats import beta, norm

METHODS = ("wilson", "clopper-pearson")


def _check(successes: int, n: int, confidence: float) -> None:
    if isinstance(successes, bool) or isinstance(n, bool) or int(successes) != successes or int(n) != n:
        raise ValueError(f"successes and n must be integers, got successes={successes!r}, n={n!r}")
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if not (0.0 < confidence < 1.0):
        raise ValueError(f"confidence must be strictly between 0 and 1, got {confidence!r}")


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion successes/n (two-sided, without continuity correction).

    Returns (low, high) within [0, 1]; (0.0, 1.0) when n == 0.
    """
    _check(successes, n, confidence)
    if n == 0:
        return 0.0, 1.0
    z = float(norm.ppf(0.5 + confidence / 2.0))
    p = successes / n
    z2n = z * z / n
    centre = (p + z2n / 2.0) / (1.0 + z2n)
    half = (z / (1.0 + z2n)) * math.sqrt(p * (1.0 - p) / n + z * z / (4.0 * n * n))
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


def clopper_pearson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Clopper–Pearson ("exact") interval for successes/n from beta-distribution quantiles.

    Returns (low, high) within [0, 1]; low is 0 when successes == 0, high is 1 when successes == n,
    (0.0, 1.0) when n == 0.
    """
    _check(successes, n, confidence)
    if n == 0:
        return 0.0, 1.0
    alpha = 1.0 - confidence
    low = 0.0 if successes == 0 else float(beta.ppf(alpha / 2.0, successes, n - successes + 1))
    high = 1.0 if successes == n else float(beta.ppf(1.0 - alpha / 2.0, successes + 1, n - successes))
    return low, high


def success_summary(successes: int, n: int, method: str = "wilson", confidence: float = 0.95) -> dict:
    """One row of success statistics: {n, successes, success_rate, ci_low, ci_high, method, confidence}.

    success_rate is NaN when n == 0. method is "wilson" (default) or "clopper-pearson"
    ("clopper_pearson" and "exact" are accepted spellings of the latter).
    """
    key = method.lower().replace("_", "-")
    if key == "exact":
        key = "clopper-pearson"
    if key not in METHODS:
        raise ValueError(f"unknown interval method {method!r}; use one of: {', '.join(METHODS)}")
    interval = wilson_interval if key == "wilson" else clopper_pearson_interval
    low, high = interval(successes, n, confidence)
    return {
        "n": int(n),
        "successes": int(successes),
        "success_rate": (successes / n) if n else float("nan"),
        "ci_low": low,
        "ci_high": high,
        "method": key,
        "confidence": confidence,
    }
