"""RL baselines: the wrappers of don_gym.wrappers.rl and short PPO and SAC runs of don_gym.agents.rl."""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from don_gym.agents import rl
from don_gym.errors import DonGymError
from don_gym.plotting import plot_learning_curve
from don_gym.wrappers.rl import (
    GRASP_OFFSET_XY_M,
    KEYPOINT_OFFSET_UNIT_M,
    NEAR_UNIT_M,
    POSITION_UNIT_M,
    WORKSPACE_CENTRE_M,
    KeypointFeatures,
    KeypointGraspAction,
    keypoint_centroid,
)


class _DictEnv(gym.Env):
    """A minimal env with a given Dict observation space (for wrapper argument checks)."""

    def __init__(self, observation_space: spaces.Dict, control: str = "grasp"):
        self.observation_space = observation_space
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.control = control

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, True, False, {}


def _keypoint_space(k: int = 2, robot: bool = True) -> spaces.Dict:
    entries = {
        "keypoint_points": spaces.Box(-10.0, 10.0, shape=(k, 3), dtype=np.float32),
        "keypoint_confidence": spaces.Box(0.0, 1.0, shape=(k,), dtype=np.float32),
    }
    if robot:
        entries["ee_pose"] = spaces.Box(-10.0, 10.0, shape=(7,), dtype=np.float32)
        entries["gripper_width"] = spaces.Box(0.0, 0.1, shape=(1,), dtype=np.float32)
    return spaces.Dict(entries)


def test_keypoint_features_layout_and_missing_keypoints():
    env = KeypointFeatures(_DictEnv(_keypoint_space(3)), relative_to="tcp", robot_state=True)
    assert env.observation_space.shape == (3 + 4 * 3 + 8,)
    unit, centre = POSITION_UNIT_M, WORKSPACE_CENTRE_M
    tcp = np.array([0.5, 0.1, 0.2])
    points = np.array([[0.50, 0.00, 0.03], [0.60, 0.05, 0.03], [0.0, 0.0, 0.45]])
    # The third keypoint was not found (no depth): confidence 0, its point is the camera centre.
    confidence = np.array([1.0, 0.5, 0.0])
    observation = {
        "keypoint_points": points.astype(np.float32),
        "keypoint_confidence": confidence.astype(np.float32),
        "ee_pose": np.array([*tcp, 0.0, 0.0, 0.0, 1.0], dtype=np.float32),
        "gripper_width": np.array([0.08], dtype=np.float32),
    }
    features = env.observation(observation)
    assert features.dtype == np.float32 and features.shape == env.observation_space.shape
    centroid = (points[0] * 1.0 + points[1] * 0.5) / 1.5  # weighted by confidence, missing point left out
    np.testing.assert_allclose(features[:3], (centroid - centre) / unit, atol=1e-5)
    relative = features[3:12].reshape(3, 3)
    np.testing.assert_allclose(relative[:2], (points[:2] - tcp) / unit, atol=1e-5)
    np.testing.assert_array_equal(relative[2], 0.0)
    np.testing.assert_allclose(features[12:15], confidence)
    np.testing.assert_allclose(features[15:18], (tcp - centre) / unit, atol=1e-5)
    np.testing.assert_allclose(features[18:22], [0, 0, 0, 1])
    assert features[22] == pytest.approx(2.0)

    centred = KeypointFeatures(_DictEnv(_keypoint_space(3, robot=False)), relative_to="centroid")
    assert centred.observation_space.shape == (3 + 4 * 3,)
    offsets = centred.observation(observation)[3:12].reshape(3, 3)
    np.testing.assert_allclose(offsets[:2], (points[:2] - centroid) / KEYPOINT_OFFSET_UNIT_M, atol=1e-4)
    np.testing.assert_array_equal(offsets[2], 0.0)

    nothing = dict(observation, keypoint_confidence=np.zeros(3, np.float32))
    assert keypoint_centroid(points, np.zeros(3)) is None
    np.testing.assert_array_equal(env.observation(nothing)[:15], 0.0)


