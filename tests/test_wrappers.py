"""Keypoint core (matching, robust depth), descriptor sources, DescriptorObservation and KeypointObservation."""

from __future__ import annotations

import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import don_gym  # noqa: F401 - registers the envs
from don_gym.errors import CheckpointError, DonGymError
from don_gym.geometry import CameraIntrinsics, make_transform, pixel_rays, transform_points
from don_gym.learning.checkpoints import CheckpointMetadata, save_checkpoint
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import (
    OracleDescriptors,
    ReferenceFrame,
    axis_end_targets,
    load_descriptor_source,
    reference_descriptors_for,
)
from don_gym.perception.keypoints import (
    best_match,
    descriptor_distances,
    locate_keypoints,
    match_confidence,
    match_region,
    project_visible,
    robust_depth,
    robust_point_from_depth,
    sample_descriptors,
    soft_match,
)
from don_gym.wrappers import DESCRIPTOR_BOUND, DescriptorObservation, KeypointObservation

# ---------------------------------------------------------------------------------------- keypoints core


def _gradient_image(height: int = 6, width: int = 8) -> np.ndarray:
    """Every pixel a different descriptor: (u / W, v / H, 0.5)."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u / width, v / height, np.full(u.shape, 0.5)], axis=2).astype(np.float32)


def test_best_match_finds_the_known_pixels_and_distances() -> None:
    image = _gradient_image()
    reference = np.array([image[4, 2], image[1, 7], [0.3, 0.1, 0.5]], dtype=np.float32)
    uv, distance = best_match(image, reference)
    assert uv.dtype == np.int64 and uv.tolist()[:2] == [[2, 4], [7, 1]]
    np.testing.assert_allclose(distance[:2], 0.0, atol=1e-7)
    # (0.3, 0.1) lies between pixels: nearest u = 0.3 * 8 = 2.4 -> 2, v = 0.1 * 6 = 0.6 -> 1.
    assert uv[2].tolist() == [2, 1]
    np.testing.assert_allclose(distance[2], np.hypot(0.3 - 2 / 8, 0.1 - 1 / 6), rtol=1e-5)
    np.testing.assert_allclose(descriptor_distances(image, reference)[0, 4, 2], 0.0, atol=1e-7)


def test_best_match_ties_go_to_the_first_pixel_and_soft_match_to_the_middle_of_a_ring() -> None:
    image = _gradient_image(9, 12)
    ring = np.array([0.9, 0.9, 0.9], dtype=np.float32)
    image[4, 3:10] = ring  # a symmetric ring seen across the part: equal descriptors on one row
    uv, _ = best_match(image, ring)
    assert uv[0].tolist() == [3, 4]
    # A sharp temperature, so that the gradient's pixels (all >= 0.5 away) get no weight.
    soft_uv, distance = soft_match(image, ring, window_px=8.0, temperature=0.05)
    np.testing.assert_allclose(soft_uv[0], [6.0, 4.0], atol=1e-6)
    assert distance[0] == 0.0
    # Window 0 keeps the best match; a narrow window averages only its part of the ring.
    np.testing.assert_array_equal(soft_match(image, ring, window_px=0.0)[0][0], [3.0, 4.0])
    np.testing.assert_allclose(soft_match(image, ring, window_px=2.0, temperature=0.05)[0][0], [4.0, 4.0], atol=1e-6)


def test_a_border_margin_keeps_best_matches_off_the_frames_edge() -> None:
    image = _gradient_image(9, 12)
    reference = np.array([image[0, 11], image[4, 5]], dtype=np.float32)  # a corner pixel and an inner one
    uv, distance = best_match(image, reference)
    assert uv.tolist() == [[11, 0], [5, 4]]
    uv, distance = best_match(image, reference, border_margin_px=2)
    # The corner's descriptor now finds the nearest pixel of the inner region; the inner pixel is unchanged.
    assert uv.tolist() == [[9, 2], [5, 4]]
    np.testing.assert_allclose(distance[0], np.hypot(2 / 12, 2 / 9), rtol=1e-5)
    assert distance[1] == 0.0
    soft_uv, _ = soft_match(image, reference, window_px=0.0, border_margin_px=2)
    np.testing.assert_array_equal(soft_uv, [[9.0, 2.0], [5.0, 4.0]])
    region = match_region(9, 12, 2)
    assert region.shape == (9, 12) and region.sum() == 5 * 8 and region[2, 2] and not region[1, 5]
    assert match_region(9, 12, 0).all()
    for bad in (-1, 5, 2.0, True):
        with pytest.raises(DonGymError, match="border_margin_px"):
            best_match(image, reference, border_margin_px=bad)


def test_match_confidence_is_one_at_zero_and_strictly_decreasing() -> None:
    distance = np.linspace(0.0, 1.0, 101)
    confidence = match_confidence(distance, sigma=0.1)
    assert confidence[0] == 1.0
    assert np.all(np.diff(confidence[:50]) < 0) and np.all(np.diff(confidence) <= 0)
    assert np.all((confidence >= 0) & (confidence <= 1))
    np.testing.assert_allclose(match_confidence(0.1, sigma=0.1), np.exp(-1.0), rtol=1e-6)
    with pytest.raises(DonGymError, match="sigma"):
        match_confidence(distance, sigma=0.0)


def test_robust_depth_fills_holes_and_gives_up_beyond_the_radius() -> None:
    intrinsics = CameraIntrinsics.d435(40, 30)
    depth = np.full((30, 40), 0.5, dtype=np.float32)
    depth[10:13, 10:13] = 0.0  # a 3x3 hole around (11, 11)
    depth[11, 30] = 0.7  # one outlier next to (30, 12): the median ignores it
    depth[20:30, 0:10] = 0.0  # a large hole: nothing valid within 2 px of (4, 25)
    uv = np.array([[11, 11], [30, 12], [4, 25], [20, 5]])
    z, valid = robust_depth(depth, uv, min_radius_px=0, max_radius_px=2)
    assert valid.tolist() == [True, True, False, True]
    np.testing.assert_allclose(z, [0.5, 0.5, 0.0, 0.5])
    points, valid = robust_point_from_depth(depth, intrinsics, uv.astype(float), min_radius_px=0, max_radius_px=2)
    np.testing.assert_allclose(points[0], pixel_rays(intrinsics, uv[:1])[0] * 0.5)
    np.testing.assert_array_equal(points[2], 0.0)
    # A growing window reaches the big hole's edge at radius 5.
    assert robust_depth(depth, uv[2:3], min_radius_px=0, max_radius_px=6)[1][0]
    with pytest.raises(DonGymError, match="min_radius_px"):
        robust_depth(depth, uv, min_radius_px=3, max_radius_px=2)


def test_project_visible_and_sample_descriptors() -> None:
    intrinsics = CameraIntrinsics.d435(40, 30)
    depth = np.full((30, 40), 0.5, dtype=np.float32)
    rays = pixel_rays(intrinsics, np.array([[5, 5], [20, 15], [39, 29]]))
    points = np.concatenate([rays * 0.5, rays[:1] * 0.6, [[0.0, 0.0, -1.0], [5.0, 0.0, 0.5]]])
    uv, visible = project_visible(points, intrinsics, depth, tolerance_m=0.003)
    assert visible.tolist() == [True, True, True, False, False, False]  # hidden, behind, outside
    assert uv[:3].tolist() == [[5, 5], [20, 15], [39, 29]]
    image = _gradient_image(30, 40)
    image[15, 20] = 9.0  # one outlier in a 3x3 window: the median ignores it
    np.testing.assert_allclose(sample_descriptors(image, uv[1:2], radius_px=1)[0], [0.5, 0.5, 0.5], atol=1e-6)


def test_locate_keypoints_lifts_matches_to_the_world() -> None:
    intrinsics = CameraIntrinsics.d435(40, 30)
    image = _gradient_image(30, 40)
    depth = np.full((30, 40), 0.4, dtype=np.float32)
    depth[12, 25] = 0.0  # the match pixel itself has no depth
    T_world_camera = make_transform(np.diag([1.0, -1.0, -1.0]), [0.5, 0.0, 0.45])
    found = locate_keypoints(image, depth, intrinsics, T_world_camera, image[[12, 3], [25, 7]])
    np.testing.assert_allclose(found.pixels, [[25, 12], [7, 3]])
    expected_camera = pixel_rays(intrinsics, found.pixels) * 0.4
    np.testing.assert_allclose(found.points_world, transform_points(T_world_camera, expected_camera), atol=1e-9)
    assert found.depth_valid.all() and np.all(found.confidence > 0.999)


# ---------------------------------------------------------------------------------------- envs


@pytest.fixture(scope="module")
def ee_env():
    """Small-image, fast-stepping env for wrapper mechanics (check_env, vector envs)."""
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=(64, 48))
    yield env
    env.close()


@pytest.fixture(scope="module")
def grasp_env():
    env = gym.make("DONToolcapPick-v0", image_size=(320, 240), sensor="ideal")
    yield env
    env.close()


def _quiet_check(env: gym.Env) -> None:
    """Both checkers; their advice on a wrapped env and on non-1D Box shapes is expected here."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*different from the unwrapped version.*")
        warnings.filterwarnings("ignore", message=".*unconventional shape.*")
        warnings.filterwarnings("ignore", message=".*is an image but.*")
        check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True, skip_render_check=True)


