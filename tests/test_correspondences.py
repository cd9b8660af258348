"""Correspondence sampling: matches are the same 3D point, occlusion pruning, non-match placement."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_scenes import Sphere, look_at, render_scene, table_scene, world_points

from don_gym.data.correspondences import Correspondences, camera_poses_differ, sample_correspondences
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, project_points, transform_points

BOX_INDEX = 1
T_A = look_at((0.4, 0.0, 0.35), (0.0, 0.0, 0.02))
T_B = look_at((0.0, 0.4, 0.35), (0.0, 0.0, 0.02))


def views(intrinsics: CameraIntrinsics, primitives=None, T_a=T_A, T_b=T_B):
    """Depth and box masks of the table scene from cameras A and B."""
    if primitives is None:
        primitives = table_scene()[0]
    depth_a, index_a = render_scene(intrinsics, T_a, primitives)
    depth_b, index_b = render_scene(intrinsics, T_b, primitives)
    return depth_a, depth_b, index_a == BOX_INDEX, index_b == BOX_INDEX, index_a, index_b


def pixel_set(uv: np.ndarray) -> set[tuple[int, int]]:
    return set(map(tuple, uv.tolist()))


def test_matches_see_the_same_world_point():
    intrinsics = CameraIntrinsics.d435(640, 480)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    rng = np.random.default_rng(0)
    tight = sample_correspondences(
        depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, rng, occlusion_margin_m=0.001, max_depth_excess_m=0.001
    )
    assert tight.num_matches > 5000
    assert tight.matches_a.dtype == np.int64 and tight.matches_b.shape == tight.matches_a.shape
    assert mask_a[tight.matches_a[:, 1], tight.matches_a[:, 0]].all()
    points_a = world_points(intrinsics, T_A, depth_a, tight.matches_a)
    points_b = world_points(intrinsics, T_B, depth_b, tight.matches_b)
    assert np.linalg.norm(points_a - points_b, axis=1).max() < 0.002
    # B's pixel is the nearest pixel to A's point projected into B.
    uv, _ = project_points(intrinsics, transform_points(invert_transform(T_B), points_a))
    assert np.abs(uv - tight.matches_b).max() <= 0.5 + 1e-6


def test_default_margins_bound_the_match_error():
    intrinsics = CameraIntrinsics.d435(320, 240)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    result = sample_correspondences(depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(1))
    error = np.linalg.norm(
        world_points(intrinsics, T_A, depth_a, result.matches_a)
        - world_points(intrinsics, T_B, depth_b, result.matches_b),
        axis=1,
    )
    # Rounding to B's nearest pixel alone moves the point by up to half a pixel's footprint
    # (0.8 mm here at normal incidence, several mm on slanted faces).
    assert np.median(error) < 0.001 and np.percentile(error, 90) < 0.002
    # At most the depth tolerance plus half a pixel's footprint on a slanted surface.
    assert error.max() < 0.007
    # The original one-sided test keeps matches that land on the table behind the box's silhouette.
    one_sided = sample_correspondences(
        depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(1), max_depth_excess_m=np.inf
    )
    error_one_sided = np.linalg.norm(
        world_points(intrinsics, T_A, depth_a, one_sided.matches_a)
        - world_points(intrinsics, T_B, depth_b, one_sided.matches_b),
        axis=1,
    )
    assert error_one_sided.max() > 0.02


def test_occluded_points_are_pruned():
    intrinsics = CameraIntrinsics.d435(160, 120)
    primitives, _ = table_scene()
    # A ball floating between camera B and the box hides part of the box from B, not from A.
    centre = 0.55 * np.array([0.0, 0.4, 0.35]) + 0.45 * np.array([0.0, 0.0, 0.02]) + np.array([0.02, 0.0, 0.0])
    occluder = Sphere(tuple(centre), 0.015)
    depth_a, depth_b, mask_a, mask_b, index_a, index_b = views(intrinsics, primitives + [occluder])
    assert np.array_equal(mask_a, views(intrinsics)[2]) and (index_b == 2).sum() > 100
    result = sample_correspondences(depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(0))
    assert result.num_matches > 500
    assert not (index_b[result.matches_b[:, 1], result.matches_b[:, 0]] == 2).any()
    # The same points without the check land on the occluder: the scene really tests occlusion.
    unchecked = sample_correspondences(
        depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(0), occlusion_margin_m=1.0
    )
    assert (index_b[unchecked.matches_b[:, 1], unchecked.matches_b[:, 0]] == 2).sum() > 50


def test_nonmatches_land_on_the_right_masks():
    intrinsics = CameraIntrinsics.d435(160, 120)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    result = sample_correspondences(
        depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(0), num_match_attempts=300
    )
    n = result.num_matches
    assert n > 200
    assert len(result.nonmatches_background_a) == 75 * n
    # A few object non-matches near the true match may be dropped after redraws, not more.
    assert 0.98 * 75 * n <= len(result.nonmatches_object_a) <= 75 * n
    assert mask_b[result.nonmatches_object_b[:, 1], result.nonmatches_object_b[:, 0]].all()
    assert not mask_b[result.nonmatches_background_b[:, 1], result.nonmatches_background_b[:, 0]].any()
    assert pixel_set(result.nonmatches_object_a) <= pixel_set(result.matches_a)
    assert pixel_set(result.nonmatches_background_a) <= pixel_set(result.matches_a)
    # Object non-matches keep away from the true match of their pixel in A (a function of it).
    match_of = {tuple(a): b for a, b in zip(result.matches_a.tolist(), result.matches_b, strict=True)}
    true_b = np.array([match_of[tuple(a)] for a in result.nonmatches_object_a.tolist()])
    assert np.abs(result.nonmatches_object_b - true_b).max(axis=1).min() > 2
    # Both kinds spread over B's masks rather than piling up on a few pixels.
    assert len(pixel_set(result.nonmatches_object_b)) > 0.9 * mask_b.sum()


def test_nonmatch_cap():
    intrinsics = CameraIntrinsics.d435(160, 120)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    result = sample_correspondences(
        depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, np.random.default_rng(0), max_nonmatches=1000
    )
    assert result.num_matches > 1000
    assert len(result.nonmatches_background_a) == 500
    assert 490 <= len(result.nonmatches_object_a) <= 500
    # Spread over many matches (A's mask has ~600 pixels here), not the first few.
    assert len(pixel_set(result.nonmatches_background_a)) > 200


def test_same_seed_same_correspondences():
    intrinsics = CameraIntrinsics.d435(160, 120)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)

    def sample(seed: int) -> Correspondences:
        rng = np.random.default_rng(seed)
        return sample_correspondences(depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, rng)

    first, again, other = sample(7), sample(7), sample(8)
    for name in Correspondences.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    assert not np.array_equal(first.matches_a, other.matches_a)


def test_empty_masks_give_empty_arrays():
    intrinsics = CameraIntrinsics.d435(160, 120)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    rng = np.random.default_rng(0)
    nothing = sample_correspondences(depth_a, depth_b, np.zeros_like(mask_a), mask_b, intrinsics, T_A, T_B, rng)
    for name in Correspondences.__dataclass_fields__:
        value = getattr(nothing, name)
        assert value.shape == (0, 2) and value.dtype == np.int64
    no_object_in_b = sample_correspondences(depth_a, depth_b, mask_a, np.zeros_like(mask_b), intrinsics, T_A, T_B, rng)
    assert no_object_in_b.num_matches > 0
    assert no_object_in_b.nonmatches_object_a.shape == (0, 2)
    assert len(no_object_in_b.nonmatches_background_b) > 0
    # B sees nothing at all: every match is pruned.
    blind = sample_correspondences(depth_a, np.zeros_like(depth_b), mask_a, mask_b, intrinsics, T_A, T_B, rng)
    assert blind.num_matches == 0 and blind.nonmatches_background_b.shape == (0, 2)


def test_camera_poses_differ():
    assert camera_poses_differ(T_A, T_B)
    assert not camera_poses_differ(T_A, T_A)
    moved = T_A.copy()
    moved[:3, 3] += [0.0, 0.0, 0.15]
    assert not camera_poses_differ(T_A, moved)
    moved[:3, 3] += [0.0, 0.0, 0.1]
    assert camera_poses_differ(T_A, moved)
    turned = look_at((0.4, 0.0, 0.35), (0.0, 0.2, 0.02))  # same centre, looking 25 degrees aside
    assert camera_poses_differ(T_A, turned)
    assert not camera_poses_differ(T_A, turned, min_rotation_rad=np.deg2rad(40))


def test_input_validation():
    intrinsics = CameraIntrinsics.d435(160, 120)
    depth_a, depth_b, mask_a, mask_b, _, _ = views(intrinsics)
    rng = np.random.default_rng(0)
    with pytest.raises(DonGymError, match="object_mask_b"):
        sample_correspondences(depth_a, depth_b, mask_a, mask_b[:-1], intrinsics, T_A, T_B, rng)
    with pytest.raises(DonGymError, match=">= 0"):
        sample_correspondences(depth_a, depth_b, mask_a, mask_b, intrinsics, T_A, T_B, rng, num_match_attempts=-1)
