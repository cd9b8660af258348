"""Descriptor sources (the oracle or a trained DON), reference descriptors and the axis-end keypoints.

:func:`load_descriptor_source` turns what a user names (``"oracle"``, a shipped network, a checkpoint)
into a :class:`DescriptorSource`; :func:`reference_descriptors_for` gives any source's descriptors of
chosen object surface points, such as the two rings of :func:`axis_end_targets`.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import warnings
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
import trimesh

from don_gym.data.render import DescriptorRenderer, RenderedTarget
from don_gym.descriptors import DescriptorField, embed, interpolate_field
from don_gym.descriptors.multi_part import PartSpace
from don_gym.errors import CheckpointError, DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, transform_points
from don_gym.learning.checkpoints import (
    CheckpointMetadata,
    PartIdentity,
    checkpoint_part_space,
    part_index_in,
    read_part_identity,
)
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import ObjectModel
from don_gym.perception.keypoints import DEFAULT_BORDER_MARGIN_PX, project_visible, sample_descriptors

__all__ = [
    "DEFAULT_AXIS_FRACTIONS",
    "DEFAULT_ORACLE_DIM",
    "FIELD_METHODS",
    "REFERENCE_POSE_ID",
    "REFERENCE_SEED",
    "AxisEndTargets",
    "DescriptorSource",
    "NetworkDescriptors",
    "OracleDescriptors",
    "PileOracleDescriptors",
    "ReferenceFrame",
    "axis_end_targets",
    "closest_surface_points",
    "default_reference_descriptors",
    "descriptor_field_for",
    "env_object_model",
    "field_descriptors",
    "load_descriptor_source",
    "reference_descriptors_for",
    "visible_surface_pixels",
]

#: Descriptor dimension of the oracle when nothing else asks for one (the paper's and the shipped nets').
DEFAULT_ORACLE_DIM = 3
#: Methods whose networks were trained towards the optimal field itself, so reference descriptors
#: can be read from the field.
FIELD_METHODS = ("supervised", "supervised-edge")
#: Reference frame used when a model needs one and none is given: ``reset(seed, pose_id)``.
REFERENCE_SEED = 0
REFERENCE_POSE_ID = 0
#: Axial fractions (from the minus end) of the two axis-end keypoints.
DEFAULT_AXIS_FRACTIONS = (0.2, 0.8)

_FIELDS: dict[tuple[str, int, bool], DescriptorField] = {}


def descriptor_field_for(
    object_model: ObjectModel, dim: int = DEFAULT_ORACLE_DIM, symmetric: bool = True
) -> DescriptorField:
    """The optimal descriptor field of an object, computed once per (mesh, dim, symmetric) in this process."""
    key = (object_model.mesh_hash, int(dim), bool(symmetric))
    field = _FIELDS.get(key)
    if field is None:
        field = embed(object_model, dim=int(dim), symmetric=symmetric)
        _FIELDS[key] = field
    return field


def _intrinsics_of(obs: Mapping[str, np.ndarray]) -> CameraIntrinsics:
    if "camera_intrinsics" not in obs:
        raise DonGymError("observation has no 'camera_intrinsics'; expected a don_gym env observation")
    return CameraIntrinsics.from_array(obs["camera_intrinsics"])


def _true_T_camera_object(info: Mapping[str, Any] | None) -> np.ndarray:
    if info is None or "T_world_object" not in info or "T_world_camera" not in info:
        raise DonGymError(
            "the oracle needs the true poses in info ('T_world_object', 'T_world_camera'); "
            "got info keys " + (str(sorted(info)) if info is not None else "None")
        )
    T_world_camera = np.asarray(info["T_world_camera"], dtype=np.float64)
    return invert_transform(T_world_camera) @ np.asarray(info["T_world_object"], dtype=np.float64)


class DescriptorSource(ABC):
    """Something that turns an observation into a descriptor image (H, W, D) float32.

    Attributes:
        object_model: the object the descriptors describe (None if unknown).
    """

    object_model: ObjectModel | None

    @property
    @abstractmethod
    def method(self) -> str:
        """``"oracle"``, a checkpoint's training method (:data:`don_gym.learning.methods.METHODS`) or ``"network"``."""

    @property
    @abstractmethod
    def descriptor_dim(self) -> int:
        """D, the number of descriptor channels."""

    @property
    def needs_info(self) -> bool:
        """True when :meth:`descriptor_image` needs the step's ``info`` (the oracle's true poses)."""
        return False

    @property
    def reference_from_field(self) -> bool:
        """True when reference descriptors may be read from the optimal field (:func:`reference_descriptors_for`)."""
        return False

    @property
    def field(self) -> DescriptorField | None:
        """The optimal field this source reproduces, when :attr:`reference_from_field`."""
        return None

    @property
    def descriptor_scale(self) -> float:
        """How far apart this source puts the part's descriptors, as a factor of its own optimal field's
        spacing: 1, except for a network of several parts, whose part regions hold each field shrunk by the
        region's scale (:class:`~don_gym.descriptors.PartSpace`). Distance scales tuned on the part's own
        field (the soft match's temperature, the keypoint confidence's sigma) are multiplied by it."""
        return 1.0

    @property
    def border_margin_px(self) -> int:
        """Pixels along each edge of the frame where best matches are not searched
        (:func:`don_gym.perception.keypoints.match_region`): 0, the whole image, for descriptors that are exact
        there."""
        return 0

    @abstractmethod
    def descriptor_image(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        """(H, W, D) float32 descriptors of the observation's image."""

    def __repr__(self) -> str:
        name = self.object_model.name if self.object_model is not None else None
        return f"{type(self).__name__}(method={self.method!r}, descriptor_dim={self.descriptor_dim}, object={name!r})"


class OracleDescriptors(DescriptorSource):
    """The object's optimal descriptors (:func:`don_gym.descriptors.embed`, the paper's "geometric"
    target) rendered from the TRUE object and camera poses in ``info``, the background elsewhere: the
    upper bound every learned model is compared with.

    Object pixels that the observed depth shows hidden (observed depth more than
    ``occlusion_tolerance_m`` in front of the rendered object, e.g. behind the gripper) become
    background; pixels without depth (holes on the metal part) keep their descriptor, as nothing
    says they are hidden.

    Args:
        object_model: the env's object.
        descriptor_dim: D of the optimal field.
        occlusion_check: make object pixels that the observed depth shows hidden background.
        occlusion_tolerance_m: how far in front of the rendered object the observed depth must be
            to count as hiding it (larger than the depth sensor's noise at 0.5 m).
    """

    def __init__(
        self,
        object_model: ObjectModel,
        descriptor_dim: int = DEFAULT_ORACLE_DIM,
        occlusion_check: bool = True,
        occlusion_tolerance_m: float = 0.01,
    ) -> None:
        self.object_model = object_model
        self._field = descriptor_field_for(object_model, descriptor_dim)
        self._renderer = DescriptorRenderer(object_model.mesh, self._field.vertex_descriptors, self._field.background)
        self.occlusion_check = bool(occlusion_check)
        self.occlusion_tolerance_m = float(occlusion_tolerance_m)

    @property
    def method(self) -> str:
        return "oracle"

    @property
    def descriptor_dim(self) -> int:
        return self._field.dim

    @property
    def needs_info(self) -> bool:
        return True

    @property
    def reference_from_field(self) -> bool:
        return True

    @property
    def field(self) -> DescriptorField:
        return self._field

    @property
    def background(self) -> np.ndarray:
        """(D,) descriptor of pixels off the object."""
        return self._field.background

    def render(self, intrinsics: CameraIntrinsics, T_camera_object: np.ndarray) -> RenderedTarget:
        """The unoccluded rendered target of one view."""
        return self._renderer.render(intrinsics, T_camera_object)

    def descriptor_image(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        intrinsics = _intrinsics_of(obs)
        target = self.render(intrinsics, _true_T_camera_object(info))
        image = target.descriptor_image
        if self.occlusion_check and "depth" in obs:
            depth = np.asarray(obs["depth"], dtype=np.float32)
            hidden = target.object_mask & (depth > 0) & (depth < target.depth_m - self.occlusion_tolerance_m)
            image[hidden] = self._field.background
        return image


class PileOracleDescriptors(OracleDescriptors):
    """:class:`OracleDescriptors` for a scene of several instances (a pile in a bin): every instance of its part
    rendered with exact occlusion between them (:class:`~don_gym.data.render.MultiPartDescriptorRenderer`), so the
    instances of the part look alike as a network of the part sees them; other parts and anything else the
    observed depth shows in front become background (the occlusion check of :class:`OracleDescriptors`).

    ``info["instances"]`` lists the instances (dicts with ``part``, the part's name, and ``T_world_object``),
    ``info["T_world_camera"]`` the true camera pose; an info without ``instances`` renders its
    ``T_world_object`` alone, as :class:`OracleDescriptors`.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        from don_gym.data.render import MultiPartDescriptorRenderer

        self._pile_renderer = MultiPartDescriptorRenderer(
            [self.object_model.mesh], [self._field.vertex_descriptors], self._field.background
        )

    def descriptor_image(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        if info is None or "instances" not in info:
            return super().descriptor_image(obs, info)
        intrinsics = _intrinsics_of(obs)
        T_camera_world = invert_transform(np.asarray(info["T_world_camera"], dtype=np.float64))
        poses = [
            T_camera_world @ np.asarray(i["T_world_object"], dtype=np.float64)
            for i in info["instances"]
            if i["part"] == self.object_model.name
        ]
        if not poses:
            return np.broadcast_to(
                self._field.background, (intrinsics.height, intrinsics.width, self.descriptor_dim)
            ).copy()
        rendered = self._pile_renderer.render(intrinsics, [(0, pose) for pose in poses])
        image = rendered.descriptor_image
        if self.occlusion_check and "depth" in obs:
            depth = np.asarray(obs["depth"], dtype=np.float32)
            hidden = rendered.object_mask & (depth > 0) & (depth < rendered.depth_m - self.occlusion_tolerance_m)
            image[hidden] = self._field.background
        return image


class NetworkDescriptors(DescriptorSource):
    """A trained DON: ``network.descriptor_image(obs["rgb"])``. :func:`load_descriptor_source` makes
    one from a shipped short name (``"toolcap/supervised-edge"``, see :mod:`don_gym.zoo`) or a path.

    Args:
        network: the network (put in eval mode by ``descriptor_image``).
        metadata: its checkpoint metadata, if it came from a checkpoint (decides how reference
            descriptors are found and :attr:`method`).
        object_model: the object it describes (needed for reference descriptors).
        source: how it was named, for messages.
        identity: the checkpoint's :class:`~don_gym.learning.checkpoints.PartIdentity` (the trained part and
            field), if it carries one.
    """

    def __init__(
        self,
        network: DenseObjectNet,
        metadata: CheckpointMetadata | None = None,
        object_model: ObjectModel | None = None,
        source: str = "network",
        identity: PartIdentity | None = None,
    ) -> None:
        self.network = network
        self.metadata = metadata
        self.object_model = object_model
        self.source = source
        self.identity = identity
        self._field: DescriptorField | None = None
        self._field_checked = False
        self._size_checked = False

    @property
    def method(self) -> str:
        return self.metadata.method if self.metadata is not None else "network"

    @property
    def descriptor_dim(self) -> int:
        return int(self.network.descriptor_dim)

    @property
    def border_margin_px(self) -> int:
        """:data:`~don_gym.perception.keypoints.DEFAULT_BORDER_MARGIN_PX`: a network's output next to the frame's edge
        comes from features that saw the convolutions' zero padding."""
        return DEFAULT_BORDER_MARGIN_PX

    @property
    def field(self) -> DescriptorField | None:
        """The field a network of :data:`FIELD_METHODS` was trained towards, on :attr:`object_model`'s
        vertices: the checkpoint's own, checked against the object's (CheckpointError when they differ
        beyond :data:`~don_gym.descriptors.FIELD_MATCH_ATOL`). None for other networks, and, with a
        warning, for a checkpoint that carries no field."""
        if not self._field_checked:
            metadata = self.metadata
            space = checkpoint_part_space(metadata) if metadata is not None else None
            if space is not None and self.object_model is not None and metadata.method in FIELD_METHODS:
                self._field = self._part_space_field(space)
            elif metadata is not None and self.object_model is not None and metadata.method in FIELD_METHODS:
                trained = self.identity.field if self.identity is not None else None
                if trained is None:
                    warnings.warn(
                        f"{self.source}: carries no descriptor field (saved without one, e.g. by an older don_gym), "
                        "so reference descriptors will come from a reference frame instead of the field; add it "
                        "with don_gym.learning.checkpoints.restamp_checkpoint (shipped networks: "
                        "python benchmarks/train_shipped.py --restamp)",
                        stacklevel=2,
                    )
                else:
                    computed = descriptor_field_for(self.object_model, trained.dim, trained.symmetric)
                    self._field = self.identity.field_on(self.object_model, computed, self.source)
            self._field_checked = True  # not before: a refused field is refused again on the next use
        return self._field

    def _part_space_field(self, space: PartSpace) -> DescriptorField:
        """A network of several parts: :attr:`object_model`'s optimal field mapped into its region of the
        network's space (the part's own field checked against the checkpoint's where it carries it)."""
        index = part_index_in(space, self.object_model)
        if index is None:  # load_descriptor_source refuses such a part first
            raise CheckpointError(f"{self.source}: part {self.object_model.name!r} is none of {list(space.names)}")
        settings = self.metadata.descriptor_field
        trained = self.identity.field if self.identity is not None else None
        symmetric = trained.symmetric if trained is not None else bool(settings.get("symmetric", True))
        own = descriptor_field_for(self.object_model, space.field_dim, symmetric)
        if trained is not None and not self.object_model.shape_signature.differences(self.identity.signature):
            own = self.identity.field_on(self.object_model, own, self.source)
        return dataclasses.replace(
            own,
            vertex_descriptors=space.map_descriptors(index, own.vertex_descriptors),
            background=np.asarray(space.background, dtype=np.float32),
        )

    @property
    def reference_from_field(self) -> bool:
        return self.field is not None

    @functools.cached_property
    def descriptor_scale(self) -> float:
        space = checkpoint_part_space(self.metadata) if self.metadata is not None else None
        index = part_index_in(space, self.object_model) if space is not None and self.object_model else None
        return 1.0 if index is None else float(space.parts[index].scale)

    def descriptor_image(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> np.ndarray:
        if "rgb" not in obs:
            raise DonGymError("a DON needs obs['rgb']; the env was made without images (image_size=None?)")
        rgb = np.asarray(obs["rgb"])
        if not self._size_checked:
            self._size_checked = True
            self._warn_on_size_mismatch(rgb.shape[1], rgb.shape[0])
        return self.network.descriptor_image(rgb)

    def descriptor_images(self, rgb_batch: np.ndarray) -> np.ndarray:
        """(N, H, W, D) float32 descriptors of a batch of uint8 (N, H, W, 3) RGB images in one forward
        pass on the network's device (``source.network.to(device)`` moves it): per image what
        :meth:`descriptor_image` gives, up to float rounding. Batching pays on a GPU, where one pass
        over N images costs about as much as one over a single image."""
        import torch

        rgb = np.asarray(rgb_batch)
        if rgb.dtype != np.uint8 or rgb.ndim != 4 or rgb.shape[3] != 3 or rgb.shape[0] == 0:
            raise DonGymError(
                f"descriptor_images expects a uint8 (N, H, W, 3) batch of RGB images, got {rgb.dtype} of shape "
                f"{rgb.shape}"
            )
        if not self._size_checked:
            self._size_checked = True
            self._warn_on_size_mismatch(rgb.shape[2], rgb.shape[1])
        network = self.network
        device = next(network.parameters()).device
        was_training = network.training
        network.eval()
        try:
            with torch.inference_mode():
                x = torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(0, 3, 1, 2)
                descriptors = network(x.float().div_(255.0)).permute(0, 2, 3, 1)
                return np.ascontiguousarray(descriptors.float().cpu().numpy())
        finally:
            network.train(was_training)

    def _warn_on_size_mismatch(self, width: int, height: int) -> None:
        # A DON is not scale invariant: the same view at another resolution shows the part at
        # another size in pixels than the network learned, and its descriptors degrade.
        if self.metadata is None or tuple(self.metadata.image_size) == (width, height):
            return
        trained_w, trained_h = self.metadata.image_size
        warnings.warn(
            f"{self.source}: trained on {trained_w}x{trained_h} images but gets {width}x{height}; "
            f"make the env with image_size=({trained_w}, {trained_h}) for the descriptors it was trained for",
            stacklevel=3,
        )


def _unknown_model_message(name: str) -> str:
    from don_gym.zoo import shipped_names

    shipped = shipped_names()
    available = ", ".join(["'oracle'", *(repr(n) for n in shipped)])
    note = "" if shipped else " (no shipped networks installed yet)"
    return f"model {name!r} is neither 'oracle', a shipped network nor a checkpoint file; available: {available}{note}"


def load_descriptor_source(
    model: str | Path | DenseObjectNet | DescriptorSource,
    object_model: ObjectModel,
    descriptor_dim: int | None = None,
    occlusion_check: bool = True,
) -> DescriptorSource:
    """A :class:`DescriptorSource` for ``object_model`` from what a user passes as ``model``.

    Args:
        model: ``"oracle"``; a shipped short name (``"toolcap/self-supervised"``) or checkpoint path
            (loaded with :func:`don_gym.zoo.load_don`, checked against the object's geometry and
            ``descriptor_dim``, and, if trained towards the optimal field, its field against the
            object's: see docs/reliability.md, "Part identity"); a
            :class:`~don_gym.learning.model.DenseObjectNet`; or a source (checked).
        object_model: the env's object.
        descriptor_dim: required D (None: the model's; the oracle then uses 3).
        occlusion_check: see :class:`OracleDescriptors`.

    Raises:
        CheckpointError: unknown name (the message lists the available ones), a checkpoint for another
            part, descriptor size or descriptor field.
        DonGymError: any other unusable ``model``.
    """
    if descriptor_dim is not None and (isinstance(descriptor_dim, bool) or int(descriptor_dim) != descriptor_dim):
        raise DonGymError(f"descriptor_dim={descriptor_dim!r}: expected a positive integer or None")
    if isinstance(model, DescriptorSource):
        source = model
    elif isinstance(model, DenseObjectNet):
        source = NetworkDescriptors(model, None, object_model, source=f"network {model.extra_repr()}")
    elif isinstance(model, (str, Path)):
        text = str(model)
        if text == "oracle":
            return OracleDescriptors(object_model, descriptor_dim or DEFAULT_ORACLE_DIM, occlusion_check)
        from don_gym.zoo import checkpoint_path, is_checkpoint_reference, load_don

        if not is_checkpoint_reference(text):
            raise CheckpointError(_unknown_model_message(text))
        path = checkpoint_path(text)
        network, metadata = load_don(path, expect_descriptor_dim=descriptor_dim, expect_part=object_model)
        identity = read_part_identity(path, metadata)
        network_source = NetworkDescriptors(network, metadata, object_model, f"checkpoint {text!r}", identity)
        if identity is not None and identity.field is not None:
            _ = network_source.field  # a field that does not fit this part is refused here, not at first use
        return network_source
    else:
        raise DonGymError(
            f"model={model!r}: expected 'oracle', a shipped network name, a checkpoint path, a DenseObjectNet "
            "or a DescriptorSource"
        )
    if source.object_model is not None and source.object_model.mesh_hash != object_model.mesh_hash:
        raise DonGymError(
            f"descriptor source is for object {source.object_model.name!r}, expected {object_model.name!r}"
        )
    if descriptor_dim is not None and source.descriptor_dim != descriptor_dim:
        raise DonGymError(
            f"descriptor source gives {source.descriptor_dim}-dimensional descriptors, expected {descriptor_dim}"
        )
    if source.object_model is None:
        source.object_model = object_model
    return source


def env_object_model(env: gym.Env) -> ObjectModel:
    """The :class:`ObjectModel` of a don_gym env (``env.unwrapped.model``)."""
    model = getattr(env.unwrapped, "model", None)
    if not isinstance(model, ObjectModel):
        raise DonGymError(
            f"{type(env.unwrapped).__name__} has no object model (env.unwrapped.model); expected a don_gym env"
        )
    return model


# ------------------------------------------------------------------------------------------------
# Reference descriptors
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceFrame:
    """One observation with its true poses, for reading a model's descriptors of known surface points.

    Attributes:
        obs: the env observation (``rgb``, ``depth``, ``camera_intrinsics`` needed).
        info: its info (``T_world_object`` and ``T_world_camera``, the TRUE poses).
    """

    obs: Mapping[str, np.ndarray]
    info: Mapping[str, Any]

    @classmethod
    def from_env(cls, env: gym.Env, seed: int = REFERENCE_SEED, pose_id: int = REFERENCE_POSE_ID) -> ReferenceFrame:
        """Reset the (unwrapped) env at a fixed seed and pose and keep that frame.

        The env's random generator is put back afterwards, so later unseeded resets go on as
        they would have (no two envs of a vector env become correlated through this). The env
        must be reset again before stepping. An env that observes a window of its wrist frame (``window_px``)
        gives its whole frame: the window is placed where the part was last seen, which at the reference pose
        need not hold the part.
        """
        base = env.unwrapped
        saved_rng = copy.deepcopy(base.np_random)
        try:
            obs, info = base.reset(seed=seed, options={"pose_id": pose_id})
            if getattr(base, "window_px", None) is not None:
                rgb, depth, frame = base.full_frame_images()
                obs = dict(obs, rgb=rgb, depth=depth, camera_intrinsics=frame.as_array().astype(np.float32))
        finally:
            base.np_random = saved_rng
        return cls({k: np.array(v) for k, v in obs.items()}, dict(info))


def closest_surface_points(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle ids (M,) and barycentric coordinates (M, 3) of the mesh points closest to ``points`` (M, 3)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    closest, _, triangle_ids = trimesh.proximity.closest_point(mesh, points)
    barycentric = trimesh.triangles.points_to_barycentric(mesh.triangles[triangle_ids], closest)
    return np.asarray(triangle_ids, dtype=np.int64), np.clip(barycentric, 0.0, 1.0)


def field_descriptors(
    field: DescriptorField, mesh: trimesh.Trimesh, surface_points: Sequence[np.ndarray]
) -> np.ndarray:
    """(K, D) mean field descriptor over each of K sets of object-frame surface points ((N_k, 3) each)."""
    out = []
    for points in surface_points:
        triangle_ids, barycentric = closest_surface_points(mesh, points)
        out.append(interpolate_field(field.vertex_descriptors, mesh.faces, triangle_ids, barycentric).mean(axis=0))
    return np.asarray(out, dtype=np.float32)


def visible_surface_pixels(
    object_model: ObjectModel,
    surface_points: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_camera_object: np.ndarray,
    margin_px: int = 1,
    tolerance_m: float = 0.003,
) -> np.ndarray:
    """(M, 2) int pixels (u, v) where object-frame surface points (N, 3) are seen in a view.

    A point counts when the ray-cast object depth at its pixel is within ``tolerance_m`` of its own
    depth (not hidden by another part of the object) and its pixel is at least ``margin_px`` inside
    the object's outline (descriptors on the outline mix with the background).
    """
    renderer = DescriptorRenderer(
        object_model.mesh, np.zeros((len(object_model.mesh.vertices), 1), np.float32), np.zeros(1, np.float32)
    )
    target = renderer.render(intrinsics, T_camera_object)
    points_camera = transform_points(T_camera_object, surface_points)
    uv, visible = project_visible(points_camera, intrinsics, target.depth_m, tolerance_m)
    if margin_px > 0:
        size = 2 * int(margin_px) + 1
        interior = cv2.erode(target.object_mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
        visible[visible] = interior[uv[visible, 1], uv[visible, 0]]
    return uv[visible]


def reference_descriptors_for(
    source: DescriptorSource,
    surface_points: Sequence[np.ndarray],
    reference: ReferenceFrame | None = None,
    radius_px: int = 1,
) -> np.ndarray:
    """The descriptors ``source`` gives to K sets of object-frame surface points: (K, D) float32.

    Each set (N_k, 3) in metres is one keypoint: points that share a descriptor (a ring about a
    symmetry axis) or a single point. Without ``reference`` and with ``source.reference_from_field``
    (the oracle, and networks of :data:`FIELD_METHODS` whose checkpoint carries their field), the mean
    field descriptor of each set. Every other model (the self-supervised DON, whose descriptor space
    is arbitrary; ``supervised-mask``, whose last dimension is a view-dependent mask channel; a bare
    network) gets them as the original DON does: its descriptor image of the reference frame, median
    over a ``radius_px`` window at each visible point's pixel (:func:`visible_surface_pixels`), then
    the median over the set's points.

    Raises:
        DonGymError: no reference frame where one is needed, or a set not visible in it.
    """
    sets = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in surface_points]
    if reference is None and source.reference_from_field:
        return field_descriptors(source.field, source.object_model.mesh, sets)
    if reference is None:
        raise DonGymError(
            f"a {source.method!r} model needs a reference frame for its reference descriptors "
            "(ReferenceFrame.from_env(env)); its descriptor space is not the optimal field"
        )
    if source.object_model is None:
        raise DonGymError("reference descriptors need the source's object_model")
    image = source.descriptor_image(reference.obs, reference.info)
    intrinsics = _intrinsics_of(reference.obs)
    T_camera_object = _true_T_camera_object(reference.info)
    out = []
    for k, points in enumerate(sets):
        pixels = visible_surface_pixels(source.object_model, points, intrinsics, T_camera_object)
        if len(pixels) == 0:
            raise DonGymError(
                f"surface point set {k} ({len(points)} points) is not visible in the reference frame; "
                "use another reference pose"
            )
        out.append(np.median(sample_descriptors(image, pixels, radius_px), axis=0))
    return np.asarray(out, dtype=np.float32)


# ------------------------------------------------------------------------------------------------
# Axis-end keypoints
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisEndTargets:
    """The two axis-end keypoints of an object (see :func:`axis_end_targets`).

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
    """The two surface keypoints of the paper's axis grasp (Kupcsik et al. 2021, "Grasp Pose Prediction").

    Along the +axis (through the centre of mass), at ``fractions`` of the part's axial length from
    the minus end: the outer surface there, i.e. the mesh vertices within ``slab_m`` of the nearest
    level that carries outer-surface vertices and whose distance from the axis is within 5 % of the
    largest at that level (never a bore or an end face's inner rim). With symmetric (GISIF)
    descriptors all points of such a ring share one descriptor, so the keypoint is the whole ring;
    its axial position and radius let an agent go from the seen surface back to the axis. 20 %/80 %
    keep both rings off the end faces and edges (where learned descriptors blend into the
    background) yet far apart, for an accurate axis direction.

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