def test_wrappers_package_re_exports_the_descriptor_sources() -> None:
    import don_gym.perception.descriptor_sources as core
    import don_gym.wrappers as wrappers

    for name in ("DescriptorSource", "ReferenceFrame", "load_descriptor_source", "axis_end_targets"):
        assert getattr(wrappers, name) is getattr(core, name)


def test_descriptor_observation_passes_both_env_checkers(ee_env) -> None:
    env = DescriptorObservation(ee_env, model="oracle")
    assert env.method == "oracle"
    space = env.observation_space["descriptors"]
    assert space.shape == (48, 64, 3) and space.high.max() == DESCRIPTOR_BOUND
    assert set(ee_env.observation_space.spaces) < set(env.observation_space.spaces)
    _quiet_check(env)
    obs, info = env.reset(seed=1)
    assert obs["descriptors"].dtype == np.float32 and obs["descriptors"].shape == (48, 64, 3)
    # The oracle is the optimal field: background off the part, field values on it.
    field_values = env.source.field.vertex_descriptors
    background = env.source.background
    on_object = np.any(obs["descriptors"] != background, axis=2)
    assert 5 < on_object.sum() < 0.2 * on_object.size
    inside = obs["descriptors"][on_object]
    assert np.all(inside >= field_values.min(axis=0) - 1e-5) and np.all(inside <= field_values.max(axis=0) + 1e-5)


