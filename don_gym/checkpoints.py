"""DON checkpoints: safetensors weights plus JSON metadata that says what the network was trained for.

A checkpoint is one ``.safetensors`` file. Its weights are the model's state dict
(float32 by default, float16 on request: :data:`WEIGHT_DTYPES`); its safetensors metadata
holds one key, ``"don_gym"``, whose value is the JSON of :class:`CheckpointMetadata`:
method, descriptor dimension, arch, training image size, object and mesh hash,
descriptor-field hash, input normalisation, renderer, sensor preset, training steps, the
don_gym version and the format version, and a SHA-256 of the weights. safetensors never
executes code on load (unlike a pickled ``.pth``), and the hash catches corruption that
leaves the file size intact.

:func:`load_checkpoint` rebuilds the :class:`~don_gym.model.DenseObjectNet` and checks
the metadata against what the caller needs; every mismatch, a missing, truncated or
corrupt file, or a safetensors file that is not a don_gym checkpoint raises a
:class:`~don_gym.errors.CheckpointError` naming the file, the field, the value found and
the value expected.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from don_gym.errors import CheckpointError, DonGymError
from don_gym.io import atomic_path
from don_gym.methods import METHODS
from don_gym.model import ARCHS, IMAGENET_MEAN, IMAGENET_STD, DenseObjectNet

#: Version of the checkpoint layout; bumped when a reader of the old layout would misread a new file.
FORMAT_VERSION = 1
METADATA_KEY = "don_gym"
WEIGHT_DTYPES = {"float32": torch.float32, "float16": torch.float16}


@dataclass(frozen=True)
class CheckpointMetadata:
    """What a checkpoint was trained on and for.

    Attributes:
        method: one of :data:`don_gym.methods.METHODS`.
        object_name: the object the network describes (``ObjectModel.name``).
        object_mesh_hash: ``ObjectModel.mesh_hash`` of its geometry.
        image_size: ``(W, H)`` in pixels of the training images.
        descriptor_field_hash: hash of the optimal-descriptor field the targets came from
            (supervised methods; empty for ``self-supervised``).
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

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

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
                elif name == "extra":
                    if not isinstance(value, dict):
                        raise TypeError(f"extra must be an object, got {value!r}")
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


def save_checkpoint(
    path: str | Path,
    model: DenseObjectNet,
    metadata: CheckpointMetadata | Mapping[str, Any],
    weights_dtype: str = "float32",
) -> CheckpointMetadata:
    """Write ``model`` and ``metadata`` to ``path`` (``.safetensors``) atomically; returns the metadata written.

    ``metadata`` is a :class:`CheckpointMetadata` or a mapping of its field names.
    ``arch``, ``descriptor_dim`` and the normalisation are taken from the model; if the
    metadata states them differently, that is an error rather than a silent overwrite.
    ``weights_dtype="float16"`` halves the file (floating-point tensors only).
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
    from safetensors.torch import save_file

    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={METADATA_KEY: json.dumps(final.to_dict(), sort_keys=True)})
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


def check_metadata(
    metadata: CheckpointMetadata,
    source: str,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    expect_field_hash: str | None = None,
) -> None:
    """Raise :class:`CheckpointError` listing every field that differs from what the caller expects."""
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
    if problems:
        raise CheckpointError(f"checkpoint {source}: " + "; ".join(problems))


def load_checkpoint(
    path: str | Path,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    expect_field_hash: str | None = None,
    map_location: str | torch.device = "cpu",
) -> tuple[DenseObjectNet, CheckpointMetadata]:
    """Load a checkpoint written by :func:`save_checkpoint`: ``(model in eval mode, metadata)``.

    Each ``expect_*`` that is not None must equal the stored value (object name,
    descriptor dimension, method, descriptor-field hash), else :class:`CheckpointError`.
    """
    path = Path(path)
    metadata = read_checkpoint_metadata(path)
    check_metadata(metadata, str(path), expect_object, expect_descriptor_dim, expect_method, expect_field_hash)
    from safetensors.torch import load_file

    try:
        tensors = load_file(str(path), device="cpu")
    except Exception as exc:  # truncated data shows up only here
        raise CheckpointError(
            f"checkpoint {path}: weights cannot be read (corrupt or truncated?): {type(exc).__name__}: {exc}"
        ) from exc
    digest = _weights_sha256(tensors)
    _check(
        digest == metadata.weights_sha256,
        f"checkpoint {path}: weights_sha256 is {digest[:16]}... for the stored weights, expected "
        f"{metadata.weights_sha256[:16]}... from its metadata (the file is corrupt)",
    )
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
