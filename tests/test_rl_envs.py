"""RL env pieces: batched DON inference over a vector env, the model of the DON (SimulatedKeypoints), goals
for HER, uint8 descriptor images for SB3's CNN, the axis action frame, run directories and resuming."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import don_gym  # noqa: F401 - registers the envs
from don_gym.agents import rl
from don_gym.agents.rl_demos import ExpertEpisodes
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, make_transform
from don_gym.learning.checkpoints import CheckpointMetadata, save_checkpoint
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import axis_end_targets, load_descriptor_source
from don_gym.sim.task import PLACE_TOLERANCE_M, seated_pose
from don_gym.wrappers import (
    DescriptorImage,
    DescriptorObservation,
    HandStarts,
    KeypointGoal,
    KeypointNoiseModel,
    KeypointObservation,
    SimulatedKeypoints,
    VectorKeypointObservation,
)
from don_gym.wrappers.goals import goal_reached
from don_gym.wrappers.rl import AXIS_OFFSET_M, AXIS_YAW_RAD, KeypointGraspAction
from don_gym.wrappers.simulated_keypoints import axis_points_world, in_view, ring_points_facing

sb3 = pytest.importorskip("stable_baselines3")


def _tiny_checkpoint(path: Path, object_name: str = "toolcap") -> Path:
    torch.manual_seed(0)
    metadata = CheckpointMetadata(
        method="supervised-edge", object_name=object_name, object_mesh_hash="0" * 16, image_size=(48, 36)
    )
    save_checkpoint(path, DenseObjectNet(descriptor_dim=3), metadata)
    return path


@pytest.fixture(scope="module")
def toolcap():
    return load_object("toolcap")


# ------------------------------------------------------------------------------------ batched DON
def test_batched_descriptor_images_equal_one_image_at_a_time(tmp_path: Path, toolcap) -> None:
    source = load_descriptor_source(_tiny_checkpoint(tmp_path / "net.safetensors"), toolcap)
    rgb = np.random.default_rng(0).integers(0, 256, size=(3, 36, 48, 3), dtype=np.uint8)
    batch = source.descriptor_images(rgb)
    assert batch.shape == (3, 36, 48, 3) and batch.dtype == np.float32
    for image, one in zip(rgb, batch, strict=True):
        np.testing.assert_allclose(one, source.descriptor_image({"rgb": image}), atol=1e-5)
    with pytest.raises(DonGymError, match=r"uint8 \(N, H, W, 3\)"):
        source.descriptor_images(rgb[0])


def test_vector_keypoints_equal_the_per_env_wrapper(tmp_path: Path) -> None:
    path = str(_tiny_checkpoint(tmp_path / "net.safetensors"))

    def base():
        return gym.make("DONToolcapPick-v0", control="ee", image_size=(64, 48), max_steps=2, sensor="ideal")

    def per_env():
        return KeypointObservation(base(), model=path, keep_images=False)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an untrained net: references from a reference frame
        expected = SyncVectorEnv([per_env] * 2, autoreset_mode=AutoresetMode.SAME_STEP)
        batched = VectorKeypointObservation(
            SyncVectorEnv([base] * 2, autoreset_mode=AutoresetMode.SAME_STEP), model=path, keep_images=False
        )
    try:
        assert batched.single_observation_space == expected.single_observation_space
        a, _ = expected.reset(seed=[3, 4])
        b, _ = batched.reset(seed=[3, 4])
        pairs = [(a, b)]
        actions = np.random.default_rng(0).uniform(-1, 1, size=(2, 2, 5)).astype(np.float32)
        for action in actions:  # the second step ends both episodes: terminal observations too
            a, *_, info_a = expected.step(action)
            b, *_, info_b = batched.step(action)
            pairs.append((a, b))
        assert info_b["_final_obs"].all()
        pairs += [(info_a["final_obs"][i], info_b["final_obs"][i]) for i in range(2)]
        for a, b in pairs:
            assert set(a) == set(b) and "keypoint_points" in b
            for key in a:
                np.testing.assert_allclose(a[key], b[key], atol=1e-4, err_msg=key)
    finally:
        expected.close()
        batched.close()


# ------------------------------------------------------------------------------ model of the DON
def test_simulated_keypoints_match_the_oracle_pipeline_and_apply_a_noise_model(tmp_path: Path, toolcap) -> None:
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=(160, 120), sensor="ideal")
    oracle = KeypointObservation(env, model="oracle", keep_images=False)
    exact = SimulatedKeypoints(env, noise=None)
    obs_oracle, _ = oracle.reset(seed=7)
    obs_exact, info = exact.reset(seed=7)
    assert exact.observation_space.contains(obs_exact)
    error_mm = 1000 * np.linalg.norm(obs_exact["keypoint_points"] - obs_oracle["keypoint_points"], axis=1)
    assert np.all(error_mm < 3.0), error_mm
    assert np.all(obs_exact["keypoint_confidence"] == 1.0)

    # A noise model of constant 1 cm error along the camera's optical axis, every episode flipped.
    rows = np.array([0, 1])
    noise = KeypointNoiseModel(
        keypoint=rows,
        error_camera_m=np.array([[0.0, 0.0, 0.01], [0.0, 0.0, 0.01]]),
        confidence=np.array([0.7, 0.7]),
        flip_rate=1.0,
        object_name=toolcap.name,
        object_mesh_hash=toolcap.mesh_hash,
        source="test",
    )
    loaded = KeypointNoiseModel.load(noise.save(tmp_path / "noise.keypoint-noise.npz"))
    np.testing.assert_allclose(loaded.error_camera_m, noise.error_camera_m, atol=1e-7)  # stored as float32
    noisy = SimulatedKeypoints(gym.make("DONToolcapPick-v0", control="ee", image_size=None), noise=loaded)
    obs, info = noisy.reset(seed=7)
    truth = ring_points_facing(toolcap, noisy.targets, info["T_world_object"], info["T_world_camera"][:3, 3])
    shift = info["T_world_camera"][:3, :3] @ np.array([0.0, 0.0, 0.01])
    np.testing.assert_allclose(obs["keypoint_points"], truth[::-1] + shift, atol=1e-5)  # swapped ends
    np.testing.assert_allclose(obs["keypoint_confidence"], 0.7)
    noisy.close()

    # From a tracking evaluation's per-match errors: magnitudes kept, matches without depth become misses.
    tracked = KeypointNoiseModel.from_tracking(np.array([0.002, 0.05, 0.01]), np.array([True, True, False]), toolcap)
    magnitudes = np.linalg.norm(tracked.error_camera_m[tracked.rows_of(0)], axis=1)
    np.testing.assert_allclose(magnitudes[:2], [0.002, 0.05])
    assert np.isnan(magnitudes[2]) and tracked.confidence[tracked.rows_of(1)].tolist() == [1.0, 1.0, 0.0]

    shaft = load_object("shaft")
    other = KeypointNoiseModel(rows, noise.error_camera_m, noise.confidence, 0.0, shaft.name, shaft.mesh_hash)
    with pytest.raises(DonGymError, match=r"noise=.*measured on object 'shaft'.*'toolcap'"):
        SimulatedKeypoints(env, noise=other)
    with pytest.raises(DonGymError, match="no-such-net"):
        SimulatedKeypoints(env, noise="toolcap/no-such-net")
    env.close()


def test_in_view_is_a_field_of_view_test() -> None:
    intrinsics = CameraIntrinsics.d435(64, 48)
    T_world_camera = make_transform(translation=[0.0, 0.0, -1.0])  # looking along world +z
    points = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
    uv, visible = in_view(points, T_world_camera, intrinsics)
    assert visible.tolist() == [True, False, False]
    np.testing.assert_allclose(uv[0], [intrinsics.cx, intrinsics.cy])


# ---------------------------------------------------------------------------------------- goals
def test_goal_env_passes_sb3_check_env_and_rewards_agree_with_success(toolcap) -> None:
    from stable_baselines3.common.env_checker import check_env

    env = KeypointGoal(SimulatedKeypoints(gym.make("DONToolcapPick-v0", control="ee", image_size=None)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, warn=True, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    targets = axis_end_targets(toolcap)
    seated = axis_points_world(toolcap, targets, seated_pose(toolcap)).reshape(6)
    np.testing.assert_allclose(obs["desired_goal"], seated, atol=1e-6)
    # Vectorised: the goal itself, within / beyond the task's placement distance, the part reversed.
    moved = seated + np.tile([0.0, 0.0, 0.9 * PLACE_TOLERANCE_M], 2)
    away = seated + np.tile([0.0, 0.0, 1.1 * PLACE_TOLERANCE_M], 2)
    reversed_part = seated.reshape(2, 3)[::-1].reshape(6)
    rewards = env.compute_reward(np.stack([seated, moved, away, reversed_part]), np.tile(seated, (4, 1)), [{}] * 4)
    np.testing.assert_array_equal(rewards, [0.0, 0.0, -1.0, -1.0])
    env.close()

    # A grasp-and-place the task judges a success leaves the part at the goal.
    grasp = gym.make("DONToolcapPick-v0", control="grasp", image_size=None).unwrapped
    grasp.reset(seed=1)
    *_, info = grasp.step(grasp.oracle_action())
    assert info["is_success"]
    assert goal_reached(axis_points_world(toolcap, targets, info["T_world_object"]).reshape(6), seated)
    grasp.close()


def test_the_lift_sub_task_is_registered_and_is_the_sac_baselines_env() -> None:
    from stable_baselines3.common.env_checker import check_env

    env = gym.make("DONToolcapLift-v0", max_steps=10, hand_starts={"in_hand": 1.0})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, warn=True, skip_render_check=True)
    baseline = rl.make_sac_env(goal="lift", keypoints="true", max_steps=10, hand_starts={"in_hand": 1.0})
    obs, info = env.reset(seed=5)
    expected, _ = baseline.reset(seed=5)
    for key in ("observation", "achieved_goal", "desired_goal"):
        np.testing.assert_allclose(obs[key], expected[key], atol=1e-6)
    start = obs["achieved_goal"].copy()
    np.testing.assert_allclose(obs["desired_goal"] - start, np.tile([0.0, 0.0, 0.06], 2), atol=1e-6)
    assert info["hand_start"] == "in_hand"
    # Up with the gripper closed: the part comes along until the goal is reached, which ends the episode.
    for _ in range(10):
        obs, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, 1.0, 0.0, -1.0], dtype=np.float32))
        assert reward == float(env.get_wrapper_attr("compute_reward")(obs["achieved_goal"], obs["desired_goal"], info))
        if terminated or truncated:
            break
    assert info["is_success"] and terminated and reward == 0.0
    assert obs["achieved_goal"][2] > start[2] + 0.05
    env.close()
    baseline.close()
    shaft = gym.make("DONShaftLift-v0", keypoints="simulated", keypoint_model="shaft/supervised-edge")
    assert shaft.get_wrapper_attr("object_model").name == "shaft"
    shaft.close()
    with pytest.raises(DonGymError, match="keypoints='camera'"):
        gym.make("DONLift-v0", object="toolcap", keypoints="camera")
    with pytest.raises(DonGymError, match="goal='stack'"):
        gym.make("DONLift-v0", goal="stack")


def test_hand_starts_put_the_hand_at_or_on_the_part_and_the_part_lifts_from_the_hand(toolcap) -> None:
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=None, max_steps=20)
    u = env.unwrapped
    _, info = env.reset(seed=3, options={"hand_start": "above_part"})
    grasp_point = u.oracle_action()[:3]
    tcp = u.robot.tcp_pose()[:3, 3]
    assert info["hand_start"] == "above_part"
    np.testing.assert_allclose(tcp[:2], grasp_point[:2], atol=0.01)
    assert tcp[2] > grasp_point[2] + 0.08 and u.robot.gripper_width() > 0.06  # open, above the part
    _, info = env.reset(seed=3, options={"hand_start": "in_hand"})
    z_start = info["T_world_object"][2, 3]
    assert all(u.robot.contacts(u.task).fingers) and u.robot.gripper_width() < 0.05
    for _ in range(3):  # up, gripper kept closed: the part comes along
        *_, info = env.step(np.array([0.0, 0.0, 1.0, 0.0, -1.0], dtype=np.float32))
    assert info["lifted"] and info["T_world_object"][2, 3] > z_start + 0.05
    # The task's own start is unchanged by the option's existence.
    obs_default, _ = env.reset(seed=3)
    obs_observe, _ = env.reset(seed=3, options={"hand_start": "observe"})
    np.testing.assert_allclose(obs_default["ee_pose"], obs_observe["ee_pose"], atol=1e-6)
    env.close()

    starts = HandStarts(gym.make("DONToolcapPick-v0", control="ee", image_size=None), {"in_hand": 0.5})
    drawn = [starts.reset(seed=seed)[1]["hand_start"] for seed in range(8)]
    assert set(drawn) == {"in_hand", "observe"}
    assert drawn == [starts.reset(seed=seed)[1]["hand_start"] for seed in range(8)]  # seeded
    assert starts.reset(seed=0, options={"hand_start": "at_part"})[1]["hand_start"] == "at_part"
    starts.close()


def test_a_hand_start_that_looks_first_remembers_the_part_as_seen_from_the_task_start() -> None:
    from don_gym.wrappers.goals import make_keypoint_env
    from don_gym.wrappers.memory import UNSEEN_POINT_M

    def env(look_first: bool) -> gym.Env:
        return make_keypoint_env(
            "toolcap", "simulated", "oracle", hand_starts={"at_part": 1.0}, memory=True, look_first=look_first,
            control="ee", max_steps=20,
        )  # fmt: skip

    seen_from_above, _ = env(False).reset(seed=5, options={"hand_start": "observe"})
    assert np.all(seen_from_above["keypoint_confidence"] > 0.5)
    # At the part the camera is too near to see it: without a look, the memory holds nothing.
    blind, info = env(False).reset(seed=5)
    assert info["hand_start"] == "at_part" and np.all(blind["keypoint_confidence"] == 0)
    np.testing.assert_allclose(blind["keypoint_age"], 20)
    np.testing.assert_allclose(blind["keypoint_memory_points"], np.tile(UNSEEN_POINT_M, (2, 1)), atol=1e-6)
    looking = env(True)
    obs, info = looking.reset(seed=5)
    assert info["hand_start"] == "at_part" and np.all(obs["keypoint_confidence"] == 0)
    np.testing.assert_allclose(obs["keypoint_age"], 1)  # seen at the reset, then one step that held still
    np.testing.assert_allclose(obs["keypoint_memory_points"], seen_from_above["keypoint_points"], atol=1e-6)
    tcp = looking.unwrapped.robot.tcp_pose()[:3, 3]
    grasp_point = looking.unwrapped.oracle_action()[:3]
    np.testing.assert_allclose(tcp, grasp_point, atol=0.02)  # the hand is at the part all the same
    # The SAC env's hand-frame encoding carries that memory into the policy's input, from the TCP.
    from don_gym.wrappers.rl import two_scale_offsets

    hand = rl.make_sac_env(
        keypoints="simulated", goal="lift", max_steps=20, memory=True, encoding="hand", hand_starts={"at_part": 1.0},
        look_first=True,
    )  # fmt: skip
    features = hand.reset(seed=5)[0]["observation"]
    assert features.shape == (39,)
    remembered = two_scale_offsets(seen_from_above["keypoint_points"] - hand.unwrapped.robot.tcp_pose()[:3, 3])
    np.testing.assert_allclose(features[21:33], remembered, atol=1e-4)
    with pytest.raises(DonGymError, match="call reset"):
        looking.unwrapped.start_hand("in_hand")  # the hold step was the episode's first
    with pytest.raises(DonGymError, match="look_first=True needs keypoints"):
        make_keypoint_env("toolcap", None, hand_starts={"at_part": 1.0}, look_first=True, control="ee")
    with pytest.raises(DonGymError, match="look_first=True: batched"):
        rl.make_batched_sac_vec_env(1, {"hand_starts": {"at_part": 1.0}, "look_first": True})
    with pytest.raises(DonGymError, match="look_first='yes'"):
        HandStarts(gym.make("DONToolcapPick-v0", control="ee", image_size=None), {"in_hand": 0.5}, look_first="yes")
    with pytest.raises(DonGymError, match="max_steps=1"):
        HandStarts(gym.make("DONToolcapPick-v0", control="ee", image_size=None, max_steps=1), {"in_hand": 1.0}, True)
    grasp_mode = gym.make("DONToolcapPick-v0", image_size=None)
    grasp_mode.reset(seed=0)
    with pytest.raises(DonGymError, match="needs control='ee'"):
        grasp_mode.unwrapped.start_hand("in_hand")
    with pytest.raises(DonGymError, match="hand_start='flying'"):
        looking.unwrapped.start_hand("flying")


def test_sac_her_trains_writes_its_run_and_resumes(tmp_path: Path) -> None:
    env_kwargs = {"keypoints": "true", "goal": "lift", "max_steps": 10}
    algo_kwargs = {
        "learning_starts": 20, "batch_size": 16, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16, 16]}
    }  # fmt: skip
    run_dir = tmp_path / "run"
    first = rl.train("sac", 40, seed=0, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False,
                     run_dir=run_dir, save_every=20)  # fmt: skip
    model = first.model
    assert type(model.replay_buffer).__name__ == "HerReplayBuffer"
    # The policy sees the keypoints and the desired goal, not the true achieved goal.
    assert set(model.policy.actor.features_extractor.extractors) == {"observation", "desired_goal"}
    for name in (
        "config",
        "curve_csv",
        "curve_png",
        "model",
        "last_model",
        "last_buffer",
        "last_curve",
        "last_progress",
    ):
        assert (run_dir / rl.RUN_FILES[name]).is_file(), name
    config = json.loads((run_dir / "config.json").read_text())
    assert config["seeds"] == {"algorithm": 0, "envs_first_reset": [0]} and config["finished"]
    assert len(rl.LearningCurve.read_csv(run_dir / "curve.csv").successes) == len(first.curve.successes) == 4
    resumed = rl.train("sac", 60, seed=0, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False,
                       run_dir=run_dir, resume=True)  # fmt: skip
    assert resumed.model.num_timesteps == 60 and len(resumed.curve.successes) == 6
    # The run's training time adds up over its sessions; a resume that trains nothing adds ~nothing.
    assert resumed.run_wall_s == pytest.approx(first.run_wall_s + resumed.wall_s)
    assert resumed.run_wall_s > first.run_wall_s
    # A finished run is only loaded, at its own budget or a smaller one: no file of it changes.
    files = {path.name: path.read_bytes() for path in run_dir.iterdir()}
    for steps in (60, 40):
        again = rl.train("sac", steps, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, run_dir=run_dir, resume=True,
                         progress=False)  # fmt: skip
        assert again.model.num_timesteps == 60 and again.run_wall_s == resumed.run_wall_s
        assert len(again.curve.successes) == 6
    assert {path.name: path.read_bytes() for path in run_dir.iterdir()} == files
    assert json.loads((run_dir / "progress_last.json").read_text()) == {"timesteps": 60, "wall_s": again.run_wall_s}
    with pytest.raises(DonGymError, match="other"):
        rl.train("sac", 80, env_kwargs=env_kwargs | {"max_steps": 5}, run_dir=run_dir, resume=True, progress=False)
    with pytest.raises(DonGymError, match="nothing|holds no"):
        rl.train("sac", 80, env_kwargs=env_kwargs, run_dir=tmp_path / "empty", resume=True, progress=False)


def test_expert_demonstrations_seed_the_buffer_and_behaviour_cloning_pulls_the_actor_to_them(tmp_path: Path) -> None:
    env_kwargs = {"keypoints": "true", "goal": "lift", "max_steps": 50, "hand_starts": {"in_hand": 1.0}}
    algo_kwargs = {
        "learning_starts": 20, "batch_size": 16, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16, 16]}
    }  # fmt: skip
    runs = {}
    for name, bc_weight in (("plain", 0.0), ("bc", 1.0)):
        runs[name] = rl.train("sac", 200, seed=0, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False,
                              run_dir=tmp_path / name, demonstrations=2, bc_weight=bc_weight)  # fmt: skip
    demos = ExpertEpisodes.load(tmp_path / "bc" / rl.RUN_FILES["demonstrations"])
    # From the task's start (not the run's in-hand starts) the expert lifts the part in both episodes.
    assert demos.successes == [True, True]
    n = len(demos.actions)
    assert demos.actions.shape == (n, 5) and 40 < n < 100 and np.abs(demos.actions).max() <= 1.0
    assert set(demos.observations) == {"observation", "achieved_goal", "desired_goal"}
    buffer = runs["bc"].model.replay_buffer
    # The demonstrations come first in the buffer, as whole episodes HER can relabel, then the run's own steps.
    assert buffer.pos == n + 200
    np.testing.assert_array_equal(buffer.actions[:n, 0], demos.actions)
    assert buffer.dones[n - 1, 0] and int(buffer.ep_length[0, 0]) + int(buffer.ep_length[n - 1, 0]) == n
    np.testing.assert_array_equal(buffer.observations["desired_goal"][:n, 0], demos.observations["desired_goal"])

    def imitation_error(model) -> float:
        actions, _ = model.predict(demos.observations, deterministic=True)
        return float(np.mean((actions - demos.actions) ** 2))

    # The same run with the behaviour-cloning step lies closer to the expert's actions on its states.
    errors = {name: imitation_error(run.model) for name, run in runs.items()}
    assert errors["bc"] < 0.5 * errors["plain"]
    config = json.loads((tmp_path / "bc" / "config.json").read_text())
    assert config["demonstrations"] == {"episodes": 2, "bc_weight": 1.0, "demo_fraction": 0.0}
    resumed = rl.train("sac", 210, seed=0, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False,
                       run_dir=tmp_path / "bc", resume=True, demonstrations=2, bc_weight=1.0)  # fmt: skip
    assert resumed.model.num_timesteps == 210
    with pytest.raises(DonGymError, match="other \\['demonstrations'\\]"):
        rl.train("sac", 100, env_kwargs=env_kwargs, run_dir=tmp_path / "bc", resume=True, progress=False)
    for bad, match in (
        ({"demonstrations": -1}, "demonstrations=-1"),
        ({"demonstrations": 2, "bc_weight": float("nan")}, "bc_weight=nan"),
        ({"bc_weight": 1.0}, "needs demonstrations"),
        ({"demonstrations": 2, "demo_fraction": 1.5}, "demo_fraction=1.5: expected a share"),
        ({"demo_fraction": 0.5}, "demo_fraction=0.5 needs demonstrations"),
    ):
        with pytest.raises(DonGymError, match=match):
            rl.train("sac", 10, env_kwargs=env_kwargs, progress=False, **bad)
    with pytest.raises(DonGymError, match="algorithm='ppo'"):
        rl.train("ppo", 10, env_kwargs={"keypoints": "true"}, progress=False, demonstrations=2)


def test_demo_fraction_draws_that_share_of_each_batch_from_the_demonstrations(tmp_path: Path) -> None:
    from don_gym.agents.rl_buffer import DemonstrationHerReplayBuffer

    env_kwargs = {"keypoints": "true", "goal": "lift", "max_steps": 10}
    algo_kwargs = {
        "learning_starts": 20, "batch_size": 16, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16, 16]}
    }  # fmt: skip
    run = rl.train("sac", 60, seed=0, env_kwargs=env_kwargs, algo_kwargs=algo_kwargs, progress=False,
                   run_dir=tmp_path / "run", demonstrations=2, demo_fraction=0.25)  # fmt: skip
    buffer = run.model.replay_buffer
    demos = ExpertEpisodes.load(tmp_path / "run" / rl.RUN_FILES["demonstrations"])
    assert isinstance(buffer, DemonstrationHerReplayBuffer) and buffer.demo_rows == len(demos.actions)
    assert buffer.pos == buffer.demo_rows + 60
    expert_actions = {tuple(a) for a in buffer.actions[: buffer.demo_rows, 0]}

    def from_demos(batch_size: int) -> int:
        samples = buffer.sample(batch_size)
        return sum(tuple(a) in expert_actions for a in samples.actions.numpy())

    # A quarter of every batch from the demonstrations, whatever their share of the buffer (2 short episodes
    # of the expert's against 60 steps of the run's own).
    assert [from_demos(64) for _ in range(5)] == [16] * 5
    buffer.demo_fraction = 0.5
    assert from_demos(64) == 32
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["demonstrations"]["demo_fraction"] == 0.25


# ------------------------------------------------------------------------------ descriptor images
def test_descriptor_images_are_sb3_images_with_a_cnn() -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_checker import check_env
    from stable_baselines3.common.torch_layers import NatureCNN

    env = gym.make("DONToolcapPick-v0", control="ee", image_size=(64, 48), sensor="ideal")
    described = DescriptorObservation(env, model="oracle")
    images = DescriptorImage(described, keep=("ee_pose", "gripper_width"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(images, warn=True, skip_render_check=True)
    obs, _ = images.reset(seed=0)
    assert obs["descriptors"].dtype == np.uint8 and obs["descriptors"].shape == (48, 64, 3)
    float_obs, _ = described.reset(seed=0)
    recovered = obs["descriptors"] * images.descriptor_scale
    np.testing.assert_allclose(recovered, np.clip(float_obs["descriptors"], 0, 1), atol=images.descriptor_scale)
    model = PPO("MultiInputPolicy", images, n_steps=8, batch_size=8, device="cpu")
    assert isinstance(model.policy.features_extractor.extractors["descriptors"], NatureCNN)
    with pytest.raises(DonGymError, match="36x36"):
        DescriptorImage(described, size=(32, 24))
    env.close()


# --------------------------------------------------------------------------------- axis actions
class _GraspEnv(gym.Env):
    control = "grasp"

    def __init__(self, points: np.ndarray, confidence: np.ndarray):
        self.observation_space = gym.spaces.Dict(
            {
                "keypoint_points": gym.spaces.Box(-10, 10, shape=(2, 3), dtype=np.float32),
                "keypoint_confidence": gym.spaces.Box(0, 1, shape=(2,), dtype=np.float32),
            }
        )
        self.action_space = gym.spaces.Box(-5, 5, shape=(4,), dtype=np.float32)
        self.points, self.confidence = points, confidence

    def reset(self, *, seed=None, options=None):
        return {"keypoint_points": self.points, "keypoint_confidence": self.confidence}, {}

    def step(self, action):
        return self.reset()[0], 0.0, True, False, {"action": action}


def test_axis_action_frame_is_residual_about_the_keypoints() -> None:
    points = np.array([[0.5, 0.0, 0.02], [0.5, 0.02, 0.02]], np.float32)  # axis along world +y
    env = KeypointGraspAction(_GraspEnv(points, np.ones(2, np.float32)), frame="axis", axis_depth_m=0.005)
    assert env.action_space.shape == (4,)
    env.reset()
    np.testing.assert_allclose(env.grasp_action(np.zeros(4)), [0.5, 0.01, 0.015, np.pi / 2], atol=1e-6)
    moved = env.grasp_action(np.array([1.0, 1.0, -1.0, 1.0]))
    expected = [0.5 - AXIS_OFFSET_M, 0.01 + AXIS_OFFSET_M, 0.015 - AXIS_OFFSET_M]
    np.testing.assert_allclose(moved[:3], expected, atol=1e-6)
    assert moved[3] == pytest.approx(np.pi / 2 + AXIS_YAW_RAD)
    # One keypoint not found: the frame falls back to the centroid of the found one, yaw 0.
    lost = KeypointGraspAction(_GraspEnv(points, np.array([1.0, 0.0], np.float32)), frame="axis", axis_depth_m=0.005)
    lost.reset()
    np.testing.assert_allclose(lost.grasp_action(np.zeros(4)), [0.5, 0.0, 0.02, 0.0], atol=1e-6)
    # By default the origin is lowered by the part's ring radius: from the surface to the axis.
    part = SimulatedKeypoints(gym.make("DONToolcapPick-v0", control="grasp", image_size=None))
    radii = axis_end_targets(part.object_model).radii_m
    assert KeypointGraspAction(part, frame="axis").axis_depth_m == pytest.approx(float(np.mean(radii)))
    part.close()


# ------------------------------------------------------------------------------------ bad input
def test_bad_rl_inputs_give_one_line_errors(tmp_path: Path) -> None:
    shaft_net = _tiny_checkpoint(tmp_path / "shaft.safetensors", object_name="shaft")
    with pytest.raises(DonGymError, match="shaft"):
        rl.make_sac_env(keypoint_model=str(shaft_net), image_size=(64, 48))
    with pytest.raises(DonGymError, match="n_envs=0"):
        rl.train("sac", 10, n_envs=0)
    with pytest.raises(DonGymError, match="n_envs=0"):
        rl.make_batched_sac_vec_env(0)
    with pytest.raises(DonGymError, match="keypoints='camera'"):
        rl.make_sac_env(keypoints="camera")
    with pytest.raises(DonGymError, match="goal='stack'"):
        rl.make_sac_env(goal="stack", keypoints="true")
    with pytest.raises(DonGymError, match="'hand_start'"):
        gym.make("DONToolcapPick-v0", control="ee", image_size=None).reset(options={"hand_start": "flying"})
    with pytest.raises(DonGymError, match="needs control='ee'"):
        gym.make("DONToolcapPick-v0", image_size=None).reset(options={"hand_start": "in_hand"})
    with pytest.raises(DonGymError, match="'in_the_air' is unknown"):
        rl.make_sac_env(keypoints="true", hand_starts={"in_the_air": 0.5})
    with pytest.raises(DonGymError, match="add up to 1.5"):
        rl.make_sac_env(keypoints="true", hand_starts={"in_hand": 0.75, "at_part": 0.75})
    with pytest.raises(DonGymError, match=r"shares\['in_hand'\]=-0.1"):
        rl.make_sac_env(keypoints="true", hand_starts={"in_hand": -0.1})
    with pytest.raises(DonGymError, match="vectorize='batched'"):
        rl.make_vec_env("ppo", 2, 0, {}, vectorize="batched")
