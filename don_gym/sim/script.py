"""The scripted grasp-and-place of ``control="grasp"`` (:class:`GraspPlaceScript`).

A pre-programmed robot program that grasps the part where the agent believes its axis is and
places it into the cradle; nothing is attached, friction alone holds the part.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from don_gym.objects import ObjectModel
from don_gym.sim.bullet import Bullet
from don_gym.sim.robot import ARM_LOWER_RAD, ARM_UPPER_RAD, MAX_WIDTH_M, MIN_TCP_HEIGHT_M, Panda, wrap_angle
from don_gym.sim.task import (
    CRADLE_APEX_HEIGHT_M,
    CRADLE_CENTER_XY_M,
    CRADLE_TARGET_YAW_RAD,
    TABLE_TOP_Z_M,
    PickPlaceTask,
    grasp_axial_position_m,
    yaw_direction,
)

#: Physics steps per control tick of the scripted motions (4 ms steps -> 50 Hz IK updates).
TICK_STEPS = 5
#: Joint 7 turns at most this fast (rad/s) so a carried part is not flung off by the rotation.
WRIST_SPEED_RAD_S = 1.2
#: Heights above the table for approach, carrying and retreat.
APPROACH_HEIGHT_M = 0.12
CARRY_HEIGHT_M = 0.16
#: Speeds (m/s): fast in free space, slow near contact.
FREE_SPEED_M_S = 0.35
APPROACH_SPEED_M_S = 0.15
LIFT_SPEED_M_S = 0.10
PLACE_SPEED_M_S = 0.05
RETRACT_SPEED_M_S = 0.2
#: The slow speeds near contact apply within this height (m) of where the part lies or lands: a held part reaches
#: at most 4 cm below the TCP, so this leaves 2 cm to spare.
CONTACT_ZONE_M = 0.06
#: Lift (m) before opening when the fingertips touch the cradle's walls.
FINGER_CLEARANCE_M = 0.004
#: The release counts as failed while a finger still touches the part after opening (stalled short
#: of fully open, or fully open with the part stuck to one pad); the script then squeezes and opens
#: again, at most RELEASE_RETRIES times.
RELEASE_RETRIES = 3
#: The grasp's first phases, in order (:meth:`GraspPlaceScript.grasp_start` stops after one of them).
GRASP_PHASES = ("approach", "descend", "close")
#: Margin (rad) kept from joint 7's limits when choosing wrist angles.
WRIST_MARGIN_RAD = 0.08
#: What a grasp holds (the bin env's 5th action element is the index): the fingers across the part's axis (the
#: pick env's grasp), along it (the fingers on the two end faces, the axis across the fingers), or across a part
#: standing on an end (its axis vertical in the hand).
GRASP_KINDS = ("across", "along", "standing")
#: What a step of the bin env does (its 5th action element is the index): a grasp of :data:`GRASP_KINDS`, or a
#: push (:meth:`GraspPlaceScript.push`) that rolls a part lying against a wall away from it, lifting nothing.
STEP_KINDS = (*GRASP_KINDS, "push")
#: A push: the closed fingers come down on the part until they touch something, press this much (m) further, move
#: this far (m) at this speed (m/s) and go up again. A round part pressed from above rolls under the fingers.
PUSH_PRESS_M = 0.005
PUSH_DISTANCE_M = 0.05
PUSH_SPEED_M_S = 0.05


def end_faces_axial_position_m(model: ObjectModel) -> float:
    """Axial position (m from the centre of mass along the +axis) of the middle between the part's two end faces:
    where fingers closing along the axis hold it, whatever point of the axis they were aimed at."""
    axis = np.asarray(model.plus_axis, dtype=np.float64)
    axial = (np.asarray(model.mesh.vertices, dtype=np.float64) - model.center_of_mass) @ axis
    return float(axial.min() + axial.max()) / 2


def held_axial_position_m(model: ObjectModel, kind: str) -> float:
    """Axial position (m from the centre of mass along the +axis) between the fingers after a grasp of ``kind``
    (:data:`GRASP_KINDS`): the part's grasp point across the axis (and across a standing part), the middle of its
    end faces along it."""
    return end_faces_axial_position_m(model) if kind == "along" else grasp_axial_position_m(model)


def move_duration_s(distance_m: float, wrist_turn_rad: float, speed_m_s: float) -> float:
    """Duration (s) of a scripted straight TCP move of ``distance_m`` at ``speed_m_s`` while joint 7 turns by
    ``wrist_turn_rad`` (at most :data:`WRIST_SPEED_RAD_S`), at least 0.1 s; without the settling after it."""
    return max(float(distance_m) / float(speed_m_s), abs(float(wrist_turn_rad)) / WRIST_SPEED_RAD_S, 0.1)


def min_jerk(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


@dataclass
class ScriptTrace:
    """What happened during the script (for info and debugging)."""

    lifted: bool = False
    left_workspace: bool = False
    grasp_width_m: float = float("nan")
    release_width_m: float = float("nan")
    release_retries: int = 0
    phases: list[str] = field(default_factory=list)
    sim_time_s: float = 0.0


class GraspPlaceScript:
    """Runs one grasp-and-place; owns no state beyond one episode.

    Given the agent's belief (grasp point and yaw of the part's +axis), the robot:

    1. moves above the grasp point with the fingers across the believed axis (top-down),
    2. descends, closes the gripper slowly with a limited force and waits for the fingers to stop,
    3. lifts slowly (with ``slow_lift_m``, as the bin env asks, only out of the pile, then fast), carries
       the part above the cradle while turning the hand so that the *believed* +axis ends along the cradle's
       target direction, the hand offset along it by the grasp point's known axial position so that the part's
       centre of mass comes over the groove's centre,
    4. lowers it with a guarded move (stops at the first contact of the part or a fingertip
       with the cradle, as a force-guarded industrial place would), lifts 4 mm if a fingertip
       rests on a groove wall, opens the gripper (squeezing and opening again if the fingers
       stalled on the part, as a program checks that a gripper move succeeded) and retracts.

    The part is held by finger friction alone, so a believed axis that is flipped (yaw + pi)
    ends reversed in the cradle. Motion: Cartesian straight lines with a quintic (minimum-jerk)
    time scaling, IK at every control tick, joint position control with the arm's torque limits;
    the hand yaw is parametrised by the wrist angle (joint 7) so the arm never winds past its limits.
    """

    def __init__(
        self,
        sim: Bullet,
        robot: Panda,
        task: PickPlaceTask,
        open_width_m: float = MAX_WIDTH_M,
        slow_lift_m: float | None = None,
    ):
        self.sim = sim
        self.robot = robot
        self.task = task
        #: Finger opening (m) on the way down to the grasp: fully open alone on a table; in a pile, just wider
        #: than the part, so that the fingers find room between its neighbours.
        self.open_width_m = float(open_width_m)
        #: How far (m) above the grasp the lift goes at :data:`LIFT_SPEED_M_S` before the free-space speed takes
        #: over up to the carry height (as the place comes down: fast, then slow within :data:`CONTACT_ZONE_M`).
        #: None: the whole lift slow, the single-part env's program (its recorded figures were measured so).
        self.slow_lift_m = None if slow_lift_m is None else float(slow_lift_m)
        self.base_xy = robot.base_position[:2]
        self.trace = ScriptTrace()
        self._tcp = robot.tcp_pose()[:3, 3].copy()
        self._wrist = float(robot.joint_positions()[6])
        #: TCP xy at the place of an across grasp (:meth:`place_xy_for`).
        self.place_xy = self.place_xy_for("across")

    def place_xy_for(self, kind: str) -> np.ndarray:
        """TCP xy (m) at the place after a grasp of ``kind``: the point held between the fingers
        (:func:`held_axial_position_m`) sits this far along the target direction from the part's centre of mass,
        which is what must end over the groove's centre."""
        target_xy = yaw_direction(CRADLE_TARGET_YAW_RAD)[:2]
        return CRADLE_CENTER_XY_M + held_axial_position_m(self.task.model, kind) * target_xy

    # ------------------------------------------------------------- helpers
    def _yaw_for(self, position: np.ndarray, wrist_rad: float) -> float:
        """Hand yaw that joint 7 at ``wrist_rad`` gives at ``position`` (top-down, see robot.wrist_angle_estimate)."""
        q1 = np.arctan2(position[1] - self.base_xy[1], position[0] - self.base_xy[0])
        return float(q1 - wrist_rad + np.pi / 4)

    def _wrist_for(self, position: np.ndarray, yaw_rad: float) -> float:
        q1 = np.arctan2(position[1] - self.base_xy[1], position[0] - self.base_xy[0])
        return wrap_angle(q1 - yaw_rad + np.pi / 4)

    def _wrist_nearer_middle(self, position: np.ndarray, hand_yaw_rad: float) -> float:
        """Joint-7 angle (rad) for a hand yaw of ``hand_yaw_rad`` or that plus pi (the fingers are symmetric), the
        one nearer the middle of its range, kept :data:`WRIST_MARGIN_RAD` inside its limits."""
        wrist = min((self._wrist_for(position, yaw) for yaw in (hand_yaw_rad, hand_yaw_rad + np.pi)), key=abs)
        return float(np.clip(wrist, ARM_LOWER_RAD[6] + WRIST_MARGIN_RAD, ARM_UPPER_RAD[6] - WRIST_MARGIN_RAD))

    def _step(self, count: int) -> None:
        self.sim.step(count)
        self.trace.sim_time_s += count * self.sim.time_step_s

    def _command(self, position: np.ndarray, wrist_rad: float) -> None:
        q = self.robot.inverse_kinematics(position, self._yaw_for(position, wrist_rad), wrist_rad=wrist_rad)
        self.robot.command_arm(q)

    def move(
        self,
        target: np.ndarray,
        wrist_rad: float,
        speed_m_s: float,
        guard: Callable[[], bool] | None = None,
        settle_s: float = 0.25,
    ) -> bool:
        """Straight TCP line to ``target`` while joint 7 turns to ``wrist_rad``.

        Returns False when ``guard`` fired (the arm then holds the pose where it fired).
        """
        start, wrist0 = self._tcp.copy(), self._wrist
        target = np.asarray(target, dtype=np.float64)
        distance = float(np.linalg.norm(target - start))
        duration = move_duration_s(distance, wrist_rad - wrist0, speed_m_s)
        tick_s = TICK_STEPS * self.sim.time_step_s
        ticks = int(np.ceil(duration / tick_s))
        for k in range(1, ticks + 1):
            s = min_jerk(k / ticks)
            position = start + s * (target - start)
            wrist = wrist0 + s * (wrist_rad - wrist0)
            self._command(position, wrist)
            self._step(TICK_STEPS)
            if guard is not None and guard():
                self._tcp, self._wrist = position, wrist
                return False
        self._tcp, self._wrist = target, float(wrist_rad)
        # Let the joint controllers catch up with the last set-point.
        for _ in range(int(np.ceil(settle_s / tick_s))):
            if np.linalg.norm(self.robot.tcp_pose()[:3, 3] - target) < 0.001:
                break
            self._step(TICK_STEPS)
        return True

    def gripper(self, width_m: float, max_time_s: float = 2.0, min_time_s: float = 0.2) -> float:
        """Drive the fingers to ``width_m``; wait until they stop (blocked by a part or arrived)."""
        self.robot.command_gripper(width_m)
        tick_s = TICK_STEPS * self.sim.time_step_s
        previous = self.robot.gripper_width()
        elapsed = 0.0
        while elapsed < max_time_s:
            self._step(TICK_STEPS)
            elapsed += tick_s
            width = self.robot.gripper_width()
            if elapsed >= min_time_s and abs(width - previous) < 2e-5:
                break
            previous = width
        return self.robot.gripper_width()

    def choose_wrists(self, grasp_xyz: np.ndarray, axis_yaw_rad: float, kind: str = "across") -> tuple[float, float]:
        """Joint-7 angles at the grasp and at the place for a believed +axis yaw and a grasp ``kind``.

        The fingers close across the axis, so the hand yaw is the axis yaw or that plus pi (a grasp
        ``"along"`` the axis: a further 90 degrees, the fingers closing along it); the place yaw turns the
        believed axis onto the target direction, the hand turning with it. Of the two, take
        the one that keeps both wrist angles inside joint 7's range (less the margin), the
        grasp one first; in the rare case neither does, the place angle is clamped, which
        costs at most the 15 degrees the range lacks of a full turn (placement tolerance 20).
        """
        place_xyz = np.array([*self.place_xy_for(kind), 0.0])
        turn = CRADLE_TARGET_YAW_RAD - axis_yaw_rad
        limit_lo, limit_hi = ARM_LOWER_RAD[6] + WRIST_MARGIN_RAD, ARM_UPPER_RAD[6] - WRIST_MARGIN_RAD
        closing_yaw = axis_yaw_rad + (np.pi / 2 if kind == "along" else 0.0)
        best = None
        for hand_yaw in (closing_yaw, closing_yaw + np.pi):
            wrist_grasp = self._wrist_for(grasp_xyz, hand_yaw)
            wrist_place = self._wrist_for(place_xyz, hand_yaw + turn)
            excess_grasp = max(0.0, limit_lo - wrist_grasp, wrist_grasp - limit_hi)
            excess_place = max(0.0, limit_lo - wrist_place, wrist_place - limit_hi)
            # Prefer the wrist angles closest to the middle of the range among feasible ones.
            cost = 100.0 * excess_grasp + 10.0 * excess_place + 0.01 * (abs(wrist_grasp) + abs(wrist_place))
            if best is None or cost < best[0]:
                best = (cost, wrist_grasp, wrist_place)
        _, wrist_grasp, wrist_place = best
        return float(np.clip(wrist_grasp, limit_lo, limit_hi)), float(np.clip(wrist_place, limit_lo, limit_hi))

    def _grasp_phases(self, grasp: np.ndarray, wrist_rad: float, last: str) -> None:
        """The grasp's first phases of :data:`GRASP_PHASES` up to ``last``: above the grasp point with the
        gripper open, down to it (stopping if a finger touches the table), the gripper closed."""
        robot, task = self.robot, self.task

        def touching_table() -> bool:
            return any(robot.finger_contacts(task.table_id))

        self.trace.phases.append("approach")
        robot.command_gripper(self.open_width_m)
        self.move(np.array([grasp[0], grasp[1], TABLE_TOP_Z_M + APPROACH_HEIGHT_M]), wrist_rad, FREE_SPEED_M_S)
        if last == "approach":
            return
        self.trace.phases.append("descend")
        self.move(grasp, wrist_rad, APPROACH_SPEED_M_S, guard=touching_table)
        if last == "descend":
            return
        self.trace.phases.append("close")
        self.trace.grasp_width_m = self.gripper(0.0)

    def grasp_start(self, grasp_xyz: np.ndarray, axis_yaw_rad: float, last: str, wrist_limit_rad: float) -> float:
        """Run the grasp's phases up to ``last`` (one of :data:`GRASP_PHASES`) and stop there: a start state
        for learning (the hand open above the part, open around it, or closed on it). Of the two hand yaws
        across the axis it takes the one whose joint-7 angle is nearer the middle, kept within
        ``wrist_limit_rad``. Returns the hand yaw (rad)."""
        if last not in GRASP_PHASES:
            raise ValueError(f"last={last!r}: expected one of {list(GRASP_PHASES)}")
        grasp = np.asarray(grasp_xyz, dtype=np.float64).copy()
        grasp[2] = max(grasp[2], TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M)
        wrist = min((self._wrist_for(grasp, yaw) for yaw in (axis_yaw_rad, axis_yaw_rad + np.pi)), key=abs)
        wrist = float(np.clip(wrist, -wrist_limit_rad, wrist_limit_rad))
        self._grasp_phases(grasp, wrist, last)
        return self._yaw_for(grasp, wrist)

    # ---------------------------------------------------------------- run
    def run(
        self,
        grasp_xyz: np.ndarray,
        axis_yaw_rad: float,
        kind: str = "across",
        set_down: tuple[np.ndarray, float, int] | None = None,
    ) -> ScriptTrace:
        """Execute the whole grasp-and-place for the believed grasp point, +axis yaw and grasp kind
        (:data:`GRASP_KINDS`: ``"along"`` closes the fingers along the believed axis and places the part as an
        across grasp would; ``"standing"`` is carried and placed as ``"across"``). ``set_down``: instead of the
        place, :meth:`set_down` what was lifted there (``(xy, hand_yaw_rad, ledge_body_id)``)."""
        if kind not in GRASP_KINDS:
            raise ValueError(f"kind={kind!r}: expected one of {list(GRASP_KINDS)}")
        task, robot, trace = self.task, self.robot, self.trace
        part_id = task.part.body_id
        grasp = np.asarray(grasp_xyz, dtype=np.float64).copy()
        grasp[2] = max(grasp[2], TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M)
        self.place_xy = self.place_xy_for(kind)
        wrist_grasp, wrist_place = self.choose_wrists(grasp, axis_yaw_rad, kind)
        self._grasp_phases(grasp, wrist_grasp, "close")
        trace.phases.append("lift")
        lift_to = np.array([grasp[0], grasp[1], TABLE_TOP_Z_M + CARRY_HEIGHT_M])
        if self.slow_lift_m is not None and self._tcp[2] + self.slow_lift_m < lift_to[2]:
            clear = np.array([grasp[0], grasp[1], self._tcp[2] + self.slow_lift_m])
            self.move(clear, wrist_grasp, LIFT_SPEED_M_S, settle_s=0.0)
            self.move(lift_to, wrist_grasp, FREE_SPEED_M_S)
        else:
            self.move(lift_to, wrist_grasp, LIFT_SPEED_M_S)
        trace.lifted = task.is_held(robot.contacts(task))
        if not trace.lifted:
            # Nothing in the hand: a real program would stop here too.
            self.gripper(MAX_WIDTH_M)
            trace.left_workspace = task.left_workspace()
            return trace
        if set_down is not None:
            self.set_down(*set_down)
            return trace

        trace.phases.append("carry")
        above_cradle = np.array([*self.place_xy, TABLE_TOP_Z_M + CARRY_HEIGHT_M])
        self.move(above_cradle, wrist_place, FREE_SPEED_M_S)
        trace.phases.append("lower")
        # Quickly to where no part held at most 4 cm below the TCP can touch, then a slow
        # guarded move: stop at the first contact of the part or a finger with the cradle.
        apex_z = TABLE_TOP_Z_M + CRADLE_APEX_HEIGHT_M
        self.move(np.array([*self.place_xy, apex_z + CONTACT_ZONE_M]), wrist_place, APPROACH_SPEED_M_S, settle_s=0.0)
        lowest = np.array([*self.place_xy, apex_z + MIN_TCP_HEIGHT_M])

        def touching_cradle() -> bool:
            if self.sim.contact_points(part_id, task.cradle_id):
                return True
            return any(robot.finger_contacts(task.cradle_id))

        self.move(lowest, wrist_place, PLACE_SPEED_M_S, guard=touching_cradle, settle_s=0.0)
        trace.phases.append("release")
        if any(robot.finger_contacts(task.cradle_id)):
            # Fingertips on the groove walls: the 45-degree walls would block the fingers from
            # opening (and wedge the part between them), so lift clear first; the part then
            # drops the last few millimetres into the groove.
            self.move(self._tcp + np.array([0.0, 0.0, FINGER_CLEARANCE_M]), self._wrist, 0.02, settle_s=0.1)
        trace.release_width_m = self.gripper(MAX_WIDTH_M, max_time_s=1.0)
        while trace.release_retries < RELEASE_RETRIES and any(robot.contacts(task).fingers):
            # A part that crept a few degrees in yaw between the pads during the carry can wedge
            # between opposite pad corners as they open (the simulated contacts then hold the
            # fingers), or stay stuck to one pad that drags it up the groove's wall and, on the
            # retract, out of the cradle; squeezing it again lines it up with the pads.
            trace.release_retries += 1
            self.gripper(0.0)
            trace.release_width_m = self.gripper(MAX_WIDTH_M, max_time_s=1.0)
        self._retract_and_settle()
        return trace

    def _retract_and_settle(self) -> None:
        """Up 10 cm, then let the part come to rest (five calm ticks in a row, at most 2 s) before judging."""
        task, trace = self.task, self.trace
        trace.phases.append("retract")
        self.move(self._tcp + np.array([0.0, 0.0, 0.10]), self._wrist, RETRACT_SPEED_M_S, settle_s=0.0)
        calm = 0
        for _ in range(100):
            self._step(TICK_STEPS)
            calm = calm + 1 if task.is_at_rest() else 0
            if calm >= 5:
                break
        trace.left_workspace = task.left_workspace()

    def push(self, press_xy: np.ndarray, push_yaw_rad: float, obstacle_ids: Sequence[int]) -> ScriptTrace:
        """Push a part by rolling it: the gripper closed, down at ``press_xy`` (world m) until a finger touches one
        of the bodies ``obstacle_ids`` (the part's top, else whatever lies there; the table at the latest), press
        :data:`PUSH_PRESS_M` further, move :data:`PUSH_DISTANCE_M` towards world yaw ``push_yaw_rad`` (rad) and go
        up. The fingers side by side across the push, so a part lying across it is pressed along its length."""
        robot, trace = self.robot, self.trace
        press = np.asarray(press_xy, dtype=np.float64)[:2]
        floor_z = TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M
        direction = np.array([np.cos(push_yaw_rad), np.sin(push_yaw_rad), 0.0])
        above = np.array([press[0], press[1], TABLE_TOP_Z_M + APPROACH_HEIGHT_M])
        wrist = self._wrist_nearer_middle(above, push_yaw_rad)

        def touching() -> bool:
            return any(any(robot.finger_contacts(int(body))) for body in obstacle_ids)

        trace.phases.append("approach")
        robot.command_gripper(0.0)
        self.move(above, wrist, FREE_SPEED_M_S)
        trace.phases.append("descend")
        self.move(np.array([press[0], press[1], floor_z]), wrist, APPROACH_SPEED_M_S, guard=touching, settle_s=0.0)
        trace.phases.append("push")
        pressed = self._tcp.copy()
        pressed[2] = max(floor_z, pressed[2] - PUSH_PRESS_M)
        self.move(pressed, wrist, PLACE_SPEED_M_S, settle_s=0.0)
        self.move(pressed + PUSH_DISTANCE_M * direction, wrist, PUSH_SPEED_M_S, settle_s=0.0)
        trace.phases.append("retract")
        self.move(self._tcp + np.array([0.0, 0.0, APPROACH_HEIGHT_M]), wrist, RETRACT_SPEED_M_S, settle_s=0.0)
        return trace

    def set_down(self, xy: np.ndarray, hand_yaw_rad: float, ledge_id: int) -> None:
        """Carry the part held to above ``xy`` (world m) with the hand at ``hand_yaw_rad`` (or that plus pi, the
        wrist nearer the middle of its range), lower it until it or a finger touches the ledge ``ledge_id`` or the
        table, open the gripper and retract: a part held standing with its axis beyond the ledge's edge tips over
        it and comes to lie below."""
        task, robot = self.task, self.robot
        part_id = task.part.body_id
        target = np.array([xy[0], xy[1], TABLE_TOP_Z_M + CARRY_HEIGHT_M])
        wrist = self._wrist_nearer_middle(target, hand_yaw_rad)
        self.trace.phases.append("carry")
        self.move(target, wrist, FREE_SPEED_M_S)

        def touching() -> bool:
            for body in (ledge_id, task.table_id):
                if self.sim.contact_points(part_id, body) or any(robot.finger_contacts(body)):
                    return True
            return False

        self.trace.phases.append("set_down")
        lowest = np.array([xy[0], xy[1], TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M])
        self.move(lowest, wrist, PLACE_SPEED_M_S * 2, guard=touching, settle_s=0.0)
        self.gripper(MAX_WIDTH_M, max_time_s=1.0)
        self._retract_and_settle()