def test_keypoint_observation_passes_checkers_and_compact_observation(ee_env) -> None:
    _quiet_check(KeypointObservation(ee_env, model="oracle"))
    compact = KeypointObservation(ee_env, model="oracle", keep_images=False)
    assert set(compact.observation_space.spaces).isdisjoint({"rgb", "depth", "descriptors"})
    _quiet_check(compact)
    obs, _ = compact.reset(seed=2)
    assert obs["keypoint_points"].shape == (2, 3) and obs["keypoint_pixels"].shape == (2, 2)
    assert compact.observation_space.contains(obs)


def test_vector_env_with_two_keypoint_envs_steps() -> None:
    def make():
        return KeypointObservation(gym.make("DONToolcapPick-v0", control="ee", image_size=(48, 36)), keep_images=False)

    envs = gym.vector.SyncVectorEnv([make, make])
    try:
        obs, _ = envs.reset(seed=[3, 4])
        assert obs["keypoint_points"].shape == (2, 2, 3)
        obs, reward, terminated, truncated, _ = envs.step(np.zeros((2, 5), dtype=np.float32))
        assert obs["keypoint_confidence"].shape == (2, 2) and reward.shape == (2,)
        assert np.all(np.isfinite(obs["keypoint_points"]))
        # Different seeds, different part poses: the keypoints differ between the two envs.
        assert np.linalg.norm(obs["keypoint_points"][0] - obs["keypoint_points"][1]) > 0.005
    finally:
        envs.close()


