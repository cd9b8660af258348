"""The bin benchmark's metrics (don_gym.evaluation.bin_metrics) on hand-made episode records with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from don_gym.evaluation.bin_metrics import EPISODE_KEYS, bin_rates, paired_ratio, placements_per_hour, rate_cells


def _episode(pile: int, **counts) -> dict:
    record = {key: 0 for key in EPISODE_KEYS}
    record |= {"method": "m", "pile": pile, "seed": pile, "cleared": False, "end_reason": "cleared"}
    record |= {"agent_error": None, "motion_seconds": 0.0, "perception_seconds": 0.0}
    return record | counts


#: Three piles of 3 targets each:
#: - pile 0: 3 attempts, all placed (one of them after a regrasp), cleared, 30 s of motion, 1.5 s of perception;
#: - pile 1: 5 attempts: 1 placed, 1 lifted but dropped (flipped), 2 fails, 1 wrong part; one regrasp that failed;
#:   the step limit; 50 s + 2.5 s;
#: - pile 2: the agent gave up after 1 placement in 1 attempt: 9 s + 1 s.
EPISODES = [
    _episode(0, targets=3, attempts=3, picks=3, cleared=True, target_axis_lifts=3, regrasps=1, regrasp_placed=1,
             motion_seconds=30.0, perception_seconds=1.5),
    _episode(1, targets=3, attempts=5, picks=1, grasp_only=1, fails=2, wrong_part_picks=1, target_axis_lifts=2,
             flipped=1, regrasps=1, end_reason="step_limit", motion_seconds=50.0, perception_seconds=2.5),
    _episode(2, targets=3, attempts=1, picks=1, target_axis_lifts=1, agent_error="no instance",
             end_reason="agent_gave_up", motion_seconds=9.0, perception_seconds=1.0),
]  # fmt: skip


def test_each_rate_counts_what_it_says():
    rates = bin_rates(EPISODES)
    assert rates["placed_per_target"] == (5, 9)  # the headline: giving up counts the targets left as failures
    assert rates["picks_per_attempt"] == (5, 9)
    assert rates["lifts_per_attempt"] == (6, 9)  # placed or not, the target lifted
    assert rates["piles_fully_placed"] == (1, 3)
    assert rates["clearance"] == (1, 3)
    assert rates["gave_up"] == (1, 3)
    assert rates["wrong_part"] == (1, 7)  # per lift of anything
    assert rates["flipped"] == (1, 6)
    assert rates["regrasps"] == (2, 9)
    assert rates["regrasp_success"] == (1, 2)


def test_cells_carry_wilson_intervals_around_the_rate():
    cells = rate_cells(EPISODES)
    headline = cells["placed_per_target"]
    assert headline["rate"] == pytest.approx(5 / 9)
    low, high = headline["interval_95"]
    assert 0.2 < low < 5 / 9 < high < 0.85
    assert rate_cells([])["picks_per_attempt"]["rate"] is None


def test_placements_per_hour_charge_motion_and_perception():
    hour = placements_per_hour(EPISODES, resamples=200)
    # 5 placements in 30 + 1.5 + 50 + 2.5 + 9 + 1 = 94 s.
    assert hour["per_hour"] == pytest.approx(5 / 94 * 3600)
    assert hour["cycle_s"] == pytest.approx(94 / 9)
    assert hour["motion_s_per_attempt"] == pytest.approx(89 / 9)
    assert hour["perception_s_per_attempt"] == pytest.approx(5 / 9)
    low, high = hour["interval_95"]
    assert low <= hour["per_hour"] <= high and low < high
    assert placements_per_hour([_episode(0, targets=3)])["per_hour"] is None


def test_ratios_to_a_baseline_are_paired_by_pile():
    # The baseline places everything, twice as fast; a pile only one method ran is left out.
    baseline = [
        _episode(p, targets=3, attempts=3, picks=3, motion_seconds=e["motion_seconds"] / 2)
        for p, e in enumerate(EPISODES)
    ] + [_episode(7, targets=3, attempts=3, picks=0, motion_seconds=10.0)]
    placed = paired_ratio(EPISODES, baseline, "placed_per_target", resamples=200)
    assert placed["piles"] == 3 and placed["ratio"] == pytest.approx(5 / 9)
    hour = paired_ratio(EPISODES, baseline, "per_hour", resamples=200)
    assert hour["ratio"] == pytest.approx((5 / 94) / (9 / 44.5))
    low, high = hour["interval_95"]
    assert np.isfinite(low) and low <= hour["ratio"] <= high
    # The same records: a ratio of 1 in every resample.
    assert paired_ratio(EPISODES, EPISODES, "placed_per_target", resamples=50)["interval_95"] == [1.0, 1.0]
