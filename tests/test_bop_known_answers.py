"""BOP's own conventions on hand-made inputs whose answer is known: a pose counts as correct when its error is
strictly below a threshold; ``scene_gt_info``'s boxes, counts and visible fraction (the silhouette beyond the
image border counted, depth validity over the whole silhouette), as bop_toolkit computes them."""

from __future__ import annotations

import numpy as np
import pytest

from don_gym.data.bop import bbox_of, gt_info
from don_gym.evaluation.pose_metrics import MSPD_THRESHOLDS_PX, MSSD_THRESHOLDS, pose_recalls


def test_an_error_on_a_threshold_is_not_below_it() -> None:
    diameter = 0.05
    # MSSD exactly at 0.05 and 0.30 of the diameter, MSPD exactly at 5 px (at 640 px width) and 20 px at 320 px.
    recalls = pose_recalls(
        mssd_m=[0.05 * diameter, 0.30 * diameter],
        mspd_px=[5.0, 10.0],
        adds_m=[0.1 * diameter, 0.02 * diameter],
        diameter_m=diameter,
        image_width_px=[640, 320],
    )
    thresholds = np.asarray(MSSD_THRESHOLDS)
    expected = (0.05 < thresholds).astype(float) / 2 + (0.30 < thresholds).astype(float) / 2
    np.testing.assert_allclose(recalls["mssd_recall"], expected)
    pixels = np.asarray(MSPD_THRESHOLDS_PX)
    expected_px = ((5.0 < pixels).astype(float) + (20.0 < pixels).astype(float)) / 2
    np.testing.assert_allclose(recalls["mspd_recall"], expected_px)
    assert recalls["adds_share"] == 0.5  # ADD-S at 10% of the diameter is not below 10%
    assert recalls["ar"] == pytest.approx((np.mean(expected) + np.mean(expected_px)) / 2)


def test_gt_info_of_a_part_half_beyond_the_border_and_partly_hidden() -> None:
    silhouette = np.zeros((6, 8), dtype=bool)
    silhouette[1:5, 4:8] = True  # 16 pixels in the image; the part goes on beyond the right border
    visible = silhouette.copy()
    visible[1:3, 4:6] = False  # 4 hidden by something in front: 12 visible
    depth_valid = np.ones((6, 8), dtype=bool)
    depth_valid[4, :] = False  # no depth on the bottom row: 4 pixels of the silhouette, 4 of them visible
    info = gt_info(silhouette, visible, depth_valid, mask_all_count=32)
    assert info["px_count_all"] == 32 and info["px_count_visib"] == 12
    assert info["px_count_valid"] == 12  # the silhouette's pixels with depth, hidden ones included
    assert info["visib_fract"] == pytest.approx(12 / 32)  # against the whole silhouette, not its part in the image
    assert info["bbox_visib"] == [4, 1, 3, 3]  # x, y, max - min as bop_toolkit's calc_2d_bbox
    assert bbox_of(silhouette) == [4, 1, 3, 3] and bbox_of(np.zeros((2, 2), bool)) == [-1, -1, -1, -1]
    hidden = gt_info(silhouette, np.zeros_like(visible), depth_valid, mask_all_count=32)
    assert hidden["visib_fract"] == 0.0 and hidden["bbox_visib"] == [-1, -1, -1, -1]
