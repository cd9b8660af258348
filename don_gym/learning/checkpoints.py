"""DON checkpoints: safetensors weights plus JSON metadata that says what the network was trained for.

:func:`save_checkpoint` writes one ``.safetensors`` file; :func:`load_checkpoint` rebuilds the
:class:`~don_gym.learning.model.DenseObjectNet` and checks the metadata (:class:`CheckpointMetadata`) against what
the caller needs, raising :class:`~don_gym.errors.CheckpointError` on any mismatch or damaged file.
A checkpoint also carries the identity of the part it was trained on (:class:`PartIdentity`), which
:func:`restamp_checkpoint` adds to one saved without it (docs/reliability.md, "Part identity").
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from don_gym.descriptors import FIELD_MATCH_ATOL, DescriptorField, embed, mesh_content_hash
from don_gym.descriptors.multi_part import PartSpace
from don_gym.errors import CheckpointError, DonGymError, MeshError
from don_gym.io import atomic_path
from don_gym.learning.methods import METHODS, is_supervised
from don_gym.learning.model import ARCHS, IMAGENET_MEAN, IMAGENET_STD, DenseObjectNet
from don_gym.objects import ObjectModel, ShapeSignature, part_name

__all__ = [
    "FIELD_ADVICE",
    "FIELD_TENSORS",
    "FORMAT_VERSION",
    "METADATA_KEY",
    "PART_TENSORS",
    "VERTEX_MATCH_ATOL_M",
    "WEIGHT_DTYPES",
    "CheckpointMetadata",
    "PartIdentity",
    "check_metadata",
    "checkpoint_part_space",
    "load_checkpoint",
    "part_index_in",
    "part_mismatch",
    "read_checkpoint_metadata",
    "read_part_identity",
    "restamp_checkpoint",
    "save_checkpoint",
]

#: Version of the checkpoint layout; bumped when a reader of the old layout would misread a new file.
#: 2: the part identity's tensors (:data:`PART_TENSORS`, :data:`FIELD_TENSORS`) beside the weights.
FORMAT_VERSION = 2
METADATA_KEY = "don_gym"
WEIGHT_DTYPES = {"float32": torch.float32, "float16": torch.float16}
#: Tensors of the trained part's mesh, and of the descriptor field its targets came from (supervised methods).
PART_TENSORS = ("part.vertices_m", "part.faces")
FIELD_TENSORS = ("field.vertex_descriptors", "field.eigenvalues", "field.background")
#: A part's vertex is the trained part's when within this distance (m) of it: covers a mesh re-exported in
#: single precision (STL), far below any feature of a part a Panda picks.
VERTEX_MATCH_ATOL_M = 1e-6
#: What to do about a network whose field cannot serve a part, for the messages that refuse it.
FIELD_ADVICE = (
    "retrain on this part, or pass reference descriptors explicitly "
    "(KeypointObservation(reference_descriptors=...) or AxisGraspAgent.from_parts)"
)


@dataclass(frozen=True)
class CheckpointMetadata:
    """What a checkpoint was trained on and for.

    Attributes:
        method: one of :data:`don_gym.learning.methods.METHODS`.
        object_name: the object the network describes (``ObjectModel.name``, :func:`~don_gym.objects.part_name`);
            for a person to read: identity is :attr:`object_signature`.
        object_mesh_hash: ``ObjectModel.mesh_hash`` of its geometry where it was trained (provenance).
        image_size: ``(W, H)`` in pixels of the training images.
        descriptor_field_hash: ``DescriptorField.field_hash`` of the dataset's field file the targets came
            from (supervised methods; empty for ``self-supervised``): provenance, not compared across machines.
        background_descriptor: the field's background descriptor (supervised methods), so
            a user of the network can tell predicted background from object.
        renderer: renderer of the training images (e.g. ``"tiny"``, ``"egl"``).
        sensor_preset: depth sensor preset behind the correspondences (``self-supervised``).
        training_steps: optimiser steps taken.
        arch, descriptor_dim, normalization_mean, normalization_std: the network's; filled
            from the model by :func:`save_checkpoint` when left at their defaults.
        weights_dtype, weights_sha256, don_gym_version, format_version: written by
            :func:`save_checkpoint`.
        extra: free-form JSON-serialisable training details (learning rate, seed, ...).
        object_signature, descriptor_field, identity_sha256: the :class:`PartIdentity`, written by
            :func:`save_checkpoint` (empty without one): ``ShapeSignature.to_dict()``, the field's
            non-array settings, and a SHA-256 of the identity's tensors.
        part_space: a network of several parts (trained on a bin dataset): the descriptor space it learned,
            :meth:`~don_gym.descriptors.multi_part.PartSpace.to_dict`, naming every part with its shape
            signature; the identity above is then its first part's. Empty for a one-part network.
    """

    method: str
    object_name: str
    object_mesh_hash: str
    image_size: tuple[int, int]
    descriptor_field_hash: str = ""
    background_descriptor: tuple[float, ...] = ()
    renderer: str = ""
    sensor_preset: str = ""
    training_steps: int = 0
    arch: str = ""
    descriptor_dim: int = 0
    normalization_mean: tuple[float, float, float] = IMAGENET_MEAN
    normalization_std: tuple[float, float, float] = IMAGENET_STD
    weights_dtype: str = "float32"
    weights_sha256: str = ""
    don_gym_version: str = ""
    format_version: int = FORMAT_VERSION
    extra: dict[str, Any] = field(default_factory=dict)
    object_signature: dict[str, Any] = field(default_factory=dict)
    descriptor_field: dict[str, Any] = field(default_factory=dict)
    identity_sha256: str = ""
    part_space: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        if not data["part_space"]:  # a one-part network's metadata reads as before the field existed
            del data["part_space"]
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "metadata", strict: bool = False) -> CheckpointMetadata:
        """Parse and type-check a metadata mapping; raises :class:`CheckpointError` naming ``source``.

        Unknown keys are ignored when reading a file (a newer don_gym may add fields) and
        are an error with ``strict`` (a caller's typo; put free-form values in ``extra``).
        """
        if not isinstance(data, Mapping):
            raise CheckpointError(f"{source}: metadata must be a JSON object, got {type(data).__name__}")
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(known))
        if strict and unknown:
            raise CheckpointError(
                f"{source}: unknown metadata fields {unknown}; the fields are {sorted(known)} "
                "(free-form values go in 'extra')"
            )
        required = [
            n for n, f in known.items() if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        ]
        absent = [n for n in required if n not in data]
        if absent:
            raise CheckpointError(f"{source}: metadata lacks the fields {absent}")
        values: dict[str, Any] = {}
        try:
            for name, value in data.items():
                if name not in known:
                    continue  # written by a newer don_gym with the same format version
                if name in ("image_size", "normalization_mean", "normalization_std", "background_descriptor"):
                    value = tuple(int(v) if name == "image_size" else float(v) for v in value)
                elif name in ("training_steps", "descriptor_dim", "format_version"):
                    if isinstance(value, bool) or not isinstance(value, int):
                        raise TypeError(f"{name} must be an integer, got {value!r}")
                elif name in ("extra", "object_signature", "descriptor_field", "part_space"):
                    if not isinstance(value, dict):
                        raise TypeError(f"{name} must be an object, got {value!r}")
                elif not isinstance(value, str):
                    raise TypeError(f"{name} must be a string, got {value!r}")
                values[name] = value
        except (TypeError, ValueError) as exc:
            raise CheckpointError(f"{source}: invalid metadata: {exc}") from exc
        if len(values["image_size"]) != 2:
            raise CheckpointError(f"{source}: image_size must be (W, H), got {values['image_size']}")
        return cls(**values)


def _weights_sha256(tensors: dict[str, torch.Tensor]) -> str:
    digest = hashlib.sha256()
    for name in sorted(tensors):
        tensor = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.view(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise CheckpointError(message)


@dataclass(frozen=True, eq=False)
class PartIdentity:
    """What a network knows of the part it was trained on: enough to recognise the part on any machine
    and to give its reference descriptors without recomputing anything.

    Attributes:
        signature: the part's :class:`~don_gym.objects.ShapeSignature` (what identity is decided by).
        vertices_m: (N, 3) float64 vertices of the trained mesh, object frame, metres.
        faces: (F, 3) int64 faces of the trained mesh.
        field: the optimal descriptor field its targets came from, on those vertices (supervised
            methods), else None.
    """

    signature: ShapeSignature
    vertices_m: np.ndarray
    faces: np.ndarray
    field: DescriptorField | None = None

    @classmethod
    def of(cls, part: ObjectModel, field: DescriptorField | None = None) -> PartIdentity:
        """The identity of ``part``, with ``field`` (one computed on ``part``'s mesh) if given."""
        vertices = np.array(part.mesh.vertices, dtype=np.float64)
        if field is not None and field.n_vertices != len(vertices):
            raise DonGymError(
                f"descriptor field has {field.n_vertices} vertices but part {part.name!r} has {len(vertices)}; "
                "expected the field computed on this part's mesh"
            )
        return cls(part.shape_signature, vertices, np.array(part.mesh.faces, dtype=np.int64), field)

    def tensors(self) -> dict[str, torch.Tensor]:
        """The tensors a checkpoint stores (:data:`PART_TENSORS`, and :data:`FIELD_TENSORS` with a field)."""
        arrays = {"part.vertices_m": self.vertices_m.astype(np.float64), "part.faces": self.faces.astype(np.int64)}
        if self.field is not None:
            arrays |= {
                "field.vertex_descriptors": self.field.vertex_descriptors.astype(np.float32),
                "field.eigenvalues": self.field.eigenvalues.astype(np.float64),
                "field.background": self.field.background.astype(np.float32),
            }
        return {name: torch.from_numpy(np.ascontiguousarray(a)) for name, a in arrays.items()}

    def field_settings(self) -> dict[str, Any]:
        """The field's non-array settings (:attr:`CheckpointMetadata.descriptor_field`); empty without a field."""
        if self.field is None:
            return {}
        return {
            "dim": self.field.dim,
            "groups": [list(g) for g in self.field.groups],
            "symmetric": bool(self.field.symmetric),
            "tolerance": float(self.field.tolerance),
            "solver": self.field.solver,
            "embedded_vertices": int(self.field.embedded_vertices),
        }

    def vertex_order(self, part: ObjectModel) -> np.ndarray | None:
        """(N,) index of the trained vertex at each of ``part``'s vertices, or None when ``part``'s vertices
        are not the trained ones (in any order, within :data:`VERTEX_MATCH_ATOL_M`, same object frame)."""
        vertices = np.asarray(part.mesh.vertices, dtype=np.float64)
        if vertices.shape != self.vertices_m.shape:
            return None
        if np.abs(vertices - self.vertices_m).max() <= VERTEX_MATCH_ATOL_M:
            return np.arange(len(vertices))
        from scipy.spatial import cKDTree

        distance, index = cKDTree(self.vertices_m).query(vertices)
        if distance.max() > VERTEX_MATCH_ATOL_M or len(np.unique(index)) != len(index):
            return None
        return np.asarray(index, dtype=np.int64)

    def field_on(self, part: ObjectModel, computed: DescriptorField, source: str) -> DescriptorField:
        """The trained field on ``part``'s vertices, after checking that it is ``computed`` (``part``'s own
        field, same dim and symmetry) within :data:`~don_gym.descriptors.FIELD_MATCH_ATOL`; else
        CheckpointError naming ``source`` and the part and saying what to do."""
        if self.field is None:
            raise DonGymError(f"{source}: carries no descriptor field")
        order = self.vertex_order(part)
        if order is None:
            raise CheckpointError(
                f"{source}: part {part.name!r} has the shape of the part the network was trained on but not its "
                f"vertices in the same object frame (within {VERTEX_MATCH_ATOL_M:g} m), so its descriptor field "
                f"cannot be placed on it; {FIELD_ADVICE}"
            )
        trained = dataclasses.replace(
            self.field, vertex_descriptors=self.field.vertex_descriptors[order], mesh_hash=part.mesh_hash
        )
        difference = trained.max_difference(computed)
        if difference > FIELD_MATCH_ATOL:
            raise CheckpointError(
                f"{source}: trained towards a descriptor field that differs from part {part.name!r}'s by "
                f"{difference:.3g} (max abs difference; tolerance {FIELD_MATCH_ATOL:g}); {FIELD_ADVICE}"
            )
        return trained


def checkpoint_part_space(metadata: CheckpointMetadata) -> PartSpace | None:
    """The descriptor space of a network of several parts (:attr:`CheckpointMetadata.part_space`), None for a
    one-part network; CheckpointError when the record is damaged."""
    if not metadata.part_space:
        return None
    try:
        return PartSpace.from_dict(metadata.part_space, "checkpoint metadata part_space")
    except DonGymError as exc:
        raise CheckpointError(str(exc)) from None


def part_index_in(space: PartSpace, part: ObjectModel) -> int | None:
    """Index of ``part`` among a space's parts, by shape signature (by name for a region without one)."""
    for k, region in enumerate(space.parts):
        if region.signature is None:
            if region.name == part.name:
                return k
        elif not part.shape_signature.differences(region.signature):
            return k
    return None


def part_mismatch(metadata: CheckpointMetadata, part: ObjectModel) -> str | None:
    """Why the network of ``metadata`` is not for ``part``, or None when it is: decided by the shape
    signature; a checkpoint without one (format 1) by name (:func:`~don_gym.objects.part_name`). A network of
    several parts (:attr:`CheckpointMetadata.part_space`) is for each of its parts."""
    if metadata.part_space:
        try:
            space = checkpoint_part_space(metadata)
        except CheckpointError as exc:
            return str(exc)
        if part_index_in(space, part) is not None:
            return None
        return (
            f"trained on the parts {list(space.names)}, and part {part.name!r} ({part.source}) has the shape of "
            "none of them; use a network trained on this part"
        )
    if not metadata.object_signature:
        if part_name(metadata.object_name) != part.name:
            return f"object_name is {metadata.object_name!r}, expected {part.name!r}"
        return None
    try:
        trained = ShapeSignature.from_dict(metadata.object_signature, "object_signature")
    except MeshError as exc:
        return str(exc)
    differences = part.shape_signature.differences(trained)
    if not differences:
        return None
    return (
        f"trained on part {metadata.object_name!r}, but part {part.name!r} ({part.source}) has another shape "
        f"({', '.join(differences[:3])}: this part vs the trained one); use a network trained on this part "
        "(build a dataset of it and train one)"
    )


def save_checkpoint(
    path: str | Path,
    model: DenseObjectNet,
    metadata: CheckpointMetadata | Mapping[str, Any],
    weights_dtype: str = "float32",
    identity: PartIdentity | None = None,
) -> CheckpointMetadata:
    """Write ``model`` and ``metadata`` to ``path`` (``.safetensors``) atomically; returns the metadata written.

    The weights are the model's state dict (float32, or float16 on request: :data:`WEIGHT_DTYPES`);
    the safetensors metadata holds one key, ``"don_gym"``, whose value is the JSON of
    :class:`CheckpointMetadata`, including a SHA-256 of the weights. safetensors never executes
    code on load (unlike a pickled ``.pth``), and the hash catches corruption that leaves the
    file size intact.

    ``metadata`` is a :class:`CheckpointMetadata` or a mapping of its field names.
    ``arch``, ``descriptor_dim`` and the normalisation are taken from the model; if the
    metadata states them differently, that is an error rather than a silent overwrite.
    ``weights_dtype="float16"`` halves the file (floating-point tensors only).
    ``identity`` (:meth:`PartIdentity.of` the trained part and field) is stored as tensors beside the
    weights and fills ``object_signature``, ``descriptor_field`` and ``identity_sha256``; without it they
    are empty and users of the network match it to a part by name only.
    """
    path = Path(path)
    if not isinstance(metadata, CheckpointMetadata):
        metadata = CheckpointMetadata.from_dict(metadata, source=f"checkpoint metadata for {path}", strict=True)
    if metadata.method not in METHODS:
        raise DonGymError(f"checkpoint metadata: method {metadata.method!r} is unknown; expected one of {METHODS}")
    if weights_dtype not in WEIGHT_DTYPES:
        raise DonGymError(f"weights_dtype must be one of {sorted(WEIGHT_DTYPES)}, got {weights_dtype!r}")
    if len(metadata.image_size) != 2 or min(metadata.image_size) < 1:
        raise DonGymError(f"checkpoint metadata: image_size must be (W, H) > 0, got {metadata.image_size}")
    from_model = {
        "arch": model.arch,
        "descriptor_dim": model.descriptor_dim,
        "normalization_mean": tuple(model.normalization_mean),
        "normalization_std": tuple(model.normalization_std),
    }
    defaults = {"arch": "", "descriptor_dim": 0, "normalization_mean": IMAGENET_MEAN, "normalization_std": IMAGENET_STD}
    for name, value in from_model.items():
        stated = getattr(metadata, name)
        stated = tuple(stated) if isinstance(stated, (tuple, list)) else stated
        if stated != defaults[name] and stated != value:
            raise DonGymError(f"checkpoint metadata states {name}={stated!r} but the model has {value!r}")
    try:
        json.dumps(metadata.extra)  # fail before writing anything
    except (TypeError, ValueError) as exc:
        raise DonGymError(f"checkpoint metadata for {path}: extra is not JSON-serialisable ({exc})") from exc
    dtype = WEIGHT_DTYPES[weights_dtype]
    tensors = {
        # safetensors wants dense row-major tensors; the model keeps conv weights channels-last.
        name: (t.to(dtype) if t.is_floating_point() else t).detach().cpu().contiguous().clone()
        for name, t in model.state_dict().items()
    }
    from don_gym import __version__

    final = dataclasses.replace(
        metadata,
        image_size=tuple(int(v) for v in metadata.image_size),
        weights_dtype=weights_dtype,
        weights_sha256=_weights_sha256(tensors),
        don_gym_version=__version__,
        format_version=FORMAT_VERSION,
        **from_model,
    )
    return _write(path, tensors, final, identity)


def _write(
    path: Path, weights: dict[str, torch.Tensor], metadata: CheckpointMetadata, identity: PartIdentity | None
) -> CheckpointMetadata:
    """Write ``weights`` and ``identity``'s tensors with ``metadata`` (its identity fields filled in) atomically."""
    extra = identity.tensors() if identity is not None else {}
    final = dataclasses.replace(
        metadata,
        object_signature=identity.signature.to_dict() if identity is not None else {},
        descriptor_field=identity.field_settings() if identity is not None else {},
        identity_sha256=_weights_sha256(extra) if extra else "",
    )
    from safetensors.torch import save_file

    with atomic_path(path) as tmp:
        save_file(weights | extra, str(tmp), metadata={METADATA_KEY: json.dumps(final.to_dict(), sort_keys=True)})
    return final


def _existing_file(path: Path) -> None:
    if not path.exists():
        raise CheckpointError(f"checkpoint {path}: no such file")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: not a file")


def read_checkpoint_metadata(path: str | Path) -> CheckpointMetadata:
    """The :class:`CheckpointMetadata` of a checkpoint, without loading its weights."""
    path = Path(path)
    _existing_file(path)
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            raw = handle.metadata() or {}
    except Exception as exc:  # safetensors raises its own error type for any bad header
        raise CheckpointError(
            f"checkpoint {path}: not a readable safetensors file (corrupt or truncated?): {type(exc).__name__}: {exc}"
        ) from exc
    if METADATA_KEY not in raw:
        raise CheckpointError(
            f"checkpoint {path}: a safetensors file but not a don_gym checkpoint (no {METADATA_KEY!r} metadata)"
        )
    try:
        data = json.loads(raw[METADATA_KEY])
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"checkpoint {path}: don_gym metadata is not valid JSON ({exc})") from exc
    version = data.get("format_version") if isinstance(data, dict) else None
    if isinstance(version, int) and version > FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path}: format_version is {version}, expected <= {FORMAT_VERSION} "
            "(written by a newer don_gym; upgrade don_gym)"
        )
    metadata = CheckpointMetadata.from_dict(data, source=f"checkpoint {path}")
    _check(metadata.method in METHODS, f"checkpoint {path}: method is {metadata.method!r}, expected one of {METHODS}")
    _check(metadata.arch in ARCHS, f"checkpoint {path}: arch is {metadata.arch!r}, expected one of {sorted(ARCHS)}")
    _check(metadata.descriptor_dim >= 1, f"checkpoint {path}: descriptor_dim is {metadata.descriptor_dim}")
    _check(
        metadata.weights_dtype in WEIGHT_DTYPES,
        f"checkpoint {path}: weights_dtype is {metadata.weights_dtype!r}, expected one of {sorted(WEIGHT_DTYPES)}",
    )
    return metadata


