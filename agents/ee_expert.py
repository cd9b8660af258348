"""A closed-loop end-effector expert with privileged state, for demonstrations (:class:`EndEffectorExpert`).

It acts in ``control="ee"`` (dx, dy, dz, dyaw, gripper) from the simulator's true state only: the TCP pose, the
finger opening, which fingers touch the part, and the part's pose; no camera. It is Markov: each action is a
function of the current state (and the goal), with no phase kept between steps, so a demonstration's every
step can be relabelled, resumed or perturbed, and behaviour cloning learns a function of what it sees (the
reference's experts and robomimic's are of this kind). The phases of a grasp are read off the state:

- not holding the part: open the fingers and go above the grasp point turned across the part's axis, then
  down to it; at it (or with a fingertip on the table) close, holding the hand there;
- both fingers on it, still closing: squeeze until the opening settles;
- holding it (both fingers touch it, the opening settled): for ``goal="lift"`` raise the part's axis points straight
  up to the goal's height; for
  ``goal="place"`` lift to carrying height, carry the part's centre of mass over the cradle with its +axis
  along the target direction, lower it slowly, and open when it touches the cradle;
- not holding it with the part lying in the cradle placed well enough: open and retract.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.perception.descriptor_sources import axis_end_targets
from don_gym.sim.robot import (
    EE_STEP_M,
    EE_WRIST_MAX_RAD,
    EE_YAW_STEP_RAD,
    FINGER_JOINTS,
    MAX_WIDTH_M,
    MIN_TCP_HEIGHT_M,
    wrap_angle,
)
from don_gym.sim.script import APPROACH_HEIGHT_M, CARRY_HEIGHT_M
from don_gym.sim.task import (
    CRADLE_APEX_HEIGHT_M,
    CRADLE_CENTER_XY_M,
    CRADLE_TARGET_YAW_RAD,
    TABLE_TOP_Z_M,
    grasp_point_object,
    within_placement_tolerance,
)
from don_gym.wrappers.simulated_keypoints import axis_points_world

__all__ = ["EXPERT_GOALS", "EndEffectorExpert"]

#: Tasks the expert solves: lift the part where it lies (the goal of :class:`~don_gym.wrappers.KeypointGoal`), or
#: the whole pick-and-place.
EXPERT_GOALS = ("lift", "place")
#: Largest TCP target offset per step (m): in free space, near the part, with the part in the hand, lowering it.
#: The arm's joint controllers cover about half of an offset in a step (25 Hz), so the TCP moves about half as far.
FREE_STEP_M = 0.04
APPROACH_STEP_M = 0.015
CARRY_STEP_M = 0.025
LOWER_STEP_M = 0.006
#: At the grasp point: within these of it (m) and of the hand yaw across the axis (rad) the fingers start to
#: close; once they are closing, within the looser CLOSING_* they go on closing.
AT_GRASP_XY_M, AT_GRASP_Z_M, AT_YAW_RAD = 0.004, 0.007, 0.12
CLOSING_XY_M, CLOSING_Z_M = 0.010, 0.015
#: Go down to the part once above it within this (m), turning on the way down (the fingers are open wide).
ABOVE_XY_M = 0.012
#: The part's centre of mass over the cradle's centre within this (m): lower it; within NEAR_CRADLE_M line it up
#: where it is.
OVER_CRADLE_M, NEAR_CRADLE_M = 0.005, 0.03
#: Open enough to go down around the part (m).
OPEN_WIDTH_M = MAX_WIDTH_M - 0.005
#: The finger opening counts as settled on the part below this speed (m/s; closing runs at about 0.08).
SETTLED_SPEED_M_S = 0.01
#: Share of the yaw error turned per step.
YAW_GAIN = 0.5
#: Margin (rad) kept from joint 7's limits when choosing which of the two yaws across the axis to grasp with.
WRIST_MARGIN_RAD = 0.15


def _hand_yaw(quaternion_xyzw: np.ndarray) -> float:
    """Yaw (rad) of a top-down hand: the direction of hand x in the world's xy plane."""
    x_axis = Rotation.from_quat(quaternion_xyzw).as_matrix()[:, 0]
    return float(np.arctan2(x_axis[1], x_axis[0]))


def _toward(target: np.ndarray, current: np.ndarray, max_step_m: float) -> np.ndarray:
    """(3,) action part moving ``current`` toward ``target`` by at most ``max_step_m`` (m) along the line."""
    delta = np.asarray(target, dtype=np.float64) - np.asarray(current, dtype=np.float64)
    norm = float(np.linalg.norm(delta))
    if norm > max_step_m:
        delta *= max_step_m / norm
    return np.clip(delta / EE_STEP_M, -1.0, 1.0)


