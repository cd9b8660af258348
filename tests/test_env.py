"""The PyBullet pick-and-place env: API checks, physics of the scripted grasp, determinism, bad input.

Images are tiny (32x24) unless a test is about images. The oracle tests are the physics proof:
with the true pose the scripted robot must put the toolcap into the cradle from every fixed pose,
and a flipped axis must end reversed (grasp_only), before any descriptor is involved.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pybullet as p
import pytest
import trimesh

import don_gym  # noqa: F401  (registers the env ids)
from don_gym.errors import DonGymError, MeshError
from don_gym.geometry import invert_transform, project_points, transform_points
from don_gym.sim.backdrop import BACKDROP_SETS
from don_gym.sim.camera import body_mask, render_camera
from don_gym.sim.env import PickPlaceEnv
from don_gym.sim.part import radius_profile
from don_gym.sim.task import FIXED_POSES, TABLE_TOP_Z_M, grasp_axial_position_m

TINY = (32, 24)


@pytest.fixture(scope="module")
def grasp_env():
    env = gym.make("DONToolcapPick-v0", image_size=None, sensor="ideal").unwrapped
    yield env
    env.close()


def _run(env: PickPlaceEnv, pose_id: int, flip: bool = False, offset=(0.0, 0.0, 0.0), yaw_error_deg: float = 0.0):
    env.reset(options={"pose_id": pose_id})
    action = env.oracle_action(flip=flip).astype(np.float64)
    action[:3] += offset
    action[3] += np.deg2rad(yaw_error_deg)
    _, reward, terminated, truncated, info = env.step(action)
    assert terminated and not truncated
    assert isinstance(reward, float)
    return info


# ----------------------------------------------------------------------------- physics proof
@pytest.mark.slow
def test_oracle_places_toolcap_from_all_fixed_poses_and_flipped_axis_ends_reversed(grasp_env):
    outcomes, flipped = [], []
    for k in range(len(FIXED_POSES)):
        info = _run(grasp_env, k)
        outcomes.append(info["outcome"])
        assert info["is_success"] == (info["outcome"] == "grasp_and_place")
        if info["outcome"] == "grasp_and_place":
            assert info["placement_distance_m"] <= 0.02 and np.rad2deg(info["placement_axis_error_rad"]) <= 20
        info = _run(grasp_env, k, flip=True)
        flipped.append(info["outcome"])
        # Reversed in the cradle: lifted and set down, but the +axis points backwards.
        assert info["lifted"]
        assert np.rad2deg(info["placement_axis_error_rad"]) > 150, k
    assert outcomes == ["grasp_and_place"] * 8, outcomes
    assert flipped == ["grasp_only"] * 8, flipped


def test_grasp_tolerates_a_few_millimetres_and_degrees(grasp_env):
    # Errors of the size a good descriptor pipeline makes: 4 mm in x, y or z, 5 degrees of yaw.
    cases = [(0, (0.004, -0.004, 0.0), 5.0), (5, (-0.004, 0.0, -0.004), -5.0), (2, (0.0, 0.004, 0.003), 4.0)]
    for pose_id, offset, yaw_error in cases:
        info = _run(grasp_env, pose_id, offset=offset, yaw_error_deg=yaw_error)
        assert info["outcome"] == "grasp_and_place", (pose_id, offset, yaw_error, info["outcome"])


def test_grasp_far_off_the_part_fails_and_reward_is_sparse(grasp_env):
    grasp_env.reset(options={"pose_id": 3})
    action = grasp_env.oracle_action()
    action[0] += 0.08  # 8 cm beside the part: the fingers close on air
    _, reward, terminated, _, info = grasp_env.step(action)
    assert terminated and info["outcome"] == "fail" and not info["lifted"] and reward == 0.0
    # The part was not moved.
    assert np.linalg.norm(info["T_world_object"][:2, 3] - np.array(FIXED_POSES[3][:2])) < 0.01


def test_shaft_oracle_on_a_few_poses():
    env = gym.make("DONShaftPick-v0", image_size=None, sensor="ideal").unwrapped
    try:
        for k in (0, 3, 6):
            info = _run(env, k)
            assert info["outcome"] == "grasp_and_place", (k, info["outcome"])
        assert _run(env, 3, flip=True)["outcome"] == "grasp_only"
    finally:
        env.close()


def test_shaft_grasp_keeps_the_pads_off_the_collar_steps_and_places_the_centre_of_mass():
    # A pad end on the collar's step hooks the part, which then follows one finger out of the
    # cradle when the gripper opens; the grasp point leaves room for millimetres of perception error.
    env = gym.make("DONShaftPick-v0", image_size=None, sensor="ideal").unwrapped
    try:
        model = env.model
        axis = np.asarray(model.plus_axis, dtype=np.float64)
        centred = model.mesh.copy()
        centred.apply_translation(-model.center_of_mass)
        profile = radius_profile(centred, axis)
        grasp = grasp_axial_position_m(model)
        under_pads = profile[np.abs(profile[:, 0] - grasp) <= 0.011 + 0.007]
        assert len(under_pads) > 2 and np.ptp(under_pads[:, 1]) < 1e-5, under_pads
        # The script offsets the hand by the grasp point's axial position: the centre of mass, not
        # the grasp point (18 mm from it), ends over the groove's centre.
        info = _run(env, 5)
        assert info["outcome"] == "grasp_and_place"
        assert info["placement_distance_m"] < 0.004, info["placement_distance_m"]
    finally:
        env.close()


def test_part_mass_and_inertia_come_from_the_model(grasp_env):
    info = grasp_env.sim.client.getDynamicsInfo(grasp_env.task.part.body_id, -1)
    assert info[0] == pytest.approx(grasp_env.model.mass_kg, rel=1e-9)
    assert 0.1 < info[0] < 0.25  # a 28 mm steel cap: ~0.16 kg
    np.testing.assert_allclose(info[2], np.diag(grasp_env.model.inertia_kg_m2), rtol=1e-6)


def test_collision_pieces_follow_the_toolcap_profile():
    from don_gym.objects import load_object
    from don_gym.sim.part import axial_slabs

    model = load_object("toolcap")
    pieces = axial_slabs(model.mesh, model.symmetry_axis)
    assert len(pieces) == 2  # chamfered body, flange
    radii = [np.linalg.norm(piece[:, :2], axis=1).max() for piece in pieces]
    assert radii == pytest.approx([0.014, 0.017], abs=2e-4)
    lengths = [np.ptp(piece[:, 2]) for piece in pieces]
    assert sum(lengths) == pytest.approx(0.040, abs=2e-4)


# --------------------------------------------------------------------------- gym/SB3 API
@pytest.mark.parametrize("control", ["grasp", "ee"])
def test_gymnasium_and_sb3_check_env(control):
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make("DONToolcapPick-v0", control=control, image_size=TINY)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # advice about action ranges and 2D observations only
            check_env(env.unwrapped)
            sb3_check_env(env.unwrapped)
    finally:
        env.close()


def test_observation_keys_dtypes_and_no_true_pose_in_observation():
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=TINY, sensor="d435")
    try:
        obs, info = env.reset(seed=1)
        assert set(obs) == {
            "rgb",
            "depth",
            "camera_intrinsics",
            "camera_pose",
            "joint_positions",
            "ee_pose",
            "gripper_width",
        }
        assert obs["rgb"].shape == (24, 32, 3) and obs["rgb"].dtype == np.uint8
        assert obs["depth"].shape == (24, 32) and obs["depth"].dtype == np.float32
        assert env.observation_space.contains(obs)
        # The reported camera pose carries the episode's hand-eye calibration error; the truth is in info.
        reported = obs["camera_pose"].astype(np.float64)
        np.testing.assert_allclose(reported, info["T_world_camera"] @ info["T_camera_reportedcamera"], atol=1e-6)
        assert np.abs(reported[:3, 3] - info["T_world_camera"][:3, 3]).max() > 1e-5
        obs, reward, terminated, truncated, info = env.step(np.zeros(5, dtype=np.float32))
        assert isinstance(reward, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    finally:
        env.close()


def test_observe_images_false_skips_images_and_dense_reward():
    env = gym.make("DONToolcapPick-v0", control="ee", observe_images=False, reward_type="dense")
    try:
        obs, _ = env.reset(seed=0)
        assert "rgb" not in obs and "depth" not in obs and "camera_pose" in obs
        _, reward, _, _, info = env.step(np.zeros(5, dtype=np.float32))
        # Dense: minus (TCP-to-part + part-to-cradle distances + 0.1 x axis error); the hand is
        # ~0.35 m above the part and the part ~0.45 m from the cradle.
        assert isinstance(reward, float) and -1.5 < reward < -0.5 and info["outcome"] == "fail"
    finally:
        env.close()


def test_async_vector_env_steps():
    envs = gym.vector.AsyncVectorEnv(
        [lambda: gym.make("DONToolcapPick-v0", control="ee", image_size=TINY, sensor="ideal")] * 2
    )
    try:
        obs, _ = envs.reset(seed=[0, 1])
        assert obs["rgb"].shape == (2, 24, 32, 3)
        for _ in range(3):
            obs, rewards, terminated, truncated, _ = envs.step(envs.action_space.sample())
        assert rewards.shape == (2,) and obs["joint_positions"].shape == (2, 9)
    finally:
        envs.close()


def test_ee_mode_scripted_pick_lifts_the_part_and_truncates():
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=None, sensor="ideal", max_steps=75).unwrapped
    try:
        env.reset(options={"pose_id": 2})
        goal = env.oracle_action()
        lifted = False
        for t in range(75):
            tcp_pose = env.robot.tcp_pose()
            tcp, hand_yaw = tcp_pose[:3, 3], np.arctan2(tcp_pose[1, 0], tcp_pose[0, 0])
            # Hand x along the part's axis (either way round): the fingers close across it.
            yaw_error = (goal[3] - hand_yaw + np.pi / 2) % np.pi - np.pi / 2
            if t < 25:  # above the part, fingers across the axis, open
                target, grip = np.array([goal[0], goal[1], 0.08]), 1.0
            elif t < 38:  # down
                target, grip = goal[:3].astype(float), 1.0
            elif t < 58:  # close (the fingers move at 4 cm/s each)
                target, grip = goal[:3].astype(float), -1.0
            else:  # lift
                target, grip = np.array([goal[0], goal[1], 0.15]), -1.0
            action = np.r_[np.clip((target - tcp) / 0.05, -1, 1), np.clip(yaw_error / 0.25, -1, 1), grip]
            _, _, terminated, truncated, info = env.step(action.astype(np.float32))
            lifted = lifted or info["lifted"]
            if terminated or truncated:
                break
        assert lifted and info["outcome"] == "grasp_only"
        assert truncated and not terminated and t == 74
        assert info["T_world_object"][2, 3] > TABLE_TOP_Z_M + 0.08
    finally:
        env.close()


def test_part_leaving_the_workspace_ends_the_episode_a_fail_unless_it_was_lifted():
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=None, sensor="ideal").unwrapped
    try:
        env.reset(seed=0)
        T = np.eye(4)
        T[:3, 3] = [1.5, 0.0, -0.3]  # beside the table, below its top: fell off
        env.task.part.set_pose(T)
        _, reward, terminated, _, info = env.step(np.zeros(5, dtype=np.float32))
        # Never lifted: pushed off, the paper's "fail".
        assert terminated and info["outcome"] == "fail" and reward == 0.0
        # Lifted, then lost over the table's edge: grasped, not placed (the paper's "grasp only").
        contacts = env.robot.contacts(env.task)
        assert not any(contacts.fingers)
        judgement = env.task.judge(True, env.task.left_workspace(), contacts)
        assert judgement.outcome == "grasp_only" and not judgement.is_success
    finally:
        env.close()


# ------------------------------------------------------------------------------ cameras
def test_camera_matches_pinhole_projection_and_hides_no_robot():
    env = gym.make("DONToolcapPick-v0", image_size=(160, 120), sensor="ideal").unwrapped
    try:
        for k in (0, 7):
            _, info = env.reset(options={"pose_id": k})
            T_world_camera = info["T_world_camera"]
            rgb, depth, seg = render_camera(env.sim.client, env.intrinsics, T_world_camera, 0.05, 3.0, "tiny")
            mask = body_mask(seg, env.task.part.body_id)
            assert mask.sum() > 50  # the part is in view from the observation pose
            points = transform_points(
                invert_transform(T_world_camera) @ info["T_world_object"], env.model.mesh.vertices
            )
            uv, z = project_points(env.intrinsics, points)
            rows, cols = np.nonzero(mask)
            # The rendered silhouette lies inside the projected vertex bounds (half a pixel of slack).
            assert cols.min() >= uv[:, 0].min() - 0.5 and cols.max() <= uv[:, 0].max() + 0.5
            assert rows.min() >= uv[:, 1].min() - 0.5 and rows.max() <= uv[:, 1].max() + 0.5
            # Metric z-depth: the nearest rendered surface is the nearest vertex (within 1 mm).
            assert depth[mask].min() == pytest.approx(z.min(), abs=1e-3)
            # The wrist camera never sees the robot, so hiding it for speed changes no pixel.
            with env.robot.hidden():
                hidden = render_camera(env.sim.client, env.intrinsics, T_world_camera, 0.05, 3.0, "tiny")
            assert all(np.array_equal(a, b) for a, b in zip((rgb, depth, seg), hidden, strict=True))
    finally:
        env.close()


def test_render_rgb_array_and_egl_or_fallback():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the EGL fallback warning where there is no EGL
        env = gym.make(
            "DONToolcapPick-v0", image_size=TINY, renderer="egl", render_mode="rgb_array", render_size=(64, 48)
        )
    try:
        assert env.unwrapped.renderer in ("egl", "tiny")
        # What EGL renders with (bench_env reports it), e.g. "llvmpipe (LLVM ...)"; nothing for TinyRenderer.
        opengl_renderer = env.unwrapped.sim.opengl_renderer
        assert opengl_renderer if env.unwrapped.renderer == "egl" else opengl_renderer is None
        obs, info = env.reset(seed=0)
        assert info["renderer"] == env.unwrapped.renderer
        frame = env.render()
        assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 5
        assert obs["depth"].max() > 0.3
    finally:
        env.close()


# ------------------------------------------------------------------------ determinism
def test_same_seed_gives_identical_observations():
    env_a = gym.make("DONToolcapPick-v0", control="ee", image_size=TINY, sensor="d435")
    env_b = gym.make("DONToolcapPick-v0", control="ee", image_size=TINY, sensor="d435")
    try:
        obs_a, info_a = env_a.reset(seed=7)
        # Another episode in between must not leak into the next one (contact caches, RNG).
        env_b.reset(seed=3)
        for _ in range(3):
            env_b.step(env_b.action_space.sample())
        obs_b, info_b = env_b.reset(seed=7)
        for key in obs_a:
            assert np.array_equal(obs_a[key], obs_b[key]), key
        assert np.array_equal(info_a["T_world_object"], info_b["T_world_object"])
        action = np.array([0.3, -0.2, -0.5, 0.1, -1.0], dtype=np.float32)
        step_a, step_b = env_a.step(action)[0], env_b.step(action)[0]
        for key in step_a:
            assert np.array_equal(step_a[key], step_b[key]), key
        other, _ = env_a.reset(seed=8)
        assert not np.array_equal(other["depth"], obs_a["depth"])
    finally:
        env_a.close()
        env_b.close()


def test_fixed_poses_are_spread_and_point_eight_ways(grasp_env):
    yaws = []
    for k in range(8):
        _, info = grasp_env.reset(options={"pose_id": k})
        axis = info["T_world_object"][:3, :3] @ grasp_env.model.plus_axis
        assert abs(axis[2]) < 0.15  # lying on its side
        yaws.append(np.rad2deg(np.arctan2(axis[1], axis[0])) % 360)
    gaps = np.diff(np.sort(yaws))
    assert len(yaws) == 8 and gaps.min() > 35  # eight directions, ~45 degrees apart


# ------------------------------------------------------------------------ backgrounds
def test_random_background_is_seeded_and_leaves_what_the_seed_gives_as_plain():
    size = (48, 36)
    plain = gym.make("DONToolcapPick-v0", image_size=size)  # the default background
    random_a = gym.make("DONToolcapPick-v0", image_size=size, background="random")
    random_b = gym.make("DONToolcapPick-v0", image_size=size, background="random")
    try:
        # A random pose: the seed draws it, then the calibration error; the backdrop must not take their draws.
        obs_plain, info_plain = plain.reset(seed=7)
        obs_a, info_a = random_a.reset(seed=7)
        random_b.reset(seed=8)  # another episode first must not leak into the next one
        obs_b, info_b = random_b.reset(seed=7)
        for key in obs_a:
            assert np.array_equal(obs_a[key], obs_b[key]), key  # same seed, same pixels
        assert info_a["backdrop"] == info_b["backdrop"]
        assert info_a["backdrop"]["table_texture_family"] in BACKDROP_SETS["classic"]
        assert info_plain["background"] == "plain" and info_plain["backdrop"] is None
        # The part, the camera, the robot and the calibration error are the seed's, as with "plain".
        for key in ("T_world_object", "T_world_camera", "T_camera_reportedcamera"):
            assert np.array_equal(info_a[key], info_plain[key]), key
        for key in ("camera_pose", "joint_positions", "ee_pose", "gripper_width"):
            assert np.array_equal(obs_a[key], obs_plain[key]), key
        # The plain table is one flat colour; the backdrop covers it, and another seed draws another one.
        colours, counts = np.unique(obs_plain["rgb"].reshape(-1, 3), axis=0, return_counts=True)
        table = np.all(obs_plain["rgb"] == colours[counts.argmax()], axis=-1)
        assert table.mean() > 0.5
        assert np.any(obs_a["rgb"] != obs_plain["rgb"], axis=-1)[table].mean() > 0.9
        # At a fixed pose the part stays where it is; the table's pixels change with the seed.
        obs_7, info_7 = random_a.reset(seed=7, options={"pose_id": 2})
        obs_9, info_9 = random_a.reset(seed=9, options={"pose_id": 2})
        assert np.array_equal(info_7["T_world_object"], info_9["T_world_object"])
        assert info_7["backdrop"] == info_a["backdrop"] != info_9["backdrop"]
        plain_7 = plain.reset(seed=7, options={"pose_id": 2})[0]["rgb"]
        colours, counts = np.unique(plain_7.reshape(-1, 3), axis=0, return_counts=True)
        table = np.all(plain_7 == colours[counts.argmax()], axis=-1)
        assert np.any(obs_9["rgb"] != obs_7["rgb"], axis=-1)[table].mean() > 0.5
        # A reset without a seed continues the backdrop stream of the last seeded one.
        random_a.reset(seed=5)
        random_b.reset(seed=5)
        after_a, after_b = random_a.reset()[1]["backdrop"], random_b.reset()[1]["backdrop"]
        assert after_a == after_b != random_a.reset(seed=5)[1]["backdrop"]
    finally:
        for env in (plain, random_a, random_b):
            env.close()


def test_random_wide_background_passes_the_env_checkers_and_bad_values_are_refused():
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    for background in ("random", "random-wide"):
        env = gym.make("DONToolcapPick-v0", image_size=TINY, background=background)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # advice about action ranges and 2D observations only
                check_env(env.unwrapped)
                if background == "random":
                    sb3_check_env(env.unwrapped)
            families = {env.reset(seed=s)[1]["backdrop"]["table_texture_family"] for s in range(12)}
            assert families <= set(BACKDROP_SETS["classic" if background == "random" else "wide"])
            if background == "random-wide":
                assert families - set(BACKDROP_SETS["classic"])  # the wide families do show up
        finally:
            env.close()
    for bad in ("wood", None, ["random"]):
        with pytest.raises(DonGymError, match=r"background=.*expected one of \['plain', 'random', 'random-wide'\]"):
            gym.make("DONToolcapPick-v0", image_size=TINY, background=bad)


# -------------------------------------------------------------------------- bad input
def test_nan_action_raises_a_clear_error(grasp_env):
    grasp_env.reset(options={"pose_id": 0})
    with pytest.raises(DonGymError, match="NaN or infinity"):
        grasp_env.step(np.array([0.5, 0.0, np.nan, 0.0], dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        grasp_env.step(np.zeros(3))


def test_step_after_the_episode_ended_raises(grasp_env):
    grasp_env.reset(options={"pose_id": 0})
    grasp_env.step(np.array([0.3, 0.3, 0.1, 0.0]))  # out of range: clipped, misses
    with pytest.raises(DonGymError, match="reset"):
        grasp_env.step(np.array([0.5, 0.0, 0.02, 0.0]))


def test_bad_pose_id_and_options(grasp_env):
    with pytest.raises(DonGymError, match="pose_id"):
        grasp_env.reset(options={"pose_id": 8})


def test_unknown_object_and_unreadable_mesh_fail_at_make(tmp_path):
    with pytest.raises(MeshError, match="neither a built-in"):
        gym.make("DONPick-v0", object="teapot")
    bad = tmp_path / "broken.stl"
    bad.write_bytes(b"solid nonsense\nthis is not an stl\n")
    with pytest.raises(MeshError, match="broken.stl"):
        gym.make("DONPick-v0", object=str(bad))
    with pytest.raises(DonGymError, match="object= is required"):
        gym.make("DONPick-v0")
    with pytest.raises(DonGymError, match="control"):
        gym.make("DONToolcapPick-v0", control="joints")
    with pytest.raises(DonGymError, match="reward_type"):
        gym.make("DONToolcapPick-v0", reward_type="shaped")
    with pytest.raises(DonGymError, match="unknown depth sensor"):
        gym.make("DONToolcapPick-v0", sensor="kinect2")


def test_user_mesh_in_millimetres_with_object_scale(tmp_path, monkeypatch):
    monkeypatch.setenv("DON_GYM_CACHE", str(tmp_path / "cache"))
    part = trimesh.creation.box(extents=(50.0, 22.0, 22.0))  # a 50 mm bar, saved in millimetres
    path = tmp_path / "bar.stl"
    part.export(path)
    env = gym.make("DONPick-v0", object=str(path), object_scale=0.001, image_size=None, sensor="ideal").unwrapped
    try:
        assert env.model.extents_m.max() == pytest.approx(0.05)
        assert list((tmp_path / "cache").glob("*_vhacd_*.obj"))  # V-HACD pieces cached for next time
        _, info = env.reset(options={"pose_id": 1})
        # It lies on the table where it was put, at rest.
        assert info["T_world_object"][2, 3] == pytest.approx(TABLE_TOP_Z_M + 0.011, abs=0.002)
        _, _, _, _, info = env.step(env.oracle_action())
        assert info["lifted"]
    finally:
        env.close()


def test_close_releases_the_client():
    env = PickPlaceEnv(object="toolcap", image_size=None, sensor="ideal")
    client_id = env.sim.id
    assert p.getConnectionInfo(physicsClientId=client_id)["isConnected"] == 1
    env.close()
    assert p.getConnectionInfo(physicsClientId=client_id)["isConnected"] == 0
    env.close()  # twice is fine
