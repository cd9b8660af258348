"""The bin benchmark's metrics, pure: episode records (one per pile and method, :data:`EPISODE_KEYS`) in, counts,
rates with their Wilson intervals and the hourly rate out. The runner is :mod:`don_gym.evaluation.bin_benchmark`.

The field measures bin picking by what reaches the receptacle: the headline is *placed per target instance*
(target parts placed correctly in the cradle over the target parts in the piles, so a pile given up counts its
parts left as failures), beside the reliability of each attempt (*picks per attempt*, Dex-Net's reliability),
*lift success per attempt* (the clutter-removal protocol's grasp success), *piles fully placed*, *give-ups*,
*wrong-part lifts*, *flips* and *regrasps* with their success, and the pace: *mean placements per hour* of
simulated time, where each attempt is charged the scripted motion's simulated seconds (grasp, carry, place, a
regrasp), the move back to the observation pose at the script's free-space speed, and the method's perception
and planning time measured on the machine that ran it (:func:`placements_per_hour`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "EPISODE_KEYS",
    "RATE_COLUMNS",
    "bin_rates",
    "paired_ratio",
    "placements_per_hour",
    "rate_cells",
]

#: Keys of an episode record (bin_episodes.json): the pile, its targets and how it ended; per attempt outcome the
#: counts (``picks``: target instances placed correctly; ``grasp_only``: target instances lifted and not placed;
#: ``fails``: nothing lifted; ``wrong_part_picks``: another part lifted); ``target_axis_lifts``: target lifts by a
#: grasp across or along the axis, of which ``flipped`` had the believed +axis more than 90 degrees off the true
#: one; ``regrasps`` (attempts that went through the regrasp station) and ``regrasp_placed`` (of those, placed);
#: ``pushes`` (steps that rolled a part away from a wall or toppled a standing one: no attempts), ``topples`` (of
#: those, the topples);
#: ``motion_seconds`` (simulated seconds of the scripted motion and of the moves back to the observation pose),
#: ``perception_seconds`` (the agent's measured time choosing its actions); ``agent_error`` (the agent gave up);
#: ``seconds`` (wall time of the episode).
EPISODE_KEYS = (
    "method",
    "pile",
    "seed",
    "cleared",
    "end_reason",
    "targets",
    "attempts",
    "picks",
    "grasp_only",
    "fails",
    "wrong_part_picks",
    "target_axis_lifts",
    "flipped",
    "regrasps",
    "regrasp_placed",
    "pushes",
    "topples",
    "motion_seconds",
    "perception_seconds",
    "agent_error",
    "seconds",
)

#: The rates of the table, (name in :func:`bin_rates`, label), the headline first.
RATE_COLUMNS = (
    ("placed_per_target", "placed per target instance"),
    ("picks_per_attempt", "picks per attempt"),
    ("lifts_per_attempt", "lift success per attempt"),
    ("piles_fully_placed", "piles fully placed"),
    ("gave_up", "piles given up"),
    ("wrong_part", "wrong-part lifts (per lift)"),
    ("flipped", "flips (per axis-grasp lift)"),
    ("regrasps", "regrasps (per attempt)"),
    ("regrasp_success", "regrasps placed"),
)


def _total(episodes: Sequence[Mapping[str, Any]], key: str) -> int:
    return sum(int(e.get(key, 0)) for e in episodes)


def bin_rates(episodes: Sequence[Mapping[str, Any]]) -> dict[str, tuple[int, int]]:
    """``{name: (count, out of)}`` over episode records (:data:`EPISODE_KEYS`):

    - ``placed_per_target``: target instances placed / target instances in the piles,
    - ``picks_per_attempt``: placed / attempts, ``lifts_per_attempt``: target instances lifted (placed or not) /
      attempts,
    - ``piles_fully_placed``: piles whose every target instance was placed / piles, ``clearance``: piles ended
      with no target left in the bin (placed or not) / piles, ``gave_up``: piles the agent gave up on / piles,
    - ``wrong_part``: instances of another part lifted / lifts of anything,
    - ``flipped``: flipped / target lifts by a grasp across or along the axis,
    - ``regrasps``: regrasps / attempts, ``regrasp_success``: regrasps placed / regrasps.
    """
    picks, grasp_only, wrong = (_total(episodes, k) for k in ("picks", "grasp_only", "wrong_part_picks"))
    attempts, regrasps = _total(episodes, "attempts"), _total(episodes, "regrasps")
    piles = len(episodes)
    return {
        "placed_per_target": (picks, _total(episodes, "targets")),
        "picks_per_attempt": (picks, attempts),
        "lifts_per_attempt": (picks + grasp_only, attempts),
        "piles_fully_placed": (sum(int(e["picks"]) == int(e["targets"]) for e in episodes), piles),
        "clearance": (sum(bool(e["cleared"]) for e in episodes), piles),
        "gave_up": (sum(e.get("agent_error") is not None for e in episodes), piles),
        "wrong_part": (wrong, picks + grasp_only + wrong),
        "flipped": (_total(episodes, "flipped"), _total(episodes, "target_axis_lifts")),
        "regrasps": (regrasps, attempts),
        "regrasp_success": (_total(episodes, "regrasp_placed"), regrasps),
    }


def rate_cells(episodes: Sequence[Mapping[str, Any]], confidence: float = 0.95) -> dict[str, dict[str, Any]]:
    """Every rate of :func:`bin_rates` with ``count``, ``total``, ``rate`` (None without trials) and its Wilson
    ``interval_95``."""
    from don_gym.stats import wilson_interval

    return {
        name: {
            "count": count,
            "total": total,
            "rate": count / total if total else None,
            "interval_95": list(wilson_interval(count, total, confidence)),
        }
        for name, (count, total) in bin_rates(episodes).items()
    }


def _pile_arrays(episodes: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pile (in the given order): placements, attempts, motion seconds, perception seconds."""
    picks = np.array([float(e["picks"]) for e in episodes])
    attempts = np.array([float(e["attempts"]) for e in episodes])
    motion = np.array([float(e.get("motion_seconds", 0.0)) for e in episodes])
    perception = np.array([float(e.get("perception_seconds", 0.0)) for e in episodes])
    return picks, attempts, motion, perception