class EndEffectorExpert:
    """The Markov expert of ``goal`` ("lift" or "place") on a don_gym pick env with ``control="ee"``.

    Args:
        env: the env (wrapped or not); the expert reads its true state through ``env.unwrapped`` (privileged).
        goal: ``"lift"``: bring the part's axis points to the observation's ``desired_goal`` (the lift sub-task of
            :func:`~don_gym.wrappers.make_goal_env`); ``"place"``: the task itself, the part into the cradle.

    :meth:`act` takes the env's latest observation (only ``desired_goal`` is read, for ``"lift"``) and returns
    the action (5,) float32 in [-1, 1].
    """

    def __init__(self, env: gym.Env, goal: str = "lift") -> None:
        if goal not in EXPERT_GOALS:
            raise DonGymError(f"goal={goal!r} is unknown; expected one of {list(EXPERT_GOALS)}")
        base = env.unwrapped
        if getattr(base, "control", None) != "ee" or not hasattr(base, "task") or not hasattr(base, "robot"):
            raise DonGymError("EndEffectorExpert needs a don_gym pick env with control='ee'")
        self.env, self.goal, self.base = env, goal, base
        self.grasp_point_object = grasp_point_object(base.model)
        #: The two axis keypoints whose points the lift goal names (:class:`~don_gym.wrappers.KeypointGoal`'s).
        self.targets = axis_end_targets(base.model)

    # ----------------------------------------------------------------- state
    def _wrist(self, position: np.ndarray, yaw_rad: float) -> float:
        """Joint 7's angle for hand yaw ``yaw_rad`` at TCP ``position`` (as the env's ee action computes it)."""
        base_xy = self.base.robot.base_position[:2]
        q1 = np.arctan2(position[1] - base_xy[1], position[0] - base_xy[0])
        return wrap_angle(q1 - yaw_rad + np.pi / 4)

    def _grasp_yaw(self, grasp: np.ndarray, axis_yaw: float, hand_yaw: float) -> float:
        """Of the two hand yaws across the part's axis, the one nearer the hand's yaw now, unless its wrist angle at
        the grasp or (for "place") after turning the part onto the target direction leaves joint 7's range less a
        margin: a smooth function of the state wherever the range allows, which a cloned policy can follow."""
        limit = EE_WRIST_MAX_RAD - WRIST_MARGIN_RAD
        place = np.array([*CRADLE_CENTER_XY_M, 0.0])
        best, best_cost = axis_yaw, np.inf
        for candidate in (axis_yaw, axis_yaw + np.pi):
            wrists = [self._wrist(grasp, candidate)]
            if self.goal == "place":
                wrists.append(self._wrist(place, candidate + wrap_angle(CRADLE_TARGET_YAW_RAD - axis_yaw)))
            cost = sum(100.0 * max(0.0, abs(w) - limit) for w in wrists) + abs(wrap_angle(candidate - hand_yaw))
            if cost < best_cost:
                best, best_cost = candidate, cost
        return wrap_angle(best)

    def _turn(self, tcp: np.ndarray, hand_yaw: float, wanted_yaw: float) -> tuple[float, float]:
        """(dyaw action, error in rad) turning the hand to ``wanted_yaw`` the way joint 7 can go (no wrapping
        through its limits)."""
        error = self._wrist(tcp, hand_yaw) - self._wrist(tcp, wanted_yaw)  # the yaw grows as the wrist angle falls
        # Half the error a step: the env turns from the yaw it commanded last, which the measured yaw lags.
        return float(np.clip(YAW_GAIN * error / EE_YAW_STEP_RAD, -1.0, 1.0)), abs(error)

    def _fingers_moving(self) -> bool:
        """Whether the finger opening still changes faster than :data:`SETTLED_SPEED_M_S` (the simulator's joint
        velocities: privileged, Markov)."""
        robot = self.base.robot
        states = robot.sim.client.getJointStates(robot.body_id, list(FINGER_JOINTS))
        return abs(sum(state[1] for state in states)) > SETTLED_SPEED_M_S

    # ------------------------------------------------------------------- act
    def act(self, obs: Any = None) -> np.ndarray:
        """The action (5,) float32 for the env's current state."""
        robot, task = self.base.robot, self.base.task
        tcp, quaternion = robot.tcp_position_quaternion()
        hand_yaw = _hand_yaw(quaternion)
        T = task.part.T_world_object
        contacts = robot.contacts(task)
        axis = task.part.plus_axis_world()
        axis_yaw = float(np.arctan2(axis[1], axis[0]))
        if all(contacts.fingers):
            if self._fingers_moving():
                # Both fingers on the part but still closing: squeeze, then lift. Lifting at the first touch of the
                # second finger leaves the moment unseen from the finger opening alone (the cloned policy lifts too
                # early, or never); a settled opening marks it.
                return np.array([0.0, 0.0, 0.0, 0.0, -1.0], dtype=np.float32)
            return self._holding(obs, tcp, hand_yaw, axis_yaw, contacts)
        placement = task.placement(contacts)
        if (
            self.goal == "place"
            and placement.in_cradle
            and bool(within_placement_tolerance(placement.distance_xy_m, placement.axis_error_rad))
        ):
            # Released in the cradle: open and retract.
            up = np.array([tcp[0], tcp[1], TABLE_TOP_Z_M + CARRY_HEIGHT_M])
            return np.array([*_toward(up, tcp, FREE_STEP_M), 0.0, 1.0], dtype=np.float32)
        grasp = T[:3, :3] @ self.grasp_point_object + T[:3, 3]
        grasp[2] = max(grasp[2], TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M)
        dyaw, yaw_error = self._turn(tcp, hand_yaw, self._grasp_yaw(grasp, axis_yaw, hand_yaw))
        xy_error = float(np.linalg.norm(tcp[:2] - grasp[:2]))
        on_table = any(robot.finger_contacts(task.table_id))
        width = robot.gripper_width()
        closing = width < OPEN_WIDTH_M  # the fingers' opening is state: a grasp under way goes on
        near_xy, near_z = (CLOSING_XY_M, CLOSING_Z_M) if closing else (AT_GRASP_XY_M, AT_GRASP_Z_M)
        at_grasp = xy_error < near_xy and yaw_error < (2 if closing else 1) * AT_YAW_RAD
        at_grasp = at_grasp and (tcp[2] - grasp[2] < near_z or on_table)
        if at_grasp:
            # Close while holding the hand at the grasp point: a hand left to drift while the fingers close (about
            # 15 steps) grasps the part off centre, or above it.
            return np.array([*_toward(grasp, tcp, APPROACH_STEP_M), dyaw, -1.0], dtype=np.float32)
        hover = np.array([grasp[0], grasp[1], max(grasp[2] + APPROACH_HEIGHT_M / 2, TABLE_TOP_Z_M + APPROACH_HEIGHT_M)])
        if width < OPEN_WIDTH_M:
            # Closed on nothing (or a lost part): open, and rise clear of the part meanwhile.
            target = np.array([tcp[0], tcp[1], max(tcp[2], hover[2])])
            return np.array([*_toward(target, tcp, APPROACH_STEP_M), dyaw, 1.0], dtype=np.float32)
        above = xy_error < ABOVE_XY_M
        if above and tcp[2] <= hover[2] + 0.01:
            move = _toward(grasp, tcp, APPROACH_STEP_M)
        elif above:
            move = _toward(hover, tcp, FREE_STEP_M)
        else:
            # Across at hover height at least, so the open fingers never sweep the part.
            target = hover if tcp[2] >= hover[2] - 0.01 else np.array([tcp[0], tcp[1], hover[2]])
            move = _toward(target, tcp, FREE_STEP_M)
        return np.array([*move, dyaw, 1.0], dtype=np.float32)

    def _holding(self, obs: Any, tcp: np.ndarray, hand_yaw: float, axis_yaw: float, contacts: Any) -> np.ndarray:
        task = self.base.task
        if self.goal == "lift":
            if not isinstance(obs, dict) or "desired_goal" not in obs:
                raise DonGymError("EndEffectorExpert(goal='lift') needs observations with 'desired_goal'")
            desired = np.asarray(obs["desired_goal"], dtype=np.float64).reshape(2, 3).mean(axis=0)
            achieved = axis_points_world(self.base.model, self.targets, task.part.T_world_object).mean(axis=0)
            # Straight up to the goal's height: the goal's horizontal offset is only the few millimetres the grasp
            # pushed the part, well inside the goal's tolerance, and a policy that does not see the goal (a cloned
            # one, whose inputs must not leak where the part lay) could not follow it.
            move = _toward(tcp + np.array([0.0, 0.0, desired[2] - achieved[2]]), tcp, CARRY_STEP_M)
            return np.array([*move, 0.0, -1.0], dtype=np.float32)
        com = task.part.center_of_mass_world
        carry_z = TABLE_TOP_Z_M + CARRY_HEIGHT_M
        over = tcp[:2] + (CRADLE_CENTER_XY_M - com[:2])
        dyaw, yaw_error = self._turn(tcp, hand_yaw, hand_yaw + wrap_angle(CRADLE_TARGET_YAW_RAD - axis_yaw))
        xy_error = float(np.linalg.norm(com[:2] - CRADLE_CENTER_XY_M))
        if contacts.cradle or any(self.base.robot.finger_contacts(task.cradle_id)):
            return np.array([0.0, 0.0, 0.0, 0.0, 1.0], dtype=np.float32)  # on the cradle: let go
        if xy_error < OVER_CRADLE_M and yaw_error < AT_YAW_RAD:
            lowest = np.array([*over, TABLE_TOP_Z_M + CRADLE_APEX_HEIGHT_M + MIN_TCP_HEIGHT_M])
            step = LOWER_STEP_M if tcp[2] < TABLE_TOP_Z_M + CRADLE_APEX_HEIGHT_M + 0.07 else CARRY_STEP_M
            return np.array([*_toward(lowest, tcp, step), dyaw, -1.0], dtype=np.float32)
        if xy_error < NEAR_CRADLE_M:
            target = np.array([*over, tcp[2]])  # nearly there: line up at this height, no climbing back
        elif tcp[2] < carry_z - 0.01:
            target = np.array([tcp[0], tcp[1], carry_z])  # up first, then across
        else:
            target = np.array([*over, carry_z])
        return np.array([*_toward(target, tcp, CARRY_STEP_M), dyaw, -1.0], dtype=np.float32)
