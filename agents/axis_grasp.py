"""The scripted two-descriptor axis-grasp agent (Kupcsik et al. 2021, "Grasp Pose Prediction").

The agent tracks two keypoints on the part's axis ends (:func:`don_gym.perception.descriptor_sources.axis_end_targets`:
the outer-surface rings at 20 % and 80 % of the axial length) and turns them into the
``control="grasp"`` action ``[x, y, z, yaw]``:

1. Keypoints: the world points ``p1`` (minus end) and ``p2`` (plus end) where the two reference
   descriptors match, from ``obs["keypoint_points"]`` of a :class:`~don_gym.wrappers.KeypointObservation`
   made by :meth:`AxisGraspAgent.wrap` (or computed here from ``obs["descriptors"]``).
2. Surface to axis: the soft match lands in the middle of each ring's visible arc, i.e. on the
   camera ray through the axis, and the depth there is the ring's surface, one ring radius ``r_k``
   in front of the axis along that ray's direction across the axis. So the axis point is
   ``q_k = p_k + r_k * perp(ray_k) / |perp(ray_k)|``, with ``perp`` the component across the axis
   direction ``(p2 - p1)`` (iterated once with the corrected axis, which matters only when the two
   radii differ). The camera centre is the *reported* camera pose's, as a real robot would know it.
3. Grasp point: the linear combination of ``q1`` and ``q2`` at the axial position of the env's
   grasp point (:func:`don_gym.sim.task.grasp_point_object`, the midpoint of the axis ends moved
   onto a flat stretch of the profile, clear of its steps), which the agent knows from the object model. Its ``z`` is
   the axis height, which is what the grasp action expects (the TCP goes to the part's centre line).
4. Yaw: ``atan2`` of ``(q2 - q1)`` in the world xy-plane, the direction of the part's +axis.

With the oracle model, the error is that of the depth sensor, the reported camera pose and the
pixel grid only; learned models add their descriptor errors (and a flipped +axis when they confuse
the two ends, the paper's "upside down" failure).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from don_gym.errors import DonGymError
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import (
    DEFAULT_AXIS_FRACTIONS,
    AxisEndTargets,
    DescriptorSource,
    ReferenceFrame,
    axis_end_targets,
    default_reference_descriptors,
    descriptor_field_for,
    env_object_model,
    load_descriptor_source,
)
from don_gym.perception.keypoints import DEFAULT_CONFIDENCE_SIGMA, DEFAULT_SOFT_TEMPERATURE
from don_gym.sim.task import grasp_axial_position_m
from don_gym.wrappers.keypoints import KeypointObservation, KeypointSettings


def _unit(v: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise DonGymError("the two keypoints coincide; the axis direction is undefined")
    return v / norm


def surface_to_axis(
    points_world: np.ndarray, camera_position_world: np.ndarray, radii_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Step 2 of the module docstring: the two ring keypoints on the seen surface (2, 3), world metres, moved
    one ring radius each (``radii_m`` (2,)) onto the part's axis, away from the camera centre (3,) across the
    axis. Returns the (2, 3) axis points and the unit +axis direction (minus end to plus end)."""
    p = np.asarray(points_world, dtype=np.float64).reshape(2, 3)
    camera = np.asarray(camera_position_world, dtype=np.float64).reshape(3)
    radii = np.asarray(radii_m, dtype=np.float64).reshape(2)
    axis_points = p.copy()
    direction = _unit(p[1] - p[0])
    for _ in range(2):
        for k in range(2):
            ray = p[k] - camera
            across = ray - (ray @ direction) * direction
            axis_points[k] = p[k] + radii[k] * _unit(across)
        direction = _unit(axis_points[1] - axis_points[0])
    return axis_points, direction


def axis_grasp_action(
    points_world: np.ndarray, camera_position_world: np.ndarray, targets: AxisEndTargets, grasp_axial_m: float
) -> np.ndarray:
    """Grasp action ``[x, y, z, yaw]`` (float32) from the two ring keypoints (2, 3) of ``targets`` seen from the
    camera centre (3,): the axis point at axial position ``grasp_axial_m`` (m from the centre of mass along the
    +axis) and the world yaw of the +axis (steps 2-4 of the module docstring)."""
    axis_points, direction = surface_to_axis(points_world, camera_position_world, targets.radii_m)
    t1, t2 = targets.axial_positions_m
    s = (float(grasp_axial_m) - t1) / (t2 - t1)
    grasp = axis_points[0] + s * (axis_points[1] - axis_points[0])
    yaw = float(np.arctan2(direction[1], direction[0]))
    return np.array([grasp[0], grasp[1], grasp[2], yaw], dtype=np.float32)