def _ring_tops_world(env: gym.Env, targets, info) -> np.ndarray:
    """True world points on each ring seen straight along the camera ray through the axis."""
    model = env.unwrapped.model
    T = info["T_world_object"]
    axis_world = T[:3, :3] @ model.plus_axis
    camera = info["T_world_camera"][:3, 3]
    out = []
    for t, r in zip(targets.axial_positions_m, targets.radii_m, strict=True):
        q = transform_points(T, model.center_of_mass + t * model.plus_axis)
        towards_camera = camera - q
        towards_camera -= (towards_camera @ axis_world) * axis_world
        out.append(q + r * towards_camera / np.linalg.norm(towards_camera))
    return np.array(out)


def test_oracle_keypoints_land_on_the_rings_over_the_axis(grasp_env) -> None:
    env = KeypointObservation(grasp_env, model="oracle")
    assert env.targets is not None and env.window_m == pytest.approx(2 * env.targets.radii_m.max())
    for pose_id in (0, 5):
        obs, info = env.reset(seed=0, options={"pose_id": pose_id})
        truth = _ring_tops_world(env, env.targets, info)
        error_mm = 1000 * np.linalg.norm(obs["keypoint_points"] - truth, axis=1)
        assert np.all(error_mm < 2.0), (pose_id, error_mm)
        assert np.all(obs["keypoint_confidence"] > 0.95)


def test_reference_frame_descriptors_of_the_oracle_equal_its_field(grasp_env) -> None:
    source = OracleDescriptors(grasp_env.unwrapped.model)
    targets = axis_end_targets(grasp_env.unwrapped.model, source.field)
    grasp_env.reset(seed=11)
    state = grasp_env.unwrapped.np_random.bit_generator.state
    reference = ReferenceFrame.from_env(grasp_env)
    # The reference reset does not disturb the env's random stream.
    assert grasp_env.unwrapped.np_random.bit_generator.state == state
    from_image = reference_descriptors_for(source, targets.surface_points, reference)
    from_field = reference_descriptors_for(source, targets.surface_points)
    np.testing.assert_allclose(from_field, targets.descriptors, atol=1e-6)
    np.testing.assert_allclose(from_image, from_field, atol=0.02)
    assert np.linalg.norm(from_field[0] - from_field[1]) > 0.3  # the two ends are far apart


# ---------------------------------------------------------------------------------------- bad input


def _checkpoint(path: Path, object_name: str, descriptor_dim: int) -> Path:
    torch.manual_seed(0)
    metadata = CheckpointMetadata(
        method="supervised-edge", object_name=object_name, object_mesh_hash="0" * 16, image_size=(64, 48)
    )
    save_checkpoint(path, DenseObjectNet(descriptor_dim=descriptor_dim), metadata)
    return path


