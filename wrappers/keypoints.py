"""Axis-end keypoint targets and the KeypointObservation wrapper.

:func:`axis_end_targets` chooses, from the object model, the two surface keypoints of the
paper's axis grasp (Kupcsik et al. 2021, "Grasp Pose Prediction"). Rule: along the +axis (through
the centre of mass), take the axial levels at ``fractions`` (default 20 % and 80 %) of the part's
axial length, from the minus end; at each, the *outer* surface there: mesh vertices within
``slab`` of the nearest level that carries outer-surface vertices, and whose distance from the axis
is within 5 % of the largest at that level (so a bore or an end face's inner rim is never chosen).
On a part lying on its side, the outer surface at both levels faces up, whatever the roll. With
symmetric (GISIF) descriptors all points of such a ring share one descriptor, so the keypoint is
the whole ring: its reference descriptor is the mean of the field over it, and the ring's axial
position and radius let an agent go from the seen surface back to the axis. 20 %/80 % keep both
rings off the end faces and edges (where descriptors blend into the background in learned nets)
while leaving them as far apart as that allows, for an accurate axis direction.

:class:`KeypointObservation` adds, for K reference descriptors, ``keypoint_pixels`` (K, 2),
``keypoint_points`` (K, 3) in the world and ``keypoint_confidence`` (K,), using
:func:`don_gym.keypoints.locate_keypoints` on the descriptor image of a
:class:`~don_gym.wrappers.descriptors.DescriptorObservation`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.descriptors import DescriptorField
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics
from don_gym.keypoints import (
    DEFAULT_CONFIDENCE_SIGMA,
    DEFAULT_MAX_RADIUS_PX,
    DEFAULT_MIN_RADIUS_PX,
    DEFAULT_SOFT_TEMPERATURE,
    locate_keypoints,
)
from don_gym.model import DenseObjectNet
from don_gym.objects import ObjectModel
from don_gym.wrappers.descriptors import (
    DescriptorObservation,
    DescriptorSource,
    ReferenceFrame,
    descriptor_field_for,
    field_descriptors,
    reference_descriptors_for,
)

#: Axial fractions (from the minus end) of the two axis-end keypoints.
DEFAULT_AXIS_FRACTIONS = (0.2, 0.8)
#: Soft-match disc radius (m) for reference descriptors given by the user.
DEFAULT_WINDOW_M = 0.02
#: World-coordinate bound of ``keypoint_points`` (m); the env's poses use the same.
POINT_BOUND_M = 10.0
#: Keys dropped with ``keep_images=False``.
IMAGE_KEYS = ("rgb", "depth", "descriptors")


@dataclass(frozen=True)
class AxisEndTargets:
    """The two axis-end keypoints of an object (see the module docstring).

    Attributes:
        surface_points: two (N_k, 3) arrays of object-frame surface points in metres, minus end first.
        axial_positions_m: (2,) position of each ring along the +axis from the centre of mass.
        radii_m: (2,) mean distance of each ring's points from the axis.
        descriptors: (2, D) float32 mean optimal-field descriptor of each ring.
        fractions: the axial fractions asked for.
    """

    surface_points: tuple[np.ndarray, np.ndarray]
    axial_positions_m: np.ndarray
    radii_m: np.ndarray
    descriptors: np.ndarray
    fractions: tuple[float, float]

    @property
    def window_m(self) -> float:
        """Soft-match radius that spans a whole ring's visible arc from any point of it: its diameter."""
        return float(2.0 * np.max(self.radii_m))


