"""Flat-vector observations and normalised grasp actions for RL policies over keypoint observations.

:class:`KeypointFeatures` flattens what :class:`~don_gym.wrappers.KeypointObservation` adds (and the
robot state) for an MLP policy; :class:`KeypointGraspAction` maps a policy's [-1, 1]^n action to a
``control="grasp"`` action in a frame set by the keypoints. Used by :mod:`don_gym.agents.rl`. The pure functions
(:func:`robot_features`, :func:`two_scale_offsets`, :func:`axis_in_hand`, :func:`hand_keypoint_features`) are the
hand-frame encoding (``encoding="hand"``) that the imitation benchmark's policies read too.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.perception.descriptor_sources import axis_end_targets, env_object_model
from don_gym.sim.task import TABLE_TOP_Z_M, WORKSPACE_M

__all__ = [
    "ACTION_FRAMES",
    "AXIS_OFFSET_M",
    "AXIS_YAW_RAD",
    "ENCODINGS",
    "GRASP_OFFSET_XY_M",
    "GRASP_OFFSET_Z_M",
    "KEYPOINT_OFFSET_UNIT_M",
    "MIN_CONFIDENCE",
    "NEAR_UNIT_M",
    "POSITION_UNIT_M",
    "WORKSPACE_CENTRE_M",
    "KeypointFeatures",
    "KeypointGraspAction",
    "axis_in_hand",
    "hand_keypoint_features",
    "hand_rotation",
    "keypoint_centroid",
    "robot_features",
    "two_scale_offsets",
]

#: ``frame`` values of :class:`KeypointGraspAction`.
ACTION_FRAMES = ("axis", "keypoints", "world")
#: Length unit (m) of positions in the flat observations, except keypoints relative to their centroid.
POSITION_UNIT_M = 0.05
#: Length unit (m) of keypoints relative to their centroid in the flat observations.
KEYPOINT_OFFSET_UNIT_M = 0.01
#: Unit (m) of the near-field copy of offsets from the TCP (``encoding="hand"``, :func:`two_scale_offsets`).
NEAR_UNIT_M = 0.01
#: ``encoding`` values of :class:`KeypointFeatures`.
ENCODINGS = ("plain", "hand")
#: Workspace centre (m, world): the reference of absolute positions in the flat observations.
WORKSPACE_CENTRE_M = np.array(
    [(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2, TABLE_TOP_Z_M]
)
#: Keypoint action frame: largest offset (m) of the grasp point from the keypoint centroid in x, y
#: and in z. The toolcap is 34 mm across and 40 mm long, and a grasp succeeds within about 1 cm.
GRASP_OFFSET_XY_M = 0.05
GRASP_OFFSET_Z_M = 0.03
#: Axis action frame: largest offset (m) of the grasp point from the keypoints' midpoint along and across
#: their axis and in z, and largest turn (rad) of the grasp yaw from the keypoints' axis direction.
#: Residuals: action 0 grasps the keypoints' midpoint across their axis, which the scripted agent's
#: geometry refines by millimetres only.
AXIS_OFFSET_M = 0.02
AXIS_YAW_RAD = np.pi / 6
#: Keypoints with a confidence at or below this count as not found.
MIN_CONFIDENCE = 0.0


# ------------------------------------------------------------------------------ observations
def hand_rotation(ee_pose: np.ndarray) -> np.ndarray:
    """(3, 3) R_world_hand of a TCP pose ``ee_pose`` (7,): x, y, z (m, world), qx, qy, qz, qw."""
    return Rotation.from_quat(np.asarray(ee_pose, dtype=np.float64).reshape(7)[3:]).as_matrix()


def robot_features(ee_pose: np.ndarray, joint_positions: np.ndarray, gripper_width: np.ndarray) -> np.ndarray:
    """(7,) the robot's own state for a policy: TCP position (``ee_pose`` (7,), in :data:`POSITION_UNIT_M`), the
    hand's yaw as (cos, sin) (the top-down hand's quaternion flips sign as the yaw passes pi), joint 7's angle
    (``joint_positions`` (9,) rad, / pi: which way the wrist can still turn) and the finger opening
    (``gripper_width`` (1,) m, / 4 cm)."""
    ee = np.asarray(ee_pose, dtype=np.float64).reshape(7)
    hand_x = hand_rotation(ee)[:2, 0]
    wrist = np.asarray(joint_positions, dtype=np.float64).reshape(-1)[6:7] / np.pi
    width = np.asarray(gripper_width, dtype=np.float64).reshape(1) / 0.04
    return np.concatenate([ee[:3] / POSITION_UNIT_M, hand_x / max(np.linalg.norm(hand_x), 1e-9), wrist, width])


def axis_in_hand(axis_world: np.ndarray, R_world_hand: np.ndarray) -> np.ndarray:
    """(4,) the part's axis direction ``axis_world`` (3,) seen from the hand (``R_world_hand`` (3, 3)): its angle a
    from hand x in the hand's xy plane as (cos a, sin a, cos 2a, sin 2a). The grasp turns the hand until a is 0 or
    pi (fingers across the axis); the doubled angle is the same for both, the plain one tells them apart: turning
    is then a smooth function of these."""
    local = np.asarray(R_world_hand, dtype=np.float64).T @ np.asarray(axis_world, dtype=np.float64)
    angle = float(np.arctan2(local[1], local[0]))
    return np.array([np.cos(angle), np.sin(angle), np.cos(2 * angle), np.sin(2 * angle)])


def two_scale_offsets(offsets_m: np.ndarray) -> np.ndarray:
    """Offsets (..., 3) m from the TCP at two scales, flat (2 * size,): in :data:`POSITION_UNIT_M` across the
    workspace, and squashed at :data:`NEAR_UNIT_M` (``tanh``), which spreads the last centimetres of the approach,
    where the grasp needs millimetres, over the whole range of a unit."""
    offsets = np.asarray(offsets_m, dtype=np.float64)
    return np.concatenate([(offsets / POSITION_UNIT_M).ravel(), np.tanh(offsets / NEAR_UNIT_M).ravel()])


def hand_keypoint_features(observation: dict[str, np.ndarray], age_unit_steps: float) -> np.ndarray:
    """(7 + 14 K + 4,) float64: a keypoint observation in the hand's terms (``encoding="hand"``).

    ``observation``: ``ee_pose`` (7,), ``joint_positions`` (9,), ``gripper_width`` (1,), ``keypoint_points``
    (K, 3) world m, ``keypoint_confidence`` (K,), ``keypoint_memory_points`` (K, 3) world m and ``keypoint_age``
    (K,) steps (:class:`~don_gym.wrappers.KeypointMemory`). Output: :func:`robot_features`; the keypoints found
    now, relative to the TCP at two scales (:func:`two_scale_offsets`, zeros where not found); confidences; the
    remembered places relative to the TCP at two scales; ages in ``age_unit_steps``; the remembered axis (first
    to last keypoint) seen from the hand (:func:`axis_in_hand`)."""
    tcp = np.asarray(observation["ee_pose"], dtype=np.float64).reshape(7)[:3]
    confidence = np.asarray(observation["keypoint_confidence"], dtype=np.float64).reshape(-1)
    points = np.asarray(observation["keypoint_points"], dtype=np.float64).reshape(-1, 3)
    found = _found(points, confidence)
    remembered = np.asarray(observation["keypoint_memory_points"], dtype=np.float64).reshape(-1, 3)
    age = np.asarray(observation["keypoint_age"], dtype=np.float64).reshape(-1) / float(age_unit_steps)
    axis = axis_in_hand(remembered[-1] - remembered[0], hand_rotation(observation["ee_pose"]))
    return np.concatenate([
        robot_features(observation["ee_pose"], observation["joint_positions"], observation["gripper_width"]),
        two_scale_offsets(np.where(found[:, None], points - tcp, 0.0)),
        np.where(found, confidence, 0.0),
        two_scale_offsets(remembered - tcp),
        age,
        axis,
    ])  # fmt: skip


def keypoint_centroid(points_m: np.ndarray, confidence: np.ndarray) -> np.ndarray | None:
    """Confidence-weighted mean (3,) of the found keypoints (K, 3), or None when none was found."""
    found = _found(points_m, confidence)
    if not found.any():
        return None
    weights = confidence[found].astype(np.float64)
    return (points_m[found].astype(np.float64) * weights[:, None]).sum(axis=0) / weights.sum()


def _found(points_m: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    return np.isfinite(points_m).all(axis=1) & np.isfinite(confidence) & (confidence > MIN_CONFIDENCE)


class KeypointFeatures(gym.ObservationWrapper):
    """Flatten a keypoint observation into the float32 vector an MLP policy reads.

    Input: a Dict observation with ``keypoint_points`` (K, 3) world m and ``keypoint_confidence``
    (K,) (from :class:`don_gym.wrappers.KeypointObservation`) and, for ``relative_to="tcp"`` or
    ``robot_state=True``, ``ee_pose`` (7,) and ``gripper_width`` (1,).

    Output, in this order (lengths in units of :data:`POSITION_UNIT_M` unless said otherwise):

    - keypoint centroid relative to the workspace centre (3,),
    - each keypoint relative to the centroid (``relative_to="centroid"``, in units of
      :data:`KEYPOINT_OFFSET_UNIT_M`) or to the TCP (``"tcp"``) (K*3,),
    - confidences (K,),
    - with ``robot_state``: TCP position relative to the workspace centre (3,), TCP quaternion
      (4,), gripper width in units of 4 cm (1,),
    - with the keys of :class:`~don_gym.wrappers.KeypointMemory` in the observation: each keypoint's last seen
      position relative to the TCP (``relative_to="tcp"``) or the workspace centre (K*3,), and its age as a
      fraction of the memory's ``max_age_steps`` (K,).

    Keypoints not found (confidence 0 or non-finite) read as zeros with confidence 0; the
    centroid of a frame without any keypoint reads as zeros. The units make the network inputs of
    order one; keypoints relative to their centroid get the finer unit because the yaw the policy
    must read off them is in their difference (the toolcap's two keypoints are 2.4 cm apart).

    ``encoding="hand"`` (with ``relative_to="tcp"``, ``robot_state=True`` and the memory's keys) gives instead
    :func:`hand_keypoint_features`, the imitation benchmark's keypoint input: the hand's yaw as (cos, sin) rather
    than a quaternion whose sign flips, offsets from the TCP also at a near-field scale, and the remembered axis
    seen from the hand, with ages in the memory's ``max_age_steps``.
    """

    def __init__(
        self, env: gym.Env, relative_to: str = "centroid", robot_state: bool = False, encoding: str = "plain"
    ) -> None:
        super().__init__(env)
        if relative_to not in ("centroid", "tcp"):
            raise DonGymError(f"relative_to={relative_to!r}: expected 'centroid' or 'tcp'")
        if encoding not in ENCODINGS:
            raise DonGymError(f"encoding={encoding!r} is unknown; expected one of {list(ENCODINGS)}")
        if encoding == "hand" and (relative_to != "tcp" or not robot_state):
            raise DonGymError(
                "encoding='hand' describes keypoints from the hand: it needs relative_to='tcp' and "
                f"robot_state=True, not relative_to={relative_to!r} and robot_state={robot_state!r}"
            )
        space = env.observation_space
        needed = ["keypoint_points", "keypoint_confidence"]
        if relative_to == "tcp" or robot_state:
            needed += ["ee_pose", "gripper_width"]
        if encoding == "hand":
            needed += ["joint_positions", "keypoint_memory_points", "keypoint_age"]
        missing = [key for key in needed if not isinstance(space, spaces.Dict) or key not in space.spaces]
        if missing:
            raise DonGymError(
                f"KeypointFeatures needs observation keys {missing}: wrap the env in "
                "don_gym.wrappers.KeypointObservation first"
                + (
                    " and don_gym.wrappers.KeypointMemory over it (encoding='hand' reads the memory)"
                    if encoding == "hand"
                    else ""
                )
            )
        self.relative_to = relative_to
        self.robot_state = robot_state
        self.encoding = encoding
        self.num_keypoints = int(space["keypoint_points"].shape[0])
        #: The observations carry :class:`~don_gym.wrappers.KeypointMemory`'s keys (and the vector them).
        self.memory = "keypoint_memory_points" in space.spaces and "keypoint_age" in space.spaces
        self._max_age = float(space["keypoint_age"].high.max()) if self.memory else 1.0
        size = 3 + 4 * self.num_keypoints + (8 if robot_state else 0) + (4 * self.num_keypoints if self.memory else 0)
        if encoding == "hand":
            size = 11 + 14 * self.num_keypoints
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)

    def observation(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        if self.encoding == "hand":
            return hand_keypoint_features(observation, self._max_age).astype(np.float32)
        points = np.asarray(observation["keypoint_points"], dtype=np.float64).reshape(-1, 3)
        confidence = np.asarray(observation["keypoint_confidence"], dtype=np.float64).reshape(-1)
        found = _found(points, confidence)
        centroid = keypoint_centroid(points, confidence)
        if self.relative_to == "tcp":
            reference, unit = np.asarray(observation["ee_pose"], dtype=np.float64)[:3], POSITION_UNIT_M
        else:
            reference = WORKSPACE_CENTRE_M if centroid is None else centroid
            unit = KEYPOINT_OFFSET_UNIT_M
        relative = np.where(found[:, None], points - reference, 0.0) / unit
        parts = [
            np.zeros(3) if centroid is None else (centroid - WORKSPACE_CENTRE_M) / POSITION_UNIT_M,
            relative.reshape(-1),
            np.where(found, confidence, 0.0),
        ]
        if self.robot_state:
            ee_pose = np.asarray(observation["ee_pose"], dtype=np.float64)
            parts += [
                (ee_pose[:3] - WORKSPACE_CENTRE_M) / POSITION_UNIT_M,
                ee_pose[3:7],
                np.asarray(observation["gripper_width"], dtype=np.float64).reshape(1) / 0.04,
            ]
        if self.memory:
            memory = np.asarray(observation["keypoint_memory_points"], dtype=np.float64).reshape(-1, 3)
            origin = np.asarray(observation["ee_pose"], dtype=np.float64)[:3] if self.relative_to == "tcp" else None
            origin = WORKSPACE_CENTRE_M if origin is None else origin
            age = np.asarray(observation["keypoint_age"], dtype=np.float64).reshape(-1)
            parts += [((memory - origin) / POSITION_UNIT_M).reshape(-1), age / self._max_age]
        return np.concatenate(parts).astype(np.float32)


# -------------------------------------------------------------------------------- actions
class KeypointGraspAction(gym.Wrapper):
    """Grasp-mode actions in [-1, 1]^n for a policy, in a frame set by the reset observation's keypoints.

    ``frame="axis"`` (n = 4: along, across, z, turn): residuals about the keypoints' own grasp. The
    frame's origin is the midpoint of the two keypoints lowered by ``axis_depth_m`` (the keypoints lie
    on the part's surface facing the camera, which looks down, about one ring radius above the axis
    the grasp aims at; None: the mean radius of the env's part's axis-end rings); the grasp point is
    the origin plus ``along`` and ``across`` times :data:`AXIS_OFFSET_M` along and across the
    keypoints' horizontal axis direction and ``z`` times :data:`AXIS_OFFSET_M` up; the yaw is that of
    the keypoint axis (minus to plus end) plus ``turn`` times :data:`AXIS_YAW_RAD`. Action 0 is a
    sound grasp, so a policy starts from one and learns the corrections; without two found keypoints
    the frame is the keypoint centroid (or the workspace centre at table height) with yaw 0.

    ``frame="keypoints"`` (n = 5: x, y, z, cos yaw, sin yaw): the grasp point is the keypoint centroid
    plus (x, y) * :data:`GRASP_OFFSET_XY_M` and z * :data:`GRASP_OFFSET_Z_M`; a frame without keypoints
    falls back to the workspace centre at table height. ``frame="world"`` (n = 5): (x, y, z) span the
    env's action box linearly. In these two, the yaw of the believed +axis is ``atan2(sin, cos)``
    (a zero vector reads as yaw 0) in the world, which the policy must work out from the keypoints.

    Must wrap an env whose observations still hold ``keypoint_points`` and ``keypoint_confidence``
    (put it below :class:`KeypointFeatures`).
    """

    def __init__(self, env: gym.Env, frame: str = "keypoints", axis_depth_m: float | None = None):
        super().__init__(env)
        if frame not in ACTION_FRAMES:
            raise DonGymError(f"action_frame={frame!r} is unknown; expected one of {list(ACTION_FRAMES)}")
        if getattr(env.unwrapped, "control", None) != "grasp":
            raise DonGymError("KeypointGraspAction needs an env with control='grasp'")
        self.frame = frame
        if frame == "axis" and axis_depth_m is None:
            axis_depth_m = float(np.mean(axis_end_targets(env_object_model(env)).radii_m))
        self.axis_depth_m = float(axis_depth_m or 0.0)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4 if frame == "axis" else 5,), dtype=np.float32)
        self._centroid = WORKSPACE_CENTRE_M.copy()
        self._axis_origin = WORKSPACE_CENTRE_M.copy()
        self._axis_yaw = 0.0

    def reset(self, **kwargs: Any):
        observation, info = self.env.reset(**kwargs)
        points = np.asarray(observation["keypoint_points"], dtype=np.float64)
        confidence = np.asarray(observation["keypoint_confidence"], dtype=np.float64)
        centroid = keypoint_centroid(points, confidence)
        self._centroid = WORKSPACE_CENTRE_M.copy() if centroid is None else centroid
        self._axis_origin, self._axis_yaw = self._centroid.copy(), 0.0
        found = _found(points, confidence)
        if len(points) >= 2 and found[:2].all():
            direction = points[1] - points[0]
            if np.hypot(direction[0], direction[1]) > 1e-6:
                self._axis_origin = 0.5 * (points[0] + points[1]) - np.array([0.0, 0.0, self.axis_depth_m])
                self._axis_yaw = float(np.arctan2(direction[1], direction[0]))
        return observation, info

    def grasp_action(self, action: np.ndarray) -> np.ndarray:
        """The env action [x, y, z, yaw] (world m, rad) of a normalised action."""
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        if action.shape != self.action_space.shape:
            raise DonGymError(f"action has shape {action.shape}, expected {self.action_space.shape}")
        if self.frame == "axis":
            along = np.array([np.cos(self._axis_yaw), np.sin(self._axis_yaw), 0.0])
            across = np.array([-along[1], along[0], 0.0])
            offset = AXIS_OFFSET_M * (action[0] * along + action[1] * across + action[2] * np.array([0.0, 0.0, 1.0]))
            yaw = float(np.angle(np.exp(1j * (self._axis_yaw + action[3] * AXIS_YAW_RAD))))
            return np.array([*(self._axis_origin + offset), yaw], dtype=np.float32)
        if self.frame == "keypoints":
            offset = action[:3] * np.array([GRASP_OFFSET_XY_M, GRASP_OFFSET_XY_M, GRASP_OFFSET_Z_M])
            point = self._centroid + offset
        else:
            low, high = self.env.action_space.low[:3], self.env.action_space.high[:3]
            point = low + (action[:3] + 1.0) * 0.5 * (high - low)
        yaw = float(np.arctan2(action[4], action[3]))
        return np.array([*point, yaw], dtype=np.float32)

    def step(self, action: np.ndarray):
        return self.env.step(self.grasp_action(action))
