"""The Gymnasium env (:class:`PickPlaceEnv`): a Panda with a wrist RGB-D camera picks a part and
places it into a handover cradle. It joins the robot (:mod:`~don_gym.sim.robot`), the task
(:mod:`~don_gym.sim.task`), the wrist camera and its depth sensor (:mod:`~don_gym.sim.sensor`).
Registered as ``DONToolcapPick-v0``, ``DONShaftPick-v0`` and ``DONPick-v0`` by ``import don_gym``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, image_window, invert_transform, project_points, transform_points
from don_gym.objects import ObjectModel, load_object
from don_gym.sim.backdrop import BACKDROP_SETS, Backdrop
from don_gym.sim.bullet import Bullet, silence_c_stdout
from don_gym.sim.camera import check_renderer, look_at_camera_pose, render_camera, specular_map
from don_gym.sim.robot import EE_WRIST_MAX_RAD, Panda, wrap_angle
from don_gym.sim.script import GraspPlaceScript
from don_gym.sim.sensor import get_sensor, sample_calibration_error, simulate_depth
from don_gym.sim.task import (
    FIXED_POSES,
    OBSERVATION_YAW_RAD,
    REWARD_TYPES,
    TABLE_TOP_Z_M,
    WORKSPACE_M,
    Judgement,
    PickPlaceTask,
    grasp_point_object,
    observation_camera_position,
)

CONTROL_MODES = ("grasp", "ee")
#: ``background=``: the scene behind the part. "plain": the plain table and no floor, the same pixels as
#: always; the others: the dataset recorder's procedural backdrops (table top and floor) and cradle colour,
#: redrawn at every reset, from the backdrop families of :data:`~don_gym.sim.backdrop.BACKDROP_SETS` given here.
BACKGROUNDS: dict[str, str | None] = {"plain": None, "random": "classic", "random-wide": "wide"}
#: Second random stream of a reset's seed, ``default_rng([seed, BACKGROUND_STREAM])``: the backdrop's draws,
#: apart from those of the part's pose, the sensor noise and the calibration error.
BACKGROUND_STREAM = 2
#: Keys of ``reset(options=...)``.
RESET_OPTIONS = ("pose_id", "hand_start")
#: ``reset(options={"hand_start": ...})``: where an ee-mode episode starts the hand. "observe": the wrist
#: camera's observation pose (the task); the others run the scripted grasp with the true pose up to a phase,
#: the hand open 12 cm above the part, open around it, or closed on it (starts for learning, as in HER).
HAND_STARTS = {"observe": None, "above_part": "approach", "at_part": "descend", "in_hand": "close"}
TIME_STEP_S = 1.0 / 250.0
SOLVER_ITERATIONS = 150
#: ee mode: 25 Hz control, 10 physics steps of 4 ms per env step.
CONTROL_STEPS = 10
#: Wrist camera clip planes (m).
NEAR_M, FAR_M = 0.05, 3.0
#: Upper bound of the observation space's ``depth`` (m); sensor depth is clipped to it.
DEPTH_OBS_MAX_M = 10.0
#: Overview camera for render(): behind-right of the workspace, looking at it and the cradle.
OVERVIEW_EYE_M = np.array([1.15, -0.55, 0.75])
OVERVIEW_TARGET_M = np.array([0.45, 0.15, 0.02])
#: ``window_px``: where a window is centred before anything is known of the part: the workspace's centre on the table.
WINDOW_CENTRE_WORLD_M = np.array(
    [(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2, TABLE_TOP_Z_M]
)


def is_integer(value: Any) -> bool:
    """Whether ``value`` is a Python or NumPy integer (a bool is not)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_window(window_px: Any, image_size: tuple[int, int] | None) -> int | None:
    """``window_px`` checked against the wrist frame: None, or a square window no larger than the frame."""
    if window_px is None:
        return None
    if not is_integer(window_px) or window_px < 8:
        raise DonGymError(f"window_px={window_px!r}: expected None or an integer of at least 8 pixels")
    if image_size is None:
        raise DonGymError(f"window_px={window_px!r} needs wrist images (image_size not None, observe_images=True)")
    if window_px > min(image_size):
        raise DonGymError(
            f"window_px={window_px}: larger than the {image_size[0]}x{image_size[1]} frame; expected at most "
            f"{min(image_size)} pixels"
        )
    return int(window_px)


