"""On-disk DON datasets: one format feeding both training methods (layout: ``docs/dataset_format.md``).

A dataset directory holds recorded scenes of one object (the paper's "static scene recordings") with
descriptor targets for the supervised method and fused depth and masks for the self-supervised one.
A scene is written into a hidden temporary directory and renamed into place when complete, so a
scene is complete iff its directory exists; writers of one dataset coordinate through ``.lock``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from don_gym.errors import DatasetError
from don_gym.geometry import CameraIntrinsics
from don_gym.io import DirectoryLock, atomic_path, write_png, write_text_atomic
from don_gym.processes import process_alive

__all__ = [
    "DATASET_FILE",
    "DEPTH_KINDS",
    "DEPTH_SOURCES",
    "FIELD_FILE",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FRAME_KINDS",
    "IDENTITY_DEFAULTS",
    "IDENTITY_KEYS",
    "MASK_KINDS",
    "OPTIONAL_FRAME_KINDS",
    "PNG_SIGNATURE",
    "SCENE_FILE",
    "SCENE_KINDS",
    "DONDataset",
    "DatasetLock",
    "SceneRecord",
    "check_dataset_identity",
    "check_dataset_info",
    "check_png_size",
    "decode_depth_mm",
    "decode_png",
    "encode_depth_mm",
    "frame_path",
    "has_fused_depth",
    "instance_mask",
    "new_partial_dir",
    "new_scene_tmp_dir",
    "part_differences",
    "png_size",
    "primary_part_record",
    "publish_scene",
    "read_frame_image",
    "read_json",
    "remove_dead_partial_dirs",
    "remove_stale_scene_dirs",
    "scene_dir",
    "scene_is_complete",
    "write_frame",
    "write_json",
]

if TYPE_CHECKING:  # imported where used, to keep this module light
    from don_gym.descriptors import DescriptorField
    from don_gym.objects import ShapeSignature

FORMAT_NAME = "don_gym-dataset"
FORMAT_VERSION = 2
DATASET_FILE = "dataset.json"
FIELD_FILE = "descriptor_field.npz"
SCENE_FILE = "scene.json"

#: Image kinds stored per frame, with their on-disk encoding.
FRAME_KINDS = ("rgb", "depth", "depth_ideal", "depth_fused", "mask", "mask_fused", "target_mask", "descriptor")
#: Image kinds a scene may store (version 2): ``instance``, the visible instance id per pixel.
OPTIONAL_FRAME_KINDS = ("instance",)
#: ``scene_kind`` of ``dataset.json`` (version 2): today's single-part scenes, piles of parts, BOP imports.
SCENE_KINDS = ("single", "bin", "bop")
DEPTH_KINDS = ("depth", "depth_ideal", "depth_fused")
MASK_KINDS = ("mask", "mask_fused", "target_mask")
#: Named depth sources: the (depth kind, object-mask kind) images each one reads.
DEPTH_SOURCES = {"fused": ("depth_fused", "mask_fused"), "sensor": ("depth", "mask"), "ideal": ("depth_ideal", "mask")}

#: Settings of ``dataset.json`` that shape the data, so they must be equal for two builds to share a
#: directory, each with the ``build-dataset`` option that sets it (named in refusals). The part and the
#: descriptor field are compared by value within tolerances (:func:`check_dataset_identity`), never by
#: hashes of float bits, which differ between machines for the same part.
IDENTITY_KEYS = {
    "descriptor_dim": "--dim",
    "symmetric": "--no-symmetry",
    "image_size": "--size",
    "frames_per_scene": "--frames",
    "sensor": "--sensor",
    "renderer": "--renderer",
    "seed": "--seed",
    "fuse_depth": "--no-fusion",
    "voxel_size_m": "voxel_size_m",
    "backgrounds": "--backgrounds",
    "distractors": "--distractors",
    "lighting": "--lighting",
}
#: Values of identity settings that datasets written before the setting existed recorded implicitly.
IDENTITY_DEFAULTS = {"backgrounds": "classic", "distractors": 0, "lighting": "fixed"}


def scene_dir(root: str | Path, scene_index: int) -> Path:
    return Path(root) / "scenes" / f"scene_{scene_index:06d}"


def frame_path(scene_path: Path, kind: str, frame_index: int, descriptor_dim: int = 3) -> Path:
    suffix = ".npy" if kind == "descriptor" and descriptor_dim != 3 else ".png"
    return scene_path / kind / f"{frame_index:06d}{suffix}"


# --- encoding ---------------------------------------------------------------------------


def encode_depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) metres -> uint16 millimetres, 0 kept for no return, rounded to the nearest mm."""
    depth_m = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(depth_m) & (depth_m > 0)
    depth_mm = np.zeros(depth_m.shape, dtype=np.uint16)
    depth_mm[valid] = np.clip(np.rint(depth_m[valid] * 1000.0), 1, 65535).astype(np.uint16)
    return depth_mm