def test_the_hand_encoding_reads_the_part_from_the_hand_and_is_continuous_in_the_yaw():
    space = _keypoint_space(2)
    space.spaces["joint_positions"] = spaces.Box(-4.0, 4.0, shape=(9,), dtype=np.float32)
    space.spaces["keypoint_memory_points"] = spaces.Box(-10.0, 10.0, shape=(2, 3), dtype=np.float32)
    space.spaces["keypoint_age"] = spaces.Box(0.0, 50.0, shape=(2,), dtype=np.float32)
    env = KeypointFeatures(_DictEnv(space), relative_to="tcp", robot_state=True, encoding="hand")
    assert env.observation_space.shape == (7 + 14 * 2 + 4,)
    tcp = np.array([0.5, 0.1, 0.2])
    remembered = np.array([[0.51, 0.10, 0.03], [0.51, 0.12, 0.03]])  # the part's axis along world y

    def observe(yaw: float, confidence=(1.0, 0.0)) -> np.ndarray:
        # A top-down hand (z down) turned by ``yaw`` about the world z axis.
        quaternion = Rotation.from_euler("ZX", [yaw, np.pi]).as_quat()
        return env.observation({
            "keypoint_points": remembered.astype(np.float32),
            "keypoint_confidence": np.array(confidence, np.float32),
            "keypoint_memory_points": remembered.astype(np.float32),
            "keypoint_age": np.array([0.0, 25.0], np.float32),
            "ee_pose": np.array([*tcp, *quaternion], dtype=np.float32),
            "joint_positions": np.full(9, 0.5, np.float32),
            "gripper_width": np.array([0.04], dtype=np.float32),
        })  # fmt: skip

    features = observe(0.3)
    np.testing.assert_allclose(features[:3], tcp / POSITION_UNIT_M, atol=1e-5)
    np.testing.assert_allclose(features[3:5], [np.cos(0.3), np.sin(0.3)], atol=1e-5)
    assert features[5] == pytest.approx(0.5 / np.pi) and features[6] == pytest.approx(1.0)
    now = features[7:19]  # the keypoints seen now: 5 cm units, then the 1 cm tanh near field; the second unseen
    np.testing.assert_allclose(now[:3], (remembered[0] - tcp) / POSITION_UNIT_M, atol=1e-5)
    np.testing.assert_array_equal(now[3:6], 0.0)
    np.testing.assert_allclose(now[6:9], np.tanh((remembered[0] - tcp) / NEAR_UNIT_M), atol=1e-5)
    np.testing.assert_allclose(features[19:21], [1.0, 0.0])
    np.testing.assert_allclose(features[33:35], [0.0, 0.5])  # ages in the memory's 50 steps
    # The axis seen from the hand: world y, so at hand yaw 0.3 (hand x turned by 0.3, y flipped by the top-down
    # hand) it lies at angle -(pi/2 - 0.3) from hand x; (cos, sin) of the angle and of its double.
    angle = -(np.pi / 2 - 0.3)
    np.testing.assert_allclose(features[35:], [np.cos(angle), np.sin(angle), np.cos(2 * angle), np.sin(2 * angle)],
                               atol=1e-5)  # fmt: skip
    # Continuous where the quaternion is not: just either side of a half turn the hand's features agree.
    a, b = observe(np.pi - 1e-4), observe(np.pi + 1e-4)
    np.testing.assert_allclose(a, b, atol=1e-3)

    with pytest.raises(DonGymError, match="relative_to='tcp'"):
        KeypointFeatures(_DictEnv(space), relative_to="centroid", robot_state=True, encoding="hand")
    with pytest.raises(DonGymError, match="KeypointMemory"):
        KeypointFeatures(_DictEnv(_keypoint_space(2)), relative_to="tcp", robot_state=True, encoding="hand")
    with pytest.raises(DonGymError, match="encoding='hands' is unknown"):
        KeypointFeatures(_DictEnv(space), relative_to="tcp", robot_state=True, encoding="hands")


def test_wrappers_reject_envs_they_cannot_serve():
    plain = spaces.Dict({"ee_pose": spaces.Box(-1.0, 1.0, shape=(7,), dtype=np.float32)})
    with pytest.raises(DonGymError, match="KeypointObservation"):
        KeypointFeatures(_DictEnv(plain))
    with pytest.raises(DonGymError, match="ee_pose"):
        KeypointFeatures(_DictEnv(_keypoint_space(robot=False)), relative_to="tcp")
    with pytest.raises(DonGymError, match="control='grasp'"):
        KeypointGraspAction(_DictEnv(_keypoint_space(), control="ee"))
    with pytest.raises(DonGymError, match="action_frame"):
        KeypointGraspAction(_DictEnv(_keypoint_space()), frame="camera")
    with pytest.raises(DonGymError, match="algorithm"):
        rl.train("dqn", 10)


def test_missing_stable_baselines3_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # makes the import fail
    with pytest.raises(ImportError, match=r'pip install "don-gym\[rl\]"'):
        rl.require_sb3()
    with pytest.raises(ImportError, match=r'pip install "don-gym\[rl\]"'):
        rl.train("ppo", 10)


def test_learning_curve_rolling_means():
    curve = rl.LearningCurve()
    for step, (ret, ok) in enumerate([(0.0, False), (1.0, True), (1.0, True), (-1.0, False)], start=1):
        curve.add(step, ret, ok)
    steps, success, returns = curve.rolling(2)
    np.testing.assert_array_equal(steps, [1, 2, 3, 4])
    np.testing.assert_allclose(success, [0.0, 0.5, 1.0, 0.5])
    np.testing.assert_allclose(returns, [0.0, 0.5, 1.0, 0.0])


