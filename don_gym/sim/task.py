"""The pick-and-place task (:class:`PickPlaceTask`): table, part, handover cradle, part poses,
observation viewpoint, and the judging of a step: outcome, success and reward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from don_gym.geometry import make_transform
from don_gym.objects import ObjectModel
from don_gym.sim.bullet import Bullet
from don_gym.sim.part import PartBody, lying_rotation, radius_profile

TABLE_TOP_Z_M = 0.0
#: Table top rectangle (x_min, x_max, y_min, y_max) in metres; the robot base sits on it at the origin.
TABLE_BOUNDS_M = (-0.25, 0.85, -0.55, 0.65)
TABLE_THICKNESS_M = 0.05
#: Where the human may leave the part: its centre of mass lies in this rectangle
#: (x_min, x_max, y_min, y_max). Chosen so that the whole part stays in the wrist camera's
#: view from the observation pose and within comfortable top-down reach.
WORKSPACE_M = (0.42, 0.60, -0.14, 0.14)

#: Cradle (handover fixture): centre of the groove on the table, target yaw of the +axis.
CRADLE_CENTER_XY_M = np.array([0.36, 0.42])
CRADLE_TARGET_YAW_RAD = 0.0
#: Height of the groove's bottom line above the table, groove length, wall width along the slope.
#: The walls are short (rim 12.7 mm above and beside the bottom line): they hold a part of up to
#: 17 mm radius (the toolcap's flange touches at 12 mm) while the fingers, which straddle the
#: 28 mm body with 14 mm thick fingertips, just clear them, so the toolcap is set down, not
#: dropped; a slimmer part (the shaft) is let go a few millimetres above its seat.
CRADLE_APEX_HEIGHT_M = 0.03
CRADLE_LENGTH_M = 0.14
CRADLE_WALL_WIDTH_M = 0.018
CRADLE_WALL_THICKNESS_M = 0.006
CRADLE_BASE_HALF_WIDTH_M = 0.025

PLACE_TOLERANCE_M = 0.02
AXIS_TOLERANCE_RAD = np.deg2rad(20.0)
#: How far (m) :func:`grasp_point_object` keeps the finger pads from a step of the radius profile
#: where the flat stretch allows: room for the perception's error along the axis (with the D435's
#: calibration error and noise even the oracle's grasp point is several millimetres off).
GRASP_STEP_CLEARANCE_M = 0.010
#: Height (m) of the centre of mass above its resting height that counts as "lifted".
LIFT_HEIGHT_M = 0.03

#: The paper's outcome categories, worst first (see :meth:`PickPlaceTask.judge`).
OUTCOMES = ("fail", "grasp_only", "grasp_and_place")
#: "sparse": 1.0 on success, else 0.0; "dense": see :meth:`PickPlaceTask.reward`.
REWARD_TYPES = ("sparse", "dense")

#: Observation pose: the wrist camera this high above the table over the workspace centre, looking
#: down with hand yaw 0, which puts image x along world +y (the image's long side across the
#: workspace's long side).
OBSERVATION_CAMERA_HEIGHT_M = 0.45
OBSERVATION_YAW_RAD = 0.0

#: A freshly placed part settles on the table for at least / at most this long (s) at reset;
#: it is calm once its speed stays below 5 mm/s and 0.1 rad/s for two checks 40 ms apart.
SETTLE_MIN_S = 0.08
SETTLE_MAX_S = 0.8


def _fixed_poses() -> list[tuple[float, float, float]]:
    """8 evaluation poses (x, y, yaw of the +axis): a 2 x 4 grid over the workspace, +axis
    every 45 degrees (offset 22.5 degrees so no pose is axis-aligned with the image)."""
    xs = (0.46, 0.56)
    ys = (-0.105, -0.035, 0.035, 0.105)
    cells = [(xs[i % 2], ys[i // 2]) for i in range(8)]
    # Spread the directions so neighbouring cells point differently.
    order = (0, 5, 2, 7, 4, 1, 6, 3)
    return [(x, y, float(np.deg2rad(22.5 + 45.0 * k))) for (x, y), k in zip(cells, order, strict=True)]


#: ``reset(options={"pose_id": k})`` poses, k in 0..7: (x m, y m, yaw rad of the +axis).
FIXED_POSES = _fixed_poses()


@dataclass(frozen=True)
class PartContacts:
    """What the part touches right now (one contact query each)."""

    fingers: tuple[bool, bool]
    table: bool
    cradle: bool


@dataclass(frozen=True)
class Placement:
    """Where the part is relative to the cradle."""

    in_cradle: bool
    distance_xy_m: float
    axis_error_rad: float

    @property
    def correct(self) -> bool:
        return self.in_cradle and bool(within_placement_tolerance(self.distance_xy_m, self.axis_error_rad))


def within_placement_tolerance(distance_m: np.ndarray | float, axis_error_rad: np.ndarray | float) -> np.ndarray:
    """Elementwise: a part whose centre is ``distance_m`` from where it should be and whose +axis is
    ``axis_error_rad`` off the target direction is placed well enough (:data:`PLACE_TOLERANCE_M`,
    :data:`AXIS_TOLERANCE_RAD`); :attr:`Placement.correct` adds that it lies in the cradle."""
    return (np.asarray(distance_m) <= PLACE_TOLERANCE_M) & (np.asarray(axis_error_rad) <= AXIS_TOLERANCE_RAD)


@dataclass(frozen=True)
class Judgement:
    """The task's verdict on the current state: outcome (one of :data:`OUTCOMES`), whether the part
    was lifted during the episode, and where it lies relative to the cradle."""

    outcome: str
    lifted: bool
    placement: Placement

    @property
    def is_success(self) -> bool:
        return self.outcome == "grasp_and_place"

    def info(self) -> dict[str, Any]:
        """The env's ``info`` entries after a step."""
        return {
            "outcome": self.outcome,
            "is_success": self.is_success,
            "lifted": self.lifted,
            "placement_distance_m": self.placement.distance_xy_m,
            "placement_axis_error_rad": self.placement.axis_error_rad,
        }


