"""The pose-grasp agent: the same descriptors as :class:`~don_gym.agents.AxisGraspAgent`, used through a 6D
pose estimate instead of two keypoints (issue #34: "the two uses of the same descriptors").

Per observation: the part's pose in the camera frame from the descriptor image and the depth
(:func:`don_gym.perception.pose.estimate_pose`: matches to the part's surface, 3D-3D RANSAC and ICP), into the world
with the *reported* camera pose (as a real robot knows it, as the axis agent does). The grasp point is the
env's (:func:`don_gym.sim.task.grasp_axial_position_m`: along the +axis from the centre of mass) placed by
that pose, on the axis, so its ``z`` is the axis height the grasp action expects; the yaw is that of the
placed +axis in the world xy-plane. A symmetric pose is only defined up to a rotation about the axis,
which changes neither.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform
from don_gym.learning.model import DenseObjectNet
from don_gym.perception.descriptor_sources import (
    REFERENCE_SEED,
    DescriptorSource,
    ReferenceFrame,
    env_object_model,
    load_descriptor_source,
)
from don_gym.perception.pose import PoseConfig, PoseEstimate, PoseTargets, estimate_pose, pose_targets_for
from don_gym.sim.task import grasp_axial_position_m
from don_gym.wrappers.descriptors import DescriptorObservation

#: Fixed poses of the env whose frames (at :data:`~don_gym.perception.descriptor_sources.REFERENCE_SEED`) give a
#: network its reference views: the part lying two ways.
REFERENCE_POSE_IDS: tuple[int, ...] = (0, 4)


def reference_views(
    env: gym.Env, source: DescriptorSource, pose_ids: Sequence[int] = REFERENCE_POSE_IDS
) -> list[tuple[np.ndarray, CameraIntrinsics, np.ndarray]]:
    """``(descriptor_image, intrinsics, T_camera_object)`` of the env reset at the reference seed and each of
    ``pose_ids`` (:meth:`ReferenceFrame.from_env`; reset the env after), the TRUE poses."""
    views = []
    for pose_id in pose_ids:
        frame = ReferenceFrame.from_env(env, REFERENCE_SEED, pose_id)
        T_camera_object = invert_transform(np.asarray(frame.info["T_world_camera"])) @ np.asarray(
            frame.info["T_world_object"]
        )
        intrinsics = CameraIntrinsics.from_array(frame.obs["camera_intrinsics"])
        views.append((source.descriptor_image(frame.obs, frame.info), intrinsics, T_camera_object))
    return views


class PoseGraspAgent:
    """A 6D pose from the descriptors -> grasp point and +axis yaw (module docstring).

    ``agent = PoseGraspAgent(env, model)`` builds the agent for ``env``'s object and keeps ``agent.env``,
    the env wrapped so that observations carry the model's descriptors (:meth:`wrap`); then
    ``action = agent.act(obs)`` on its observations.

    Args:
        env: a don_gym env with images and depth (``control="grasp"`` to act with the action).
        model: any model :func:`~don_gym.perception.descriptor_sources.load_descriptor_source` accepts.
        config: pose estimation settings.
        pose_ids: the env's fixed poses whose frames give the reference views (networks; the oracle matches
            its field and needs none).
    """

    def __init__(
        self,
        env: gym.Env,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        config: PoseConfig | None = None,
        pose_ids: Sequence[int] = REFERENCE_POSE_IDS,
    ) -> None:
        self.object_model = env_object_model(env)
        self.source = load_descriptor_source(model, self.object_model)
        views = [] if self.source.method == "oracle" else reference_views(env, self.source, pose_ids)
        self.targets: PoseTargets = pose_targets_for(self.source, views)
        self.config = config if config is not None else PoseConfig()
        #: Axial position (m from the centre of mass along +axis) the grasp aims at.
        self.grasp_axial_m = grasp_axial_position_m(self.object_model)
        #: The last observation's estimate (None before the first).
        self.last_estimate: PoseEstimate | None = None
        #: ``env`` wrapped with this agent's descriptors (:meth:`wrap`).
        self.env: DescriptorObservation = self.wrap(env)

    @property
    def method(self) -> str:
        return self.source.method

    def wrap(self, env: gym.Env) -> DescriptorObservation:
        """``env`` with observations carrying this agent's descriptors (same model)."""
        return DescriptorObservation(env, self.source)

    def T_world_object(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """(4, 4) estimated pose of the part in the world (reported camera pose); DonGymError when none."""
        for key in ("descriptors", "depth", "camera_intrinsics", "camera_pose"):
            if key not in obs:
                raise DonGymError(f"observation has no {key!r}; wrap the env with agent.wrap(env)")
        estimate = estimate_pose(
            obs["descriptors"],
            self.targets,
            CameraIntrinsics.from_array(obs["camera_intrinsics"]),
            np.asarray(obs["depth"]),
            config=self.config,
        )
        self.last_estimate = estimate
        if not estimate.found:
            raise DonGymError(
                f"no pose of the part found ({estimate.correspondences} matches, fewer than "
                f"{self.config.min_inliers} agree)"
            )
        return np.asarray(obs["camera_pose"], dtype=np.float64) @ estimate.T_camera_object

    def action_from_pose(self, T_world_object: np.ndarray) -> np.ndarray:
        """Grasp action ``[x, y, z, yaw]`` (float32) from the part's world pose (4, 4)."""
        T = np.asarray(T_world_object, dtype=np.float64)
        plus_axis = np.asarray(self.object_model.plus_axis, dtype=np.float64)
        plus_axis = plus_axis / np.linalg.norm(plus_axis)
        axis = T[:3, :3] @ plus_axis
        grasp = T[:3, :3] @ (self.object_model.center_of_mass + self.grasp_axial_m * plus_axis) + T[:3, 3]
        yaw = float(np.arctan2(axis[1], axis[0]))
        return np.array([grasp[0], grasp[1], grasp[2], yaw], dtype=np.float32)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The grasp-mode action (4,) float32 for one observation."""
        return self.action_from_pose(self.T_world_object(obs))

    def predict(
        self,
        observation: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Stable-Baselines3-style ``(action, None)`` for one observation."""
        return self.act(observation), None

    def __repr__(self) -> str:
        return f"PoseGraspAgent(object={self.object_model.name!r}, method={self.method!r})"