class AxisGraspAgent:
    """Two tracked descriptors on the axis ends -> grasp point and +axis yaw (module docstring).

    ``agent = AxisGraspAgent(env, model)`` builds the agent for ``env``'s object and keeps
    ``agent.env``, the env wrapped so that observations carry the agent's keypoints
    (:meth:`wrap`); then ``action = agent.act(obs)`` on its observations.

    Args:
        env: a don_gym env with images (``control="grasp"`` to act with the action).
        model: any model :class:`~don_gym.wrappers.DescriptorObservation` accepts (``"oracle"``, a
            shipped name, a checkpoint path, a DenseObjectNet, a DescriptorSource).
        reference_frame: frame to read the reference descriptors from (:class:`~don_gym.wrappers.ReferenceFrame`).
            None: the optimal field for the oracle and networks trained towards it, else the env reset
            at a fixed seed and pose (reset it after). Given, it is used for every model, which also
            takes out a supervised network's systematic bias (its own output at the rings, not the
            descriptors it was trained towards).
        fractions: axial fractions of the two keypoints
        (:func:`~don_gym.perception.descriptor_sources.axis_end_targets`).
        descriptor_dim: required descriptor size (None: the model's).
        window_m, temperature, confidence_sigma: keypoint matching (see
            :func:`don_gym.perception.keypoints.locate_keypoints`); window None = the rings' diameter.

    :meth:`from_parts` builds one without an env from an object, a source and reference descriptors.
    """

    def __init__(
        self,
        env: gym.Env,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        reference_frame: ReferenceFrame | None = None,
        fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS,
        descriptor_dim: int | None = None,
        window_m: float | None = None,
        temperature: float = DEFAULT_SOFT_TEMPERATURE,
        confidence_sigma: float = DEFAULT_CONFIDENCE_SIGMA,
    ) -> None:
        object_model = env_object_model(env)
        source = load_descriptor_source(model, object_model, descriptor_dim)
        field = source.field if source.reference_from_field else descriptor_field_for(object_model)
        targets = axis_end_targets(object_model, field, fractions)
        reference = default_reference_descriptors(source, targets, env, reference_frame)
        self._setup(object_model, source, reference, targets, window_m, temperature, confidence_sigma)
        #: ``env`` wrapped with this agent's keypoints (:meth:`wrap`).
        self.env: KeypointObservation | None = self.wrap(env)

    @classmethod
    def from_parts(
        cls,
        object_model: ObjectModel,
        source: DescriptorSource,
        reference_descriptors: np.ndarray,
        targets: AxisEndTargets | None = None,
        window_m: float | None = None,
        temperature: float = DEFAULT_SOFT_TEMPERATURE,
        confidence_sigma: float = DEFAULT_CONFIDENCE_SIGMA,
    ) -> AxisGraspAgent:
        """An agent from its parts, without an env (``agent.env`` is None): ``reference_descriptors``
        (2, D) are ``source``'s descriptors of ``targets`` (None: :func:`axis_end_targets` of the object)."""
        agent = cls.__new__(cls)
        agent._setup(object_model, source, reference_descriptors, targets, window_m, temperature, confidence_sigma)
        agent.env = None
        return agent

    def _setup(
        self,
        object_model: ObjectModel,
        source: DescriptorSource,
        reference_descriptors: np.ndarray,
        targets: AxisEndTargets | None,
        window_m: float | None,
        temperature: float,
        confidence_sigma: float,
    ) -> None:
        self.object_model = object_model
        self.source = source
        self.targets = targets if targets is not None else axis_end_targets(object_model)
        reference = np.asarray(reference_descriptors, dtype=np.float32)
        if reference.shape != (2, source.descriptor_dim):
            raise DonGymError(
                f"reference_descriptors has shape {reference.shape}: expected (2, {source.descriptor_dim}), "
                f"two descriptors of the {source.method!r} model's length {source.descriptor_dim}"
            )
        self.reference_descriptors = reference
        #: How the two keypoints are located, here and in :meth:`wrap`'s wrapper alike.
        self.settings = KeypointSettings(
            self.targets.window_m if window_m is None else float(window_m), float(temperature), float(confidence_sigma)
        )
        #: Axial position (m from the centre of mass along +axis) the grasp aims at.
        self.grasp_axial_m = grasp_axial_position_m(object_model)

    @property
    def method(self) -> str:
        return self.source.method

    def wrap(self, env: gym.Env, keep_images: bool = True) -> KeypointObservation:
        """``env`` with observations carrying this agent's two keypoints (same model and references)."""
        return KeypointObservation(
            env,
            self.source,
            self.reference_descriptors,
            keep_images=keep_images,
            window_m=self.settings.window_m,
            temperature=self.settings.temperature,
            confidence_sigma=self.settings.confidence_sigma,
            min_radius_px=self.settings.min_radius_px,
            max_radius_px=self.settings.max_radius_px,
            border_margin_px=self.settings.border_margin_px,
        )

    # ----------------------------------------------------------------- acting
    def keypoints(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """(2, 3) world points of the minus-end and plus-end keypoints of one observation."""
        if "keypoint_points" in obs:
            points = np.asarray(obs["keypoint_points"], dtype=np.float64)
            if points.shape != (2, 3):
                raise DonGymError(
                    f"obs['keypoint_points'] has shape {points.shape}: expected (2, 3); "
                    "wrap the env with agent.wrap(env)"
                )
            return points
        if "descriptors" in obs and "depth" in obs:
            found = self.settings.locate(obs, self.source, self.reference_descriptors)
            return found.points_world
        raise DonGymError(
            "observation has neither 'keypoint_points' nor 'descriptors'; wrap the env with agent.wrap(env)"
        )

    def action_from_keypoints(self, points_world: np.ndarray, camera_position_world: np.ndarray) -> np.ndarray:
        """Grasp action ``[x, y, z, yaw]`` (float32) from the two keypoints (2, 3) and the camera centre (3,)."""
        return axis_grasp_action(points_world, camera_position_world, self.targets, self.grasp_axial_m)

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The grasp-mode action (4,) float32 for one observation."""
        camera = np.asarray(obs["camera_pose"], dtype=np.float64)[:3, 3]
        return self.action_from_keypoints(self.keypoints(obs), camera)

    def predict(
        self,
        observation: Mapping[str, np.ndarray],
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Stable-Baselines3-style ``(action, None)``; a batch of observations (leading axis) gives (N, 4)."""
        pose = np.asarray(observation["camera_pose"])
        if pose.ndim == 2:
            return self.act(observation), None
        actions = [self.act({k: np.asarray(v)[i] for k, v in observation.items()}) for i in range(len(pose))]
        return np.stack(actions), None

    def __repr__(self) -> str:
        return f"AxisGraspAgent(object={self.object_model.name!r}, method={self.method!r})"
