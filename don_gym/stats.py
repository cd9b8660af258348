"""Statistics for the figures the benchmarks report: how far a rate or a percentile from a small sample can be trusted.

:func:`wilson_interval` is the Wilson score interval of a binomial proportion, which stays inside [0, 1]
and is informative at 0/n and n/n, where the normal approximation collapses to a point;
:func:`format_rate` writes a count with its interval, e.g. ``22/24 (74-98%)``.

The scene bootstrap (:func:`scene_bootstrap_percentiles`, and underneath it :func:`scene_resample_counts`,
:func:`resampled_percentiles`, :func:`resampled_means`, :func:`percentile_interval`) gives intervals for
statistics of matches that come in correlated groups: tracking matches of one scene share its background,
lighting and part pose, so a scene that goes wrong makes many far matches at once. Resampling single
matches would treat them as independent and give intervals far too narrow; the scenes are resampled.
:func:`format_estimate` writes a figure with its interval, e.g. ``39.5 [31.0, 52.3]``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np

from don_gym.errors import DonGymError

#: Confidence level of the intervals the benchmarks print.
DEFAULT_CONFIDENCE = 0.95
#: Resamples of the scene bootstrap: enough that the 2.5 and 97.5 percentiles of the replicates move by
#: well under the figures' rounding from one seed to another.
BOOTSTRAP_RESAMPLES = 2000
#: Resamples are drawn in blocks of this many, which bounds the (block, matches) weight arrays in memory.
_BLOCK = 128


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise DonGymError(f"confidence={confidence!r}: expected a level in (0, 1), e.g. 0.95")


def wilson_interval(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> tuple[float, float]:
    """(low, high) Wilson score interval of the success probability after ``successes`` out of ``trials``.

    ``trials=0`` gives (0, 1): no episodes say nothing.
    """
    if isinstance(successes, bool) or isinstance(trials, bool) or int(successes) != successes or int(trials) != trials:
        raise DonGymError(f"successes={successes!r}, trials={trials!r}: expected integer counts")
    if not 0 <= successes <= trials:
        raise DonGymError(f"successes={successes}, trials={trials}: expected 0 <= successes <= trials")
    _check_confidence(confidence)
    if trials == 0:
        return 0.0, 1.0
    from scipy.stats import binomtest  # SciPy's own Wilson score interval; imported here, it loads slowly

    interval = binomtest(int(successes), int(trials)).proportion_ci(confidence_level=confidence, method="wilson")
    # The bounds are exactly 0 and 1 at 0/n and n/n; rounding must not move them past.
    return max(0.0, float(interval.low)), min(1.0, float(interval.high))


def format_interval(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> str:
    """``"74-98%"``: the Wilson interval of ``successes`` out of ``trials`` in whole percent."""
    low, high = wilson_interval(successes, trials, confidence)
    return f"{100.0 * low:.0f}-{100.0 * high:.0f}%"


def format_rate(successes: int, trials: int, confidence: float = DEFAULT_CONFIDENCE) -> str:
    """``"22/24 (74-98%)"``: the count and its Wilson interval in whole percent."""
    return f"{successes}/{trials} ({format_interval(successes, trials, confidence)})"


def scene_resample_counts(n_scenes: int, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> np.ndarray:
    """(resamples, n_scenes) int64: how often each scene is drawn when ``n_scenes`` scenes are drawn with
    replacement, once per resample. Every row sums to ``n_scenes``.

    The counts depend only on ``n_scenes``, ``resamples`` and ``seed``: statistics of several methods
    evaluated on the same scenes, resampled with the same counts, are paired resample by resample.
    """
    if isinstance(n_scenes, bool) or int(n_scenes) != n_scenes or n_scenes < 1:
        raise DonGymError(f"n_scenes={n_scenes!r}: expected an integer >= 1")
    if isinstance(resamples, bool) or int(resamples) != resamples or resamples < 1:
        raise DonGymError(f"resamples={resamples!r}: expected an integer >= 1")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(n_scenes)]))
    return rng.multinomial(int(n_scenes), np.full(int(n_scenes), 1.0 / n_scenes), size=int(resamples))


def _finite_with_scenes(values: np.ndarray, scene: np.ndarray, n_scenes: int) -> tuple[np.ndarray, np.ndarray]:
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    scene = np.asarray(scene).reshape(-1)
    if len(scene) != len(values):
        raise DonGymError(f"scene has {len(scene)} entries for {len(values)} values; expected one per value")
    if len(scene) and (not np.issubdtype(scene.dtype, np.integer) or scene.min() < 0 or scene.max() >= n_scenes):
        raise DonGymError(f"scene labels must be integers in [0, {n_scenes}), one per value")
    keep = np.isfinite(values)
    return values[keep], scene[keep].astype(np.int64)


def resampled_percentiles(values: np.ndarray, scene: np.ndarray, counts: np.ndarray, q: Sequence[float]) -> np.ndarray:
    """(R, Q) percentiles ``q`` (0-100) of the finite ``values`` in each of the R resamples ``counts``.

    Args:
        values: (M,) values; NaN and infinities are left out (e.g. matches without depth).
        scene: (M,) int scene of each value, in [0, S).
        counts: (R, S) how often each scene is drawn per resample (:func:`scene_resample_counts`).
        q: percentiles.

    A resample holds every value of a scene as often as the scene is drawn; its percentile is
    ``numpy.percentile``'s (linear interpolation) of that pooled sample, computed from cumulative weights
    over the values sorted once. A resample without values gives NaN.
    """
    counts = np.asarray(counts)
    finite, labels = _finite_with_scenes(values, scene, counts.shape[1])
    q = np.asarray(q, dtype=np.float64).reshape(-1)
    out = np.full((len(counts), len(q)), np.nan)
    if len(finite) == 0:
        return out
    order = np.argsort(finite, kind="stable")
    ordered, ordered_scene = finite[order], labels[order]
    for start in range(0, len(counts), _BLOCK):
        weights = counts[start : start + _BLOCK][:, ordered_scene]  # (B, M)
        cumulative = np.cumsum(weights, axis=1)
        total = cumulative[:, -1]
        for column, percent in enumerate(q):
            position = percent / 100.0 * (total - 1)
            below = np.floor(position)
            # The k-th smallest pooled value (0-based) is the first sorted value whose cumulative weight exceeds k.
            low = (cumulative <= below[:, None]).sum(axis=1)
            high = (cumulative <= np.ceil(position)[:, None]).sum(axis=1)
            low, high = np.minimum(low, len(ordered) - 1), np.minimum(high, len(ordered) - 1)
            value = ordered[low] + (position - below) * (ordered[high] - ordered[low])
            out[start : start + _BLOCK, column] = np.where(total > 0, value, np.nan)
    return out


def resampled_means(values: np.ndarray, scene: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(R,) mean of the finite ``values`` in each resample ``counts`` (as :func:`resampled_percentiles`);
    the share of a condition is the mean of a 0/1 array. NaN for a resample without values."""
    counts = np.asarray(counts)
    finite, labels = _finite_with_scenes(values, scene, counts.shape[1])
    sums = np.bincount(labels, weights=finite, minlength=counts.shape[1])
    sizes = np.bincount(labels, minlength=counts.shape[1]).astype(np.float64)
    totals = counts @ sizes
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(totals > 0, (counts @ sums) / totals, np.nan)