def _as_size(image_size: Any, what: str, allow_none: bool = True) -> tuple[int, int] | None:
    if image_size is None and allow_none:
        return None
    expected = "(width, height) in pixels" + (" or None" if allow_none else "")
    if isinstance(image_size, (str, bytes)) or not isinstance(image_size, (tuple, list, np.ndarray)):
        raise DonGymError(f"{what}={image_size!r}: expected {expected}")
    if len(image_size) != 2 or not all(is_integer(v) for v in image_size):
        raise DonGymError(f"{what}={image_size!r}: expected {expected}, two integers")
    width, height = (int(v) for v in image_size)
    if not (8 <= width <= 1280 and 8 <= height <= 960):
        raise DonGymError(f"{what}={image_size!r}: width and height must be 8..1280 and 8..960 pixels")
    return width, height


def _check_choice(value: Any, what: str, choices: tuple[str, ...] | list[str]) -> None:
    if not isinstance(value, str) or value not in choices:
        raise DonGymError(f"{what}={value!r} is unknown; expected one of {list(choices)}")


def check_view_arguments(
    control: Any,
    reward_type: Any,
    reward_types: tuple[str, ...],
    background: Any,
    render_mode: Any,
    observe_images: Any,
) -> None:
    """The arguments every pick env checks before anything is loaded, besides its parts and episode length."""
    _check_choice(control, "control", CONTROL_MODES)
    _check_choice(reward_type, "reward_type", reward_types)
    _check_choice(background, "background", tuple(BACKGROUNDS))
    if render_mode is not None and not (isinstance(render_mode, str) and render_mode == "rgb_array"):
        raise DonGymError(f"render_mode={render_mode!r} is unsupported; expected None or 'rgb_array'")
    if not isinstance(observe_images, (bool, np.bool_)):
        raise DonGymError(f"observe_images={observe_images!r}: expected True or False")


def _check_arguments(
    object: Any,  # noqa: A002 - the env's kwarg name
    object_scale: Any,
    control: Any,
    observe_images: Any,
    reward_type: Any,
    render_mode: Any,
    max_steps: Any,
    background: Any = "plain",
) -> None:
    """The env's arguments that are checked before anything is loaded (the sizes, sensor and renderer:
    where they are used); each DonGymError names the argument and what it expects."""
    if object is None:
        raise DonGymError("object= is required: a built-in name ('toolcap', 'shaft') or a mesh file path")
    if not isinstance(object, (str, Path)) or not str(object):
        raise DonGymError(f"object={object!r}: expected a built-in name ('toolcap', 'shaft') or a mesh file path")
    scale_ok = isinstance(object_scale, (int, float, np.integer, np.floating)) and not isinstance(object_scale, bool)
    if object_scale is not None and not (scale_ok and np.isfinite(object_scale) and object_scale > 0):
        raise DonGymError(f"object_scale={object_scale!r}: expected a positive, finite factor (mesh units to metres)")
    check_view_arguments(control, reward_type, REWARD_TYPES, background, render_mode, observe_images)
    if not is_integer(max_steps) or max_steps < 1:
        raise DonGymError(f"max_steps={max_steps!r}: expected a positive integer number of steps")


