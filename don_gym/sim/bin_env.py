"""The bin-picking Gymnasium env (:class:`BinPickEnv`): the pick env's Panda, wrist RGB-D camera and cradle,
with a bin holding a pile of several part instances (:class:`~don_gym.sim.bin_task.BinPickTask`) instead of
one part. Registered as ``DONBinPick-v0``, ``DONToolcapBinPick-v0`` and ``DONShaftBinPick-v0`` by ``import don_gym``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics
from don_gym.objects import ObjectModel, builtin_names, load_object, part_name
from don_gym.sim.bin_task import (
    DEFAULT_PARTS,
    DEFAULT_STATION_XY_M,
    DEFAULT_TARGET,
    LEDGE_OVERHANG_RADII,
    STATION_CAMERA_HEIGHT_M,
    BinPickTask,
    Instance,
    check_bin_parts,
    check_station,
    grasp_opening_m,
    lying_footprint_m,
    station_bounds,
    station_ledge,
)
from don_gym.sim.camera import decode_segmentation
from don_gym.sim.env import (
    CONTROL_STEPS,
    PickPlaceEnv,
    check_view_arguments,
    is_integer,
)
from don_gym.sim.robot import FINGER_JOINTS, Panda, wrap_angle
from don_gym.sim.script import CONTACT_ZONE_M, FREE_SPEED_M_S, STEP_KINDS, GraspPlaceScript, move_duration_s
from don_gym.sim.sensor import sample_calibration_error
from don_gym.sim.task import OBSERVATION_YAW_RAD, observation_camera_position

#: ``info["outcome"]`` of a step, worst first: nothing lifted; a target lifted but not placed in the cradle
#: as it should be; a target placed; a part that is not the target lifted; a target lifted standing and set down
#: at the regrasp station (the attempt goes on with the next step's grasp there); a push (no attempt: nothing was
#: grasped).
BIN_OUTCOMES = ("fail", "grasp_only", "grasp_and_place", "wrong_part", "set_down", "pushed")
#: ``info["phase"]``: what the next action is for: a pick from the bin, or the regrasp at the station.
PHASES = ("pick", "regrasp")
#: ``info["end_reason"]`` once an episode is over.
END_REASONS = ("cleared", "failed_attempts", "step_limit")
#: Grasp mode: default step limit per instance in the pile; ee mode: per target instance.
GRASP_STEPS_PER_INSTANCE = 2
EE_STEPS_PER_TARGET = 200


def resolve_parts(parts: Any, target: Any, part_scales: Any) -> tuple[dict[str, ObjectModel], dict[str, int], str]:
    """``(models, counts, target)`` keyed by part name (:func:`~don_gym.objects.part_name`), in the order given;
    DonGymError naming the input for anything a user can get wrong, before and after loading the meshes."""
    example = "e.g. {'toolcap': 3, 'shaft': 2}"
    if parts is None:
        parts = DEFAULT_PARTS
    if not isinstance(parts, Mapping) or not parts:
        raise DonGymError(f"parts={parts!r}: expected a dict of part (built-in name or mesh file) -> count, {example}")
    if part_scales is not None and not isinstance(part_scales, Mapping):
        raise DonGymError(
            f"part_scales={part_scales!r}: expected None or a dict of part -> scale (mesh units to metres)"
        )
    part_scales = dict(part_scales or {})
    unknown_scales = [key for key in part_scales if key not in parts]
    if unknown_scales:
        raise DonGymError(f"part_scales: {unknown_scales[0]!r} is not among the parts; expected keys of {list(parts)}")
    counts_by_key: dict[str, int] = {}
    for key, count in parts.items():
        if not isinstance(key, (str, Path)) or not str(key):
            raise DonGymError(
                f"parts: key {key!r}: expected a built-in name ({', '.join(builtin_names())}) or a mesh path"
            )
        if not is_integer(count) or count < 0:
            raise DonGymError(f"parts: count {count!r} of {str(key)!r}: expected an integer >= 0")
        key = str(key)
        if key not in builtin_names() and not Path(key).expanduser().is_file():
            raise DonGymError(
                f"parts: {key!r} is neither a built-in part ({', '.join(builtin_names())}) nor an existing mesh file"
            )
        counts_by_key[key] = int(count)
    names = {key: part_name(key) for key in counts_by_key}
    if len(set(names.values())) < len(names):
        raise DonGymError(
            f"parts={list(counts_by_key)}: two parts share the name {sorted(names.values())}; expected distinct names"
        )
    present = [key for key, count in counts_by_key.items() if count > 0]
    target_key = (
        next((key for key in present if target in (key, names[key])), None) if isinstance(target, (str, Path)) else None
    )
    if target_key is None:
        raise DonGymError(f"target={target!r} is not among the parts; expected one of {[names[k] for k in present]}")
    models = {names[key]: load_object(key, scale=part_scales.get(key)) for key in counts_by_key}
    counts = {names[key]: count for key, count in counts_by_key.items()}
    check_bin_parts(counts, models)
    return models, counts, names[target_key]


class BinPickEnv(PickPlaceEnv):
    """Panda picking part instances out of a bin, one after another, into the handover cradle, seen through a
    wrist RGB-D camera.

    ## Description
    A bin (a tray of 0.20 x 0.28 m inside with 3.5 cm walls, :mod:`~don_gym.sim.bin_task`) stands on the table
    under the observation pose; the parts of ``parts`` are dropped into it and settle into a pile. The robot
    must take out every instance of the ``target`` part, one per pick, and place each into the cradle as in
    :class:`~don_gym.sim.env.PickPlaceEnv`: lying, its +axis along the cradle's target direction. A picked
    instance is cleared (taken out of the scene) before the next step; so is any instance that left the bin
    (dropped beside it, pushed over a wall, placed in the cradle). Physics, robot, camera, sensor presets,
    renderers and backgrounds are those of the pick env.

    ## Action Space
    - ``control="grasp"`` (one pick attempt per step): ``Box(5)`` ``[x, y, z, yaw, kind]``, the grasp point in
      the world (m), the world yaw (rad) of the +axis of the part the agent means to pick, as in the pick env,
      and the grasp kind: the index (rounded) of one of :data:`~don_gym.sim.script.STEP_KINDS`, 0 "across"
      the axis, 1 "along" it (the fingers on the end faces), 2 "standing" (across a part standing on an end),
      or 3 "push": no grasp, the closed fingers come down at ``[x, y]`` and move
      :data:`~don_gym.sim.script.PUSH_DISTANCE_M` towards world yaw ``yaw``, rolling a part lying against a wall
      away from it (:meth:`~don_gym.sim.script.GraspPlaceScript.push`; ``z`` unused; outcome "pushed", not an
      attempt, but a step). A 4-number action is an "across" grasp. The scripted program
      (:class:`~don_gym.sim.script.GraspPlaceScript`) grasps there (the fingers closing across the believed
      axis, or along it) and, if something is lifted, carries it to the cradle and places it, the believed axis
      turned onto the cradle's direction and the point held offset by its axial position on the part (the grasp
      point; for "along" the middle of the end faces). The arm then returns to the observation pose.
    - ``control="ee"`` (25 Hz, for RL): ``Box(-1, 1, (5,))`` as in the pick env.

    ## Observation Space
    That of the pick env: ``rgb``, ``depth`` (metres, 0 = no return), ``camera_intrinsics``, ``camera_pose``
    (reported, with the episode's hand-eye calibration error), ``joint_positions``, ``ee_pose``,
    ``gripper_width``. True poses and segmentations are only in ``info`` and the oracle methods.

    ## Rewards
    1.0 for a step whose outcome is ``grasp_and_place`` (a target instance placed), else 0.0 (``reward_type``
    "sparse", the only one).

    ## Starting State
    ``reset(seed=...)`` drops the pile: in a random order, each instance lying on its side at a random yaw and
    roll, tilted up to 20 degrees, at a random spot inside the walls, above the instances dropped before it
    where their boxes overlap; then the pile settles under gravity (up to 3 s). A pile from which a part bounced
    out is drawn again. The same seed gives the same pile, bit for bit, and the same sensor noise and
    calibration error, and the same actions the same episode, whatever episodes the env ran before (each reset
    after the first builds the physics world anew). The wrist camera looks down from 0.45 m above the bin, the
    gripper open.

    ## Episode End
    Terminated when no target instance is left in play (``end_reason`` "cleared"), or in grasp mode after
    ``max_failed_attempts`` steps in a row whose outcome is ``fail`` (nothing lifted; "failed_attempts").
    Truncated after ``max_steps`` steps, attempts and pushes ("step_limit"). A step whose outcome is ``set_down``
    is half an attempt (the regrasp's step ends it) and never ends the episode; a push is a step, not an attempt,
    and leaves the count of failed attempts in a row as it was.

    ## Regrasp station
    A grasp of kind "standing" carries what it lifted to the station (``regrasp_station``, a free square of table
    beside the bin with a ledge, :func:`~don_gym.sim.bin_task.check_station`) instead of the cradle and sets it
    down over the ledge's edge, where it tips over and lies. If a target instance then lies on the station, the
    outcome is ``set_down``, ``info["phase"]`` becomes "regrasp", the observation is the wrist camera's view from the
    station's observation pose, and the next action is a grasp there, placed as any pick; that step's ``info``
    has ``regrasp`` True and ``regrasp_outcome``, and the instance leaves play whatever happened.

    ## Arguments
    - ``parts``: part -> instance count (default ``{"toolcap": 3, "shaft": 2}``); a part is a built-in name or
      a mesh file path, as the pick env's ``object``. The parts must cover at most half the bin's floor lying down.
    - ``target``: the part to pick (a key of ``parts`` or its part name; default "toolcap").
    - ``part_scales``: part -> factor from mesh-file units to metres (None: as the pick env's ``object_scale=None``).
    - ``control``, ``image_size``, ``observe_images``, ``sensor``, ``renderer``, ``render_mode``, ``render_size``,
      ``background``: as in the pick env.
    - ``max_steps``: step limit (None: 2 per instance in grasp mode, 200 per target instance in ee mode).
    - ``max_failed_attempts``: grasp mode: failed attempts in a row that end the episode (default 3).
    - ``regrasp_station``: (x, y) centre of the regrasp station on the table, m (None: no station; a "standing"
      grasp is then placed as an "across" one).

    ## Info
    After reset and every step: ``outcome`` (:data:`BIN_OUTCOMES`; "fail" after a reset and in ee mode while
    nothing is judged), ``is_success`` (outcome ``grasp_and_place``), ``instance`` (id of the instance lifted,
    or None), ``part`` (its part name, or None), ``targets_left``, ``target``, ``cleared`` (ids of instances
    taken out this step, picked or not), ``attempts`` (attempts so far), ``pushes`` (pushes so far),
    ``failed_in_a_row``, ``end_reason``
    (:data:`END_REASONS` or None), ``instances`` (:meth:`instance_poses`), ``instance_segmentation`` ((H, W)
    int32 instance id per pixel of the wrist image, -1 elsewhere; None without images), ``T_world_camera``,
    ``T_camera_reportedcamera``, ``sensor``, ``renderer``, ``background``, ``backdrop``; in grasp mode after a
    step also ``lifted``, ``placement_distance_m``, ``placement_axis_error_rad`` of the instance in focus,
    ``sim_time_s`` (the scripted motion's simulated seconds), ``observation_move_s`` (the seconds the move back to
    the observation pose takes at the script's free-space speed; the arm is put there, not moved), ``grasp_kind``
    and ``regrasp`` (with ``regrasp_outcome`` when True); always ``phase`` (:data:`PHASES`: what the next action is
    for) and ``regrasp_instance`` (the id of the instance waiting at the station, or None).

    ## For agents and oracles
    - :meth:`instance_poses`: the true pose, part name, id, grasp point and visible pixel count of every
      instance in play (``visible_only=True``: those the last wrist image shows).
    - :meth:`instance_segmentation`: the last wrist image's instance ids per pixel.
    - :meth:`oracle_action`: the grasp action of a perfect perception for an instance (default: the target
      instance the task prefers, :meth:`~don_gym.sim.bin_task.BinPickTask.top_instance`: room for the fingers,
      lying, highest; ``exclude=`` ids to try last, e.g. the one the last attempt failed on).
    - ``task.grasp_is_clear(instance)``: whether the fingers find room around an instance (walls, neighbours).
    - Attributes: ``target`` (part name), ``part_names`` (in instance-id order), ``models`` (part name ->
      :class:`~don_gym.objects.ObjectModel`), ``task`` (:class:`~don_gym.sim.bin_task.BinPickTask`; a new one
      each reset: look it up on the env).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        parts: Mapping[str | Path, int] | None = None,
        target: str = DEFAULT_TARGET,
        part_scales: Mapping[str | Path, float] | None = None,
        control: str = "grasp",
        image_size: tuple[int, int] | None = (160, 120),
        observe_images: bool = True,
        sensor: str = "d435",
        renderer: str = "tiny",
        reward_type: str = "sparse",
        render_mode: str | None = None,
        render_size: tuple[int, int] = (320, 240),
        max_steps: int | None = None,
        max_failed_attempts: int = 3,
        background: str = "plain",
        regrasp_station: tuple[float, float] | None = DEFAULT_STATION_XY_M,
    ):
        gym.Env.__init__(self)
        check_view_arguments(control, reward_type, ("sparse",), background, render_mode, observe_images)
        if max_steps is not None and (not is_integer(max_steps) or max_steps < 1):
            raise DonGymError(f"max_steps={max_steps!r}: expected None or a positive integer number of steps")
        if not is_integer(max_failed_attempts) or max_failed_attempts < 1:
            raise DonGymError(f"max_failed_attempts={max_failed_attempts!r}: expected a positive integer")
        image_size = self._set_camera_options(image_size, render_size, sensor, renderer)
        self.models, self.counts, self.target = resolve_parts(parts, target, part_scales)
        self.station_xy_m = None if regrasp_station is None else check_station(regrasp_station)
        self.control = control
        self.reward_type = reward_type
        self.render_mode = render_mode
        self.max_failed_attempts = int(max_failed_attempts)
        if max_steps is None:
            per = GRASP_STEPS_PER_INSTANCE * sum(self.counts.values())
            max_steps = per if control == "grasp" else EE_STEPS_PER_TARGET * self.counts[self.target]
        self.max_steps = int(max_steps)
        self.image_size = image_size if observe_images else None
        self.intrinsics = CameraIntrinsics.d435(*(self.image_size or (640, 480)))

        self._build_world(renderer, background)
        self.part_names = [instance.part for instance in self.task.instances]
        self.model = self.models[self.target]

        self.action_space = self._make_action_space()
        self.observation_space = self._make_observation_space()
        self._segmentation: np.ndarray | None = None
        self._T_camera_reportedcamera = np.eye(4)
        self._episode_over = True
        self._steps = 0
        self._pushes = 0
        self._failed_in_a_row = 0
        self._ee_yaw_rad = 0.0
        self._phase = "pick"
        self._regrasp_instance: Instance | None = None

    # ------------------------------------------------------------- the world
    def _build_world(self, renderer: str, background: str) -> None:
        """A new physics world as every episode starts from: client, table, cradle, bin, the instances on the
        shelf, the robot observing, the backdrop; its snapshot taken."""
        self._open_sim(renderer)
        known = getattr(self, "task", None)  # when rebuilding: the grasp points of the same parts, slow to compute
        self.task = BinPickTask(
            self.sim,
            self.models,
            self.counts,
            self.target,
            grasp_points_object=None if known is None else known.grasp_points_object,
            station_xy_m=self.station_xy_m,
        )
        self.robot = Panda(self.sim)
        self.task.attach_gripper(self.robot.body_id, FINGER_JOINTS)
        self.observation_arm_rad = self.robot.solve_top_down_camera(observation_camera_position(), OBSERVATION_YAW_RAD)
        self.robot.reset(self.observation_arm_rad)
        #: TCP position (world, m) at the observation pose.
        self._observation_tcp_m = self.robot.tcp_pose()[:3, 3].copy()
        if self.station_xy_m is not None:
            # The second observation pose: the wrist camera over the ledge's foot, where a part set down lies.
            _, edge, away = station_ledge(self.station_xy_m)
            camera = np.array([*(edge + 0.03 * away), STATION_CAMERA_HEIGHT_M])
            self.station_arm_rad = self.robot.solve_top_down_camera(camera, OBSERVATION_YAW_RAD)
            self.robot.reset(self.station_arm_rad)
            self._station_tcp_m = self.robot.tcp_pose()[:3, 3].copy()
            self.robot.reset(self.observation_arm_rad)
        self._set_up_backdrop(background)
        self.sim.take_snapshot()
        self._specular = {i.body.body_id: i.model.material.specular for i in self.task.instances}
        # PyBullet body id -> instance id (-1: not an instance), for the segmentation.
        self._instance_of_body = np.full(self.sim.client.getNumBodies() + 1, -1, dtype=np.int32)
        for instance in self.task.instances:
            self._instance_of_body[instance.body.body_id] = instance.instance_id
        #: Whether an episode has run in this world since it was built.
        self._world_used = False

    def _rebuild_world(self) -> None:
        """Replace a world an episode ran in by a new one. Restoring the snapshot is not enough here: Bullet's
        collision detection keeps state that ``restoreState`` does not restore and no call resets (the
        broadphase's pair cache, which drops pairs that stopped overlapping a few per step, its trees, the
        order of the contact manifolds, hence of the solver's contact rows). With a pile's many contacts that
        state differs after different episodes, and so did the picks: a pile replayed after another one
        diverged from the same pile in a new env at its second pick. A new world makes ``reset(seed=s)`` the
        same episode whatever ran before (about 0.1 s more a reset)."""
        backdrop_rng = self._backdrop_rng  # an unseeded backdrop stream goes on where it was
        self.sim.close()
        if self._backdrop is not None:
            self._backdrop.close()
        self._build_world(self.renderer, self.background)
        self._backdrop_rng = backdrop_rng

    # ---------------------------------------------------------- observation
    def _keep_segmentation(self, segmentation: np.ndarray) -> None:
        body = decode_segmentation(segmentation)[0]
        known = (body >= 0) & (body < len(self._instance_of_body))
        self._segmentation = np.where(known, self._instance_of_body[np.clip(body, 0, None)], -1).astype(np.int32)

    def instance_segmentation(self) -> np.ndarray | None:
        """(H, W) int32: the instance id each pixel of the last wrist image shows, -1 for anything else
        (table, bin, cradle, background); None without images."""
        return None if self._segmentation is None else self._segmentation.copy()

    def instance_poses(self, visible_only: bool = False) -> list[dict[str, Any]]:
        """The instances in play (:meth:`~don_gym.sim.bin_task.BinPickTask.instance_poses`: ``instance``,
        ``part``, ``T_world_object``, ``grasp_point_world``, ``in_bin``, ``visible_pixels`` in the last wrist
        image, None without images). ``visible_only``: only those with visible pixels. True poses: for oracles,
        evaluation and tests only."""
        pixels = None
        if self._segmentation is not None:
            ids, counts = np.unique(self._segmentation[self._segmentation >= 0], return_counts=True)
            pixels = dict(zip(ids.tolist(), counts.tolist(), strict=True))
        poses = self.task.instance_poses(pixels)
        return [pose for pose in poses if pose["visible_pixels"]] if visible_only else poses

    def _info(self) -> dict[str, Any]:
        return {
            "T_world_camera": self.robot.camera_pose(),
            "T_camera_reportedcamera": self._T_camera_reportedcamera.copy(),
            "sensor": self.sensor_name,
            "renderer": self.renderer,
            "background": self.background,
            "backdrop": None if self._backdrop_settings is None else dict(self._backdrop_settings),
            "target": self.target,
            "targets_left": self.task.targets_left(),
            "attempts": self._steps - self._pushes,
            "pushes": self._pushes,
            "failed_in_a_row": self._failed_in_a_row,
            "instances": self.instance_poses(),
            "instance_segmentation": self.instance_segmentation(),
            "phase": self._phase,
            "regrasp_instance": None if self._regrasp_instance is None else self._regrasp_instance.instance_id,
        }

    # ----------------------------------------------------------------- reset
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None and (not is_integer(seed) or seed < 0):
            raise DonGymError(f"seed={seed!r}: expected a non-negative integer or None")
        if options is not None and (not isinstance(options, Mapping) or options):
            raise DonGymError(f"options={options!r}: the bin env takes no reset options; expected None or {{}}")
        gym.Env.reset(self, seed=None if seed is None else int(seed))
        if self._world_used:
            self._rebuild_world()
        self._world_used = True
        self._restore_snapshot()
        self.task.drop_pile(self.np_random)
        if self.station_xy_m is not None:
            self.task.check_station_free()
        self._phase, self._regrasp_instance = "pick", None
        self._T_camera_reportedcamera = sample_calibration_error(self.sensor, self.np_random)
        self._episode_over = False
        self._steps = self._pushes = 0
        self._failed_in_a_row = 0
        self._ee_yaw_rad = float(OBSERVATION_YAW_RAD)
        self._randomise_backdrop(seed)
        observation = self._observation()
        info = self._info() | {
            "outcome": "fail",
            "is_success": False,
            "instance": None,
            "part": None,
            "cleared": [],
            "end_reason": None,
        }
        return observation, info

    # ------------------------------------------------------------------ step
    def _make_action_space(self) -> gym.spaces.Box:
        space = super()._make_action_space()
        if self.control != "grasp":
            return space
        low, high = space.low.copy(), space.high.copy()
        if self.station_xy_m is not None:  # grasps at the regrasp station too
            x0, x1, y0, y1 = station_bounds(self.station_xy_m)
            low[:2], high[:2] = np.minimum(low[:2], [x0, y0]), np.maximum(high[:2], [x1, y1])
        # One more element: the step kind's index in STEP_KINDS (rounded to the nearest).
        low = np.append(low, 0.0).astype(np.float32)
        high = np.append(high, float(len(STEP_KINDS) - 1)).astype(np.float32)
        return gym.spaces.Box(low, high, dtype=np.float32)

    def step(self, action):
        if self.control == "grasp" and not self._episode_over:
            action = self._with_grasp_kind(action)
        return super().step(action)

    def _with_grasp_kind(self, action: Any) -> Any:
        """A grasp action of 4 numbers with the kind "across" appended (their meaning before the kind existed);
        DonGymError for a kind that is not one of :data:`~don_gym.sim.script.STEP_KINDS`' indices, and for a push
        at the regrasp station (a grasp is expected there)."""
        try:
            numbers = np.asarray(action, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            return action  # the parent names it
        if numbers.shape == (4,):
            return np.append(numbers, 0.0)
        if numbers.shape == (5,) and not (np.isfinite(numbers[4]) and -0.5 < numbers[4] < len(STEP_KINDS) - 0.5):
            raise DonGymError(
                f"action[4]={float(numbers[4])!r} (grasp kind): expected the index of one of {list(STEP_KINDS)} "
                f"(0..{len(STEP_KINDS) - 1})"
            )
        if numbers.shape == (5,) and self._phase == "regrasp" and STEP_KINDS[int(round(numbers[4]))] == "push":
            raise DonGymError(
                f"action[4]={float(numbers[4])!r} (push) at the regrasp station: expected a grasp kind there "
                f"(0..{len(STEP_KINDS) - 2})"
            )
        return numbers

    def _clear_out_of_bin(self, require_rest: bool, keep: Instance | None = None) -> list[int]:
        """Take every instance in play that is no longer in the bin out of play (``require_rest``: only once
        it is at rest and touches no finger, or has fallen off the table; ``keep``: not that one); their ids."""
        cleared = []
        for instance in self.task.in_play():
            if self.task.in_bin(instance) or instance is keep:
                continue
            if require_rest:
                self.task.set_focus(instance)
                touched = any(self.robot.contacts(self.task).fingers)
                if not (self.task.left_workspace() or (self.task.is_at_rest() and not touched)):
                    continue
            self.task.clear(instance)
            cleared.append(instance.instance_id)
        return cleared

    def _finish_step(self, outcome: str, picked: Instance | None, cleared: list[int], extra: dict[str, Any]):
        # A part set down at the station is half an attempt: the attempt ends with the regrasp's step.
        self._steps += outcome != "set_down"
        self._pushes += outcome == "pushed"
        targets_left = self.task.targets_left()
        if self.control == "grasp" and outcome != "pushed":  # a push is no attempt: the count goes on past it
            self._failed_in_a_row = self._failed_in_a_row + 1 if outcome == "fail" else 0
        end_reason = None
        if outcome == "set_down":
            pass
        elif targets_left == 0:
            end_reason = "cleared"
        elif self.control == "grasp" and self._failed_in_a_row >= self.max_failed_attempts:
            end_reason = "failed_attempts"
        elif self._steps >= self.max_steps:
            end_reason = "step_limit"
        terminated = end_reason in ("cleared", "failed_attempts")
        truncated = end_reason == "step_limit"
        self._episode_over = terminated or truncated
        observation = self._observation()
        info = self._info() | extra
        info |= {
            "outcome": outcome,
            "is_success": outcome == "grasp_and_place",
            "instance": None if picked is None else picked.instance_id,
            "part": None if picked is None else picked.part,
            "cleared": cleared,
            "end_reason": end_reason,
        }
        return observation, float(outcome == "grasp_and_place"), terminated, truncated, info

    def _step_grasp(self, action: np.ndarray):
        kind = STEP_KINDS[int(round(float(action[4])))]
        if kind == "push":
            return self._step_push(action)
        if self._phase == "regrasp":
            return self._step_regrasp(action, kind)
        # The program is written for the target part (its opening, its grasp point's axial position for the
        # place); the judging starts at the target instance nearest the grasp and follows what is lifted.
        aimed = self.task.nearest_instance(action[:3], part=self.target)
        if aimed is not None:
            self.task.set_focus(aimed)
        opening = grasp_opening_m(self.model, kind, action[:2], float(action[3]))
        script = GraspPlaceScript(self.sim, self.robot, self.task, open_width_m=opening, slow_lift_m=CONTACT_ZONE_M)
        set_down = self._set_down_spec() if kind == "standing" and self.station_xy_m is not None else None
        trace = script.run(action[:3], float(action[3]), kind, set_down=set_down)
        judgement = self.task.judge(trace.lifted, trace.left_workspace, self.robot.contacts(self.task))
        picked = self.task.focus if trace.lifted else None
        outcome = judgement.outcome
        if picked is not None and picked.part != self.target:
            outcome = "wrong_part"
        elif set_down is not None and picked is not None:
            self.task.settle()
            if self.task.at_station(picked):
                # The attempt goes on at the station: observed from the second pose, grasped again by the agent.
                outcome, self._phase, self._regrasp_instance = "set_down", "regrasp", picked
        extra = {
            "lifted": judgement.lifted,
            "placement_distance_m": judgement.placement.distance_xy_m,
            "placement_axis_error_rad": judgement.placement.axis_error_rad,
            "sim_time_s": trace.sim_time_s,
            "grasp_kind": kind,
            "regrasp": False,
        }
        return self._end_grasp_step(outcome, picked, extra)

    def _step_push(self, action: np.ndarray):
        """A push (:meth:`~don_gym.sim.script.GraspPlaceScript.push`): the fingers stop on the first instance in
        play, the bin or the table they touch."""
        obstacles = [instance.body.body_id for instance in self.task.in_play()]
        obstacles += [self.task.bin_id, self.task.table_id]
        trace = GraspPlaceScript(self.sim, self.robot, self.task).push(action[:2], float(action[3]), obstacles)
        extra = {
            "lifted": False,
            "placement_distance_m": None,
            "placement_axis_error_rad": None,
            "sim_time_s": trace.sim_time_s,
            "grasp_kind": "push",
            "regrasp": False,
        }
        return self._end_grasp_step("pushed", None, extra)

    def _set_down_spec(self) -> tuple[np.ndarray, float, int]:
        """Where :meth:`~don_gym.sim.script.GraspPlaceScript.set_down` puts a part held standing: its axis over
        the table beyond the ledge's edge by :data:`~don_gym.sim.bin_task.LEDGE_OVERHANG_RADII` of its radius, the
        fingers closing along the edge (so that none is in the way of the part tipping over it)."""
        _, edge, away = station_ledge(self.station_xy_m)
        radius = lying_footprint_m(self.model)[1] / 2
        return edge + LEDGE_OVERHANG_RADII * radius * away, float(np.arctan2(away[1], away[0])), self.task.ledge_id

    def _step_regrasp(self, action: np.ndarray, kind: str):
        """The second grasp of an attempt, at the station: of the instance set down there, placed as a pick is.
        Whatever happens, that instance leaves play with the step (placed, dropped, or left at the station)."""
        instance = self._regrasp_instance
        self.task.set_focus(instance)
        opening = grasp_opening_m(self.model, kind, action[:2], float(action[3]))
        script = GraspPlaceScript(self.sim, self.robot, self.task, open_width_m=opening, slow_lift_m=CONTACT_ZONE_M)
        trace = script.run(action[:3], float(action[3]), kind)
        judgement = self.task.judge(trace.lifted, trace.left_workspace, self.robot.contacts(self.task))
        # The target was lifted out of the bin in this attempt: a regrasp that lifts nothing has not placed it.
        outcome = judgement.outcome if trace.lifted else "grasp_only"
        if trace.lifted and self.task.focus is not instance:
            outcome = "wrong_part"
        self._phase, self._regrasp_instance = "pick", None
        extra = {
            "lifted": True,
            "placement_distance_m": judgement.placement.distance_xy_m,
            "placement_axis_error_rad": judgement.placement.axis_error_rad,
            "sim_time_s": trace.sim_time_s,
            "grasp_kind": kind,
            "regrasp": True,
            "regrasp_outcome": outcome,
        }
        return self._end_grasp_step(outcome, instance, extra)

    def _end_grasp_step(self, outcome: str, picked: Instance | None, extra: dict[str, Any]):
        """The program's last move: to the observation pose of the next phase (the arm is clear above the cradle,
        the bin or the station); the arm is put there, and the time the move takes at the script's free-space
        speed is charged in ``info["observation_move_s"]``. The scene settles, every instance out of the bin (but
        one waiting at the station) is cleared."""
        regrasp = self._phase == "regrasp"
        arm, tcp = (self.station_arm_rad, self._station_tcp_m) if regrasp else (self.observation_arm_rad, None)
        extra["observation_move_s"] = self._observation_move_s(arm, tcp)
        self.robot.reset(arm)
        self.task.settle()
        cleared = self._clear_out_of_bin(require_rest=False, keep=self._regrasp_instance)
        return self._finish_step(outcome, picked, cleared, extra)

    def _observation_move_s(self, arm_rad: np.ndarray, tcp_m: np.ndarray | None = None) -> float:
        """Seconds a scripted straight move from the TCP's pose now to an observation pose (arm angles, TCP position;
        None: the bin's) takes (:func:`~don_gym.sim.script.move_duration_s` at the free-space speed)."""
        tcp = self._observation_tcp_m if tcp_m is None else tcp_m
        distance = float(np.linalg.norm(self.robot.tcp_pose()[:3, 3] - tcp))
        wrist_turn = float(arm_rad[6]) - float(self.robot.joint_positions()[6])
        return move_duration_s(distance, wrist_turn, FREE_SPEED_M_S)

    def _step_ee(self, action: np.ndarray):
        self._ee_yaw_rad = self.robot.apply_ee_action(action, self._ee_yaw_rad)
        self.sim.step(CONTROL_STEPS)
        outcome, picked = "fail", None
        for instance in self.task.in_play():
            contacts = self.task.instance_contacts(instance, self.robot.body_id, FINGER_JOINTS)
            instance.lifted = instance.lifted or self.task.instance_held(instance, contacts)
            if not instance.lifted:
                continue
            self.task.set_focus(instance)
            if self.task.in_bin(instance) and self.task.is_at_rest() and not any(contacts.fingers):
                instance.lifted = False  # dropped back into the bin: a part of the pile again
                instance.rest_com_z_m = float(instance.body.center_of_mass_world[2])
                continue
            judgement = self.task.judge(True, self.task.left_workspace(), contacts, require_rest=True)
            if judgement.is_success:
                outcome, picked = ("grasp_and_place" if instance.part == self.target else "wrong_part"), instance
                self.task.clear(instance)
        lifted_before = {i.instance_id: i for i in self.task.in_play() if i.lifted}
        cleared = self._clear_out_of_bin(require_rest=True)
        for instance_id in cleared:
            if instance_id in lifted_before and picked is None:
                instance = lifted_before[instance_id]
                outcome, picked = ("grasp_only" if instance.part == self.target else "wrong_part"), instance
        if picked is not None and picked.instance_id not in cleared:
            cleared = [picked.instance_id, *cleared]
        return self._finish_step(outcome, picked, cleared, {})

    # ------------------------------------------------------ for oracles
    def oracle_action(  # type: ignore[override]
        self, instance: int | None = None, flip: bool = False, exclude: Iterable[int] = ()
    ) -> np.ndarray:
        """The grasp-mode action of a perfect perception for instance ``instance`` (an id; default: the target
        instance :meth:`~don_gym.sim.bin_task.BinPickTask.top_instance` prefers, those in ``exclude`` last, e.g.
        the one the last attempt failed on): its grasp point in the world and the world yaw of its +axis
        projected on the table (``flip``: plus pi). Uses the true pose: tests and baselines only."""
        if instance is None and self._regrasp_instance is not None:
            chosen = self._regrasp_instance
        elif instance is None:
            chosen = self.task.top_instance(self.target, exclude=exclude)
            if chosen is None:
                raise DonGymError("oracle_action(): no target instance is left in play; reset() first")
        else:
            if not is_integer(instance) or not 0 <= instance < len(self.task.instances):
                raise DonGymError(f"instance={instance!r}: expected an instance id 0..{len(self.task.instances) - 1}")
            chosen = self.task.instances[int(instance)]
            if not chosen.in_play:
                raise DonGymError(f"instance={instance!r} was cleared; expected one in play")
        T = chosen.body.T_world_object
        point = self.task.grasp_point_world(chosen)
        axis = T[:3, :3] @ chosen.model.plus_axis
        yaw = float(np.arctan2(axis[1], axis[0])) + (np.pi if flip else 0.0)
        return np.array([point[0], point[1], point[2], wrap_angle(yaw)], dtype=np.float32)