def percentile_interval(replicates: np.ndarray, confidence: float = DEFAULT_CONFIDENCE) -> np.ndarray:
    """(..., 2) percentile interval of bootstrap ``replicates`` (R, ...): their (1 - confidence) / 2 and
    (1 + confidence) / 2 quantiles along the first axis, NaN replicates left out (all NaN: NaN)."""
    _check_confidence(confidence)
    replicates = np.asarray(replicates, dtype=np.float64)
    tails = [50.0 * (1.0 - confidence), 50.0 * (1.0 + confidence)]
    if replicates.shape[0] == 0 or np.isnan(replicates).all():
        return np.full((*replicates.shape[1:], 2), np.nan)
    with warnings.catch_warnings():
        # Columns that are all NaN come out NaN; numpy's warning about them is no news to the caller.
        warnings.simplefilter("ignore", RuntimeWarning)
        bounds = np.nanpercentile(replicates, tails, axis=0)
    return np.moveaxis(bounds, 0, -1)


def _label_resample_counts(scene: np.ndarray, resamples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Any hashable scene labels (M,) as indices into their sorted unique values, and the resample counts of
    those scenes (:func:`scene_resample_counts`; one empty scene when there are no labels)."""
    labels, scene_index = np.unique(np.asarray(scene), return_inverse=True)
    counts = scene_resample_counts(len(labels), resamples, seed) if len(labels) else np.zeros((resamples, 1), int)
    return scene_index.reshape(-1), counts


def scene_bootstrap_percentiles(
    values: np.ndarray,
    scene: np.ndarray,
    q: Sequence[float] = (50, 90, 99),
    resamples: int = BOOTSTRAP_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> np.ndarray:
    """(Q, 2) bootstrap intervals of the percentiles ``q`` of ``values`` (M,), resampling the groups given by
    ``scene`` (M,), any hashable labels, e.g. scene indices: the unit drawn is the scene, not the value.
    Non-finite values are left out; seeded, so the same call gives the same intervals."""
    scene_index, counts = _label_resample_counts(scene, resamples, seed)
    return percentile_interval(resampled_percentiles(values, scene_index, counts, q), confidence)


def scene_bootstrap_mean(
    values: np.ndarray,
    scene: np.ndarray,
    resamples: int = BOOTSTRAP_RESAMPLES,
    confidence: float = DEFAULT_CONFIDENCE,
    seed: int = 0,
) -> np.ndarray:
    """(2,) bootstrap interval of the mean of the finite ``values`` (a share, for 0/1 values), resampling
    the groups given by ``scene`` as :func:`scene_bootstrap_percentiles` does."""
    scene_index, counts = _label_resample_counts(scene, resamples, seed)
    return percentile_interval(resampled_means(values, scene_index, counts), confidence)


def format_estimate(value: float | None, interval: Sequence[float] | None = None, digits: int = 1) -> str:
    """``"39.5 [31.0, 52.3]"``: a figure and its interval at ``digits`` decimals; ``"-"`` for a missing
    or non-finite figure, the figure alone when the interval is missing."""
    if value is None or not math.isfinite(value):
        return "-"
    text = f"{value:.{digits}f}"
    if interval is None or len(interval) != 2 or any(v is None or not math.isfinite(v) for v in interval):
        return text
    return f"{text} [{interval[0]:.{digits}f}, {interval[1]:.{digits}f}]"
