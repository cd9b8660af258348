"""Windowed wrist images (``window_px``): the window's intrinsics, its pixels against the whole frame's, and the
keypoint wrapper that places it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import don_gym  # noqa: F401  (registers the env ids)
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, image_window, project_points, window_origin_px
from don_gym.wrappers import KeypointObservation


def test_window_intrinsics_shift_the_principal_point_only():
    frame = CameraIntrinsics.d435(640, 480)
    window = frame.window((100, 50), 192, 160)
    assert (window.fx, window.fy, window.width, window.height) == (frame.fx, frame.fy, 192, 160)
    assert window_origin_px(frame, window) == (100, 50)
    point = np.array([[0.03, -0.02, 0.4]])
    # A point lands on the same pixel of the frame whether projected in the frame or in the window.
    np.testing.assert_allclose(project_points(window, point)[0] + [100, 50], project_points(frame, point)[0])


def test_image_window_is_centred_and_kept_inside_the_frame():
    frame = CameraIntrinsics.d435(640, 480)
    assert window_origin_px(frame, image_window(frame, np.array([320.0, 240.0]), 100)) == (270, 190)
    assert window_origin_px(frame, image_window(frame, np.array([5.0, 470.0]), 100)) == (0, 380)
    assert window_origin_px(frame, image_window(frame, None, 480)) == (80, 0)
    assert window_origin_px(frame, image_window(frame, np.array([np.nan, 1.0]), 100)) == (270, 190)


def test_a_window_larger_than_the_frame_is_a_one_line_error():
    frame = CameraIntrinsics.d435(160, 120)
    with pytest.raises(DonGymError, match="larger than the 160x120 frame") as error:
        image_window(frame, None, 121)
    assert "\n" not in str(error.value)
    with pytest.raises(DonGymError, match="leaves the"):
        frame.window((100, 0), 64, 64)
    with pytest.raises(DonGymError, match=r"window_px=200: larger than the 160x120 frame") as error:
        gym.make("DONToolcapPick-v0", image_size=(160, 120), window_px=200)
    assert "\n" not in str(error.value)
    with pytest.raises(DonGymError, match="needs wrist images"):
        gym.make("DONToolcapPick-v0", image_size=None, window_px=64)
    with pytest.raises(DonGymError, match="integer of at least 8"):
        gym.make("DONToolcapPick-v0", image_size=(160, 120), window_px=4.5)


def test_window_pixels_equal_the_crop_of_the_whole_frame():
    kwargs = {"control": "ee", "image_size": (160, 120), "sensor": "ideal"}
    full = gym.make("DONToolcapPick-v0", **kwargs)
    windowed = gym.make("DONToolcapPick-v0", window_px=64, **kwargs)
    try:
        assert windowed.observation_space["rgb"].shape == (64, 64, 3)
        for seed in (0, 5):
            a, _ = full.reset(seed=seed)
            b, _ = windowed.reset(seed=seed)
            window = CameraIntrinsics.from_array(b["camera_intrinsics"])
            u0, v0 = window_origin_px(full.unwrapped.intrinsics, window)
            assert b["rgb"].shape == (64, 64, 3) and windowed.observation_space.contains(b)
            np.testing.assert_array_equal(b["rgb"], a["rgb"][v0 : v0 + 64, u0 : u0 + 64])
            np.testing.assert_allclose(b["depth"], a["depth"][v0 : v0 + 64, u0 : u0 + 64], atol=1e-5)
        # The window follows the point it is given, as the reported camera sees it.
        part = windowed.unwrapped.task.part.T_world_object[:3, 3]
        windowed.unwrapped.set_window_centre(part)
        obs, *_ = windowed.step(np.zeros(5, np.float32))
        window = CameraIntrinsics.from_array(obs["camera_intrinsics"])
        T_camera_world = np.linalg.inv(obs["camera_pose"].astype(np.float64))
        uv, _ = project_points(window, (T_camera_world @ np.append(part, 1.0))[:3])
        assert np.all(np.abs(uv[0] - 31.5) <= 1.0)
        with pytest.raises(DonGymError, match="point_world"):
            windowed.unwrapped.set_window_centre([0.0, 1.0])
    finally:
        full.close()
        windowed.close()


def test_keypoints_in_a_window_match_the_whole_frame():
    kwargs = {"control": "ee", "image_size": (160, 120), "sensor": "ideal"}
    full = KeypointObservation(gym.make("DONToolcapPick-v0", **kwargs), keep_images=False)
    windowed = KeypointObservation(gym.make("DONToolcapPick-v0", window_px=64, **kwargs), keep_images=False)
    try:
        assert windowed.window_px == 64
        assert windowed.observation_space["keypoint_pixels"].high.max() == 159  # the whole frame's pixels
        for seed in (1, 2):
            a, _ = full.reset(seed=seed)
            b, _ = windowed.reset(seed=seed)
            assert windowed.observation_space.contains(b)
            np.testing.assert_allclose(b["keypoint_pixels"], a["keypoint_pixels"], atol=0.01)
            for _ in range(3):
                action = np.array([0.0, 0.0, -0.6, 0.0, 1.0], np.float32)
                a, *_ = full.step(action)
                b, *_ = windowed.step(action)
                assert np.all(b["keypoint_confidence"] > 0.5)
                assert np.max(np.abs(b["keypoint_pixels"] - a["keypoint_pixels"])) < 1.5
                np.testing.assert_allclose(b["keypoint_points"], a["keypoint_points"], atol=0.005)
            centre = windowed.unwrapped.window_centre_world
            np.testing.assert_allclose(centre, b["keypoint_points"].mean(axis=0), atol=1e-5)
    finally:
        full.close()
        windowed.close()


def test_windowed_observations_reach_the_rl_envs():
    from don_gym.agents.rl_envs import make_batched_sac_vec_env, make_sac_env

    env = make_sac_env(keypoints="don", image_size=(160, 120), window_px=64, sensor="ideal")
    try:
        assert env.unwrapped.window_px == 64
        obs, _ = env.reset(seed=0)
        assert env.observation_space.contains(obs)
    finally:
        env.close()
    simulated = make_sac_env(keypoints="true", window_px=64)  # renders nothing: no window to place
    simulated.close()
    with pytest.raises(DonGymError, match="batched envs see whole frames"):
        make_batched_sac_vec_env(2, {"window_px": 64})


@pytest.mark.filterwarnings("ignore:.*trained on 640x480")
def test_a_network_read_from_a_reference_frame_takes_the_whole_frame_in_a_windowed_env():
    """A model whose reference descriptors come from a reference frame (self-supervised) reads them from the
    windowed env's whole frame, not from a window that need not hold the part: the same as without a window."""
    kwargs = {"control": "ee", "image_size": (160, 120), "sensor": "ideal"}
    model = "toolcap/self-supervised"
    full = KeypointObservation(gym.make("DONToolcapPick-v0", **kwargs), model=model, keep_images=False)
    windowed = KeypointObservation(
        gym.make("DONToolcapPick-v0", window_px=64, **kwargs), model=model, keep_images=False
    )
    try:
        assert not windowed.source.reference_from_field
        np.testing.assert_allclose(windowed.reference_descriptors, full.reference_descriptors, atol=1e-5)
    finally:
        full.close()
        windowed.close()