def axis_end_targets(
    object_model: ObjectModel,
    field: DescriptorField | None = None,
    fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS,
    slab_m: float | None = None,
) -> AxisEndTargets:
    """The two axis-end keypoints of ``object_model`` (rule in the module docstring).

    Args:
        object_model: the part (its ``plus_axis`` and mesh).
        field: its optimal descriptor field (None: :func:`descriptor_field_for` with 3 dimensions).
        fractions: (minus-end, plus-end) axial fractions in (0, 1), the first smaller.
        slab_m: half-width of the axial slab of one ring (None: 1 % of the axial length, at least 0.1 mm).
    """
    f1, f2 = (float(f) for f in fractions)
    if not (0.0 < f1 < f2 < 1.0):
        raise DonGymError(f"fractions={fractions!r}: expected 0 < minus-end fraction < plus-end fraction < 1")
    field = field if field is not None else descriptor_field_for(object_model)
    axis = np.asarray(object_model.plus_axis, dtype=np.float64)
    vertices = np.asarray(object_model.mesh.vertices, dtype=np.float64)
    along = (vertices - object_model.center_of_mass) @ axis
    radius = np.linalg.norm((vertices - object_model.center_of_mass) - np.outer(along, axis), axis=1)
    length = float(along.max() - along.min())
    slab = float(slab_m) if slab_m is not None else max(0.01 * length, 1e-4)
    # Outer surface: within 5 % of the largest radius among vertices at (about) the same level.
    order = np.argsort(along)
    sorted_along = along[order]
    lo = np.searchsorted(sorted_along, along - slab, side="left")
    hi = np.searchsorted(sorted_along, along + slab, side="right")
    level_max = np.array([radius[order[a:b]].max() for a, b in zip(lo, hi, strict=True)])
    outer = radius >= 0.95 * level_max
    sets, positions, radii = [], [], []
    for fraction in (f1, f2):
        target = along.min() + fraction * length
        nearest = float(along[outer][np.argmin(np.abs(along[outer] - target))])
        chosen = outer & (np.abs(along - nearest) <= slab)
        sets.append(vertices[chosen])
        positions.append(float(along[chosen].mean()))
        radii.append(float(radius[chosen].mean()))
    descriptors = field_descriptors(field, object_model.mesh, sets)
    return AxisEndTargets(
        surface_points=(sets[0], sets[1]),
        axial_positions_m=np.asarray(positions),
        radii_m=np.asarray(radii),
        descriptors=descriptors,
        fractions=(f1, f2),
    )


def default_reference_descriptors(
    source: DescriptorSource, targets: AxisEndTargets, env: gym.Env | None, reference: ReferenceFrame | None = None
) -> np.ndarray:
    """(2, D) reference descriptors of the axis-end targets for ``source``: from the field when the
    source reproduces it, else from ``reference`` (or :meth:`ReferenceFrame.from_env` of ``env``)."""
    if reference is None and not source.reference_from_field:
        if env is None:
            raise DonGymError(f"a {source.method!r} model needs a reference frame or an env to take one from")
        reference = ReferenceFrame.from_env(env)
    return reference_descriptors_for(source, targets.surface_points, reference)


