"""Gymnasium env: a Panda with a wrist RGB-D camera picks a part and places it into a cradle.

Registered ids (``import don_gym``): ``DONToolcapPick-v0`` (object="toolcap"),
``DONShaftPick-v0`` (object="shaft") and ``DONPick-v0`` (``object=`` a built-in name or a
mesh path, ``object_scale=`` its unit factor).

Two control modes:

- ``control="grasp"`` (the paper's experiment): one step per episode. The action is the
  agent's belief ``[x, y, z, yaw]``: grasp point in the world (m) and world yaw (rad) of the
  part's +axis. A scripted robot program (:mod:`don_gym.sim.script`) grasps there across the
  axis, carries the part to the handover cradle and places it with the believed +axis along
  the cradle's target direction. The observation at reset comes from a fixed observation
  pose of the wrist camera 0.45 m above the workspace.
- ``control="ee"`` (for RL): 25 Hz Cartesian control, action in [-1, 1]^5 =
  (dx, dy, dz, dyaw, gripper) scaled by 5 cm, 5 cm, 5 cm, 0.25 rad and 2 cm of finger
  opening per step; the hand stays top-down. Episodes are truncated after ``max_steps``.

Observation (a flat Dict, SB3-compatible): ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W)
float32 metres (0 = no return) from the wrist camera through the depth-sensor model,
``camera_intrinsics`` (6,) ``[fx, fy, cx, cy, W, H]``, ``camera_pose`` (4, 4) the *reported*
``T_world_camera`` (true pose times the episode's hand-eye calibration error), and the robot
state ``joint_positions`` (9,), ``ee_pose`` (7,) TCP position + quaternion (x, y, z, w) and
``gripper_width`` (1,). ``observe_images=False`` (or ``image_size=None``) drops ``rgb`` and
``depth`` and skips rendering. The true part pose and camera pose are only in ``info``.

``info``: ``T_world_object``, ``T_world_camera`` (true), ``T_camera_reportedcamera``
(calibration error), ``outcome`` in ("fail", "grasp_only", "grasp_and_place"),
``is_success``, ``pose_id``, ``sensor``, ``renderer``, and after a step ``lifted``,
``placement_distance_m``, ``placement_axis_error_rad``.

Physics: 4 ms steps (1/250 s), up to 150 solver iterations, the part's collision shape made of
convex pieces (:mod:`don_gym.sim.part`), mass and inertia from its density, gear-coupled fingers
with friction 1.8 and 40 N each; nothing is attached to the hand, friction holds the part.

Renderer: "tiny" (TinyRenderer) by default, for pixels identical on every machine; "egl" on
request (falls back to "tiny" with a warning); ``info["renderer"]`` says which one ran. The
wrist camera never sees the robot, so the robot is hidden while it renders (4x faster with
TinyRenderer); ``render()`` (overview camera) shows everything.

Default sensor "d435": the paper's wrist camera was a RealSense D435, and its missing depth on
the steel part is what makes self-supervised DON training hard; ``sensor="ideal"`` gives exact
depth (and no calibration error) for debugging.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, make_transform
from don_gym.objects import ObjectModel, load_object
from don_gym.sim.bullet import Bullet, silence_c_stdout
from don_gym.sim.camera import check_renderer, render_camera, specular_map
from don_gym.sim.robot import (
    T_HAND_CAMERA,
    TCP_OFFSET_M,
    Panda,
    top_down_quaternion,
    wrap_angle,
    wrist_angle_estimate,
)
from don_gym.sim.script import MIN_TCP_HEIGHT_M, GraspPlaceScript
from don_gym.sim.task import (
    FIXED_POSES,
    TABLE_TOP_Z_M,
    WORKSPACE_M,
    PartContacts,
    PickPlaceTask,
    Placement,
    grasp_point_object,
)

try:  # the sensor model lives in its own module; without it only the ideal sensor exists
    from don_gym.sim import sensor as _sensor
except ImportError:  # pragma: no cover - only while the module is missing
    _sensor = None

CONTROL_MODES = ("grasp", "ee")
REWARD_TYPES = ("sparse", "dense")
TIME_STEP_S = 1.0 / 250.0
SOLVER_ITERATIONS = 150
#: ee mode: 25 Hz control, 10 physics steps of 4 ms per env step.
CONTROL_STEPS = 10
EE_STEP_M = 0.05
EE_YAW_STEP_RAD = 0.25
EE_GRIPPER_STEP_M = 0.02
#: ee mode: the TCP target is kept in this box (x0, x1, y0, y1, z0, z1), metres; its floor keeps
#: the fingertips 3 mm above the table.
EE_BOUNDS_M = (0.20, 0.80, -0.35, 0.60, TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M, TABLE_TOP_Z_M + 0.45)
#: ee mode: joint 7 stays this far inside its +-2.97 rad range.
EE_WRIST_MAX_RAD = 2.85
#: Wrist camera clip planes (m) and the largest depth an observation can hold.
NEAR_M, FAR_M = 0.05, 3.0
MAX_DEPTH_M = 10.0
#: Observation pose: wrist camera 0.45 m above the table over the workspace centre, looking down,
#: image x along world +y (the long side of the image across the long side of the workspace).
OBSERVATION_CAMERA_HEIGHT_M = 0.45
OBSERVATION_YAW_RAD = 0.0
#: Overview camera for render(): behind-right of the workspace, looking at it and the cradle.
OVERVIEW_EYE_M = np.array([1.15, -0.55, 0.75])
OVERVIEW_TARGET_M = np.array([0.45, 0.15, 0.02])


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV ``T_world_camera`` at ``eye`` looking at ``target``, image up towards world +z."""
    up = np.array([0.0, 0.0, 1.0])
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def _as_size(image_size: Any, what: str) -> tuple[int, int] | None:
    if image_size is None:
        return None
    try:
        width, height = (int(v) for v in image_size)
    except (TypeError, ValueError) as exc:
        raise DonGymError(f"{what}={image_size!r}: expected (width, height) in pixels or None") from exc
    if not (8 <= width <= 1280 and 8 <= height <= 960):
        raise DonGymError(f"{what}={image_size!r}: width and height must be 8..1280 and 8..960 pixels")
    return width, height


