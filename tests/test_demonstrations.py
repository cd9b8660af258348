"""The Markov end-effector expert and its demonstrations in robomimic's HDF5 layout."""

from __future__ import annotations

import json

import numpy as np
import pytest

import don_gym  # noqa: F401  (registers the env ids)
from don_gym.agents.ee_expert import EndEffectorExpert
from don_gym.errors import DonGymError
from don_gym.wrappers import make_goal_env

h5py = pytest.importorskip("h5py")

from don_gym.evaluation.demonstrations import (  # noqa: E402
    DEMO_FORMAT,
    read_demonstrations,
    record_demonstrations,
)


def run_expert(goal: str, seed: int, max_steps: int) -> tuple[bool, int]:
    env = make_goal_env("toolcap", goal=goal, keypoints="true", max_steps=max_steps)
    expert = EndEffectorExpert(env, goal)
    obs, info = env.reset(seed=seed)
    steps = 0
    try:
        while steps < max_steps:
            obs, _, terminated, truncated, info = env.step(expert.act(obs))
            steps += 1
            if terminated or truncated:
                break
    finally:
        env.close()
    return bool(info["is_success"]), steps


@pytest.mark.parametrize(("goal", "max_steps"), [("lift", 100), ("place", 200)])
def test_expert_solves_the_task(goal, max_steps):
    success, steps = run_expert(goal, seed=11, max_steps=max_steps)
    assert success and steps < max_steps


def test_expert_is_markov_it_recovers_from_any_state():
    """No phase is kept: an expert made mid-episode (or fed a state another policy left) carries on."""
    env = make_goal_env("toolcap", goal="lift", keypoints="true", max_steps=100)
    try:
        obs, _ = env.reset(seed=5)
        first = EndEffectorExpert(env, "lift")
        for _ in range(10):
            obs, *_ = env.step(first.act(obs))
        for _ in range(6):  # a disturbance on the way down: off course, turned, the gripper closing on nothing
            obs, *_ = env.step(np.array([0.3, -0.4, 0.2, 0.5, -1.0], np.float32))
        second = EndEffectorExpert(env, "lift")
        np.testing.assert_array_equal(first.act(obs), second.act(obs))
        info = {"is_success": False}
        for _ in range(84):
            obs, _, terminated, truncated, info = env.step(second.act(obs))
            if terminated or truncated:
                break
        assert info["is_success"]
    finally:
        env.close()
    with pytest.raises(DonGymError, match="goal="):
        EndEffectorExpert(env, "stack")


def test_recorded_demonstrations_follow_robomimics_layout(tmp_path):
    path = record_demonstrations(
        tmp_path / "lift.hdf5", "toolcap", "lift", episodes=2, seed=3,
        kinds=["true", "rgbd", "simulated:toolcap/supervised-edge"], progress=False,
    )  # fmt: skip
    with h5py.File(path, "r") as f:
        data = f["data"]
        assert data.attrs["format"] == DEMO_FORMAT
        env_args = json.loads(data.attrs["env_args"])
        assert env_args["env_kwargs"]["object"] == "toolcap" and env_args["goal"] == "lift"
        assert sorted(data) == ["demo_0", "demo_1"]
        demo = data["demo_0"]
        T = int(demo.attrs["num_samples"])
        assert data.attrs["total"] == T + int(data["demo_1"].attrs["num_samples"])
        assert demo["actions"].shape == (T, 5) and demo["dones"][-1] == 1 and demo["rewards"][-1] == 0.0
        assert demo["obs/rgb"].shape == (T, 96, 128, 3) and demo["next_obs/depth"].shape == (T, 96, 128)
        # next_obs is obs one step on; the true keypoints sit on the part, the simulated ones near them.
        np.testing.assert_array_equal(demo["next_obs/ee_pose"][:-1], demo["obs/ee_pose"][1:])
        true_points = demo["obs/true.keypoint_points"][()]
        simulated = demo["obs/simulated-toolcap-supervised-edge.keypoint_points"][()]
        seen = demo["obs/simulated-toolcap-supervised-edge.keypoint_confidence"][()] > 0.5
        assert seen[0].all() and np.median(np.linalg.norm(true_points - simulated, axis=-1)[seen]) < 0.01
        np.testing.assert_allclose(true_points[0].mean(axis=0)[:2], demo["obs/part_pose"][0, :2], atol=0.03)
        assert list(f["mask/all"][()]) == [b"demo_0", b"demo_1"]
    demos = read_demonstrations(path, count=1, part="toolcap", goal="lift", keys=["true.keypoint_points"])
    assert len(demos.actions) == 1 and list(demos.observations[0]) == ["true.keypoint_points"]
    assert demos.seeds == [3]


