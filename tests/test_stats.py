"""Wilson score intervals of the benchmark rates against published values."""

from __future__ import annotations

import pytest

from don_gym.errors import DonGymError
from don_gym.stats import format_interval, format_rate, wilson_interval


def test_wilson_interval_known_values() -> None:
    # 95% Wilson intervals: 0/8 -> (0, 0.3244), 8/8 -> (0.6756, 1), 4/8 -> (0.2152, 0.7848).
    assert wilson_interval(0, 8) == pytest.approx((0.0, 0.32441), abs=1e-5)
    assert wilson_interval(8, 8) == pytest.approx((0.67559, 1.0), abs=1e-5)
    assert wilson_interval(4, 8) == pytest.approx((0.21522, 0.78478), abs=1e-5)
    assert wilson_interval(22, 24) == pytest.approx((0.74151, 0.97684), abs=1e-5)
    # Wider at a higher confidence level; no episodes say nothing.
    low99, high99 = wilson_interval(4, 8, confidence=0.99)
    assert low99 < 0.2152 and high99 > 0.7848
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_rate_text() -> None:
    assert format_rate(22, 24) == "22/24 (74-98%)"
    assert format_rate(0, 8) == "0/8 (0-32%)"
    assert format_rate(8, 8) == "8/8 (68-100%)"
    assert format_interval(4, 8) == "22-78%"


@pytest.mark.parametrize(("successes", "trials"), [(9, 8), (-1, 8), (1.5, 8), (True, 8)])
def test_bad_counts_are_refused(successes, trials) -> None:
    with pytest.raises(DonGymError, match="successes"):
        wilson_interval(successes, trials)
