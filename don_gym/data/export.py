"""Export don_gym scenes in other projects' layouts.

Users of the original pipeline (Florence et al. 2018; layout in docs/background.md, section
"Self-supervised DON training") can read our data with their loaders: :func:`export_scene_pdc`.
:func:`export_bop` writes a whole dataset as a BOP scene-wise dataset (the Benchmark for 6D Object
Pose estimation), which BOP's toolkit and pose evaluation read.
"""

from __future__ import annotations

import fcntl
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from don_gym.data.dataset import DONDataset, check_png_size, decode_png, frame_path, png_size
from don_gym.errors import DatasetError
from don_gym.geometry import pose_from_transform
from don_gym.io import write_bytes_atomic, write_png, write_text_atomic

__all__ = [
    "BOP_SPLITS",
    "BopExport",
    "EXPORT_FORMATS",
    "bop_models_info",
    "export_bop",
    "export_scene_pdc",
    "pdc_scene_dir",
]

EXPORT_FORMATS = ("pdc", "bop")
#: Splits ``export_bop`` writes (BOP's split directories).
BOP_SPLITS = ("train", "test")


def _checked_png(path: Path, shape: tuple[int, ...], dtype: type) -> tuple[bytes, np.ndarray]:
    """The bytes and pixels of PNG ``path``; DatasetError unless it decodes to ``shape`` and ``dtype``."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing; the scene is damaged (rebuild it: delete the scene and resume)") from None
    if png_size(data) is not None:
        check_png_size(data, (shape[1], shape[0]), path)  # before decoding: a header may declare gigapixels
    image = decode_png(data) if png_size(data) is not None else None
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

    The scene is written under a temporary name and renamed when complete; an existing scene directory (another
    export's, maybe of another dataset) is refused, never written into. Returns the scene's output directory.
    Raises DatasetError for an unknown scene.
    """
    from don_gym.data.dataset import new_partial_dir, remove_dead_partial_dirs

    if not 0 <= scene < len(dataset.scenes):
        raise DatasetError(f"scene {scene} does not exist; the dataset has {len(dataset.scenes)} complete scenes")
    record = dataset.scenes[scene]
    final = pdc_scene_dir(out_dir, dataset, scene)
    if final.exists():
        raise DatasetError(f"{final}: exists; export into another directory or remove it")
    files, camera_info, poses = _pdc_scene_files(record, final / "processed")
    remove_dead_partial_dirs(final)  # what exports killed on this machine left
    tmp = new_partial_dir(final)
    try:
        for path, content in files.items():
            path = tmp / path.relative_to(final)
            if isinstance(content, bytes):
                write_bytes_atomic(path, content)
            else:
                write_png(path, content)
        images = tmp / "processed" / "images"
        write_text_atomic(images / "pose_data.yaml", yaml.safe_dump(poses, sort_keys=True))
        write_text_atomic(images / "camera_info.yaml", yaml.safe_dump(camera_info, sort_keys=False))
        os.rename(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


def pdc_scene_dir(out_dir: str | Path, dataset: DONDataset, scene: int) -> Path:
    """Where :func:`export_scene_pdc` writes scene position ``scene`` of ``dataset`` in ``out_dir``."""
    return Path(out_dir) / dataset.scenes[scene].path.name


def _pdc_scene_files(record, processed: Path) -> tuple[dict[Path, bytes | np.ndarray], dict, dict]:
    """A scene's pdc files (path -> PNG bytes or a mask to encode), ``camera_info.yaml`` and ``pose_data.yaml``,
    every image checked first: a damaged dataset is refused, naming the file, before anything is written."""
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
    camera_info = {
        "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in intrinsics.K.ravel()]},
        "image_width": intrinsics.width,
        "image_height": intrinsics.height,
        "width": intrinsics.width,
        "height": intrinsics.height,
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.0] * 5},
    }
    return files, camera_info, poses


