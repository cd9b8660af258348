"""TSDF fusion: fused depth re-rendered from new poses, hole filling, noise averaging, masks."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_scenes import Sphere, distance_to_surfaces, look_at, render_scene, table_scene

from don_gym.data.fusion import TSDFVolume, fuse_scene, fused_object_masks, object_mask_from_depth
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, transform_points

INTRINSICS = CameraIntrinsics.d435(160, 120)
BOUNDS = np.array([[-0.15, -0.15, -0.03], [0.15, 0.15, 0.1]])
VOXEL_M = 0.003
BOX_INDEX = 1


@pytest.fixture(scope="module")
def scene():
    """Table, a box and a sphere, seen by 8 cameras on a circle looking at the box."""
    primitives, box = table_scene()
    primitives = primitives + [Sphere((0.07, -0.07, 0.03), 0.03)]
    poses = [
        look_at((0.4 * np.cos(a), 0.4 * np.sin(a), 0.4), (0.0, 0.0, 0.02))
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ]
    depths = [render_scene(INTRINSICS, T, primitives)[0] for T in poses]
    volume = fuse_scene(depths, INTRINSICS, poses, BOUNDS, voxel_size_m=VOXEL_M)
    return primitives, box, poses, depths, volume


def errors_inside_bounds(rendered: np.ndarray, T_world_camera: np.ndarray, primitives) -> tuple[np.ndarray, float]:
    """|rendered - exact| on pixels whose exact surface point lies well inside the volume, and their coverage."""
    exact, _ = render_scene(INTRINSICS, T_world_camera, primitives)
    points = transform_points(T_world_camera, backproject_depth(INTRINSICS, exact))
    inside = np.all((points > BOUNDS[0] + 0.01) & (points < BOUNDS[1] - 0.01), axis=-1) & (exact > 0)
    assert inside.sum() > 1000
    return np.abs(rendered - exact)[inside], float((rendered[inside] > 0).mean())


def test_fused_depth_from_a_new_pose_matches_the_scene(scene):
    primitives, _, _, _, volume = scene
    new_pose = look_at((0.1, 0.3, 0.45), (0.0, 0.0, 0.02))
    errors, coverage = errors_inside_bounds(volume.render_depth(INTRINSICS, new_pose), new_pose, primitives)
    assert coverage > 0.99
    assert np.median(errors) < VOXEL_M / 3
    assert np.percentile(errors, 90) < VOXEL_M


def test_empty_volume_renders_no_depth():
    volume = TSDFVolume(BOUNDS[0], BOUNDS[1], VOXEL_M)
    depth = volume.render_depth(INTRINSICS, look_at((0.3, 0.0, 0.4), (0.0, 0.0, 0.0)))
    assert depth.shape == (INTRINSICS.height, INTRINSICS.width) and not depth.any()
    assert volume.extract_points().shape == (0, 3)


def test_hole_in_one_frame_is_filled_by_the_others(scene):
    primitives, _, poses, depths, _ = scene
    hole = (slice(40, 80), slice(60, 100))
    with_hole = [d.copy() for d in depths]
    with_hole[0][hole] = 0.0
    alone = fuse_scene(with_hole[:1], INTRINSICS, poses[:1], BOUNDS, voxel_size_m=VOXEL_M)
    assert not alone.render_depth(INTRINSICS, poses[0])[hole].any()
    fused = fuse_scene(with_hole, INTRINSICS, poses, BOUNDS, voxel_size_m=VOXEL_M).render_depth(INTRINSICS, poses[0])
    assert (fused[hole] > 0).mean() > 0.97
    errors = np.abs(fused[hole] - depths[0][hole])[fused[hole] > 0]
    assert np.median(errors) < VOXEL_M / 3


def test_fusion_averages_out_depth_noise(scene):
    primitives, _, poses, depths, _ = scene
    rng = np.random.default_rng(0)
    noisy = [np.where(d > 0, d + rng.normal(0.0, 0.003, d.shape), 0.0).astype(np.float32) for d in depths]
    volume = fuse_scene(noisy, INTRINSICS, poses, BOUNDS, voxel_size_m=VOXEL_M, truncation_m=0.012)
    single, _ = errors_inside_bounds(noisy[0], poses[0], primitives)
    fused, coverage = errors_inside_bounds(volume.render_depth(INTRINSICS, poses[0]), poses[0], primitives)
    assert coverage > 0.99
    # 8 frames: averaging alone would divide the error by sqrt(8) = 2.8.
    assert np.median(fused) < 0.5 * np.median(single)
    assert np.percentile(fused, 90) < 0.5 * np.percentile(single, 90)


def test_extracted_points_lie_on_the_surfaces(scene):
    primitives, _, _, _, volume = scene
    points = volume.extract_points()
    assert len(points) > 5000
    distance = distance_to_surfaces(points, primitives)
    assert np.median(distance) < VOXEL_M / 6
    assert np.percentile(distance, 95) < VOXEL_M / 2


def test_object_masks_from_the_fused_model(scene):
    primitives, box, poses, _, volume = scene
    region = (box.T_world_box, np.asarray(box.half_extents))
    depths, masks = fused_object_masks(volume, INTRINSICS, poses[:3], region, margin_m=0.01, table_height_m=0.0)
    for depth, mask, T in zip(depths, masks, poses[:3], strict=True):
        exact_depth, index = render_scene(INTRINSICS, T, primitives)
        exact = index == BOX_INDEX
        iou = (mask & exact).sum() / (mask | exact).sum()
        assert iou > 0.9
        np.testing.assert_array_equal(depth, volume.render_depth(INTRINSICS, T))
    # Without the table cut, the margin around the box takes in the table.
    loose = object_mask_from_depth(depths[0], INTRINSICS, poses[0], region, margin_m=0.01)
    assert loose.sum() > masks[0].sum()
    # A predicate works as well as a box.
    predicate = lambda p: box.contains(p, 0.01) & (p[:, 2] > 0.004)  # noqa: E731
    assert np.array_equal(object_mask_from_depth(depths[0], INTRINSICS, poses[0], predicate), masks[0])
    # So does a sphere around the object, given with the same depths.
    radius = float(np.linalg.norm(box.half_extents)) + 0.005
    _, sphere_masks = fused_object_masks(
        volume,
        INTRINSICS,
        poses[:3],
        object_center_world=box.T_world_box[:3, 3],
        object_radius_m=radius,
        table_height_m=0.0,
        depths_m=depths,
    )
    _, index = render_scene(INTRINSICS, poses[0], primitives)
    assert (sphere_masks[0] & (index == BOX_INDEX)).sum() > 0.95 * masks[0].sum()
    assert not (sphere_masks[0] & (index == 2)).any()  # the sphere primitive stands outside it
    with pytest.raises(DonGymError, match="not both"):
        object_mask_from_depth(depths[0], INTRINSICS, poses[0], region, object_radius_m=0.1)


def test_input_validation():
    volume = TSDFVolume(BOUNDS[0], BOUNDS[1], VOXEL_M)
    with pytest.raises(DonGymError, match="shape"):
        volume.integrate(np.zeros((10, 10), np.float32), INTRINSICS, np.eye(4))
    with pytest.raises(DonGymError, match=">= 0"):
        volume.integrate(np.full((120, 160), -1.0, np.float32), INTRINSICS, np.eye(4))
    with pytest.raises(DonGymError, match="bounds"):
        TSDFVolume(BOUNDS[1], BOUNDS[0], VOXEL_M)
    with pytest.raises(DonGymError, match="truncation"):
        TSDFVolume(BOUNDS[0], BOUNDS[1], VOXEL_M, truncation_m=VOXEL_M / 2)
    with pytest.raises(DonGymError, match="exceeds"):
        TSDFVolume([0, 0, 0], [10, 10, 10], 0.001)
    with pytest.raises(DonGymError, match="camera poses"):
        fuse_scene([np.zeros((120, 160), np.float32)], INTRINSICS, [], BOUNDS)