def placements_per_hour(
    episodes: Sequence[Mapping[str, Any]], resamples: int | None = None, seed: int = 0
) -> dict[str, Any]:
    """Mean placements per hour of simulated time: placements / (motion + perception seconds) x 3600, pooled over
    the piles, with what an attempt is charged on average (``motion_s_per_attempt``, ``perception_s_per_attempt``,
    ``cycle_s``: seconds per attempt) and a 95% interval from resampling piles (:mod:`don_gym.stats`; ``resamples``
    None: its default). ``per_hour`` is None when no time was charged."""
    from don_gym.stats import BOOTSTRAP_RESAMPLES, percentile_interval, scene_resample_counts

    picks, attempts, motion, perception = _pile_arrays(episodes)
    seconds = motion + perception
    total_s, total_attempts = float(seconds.sum()), float(attempts.sum())
    out: dict[str, Any] = {
        "placements": int(picks.sum()),
        "attempts": int(total_attempts),
        "seconds": total_s,
        "motion_s_per_attempt": float(motion.sum()) / total_attempts if total_attempts else None,
        "perception_s_per_attempt": float(perception.sum()) / total_attempts if total_attempts else None,
        "cycle_s": total_s / total_attempts if total_attempts else None,
        "per_hour": 3600.0 * float(picks.sum()) / total_s if total_s > 0 else None,
        "interval_95": [float("nan"), float("nan")],
    }
    if total_s > 0 and len(episodes) > 1:
        counts = scene_resample_counts(len(episodes), resamples or BOOTSTRAP_RESAMPLES, seed).astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            replicates = 3600.0 * (counts @ picks) / (counts @ seconds)
        out["interval_95"] = [float(v) for v in percentile_interval(replicates[np.isfinite(replicates)])]
    return out


def paired_ratio(
    episodes: Sequence[Mapping[str, Any]],
    baseline: Sequence[Mapping[str, Any]],
    measure: str,
    resamples: int | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """A method's figure over a baseline's on the same piles (records matched by ``pile``), with a 95% interval
    from resampling piles, the same resample for both (paired). ``measure``: ``"placed_per_target"`` (placements
    over target instances) or ``"per_hour"`` (placements over charged seconds). ``ratio`` None when the baseline's
    figure is 0."""
    from don_gym.stats import BOOTSTRAP_RESAMPLES, percentile_interval, scene_resample_counts

    if measure not in ("placed_per_target", "per_hour"):
        raise ValueError(f"measure={measure!r}: expected 'placed_per_target' or 'per_hour'")
    by_pile = {int(e["pile"]): e for e in baseline}
    piles = sorted(int(e["pile"]) for e in episodes if int(e["pile"]) in by_pile)
    mine = {int(e["pile"]): e for e in episodes}

    def parts(records: list[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
        picks, _, motion, perception = _pile_arrays(records)
        below = np.array([float(e["targets"]) for e in records]) if measure == "placed_per_target" else None
        return picks, (motion + perception if below is None else below)

    a_num, a_den = parts([mine[p] for p in piles])
    b_num, b_den = parts([by_pile[p] for p in piles])

    def ratio(weights: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return (weights @ a_num / (weights @ a_den)) / (weights @ b_num / (weights @ b_den))

    point = ratio(np.ones((1, len(piles))))[0] if piles else float("nan")
    out: dict[str, Any] = {"piles": len(piles), "ratio": float(point) if np.isfinite(point) else None}
    out["interval_95"] = [float("nan"), float("nan")]
    if len(piles) > 1 and out["ratio"] is not None:
        counts = scene_resample_counts(len(piles), resamples or BOOTSTRAP_RESAMPLES, seed).astype(np.float64)
        replicates = ratio(counts)
        out["interval_95"] = [float(v) for v in percentile_interval(replicates[np.isfinite(replicates)])]
    return out