@pytest.fixture(scope="module")
def sb3():
    return pytest.importorskip("stable_baselines3")


def test_ppo_on_grasp_with_keypoints(sb3, tmp_path):
    env_kwargs = {"image_size": (64, 48), "sensor": "ideal", "action_frame": "keypoints"}
    # The action frame is the keypoint centroid of the reset observation: action 0 grasps there.
    env = rl.make_ppo_env(**env_kwargs)
    observation, _ = env.reset(seed=3)
    assert env.observation_space.shape == (11,) and env.observation_space.contains(observation)
    grasp_wrapper = env.env
    assert isinstance(grasp_wrapper, KeypointGraspAction)
    centroid = WORKSPACE_CENTRE_M + observation[:3] * POSITION_UNIT_M
    action = grasp_wrapper.grasp_action(np.array([0.0, 0.0, 0.0, 0.0, 1.0]))
    np.testing.assert_allclose(action[:3], centroid, atol=1e-6)
    assert action[3] == pytest.approx(np.pi / 2)
    shifted = grasp_wrapper.grasp_action(np.array([1.0, -1.0, 0.0, -1.0, 0.0]))
    np.testing.assert_allclose(shifted[:2] - centroid[:2], [GRASP_OFFSET_XY_M, -GRASP_OFFSET_XY_M], atol=1e-6)
    assert abs(shifted[3]) == pytest.approx(np.pi)
    # The oracle's keypoints lie on the part: its true position is within a few centimetres.
    true_position = env.unwrapped.task.part.T_world_object[:3, 3]
    assert np.linalg.norm(centroid[:2] - true_position[:2]) < 0.03
    env.close()

    # Every step is a whole scripted grasp-and-place (0.3-1.5 s of physics): 16 steps, two updates.
    steps, n_steps, n_epochs = 16, 8, 2
    result = rl.train(
        "ppo",
        steps,
        seed=0,
        env_kwargs=env_kwargs,
        algo_kwargs={"n_steps": n_steps, "batch_size": n_steps, "n_epochs": n_epochs},
        progress=False,
    )
    model, curve = result.model, result.curve
    assert model.num_timesteps == steps
    assert model._n_updates == n_epochs * steps // n_steps  # two rollouts, each trained on
    # One grasp-and-place per step: every step ends an episode, each judged by the env.
    assert curve.env_steps == list(range(1, steps + 1))
    assert all(isinstance(s, bool) for s in curve.successes)
    returns = np.asarray(curve.returns)
    assert np.all(np.isfinite(returns)) and np.all(returns <= 1.0) and np.all(returns > -3.0)
    # Dense reward: minus distances (<= 0) unless the episode succeeded, which adds 1.
    successes = np.asarray(curve.successes)
    assert np.all(returns[~successes] <= 0.0) and np.all(returns[successes] > 0.5)
    action, _ = model.predict(observation, deterministic=True)
    assert model.action_space.contains(action.astype(np.float32))

    plot_learning_curve([("ppo", curve.rolling(8))], tmp_path / "curve.png", window=8, title="t")
    assert (tmp_path / "curve.png").stat().st_size > 1000


def test_sac_on_ee_repeats_with_a_seed(sb3):
    # Rendering the wrist camera dominates (tens of ms per step even at 48x36): 200 steps per run.
    env_kwargs = {"image_size": (48, 36), "sensor": "ideal", "max_steps": 40}
    algo_kwargs = {"learning_starts": 100, "batch_size": 32, "policy_kwargs": {"net_arch": [32, 32]}}
    runs = [rl.train("sac", 200, seed=1, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False) for _ in "ab"]
    model, curve = runs[0].model, runs[0].curve
    assert model.num_timesteps == 200
    assert model.replay_buffer.size() == 200
    assert model._n_updates == 200 - 100  # one gradient step per env step after learning_starts
    # Episodes of at most 40 steps (truncated there, or ended early when the part left the workspace).
    lengths = np.diff([0, *curve.env_steps])
    assert len(lengths) >= 200 // 40 and np.all((lengths >= 1) & (lengths <= 40))
    assert np.all(np.isfinite(curve.returns)) and np.all(np.asarray(curve.returns) < 0)  # dense: distances
    # Same seed, same run: physics, keypoints and SAC all deterministic with one thread.
    assert runs[1].curve.returns == curve.returns
    for a, b in zip(model.policy.parameters(), runs[1].model.policy.parameters(), strict=True):
        assert np.array_equal(a.detach().numpy(), b.detach().numpy())

    env = rl.make_sac_env(**env_kwargs)
    evaluation = rl.evaluate(env, rl.model_policy(model), n_episodes=1, seed=5, progress=False)
    env.close()
    assert evaluation.lengths[0] <= 40 and len(evaluation.successes) == 1