def bop_models_info(model) -> dict:
    """The ``models_info.json`` entry of a part (:class:`~don_gym.objects.ObjectModel`, metres): diameter
    and box in mm, and a continuous symmetry about its declared symmetry axis through its centre of mass
    (the toolcap's and the shaft's), none for a part without one."""
    from don_gym.data import bop

    symmetries = {}
    if model.symmetry_axis is not None:
        symmetries["symmetries_continuous"] = [
            {"axis": np.asarray(model.symmetry_axis, dtype=np.float64), "offset": model.center_of_mass * 1000.0}
        ]
    return bop.models_info_entry(np.asarray(model.mesh.vertices) * 1000.0, **symmetries)


def _scene_bop_files(dataset: DONDataset, scene: int, obj_ids: dict[str, int], silhouette) -> dict:
    """One scene's BOP annotations (camera, gt, gt_info by image id) and masks (path parts -> bool image); every
    instance annotated as its part's object (``obj_ids``: part name -> BOP object id)."""
    from don_gym.data import bop
    from don_gym.data.dataset import instance_mask

    record = dataset.scenes[scene]
    intrinsics = record.intrinsics
    size = (intrinsics.height, intrinsics.width)
    part_of = _instance_parts(record, obj_ids)
    cameras, gt, gt_info, masks = {}, {}, {}, {}
    for frame in range(record.num_frames):
        T_camera_world = np.linalg.inv(record.T_world_camera[frame])
        cameras[frame] = {
            "cam_K": intrinsics.K,
            "depth_scale": 1.0,  # don_gym's depth PNGs hold millimetres
            "cam_R_w2c": T_camera_world[:3, :3],
            "cam_t_w2c": T_camera_world[:3, 3] * 1000.0,
        }
        depth_valid = _checked_png(frame_path(record.path, "depth", frame), size, np.uint16)[1] > 0
        instances = instance_mask(dataset, scene, frame)
        gt[frame], gt_info[frame] = [], []
        for gt_id, (instance_id, T) in enumerate(sorted(record.T_camera_object(frame).items())):
            part = part_of[instance_id]
            full, full_count, full_box = silhouette(part, intrinsics, T)
            visible = (instances == instance_id) & full
            gt[frame].append({"obj_id": obj_ids[part], "cam_R_m2c": T[:3, :3], "cam_t_m2c": T[:3, 3] * 1000.0})
            info = bop.gt_info(full, visible, depth_valid, mask_all_count=full_count)
            if info["px_count_visib"]:
                info["bbox_obj"] = full_box
            gt_info[frame].append(info)
            masks[("mask", frame, gt_id)] = full
            masks[("mask_visib", frame, gt_id)] = visible
    return {"cameras": cameras, "gt": gt, "gt_info": gt_info, "masks": masks}


def _instance_parts(record, obj_ids: dict[str, int]) -> dict[int, str]:
    """Instance id -> part name of a scene; in a dataset of one part every instance is that part."""
    if len(obj_ids) == 1:
        (only,) = obj_ids
        return {int(i["instance_id"]): only for i in record.instances}
    parts = {int(i["instance_id"]): str(i["part"]) for i in record.instances}
    unknown = sorted({p for p in parts.values() if p not in obj_ids})
    if unknown:
        raise DatasetError(
            f"{record.path}: instances of part {unknown[0]!r}, which the dataset's parts ({', '.join(obj_ids)}) lack"
        )
    return parts


def _part_models(dataset: DONDataset) -> dict:
    """Part name -> :class:`~don_gym.objects.ObjectModel` of every part of ``dataset`` (primary first)."""
    from don_gym.data.bin_dataset import is_multi_part, load_part_models

    if is_multi_part(dataset) or len(dataset.parts) > 1:
        return load_part_models(dataset)
    return {str(dataset.parts[0]["name"]): dataset.object_model()}


def _same_part(path: Path, model) -> bool:
    """Whether the BOP model at ``path`` (mm) is ``model``, by shape (any vertex order, any file name)."""
    from don_gym.errors import DonGymError
    from don_gym.objects import load_object

    try:
        other = load_object(path, scale=0.001)
    except DonGymError:
        return False
    return not model.shape_signature.differences(other.shape_signature)