class PickPlaceEnv(gym.Env):
    """Panda pick-and-place of one part into a handover cradle (see the module docstring).

    Args:
        object: built-in name ("toolcap", "shaft") or a mesh file path (required for DONPick-v0).
        object_scale: factor from mesh-file units to metres (None: built-ins as they are, files
            auto-detected, see :func:`don_gym.objects.load_object`).
        control: "grasp" (one scripted grasp-and-place per episode) or "ee" (25 Hz Cartesian).
        image_size: (width, height) of the wrist camera, D435 intrinsics scaled to it; None = no images.
        observe_images: False drops ``rgb``/``depth`` from the observation (no rendering at all).
        sensor: depth-sensor preset ("d435" default: the paper's wrist camera, including missing
            depth on the steel part that makes self-supervised DONs struggle; "ideal" for exact depth).
        renderer: "tiny" (TinyRenderer, default, identical pixels everywhere) or "egl".
        reward_type: "sparse" (1.0 on grasp_and_place, else 0.0) or "dense".
        render_mode: None or "rgb_array" (the fixed overview camera).
        render_size: (width, height) of ``render()``.
        max_steps: ee mode truncation (grasp mode episodes are one step).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        object: str | Path | None = None,  # noqa: A002 - the public kwarg name of gym.make
        object_scale: float | None = None,
        control: str = "grasp",
        image_size: tuple[int, int] | None = (160, 120),
        observe_images: bool = True,
        sensor: str = "d435",
        renderer: str = "tiny",
        reward_type: str = "sparse",
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        max_steps: int = 100,
    ):
        super().__init__()
        if object is None:
            raise DonGymError("object= is required: a built-in name ('toolcap', 'shaft') or a mesh file path")
        if control not in CONTROL_MODES:
            raise DonGymError(f"control={control!r} is unknown; expected one of {list(CONTROL_MODES)}")
        if reward_type not in REWARD_TYPES:
            raise DonGymError(f"reward_type={reward_type!r} is unknown; expected one of {list(REWARD_TYPES)}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise DonGymError(f"render_mode={render_mode!r} is unsupported; expected None or 'rgb_array'")
        if int(max_steps) < 1:
            raise DonGymError(f"max_steps={max_steps!r}: expected a positive number of steps")
        check_renderer(renderer)
        self.model: ObjectModel = load_object(object, scale=object_scale)
        self.control = control
        self.reward_type = reward_type
        self.render_mode = render_mode
        self.max_steps = int(max_steps)
        self.image_size = _as_size(image_size, "image_size") if observe_images else None
        self.render_size = _as_size(render_size, "render_size")
        self.sensor = self._resolve_sensor(sensor)
        self.intrinsics = CameraIntrinsics.d435(*(self.image_size or (640, 480)))

        self.sim = Bullet(time_step_s=TIME_STEP_S, solver_iterations=SOLVER_ITERATIONS, renderer=renderer)
        self.renderer = self.sim.renderer
        self.task = PickPlaceTask(self.sim, self.model)
        self.robot = Panda(self.sim)
        self.observation_arm_rad = self._solve_observation_pose()
        self.robot.reset(self.observation_arm_rad)
        self.task.place_part(*FIXED_POSES[0])
        self.sim.take_snapshot()

        self._grasp_point_object = grasp_point_object(self.model)
        self.action_space = self._make_action_space()
        self.observation_space = self._make_observation_space()
        self._T_camera_reportedcamera = np.eye(4)
        self._episode_over = True
        self._steps = 0
        self._lifted = False
        self._pose_id: int | None = None
        self._ee_yaw = 0.0

    # --------------------------------------------------------------- set-up
    @staticmethod
    def _resolve_sensor(sensor: Any):
        if _sensor is None:
            if sensor != "ideal":
                warnings.warn(
                    f"sensor={sensor!r} requested but don_gym.sim.sensor is unavailable; using ideal depth",
                    stacklevel=3,
                )
            return None
        return _sensor.get_sensor(sensor)

    @property
    def sensor_name(self) -> str:
        return "ideal" if self.sensor is None else self.sensor.name

    def _solve_observation_pose(self) -> np.ndarray:
        """Arm angles that put the wrist camera OBSERVATION_CAMERA_HEIGHT_M above the workspace centre."""
        centre = np.array([(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2])
        yaw = OBSERVATION_YAW_RAD
        R_world_hand = Rotation.from_quat(top_down_quaternion(yaw)).as_matrix()
        camera_offset_world = R_world_hand @ T_HAND_CAMERA[:3, 3]
        tcp_offset_world = R_world_hand @ np.array([0.0, 0.0, TCP_OFFSET_M])
        camera = np.array([centre[0], centre[1], TABLE_TOP_Z_M + OBSERVATION_CAMERA_HEIGHT_M])
        tcp = camera - camera_offset_world + tcp_offset_world
        wrist = wrist_angle_estimate(tcp, yaw)
        arm = self.robot.inverse_kinematics(tcp, yaw, wrist_rad=wrist)
        for _ in range(4):  # IK from the solution again: converge to sub-millimetre
            self.robot.reset(arm)
            arm = self.robot.inverse_kinematics(tcp, yaw, wrist_rad=wrist)
        return arm

    def _make_action_space(self) -> spaces.Box:
        if self.control == "grasp":
            x0, x1, y0, y1 = WORKSPACE_M
            margin = 0.15
            low = np.array([x0 - margin, y0 - margin, TABLE_TOP_Z_M, -np.pi], dtype=np.float32)
            high = np.array([x1 + margin, y1 + margin, TABLE_TOP_Z_M + 0.25, np.pi], dtype=np.float32)
            return spaces.Box(low, high, dtype=np.float32)
        return spaces.Box(-1.0, 1.0, shape=(5,), dtype=np.float32)

    def _make_observation_space(self) -> spaces.Dict:
        entries: dict[str, spaces.Space] = {}
        if self.image_size is not None:
            width, height = self.image_size
            entries["rgb"] = spaces.Box(0, 255, shape=(height, width, 3), dtype=np.uint8)
            entries["depth"] = spaces.Box(0.0, MAX_DEPTH_M, shape=(height, width), dtype=np.float32)
        big = 1e4
        entries["camera_intrinsics"] = spaces.Box(0.0, big, shape=(6,), dtype=np.float32)
        entries["camera_pose"] = spaces.Box(-10.0, 10.0, shape=(4, 4), dtype=np.float32)
        entries["joint_positions"] = spaces.Box(-4.0, 4.0, shape=(9,), dtype=np.float32)
        entries["ee_pose"] = spaces.Box(-10.0, 10.0, shape=(7,), dtype=np.float32)
        entries["gripper_width"] = spaces.Box(0.0, 0.1, shape=(1,), dtype=np.float32)
        return spaces.Dict(entries)

    # ---------------------------------------------------------- observation
    def _quiet_renderer(self):
        """The EGL plugin prints to the C stdout whenever it sets up a framebuffer; keep it quiet."""
        return silence_c_stdout() if self.renderer == "egl" else contextlib.nullcontext()

    def _camera_images(self, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with self.robot.hidden(), self._quiet_renderer():
            rgb, depth_ideal, segmentation = render_camera(
                self.sim.client, self.intrinsics, T_world_camera, NEAR_M, FAR_M, self.renderer
            )
        if self.sensor is None:
            return rgb, depth_ideal
        specular = specular_map(segmentation, {self.task.part.body_id: self.model.material.specular})
        depth = _sensor.simulate_depth(depth_ideal, specular, self.intrinsics, self.sensor, self.np_random)
        return rgb, np.clip(depth, 0.0, MAX_DEPTH_M).astype(np.float32)

    def _observation(self) -> dict[str, np.ndarray]:
        T_world_camera = self.robot.camera_pose()
        obs: dict[str, np.ndarray] = {}
        if self.image_size is not None:
            obs["rgb"], obs["depth"] = self._camera_images(T_world_camera)
        obs["camera_intrinsics"] = self.intrinsics.as_array().astype(np.float32)
        obs["camera_pose"] = (T_world_camera @ self._T_camera_reportedcamera).astype(np.float32)
        obs["joint_positions"] = self.robot.joint_positions().astype(np.float32)
        position, quaternion = self.robot.tcp_position_quaternion()
        obs["ee_pose"] = np.concatenate([position, quaternion]).astype(np.float32)
        obs["gripper_width"] = np.array([self.robot.gripper_width()], dtype=np.float32)
        return obs

    def _info(self) -> dict[str, Any]:
        # The true poses are for evaluation and oracles only, never part of the observation.
        return {
            "T_world_object": self.task.part.T_world_object,
            "T_world_camera": self.robot.camera_pose(),
            "T_camera_reportedcamera": self._T_camera_reportedcamera.copy(),
            "pose_id": self._pose_id,
            "sensor": self.sensor_name,
            "renderer": self.renderer,
        }

    # ----------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        pose_id = options.get("pose_id")
        if pose_id is not None:
            if isinstance(pose_id, bool) or not isinstance(pose_id, (int, np.integer)) or not 0 <= pose_id < 8:
                raise DonGymError(f"options['pose_id']={pose_id!r}: expected an integer 0..7")
            x, y, yaw = FIXED_POSES[int(pose_id)]
            self._pose_id = int(pose_id)
        else:
            x, y, yaw = self.task.sample_pose(self.np_random)
            self._pose_id = None
        # Contact manifolds survive restoreState and warm-start the solver: a part put back where
        # it lay last episode would then move differently. Parking the part and the robot away
        # from everything and running collision detection deletes them.
        self.task.part.set_pose(make_transform(translation=[0.0, 0.0, 50.0]))
        self.robot.reset(self.observation_arm_rad)
        self.sim.client.performCollisionDetection()
        self.sim.restore_snapshot()
        self.robot.reset(self.observation_arm_rad)
        self.task.place_part(x, y, yaw)
        self.task.settle()
        if self.sensor is not None:
            self._T_camera_reportedcamera = _sensor.sample_calibration_error(self.sensor, self.np_random)
        self._episode_over = False
        self._steps = 0
        self._lifted = False
        self._ee_yaw = float(OBSERVATION_YAW_RAD)
        return self._observation(), self._info() | {"outcome": "fail", "is_success": False}

    # ------------------------------------------------------------------ step
    def step(self, action):
        if self._episode_over:
            raise DonGymError("step() after the episode ended (or before reset()); call reset() first")
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape != self.action_space.shape:
            raise DonGymError(f"action has shape {action.shape}, expected {self.action_space.shape}")
        if not np.all(np.isfinite(action)):
            raise DonGymError(f"action {action.tolist()} contains NaN or infinity; expected finite numbers")
        action = np.clip(action, self.action_space.low, self.action_space.high)
        if self.control == "grasp":
            return self._step_grasp(action)
        return self._step_ee(action)

    def _outcome(self, lifted: bool, left: bool, contacts: PartContacts) -> tuple[str, Placement]:
        placement = self.task.placement(contacts)
        if left or not lifted:
            return "fail", placement
        if placement.correct and not any(contacts.fingers):
            return "grasp_and_place", placement
        return "grasp_only", placement

    def _reward(self, outcome: str, placement) -> float:
        if self.reward_type == "sparse":
            return float(outcome == "grasp_and_place")
        # Dense: distance of the TCP to the part (until lifted), of the part to the cradle, and
        # the axis error in radians scaled to "1 rad ~ 10 cm"; +1 on success.
        com = self.task.part.center_of_mass_world
        reach = 0.0 if self._lifted else float(np.linalg.norm(self.robot.tcp_pose()[:3, 3] - com))
        place = float(np.linalg.norm(com - self.task.cradle_rest_center()))
        return float(-(reach + place + 0.1 * placement.axis_error_rad) + (outcome == "grasp_and_place"))

    def _step_info(self, outcome: str, placement) -> dict[str, Any]:
        return self._info() | {
            "outcome": outcome,
            "is_success": outcome == "grasp_and_place",
            "lifted": self._lifted,
            "placement_distance_m": placement.distance_xy_m,
            "placement_axis_error_rad": placement.axis_error_rad,
        }

    def _step_grasp(self, action: np.ndarray):
        script = GraspPlaceScript(self.sim, self.robot, self.task)
        trace = script.run(action[:3], float(action[3]))
        self._lifted = trace.lifted
        outcome, placement = self._outcome(trace.lifted, trace.left_workspace, self.robot.contacts(self.task))
        self._episode_over = True
        info = self._step_info(outcome, placement)
        # None (not NaN, which never equals itself) for a phase the script did not reach.
        info |= {
            "sim_time_s": trace.sim_time_s,
            "grasp_width_m": None if np.isnan(trace.grasp_width_m) else trace.grasp_width_m,
            "release_width_m": None if np.isnan(trace.release_width_m) else trace.release_width_m,
        }
        return self._observation(), self._reward(outcome, placement), True, False, info

    def _step_ee(self, action: np.ndarray):
        robot = self.robot
        tcp, _ = robot.tcp_position_quaternion()
        x0, x1, y0, y1, z0, z1 = EE_BOUNDS_M
        target = np.clip(tcp + EE_STEP_M * action[:3], [x0, y0, z0], [x1, y1, z1])
        # Hand yaw as joint 7 sees it (see robot.wrist_angle_estimate), kept inside its range.
        q1 = float(np.arctan2(target[1] - robot.base_position[1], target[0] - robot.base_position[0]))
        wanted_yaw = self._ee_yaw + EE_YAW_STEP_RAD * action[3]
        wrist = float(np.clip(q1 - wanted_yaw + np.pi / 4, -EE_WRIST_MAX_RAD, EE_WRIST_MAX_RAD))
        self._ee_yaw = q1 + np.pi / 4 - wrist
        # 20 IK iterations (~2 mm left of a 5 cm move): the next step re-solves from the measured pose.
        robot.command_arm(robot.inverse_kinematics(target, self._ee_yaw, wrist_rad=wrist, iterations=20))
        robot.command_gripper(robot.width_target_m + EE_GRIPPER_STEP_M * action[4])
        self.sim.step(CONTROL_STEPS)
        self._steps += 1

        contacts = robot.contacts(self.task)
        self._lifted = self._lifted or self.task.is_held(contacts)
        left = self.task.left_workspace()
        outcome, placement = self._outcome(self._lifted, left, contacts)
        success = outcome == "grasp_and_place" and self.task.is_at_rest()
        if outcome == "grasp_and_place" and not success:
            outcome = "grasp_only"
        terminated = success or left
        truncated = (not terminated) and self._steps >= self.max_steps
        self._episode_over = terminated or truncated
        return (
            self._observation(),
            self._reward(outcome, placement),
            bool(terminated),
            bool(truncated),
            self._step_info(outcome, placement),
        )

    # ------------------------------------------------------------- render
    def render(self):
        if self.render_mode != "rgb_array":
            return None
        width, height = self.render_size
        with self._quiet_renderer():
            rgb, _, _ = render_camera(
                self.sim.client,
                CameraIntrinsics.d435(width, height),
                _look_at(OVERVIEW_EYE_M, OVERVIEW_TARGET_M),
                0.05,
                5.0,
                self.renderer,
            )
        return rgb

    def close(self) -> None:
        if getattr(self, "sim", None) is not None:
            self.sim.close()
            self.sim = None
        super().close()

    # ------------------------------------------------------ for oracles
    def oracle_action(self, flip: bool = False) -> np.ndarray:
        """The grasp-mode action of a perfect perception: the part's grasp point
        (:func:`~don_gym.sim.task.grasp_point_object`) in the world and the true +axis yaw
        (``flip``: plus pi, the "upside down" mistake). Uses the true pose: tests and baselines only."""
        T = self.task.part.T_world_object
        point = T[:3, :3] @ self._grasp_point_object + T[:3, 3]
        axis = T[:3, :3] @ self.model.plus_axis
        yaw = float(np.arctan2(axis[1], axis[0])) + (np.pi if flip else 0.0)
        return np.array([point[0], point[1], point[2], wrap_angle(yaw)], dtype=np.float32)
