"""Flat-vector observations and normalised grasp actions for RL policies over keypoint observations.

:class:`KeypointFeatures` flattens what :class:`~don_gym.wrappers.KeypointObservation` adds (and the
robot state) for an MLP policy; :class:`KeypointGraspAction` maps a policy's [-1, 1]^n action to a
``control="grasp"`` action in a frame set by the keypoints. Used by :mod:`don_gym.agents.rl`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.perception.descriptor_sources import axis_end_targets, env_object_model
from don_gym.sim.task import TABLE_TOP_Z_M, WORKSPACE_M

#: ``frame`` values of :class:`KeypointGraspAction`.
ACTION_FRAMES = ("axis", "keypoints", "world")
#: Length unit (m) of positions in the flat observations, except keypoints relative to their centroid.
POSITION_UNIT_M = 0.05
#: Length unit (m) of keypoints relative to their centroid in the flat observations.
KEYPOINT_OFFSET_UNIT_M = 0.01
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
    """

    def __init__(self, env: gym.Env, relative_to: str = "centroid", robot_state: bool = False):
        super().__init__(env)
        if relative_to not in ("centroid", "tcp"):
            raise DonGymError(f"relative_to={relative_to!r}: expected 'centroid' or 'tcp'")
        space = env.observation_space
        needed = ["keypoint_points", "keypoint_confidence"]
        if relative_to == "tcp" or robot_state:
            needed += ["ee_pose", "gripper_width"]
        missing = [key for key in needed if not isinstance(space, spaces.Dict) or key not in space.spaces]
        if missing:
            raise DonGymError(
                f"KeypointFeatures needs observation keys {missing}: wrap the env in "
                "don_gym.wrappers.KeypointObservation first"
            )
        self.relative_to = relative_to
        self.robot_state = robot_state
        self.num_keypoints = int(space["keypoint_points"].shape[0])
        #: The observations carry :class:`~don_gym.wrappers.KeypointMemory`'s keys (and the vector them).
        self.memory = "keypoint_memory_points" in space.spaces and "keypoint_age" in space.spaces
        self._max_age = float(space["keypoint_age"].high.max()) if self.memory else 1.0
        size = 3 + 4 * self.num_keypoints + (8 if robot_state else 0) + (4 * self.num_keypoints if self.memory else 0)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)

    def observation(self, observation: dict[str, np.ndarray]) -> np.ndarray:
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