def _assign_object_ids(out_dir: Path, models: dict) -> tuple[dict[str, int], dict[str, Any]]:
    """BOP object ids of ``models`` in the BOP folder ``out_dir``: a part whose model is there already (same shape)
    keeps its id; any other part gets an id no model there uses. Returns the ids by part name and the raw
    ``models_info.json`` on disk (empty if none). A folder whose ``models/`` cannot be read is refused."""
    from don_gym.data import bop

    info_path = out_dir / "models" / "models_info.json"
    existing: dict[str, Any] = {}
    if info_path.is_file():
        existing = bop.read_bop_json(info_path)
        bop.read_models_info(info_path)  # a malformed file is refused here, naming it
    elif (out_dir / "models").is_dir() and any((out_dir / "models").glob("obj_*.ply")):
        raise DatasetError(
            f"{out_dir / 'models'}: holds models but no models_info.json; export into another directory (a BOP "
            "dataset's models need their models_info.json)"
        )
    taken = {int(k) for k in existing}
    for path in (out_dir / "models").glob("obj_*.ply"):
        number = path.stem[len("obj_") :]
        if number.isdigit():
            taken.add(int(number))
    ids: dict[str, int] = {}
    for name, model in models.items():
        found = next(
            (
                obj_id
                for obj_id in sorted(taken)
                if obj_id not in ids.values() and _same_part(out_dir / "models" / f"obj_{obj_id:06d}.ply", model)
            ),
            None,
        )
        if found is None:
            found = max([*taken, *ids.values(), 0]) + 1
        ids[name] = found
    return ids, existing


@dataclass(frozen=True)
class BopExport:
    """What :func:`export_bop` wrote: the split directory and each part's BOP object id, by part name."""

    split_dir: Path
    object_ids: dict[str, int]


def export_bop(dataset: DONDataset, out_dir: str | Path, split: str = "train", scenes=None) -> BopExport:
    """Write ``dataset`` as a BOP scene-wise dataset in ``out_dir``, every part as an object of its own::

        models/obj_NNNNNN.ply, models/models_info.json   each part in millimetres
        camera.json                                      the first scene's intrinsics (if there is none yet)
        SPLIT/NNNNNN/ (one per scene, NNNNNN = scene_index)
          scene_camera.json   cam_K, depth_scale 1.0, cam_R_w2c / cam_t_w2c (mm) from the true camera poses
          scene_gt.json       per image every instance: its part's obj_id, cam_R_m2c, cam_t_m2c (mm)
          scene_gt_info.json  bbox_obj, bbox_visib, px_count_all/valid/visib, visib_fract (as BOP computes them:
                              the silhouette also beyond the image border)
          rgb/NNNNNN.png, depth/NNNNNN.png (uint16 mm, the sensor's), mask/ and mask_visib/NNNNNN_GGGGGG.png

    A folder that holds a BOP dataset already is added to, never changed: a part whose model is there (the same
    shape) keeps its object id, any other part gets a new one (into a new folder: 1, 2, ... in the order of the
    dataset's parts, the primary part first), and the models, ``models_info.json``'s other entries and
    ``camera.json`` stay as they are. Poses are the TRUE ones (``SceneRecord.T_camera_object``): what pose
    evaluation compares against. The split directory is written under a temporary name and renamed when
    complete; an existing one is refused. Exports into one folder on one machine take turns (``OUT/.lock``).
    """
    from don_gym.data import bop
    from don_gym.data.dataset import new_partial_dir, remove_dead_partial_dirs
    from don_gym.data.render import DescriptorRenderer
    from don_gym.geometry import CameraIntrinsics
    from don_gym.io import DirectoryLock

    if split not in BOP_SPLITS:
        raise DatasetError(f"--split {split!r}: expected one of {', '.join(BOP_SPLITS)}")
    out_dir = Path(out_dir)
    split_dir = out_dir / split
    if split_dir.exists():
        raise DatasetError(f"{split_dir}: exists; export into another directory or remove it")
    models = _part_models(dataset)
    scenes = list(range(len(dataset.scenes))) if scenes is None else list(scenes)
    renderers = {
        name: DescriptorRenderer(m.mesh, np.zeros((len(m.mesh.vertices), 1)), np.zeros(1)) for name, m in models.items()
    }

    def silhouette(part: str, intrinsics: CameraIntrinsics, T: np.ndarray) -> tuple[np.ndarray, int, list[int]]:
        # A canvas three times the image, the image in its middle: BOP counts and boxes the whole silhouette.
        W, H = intrinsics.width, intrinsics.height
        large = CameraIntrinsics(intrinsics.fx, intrinsics.fy, intrinsics.cx + W, intrinsics.cy + H, 3 * W, 3 * H)
        mask = renderers[part].render(large, T).object_mask
        box = bop.bbox_of(mask)
        if box[0] >= 0:
            box = [box[0] - W, box[1] - H, box[2], box[3]]
        return mask[H : 2 * H, W : 2 * W], int(mask.sum()), box

    out_dir.mkdir(parents=True, exist_ok=True)
    lock = DirectoryLock(out_dir)
    try:
        lock.lock(0, fcntl.LOCK_EX)  # ids are chosen and models added by one export at a time
        if split_dir.exists():  # another export got here first
            raise DatasetError(f"{split_dir}: exists; export into another directory or remove it")
        obj_ids, models_info = _assign_object_ids(out_dir, models)
        annotations = {scene: _scene_bop_files(dataset, scene, obj_ids, silhouette) for scene in scenes}
        remove_dead_partial_dirs(split_dir)  # what exports killed on this machine left
        tmp = new_partial_dir(split_dir)
        try:
            for scene in scenes:
                _write_bop_scene(dataset, scene, tmp, annotations[scene])
            _add_models(out_dir, models, obj_ids, models_info)
            first = dataset.scenes[scenes[0]].intrinsics if scenes else None
            if first is not None and not (out_dir / "camera.json").exists():
                bop.write_bop_json(
                    out_dir / "camera.json",
                    {"fx": first.fx, "fy": first.fy, "cx": first.cx, "cy": first.cy, "width": first.width,
                     "height": first.height, "depth_scale": 1.0},
                )  # fmt: skip
            os.rename(tmp, split_dir)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    finally:
        lock.close()
    return BopExport(split_dir, obj_ids)


