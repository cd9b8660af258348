"""Ready-trained DONs shipped inside the package, loadable by a short name.

Short names are ``"<object>/<method>"``, e.g. ``"toolcap/supervised-edge"``; the files
live in ``don_gym/shipped/<object>/<method>.safetensors`` and are reproduced from
scratch by ``benchmarks/train_shipped.py`` (command, seeds, times and final losses in
``benchmarks/RESULTS.md``). Networks of several parts, trained on bin piles, are ``"bin/<method>"``
(:func:`shipped_multi_part_names`; made by the commands in docs/bin.md).
"""

from __future__ import annotations

from pathlib import Path

from don_gym.errors import CheckpointError
from don_gym.learning.checkpoints import (
    CheckpointMetadata,
    check_metadata,
    load_checkpoint,
    part_mismatch,
    read_checkpoint_metadata,
)
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import ObjectModel

SHIPPED_DIR = Path(__file__).resolve().parent / "shipped"


def shipped_names() -> list[str]:
    """Short names of the networks in this installation, e.g. ``["shaft/self-supervised", ...]``."""
    return sorted(f"{p.parent.name}/{p.stem}" for p in SHIPPED_DIR.glob("*/*.safetensors"))


def shipped_multi_part_names() -> list[str]:
    """Short names of the shipped networks of several parts (trained on bin piles, e.g.
    ``"bin/supervised-edge"``): each is for every part of its descriptor space (its checkpoint's ``part_space``)."""
    return [name for name in shipped_names() if read_checkpoint_metadata(shipped_path(name)).part_space]


def shipped_names_for(part: ObjectModel) -> list[str]:
    """Short names of the shipped networks trained on ``part``, matched by its geometry
    (:func:`~don_gym.learning.checkpoints.part_mismatch`), not by its name."""
    return [
        name for name in shipped_names() if part_mismatch(read_checkpoint_metadata(shipped_path(name)), part) is None
    ]


def shipped_path(name: str) -> Path:
    """File of a shipped network; CheckpointError listing the available names otherwise."""
    path = SHIPPED_DIR / f"{name}.safetensors"
    if "/" not in name or not path.is_file():
        available = ", ".join(shipped_names()) or "none (run benchmarks/train_shipped.py)"
        raise CheckpointError(f"no shipped network named {name!r}; available: {available}")
    return path


def is_checkpoint_reference(name_or_path: str | Path) -> bool:
    """True for a path to an existing file, a training run directory (with ``model.safetensors``) or a
    shipped short name: what :func:`checkpoint_path` resolves."""
    text = str(name_or_path)
    path = Path(text)
    return path.is_file() or (path / "model.safetensors").is_file() or (SHIPPED_DIR / f"{text}.safetensors").is_file()


def checkpoint_path(name_or_path: str | Path) -> Path:
    """The checkpoint file meant by a shipped short name, a checkpoint file or a training run
    directory (its ``model.safetensors``); CheckpointError listing the shipped names otherwise."""
    text = str(name_or_path)
    path = Path(text)
    if path.is_dir() and (path / "model.safetensors").is_file():
        return path / "model.safetensors"
    if path.is_file():
        return path
    if (SHIPPED_DIR / f"{text}.safetensors").is_file():
        return shipped_path(text)
    # Neither: say what was wrong with what the user evidently meant.
    if path.is_dir():
        raise CheckpointError(f"{text!r} is a directory without model.safetensors (not a training run directory)")
    if path.suffix or path.is_absolute():
        raise CheckpointError(f"checkpoint {text!r}: no such file")
    return shipped_path(text)


def read_don_metadata(
    name_or_path: str | Path,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    expect_part: ObjectModel | None = None,
) -> CheckpointMetadata:
    """What :func:`load_don` would check and return as metadata, without loading the weights
    (training image size, object, method, ...); CheckpointError naming what differs."""
    path = checkpoint_path(name_or_path)
    metadata = read_checkpoint_metadata(path)
    check_metadata(metadata, str(path), expect_object, expect_descriptor_dim, expect_method, expect_part=expect_part)
    return metadata


def load_don(
    name_or_path: str | Path,
    expect_object: str | None = None,
    expect_descriptor_dim: int | None = None,
    expect_method: str | None = None,
    map_location: str = "cpu",
    expect_part: ObjectModel | None = None,
) -> tuple[DenseObjectNet, CheckpointMetadata]:
    """Load a shipped network by short name, a checkpoint file or a training run directory
    (its ``model.safetensors``), checking expectations (``expect_part``: the part it must have been
    trained on, by geometry; ``expect_object``: its recorded name).

    Returns ``(model in eval mode, metadata)``; raises CheckpointError naming what differs.
    """
    return load_checkpoint(
        checkpoint_path(name_or_path),
        expect_object=expect_object,
        expect_descriptor_dim=expect_descriptor_dim,
        expect_method=expect_method,
        map_location=map_location,
        expect_part=expect_part,
    )