def read_part_identity(path: str | Path, metadata: CheckpointMetadata | None = None) -> PartIdentity | None:
    """The :class:`PartIdentity` stored in a checkpoint (None for one saved without it, e.g. format 1),
    checked against its ``identity_sha256``; ``metadata``: the file's, if already read."""
    path = Path(path)
    metadata = metadata if metadata is not None else read_checkpoint_metadata(path)
    if not metadata.object_signature:
        return None
    names = PART_TENSORS + (FIELD_TENSORS if metadata.descriptor_field else ())
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            missing = sorted(set(names) - set(handle.keys()))
            _check(
                not missing,
                f"checkpoint {path}: its metadata states a part identity but the tensors {missing} are missing",
            )
            tensors = {name: handle.get_tensor(name) for name in names}
    except CheckpointError:
        raise
    except Exception as exc:  # safetensors raises its own error type for damaged data
        raise CheckpointError(
            f"checkpoint {path}: part identity cannot be read (corrupt or truncated?): {type(exc).__name__}: {exc}"
        ) from exc
    digest = _weights_sha256(tensors)
    _check(
        digest == metadata.identity_sha256,
        f"checkpoint {path}: identity_sha256 is {digest[:16]}... for the stored part identity, expected "
        f"{metadata.identity_sha256[:16]}... from its metadata (the file is corrupt)",
    )
    try:
        signature = ShapeSignature.from_dict(metadata.object_signature, f"checkpoint {path}: object_signature")
    except MeshError as exc:
        raise CheckpointError(str(exc)) from exc
    vertices = tensors["part.vertices_m"].numpy().astype(np.float64)
    faces = tensors["part.faces"].numpy().astype(np.int64)
    _check(
        vertices.ndim == 2 and vertices.shape[1:] == (3,) and faces.ndim == 2 and faces.shape[1:] == (3,),
        f"checkpoint {path}: part mesh has vertices {tuple(vertices.shape)} and faces {tuple(faces.shape)}; "
        "expected (N, 3) and (F, 3)",
    )
    field_obj = None
    if metadata.descriptor_field:
        settings = metadata.descriptor_field
        try:
            field_obj = DescriptorField(
                vertex_descriptors=tensors["field.vertex_descriptors"].numpy().astype(np.float32),
                eigenvalues=tensors["field.eigenvalues"].numpy().astype(np.float64),
                groups=tuple(tuple(int(i) for i in g) for g in settings["groups"]),
                background=tensors["field.background"].numpy().astype(np.float32),
                symmetric=bool(settings["symmetric"]),
                mesh_hash=mesh_content_hash(vertices, faces),
                tolerance=float(settings["tolerance"]),
                solver=str(settings["solver"]),
                embedded_vertices=int(settings["embedded_vertices"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"checkpoint {path}: invalid descriptor_field settings ({exc})") from exc
        _check(
            field_obj.n_vertices == len(vertices) and field_obj.background.shape == (field_obj.dim,),
            f"checkpoint {path}: descriptor field of {field_obj.n_vertices} vertices and background "
            f"{tuple(field_obj.background.shape)} does not fit its part's {len(vertices)} vertices",
        )
    return PartIdentity(signature, vertices, faces, field_obj)


def check_metadata(
    metadata: CheckpointMetadata,
    source: str,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    expect_field_hash: str | None = None,
    expect_part: ObjectModel | None = None,
) -> None:
    """Raise :class:`CheckpointError` listing every field that differs from what the caller expects.

    ``expect_part`` is the part the network will describe: matched by geometry (:func:`part_mismatch`);
    ``expect_object`` compares the recorded name only.
    """
    expectations = {
        "object_name": expect_object,
        "descriptor_dim": expect_descriptor_dim,
        "method": expect_method,
        "descriptor_field_hash": expect_field_hash,
    }
    problems = [
        f"{name} is {getattr(metadata, name)!r}, expected {expected!r}"
        for name, expected in expectations.items()
        if expected is not None and getattr(metadata, name) != expected
    ]
    mismatch = part_mismatch(metadata, expect_part) if expect_part is not None else None
    if mismatch:
        problems.append(mismatch)
    if problems:
        raise CheckpointError(f"checkpoint {source}: " + "; ".join(problems))


def load_checkpoint(
    path: str | Path,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    expect_field_hash: str | None = None,
    map_location: str | torch.device = "cpu",
    expect_part: ObjectModel | None = None,
) -> tuple[DenseObjectNet, CheckpointMetadata]:
    """Load a checkpoint written by :func:`save_checkpoint`: ``(model in eval mode, metadata)``.

    Each ``expect_*`` that is not None must equal the stored value (object name,
    descriptor dimension, method, descriptor-field hash; ``expect_part``: the part, by geometry, see
    :func:`check_metadata`), else :class:`CheckpointError`. So does
    a missing, truncated or corrupt file, or a safetensors file that is not a don_gym checkpoint;
    the message names the file, the field, the value found and the value expected.
    """
    path = Path(path)
    metadata = read_checkpoint_metadata(path)
    check_metadata(
        metadata, str(path), expect_object, expect_descriptor_dim, expect_method, expect_field_hash, expect_part
    )
    tensors = _read_weights(path, metadata)
    model = DenseObjectNet(
        metadata.arch,
        metadata.descriptor_dim,
        normalization_mean=metadata.normalization_mean,
        normalization_std=metadata.normalization_std,
    )
    own = model.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    mismatched = [k for k in own if k in tensors and tuple(own[k].shape) != tuple(tensors[k].shape)]
    _check(
        not (missing or unexpected or mismatched),
        f"checkpoint {path}: weights do not fit arch {metadata.arch!r} with descriptor_dim "
        f"{metadata.descriptor_dim}: missing {missing[:5]}, unexpected {unexpected[:5]}, "
        f"shape differs {mismatched[:5]}",
    )
    model.load_state_dict(tensors)  # copy_ converts float16 weights to the model's float32
    return model.to(map_location).eval(), metadata


def _read_weights(path: Path, metadata: CheckpointMetadata) -> dict[str, torch.Tensor]:
    """The stored weights (every tensor but the part identity's), checked against ``weights_sha256``."""
    from safetensors.torch import load_file

    try:
        tensors = load_file(str(path), device="cpu")
    except Exception as exc:  # truncated data shows up only here
        raise CheckpointError(
            f"checkpoint {path}: weights cannot be read (corrupt or truncated?): {type(exc).__name__}: {exc}"
        ) from exc
    tensors = {name: t for name, t in tensors.items() if name not in PART_TENSORS + FIELD_TENSORS}
    digest = _weights_sha256(tensors)
    _check(
        digest == metadata.weights_sha256,
        f"checkpoint {path}: weights_sha256 is {digest[:16]}... for the stored weights, expected "
        f"{metadata.weights_sha256[:16]}... from its metadata (the file is corrupt)",
    )
    return tensors


def restamp_checkpoint(
    path: str | Path, part: ObjectModel, candidate_fields: Sequence[DescriptorField] = ()
) -> tuple[CheckpointMetadata, str]:
    """Add the part identity of ``part`` (and, for a supervised network, its descriptor field) to a
    checkpoint saved without one, leaving its weights byte for byte as they are; ``(metadata, what was done)``.

    The checkpoint must have been trained on ``part``: its recorded name and ``object_mesh_hash`` must be
    ``part``'s. The field is the first of ``candidate_fields`` (e.g. its dataset's ``descriptor_field.npz``),
    else :func:`~don_gym.descriptors.embed` of ``part`` computed here, whose ``field_hash`` is the recorded
    ``descriptor_field_hash``. Both hashes are of float bytes, so run this where the network was trained
    (or where the same code gives the same bytes); without a matching field only the part is stamped, and
    users take reference descriptors from a reference frame. Idempotent: a checkpoint that already has all
    it can get is left untouched, and one stamped without a field gets it once a matching one is found.
    """
    path = Path(path)
    metadata = read_checkpoint_metadata(path)
    existing = read_part_identity(path, metadata)
    wants_field = is_supervised(metadata.method)
    if existing is not None:
        differences = part.shape_signature.differences(existing.signature)
        _check(
            not differences and existing.vertex_order(part) is not None,
            f"checkpoint {path}: carries the identity of another part than {part.name!r} "
            f"({', '.join(differences[:3]) or 'other vertices'}); nothing restamped",
        )
        if existing.field is not None or not wants_field:
            return metadata, "unchanged: carries its part identity" + (" and field" if existing.field else "")
    elif part_name(metadata.object_name) != part.name or metadata.object_mesh_hash != part.mesh_hash:
        raise CheckpointError(
            f"checkpoint {path}: trained on part {metadata.object_name!r} with mesh hash "
            f"{metadata.object_mesh_hash}, but part {part.name!r} has mesh hash {part.mesh_hash} here; restamp "
            "it with the part it was trained on, where that part's mesh is built as the trainer's was"
        )
    field_obj = None
    if wants_field:
        recorded = metadata.descriptor_field_hash
        found = [f for f in candidate_fields if f.field_hash == recorded and f.n_vertices == len(part.mesh.vertices)]
        space = checkpoint_part_space(metadata)  # the part's own field has the space's field_dim
        dim = space.field_dim if space is not None else metadata.descriptor_dim
        computed = [] if found else [embed(part, dim=dim, symmetric=s) for s in (True, False)]
        found += [f for f in computed if f.field_hash == recorded]
        field_obj = found[0] if found else None
        if field_obj is None and existing is not None:
            return metadata, f"unchanged: carries its part identity; still no field with hash {recorded}"
    weights = _read_weights(path, metadata)
    final = _write(
        path, weights, dataclasses.replace(metadata, format_version=FORMAT_VERSION), PartIdentity.of(part, field_obj)
    )
    if not wants_field:
        return final, "stamped the part identity (no field: not a supervised network)"
    if field_obj is not None:
        return final, f"stamped the part identity and its descriptor field {recorded}"
    others = ", ".join(sorted({f.field_hash for f in list(candidate_fields) + computed}))
    return final, (
        f"stamped the part identity only: no field has the recorded hash {recorded} (found: {others}), so "
        "its users take reference descriptors from a reference frame"
    )
