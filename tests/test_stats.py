"""Wilson score intervals of the benchmark rates against published values; the scene bootstrap."""

from __future__ import annotations

import numpy as np
import pytest

from don_gym.errors import DonGymError
from don_gym.stats import (
    format_estimate,
    format_interval,
    format_rate,
    resampled_percentiles,
    scene_bootstrap_mean,
    scene_bootstrap_percentiles,
    scene_resample_counts,
    wilson_interval,
)


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


def _scenes_with_one_bad(scenes: int = 12, per_scene: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Errors of ``scenes`` scenes, ``per_scene`` matches each, all near 5 mm except that one scene holds every
    far match (half its matches at 300 mm): 50 far matches of 1200."""
    rng = np.random.default_rng(1)
    errors = rng.uniform(3.0, 7.0, size=(scenes, per_scene))
    errors[0, : per_scene // 2] = 300.0
    return errors.ravel(), np.repeat(np.arange(scenes), per_scene)


def test_scene_bootstrap_of_far_matches_in_one_scene_is_wide_and_unlike_resampling_matches() -> None:
    errors, scene = _scenes_with_one_bad()
    far = (errors > 100.0).astype(float)
    by_scene = scene_bootstrap_mean(far, scene)
    by_match = scene_bootstrap_mean(far, np.arange(len(far)))  # every match its own group
    # The share is 50/1200 = 4.2%. Drawn by scene, the bad scene is absent from about a third of the
    # resamples (share 0) and twice or more in a quarter of them: the interval runs from 0 to past 10%.
    assert by_scene[0] == 0.0 and by_scene[1] > 0.1
    # Drawn by match, the 50 far matches look independent: a narrow interval around 4.2%.
    assert 0.025 < by_match[0] < 0.042 < by_match[1] < 0.06
    # The same for the 99th percentile: by scene it spans from the good scenes' errors to the bad one's.
    p99_scene = scene_bootstrap_percentiles(errors, scene, [99])[0]
    p99_match = scene_bootstrap_percentiles(errors, np.arange(len(errors)), [99])[0]
    assert p99_scene[0] < 8.0 and p99_scene[1] == pytest.approx(300.0)
    assert p99_match[0] == pytest.approx(300.0)


def test_scene_bootstrap_is_seeded_and_its_percentiles_are_numpys() -> None:
    errors, scene = _scenes_with_one_bad()
    errors[5] = np.nan  # left out, like a match without depth
    first = scene_bootstrap_percentiles(errors, scene, [50, 90, 99], seed=3)
    np.testing.assert_array_equal(first, scene_bootstrap_percentiles(errors, scene, [50, 90, 99], seed=3))
    assert not np.array_equal(first, scene_bootstrap_percentiles(errors, scene, [50, 90, 99], seed=4))
    assert first.shape == (3, 2) and (first[:, 0] <= first[:, 1]).all()
    # A resample is every value of each drawn scene, as often as it is drawn: numpy's percentile of that sample.
    counts = scene_resample_counts(12, resamples=5, seed=0)
    assert (counts.sum(axis=1) == 12).all()
    replicates = resampled_percentiles(errors, scene, counts, [1, 50, 97.5])
    for row, drawn in zip(replicates, counts, strict=True):
        pooled = np.concatenate([errors[scene == s] for s in range(12) for _ in range(drawn[s])])
        np.testing.assert_allclose(row, np.nanpercentile(pooled, [1, 50, 97.5]))
    with pytest.raises(DonGymError, match="scene"):
        resampled_percentiles(errors, scene[:-1], counts, [50])


def test_estimate_text() -> None:
    assert format_estimate(39.49, [31.04, 52.26]) == "39.5 [31.0, 52.3]"
    assert format_estimate(0.0123, (0.01, 0.02), digits=3) == "0.012 [0.010, 0.020]"
    assert format_estimate(None, [1.0, 2.0]) == "-"
    assert format_estimate(2.0, None) == "2.0"


def _wilson_by_formula(successes: int, trials: int, confidence: float) -> tuple[float, float]:
    """The Wilson score interval written out (Wilson 1927), independent of SciPy."""
    from statistics import NormalDist

    z = NormalDist().inv_cdf(0.5 + confidence / 2.0)
    n, p = float(trials), successes / trials
    denominator = 1.0 + z * z / n
    centre = (p + z * z / (2.0 * n)) / denominator
    half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)) ** 0.5 / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


@pytest.mark.parametrize("confidence", [0.8, 0.95, 0.99])
def test_wilson_interval_equals_the_formula_on_a_grid_of_counts(confidence: float) -> None:
    for trials in (1, 2, 3, 7, 8, 24, 100, 211, 1000):
        for successes in sorted({0, 1, trials // 3, trials // 2, trials - 1, trials}):
            if 0 <= successes <= trials:
                got = wilson_interval(successes, trials, confidence)
                assert got == pytest.approx(_wilson_by_formula(successes, trials, confidence), abs=1e-12), (
                    successes,
                    trials,
                )