class PickPlaceEnv(gym.Env):
    """Panda pick-and-place of one part into a handover cradle, seen through a wrist RGB-D camera.

    ## Description
    The part lies on its side on the table; the robot must grasp it and place it into the cradle
    with the part's +axis along the cradle's target direction (:class:`~don_gym.sim.task.PickPlaceTask`).
    Physics: 4 ms steps, 150 solver iterations, the part's collision shape made of convex pieces
    (:mod:`~don_gym.sim.part`), mass and inertia from its density, gear-coupled fingers with friction
    1.8 and 40 N each; nothing is attached to the hand, friction holds the part. The robot is hidden
    while the wrist camera renders (it never sees it); ``render()`` shows everything.

    ## Action Space
    - ``control="grasp"`` (the paper's experiment, one step per episode): ``Box(4)``, the agent's
      belief ``[x, y, z, yaw]``: grasp point in the world (m, within 0.15 m of the workspace, up to
      0.25 m above the table) and world yaw (rad) of the part's +axis. A scripted robot program
      (:class:`~don_gym.sim.script.GraspPlaceScript`) grasps there across the axis, carries the part
      to the cradle and places it with the believed +axis along the target direction.
    - ``control="ee"`` (for RL, 25 Hz): ``Box(-1, 1, (5,))`` = (dx, dy, dz, dyaw, gripper), scaled by
      5 cm, 0.25 rad and 2 cm of finger opening per step (:meth:`~don_gym.sim.robot.Panda.apply_ee_action`);
      the hand stays top-down.

    ## Observation Space
    A flat ``Dict`` (SB3-compatible): ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W) float32 metres
    (0 = no return) from the wrist camera through the depth-sensor model; ``camera_intrinsics`` (6,)
    ``[fx, fy, cx, cy, W, H]``; ``camera_pose`` (4, 4) the *reported* ``T_world_camera`` (true pose
    times the episode's hand-eye calibration error); ``joint_positions`` (9,); ``ee_pose`` (7,) TCP
    position + quaternion (x, y, z, w); ``gripper_width`` (1,). Without images (``observe_images=False``
    or ``image_size=None``) ``rgb`` and ``depth`` are absent and nothing is rendered. The true part and
    camera poses are only in ``info``.

    ## Rewards
    ``reward_type="sparse"``: 1.0 on ``grasp_and_place``, else 0.0. ``"dense"``: minus the TCP-to-part
    distance (until lifted), the part-to-cradle distance and 0.1 x the axis error (rad), +1 on success
    (:meth:`~don_gym.sim.task.PickPlaceTask.reward`).

    ## Starting State
    The part lies settled at a uniformly random position in the workspace with a uniformly random
    yaw, or at one of 8 fixed poses with ``reset(options={"pose_id": k})``, k in 0..7. The wrist
    camera looks straight down from 0.45 m above the workspace centre, the gripper open. The sensor's
    hand-eye calibration error is drawn per episode. In ee mode ``reset(options={"hand_start": ...})``
    starts the hand elsewhere (:data:`HAND_STARTS`): the scripted grasp, run with the true pose, stops
    with the hand open 12 cm above the part (``"above_part"``), open around it (``"at_part"``) or closed
    on it (``"in_hand"``); a start for learning (:class:`~don_gym.wrappers.HandStarts`), not the task.
    :meth:`start_hand` makes the same move right after a reset at the task's start, once the camera has seen the part.
    With ``background="random"`` the table top, the floor and the cradle get a new look at every reset
    (see Arguments), drawn from the reset's seed apart from everything above, which stays as with
    ``"plain"``: the same seed gives the same part pose, sensor noise and calibration error either way.

    ## Episode End
    ``control="grasp"``: terminated after its one step. ``control="ee"``: terminated on success
    (``grasp_and_place`` with the part at rest) or when the part leaves the table; truncated after
    ``max_steps``.

    ## Arguments
    - ``object``: built-in name ("toolcap", "shaft") or a mesh file path (required for DONPick-v0).
    - ``object_scale``: factor from mesh-file units to metres (None: built-ins as they are, files
      auto-detected, see :func:`don_gym.objects.load_object`).
    - ``control``: "grasp" or "ee" (see Action Space).
    - ``image_size``: (width, height) of the wrist camera, D435 intrinsics scaled to it; None = no images.
    - ``observe_images``: False drops ``rgb``/``depth`` from the observation.
    - ``sensor``: depth-sensor preset (:mod:`~don_gym.sim.sensor`). "d435" (default): the paper's wrist
      camera, whose missing depth on the steel part makes self-supervised DON training hard; "ideal":
      exact depth and no calibration error.
    - ``renderer``: "tiny" (TinyRenderer, default, identical pixels on every machine), "egl" (falls
      back to "tiny" with a warning) or "pbr" (path-traced with Mitsuba 3: steel that looks like steel, far
      slower; the ``pbr`` extra; docs/background.md, "Physically based rendering"). Depth and segmentation
      are the same with every renderer.
    - ``reward_type``: "sparse" or "dense" (see Rewards).
    - ``background`` (:data:`BACKGROUNDS`): "plain" (default): the plain wooden-brown table and green cradle, pixel
      for pixel the scene the shipped networks' benchmarks were measured on. "random": what ``build-dataset`` records by
      default (the classic backdrop families, :data:`~don_gym.sim.backdrop.BACKDROP_SETS`: two-colour noise,
      stripes or checks in random colours) on the table top and on a floor under the table, and a random
      cradle colour, redrawn at every reset from ``default_rng([seed, BACKGROUND_STREAM])`` (a ``reset``
      without a seed continues that stream): the same seed gives the same pixels. "random-wide": the same
      with the nine "wide" families (plain colours, gradients, many-colour noise, dots, rectangles, grain too).
      Pixels only: the backdrop quads have no collision shape.
    - ``render_mode``: None or "rgb_array" (a fixed overview camera); ``render_size``: its (width, height).
    - ``max_steps``: ee-mode truncation.
    - ``window_px``: None (default), the whole wrist frame; an integer, a ``window_px`` x ``window_px`` window of
      it rendered at the frame's own intrinsics (principal point shifted,
      :meth:`~don_gym.geometry.CameraIntrinsics.window`), so a network trained on full frames sees the part at the
      same scale at a fraction of the cost. The window is centred on :attr:`window_centre_world`
      (:meth:`set_window_centre`; the workspace's centre after each reset), and ``camera_intrinsics`` are the
      window's; :meth:`full_frame_images` renders the whole frame on demand.
      :class:`~don_gym.wrappers.KeypointObservation` places it from the keypoints it tracks.

    ## Info
    ``T_world_object``, ``T_world_camera`` (true), ``T_camera_reportedcamera`` (calibration error),
    ``outcome`` (one of :data:`~don_gym.sim.task.OUTCOMES`), ``is_success``, ``pose_id``, ``sensor``,
    ``renderer`` (the one that ran), ``background`` (the argument), ``backdrop`` (None with "plain", else what
    the reset drew: each surface's texture family and mean RGB, ``cradle_rgba``), after a reset ``hand_start``;
    after a step also ``lifted``, ``placement_distance_m``, ``placement_axis_error_rad``, and in grasp mode
    ``sim_time_s``, ``grasp_width_m``, ``release_width_m`` (None for a phase the script did not reach).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}
    #: Side of the wrist images' window in pixels (None: the whole frame); subclasses without it see whole frames.
    window_px: int | None = None
    window_centre_world: np.ndarray = WINDOW_CENTRE_WORLD_M

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
        background: str = "plain",
        window_px: int | None = None,
    ):
        super().__init__()
        _check_arguments(object, object_scale, control, observe_images, reward_type, render_mode, max_steps, background)
        image_size = self._set_camera_options(image_size, render_size, sensor, renderer)
        self.window_px = _check_window(window_px, image_size if observe_images else None)
        #: World point (m) the next wrist image's window is centred on (:meth:`set_window_centre`).
        self.window_centre_world = WINDOW_CENTRE_WORLD_M.copy()
        self.model: ObjectModel = load_object(object, scale=object_scale)
        self.control = control
        self.reward_type = reward_type
        self.render_mode = render_mode
        self.max_steps = int(max_steps)
        self.image_size = image_size if observe_images else None
        self.intrinsics = CameraIntrinsics.d435(*(self.image_size or (640, 480)))

        self._open_sim(renderer)
        self.task = PickPlaceTask(self.sim, self.model)
        self._specular = {self.task.part.body_id: self.model.material.specular}
        self.robot = Panda(self.sim)
        self.observation_arm_rad = self.robot.solve_top_down_camera(observation_camera_position(), OBSERVATION_YAW_RAD)
        self.robot.reset(self.observation_arm_rad)
        self.task.place_part(*FIXED_POSES[0])
        self._set_up_backdrop(background)
        self.sim.take_snapshot()

        self._grasp_point_object = grasp_point_object(self.model)
        self.action_space = self._make_action_space()
        self.observation_space = self._make_observation_space()
        self._T_camera_reportedcamera = np.eye(4)
        self._episode_over = True
        self._steps = 0
        self._lifted = False
        self._pose_id: int | None = None
        #: ee mode: the hand yaw commanded last step (rad).
        self._ee_yaw_rad = 0.0

    # --------------------------------------------------------------- set-up
    def _set_camera_options(
        self, image_size: Any, render_size: Any, sensor: str, renderer: str
    ) -> tuple[int, int] | None:
        """Check and keep the render size and sensor, check the renderer; the wrist image size, checked."""
        image_size = _as_size(image_size, "image_size")
        self.render_size = _as_size(render_size, "render_size", allow_none=False)
        self.sensor = get_sensor(sensor)
        check_renderer(renderer)
        return image_size

    def _open_sim(self, renderer: str) -> None:
        self.sim = Bullet(time_step_s=TIME_STEP_S, solver_iterations=SOLVER_ITERATIONS, renderer=renderer)
        self.renderer = self.sim.renderer

    def _set_up_backdrop(self, background: str) -> None:
        self.background = background
        # "plain" adds nothing to the scene: the same bodies, the same pixels as before the option existed.
        families = BACKDROP_SETS[BACKGROUNDS[background]] if BACKGROUNDS[background] else None
        self._backdrop = Backdrop(self.sim, cradle_id=self.task.cradle_id) if families else None
        self._backdrop_families = families
        self._backdrop_rng: np.random.Generator | None = None
        self._backdrop_settings: dict[str, Any] | None = None

    @property
    def sensor_name(self) -> str:
        return self.sensor.name

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
            width, height = self.image_size if self.window_px is None else (self.window_px, self.window_px)
            entries["rgb"] = spaces.Box(0, 255, shape=(height, width, 3), dtype=np.uint8)
            entries["depth"] = spaces.Box(0.0, DEPTH_OBS_MAX_M, shape=(height, width), dtype=np.float32)
        big = 1e4
        # A window's principal point may lie outside it (window_px), so cx and cy may be negative.
        low = np.array([0.0, 0.0, -big, -big, 0.0, 0.0], dtype=np.float32)
        entries["camera_intrinsics"] = spaces.Box(low, np.full(6, big, np.float32), dtype=np.float32)
        entries["camera_pose"] = spaces.Box(-10.0, 10.0, shape=(4, 4), dtype=np.float32)
        entries["joint_positions"] = spaces.Box(-4.0, 4.0, shape=(9,), dtype=np.float32)
        entries["ee_pose"] = spaces.Box(-10.0, 10.0, shape=(7,), dtype=np.float32)
        entries["gripper_width"] = spaces.Box(0.0, 0.1, shape=(1,), dtype=np.float32)
        return spaces.Dict(entries)

    # ---------------------------------------------------------- observation
    def _quiet_renderer(self):
        """The EGL plugin prints to the C stdout whenever it sets up a framebuffer; keep it quiet."""
        return silence_c_stdout() if self.renderer == "egl" else contextlib.nullcontext()

    def _camera_images(
        self, T_world_camera: np.ndarray, intrinsics: CameraIntrinsics | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        intrinsics = self.intrinsics if intrinsics is None else intrinsics
        with self.robot.hidden(), self._quiet_renderer():
            rgb, depth_ideal, segmentation = render_camera(
                self.sim.client, intrinsics, T_world_camera, NEAR_M, FAR_M, self.renderer
            )
        self._keep_segmentation(segmentation)
        specular = specular_map(segmentation, self._specular)
        depth = simulate_depth(depth_ideal, specular, intrinsics, self.sensor, self.np_random)
        return rgb, np.clip(depth, 0.0, DEPTH_OBS_MAX_M).astype(np.float32)

    def set_window_centre(self, point_world: np.ndarray | None) -> None:
        """Centre the next wrist images' window (``window_px``) on ``point_world`` (3,) metres, as seen from the
        camera's reported pose at that observation (None: :data:`WINDOW_CENTRE_WORLD_M`, the workspace's
        centre); the window stays inside the frame. Without ``window_px`` it changes nothing."""
        if point_world is None:
            self.window_centre_world = WINDOW_CENTRE_WORLD_M.copy()
            return
        point = np.asarray(point_world, dtype=np.float64).reshape(-1)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise DonGymError(f"point_world={point_world!r}: expected 3 finite world coordinates in metres")
        self.window_centre_world = point

    def image_window(self, T_world_reportedcamera: np.ndarray) -> CameraIntrinsics:
        """The intrinsics of the next wrist images: the full frame's, or with ``window_px`` the window around
        :attr:`window_centre_world` seen from ``T_world_reportedcamera`` (a point behind the camera: the frame's
        centre)."""
        if self.window_px is None:
            return self.intrinsics
        point_camera = transform_points(invert_transform(T_world_reportedcamera), self.window_centre_world)
        uv, _ = project_points(self.intrinsics, point_camera)
        return image_window(self.intrinsics, uv[0], self.window_px)

    def full_frame_images(self) -> tuple[np.ndarray, np.ndarray, CameraIntrinsics]:
        """Wrist ``rgb`` (H, W, 3) uint8 and sensor ``depth`` (H, W) metres of the whole frame now, whatever
        ``window_px`` is, and its intrinsics: where a windowed observer first looks for the part. Draws sensor noise
        from the env's generator like any observation; steps nothing."""
        if self.image_size is None:
            raise DonGymError("full_frame_images needs an env with images (image_size not None, observe_images)")
        rgb, depth = self._camera_images(self.robot.camera_pose())
        return rgb, depth, self.intrinsics

    def _keep_segmentation(self, segmentation: np.ndarray) -> None:
        """What the env keeps of the last wrist image's PyBullet segmentation: nothing here."""

    def _restore_snapshot(self) -> None:
        """Back to the state after construction, the arm observing."""
        self.robot.reset(self.observation_arm_rad)
        self.task.forget_contacts()
        self.sim.restore_snapshot()
        self.robot.reset(self.observation_arm_rad)

    def _observation(self) -> dict[str, np.ndarray]:
        T_world_camera = self.robot.camera_pose()
        intrinsics = self.image_window(T_world_camera @ self._T_camera_reportedcamera)
        obs: dict[str, np.ndarray] = {}
        if self.image_size is not None:
            obs["rgb"], obs["depth"] = self._camera_images(T_world_camera, intrinsics)
        obs["camera_intrinsics"] = intrinsics.as_array().astype(np.float32)
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
            "background": self.background,
            "backdrop": None if self._backdrop_settings is None else dict(self._backdrop_settings),
        }

    # ----------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None and (not is_integer(seed) or seed < 0):
            raise DonGymError(f"seed={seed!r}: expected a non-negative integer or None")
        if options is not None and not isinstance(options, Mapping):
            raise DonGymError(f"options={options!r}: expected a dict such as {{'pose_id': 3}} or None")
        options = options or {}
        unknown = sorted(str(k) for k in options if k not in RESET_OPTIONS)
        if unknown:
            raise DonGymError(f"options {unknown}: unknown; reset() takes {list(RESET_OPTIONS)}")
        pose_id = options.get("pose_id")
        if pose_id is not None and (not is_integer(pose_id) or not 0 <= pose_id < len(FIXED_POSES)):
            raise DonGymError(f"options['pose_id']={pose_id!r}: expected an integer 0..{len(FIXED_POSES) - 1}")
        hand_start = options.get("hand_start", "observe")
        self._check_hand_start(hand_start, "options['hand_start']")
        super().reset(seed=None if seed is None else int(seed))  # only once everything is checked
        if pose_id is not None:
            x, y, yaw = FIXED_POSES[int(pose_id)]
            self._pose_id = int(pose_id)
        else:
            x, y, yaw = self.task.sample_pose(self.np_random)
            self._pose_id = None
        self._restore_snapshot()
        self.task.place_part(x, y, yaw)
        self.task.settle()
        self._T_camera_reportedcamera = sample_calibration_error(self.sensor, self.np_random)
        self._episode_over = False
        self._steps = 0
        self._lifted = False
        self._ee_yaw_rad = float(OBSERVATION_YAW_RAD)
        self.window_centre_world = WINDOW_CENTRE_WORLD_M.copy()
        self._randomise_backdrop(seed)
        self._move_hand_to_start(hand_start)
        info = self._info() | {"outcome": "fail", "is_success": False, "hand_start": hand_start}
        return self._observation(), info

    def _move_hand_to_start(self, hand_start: str) -> None:
        if HAND_STARTS[hand_start] is not None:
            action = self.oracle_action()
            script = GraspPlaceScript(self.sim, self.robot, self.task)
            yaw = script.grasp_start(action[:3], float(action[3]), HAND_STARTS[hand_start], EE_WRIST_MAX_RAD)
            self._ee_yaw_rad = yaw

    def _check_hand_start(self, hand_start: Any, name: str, always_ee: bool = False) -> None:
        """A one-line DonGymError naming ``name`` unless ``hand_start`` is one of :data:`HAND_STARTS` this env can
        take: any but "observe" (with ``always_ee``, any) needs ee mode."""
        if not isinstance(hand_start, str) or hand_start not in HAND_STARTS:
            raise DonGymError(f"{name}={hand_start!r}: expected one of {list(HAND_STARTS)}")
        if (always_ee or hand_start != "observe") and self.control != "ee":
            raise DonGymError(f"{name}={hand_start!r} needs control='ee' (grasp mode starts observing)")

    def start_hand(self, hand_start: str) -> None:
        """Move the hand from the observation pose to ``hand_start`` (one of :data:`HAND_STARTS`) as
        ``reset(options={"hand_start": ...})`` does, but after a reset at the task's start: the wrist camera has
        then seen the part once from above, as on the way down of a real grasp
        (:class:`~don_gym.wrappers.HandStarts` with ``look_first``). Only in ee mode, before the episode's first
        step; uses the true pose, like the reset option."""
        self._check_hand_start(hand_start, "hand_start", always_ee=True)
        if self._episode_over or self._steps != 0:
            raise DonGymError("start_hand() moves the hand of an episode just reset: call reset() first")
        self._move_hand_to_start(hand_start)

    def _randomise_backdrop(self, seed: int | None) -> None:
        """New backdrop and cradle colour for the episode; a stream of its own, so that the part's pose, the
        sensor noise and the calibration error (``self.np_random``) are those of ``background="plain"``."""
        if self._backdrop is None:
            return
        if seed is not None:
            self._backdrop_rng = np.random.default_rng([int(seed), BACKGROUND_STREAM])
        elif self._backdrop_rng is None:
            self._backdrop_rng = np.random.default_rng()  # never seeded: as unseeded as the part's pose
        drawn = self._backdrop.randomise(self._backdrop_rng, self._backdrop_families)
        self._backdrop_settings = {k: v if isinstance(v, str) else np.asarray(v).tolist() for k, v in drawn.items()}

    # ------------------------------------------------------------------ step
    def step(self, action):
        if self._episode_over:
            raise DonGymError("step() after the episode ended (or before reset()); call reset() first")
        try:
            action = np.asarray(action, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise DonGymError(
                f"action {action!r}: expected {self.action_space.shape[0]} numbers (see the action space)"
            ) from None
        if action.shape != self.action_space.shape:
            raise DonGymError(f"action has shape {action.shape}, expected {self.action_space.shape}")
        if not np.all(np.isfinite(action)):
            raise DonGymError(f"action {action.tolist()} contains NaN or infinity; expected finite numbers")
        action = np.clip(action, self.action_space.low, self.action_space.high)
        if self.control == "grasp":
            return self._step_grasp(action)
        return self._step_ee(action)

    def _reward(self, judgement: Judgement) -> float:
        return self.task.reward(judgement, self.reward_type, self.robot.tcp_pose()[:3, 3])

    def _step_grasp(self, action: np.ndarray):
        script = GraspPlaceScript(self.sim, self.robot, self.task)
        trace = script.run(action[:3], float(action[3]))
        self._lifted = trace.lifted
        judgement = self.task.judge(trace.lifted, trace.left_workspace, self.robot.contacts(self.task))
        self._episode_over = True
        info = self._info() | judgement.info()
        # None (not NaN, which never equals itself) for a phase the script did not reach.
        info |= {
            "sim_time_s": trace.sim_time_s,
            "grasp_width_m": None if np.isnan(trace.grasp_width_m) else trace.grasp_width_m,
            "release_width_m": None if np.isnan(trace.release_width_m) else trace.release_width_m,
        }
        return self._observation(), self._reward(judgement), True, False, info

    def _step_ee(self, action: np.ndarray):
        self._ee_yaw_rad = self.robot.apply_ee_action(action, self._ee_yaw_rad)
        self.sim.step(CONTROL_STEPS)
        self._steps += 1

        contacts = self.robot.contacts(self.task)
        self._lifted = self._lifted or self.task.is_held(contacts)
        left = self.task.left_workspace()
        # Success ends the episode, so it needs the part to be at rest, not merely passing through the cradle.
        judgement = self.task.judge(self._lifted, left, contacts, require_rest=True)
        terminated = judgement.is_success or left
        truncated = (not terminated) and self._steps >= self.max_steps
        self._episode_over = terminated or truncated
        return (
            self._observation(),
            self._reward(judgement),
            bool(terminated),
            bool(truncated),
            self._info() | judgement.info(),
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
                look_at_camera_pose(OVERVIEW_EYE_M, OVERVIEW_TARGET_M),
                0.05,
                5.0,
                self.renderer,
            )
        return rgb

    def close(self) -> None:
        if getattr(self, "sim", None) is not None:
            self.sim.close()
            self.sim = None
        if getattr(self, "_backdrop", None) is not None:
            self._backdrop.close()
            self._backdrop = None
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