def observation_camera_position() -> np.ndarray:
    """(3,) world position (m) of the wrist camera in the observation pose."""
    centre = np.array([(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2])
    return np.array([centre[0], centre[1], TABLE_TOP_Z_M + OBSERVATION_CAMERA_HEIGHT_M])


def grasp_point_object(
    model: ObjectModel, pad_half_width_m: float = 0.011, step_clearance_m: float = GRASP_STEP_CLEARANCE_M
) -> np.ndarray:
    """(3,) object-frame point on the +axis where a top-down grasp across the axis holds best.

    The paper's axis grasp takes the midpoint of two tracked points; here the midpoint of the
    axis end points. For a part with a declared symmetry axis the point moves, if needed, onto
    the nearest stretch where the radius is constant under the whole finger pad (``+-pad_half_width_m``),
    and there as far as the stretch allows (up to ``step_clearance_m``) from its steps, so that a
    grasp a few millimetres off along the axis still does not put a pad on a step (the shaft's
    midpoint is the collar's edge: a pad corner on that edge hooks the part, which then follows
    one finger when the gripper opens).
    """
    midpoint = np.mean(model.axis_endpoints(), axis=0)
    if model.symmetry_axis is None:
        return midpoint
    axis = np.asarray(model.plus_axis, dtype=np.float64)
    com = model.center_of_mass
    centred = model.mesh.copy()
    centred.apply_translation(-com)
    profile = radius_profile(centred, axis)
    # Flat stretches of the profile: runs of consecutive points with the same radius.
    stretches, start = [], 0
    for i in range(1, len(profile) + 1):
        if i == len(profile) or abs(profile[i, 1] - profile[start, 1]) > 1e-5:
            if profile[start, 1] > 0:
                stretches.append((profile[start, 0], profile[i - 1, 0]))
            start = i
    best, best_distance = None, np.inf
    target = float((midpoint - com) @ axis)
    for t0, t1 in stretches:
        if t1 - t0 < 2 * pad_half_width_m:
            continue
        candidate = float(np.clip(target, t0 + pad_half_width_m, t1 - pad_half_width_m))
        if abs(candidate - target) < best_distance:
            best, best_distance = (t0, t1), abs(candidate - target)
    if best is None:
        return midpoint
    t0, t1 = best
    margin = pad_half_width_m + min(step_clearance_m, (t1 - t0) / 2 - pad_half_width_m)
    return com + float(np.clip(target, t0 + margin, t1 - margin)) * axis


def grasp_axial_position_m(model: ObjectModel) -> float:
    """Axial position (m from the centre of mass along +axis) of :func:`grasp_point_object`."""
    axis = np.asarray(model.plus_axis, dtype=np.float64)
    return float((grasp_point_object(model) - model.center_of_mass) @ axis)


def yaw_direction(yaw_rad: float) -> np.ndarray:
    return np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])


