"""The KeypointObservation wrapper: K keypoints tracked in each observation's descriptor image.

Keypoint matching is :func:`don_gym.perception.keypoints.locate_keypoints`; the default keypoints are the
axis-end rings of :func:`don_gym.perception.descriptor_sources.axis_end_targets`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, image_window, window_origin_px
from don_gym.learning.model import DenseObjectNet
from don_gym.perception.descriptor_sources import (
    AxisEndTargets,
    DescriptorSource,
    ReferenceFrame,
    axis_end_targets,
    default_reference_descriptors,
    descriptor_field_for,
)
from don_gym.perception.keypoints import (
    DEFAULT_CONFIDENCE_SIGMA,
    DEFAULT_MAX_RADIUS_PX,
    DEFAULT_MIN_RADIUS_PX,
    DEFAULT_SOFT_TEMPERATURE,
    Keypoints,
    locate_keypoints,
    match_region,
)
from don_gym.wrappers.descriptors import DescriptorObservation

#: Soft-match disc radius (m) for reference descriptors given by the user.
DEFAULT_WINDOW_M = 0.02
#: World-coordinate bound of ``keypoint_points`` (m); the env's poses use the same.
POINT_BOUND_M = 10.0
#: Keys dropped with ``keep_images=False``.
IMAGE_KEYS = ("rgb", "depth", "descriptors")
#: Windowed envs (``window_px``): keypoints at least this confident place the next window (their mean world point).
WINDOW_MIN_CONFIDENCE = 0.2


@dataclass(frozen=True)
class KeypointSettings:
    """How tracked keypoints are located in an observation (:func:`~don_gym.perception.keypoints.locate_keypoints`):
    the soft-match radius ``window_m`` (metres; 0: plain best match), the descriptor-distance scales of the soft
    match and the confidence in the part's own field's units (multiplied by the source's ``descriptor_scale``),
    the depth windows ``min_radius_px``/``max_radius_px`` and ``border_margin_px`` (None: the source's own). The
    one place the wrapper and the :class:`~don_gym.agents.AxisGraspAgent` take them from."""

    window_m: float
    temperature: float = DEFAULT_SOFT_TEMPERATURE
    confidence_sigma: float = DEFAULT_CONFIDENCE_SIGMA
    min_radius_px: int = DEFAULT_MIN_RADIUS_PX
    max_radius_px: int = DEFAULT_MAX_RADIUS_PX
    border_margin_px: int | None = None

    def locate(self, obs: dict[str, np.ndarray], source: DescriptorSource, reference: np.ndarray) -> Keypoints:
        """The keypoints of the (K, D) ``reference`` descriptors in an observation with ``descriptors`` (H, W, D),
        ``depth`` (H, W) metres, ``camera_intrinsics`` and ``camera_pose`` (``T_world_camera``)."""
        return locate_keypoints(
            obs["descriptors"],
            obs["depth"],
            CameraIntrinsics.from_array(obs["camera_intrinsics"]),
            np.asarray(obs["camera_pose"], dtype=np.float64),
            reference,
            window_m=self.window_m,
            temperature=self.temperature * source.descriptor_scale,
            sigma=self.confidence_sigma * source.descriptor_scale,
            min_radius_px=self.min_radius_px,
            max_radius_px=self.max_radius_px,
            border_margin_px=source.border_margin_px if self.border_margin_px is None else self.border_margin_px,
        )


class KeypointObservation(DescriptorObservation):
    """Adds K tracked keypoints to each observation (and, by default, the descriptor image).

    Added keys: ``keypoint_pixels`` (K, 2) float32 soft-match pixel (u, v); ``keypoint_points``
    (K, 3) float32 world point in metres from the depth image (robust to holes, see
    :func:`don_gym.perception.keypoints.robust_depth`; the camera centre if no depth is found within
    ``max_radius_px``); ``keypoint_confidence`` (K,) float32 in [0, 1], ``exp(-(d / sigma)^2)`` of the
    best-match descriptor distance ``d`` (0 without depth).

    Args:
        env: a don_gym env with images.
        model: as for :class:`DescriptorObservation`.
        reference_descriptors: (K, D) descriptors to track, D the model's. None: the two axis-end
            keypoints of :func:`~don_gym.perception.descriptor_sources.axis_end_targets` (the
            :class:`~don_gym.agents.AxisGraspAgent`'s), their descriptors from the field or from
            ``reference_frame`` (see :func:`~don_gym.perception.descriptor_sources.reference_descriptors_for`).
        keep_images: False drops ``rgb``, ``depth`` and ``descriptors`` for a compact observation.
        reference_frame: frame to read the default reference descriptors from; given, it is used for
            every model (None: the field where the model reproduces it, else the env reset at a fixed
            seed and pose, see :meth:`ReferenceFrame.from_env`).
        window_m: soft-match radius in metres (None: the rings' diameter for the default keypoints,
            :data:`DEFAULT_WINDOW_M` otherwise; 0: plain best match).
        temperature, confidence_sigma: descriptor-distance scales of the soft match and the confidence, in the
            part's own field's units (multiplied by the source's ``descriptor_scale`` for a network of several parts).
        descriptor_dim, occlusion_check: as for :class:`DescriptorObservation`.
        min_radius_px, max_radius_px: depth windows (:func:`don_gym.perception.keypoints.robust_depth`).
        border_margin_px: pixels along each edge of the frame where matches are not searched (None: the
            model's own, :attr:`~don_gym.perception.descriptor_sources.DescriptorSource.border_margin_px`; 0:
            everywhere).
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
        border_margin_px: int | None = None,
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
            border_margin_px=border_margin_px,
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
        self.keep_images = bool(keep_images)

        K = len(reference)
        height, width = self.observation_space["rgb"].shape[:2]
        #: The env's wrist window (``window_px``; None: whole frames) and its whole frame's intrinsics.
        self.window_px: int | None = getattr(env.unwrapped, "window_px", None)
        self.frame_intrinsics = getattr(env.unwrapped, "intrinsics", None) or CameraIntrinsics.d435(width, height)
        margin = self.source.border_margin_px if border_margin_px is None else border_margin_px
        try:
            match_region(height, width, margin)  # refuses a margin that is not a count or leaves no pixels
        except DonGymError as error:
            source = "given" if border_margin_px is not None else f"the {self.source.method!r} model's own"
            raise DonGymError(
                f"{error} ({source}, for the env's {width}x{height} images; pass a smaller border_margin_px, "
                "0 to search the whole frame)"
            ) from None
        self.settings = KeypointSettings(
            window, float(temperature), float(confidence_sigma), int(min_radius_px), int(max_radius_px), int(margin)
        )
        entries = dict(self.observation_space.spaces)
        if not self.keep_images:
            for key in IMAGE_KEYS:
                entries.pop(key, None)
        frame = self.frame_intrinsics
        entries["keypoint_pixels"] = spaces.Box(
            np.zeros((K, 2), np.float32),
            np.tile(np.array([frame.width - 1, frame.height - 1], np.float32), (K, 1)),
            dtype=np.float32,
        )
        entries["keypoint_points"] = spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, shape=(K, 3), dtype=np.float32)
        entries["keypoint_confidence"] = spaces.Box(0.0, 1.0, shape=(K,), dtype=np.float32)
        self.observation_space = spaces.Dict(entries)

    @property
    def window_m(self) -> float:
        """Soft-match radius in metres (:attr:`settings`)."""
        return self.settings.window_m

    @property
    def border_margin_px(self) -> int:
        """Pixels along each edge of the frame where matches are not searched (:attr:`settings`)."""
        return int(self.settings.border_margin_px)

    def _add_descriptors(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        return self.add_keypoints(super()._add_descriptors(obs, info))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if self.window_px is None:
            return self._add_descriptors(obs, info), info
        return self._first_window(obs, info), info

    def _first_window(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        """A windowed env's first observation: nothing is known of the part yet, so the DON looks at the whole
        frame (the observation pose sees the whole workspace), and the observation is the window around what it
        found, as a step's would be."""
        rgb, depth, frame = self.env.unwrapped.full_frame_images()
        full = dict(obs, rgb=rgb, depth=depth, camera_intrinsics=frame.as_array().astype(np.float32))
        full = DescriptorObservation._add_descriptors(self, full, info)
        found = self.settings.locate(full, self.source, self.reference_descriptors)
        seen = found.confidence >= WINDOW_MIN_CONFIDENCE
        window = image_window(frame, found.pixels[seen].mean(axis=0) if seen.any() else None, self.window_px)
        u0, v0 = window_origin_px(frame, window)
        rows, columns = slice(v0, v0 + window.height), slice(u0, u0 + window.width)
        obs = dict(full, camera_intrinsics=window.as_array().astype(np.float32))
        for key in IMAGE_KEYS:
            obs[key] = np.ascontiguousarray(full[key][rows, columns])
        return self._with_keypoints(obs, found)

    def add_keypoints(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``obs`` with ``descriptors`` (H, W, D) plus the tracked keypoints (and without the images
        unless ``keep_images``); shared with :class:`~don_gym.wrappers.VectorKeypointObservation`. In a window
        (``camera_intrinsics`` of a window of the env's frame) the pixels are the whole frame's."""
        found = self.settings.locate(obs, self.source, self.reference_descriptors)
        window = CameraIntrinsics.from_array(obs["camera_intrinsics"])
        origin = np.array(window_origin_px(self.frame_intrinsics, window), dtype=np.float64)
        return self._with_keypoints(obs, replace(found, pixels=found.pixels + origin))

    def _with_keypoints(self, obs: dict[str, np.ndarray], found: Keypoints) -> dict[str, np.ndarray]:
        """``obs`` with the keypoints ``found`` (pixels in the whole frame); a windowed env's next window goes
        where the confident ones are (unchanged when none is: the part's last seen place)."""
        if self.window_px is not None:
            seen = found.confidence >= WINDOW_MIN_CONFIDENCE
            if seen.any():
                self.env.unwrapped.set_window_centre(found.points_world[seen].mean(axis=0))
        if not self.keep_images:
            obs = {k: v for k, v in obs.items() if k not in IMAGE_KEYS}
        obs["keypoint_pixels"] = found.pixels.astype(np.float32)
        obs["keypoint_points"] = np.clip(found.points_world, -POINT_BOUND_M, POINT_BOUND_M).astype(np.float32)
        obs["keypoint_confidence"] = found.confidence
        return obs
