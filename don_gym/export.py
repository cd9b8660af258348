"""Export a don_gym scene in the layout of the original Dense Object Nets code ("pdc").

Users of the original pipeline (Florence et al. 2018) can read our data with their
loaders. Per scene::

    OUT/<scene name>/processed/
      images/000000_rgb.png          RGB, uint8
      images/000000_depth.png        sensor depth, uint16 millimetres, 0 = no return
      images/pose_data.yaml          {idx: {camera_to_world: {translation: {x, y, z},
                                             quaternion: {w, x, y, z}}, ...}}
      images/camera_info.yaml        {camera_matrix: {rows, cols, data (row-major 3x3)},
                                      image_width, image_height, width, height}
      image_masks/000000_mask.png    object mask, uint8 0/1 (from the fused model, as there)
      rendered_images/000000_depth.png   fused depth re-rendered per frame, uint16 mm

Camera poses are the *reported* ones (with calibration error), the only poses a real
robot would have; the camera frame is the optical frame (x right, y down, z forward).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import yaml

from don_gym.dataset import DONDataset, frame_path
from don_gym.errors import DatasetError
from don_gym.geometry import pose_from_transform
from don_gym.io import atomic_path, write_text_atomic

EXPORT_FORMATS = ("pdc",)


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
    """Write scene number ``scene`` (position in ``dataset.scenes``) in the pdc layout.

    Returns the scene's output directory. Raises DatasetError for an unknown scene.
    """
    if not 0 <= scene < len(dataset.scenes):
        raise DatasetError(f"scene {scene} does not exist; the dataset has {len(dataset.scenes)} complete scenes")
    record = dataset.scenes[scene]
    processed = Path(out_dir) / record.path.name / "processed"
    images = processed / "images"
    intrinsics = record.intrinsics
    poses = {}
    for frame in range(record.num_frames):
        name = f"{frame:06d}"
        with atomic_path(images / f"{name}_rgb.png") as tmp:
            shutil.copyfile(frame_path(record.path, "rgb", frame), tmp)
        with atomic_path(images / f"{name}_depth.png") as tmp:
            shutil.copyfile(frame_path(record.path, "depth", frame), tmp)
        fused_depth_path = frame_path(record.path, "depth_fused", frame)
        if fused_depth_path.exists():
            with atomic_path(processed / "rendered_images" / f"{name}_depth.png") as tmp:
                shutil.copyfile(fused_depth_path, tmp)
        mask_kind = "mask_fused" if frame_path(record.path, "mask_fused", frame).exists() else "mask"
        mask = dataset.image(scene, frame, mask_kind)
        with atomic_path(processed / "image_masks" / f"{name}_mask.png") as tmp:
            cv2.imwrite(str(tmp), mask.astype(np.uint8))
        poses[frame] = _pose_entry(record.T_world_camera_reported[frame])
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