class KeypointObservation(DescriptorObservation):
    """Adds K tracked keypoints to each observation (and, by default, the descriptor image).

    Added keys: ``keypoint_pixels`` (K, 2) float32 soft-match pixel (u, v); ``keypoint_points``
    (K, 3) float32 world point in metres from the depth image (robust to holes, see
    :func:`don_gym.keypoints.robust_depth`; the camera centre if no depth is found within
    ``max_radius_px``); ``keypoint_confidence`` (K,) float32 in [0, 1], ``exp(-(d / sigma)^2)`` of the
    best-match descriptor distance ``d`` (0 without depth).

    Args:
        env: a don_gym env with images.
        model: as for :class:`DescriptorObservation`.
        reference_descriptors: (K, D) descriptors to track, D the model's. None: the two axis-end
            keypoints of :func:`axis_end_targets` (the :class:`~don_gym.agents.AxisGraspAgent`'s),
            their descriptors from the field or from ``reference_frame`` (see
            :func:`~don_gym.wrappers.descriptors.reference_descriptors_for`).
        keep_images: False drops ``rgb``, ``depth`` and ``descriptors`` for a compact observation.
        reference_frame: frame to read the default reference descriptors from; given, it is used for
            every model (None: the field where the model reproduces it, else the env reset at a fixed
            seed and pose, see :meth:`ReferenceFrame.from_env`).
        window_m: soft-match radius in metres (None: the rings' diameter for the default keypoints,
            :data:`DEFAULT_WINDOW_M` otherwise; 0: plain best match).
        temperature, confidence_sigma: descriptor-distance scales of the soft match and the confidence.
        descriptor_dim, occlusion_check: as for :class:`DescriptorObservation`.
        min_radius_px, max_radius_px: depth windows (:func:`don_gym.keypoints.robust_depth`).
    """

    def __init__(
        self,
        env: gym.Env,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        reference_descriptors: np.ndarray | None = None,
        *,
        keep_images: bool = True,
        reference_frame: ReferenceFrame | None = None,
        window_m: float | None = None,
        temperature: float = DEFAULT_SOFT_TEMPERATURE,
        confidence_sigma: float = DEFAULT_CONFIDENCE_SIGMA,
        descriptor_dim: int | None = None,
        occlusion_check: bool = True,
        min_radius_px: int = DEFAULT_MIN_RADIUS_PX,
        max_radius_px: int = DEFAULT_MAX_RADIUS_PX,
    ) -> None:
        # Recorded first: DescriptorObservation's own recording is then ignored (RecordConstructorArgs).
        gym.utils.RecordConstructorArgs.__init__(
            self,
            _disable_deepcopy=True,
            model=model,
            reference_descriptors=reference_descriptors,
            keep_images=keep_images,
            reference_frame=reference_frame,
            window_m=window_m,
            temperature=temperature,
            confidence_sigma=confidence_sigma,
            descriptor_dim=descriptor_dim,
            occlusion_check=occlusion_check,
            min_radius_px=min_radius_px,
            max_radius_px=max_radius_px,
        )
        super().__init__(env, model, descriptor_dim=descriptor_dim, occlusion_check=occlusion_check)
        dim = self.source.descriptor_dim
        if reference_descriptors is None:
            field = self.source.field if self.source.reference_from_field else None
            self.targets: AxisEndTargets | None = axis_end_targets(
                self.object_model, field or descriptor_field_for(self.object_model)
            )
            reference = default_reference_descriptors(self.source, self.targets, env, reference_frame)
            window = self.targets.window_m if window_m is None else float(window_m)
        else:
            self.targets = None
            reference = np.asarray(reference_descriptors, dtype=np.float32)
            if reference.ndim == 1:
                reference = reference[None]
            if reference.ndim != 2 or reference.shape[0] == 0 or reference.shape[1] != dim:
                raise DonGymError(
                    f"reference_descriptors has shape {reference.shape}: expected (K, {dim}), K descriptors of "
                    f"length {dim} like the {self.source.method!r} model's, got length "
                    f"{reference.shape[-1] if reference.ndim else 'scalar'}"
                )
            if not np.all(np.isfinite(reference)):
                raise DonGymError("reference_descriptors: contain NaN or infinite values")
            window = DEFAULT_WINDOW_M if window_m is None else float(window_m)
        if not (np.isfinite(window) and window >= 0):
            raise DonGymError(f"window_m={window_m!r}: expected a radius >= 0 in metres")
        self.reference_descriptors = reference
        self.window_m = window
        self.temperature = float(temperature)
        self.confidence_sigma = float(confidence_sigma)
        self.min_radius_px = int(min_radius_px)
        self.max_radius_px = int(max_radius_px)
        self.keep_images = bool(keep_images)

        K = len(reference)
        height, width = self.observation_space["rgb"].shape[:2]
        entries = dict(self.observation_space.spaces)
        if not self.keep_images:
            for key in IMAGE_KEYS:
                entries.pop(key, None)
        entries["keypoint_pixels"] = spaces.Box(
            np.zeros((K, 2), np.float32),
            np.tile(np.array([width - 1, height - 1], np.float32), (K, 1)),
            dtype=np.float32,
        )
        entries["keypoint_points"] = spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, shape=(K, 3), dtype=np.float32)
        entries["keypoint_confidence"] = spaces.Box(0.0, 1.0, shape=(K,), dtype=np.float32)
        self.observation_space = spaces.Dict(entries)

    def _add_descriptors(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        obs = super()._add_descriptors(obs, info)
        found = locate_keypoints(
            obs["descriptors"],
            obs["depth"],
            CameraIntrinsics.from_array(obs["camera_intrinsics"]),
            np.asarray(obs["camera_pose"], dtype=np.float64),
            self.reference_descriptors,
            window_m=self.window_m,
            temperature=self.temperature,
            sigma=self.confidence_sigma,
            min_radius_px=self.min_radius_px,
            max_radius_px=self.max_radius_px,
        )
        if not self.keep_images:
            obs = {k: v for k, v in obs.items() if k not in IMAGE_KEYS}
        obs["keypoint_pixels"] = found.pixels.astype(np.float32)
        obs["keypoint_points"] = np.clip(found.points_world, -POINT_BOUND_M, POINT_BOUND_M).astype(np.float32)
        obs["keypoint_confidence"] = found.confidence
        return obs