def test_bad_demonstration_requests_are_one_line_errors(tmp_path):
    path = record_demonstrations(tmp_path / "lift.hdf5", "toolcap", "lift", episodes=1, seed=0, progress=False)
    cases = [
        ({"goal": "place"}, "are of the task 'lift'; expected 'place'"),
        ({"part": "shaft"}, "are of the part 'toolcap'; expected 'shaft'"),
        ({"count": 5}, "count=5: demonstrations .* hold 1"),
        ({"keys": ["rgb"]}, r"observation keys \['rgb'\]: not in"),
    ]
    for kwargs, message in cases:
        with pytest.raises(DonGymError, match=message) as error:
            read_demonstrations(path, **kwargs)
        assert "\n" not in str(error.value)
    with pytest.raises(DonGymError, match="no such file"):
        read_demonstrations(tmp_path / "missing.hdf5")
    with pytest.raises(DonGymError, match="observation kind 'depth' is unknown"):
        record_demonstrations(tmp_path / "x.hdf5", kinds=["depth"], progress=False)
    assert not (tmp_path / "x.hdf5").exists()


def test_dart_demonstrations_run_noisy_actions_and_keep_the_experts(tmp_path):
    """With action_noise the episodes run the expert's actions plus noise on the motion, the file labels each state
    with the expert's own action, and the other kinds replay what ran (the replay checks it step by step)."""
    path = record_demonstrations(
        tmp_path / "dart.hdf5", "toolcap", "lift", episodes=1, seed=4, kinds=["true"], progress=False,
        action_noise=0.1,
    )  # fmt: skip
    with h5py.File(path, "r") as f:
        demo = f["data/demo_0"]
        expert, executed = demo["actions"][()], demo["executed_actions"][()]
        assert f["data"].attrs["action_noise"] == 0.1
    motion = executed[:, :4] - expert[:, :4]
    assert 0.05 < np.std(motion) < 0.15  # the noise, clipped at the action box's edge
    np.testing.assert_array_equal(executed[:, 4], expert[:, 4])  # the gripper is never perturbed
    assert read_demonstrations(path).action_noise == 0.1
    # The expert holds its hand at the grasp point while closing: it corrects the drift noise causes there.
    env = make_goal_env("toolcap", goal="lift", keypoints="true", max_steps=100)
    try:
        obs, _ = env.reset(seed=4)
        expert_policy = EndEffectorExpert(env, "lift")
        while env.unwrapped.robot.gripper_width() > 0.07:  # until the fingers are closing
            obs, *_ = env.step(expert_policy.act(obs))
        obs, *_ = env.step(np.array([0.0, 0.0, 0.2, 0.0, -1.0], np.float32))  # knocked up some millimetres
        action = expert_policy.act(obs)
        assert action[4] == -1.0 and action[2] < -0.05  # still closing, and back down
    finally:
        env.close()
    for noise in (-0.1, 1.5, True, "0.1"):
        with pytest.raises(DonGymError, match="action_noise=") as error:
            record_demonstrations(tmp_path / "x.hdf5", action_noise=noise, progress=False)
        assert "\n" not in str(error.value)
    assert not (tmp_path / "x.hdf5").exists()