def cradle_rest_center(model: ObjectModel) -> np.ndarray:
    """(3,) world point above the groove centre at the part's typical resting height (for rewards and goals)."""
    radius = 0.5 * float(np.sort(model.extents_m)[:2].mean())
    return np.array(
        [*CRADLE_CENTER_XY_M, TABLE_TOP_Z_M + CRADLE_APEX_HEIGHT_M + radius * np.sqrt(2.0)], dtype=np.float64
    )


def seated_pose(model: ObjectModel) -> np.ndarray:
    """T_world_object (4, 4) of the part seated in the cradle as a correct placement leaves it, to
    within the placement tolerances: lying on its side, +axis along the target direction, centre
    of mass at :func:`cradle_rest_center` (a goal for goal-conditioned agents)."""
    R = lying_rotation(model, CRADLE_TARGET_YAW_RAD)
    return make_transform(R, cradle_rest_center(model) - R @ model.center_of_mass)


class PickPlaceTask:
    """Builds the static scene and the part; samples part poses; judges outcome and reward.

    World frame: z up, origin at the robot base on the table top (:data:`TABLE_TOP_Z_M` = 0), x
    away from the robot. A human leaves the part lying on its side somewhere in the workspace in
    front of the robot; the robot must put it into the *handover cradle*, a 90-degree V-groove to
    the robot's left, with the part's +axis along the cradle's target direction, because a second
    robot without vision takes it from there (paper, "Experiment setup").
    """

    def __init__(self, sim: Bullet, model: ObjectModel):
        self.sim = sim
        self.model = model
        self.table_id = self._build_table()
        self.cradle_id = self._build_cradle()
        self.part = PartBody.create(sim, model, name="object")
        self.rest_com_z_m = TABLE_TOP_Z_M  # set by settle()

    def _build_table(self) -> int:
        x0, x1, y0, y1 = TABLE_BOUNDS_M
        half = [(x1 - x0) / 2, (y1 - y0) / 2, TABLE_THICKNESS_M / 2]
        centre = [(x0 + x1) / 2, (y0 + y1) / 2, TABLE_TOP_Z_M - TABLE_THICKNESS_M / 2]
        return self.sim.create_static_boxes("table", [(half, centre, (0, 0, 0, 1))], rgba=(0.55, 0.45, 0.35, 1.0))

    def _build_cradle(self) -> int:
        """A V-groove along the target direction: two walls at +-45 degrees on a base block."""
        yaw = CRADLE_TARGET_YAW_RAD
        R_world_cradle = Rotation.from_euler("z", yaw).as_matrix()
        T_world_cradle = make_transform(
            R_world_cradle, [CRADLE_CENTER_XY_M[0], CRADLE_CENTER_XY_M[1], TABLE_TOP_Z_M + CRADLE_APEX_HEIGHT_M]
        )
        boxes = []
        half_wall = [CRADLE_LENGTH_M / 2, CRADLE_WALL_WIDTH_M / 2, CRADLE_WALL_THICKNESS_M / 2]
        for side in (1.0, -1.0):
            # Cradle frame: x along the groove, y across, z up, origin on the groove's bottom line.
            slope = np.array([0.0, side, 1.0]) / np.sqrt(2.0)
            inward_normal = np.array([0.0, -side, 1.0]) / np.sqrt(2.0)
            centre = slope * CRADLE_WALL_WIDTH_M / 2 - inward_normal * CRADLE_WALL_THICKNESS_M / 2
            R_cradle_wall = Rotation.from_euler("x", side * np.pi / 4).as_matrix()
            T_world_wall = T_world_cradle @ make_transform(R_cradle_wall, centre)
            boxes.append((half_wall, T_world_wall[:3, 3], Rotation.from_matrix(T_world_wall[:3, :3]).as_quat()))
        base_half = [CRADLE_LENGTH_M / 2, CRADLE_BASE_HALF_WIDTH_M, CRADLE_APEX_HEIGHT_M / 2]
        base_centre = T_world_cradle @ np.array([0.0, 0.0, -CRADLE_APEX_HEIGHT_M / 2, 1.0])
        boxes.append((base_half, base_centre[:3], Rotation.from_matrix(R_world_cradle).as_quat()))
        return self.sim.create_static_boxes("cradle", boxes, rgba=(0.25, 0.5, 0.3, 1.0), lateral_friction=0.6)

    # ------------------------------------------------------------ part pose
    def lying_pose(self, x: float, y: float, yaw_rad: float) -> np.ndarray:
        """T_world_object of the part on its side, +axis at ``yaw_rad``, centre of mass over (x, y),
        lowest point 1 mm above the table (it then settles under gravity)."""
        R = lying_rotation(self.model, yaw_rad)
        com = self.model.center_of_mass
        lowest = float((self.model.mesh.vertices @ R.T)[:, 2].min())
        com_world = np.array([x, y, 0.0])
        T = make_transform(R, com_world - R @ com)
        T[2, 3] = TABLE_TOP_Z_M + 0.001 - lowest
        return T

    def sample_pose(self, rng: np.random.Generator) -> tuple[float, float, float]:
        """Random (x, y, yaw): uniform over the workspace and over all yaws."""
        x0, x1, y0, y1 = WORKSPACE_M
        return float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)), float(rng.uniform(-np.pi, np.pi))

    def forget_contacts(self) -> None:
        """Delete the contact manifolds of the part before a snapshot is restored: they survive
        ``restoreState`` and warm-start the solver, so a part put back where it lay in an earlier
        episode or scene would move differently. Parks the part far above everything and runs
        collision detection; the caller moves the robot clear first (its own reset pose)."""
        self.part.set_pose(make_transform(translation=[0.0, 0.0, 50.0]))
        self.sim.client.performCollisionDetection()

    def place_part(self, x: float, y: float, yaw_rad: float) -> None:
        self.part.set_pose(self.lying_pose(x, y, yaw_rad))

    def settle(self) -> None:
        """Let the part come to rest on the table (the robot is away from it) and remember its height.

        Deterministic: how long it runs depends on the simulated state only.
        """
        chunk = max(1, int(round(0.04 / self.sim.time_step_s)))
        elapsed, calm = 0.0, 0
        while elapsed < SETTLE_MAX_S:
            self.sim.step(chunk)
            elapsed += chunk * self.sim.time_step_s
            linear, angular = self.part.velocity
            calm = calm + 1 if np.linalg.norm(linear) < 0.005 and np.linalg.norm(angular) < 0.1 else 0
            if calm >= 2 and elapsed >= SETTLE_MIN_S:
                break
        self.rest_com_z_m = float(self.part.center_of_mass_world[2])

    # -------------------------------------------------------------- judging
    def cradle_rest_center(self) -> np.ndarray:
        """(3,) world point above the groove centre at the part's typical resting height (for rewards)."""
        return cradle_rest_center(self.model)

    def contacts(self, robot_id: int, finger_links: tuple[int, int]) -> PartContacts:
        part_id = self.part.body_id
        fingers = tuple(bool(self.sim.contact_points(robot_id, part_id, link_a=link)) for link in finger_links)
        return PartContacts(
            fingers=fingers,
            table=bool(self.sim.contact_points(part_id, self.table_id)),
            cradle=bool(self.sim.contact_points(part_id, self.cradle_id)),
        )

    def placement(self, contacts: PartContacts) -> Placement:
        part = self.part
        com = part.center_of_mass_world
        in_cradle = contacts.cradle and not contacts.table
        axis = part.plus_axis_world()
        target = yaw_direction(CRADLE_TARGET_YAW_RAD)
        axis_error = float(np.arccos(np.clip(axis @ target, -1.0, 1.0)))
        distance = float(np.linalg.norm(com[:2] - CRADLE_CENTER_XY_M))
        return Placement(in_cradle, distance, axis_error)

    def is_held(self, contacts: PartContacts) -> bool:
        """Lifted: touched by both fingers, off the table, centre of mass raised by :data:`LIFT_HEIGHT_M`."""
        if not all(contacts.fingers) or contacts.table:
            return False
        return float(self.part.center_of_mass_world[2]) > self.rest_com_z_m + LIFT_HEIGHT_M

    def left_workspace(self) -> bool:
        """True when the part fell off the table (or tunnelled through it)."""
        com = self.part.center_of_mass_world
        x0, x1, y0, y1 = TABLE_BOUNDS_M
        return not (x0 <= com[0] <= x1 and y0 <= com[1] <= y1 and com[2] > TABLE_TOP_Z_M - 0.02)

    def is_at_rest(self) -> bool:
        linear, angular = self.part.velocity
        return float(np.linalg.norm(linear)) < 0.02 and float(np.linalg.norm(angular)) < 0.5

    def judge(
        self, lifted: bool, left_workspace: bool, contacts: PartContacts, require_rest: bool = False
    ) -> Judgement:
        """The paper's outcome now, given whether the part was lifted this episode and has left the table.

        - ``"fail"``: the part was never lifted (a part pushed off the table without a lift included).
        - ``"grasp_only"``: it was lifted, but then dropped (off the table too), misplaced, or placed
          reversed (+axis against the target direction, "upside down"). The paper's "fail" is a grasp
          that left the part untouched and its "grasp only" a successful grasp whose placement failed,
          "e.g. dropped": a part lifted and then lost over the table's edge was grasped.
        - ``"grasp_and_place"``: it lies in the cradle (touches it, not the table), its centre of
          mass within :data:`PLACE_TOLERANCE_M` (horizontally) of the cradle centre and its +axis
          within :data:`AXIS_TOLERANCE_RAD` of the target direction, released by the gripper; with
          ``require_rest`` also at rest. A toolcap seated correctly has its axis about 7 degrees from
          horizontal (the flange is 3 mm larger in radius than the body), which counts towards the
          tolerance.
        """
        placement = self.placement(contacts)
        if not lifted:
            outcome = "fail"
        elif placement.correct and not left_workspace and not any(contacts.fingers):
            outcome = "grasp_and_place"
        else:
            outcome = "grasp_only"
        if outcome == "grasp_and_place" and require_rest and not self.is_at_rest():
            outcome = "grasp_only"
        return Judgement(outcome, bool(lifted), placement)

    def reward(self, judgement: Judgement, reward_type: str, tcp_position_m: np.ndarray) -> float:
        """Reward of a step (``reward_type`` one of :data:`REWARD_TYPES`).

        Dense: minus the distance of the TCP to the part's centre of mass (until lifted), of the
        part to :meth:`cradle_rest_center`, and the axis error scaled to "1 rad ~ 10 cm"; +1 on success.
        """
        if reward_type == "sparse":
            return float(judgement.is_success)
        com = self.part.center_of_mass_world
        reach = 0.0 if judgement.lifted else float(np.linalg.norm(tcp_position_m - com))
        place = float(np.linalg.norm(com - self.cradle_rest_center()))
        return float(-(reach + place + 0.1 * judgement.placement.axis_error_rad) + judgement.is_success)
