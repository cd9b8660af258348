"""Export a don_gym scene in the layout of the original Dense Object Nets code ("pdc").

Users of the original pipeline (Florence et al. 2018; layout in docs/background.md, section
"Self-supervised DON training") can read our data with their loaders: :func:`export_scene_pdc`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from don_gym.dataset import DONDataset, decode_png, frame_path
from don_gym.errors import DatasetError
from don_gym.geometry import pose_from_transform
from don_gym.io import write_bytes_atomic, write_png, write_text_atomic

EXPORT_FORMATS = ("pdc",)


def _checked_png(path: Path, shape: tuple[int, ...], dtype: type) -> tuple[bytes, np.ndarray]:
    """The bytes and pixels of PNG ``path``; DatasetError unless it decodes to ``shape`` and ``dtype``."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing; the scene is damaged (rebuild it: delete the scene and resume)") from None
    image = decode_png(data)
    if image is None:
        raise DatasetError(f"{path}: not a readable PNG (empty, truncated or corrupt); the scene is damaged")
    if image.shape != shape or image.dtype != dtype:
        raise DatasetError(
            f"{path}: a {image.dtype} image of shape {image.shape}; expected {np.dtype(dtype)} of shape {shape}"
        )
    return data, image


def _pose_entry(T_world_camera: np.ndarray) -> dict:
    position, quat_xyzw = pose_from_transform(T_world_camera)
    x, y, z, w = (float(v) for v in quat_xyzw)
    return {
        "camera_to_world": {
            "translation": {"x": float(position[0]), "y": float(position[1]), "z": float(position[2])},
            "quaternion": {"w": w, "x": x, "y": y, "z": z},
        }
    }


def export_scene_pdc(dataset: DONDataset, scene: int, out_dir: str | Path) -> Path:
    """Write scene number ``scene`` (position in ``dataset.scenes``) in the pdc layout::

        OUT/<scene name>/processed/
          images/000000_rgb.png          RGB, uint8
          images/000000_depth.png        sensor depth, uint16 millimetres, 0 = no return
          images/pose_data.yaml          {idx: {camera_to_world: {translation: {x, y, z},
                                                 quaternion: {w, x, y, z}}, ...}}
          images/camera_info.yaml        {camera_matrix: {rows, cols, data (row-major 3x3)},
                                          image_width, image_height, width, height}
          image_masks/000000_mask.png    object mask, uint8 0/1 (from the fused model, as there)
          rendered_images/000000_depth.png   fused depth re-rendered per frame, uint16 mm

    Camera poses are the *reported* ones (with calibration error), the only poses a real robot
    would have; the camera frame is the optical frame (x right, y down, z forward).

    Returns the scene's output directory. Raises DatasetError for an unknown scene.
    """
    if not 0 <= scene < len(dataset.scenes):
        raise DatasetError(f"scene {scene} does not exist; the dataset has {len(dataset.scenes)} complete scenes")
    record = dataset.scenes[scene]
    processed = Path(out_dir) / record.path.name / "processed"
    images = processed / "images"
    intrinsics = record.intrinsics
    size = (intrinsics.height, intrinsics.width)
    # Check every image of the scene before writing any: a damaged dataset is refused, naming the
    # file, instead of exported as files the other code cannot read.
    files: dict[Path, bytes | np.ndarray] = {}
    poses = {}
    for frame in range(record.num_frames):
        name = f"{frame:06d}"
        rgb_path, depth_path = frame_path(record.path, "rgb", frame), frame_path(record.path, "depth", frame)
        files[images / f"{name}_rgb.png"] = _checked_png(rgb_path, (*size, 3), np.uint8)[0]
        files[images / f"{name}_depth.png"] = _checked_png(depth_path, size, np.uint16)[0]
        fused_depth_path = frame_path(record.path, "depth_fused", frame)
        if fused_depth_path.exists():
            files[processed / "rendered_images" / f"{name}_depth.png"] = _checked_png(
                fused_depth_path, size, np.uint16
            )[0]
        mask_path = frame_path(record.path, "mask_fused", frame)
        if not mask_path.exists():
            mask_path = frame_path(record.path, "mask", frame)
        mask = _checked_png(mask_path, size, np.uint8)[1]
        files[processed / "image_masks" / f"{name}_mask.png"] = (mask > 127).astype(np.uint8)
        poses[frame] = _pose_entry(record.T_world_camera_reported[frame])
    for path, content in files.items():
        if isinstance(content, bytes):
            write_bytes_atomic(path, content)
        else:
            write_png(path, content)
    camera_info = {
        "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in intrinsics.K.ravel()]},
        "image_width": intrinsics.width,
        "image_height": intrinsics.height,
        "width": intrinsics.width,
        "height": intrinsics.height,
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
    }
    write_text_atomic(images / "pose_data.yaml", yaml.safe_dump(poses, sort_keys=True))
    write_text_atomic(images / "camera_info.yaml", yaml.safe_dump(camera_info, sort_keys=False))
    return processed.parent
