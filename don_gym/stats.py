"""Statistics for the rates the benchmarks report: how far a success count out of a few episodes can be trusted.

:func:`wilson_interval` is the Wilson score interval of a binomial proportion, which stays inside [0, 1]
and is informative at 0/n and n/n, where the normal approximation collapses to a point;
:func:`format_rate` writes a count with its interval, e.g. ``22/24 (74-98%)``.
"""

from __future__ import annotations

import math
from statistics import NormalDist

from don_gym.errors import DonGymError

#: Confidence level of the intervals the benchmarks print.
DEFAULT_CONFIDENCE = 0.95


def wilson_interval(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> tuple[float, float]:
    """(low, high) Wilson score interval of the success probability after ``successes`` out of ``trials``.

    ``trials=0`` gives (0, 1): no episodes say nothing.
    """
    if isinstance(successes, bool) or isinstance(trials, bool) or int(successes) != successes or int(trials) != trials:
        raise DonGymError(f"successes={successes!r}, trials={trials!r}: expected integer counts")
    if not 0 <= successes <= trials:
        raise DonGymError(f"successes={successes}, trials={trials}: expected 0 <= successes <= trials")
    if not 0.0 < confidence < 1.0:
        raise DonGymError(f"confidence={confidence!r}: expected a level in (0, 1), e.g. 0.95")
    if trials == 0:
        return 0.0, 1.0
    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    n, p = float(trials), successes / trials
    denominator = 1.0 + z * z / n
    center = (p + z * z / (2.0 * n)) / denominator
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4.0 * n * n)) / denominator
    # The bounds are exactly 0 and 1 at 0/n and n/n; rounding must not move them past.
    return max(0.0, center - half), min(1.0, center + half)


def format_interval(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> str:
    """``"74-98%"``: the Wilson interval of ``successes`` out of ``trials`` in whole percent."""
    low, high = wilson_interval(successes, trials, confidence)
    return f"{100.0 * low:.0f}-{100.0 * high:.0f}%"


def format_rate(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> str:
    """``"22/24 (74-98%)"``: the count and its Wilson interval in whole percent."""
    return f"{successes}/{trials} ({format_interval(successes, trials, confidence)})"
