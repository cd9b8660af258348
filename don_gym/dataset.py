"""On-disk DON datasets: one format feeding both training methods.

A dataset directory holds recorded scenes of one object (the paper's "static scene
recordings"), plus everything each training method needs: descriptor targets rendered
from the object model for the supervised method, and fused depth and masks for the
self-supervised one. Format version 1 (documented in ``docs/dataset_format.md``)::

    DIR/
      dataset.json                 dataset-wide settings (object, sizes, sensor, renderer,
                                   seed, descriptor-field hash, format name and version)
      descriptor_field.npz         the object's optimal descriptor field (DescriptorField)
      scenes/scene_000000/
        scene.json                 written last: marks the scene complete (intrinsics,
                                   per-frame poses, object pose, scene seed, background)
        rgb/000000.png             uint8 RGB
        depth/000000.png           uint16 millimetres, sensor depth (0 = no return)
        depth_ideal/000000.png     uint16 millimetres, simulator z-buffer depth
        depth_fused/000000.png     uint16 millimetres, TSDF-fused sensor depth re-rendered
        mask/000000.png            uint8 {0, 255}, object mask from the simulator's segmentation
        mask_fused/000000.png      uint8 {0, 255}, object mask from the fused model
        target_mask/000000.png     uint8 {0, 255}, mask of the rendered descriptor target
        descriptor/000000.png      uint16 RGB (D = 3) or descriptor/000000.npy float16 (D != 3):
                                   geometric descriptor target in [0, 1], background outside

Frame files are written under a temporary name and renamed; ``scene.json`` is written
only after all frames of the scene, so an interrupted build leaves no half-written frame
and a resumed build redoes exactly the incomplete scenes.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from don_gym.errors import DatasetError
from don_gym.geometry import CameraIntrinsics
from don_gym.io import atomic_path, write_text_atomic

FORMAT_NAME = "don_gym-dataset"
FORMAT_VERSION = 1
DATASET_FILE = "dataset.json"
FIELD_FILE = "descriptor_field.npz"
SCENE_FILE = "scene.json"

#: Image kinds stored per frame, with their on-disk encoding.
FRAME_KINDS = ("rgb", "depth", "depth_ideal", "depth_fused", "mask", "mask_fused", "target_mask", "descriptor")
DEPTH_KINDS = ("depth", "depth_ideal", "depth_fused")
MASK_KINDS = ("mask", "mask_fused", "target_mask")

#: Largest depth a uint16 millimetre PNG can hold, metres.
MAX_DEPTH_M = 65.535

#: Settings that must match for two builds to share a directory.
IDENTITY_KEYS = (
    "object",
    "mesh_hash",
    "descriptor_field_hash",
    "descriptor_dim",
    "image_size",
    "frames_per_scene",
    "sensor",
    "renderer",
    "seed",
)


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


def _write_png(path: Path, image: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"could not write {path}")


def _read_png(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise DatasetError(f"{path}: missing or unreadable image")
    return image


def write_frame(scene_path: Path, frame_index: int, images: Mapping[str, np.ndarray], descriptor_dim: int) -> None:
    """Write one frame's images (any subset of ``FRAME_KINDS``) atomically.

    ``rgb`` uint8 (H, W, 3); depth kinds float metres; mask kinds bool; ``descriptor``
    float (H, W, D) in [0, 1].
    """
    for kind, image in images.items():
        if kind not in FRAME_KINDS:
            raise ValueError(f"unknown frame kind {kind!r}; expected one of {FRAME_KINDS}")
        path = frame_path(scene_path, kind, frame_index, descriptor_dim)
        if kind == "rgb":
            _write_png(path, cv2.cvtColor(np.asarray(image, dtype=np.uint8), cv2.COLOR_RGB2BGR))
        elif kind in DEPTH_KINDS:
            _write_png(path, encode_depth_mm(image))
        elif kind in MASK_KINDS:
            _write_png(path, np.asarray(image, dtype=bool).astype(np.uint8) * 255)
        elif descriptor_dim == 3:
            quantised = np.rint(np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0) * 65535.0).astype(np.uint16)
            _write_png(path, quantised[..., ::-1])
        else:
            with atomic_path(path) as tmp:
                np.save(tmp, np.asarray(image, dtype=np.float16))


def read_frame_image(scene_path: Path, kind: str, frame_index: int, descriptor_dim: int = 3) -> np.ndarray:
    """Inverse of :func:`write_frame` for one kind: RGB uint8, depth float32 metres,
    masks bool, descriptor float32 (H, W, D)."""
    path = frame_path(scene_path, kind, frame_index, descriptor_dim)
    if kind == "rgb":
        return cv2.cvtColor(_read_png(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    if kind in DEPTH_KINDS:
        return decode_depth_mm(_read_png(path))
    if kind in MASK_KINDS:
        return _read_png(path, cv2.IMREAD_GRAYSCALE) > 127
    if kind == "descriptor":
        if descriptor_dim == 3:
            return _read_png(path)[..., ::-1].astype(np.float32) / 65535.0
        try:
            return np.load(path).astype(np.float32)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{path}: missing or unreadable descriptor target ({exc})") from exc
    raise ValueError(f"unknown frame kind {kind!r}; expected one of {FRAME_KINDS}")


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


def write_json(path: Path, data: Mapping[str, Any]) -> None:
    write_text_atomic(path, json.dumps(_to_jsonable(data), indent=1) + "\n")


def read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        raise DatasetError(f"{path}: not found") from exc
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable JSON ({exc})") from exc


def check_dataset_identity(existing: Mapping[str, Any], wanted: Mapping[str, Any], root: Path) -> None:
    """Raise DatasetError if ``existing`` (dataset.json on disk) is a different dataset."""
    if existing.get("format") != FORMAT_NAME:
        raise DatasetError(f"{root}: holds something that is not a don_gym dataset; use an empty directory")
    different = [k for k in IDENTITY_KEYS if _to_jsonable(existing.get(k)) != _to_jsonable(wanted.get(k))]
    if different:
        details = ", ".join(f"{k}: {existing.get(k)!r} on disk vs {wanted.get(k)!r} asked" for k in different)
        raise DatasetError(f"{root}: holds a different dataset ({details}); pass --overwrite to replace it")


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


class DONDataset:
    """Read access to a dataset directory written by ``don-gym build-dataset``.

    Only complete scenes (with ``scene.json``) are listed. Raises DatasetError for a
    missing directory, a directory that is not a don_gym dataset, or a newer format.
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset directory {str(self.root)!r} does not exist")
        info_path = self.root / DATASET_FILE
        if not info_path.is_file():
            raise DatasetError(f"{self.root}: no {DATASET_FILE}; expected a directory written by don-gym build-dataset")
        self.info = read_json(info_path)
        if self.info.get("format") != FORMAT_NAME:
            raise DatasetError(f"{info_path}: not a don_gym dataset (format={self.info.get('format')!r})")
        if int(self.info.get("version", -1)) > FORMAT_VERSION:
            raise DatasetError(
                f"{info_path}: format version {self.info.get('version')} is newer than this don_gym reads "
                f"({FORMAT_VERSION}); upgrade don_gym"
            )
        self.descriptor_dim = int(self.info["descriptor_dim"])
        self.scenes = [
            self._read_scene(p) for p in sorted((self.root / "scenes").glob("scene_*")) if (p / SCENE_FILE).is_file()
        ]
        if not self.scenes:
            raise DatasetError(f"{self.root}: no complete scene; run don-gym build-dataset to finish it")

    def _read_scene(self, path: Path) -> SceneRecord:
        meta = read_json(path / SCENE_FILE)
        try:
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
        return read_frame_image(self.scenes[scene].path, kind, frame, self.descriptor_dim)

    def descriptor_field(self):  # -> DescriptorField; imported lazily to keep this module light
        from don_gym.descriptors import DescriptorField

        return DescriptorField.load(self.root / FIELD_FILE)