def decode_depth_mm(depth_mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> (H, W) float32 metres, 0 = no return."""
    return np.asarray(depth_mm, dtype=np.float32) / 1000.0


def decode_png(data: bytes, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """The pixels of PNG bytes ``data``; None if they do not decode. OpenCV's log is silenced meanwhile:
    its warnings about a truncated or corrupt file would reach the user beside the caller's own error."""
    if not data:
        return None
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    finally:
        cv2.utils.logging.setLogLevel(level)


#: The first bytes of every PNG file.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels that PNG bytes ``data`` declare in their header (the IHDR chunk, bytes 16-24),
    read without decoding a pixel; None for bytes that do not begin as a PNG."""
    if len(data) < 24 or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def check_png_size(data: bytes, size: tuple[int, int], path: Path) -> None:
    """DatasetError naming ``path`` unless PNG bytes ``data`` declare ``size`` (width, height) in their header:
    a frame of another size is refused before it is decoded (a header may declare 16000x12000 in 0.5 MB)."""
    declared = png_size(data)
    if declared is None:
        raise DatasetError(f"{path}: unreadable image (empty, truncated or not a PNG)")
    if tuple(declared) != tuple(size):
        raise DatasetError(
            f"{path}: a {declared[0]}x{declared[1]} image (its PNG header); expected {size[0]}x{size[1]}, the size of "
            "its scene's frames; the file was replaced or damaged (rebuild the scene: delete it and resume)"
        )


def _read_png(path: Path, flags: int = cv2.IMREAD_UNCHANGED, size: tuple[int, int] | None = None) -> np.ndarray:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: missing or unreadable image ({exc.strerror or exc})") from None
    if size is not None:
        check_png_size(data, size, path)
    image = decode_png(data, flags)
    if image is None:
        raise DatasetError(f"{path}: unreadable image (empty, truncated or not a PNG)")
    return image


def write_frame(scene_path: Path, frame_index: int, images: Mapping[str, np.ndarray], descriptor_dim: int) -> None:
    """Write one frame's images (any subset of ``FRAME_KINDS``) atomically.

    ``rgb`` uint8 (H, W, 3); depth kinds float metres; mask kinds bool; ``descriptor``
    float (H, W, D) in [0, 1]; ``instance`` int (H, W), the visible instance id (0 = none), as 16-bit PNG.
    """
    for kind, image in images.items():
        if kind not in FRAME_KINDS + OPTIONAL_FRAME_KINDS:
            raise ValueError(f"unknown frame kind {kind!r}; expected one of {FRAME_KINDS + OPTIONAL_FRAME_KINDS}")
        path = frame_path(scene_path, kind, frame_index, descriptor_dim)
        if kind == "rgb":
            write_png(path, cv2.cvtColor(np.asarray(image, dtype=np.uint8), cv2.COLOR_RGB2BGR))
        elif kind in DEPTH_KINDS:
            write_png(path, encode_depth_mm(image))
        elif kind in MASK_KINDS:
            write_png(path, np.asarray(image, dtype=bool).astype(np.uint8) * 255)
        elif kind == "instance":
            ids = np.asarray(image)
            if ids.size and (ids.min() < 0 or ids.max() > 65535):
                raise ValueError("instance ids must lie in 0..65535")
            write_png(path, ids.astype(np.uint16))
        elif descriptor_dim == 3:
            quantised = np.rint(np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * 65535.0).astype(np.uint16)
            write_png(path, quantised[..., ::-1])
        else:
            with atomic_path(path) as tmp:
                np.save(tmp, np.asarray(image, dtype=np.float16))


def read_frame_image(
    scene_path: Path, kind: str, frame_index: int, descriptor_dim: int = 3, size: tuple[int, int] | None = None
) -> np.ndarray:
    """Inverse of :func:`write_frame` for one kind: RGB uint8, depth float32 metres,
    masks bool, descriptor float32 (H, W, D). ``size`` (width, height): the frame's size; a file that
    declares another is refused (DatasetError naming it) before it is decoded."""
    path = frame_path(scene_path, kind, frame_index, descriptor_dim)
    if kind == "rgb":
        return cv2.cvtColor(_read_png(path, cv2.IMREAD_COLOR, size), cv2.COLOR_BGR2RGB)
    if kind in DEPTH_KINDS:
        return decode_depth_mm(_read_png(path, size=size))
    if kind in MASK_KINDS:
        return _read_png(path, cv2.IMREAD_GRAYSCALE, size) > 127
    if kind == "instance":
        if not path.is_file():
            raise DatasetError(
                f"{path}: missing; this scene stores no instance image (a single-part scene: its mask is instance 1; "
                "use don_gym.data.dataset.instance_mask)"
            )
        return _read_png(path, cv2.IMREAD_UNCHANGED, size).astype(np.int32)
    if kind == "descriptor":
        if descriptor_dim == 3:
            return _read_png(path, size=size)[..., ::-1].astype(np.float32) / 65535.0
        try:
            stored = np.load(path, mmap_mode="r")  # the header alone until the shape is checked
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{path}: missing or unreadable descriptor target ({exc})") from exc
        if size is not None and tuple(stored.shape) != (size[1], size[0], descriptor_dim):
            raise DatasetError(
                f"{path}: a descriptor target of shape {tuple(stored.shape)}; expected "
                f"{(size[1], size[0], descriptor_dim)} (height, width, --dim)"
            )
        return np.array(stored, dtype=np.float32)
    raise ValueError(f"unknown frame kind {kind!r}; expected one of {FRAME_KINDS + OPTIONAL_FRAME_KINDS}")


# --- metadata ---------------------------------------------------------------------------


def _to_jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_jsonable(v) for v in value]
    return value


def write_json(path: Path, data: Mapping[str, Any], *, exclusive: bool = False) -> None:
    """Write ``data`` as JSON atomically; ``exclusive``: only if ``path`` does not exist (FileExistsError)."""
    write_text_atomic(path, json.dumps(_to_jsonable(data), indent=1) + "\n", exclusive=exclusive)


def read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise DatasetError(f"{path}: not found") from exc
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable JSON ({exc})") from exc


def check_dataset_info(info: Any, path: Path) -> dict[str, Any]:
    """``info`` (the parsed ``dataset.json`` at ``path``) if this don_gym can read it, else DatasetError."""
    if not isinstance(info, dict) or info.get("format") != FORMAT_NAME:
        found = info.get("format") if isinstance(info, dict) else type(info).__name__
        raise DatasetError(f"{path}: not a don_gym dataset (format={found!r}; expected {FORMAT_NAME!r})")
    version = info.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise DatasetError(f"{path}: format version {version!r} is not an integer; the file is corrupt")
    if version > FORMAT_VERSION:
        raise DatasetError(
            f"{path}: written by a newer don_gym (format version {version}; this one reads up to "
            f"{FORMAT_VERSION}); upgrade don_gym"
        )
    if version < 1:
        raise DatasetError(f"{path}: unknown format version {version}; expected 1 to {FORMAT_VERSION}")
    return info


def part_differences(info: Mapping[str, Any], signature: ShapeSignature, mesh_hash: str, source: Path) -> list[str]:
    """How a part with ``signature`` (and ``mesh_hash``) differs from the one recorded in ``info`` (the
    ``dataset.json`` at ``source``), as ``"name given vs recorded"``; empty: the same part. Decided by the
    shape signature within :data:`~don_gym.objects.SHAPE_MATCH_RTOL`; a dataset written before signatures
    by its mesh hash (equal only on one machine)."""
    from don_gym.errors import MeshError
    from don_gym.objects import ShapeSignature

    recorded = info.get("object_signature")
    if recorded:
        try:
            return signature.differences(ShapeSignature.from_dict(recorded, f"{source}: object_signature"))
        except MeshError as exc:
            raise DatasetError(f"{exc}; the file is corrupt") from exc
    if info.get("mesh_hash") not in (None, mesh_hash):
        return [f"mesh hash {mesh_hash} vs {info['mesh_hash']}"]
    return []


def check_dataset_identity(
    existing: Mapping[str, Any],
    wanted: Mapping[str, Any],
    root: Path,
    recorded_field: DescriptorField | None = None,
    computed_field: DescriptorField | None = None,
) -> None:
    """Raise DatasetError, naming each differing option with both values, if ``existing`` (dataset.json
    on disk) and ``wanted`` describe different data: settings (:data:`IDENTITY_KEYS`) must be equal, the
    part the same by :func:`part_differences`, and ``recorded_field`` (the dataset's field file) within
    :data:`~don_gym.descriptors.FIELD_MATCH_ATOL` of ``computed_field`` (the part's field computed here)."""
    from don_gym.descriptors import FIELD_MATCH_ATOL
    from don_gym.objects import ShapeSignature

    info_path = Path(root) / DATASET_FILE
    check_dataset_info(existing, info_path)
    on_disk, asked = _to_jsonable(existing), _to_jsonable(wanted)
    on_disk = {**IDENTITY_DEFAULTS, **on_disk}
    different = [k for k in IDENTITY_KEYS if on_disk.get(k) != asked.get(k)]
    details = [f"{k} ({IDENTITY_KEYS[k]}): {on_disk.get(k)!r} on disk, {asked.get(k)!r} asked" for k in different]
    signature = ShapeSignature.from_dict(wanted["object_signature"])
    part = part_differences(existing, signature, str(wanted["mesh_hash"]), info_path)
    if part:
        details.append(f"the part (--object/--object-scale): {', '.join(part[:3])} (asked vs on disk)")
    elif recorded_field is not None and computed_field is not None and not different:
        difference = recorded_field.max_difference(computed_field)
        if difference > FIELD_MATCH_ATOL:
            details.append(
                f"the descriptor field ({FIELD_FILE}) differs from the part's computed here by {difference:.3g} "
                f"(max abs difference; tolerance {FIELD_MATCH_ATOL:g})"
            )
    if details:
        objects = f" [object {existing.get('object')!r} on disk, {wanted.get('object')!r} asked]"
        empty = not any((p / SCENE_FILE).is_file() for p in (Path(root) / "scenes").glob("scene_*"))
        raise DatasetError(
            f"{root}: holds a different dataset ({'; '.join(details)}){objects if part else ''}; "
            f"pass --overwrite to replace it{' (it has no complete scene yet)' if empty else ''} "
            "or use another directory"
        )


# --- writing scenes: temporary directory, then one rename ---------------------------------------

_HOST = "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname()) or "host"


def scene_is_complete(path: Path) -> bool:
    """A scene directory under its final name is complete; one without ``scene.json`` was left by
    an older don_gym (which wrote in place) or damaged by hand, and is rebuilt."""
    return (path / SCENE_FILE).is_file()


def new_scene_tmp_dir(root: Path, scene_index: int) -> Path:
    """A fresh hidden directory next to the scene's final one, named after this host and process."""
    return new_partial_dir(scene_dir(root, scene_index))


def new_partial_dir(final: Path, kind: str = "partial") -> Path:
    """A fresh hidden directory beside ``final`` (``.NAME.partial-HOST-PID-XXXX``) to write it in, then rename
    (``kind`` ``"stale"``: to move an old ``final`` aside onto, then remove): named after this host and process,
    so that :func:`remove_dead_partial_dirs` knows when its writer is gone."""
    final.parent.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(prefix=f".{final.name}.{kind}-{_HOST}-{os.getpid()}-", dir=final.parent))
    # mkdtemp makes it owner-only; the result keeps these permissions, and others may read it.
    umask = os.umask(0)
    os.umask(umask)
    path.chmod(0o777 & ~umask)
    return path


def remove_dead_partial_dirs(final: Path, kinds: tuple[str, ...] = ("partial",)) -> list[Path]:
    """Remove the hidden directories beside ``final`` that processes of this host, now dead, were writing
    (:func:`new_partial_dir`; ``kinds`` ``"partial"`` and ``"stale"``); returns them. A directory of a live process
    or of another host (whose writer may be alive) is left alone, as is any name of another pattern."""
    removed = []
    if not final.parent.is_dir():
        return removed
    for kind in kinds:
        prefix = f".{final.name}.{kind}-{_HOST}-"
        for path in final.parent.iterdir():
            pid = path.name[len(prefix) :].split("-")[0] if path.name.startswith(prefix) else ""
            if pid.isdigit() and path.is_dir() and not path.is_symlink() and not process_alive(int(pid)):
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
    return removed


def publish_scene(tmp: Path, final: Path) -> bool:
    """Rename the complete scene ``tmp`` to ``final``, atomically also on NFS; False (and ``tmp``
    removed) when another writer got there first with its own complete copy."""
    stale = None
    if final.exists() and not scene_is_complete(final):
        stale = final.with_name(f".{final.name}.stale-{_HOST}-{os.getpid()}-{os.urandom(4).hex()}")
        with contextlib.suppress(FileNotFoundError):  # another writer moved it aside first
            os.rename(final, stale)
    try:
        os.rename(tmp, final)
        return True
    except OSError as exc:
        if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY) or not scene_is_complete(final):
            raise
        shutil.rmtree(tmp, ignore_errors=True)
        return False
    finally:
        if stale is not None:
            shutil.rmtree(stale, ignore_errors=True)


def remove_stale_scene_dirs(root: Path, scene_index: int) -> None:
    """Remove temporary directories of scene ``scene_index`` left by dead processes of this host.

    Call it holding the scene's lock: no live process of this machine is then writing the scene.
    Directories of other hosts are left alone (their writers may be alive; readers ignore them).
    """
    remove_dead_partial_dirs(scene_dir(root, scene_index), ("partial", "stale"))


class DatasetLock(DirectoryLock):
    """The writers of one dataset on one machine (:class:`~don_gym.io.DirectoryLock` on ``DIR/.lock``).

    Byte 0 is held shared by every writer for its whole run and exclusively by ``--overwrite``; byte 1
    exclusively while the dataset-level files are checked or written; byte 2 + k while scene k is
    written. Correctness across machines does not rest on them (files are published by atomic
    create and rename); they keep one machine's writers from racing and repeating each other's work.
    """

    _SESSION, _METADATA, _FIRST_SCENE = 0, 1, 2

    def hold_session(self, exclusive: bool = False) -> None:
        """Join the writers of this dataset (shared) or, for ``--overwrite``, become the only one."""
        if self.lock(self._SESSION, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH, blocking=False):
            return
        if exclusive:
            raise DatasetError(
                f"{self.root}: another don-gym process is writing this dataset; wait for it to finish "
                "before --overwrite, or use another directory"
            )
        raise DatasetError(
            f"{self.root}: another don-gym process is replacing this dataset (--overwrite); wait for it to finish"
        )

    def share_session(self) -> None:
        """After ``hold_session(exclusive=True)``: let other writers of the same dataset join."""
        self.lock(self._SESSION, fcntl.LOCK_SH)

    @contextlib.contextmanager
    def metadata(self) -> Iterator[None]:
        self.lock(self._METADATA, fcntl.LOCK_EX)
        try:
            yield
        finally:
            self.lock(self._METADATA, fcntl.LOCK_UN)

    @contextlib.contextmanager
    def scene(self, scene_index: int) -> Iterator[None]:
        self.lock(self._FIRST_SCENE + scene_index, fcntl.LOCK_EX)
        try:
            yield
        finally:
            self.lock(self._FIRST_SCENE + scene_index, fcntl.LOCK_UN)


@dataclass(frozen=True)
class SceneRecord:
    """Metadata of one complete scene, as read from its ``scene.json``."""

    path: Path
    index: int
    intrinsics: CameraIntrinsics
    T_world_object: np.ndarray  # (4, 4)
    T_world_camera: np.ndarray  # (F, 4, 4) true camera poses
    T_world_camera_reported: np.ndarray  # (F, 4, 4) with calibration error: what targets use
    metadata: dict[str, Any]

    @property
    def num_frames(self) -> int:
        return len(self.T_world_camera)

    @property
    def instances(self) -> list[dict[str, Any]]:
        """The annotated part instances: dicts with ``instance_id`` (int >= 1), ``part`` (a name of
        :attr:`DONDataset.parts`) and, in static scenes, ``T_world_object`` (4, 4). A version 1 scene is one
        instance, id 1, of the dataset's object at the scene's ``T_world_object``."""
        recorded = self.metadata.get("instances")
        if recorded is None:
            part = str(self.metadata.get("object", ""))
            return [{"instance_id": 1, "part": part, "T_world_object": self.T_world_object.copy()}]
        instances = []
        for entry in recorded:
            instance = {"instance_id": int(entry["instance_id"]), "part": str(entry["part"])}
            if entry.get("T_world_object") is not None:
                instance["T_world_object"] = np.asarray(entry["T_world_object"], dtype=np.float64)
            instances.append(instance)
        return instances

    def T_camera_object(self, frame: int) -> dict[int, np.ndarray]:
        """The TRUE pose (4, 4; OpenCV camera axes, metres) of each instance annotated in frame ``frame``,
        by instance id: recorded per frame in version 2, else from the true camera pose and the static
        object pose (``inv(T_world_camera[frame]) @ T_world_object``)."""
        if not 0 <= frame < self.num_frames:
            raise IndexError(f"frame {frame}: the scene has frames 0..{self.num_frames - 1}")
        recorded = self.metadata.get("T_camera_object")
        if recorded is not None:
            return {int(k): np.asarray(v, dtype=np.float64) for k, v in recorded[frame].items()}
        T_camera_world = np.linalg.inv(self.T_world_camera[frame])
        return {
            int(i["instance_id"]): T_camera_world @ i["T_world_object"] for i in self.instances if "T_world_object" in i
        }


class DONDataset:
    """Read access to a dataset directory written by ``don-gym build-dataset``.

    Only complete scenes (with ``scene.json``) are listed. Raises DatasetError for a
    missing directory, a directory that is not a don_gym dataset, or a newer format.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            what = "a file" if self.root.is_file() else "not a directory"
            raise DatasetError(
                f"{self.root}: is {what}, not a dataset directory (one written by don-gym build-dataset)"
            )
        if not self.root.is_dir():
            raise DatasetError(f"dataset directory {str(self.root)!r} does not exist")
        info_path = self.root / DATASET_FILE
        if not info_path.is_file():
            raise DatasetError(f"{self.root}: no {DATASET_FILE}; expected a directory written by don-gym build-dataset")
        self.info = check_dataset_info(read_json(info_path), info_path)
        dim = self.info.get("descriptor_dim")
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            raise DatasetError(f"{info_path}: descriptor_dim {dim!r} is not an integer >= 1; the file is corrupt")
        self.descriptor_dim = dim
        self.scene_kind = str(self.info.get("scene_kind", "single"))
        self.scenes = [
            self._read_scene(p) for p in sorted((self.root / "scenes").glob("scene_*")) if (p / SCENE_FILE).is_file()
        ]
        if not self.scenes:
            raise DatasetError(f"{self.root}: no complete scene; run don-gym build-dataset to finish it")

    @property
    def parts(self) -> list[dict[str, Any]]:
        """The distinct parts of the dataset: dicts with ``name``, ``object_source``, ``object_scale``,
        ``object_signature`` and ``mesh_hash``; the first is the primary part (the one of
        ``descriptor_field.npz``, named by the top-level ``object*`` keys). Version 1: that part alone."""
        recorded = self.info.get("parts")
        if recorded:
            return [dict(p) for p in recorded]
        return [primary_part_record(self.info)]

    def _read_scene(self, path: Path) -> SceneRecord:
        meta = read_json(path / SCENE_FILE)
        try:
            _check_v2_scene(meta)
            return SceneRecord(
                path=path,
                index=int(meta["scene_index"]),
                intrinsics=CameraIntrinsics.from_array(np.asarray(meta["intrinsics"])),
                T_world_object=np.asarray(meta["T_world_object"], dtype=np.float64),
                T_world_camera=np.asarray(meta["T_world_camera"], dtype=np.float64),
                T_world_camera_reported=np.asarray(meta["T_world_camera_reported"], dtype=np.float64),
                metadata=meta,
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise DatasetError(f"{path / SCENE_FILE}: missing or malformed field ({exc})") from exc

    @property
    def frames(self) -> list[tuple[int, int]]:
        """All (scene position in ``self.scenes``, frame index) pairs."""
        return [(s, f) for s, scene in enumerate(self.scenes) for f in range(scene.num_frames)]

    def image(self, scene: int, frame: int, kind: str) -> np.ndarray:
        """Frame ``frame`` of scene position ``scene`` as ``kind`` (:func:`read_frame_image`): a file whose header
        declares another size than the scene's camera is refused, naming it, before it is decoded."""
        record = self.scenes[scene]
        size = (record.intrinsics.width, record.intrinsics.height)
        return read_frame_image(record.path, kind, frame, self.descriptor_dim, size)

    def descriptor_field(self):  # -> DescriptorField; imported lazily to keep this module light
        from don_gym.descriptors import DescriptorField

        return DescriptorField.load(self.root / FIELD_FILE)

    def object_model(self):  # -> ObjectModel; imported lazily like descriptor_field
        """The dataset's object loaded as it was built (same scale; a mesh file from ``object_source`` when
        ``object`` was a relative path that is not found from here), checked to be the recorded part: by its
        shape signature, or by mesh hash in a dataset written before signatures. DatasetError otherwise.
        ``object_symmetry_axis`` of ``dataset.json`` (BOP imports) declares a mesh file's symmetry axis."""
        from don_gym.errors import DonGymError
        from don_gym.objects import builtin_names, load_object

        spec, source = str(self.info["object"]), str(self.info.get("object_source", ""))
        if spec not in builtin_names() and self.info.get("scene_kind") == "bop" and (self.root / spec).is_file():
            spec = str(self.root / spec)  # the model stored with the dataset
        elif spec not in builtin_names() and not Path(spec).expanduser().exists() and Path(source).is_file():
            spec = source
        try:
            model = load_object(spec, scale=self.info.get("object_scale"))
            differences = part_differences(self.info, model.shape_signature, model.mesh_hash, self.root / DATASET_FILE)
        except DonGymError as exc:
            raise DatasetError(f"{self.root}: the dataset's object cannot be loaded: {exc}") from exc
        if differences:
            raise DatasetError(
                f"{self.root}: was built from a {self.info['object']!r} part that differs from the one that loads "
                f"now ({', '.join(differences[:3])}: now vs recorded)"
            )
        axis = self.info.get("object_symmetry_axis")
        if axis is not None and model.symmetry_axis is None:
            # A mesh file declares no symmetry; an import may know one (BOP's models_info.json).
            import dataclasses

            unit = np.asarray(axis, dtype=np.float64).reshape(3)
            model = dataclasses.replace(model, symmetry_axis=unit / np.linalg.norm(unit))
        return model


def primary_part_record(info: Mapping[str, Any]) -> dict[str, Any]:
    """The ``parts`` entry of the dataset's primary part, from the top-level keys of ``dataset.json``."""
    from don_gym.objects import part_name

    return {
        "name": str(info.get("object_name") or part_name(str(info.get("object", "")))),
        "object_source": info.get("object_source"),
        "object_scale": info.get("object_scale"),
        "object_signature": info.get("object_signature"),
        "mesh_hash": info.get("mesh_hash"),
    }


def _check_v2_scene(meta: Mapping[str, Any]) -> None:
    """KeyError/ValueError/TypeError for version 2 keys of ``scene.json`` that do not fit together."""
    instances = meta.get("instances")
    if instances is None:
        return
    ids = [int(i["instance_id"]) for i in instances]
    if any(i < 1 for i in ids) or len(set(ids)) != len(ids):
        raise ValueError(f"instance ids {ids}: expected distinct integers >= 1")
    per_frame = meta.get("T_camera_object")
    if per_frame is not None:
        if len(per_frame) != len(meta["T_world_camera"]):
            raise ValueError(
                f"T_camera_object has {len(per_frame)} frames, T_world_camera {len(meta['T_world_camera'])}"
            )
        for poses in per_frame:
            for key, pose in poses.items():
                if int(key) not in ids or np.asarray(pose, dtype=np.float64).shape != (4, 4):
                    raise ValueError(f"T_camera_object: instance {key} is not in instances or its pose is not 4x4")


def instance_mask(data: DONDataset, scene: int, frame: int) -> np.ndarray:
    """(H, W) int32 visible instance id per pixel (0 = none): the scene's ``instance`` image, or for a scene
    without one (single-part scenes) its object ``mask`` as instance 1."""
    record = data.scenes[scene]
    if frame_path(record.path, "instance", frame).is_file():
        return data.image(scene, frame, "instance")
    ids = [i["instance_id"] for i in record.instances]
    if len(ids) != 1:
        raise DatasetError(
            f"{record.path}: {len(ids)} instances and no instance image for frame {frame}; expected "
            f"{frame_path(record.path, 'instance', frame)}"
        )
    return np.where(data.image(scene, frame, "mask"), ids[0], 0).astype(np.int32)


def has_fused_depth(data: DONDataset) -> bool:
    """Whether every scene of ``data`` has TSDF-fused depth and masks (a build without ``--no-fusion``)."""
    return data.info.get("fuse_depth", True) is not False and all(
        scene.metadata.get("fused_depth", True) is not False for scene in data.scenes
    )
