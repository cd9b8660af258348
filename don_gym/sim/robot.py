"""The Franka Panda with its parallel gripper and wrist RGB-D camera (:class:`Panda`).

Besides joint-level control it maps the env's Cartesian ee actions to joint targets
(:meth:`Panda.apply_ee_action`) and solves the top-down camera pose the env observes from
(:meth:`Panda.solve_top_down_camera`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from don_gym.geometry import make_transform
from don_gym.sim.bullet import Bullet, pose_matrix
from don_gym.sim.task import TABLE_TOP_Z_M, PartContacts, PickPlaceTask

ARM_JOINTS = (0, 1, 2, 3, 4, 5, 6)
FINGER_JOINTS = (9, 10)
HAND_LINK = 8
TCP_LINK = 11
#: Joint torque limits of the real arm (N m) and the URDF joint ranges (rad).
ARM_FORCES_N_M = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
ARM_LOWER_RAD = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
ARM_UPPER_RAD = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
#: A comfortable top-down configuration, the null-space rest pose of the IK.
ARM_HOME_RAD = np.array([0.0, -0.25, 0.0, -2.3, 0.0, 2.05, np.pi / 4])
#: Fully open gripper: distance between the finger pads (m).
MAX_WIDTH_M = 0.08
#: Gripping force per finger (N): 80 N in all, within the real Panda hand's 70 N continuous /
#: 140 N peak. With 30 N the 0.13 kg shaft, held 10 mm from its centre of mass, yawed a few
#: degrees in the pads while the wrist turned and could wedge between them on release.
FINGER_FORCE_N = 40.0
#: Finger speed (m/s); slow closing lets the part settle between the pads instead of being kicked.
FINGER_SPEED_M_S = 0.04
#: Finger pads: rubber-like friction (ManiSkill uses 2.0); PyBullet multiplies it with the part's.
FINGER_LATERAL_FRICTION = 1.8
FINGER_SPINNING_FRICTION = 0.05
#: TCP offset from the hand frame along hand z (m), from the URDF.
TCP_OFFSET_M = 0.105
#: Lowest TCP height above the table: the fingertips (7 mm below the TCP) stay 3 mm clear.
MIN_TCP_HEIGHT_M = 0.010

#: ee control: an action (dx, dy, dz, dyaw, gripper) in [-1, 1] moves the TCP target by up to
#: EE_STEP_M per axis, the hand yaw by EE_YAW_STEP_RAD and the finger opening by EE_GRIPPER_STEP_M.
EE_STEP_M = 0.05
EE_YAW_STEP_RAD = 0.25
EE_GRIPPER_STEP_M = 0.02
#: ee control keeps the TCP target in this box (x0, x1, y0, y1, z0, z1), metres; its floor keeps
#: the fingertips 3 mm above the table.
EE_BOUNDS_M = (0.20, 0.80, -0.35, 0.60, TABLE_TOP_Z_M + MIN_TCP_HEIGHT_M, TABLE_TOP_Z_M + 0.45)
#: ee control keeps joint 7 this far inside its +-2.97 rad range.
EE_WRIST_MAX_RAD = 2.85

#: Wrist camera pose in the hand frame (OpenCV camera axes): 6.5 cm to the side of the
#: gripper along hand -x, 1 cm above the hand flange plane, looking along hand z (down when the
#: hand is top-down), image rows along hand x. Like a D435 on a side bracket, it sees the
#: workspace past the fingers rather than through them.
T_HAND_CAMERA = make_transform(
    Rotation.from_euler("z", -np.pi / 2).as_matrix(),
    np.array([-0.065, 0.0, -0.01]),
)


def top_down_quaternion(yaw_rad: float) -> np.ndarray:
    """(x, y, z, w) of the top-down hand orientation with yaw ``yaw_rad``.

    Hand z points down, hand x = (cos yaw, sin yaw, 0) and the fingers close along hand
    y = (sin yaw, -cos yaw, 0). Closed form of Rz(yaw) Rx(pi) rather than scipy: it is called
    at every control tick.
    """
    return np.array([np.cos(0.5 * yaw_rad), np.sin(0.5 * yaw_rad), 0.0, 0.0])


def wrap_angle(angle_rad: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    wrapped = (float(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi
    return np.pi if wrapped == -np.pi else wrapped


def wrist_angle_estimate(position: np.ndarray, yaw_rad: float) -> float:
    """Joint-7 angle (wrapped to (-pi, pi]) for a top-down hand at ``position`` with ``yaw_rad``.

    With joints 3 and 5 near zero the hand yaw is ``q1 - q7 + pi/4`` and ``q1`` points the arm
    at the target; the estimate picks the IK branch and tells whether a yaw is reachable.
    """
    q1 = np.arctan2(position[1], position[0])
    return wrap_angle(q1 - yaw_rad + np.pi / 4)


class Panda:
    """Panda arm + gripper in a :class:`Bullet` world, base at ``base_position``.

    Model: ``pybullet_data/franka_panda/panda.urdf``. Joints 0-6 are the arm, 7 and 8 fixed,
    9 and 10 the prismatic fingers (0-0.04 m each); link 11 ``panda_grasptarget``, 0.105 m in
    front of the hand between the finger pads, is the tool centre point (TCP). PyBullet ignores
    the URDF's ``<mimic>``, so a gear constraint ties finger 10 to finger 9: the fingers stay
    centred like the real, mechanically coupled gripper, and a part touched by one finger first
    is pushed to the middle instead of away. The wrist camera is mounted at :data:`T_HAND_CAMERA`.
    """

    def __init__(self, sim: Bullet, base_position: Sequence[float] = (0.0, 0.0, 0.0)):
        self.sim = sim
        client = sim.client
        self.body_id = sim.load_urdf("panda", "franka_panda/panda.urdf", base_position, fixed_base=True)
        self.base_position = np.asarray(base_position, dtype=np.float64)
        for link in FINGER_JOINTS:
            client.changeDynamics(
                self.body_id,
                link,
                lateralFriction=FINGER_LATERAL_FRICTION,
                spinningFriction=FINGER_SPINNING_FRICTION,
            )
        gear = client.createConstraint(
            self.body_id,
            FINGER_JOINTS[0],
            self.body_id,
            FINGER_JOINTS[1],
            jointType=p.JOINT_GEAR,
            jointAxis=[1, 0, 0],
            parentFramePosition=[0, 0, 0],
            childFramePosition=[0, 0, 0],
        )
        # Both finger joints open along their own axes (+y and -y of the hand), so ratio -1
        # makes q9 == q10; the constraint is stronger than the finger motors so it wins.
        client.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=4 * FINGER_FORCE_N)
        self.gear_constraint = gear
        # Null-space IK wants 9 values (all movable joints, fingers included).
        self._ik_lower = list(ARM_LOWER_RAD) + [0.0, 0.0]
        self._ik_upper = list(ARM_UPPER_RAD) + [0.04, 0.04]
        self._ik_range = [u - lo for u, lo in zip(self._ik_upper, self._ik_lower, strict=True)]
        self.width_target_m = MAX_WIDTH_M
        self.arm_target_rad = ARM_HOME_RAD.copy()
        # The URDF loads stretched straight up, a singular pose that IK cannot leave.
        self.reset(ARM_HOME_RAD)
        self._visual_rgba = {int(d[1]): tuple(d[7]) for d in client.getVisualShapeData(self.body_id)}

    @contextlib.contextmanager
    def hidden(self) -> Iterator[None]:
        """Make the robot invisible to cameras for the duration (alpha 0, which both renderers skip).

        The wrist camera looks down and away from the arm and 6.5 cm beside the fingers, so the
        robot never appears in its images (a test checks this) and the renderer can skip the
        arm's ~100k visual triangles.
        """
        client = self.sim.client
        for link in self._visual_rgba:
            client.changeVisualShape(self.body_id, link, rgbaColor=[1.0, 1.0, 1.0, 0.0])
        try:
            yield
        finally:
            for link, rgba in self._visual_rgba.items():
                client.changeVisualShape(self.body_id, link, rgbaColor=list(rgba))

    # ---------------------------------------------------------------- state
    def reset(self, arm_rad: np.ndarray, width_m: float = MAX_WIDTH_M) -> None:
        """Teleport the joints (zero velocity) and hold them there; only for resets."""
        client = self.sim.client
        for joint, angle in zip(ARM_JOINTS, arm_rad, strict=True):
            client.resetJointState(self.body_id, joint, float(angle), 0.0)
        for joint in FINGER_JOINTS:
            client.resetJointState(self.body_id, joint, width_m / 2.0, 0.0)
        self.command_arm(arm_rad)
        self.command_gripper(width_m)

    def joint_positions(self) -> np.ndarray:
        """(9,) arm joints 0-6 (rad) then both finger joints (m)."""
        states = self.sim.client.getJointStates(self.body_id, list(ARM_JOINTS) + list(FINGER_JOINTS))
        return np.array([s[0] for s in states], dtype=np.float64)

    def gripper_width(self) -> float:
        """Distance between the finger pads (m)."""
        states = self.sim.client.getJointStates(self.body_id, list(FINGER_JOINTS))
        return float(states[0][0] + states[1][0])

    def link_pose(self, link: int) -> np.ndarray:
        state = self.sim.client.getLinkState(self.body_id, link, computeForwardKinematics=True)
        return pose_matrix(state[4], state[5])

    def tcp_position_quaternion(self) -> tuple[np.ndarray, np.ndarray]:
        """TCP position (3,) in metres and quaternion (x, y, z, w) in the world."""
        state = self.sim.client.getLinkState(self.body_id, TCP_LINK, computeForwardKinematics=True)
        return np.asarray(state[4], dtype=np.float64), np.asarray(state[5], dtype=np.float64)

    def tcp_pose(self) -> np.ndarray:
        """(4, 4) pose of the tool centre point (``panda_grasptarget``) in the world."""
        return self.link_pose(TCP_LINK)

    def hand_pose(self) -> np.ndarray:
        return self.link_pose(HAND_LINK)

    def camera_pose(self) -> np.ndarray:
        """(4, 4) true ``T_world_camera`` of the wrist camera (OpenCV axes)."""
        return self.hand_pose() @ T_HAND_CAMERA

    def finger_contacts(self, body_id: int) -> tuple[bool, bool]:
        """Whether each finger touches ``body_id``."""
        return tuple(bool(self.sim.contact_points(self.body_id, body_id, link_a=f)) for f in FINGER_JOINTS)

    def contacts(self, task: PickPlaceTask) -> PartContacts:
        """What the task's part touches: each finger, the table, the cradle."""
        return task.contacts(self.body_id, FINGER_JOINTS)

    # -------------------------------------------------------------- control
    def inverse_kinematics(
        self, tcp_position: np.ndarray, yaw_rad: float, wrist_rad: float | None = None, iterations: int = 100
    ) -> np.ndarray:
        """(7,) arm joint angles putting the TCP at ``tcp_position`` with a top-down hand of yaw ``yaw_rad``.

        ``wrist_rad`` (joint 7) is the null-space rest angle of joint 7; by default
        :func:`wrist_angle_estimate`. Null-space IK pulls the other joints to :data:`ARM_HOME_RAD`.
        PyBullet's iteration shrinks the error by about half every five iterations: 100 (stop at
        10 um) gives sub-millimetre poses for any move; a closed loop that re-solves every step
        from the measured state can use fewer.
        """
        tcp_position = np.asarray(tcp_position, dtype=np.float64)
        if wrist_rad is None:
            wrist_rad = wrist_angle_estimate(tcp_position - self.base_position, yaw_rad)
        wrist_rad = float(np.clip(wrist_rad, ARM_LOWER_RAD[6], ARM_UPPER_RAD[6]))
        rest = list(ARM_HOME_RAD[:6]) + [wrist_rad, 0.02, 0.02]
        # No ``currentPositions``: PyBullet then takes the Jacobian there but the error from the
        # body's actual state, and its iterations stall centimetres off. The iteration starts from
        # the actual joints, which the scripted motions keep within a few millimetres of the target.
        solution = self.sim.client.calculateInverseKinematics(
            self.body_id,
            TCP_LINK,
            list(tcp_position),
            list(top_down_quaternion(yaw_rad)),
            lowerLimits=self._ik_lower,
            upperLimits=self._ik_upper,
            jointRanges=self._ik_range,
            restPoses=rest,
            maxNumIterations=int(iterations),
            residualThreshold=1e-5,
        )
        return np.clip(np.asarray(solution[:7]), ARM_LOWER_RAD, ARM_UPPER_RAD)

    def command_arm(self, arm_rad: np.ndarray) -> None:
        """Position-control the arm joints towards ``arm_rad`` with the real torque limits."""
        self.arm_target_rad = np.asarray(arm_rad, dtype=np.float64).copy()
        self.sim.client.setJointMotorControlArray(
            self.body_id,
            list(ARM_JOINTS),
            p.POSITION_CONTROL,
            targetPositions=list(self.arm_target_rad),
            forces=list(ARM_FORCES_N_M),
        )

    def command_gripper(self, width_m: float, force_n: float = FINGER_FORCE_N) -> None:
        """Move the fingers towards pad distance ``width_m`` at :data:`FINGER_SPEED_M_S`, at most ``force_n`` each."""
        self.width_target_m = float(np.clip(width_m, 0.0, MAX_WIDTH_M))
        client = self.sim.client
        for joint in FINGER_JOINTS:
            client.setJointMotorControl2(
                self.body_id,
                joint,
                p.POSITION_CONTROL,
                self.width_target_m / 2.0,
                force=force_n,
                maxVelocity=FINGER_SPEED_M_S,
            )

    def apply_ee_action(self, action: np.ndarray, yaw_rad: float) -> float:
        """Command one step of Cartesian control; the hand stays top-down.

        ``action`` (dx, dy, dz, dyaw, gripper) in [-1, 1] is scaled by :data:`EE_STEP_M`,
        :data:`EE_YAW_STEP_RAD` and :data:`EE_GRIPPER_STEP_M`. The TCP target is the measured TCP
        plus the step, kept in :data:`EE_BOUNDS_M`; the hand yaw is ``yaw_rad`` (the yaw commanded
        last step) plus the step, limited so joint 7 stays within :data:`EE_WRIST_MAX_RAD`.
        Returns the commanded hand yaw, the next step's ``yaw_rad``.
        """
        tcp, _ = self.tcp_position_quaternion()
        x0, x1, y0, y1, z0, z1 = EE_BOUNDS_M
        target = np.clip(tcp + EE_STEP_M * action[:3], [x0, y0, z0], [x1, y1, z1])
        # Hand yaw as joint 7 sees it (see wrist_angle_estimate), kept inside its range.
        q1 = float(np.arctan2(target[1] - self.base_position[1], target[0] - self.base_position[0]))
        wanted_yaw = yaw_rad + EE_YAW_STEP_RAD * action[3]
        wrist = float(np.clip(q1 - wanted_yaw + np.pi / 4, -EE_WRIST_MAX_RAD, EE_WRIST_MAX_RAD))
        yaw_rad = q1 + np.pi / 4 - wrist
        # 20 IK iterations (~2 mm left of a 5 cm move): the next step re-solves from the measured pose.
        self.command_arm(self.inverse_kinematics(target, yaw_rad, wrist_rad=wrist, iterations=20))
        self.command_gripper(self.width_target_m + EE_GRIPPER_STEP_M * action[4])
        return yaw_rad

    def solve_top_down_camera(self, camera_position: np.ndarray, yaw_rad: float) -> np.ndarray:
        """(7,) arm angles that put the wrist camera at world ``camera_position`` (m), looking straight
        down with hand yaw ``yaw_rad``.

        Teleports the joints while it re-solves IK from its own solution (sub-millimetre result);
        :meth:`reset` to the returned angles before using them.
        """
        R_world_hand = Rotation.from_quat(top_down_quaternion(yaw_rad)).as_matrix()
        camera_offset_world = R_world_hand @ T_HAND_CAMERA[:3, 3]
        tcp_offset_world = R_world_hand @ np.array([0.0, 0.0, TCP_OFFSET_M])
        tcp = np.asarray(camera_position, dtype=np.float64) - camera_offset_world + tcp_offset_world
        wrist = wrist_angle_estimate(tcp - self.base_position, yaw_rad)
        arm = self.inverse_kinematics(tcp, yaw_rad, wrist_rad=wrist)
        for _ in range(4):  # IK from the solution again: converge to sub-millimetre
            self.reset(arm)
            arm = self.inverse_kinematics(tcp, yaw_rad, wrist_rad=wrist)
        return arm