def test_bad_models_and_references_give_clear_errors(ee_env, tmp_path: Path) -> None:
    model = ee_env.unwrapped.model
    with pytest.raises(CheckpointError, match=r"'toolcap/no-such-net'.*available: 'oracle'"):
        DescriptorObservation(ee_env, model="toolcap/no-such-net")
    shaft = _checkpoint(tmp_path / "shaft.safetensors", "shaft", 3)
    with pytest.raises(CheckpointError, match=r"object_name is 'shaft', expected 'toolcap'"):
        DescriptorObservation(ee_env, model=shaft)
    toolcap4 = _checkpoint(tmp_path / "toolcap4.safetensors", "toolcap", 4)
    with pytest.raises(CheckpointError, match=r"descriptor_dim is 4, expected 3"):
        DescriptorObservation(ee_env, model=toolcap4, descriptor_dim=3)
    assert load_descriptor_source(toolcap4, model).descriptor_dim == 4
    with pytest.raises(DonGymError, match=r"expected \(K, 3\).*got length 4"):
        KeypointObservation(ee_env, model="oracle", reference_descriptors=np.zeros((2, 4)))
    with pytest.raises(DonGymError, match="expected 'oracle'"):
        DescriptorObservation(ee_env, model=3.5)
    no_images = gym.make("DONToolcapPick-v0", control="ee", image_size=None)
    try:
        with pytest.raises(DonGymError, match="observes 'rgb'"):
            DescriptorObservation(no_images)
    finally:
        no_images.close()


def test_network_descriptors_through_the_wrapper(ee_env, tmp_path: Path) -> None:
    path = _checkpoint(tmp_path / "toolcap.safetensors", "toolcap", 3)
    env = KeypointObservation(ee_env, model=str(path), reference_descriptors=np.zeros((3, 3), np.float32))
    assert env.method == "supervised-edge"
    obs, _ = env.reset(seed=0)
    expected = env.source.network.descriptor_image(obs["rgb"])
    np.testing.assert_allclose(obs["descriptors"], expected, atol=1e-6)
    assert obs["keypoint_points"].shape == (3, 3) and env.observation_space.contains(obs)
    # A network's matches keep off the outer 16 px, where its output saw zero padding; the oracle's do not.
    height, width = obs["descriptors"].shape[:2]
    assert env.border_margin_px == env.source.border_margin_px == 16
    best_only = KeypointObservation(
        ee_env, model=str(path), reference_descriptors=np.random.default_rng(0).random((8, 3)), window_m=0.0
    )
    pixels = best_only.reset(seed=0)[0]["keypoint_pixels"]
    assert np.all((pixels >= 16) & (pixels <= np.array([width - 17, height - 17])))
    assert KeypointObservation(ee_env, model="oracle").border_margin_px == 0
    assert (
        KeypointObservation(
            ee_env, model=str(path), reference_descriptors=np.zeros((3, 3), np.float32), border_margin_px=0
        ).border_margin_px
        == 0
    )
    tiny = gym.make("DONToolcapPick-v0", control="ee", image_size=(32, 24))
    try:
        with pytest.raises(DonGymError, match=r"border_margin_px=16.*'supervised-edge' model's own.*32x24"):
            KeypointObservation(tiny, model=str(path), reference_descriptors=np.zeros((3, 3), np.float32))
    finally:
        tiny.close()
    with pytest.raises(DonGymError, match="border_margin_px=24"):
        KeypointObservation(
            ee_env, model=str(path), reference_descriptors=np.zeros((3, 3), np.float32), border_margin_px=24
        )
    # An untrained net is not trained on this field: its hash does not match, so no field references.
    with pytest.warns(UserWarning, match="reference frame"):
        assert not env.source.reference_from_field


def test_network_warns_once_when_the_env_image_size_differs_from_its_training_size(tmp_path: Path) -> None:
    path = _checkpoint(tmp_path / "toolcap.safetensors", "toolcap", 3)  # trained at 64x48
    source = load_descriptor_source(path, load_object("toolcap"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        source.descriptor_image({"rgb": np.zeros((48, 64, 3), np.uint8)})
    other = load_descriptor_source(path, load_object("toolcap"))
    with pytest.warns(UserWarning, match=r"trained on 64x48 images but gets 32x24.*image_size=\(64, 48\)"):
        other.descriptor_image({"rgb": np.zeros((24, 32, 3), np.uint8)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        other.descriptor_image({"rgb": np.zeros((24, 32, 3), np.uint8)})