def _write_bop_scene(dataset: DONDataset, scene: int, split_tmp: Path, files: dict) -> None:
    from don_gym.data import bop

    record = dataset.scenes[scene]
    size = (record.intrinsics.height, record.intrinsics.width)
    path = split_tmp / f"{record.index:06d}"
    for frame in range(record.num_frames):
        rgb = _checked_png(frame_path(record.path, "rgb", frame), (*size, 3), np.uint8)[0]
        depth = _checked_png(frame_path(record.path, "depth", frame), size, np.uint16)[0]
        write_bytes_atomic(path / "rgb" / f"{frame:06d}.png", rgb)
        write_bytes_atomic(path / "depth" / f"{frame:06d}.png", depth)
    for (kind, frame, gt_id), mask in files["masks"].items():
        bop.write_mask(bop.mask_path(path, kind, frame, gt_id), mask)
    bop.write_scene_camera(path / "scene_camera.json", files["cameras"])
    bop.write_scene_gt(path / "scene_gt.json", files["gt"])
    bop.write_scene_gt_info(path / "scene_gt_info.json", files["gt_info"])


def _add_models(out_dir: Path, models: dict, obj_ids: dict[str, int], models_info: dict[str, Any]) -> None:
    """The models of the parts new to ``out_dir``, then ``models_info.json`` with their entries added (the others'
    as they were): a ``models_info.json`` never names a model that is not there."""
    from don_gym.data import bop

    new = {name: obj_id for name, obj_id in obj_ids.items() if str(obj_id) not in models_info}
    for name, obj_id in new.items():
        vertices_mm = np.asarray(models[name].mesh.vertices) * 1000.0
        bop.write_ply_model(out_dir / "models" / f"obj_{obj_id:06d}.ply", vertices_mm, models[name].mesh.faces)
    if new:
        entries = {obj_id: bop_models_info(models[name]) for name, obj_id in new.items()}
        bop.write_bop_json(out_dir / "models" / "models_info.json", {**models_info, **bop.models_info_json(entries)})
