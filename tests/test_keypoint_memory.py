"""KeypointMemory (last seen places and ages) and SimulatedKeypoints' model of the depth sensor's range."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

import don_gym  # noqa: F401  (registers the env ids)
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, transform_points
from don_gym.sim.sensor import depth_range_m
from don_gym.wrappers import KeypointFeatures, KeypointMemory, SimulatedKeypoints, make_keypoint_env
from don_gym.wrappers.memory import UNSEEN_POINT_M


class ScriptedKeypoints(gym.Env):
    """Two keypoints whose points and confidences follow a script, one row per reset/step."""

    def __init__(self, points: np.ndarray, confidence: np.ndarray):
        self.points, self.confidence, self.t = points, confidence, 0
        self.observation_space = spaces.Dict(
            {
                "keypoint_points": spaces.Box(-10, 10, (2, 3), np.float32),
                "keypoint_confidence": spaces.Box(0, 1, (2,), np.float32),
                "ee_pose": spaces.Box(-10, 10, (7,), np.float32),
                "gripper_width": spaces.Box(0, 0.1, (1,), np.float32),
            }
        )
        self.action_space = spaces.Box(-1, 1, (1,), np.float32)

    def _obs(self):
        return {
            "keypoint_points": self.points[self.t].astype(np.float32),
            "keypoint_confidence": self.confidence[self.t].astype(np.float32),
            "ee_pose": np.array([0.5, 0, 0.3, 1, 0, 0, 0], np.float32),
            "gripper_width": np.array([0.08], np.float32),
        }

    def reset(self, *, seed=None, options=None):
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), 0.0, False, False, {}


def test_memory_keeps_last_seen_places_and_counts_ages():
    rng = np.random.default_rng(0)
    points = rng.uniform(0.3, 0.6, size=(6, 2, 3))
    confidence = np.array([[0.0, 0.9], [0.9, 0.9], [0.1, 0.8], [0.0, 0.0], [0.0, 0.7], [0.0, 0.0]])
    env = KeypointMemory(ScriptedKeypoints(points, confidence), max_age_steps=3)
    obs, _ = env.reset()
    assert env.observation_space.contains(obs)
    np.testing.assert_allclose(obs["keypoint_memory_points"][0], UNSEEN_POINT_M, atol=1e-6)  # never seen yet
    np.testing.assert_allclose(obs["keypoint_memory_points"][1], points[0, 1], atol=1e-6)
    np.testing.assert_array_equal(obs["keypoint_age"], [3, 0])
    ages, remembered = [], []
    for _ in range(5):
        obs, *_ = env.step(np.zeros(1))
        ages.append(obs["keypoint_age"].tolist())
        remembered.append(obs["keypoint_memory_points"].copy())
    assert ages == [[0, 0], [1, 0], [2, 1], [3, 0], [3, 1]]  # capped at max_age_steps
    np.testing.assert_allclose(remembered[-1][0], points[1, 0], atol=1e-6)  # last seen at step 1
    np.testing.assert_allclose(remembered[-1][1], points[4, 1], atol=1e-6)
    obs, _ = env.reset()  # a reset forgets
    np.testing.assert_array_equal(obs["keypoint_age"], [3, 0])
    np.testing.assert_allclose(obs["keypoint_memory_points"][0], UNSEEN_POINT_M, atol=1e-6)


def test_features_carry_the_memory():
    points = np.tile(np.array([[0.5, 0.0, 0.02], [0.52, 0.0, 0.02]]), (3, 1, 1))
    confidence = np.array([[0.9, 0.9], [0.0, 0.0], [0.0, 0.0]])
    plain = KeypointFeatures(ScriptedKeypoints(points, confidence), relative_to="tcp", robot_state=True)
    env = KeypointFeatures(KeypointMemory(ScriptedKeypoints(points, confidence), max_age_steps=4), "tcp", True)
    assert env.memory and not plain.memory
    assert env.observation_space.shape[0] == plain.observation_space.shape[0] + 8
    env.reset()
    env.step(np.zeros(1))
    vector, *_ = env.step(np.zeros(1))
    tail = vector[-8:]
    np.testing.assert_allclose(tail[:6], ((points[0] - [0.5, 0, 0.3]) / 0.05).reshape(-1), atol=1e-5)
    np.testing.assert_allclose(tail[6:], [0.5, 0.5])  # two steps of four


def test_memory_refuses_observations_without_keypoints_and_bad_arguments():
    with pytest.raises(DonGymError, match="KeypointMemory needs"):
        KeypointMemory(gym.make("DONToolcapPick-v0", image_size=None))
    env = ScriptedKeypoints(np.zeros((1, 2, 3)), np.zeros((1, 2)))
    with pytest.raises(DonGymError, match="max_age_steps"):
        KeypointMemory(env, max_age_steps=0)
    with pytest.raises(DonGymError, match="seen_confidence"):
        KeypointMemory(env, seen_confidence=2.0)
    with pytest.raises(DonGymError, match="memory=True needs keypoints"):
        make_keypoint_env(keypoints=None, memory=True)


def test_depth_range_of_the_sensor_presets():
    near, far = depth_range_m("d435", CameraIntrinsics.d435(640, 480))
    assert near == pytest.approx(615 * 0.05 / 126) and far == 10.0
    assert depth_range_m("d435", CameraIntrinsics.d435(320, 240))[0] == pytest.approx(near / 2)
    assert depth_range_m("ideal", CameraIntrinsics.d435(640, 480)) == (0.0, float("inf"))


@pytest.mark.parametrize("sensor", ["d435", "ideal"])
def test_simulated_keypoints_vanish_where_the_sensor_has_no_depth(sensor):
    """Down a descent onto the part, a simulated keypoint is seen exactly where it is in view and the rendered
    sensor depth could exist: not nearer than the sensor's range (0.24 m for the D435), at any depth if ideal."""
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=None, sensor=sensor)
    wrapped = KeypointMemory(SimulatedKeypoints(env, noise=None), max_age_steps=50)
    near = depth_range_m(sensor, env.unwrapped.intrinsics)[0]
    obs, info = wrapped.reset(seed=3)
    depths, seen = [], []
    for _ in range(14):
        T_camera_world = invert_transform(info["T_world_camera"])
        target = info["T_world_object"][:3, 3]
        keypoint_depth = transform_points(T_camera_world, obs["keypoint_memory_points"].astype(np.float64))[:, 2]
        depths.append(keypoint_depth.min())
        seen.append(bool(np.all(obs["keypoint_confidence"] > 0)))
        tcp = obs["ee_pose"][:3]
        action = np.zeros(5, np.float32)
        action[:2] = np.clip((target[:2] - tcp[:2]) / 0.05, -1, 1)
        action[2] = -0.6
        action[4] = 1.0
        obs, _, _, _, info = wrapped.step(action)
    depths, seen = np.array(depths), np.array(seen)
    assert seen[0] and depths.min() < 0.2  # the descent went closer than the D435 can see
    if sensor == "ideal":
        assert seen[depths > 0.15].all()
    else:
        assert not seen[depths < near - 0.01].any() and seen[depths > near + 0.03].all()
        # The memory still knows where the part is: the last seen places are near the true part.
        assert np.all(obs["keypoint_age"] > 0)
        np.testing.assert_allclose(obs["keypoint_memory_points"].mean(axis=0)[:2], target[:2], atol=0.03)
    wrapped.close()
