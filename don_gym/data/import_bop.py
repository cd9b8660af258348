"""Import one part of a BOP scene-wise dataset as a don_gym dataset (format version 2, ``scene_kind`` "bop").

The paper's method needs no more than a BOP scene holds: images, intrinsics, the part's mesh and its pose.
From each image where the part is annotated this writes RGB, depth in metres, the part's masks with
occlusion by every other annotated object, descriptor targets rendered from the ground-truth poses (every
instance of the part gets its field) and, for the self-supervised method, depth rendered from the
annotated meshes. A BOP scene has no static world frame in general (objects may move between images), so
the scene's "world" is the frame of one instance of the part in each image (its ``reference_instance``):
``T_world_camera[f] = inv(T_camera_object[f][reference])``, ``T_world_object`` the identity. Everything
that relates two frames through camera poses (correspondences, tracking evaluation) then follows that
instance, exactly, without a world frame. Layout: ``docs/dataset_format.md``, section "BOP imports".
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.data import bop
from don_gym.data.dataset import (
    DATASET_FILE,
    FIELD_FILE,
    FORMAT_NAME,
    FORMAT_VERSION,
    SCENE_FILE,
    new_partial_dir,
    remove_dead_partial_dirs,
    scene_dir,
    write_frame,
    write_json,
)
from don_gym.errors import DatasetError, MeshError
from don_gym.geometry import CameraIntrinsics, invert_transform, make_transform

__all__ = [
    "DIAMETER_RATIO_TOLERANCE",
    "MIN_DIAMETER_MM",
    "NO_TABLE_HEIGHT_M",
    "SYMMETRY_DESCRIPTOR_TOLERANCE",
    "BopImportResult",
    "import_bop",
    "load_bop_model_m",
    "model_path",
    "symmetry_disagreements",
]

#: A model whose diameter is below this many file units is taken to be in metres, not millimetres
#: (the smallest BOP parts measure about 10 mm; a 5 m part in metres would be 5 units).
MIN_DIAMETER_MM = 5.0
#: models_info.json's diameter and the mesh's may differ by this factor (BOP computes it on the mesh).
DIAMETER_RATIO_TOLERANCE = 1.5
#: Far below any scene: BOP imports have no table (see :func:`import_bop`).
NO_TABLE_HEIGHT_M = -1.0e6
#: A symmetry counts as held by a descriptor field when the median descriptor change it causes over surface
#: points is below this (descriptors span [0, 1] per dimension).
SYMMETRY_DESCRIPTOR_TOLERANCE = 0.03


@dataclass
class BopImportResult:
    """What :func:`import_bop` wrote: the dataset directory, its scenes and frames, and notes (one line each:
    symmetry disagreements, skipped images) for the caller to show."""

    out: Path
    scenes: int
    frames: int
    notes: list[str] = field(default_factory=list)


@dataclass
class _Image:
    scene_id: int
    im_id: int
    rgb_path: Path
    depth_path: Path
    camera: dict[str, Any]
    annotations: list[dict[str, Any]]


def model_path(root: Path, obj_id: int, models_dir: str = "models") -> Path:
    return Path(root) / models_dir / f"obj_{obj_id:06d}.ply"


def load_bop_model_m(
    root: Path, obj_id: int, models_info: dict[int, dict[str, Any]] | None, models_dir: str = "models"
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices in metres and faces of object ``obj_id``'s model, refused (MeshError naming the file) when
    missing, without faces, or evidently not in millimetres (by its diameter, and against models_info.json)."""
    path = model_path(root, obj_id, models_dir)
    vertices_mm, faces = bop.read_ply_model(path)
    diameter = bop.model_diameter(vertices_mm)
    if diameter < MIN_DIAMETER_MM:
        raise MeshError(
            f"{path}: diameter {diameter:.4g} in file units: evidently metres (or smaller); BOP models are in "
            f"millimetres (expected a diameter >= {MIN_DIAMETER_MM:g}); scale the model by 1000"
        )
    recorded = (models_info or {}).get(obj_id, {}).get("diameter")
    if recorded is not None and not 1 / DIAMETER_RATIO_TOLERANCE <= recorded / diameter <= DIAMETER_RATIO_TOLERANCE:
        raise MeshError(
            f"{path}: diameter {diameter:.4g} mm, but models_info.json records {recorded:.4g} mm for object "
            f"{obj_id}: the model and models_info.json are in different units or describe different parts"
        )
    return vertices_mm / 1000.0, faces


def _scene_ids(split_dir: Path, scenes: Sequence[int] | None) -> list[int]:
    if not split_dir.is_dir():
        raise DatasetError(f"{split_dir}: split directory not found (expected ROOT/SPLIT with scenes NNNNNN/)")
    present = sorted(int(p.name) for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit())
    if scenes:
        missing = [s for s in scenes if s not in present]
        if missing:
            raise DatasetError(
                f"{split_dir}: no scene {missing[0]:06d} (--scenes); present: {', '.join(map(str, present)) or 'none'}"
            )
        return sorted(set(int(s) for s in scenes))
    if not present:
        raise DatasetError(f"{split_dir}: holds no scene directory (NNNNNN/)")
    return present


def _scan(root: Path, split: str, obj_id: int, scenes: Sequence[int] | None) -> tuple[list[_Image], set[int]]:
    """Every image of the chosen scenes that annotates ``obj_id`` and the ids of all objects annotated
    there; the cheap checks (files present, depth_scale) for all of them before any pixel is read."""
    images, objects, seen = [], set(), set()
    split_dir = Path(root) / split
    for scene_id in _scene_ids(split_dir, scenes):
        path = split_dir / f"{scene_id:06d}"
        cameras = bop.read_scene_camera(path / "scene_camera.json")
        gt = bop.read_scene_gt(path / "scene_gt.json")
        for im_id in sorted(gt):
            annotations = gt[im_id]
            seen.update(a["obj_id"] for a in annotations)
            if not any(a["obj_id"] == obj_id for a in annotations):
                continue
            if im_id not in cameras:
                raise DatasetError(f"{path / 'scene_camera.json'}: no entry for image {im_id}")
            camera = cameras[im_id]
            if camera["depth_scale"] is None:
                raise DatasetError(
                    f"{path / 'scene_camera.json'}: image {im_id} has no depth_scale (depth PNG value times it is mm)"
                )
            rgb = bop.find_image(path / "rgb", im_id) or bop.find_image(path / "gray", im_id)
            if rgb is None:
                raise DatasetError(f"{path}: no rgb/ or gray/ image {im_id:06d} (.png, .jpg or .tif)")
            depth = bop.find_image(path / "depth", im_id)
            if depth is None:
                raise DatasetError(f"{path / 'depth'}: no depth image {im_id:06d}")
            images.append(_Image(scene_id, im_id, rgb, depth, camera, annotations))
            objects.update(a["obj_id"] for a in annotations)
    if not images:
        listed = ", ".join(str(i) for i in sorted(seen)) or "none"
        raise DatasetError(
            f"{split_dir}: --object {obj_id} is annotated in no image of the chosen scenes (annotated: {listed})"
        )
    return images, objects


def _intrinsics(image: _Image, width: int, height: int) -> CameraIntrinsics:
    K = image.camera["cam_K"]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height):
        raise DatasetError(
            f"{image.rgb_path}: a {width}x{height} image does not fit cam_K of scene_camera.json image {image.im_id} "
            f"(principal point ({cx:g}, {cy:g}) must lie inside the image, focal lengths positive)"
        )
    return CameraIntrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))


def _pose_m(annotation: dict[str, Any]) -> np.ndarray:
    return make_transform(annotation["cam_R_m2c"], np.asarray(annotation["cam_t_m2c"], dtype=np.float64) / 1000.0)


def _axis_text(axis: np.ndarray) -> str:
    return str((np.round(np.asarray(axis, dtype=np.float64), 3) + 0.0).tolist())


def symmetry_disagreements(
    mesh, vertex_descriptors: np.ndarray, model_info: dict[str, Any], rng: np.random.Generator
) -> list[str]:
    """How the symmetries of ``model_info`` (a models_info.json entry; translations in mm) and those of a
    descriptor field (``vertex_descriptors`` on ``mesh``, metres) disagree, one sentence each; empty when
    they agree. A declared symmetry the field does not hold means the targets tell apart poses that BOP
    scores as one; a rotation about a principal axis that the field holds and BOP does not declare means
    the field cannot tell apart poses that BOP scores as different."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from don_gym.descriptors import interpolate_field

    points, faces = trimesh.sample.sample_surface(mesh, 400, seed=int(rng.integers(2**31)))
    faces = np.asarray(faces)
    barycentric = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    here = interpolate_field(vertex_descriptors, mesh.faces, faces, barycentric)

    def change(T: np.ndarray) -> float:
        moved = points @ T[:3, :3].T + T[:3, 3]
        closest, _, triangles = trimesh.proximity.closest_point(mesh, moved)
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[triangles], closest)
        there = interpolate_field(vertex_descriptors, mesh.faces, np.asarray(triangles), bary)
        return float(np.median(np.abs(there - here).max(axis=1)))

    def rotation(axis: np.ndarray, angle: float, offset_m: np.ndarray) -> np.ndarray:
        R = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
        return make_transform(R, offset_m - R @ offset_m)

    notes = []
    declared: list[np.ndarray] = []
    for S in model_info.get("symmetries_discrete", []):
        T = np.array(S, dtype=np.float64)
        T[:3, 3] /= 1000.0
        declared.append(T)
        moved = change(T)
        if moved > SYMMETRY_DESCRIPTOR_TOLERANCE:
            rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
            angle = float(np.linalg.norm(rotvec))
            axis = _axis_text(rotvec / angle if angle > 1e-9 else np.zeros(3))
            notes.append(
                f"the declared discrete symmetry ({np.degrees(angle):.0f} deg about {axis}) changes the descriptors "
                f"by {moved:.3f} (median), so the targets tell apart poses that BOP scores as equal"
            )
    continuous_axes = []
    for S in model_info.get("symmetries_continuous", []):
        axis = np.asarray(S["axis"], dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        offset = np.asarray(S["offset"], dtype=np.float64) / 1000.0
        continuous_axes.append(axis)
        moved = max(change(rotation(axis, a, offset)) for a in np.radians([45.0, 90.0, 135.0]))
        if moved > SYMMETRY_DESCRIPTOR_TOLERANCE:
            notes.append(
                f"the declared continuous symmetry about {_axis_text(axis)} changes the descriptors by up to "
                f"{moved:.3f} (median), so the targets tell apart poses that BOP scores as equal"
            )
    # Candidates the field may hold that BOP does not declare: rotations about the principal axes.
    centre = np.asarray(mesh.centroid, dtype=np.float64)
    _, vectors = np.linalg.eigh(mesh.moment_inertia)
    for k in range(3):
        axis = vectors[:, k]
        if any(abs(float(axis @ a)) > 0.99 for a in continuous_axes):
            continue
        for angle in (90.0, 180.0):
            T = rotation(axis, np.radians(angle), centre)
            covered = any(np.allclose(T, D, atol=1e-3 * max(1.0, float(np.abs(D[:3, 3]).max()))) for D in declared)
            if not covered and change(T) <= SYMMETRY_DESCRIPTOR_TOLERANCE:
                notes.append(
                    f"the descriptors are unchanged by a {angle:.0f} deg rotation about {_axis_text(axis)} "
                    "that models_info.json does not declare, so they cannot tell apart poses that BOP scores as "
                    "different"
                )
                break
    return notes


def _continuous_axis_through_centre(model_info: dict[str, Any], center_of_mass_m: np.ndarray) -> list[float] | None:
    """The axis (unit, model frame) of the part's one continuous symmetry when it passes within 0.5 mm of the
    centre of mass (don_gym measures errors "mod symmetry" about such an axis), else None."""
    symmetries = model_info.get("symmetries_continuous", [])
    if len(symmetries) != 1:
        return None
    axis = np.asarray(symmetries[0]["axis"], dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    offset_m = np.asarray(symmetries[0]["offset"], dtype=np.float64) / 1000.0
    if np.linalg.norm(np.cross(np.asarray(center_of_mass_m) - offset_m, axis)) > 0.0005:
        return None
    return [float(v) for v in axis]


def import_bop(
    root: str | Path,
    split: str,
    obj_id: int,
    out: str | Path,
    scenes: Sequence[int] | None = None,
    descriptor_dim: int = 3,
    symmetric: bool = True,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
    models_dir: str = "models",
) -> BopImportResult:
    """Write object ``obj_id`` of ``root/split`` (scenes ``scenes``, default all) as a don_gym dataset at
    ``out``, reading models from ``root/models_dir``. All of it or nothing: the dataset is written into a
    temporary directory beside ``out`` and renamed into place when complete; every user error
    (DatasetError/MeshError) names its file.

    Images whose camera matrix differs from the others of their BOP scene go to a don_gym scene of their
    own (one camera matrix per scene); a group of a single image is skipped (two views are needed for
    correspondences), with a note.
    """
    from don_gym import __version__
    from don_gym.data.render import DescriptorRenderer
    from don_gym.descriptors import embed
    from don_gym.objects import load_object

    root, out = Path(root), Path(out)
    if isinstance(obj_id, bool) or not isinstance(obj_id, int) or obj_id < 1:
        raise DatasetError(f"--object {obj_id!r}: expected a BOP object id (integer >= 1)")
    if not root.is_dir():
        raise DatasetError(f"{root}: BOP dataset directory not found")
    if out.exists() and not (out.is_dir() and not any(out.iterdir())):
        if not out.is_dir() or not overwrite:
            raise DatasetError(f"{out}: exists and is not an empty directory; pass --overwrite to replace a dataset")
        if not (out / DATASET_FILE).is_file():
            raise DatasetError(f"{out}: holds no {DATASET_FILE}, so it is not a dataset --overwrite may replace")
    info_path = root / models_dir / "models_info.json"
    models_info = bop.read_models_info(info_path) if info_path.is_file() else {}
    images, objects = _scan(root, split, obj_id, scenes)
    if not model_path(root, obj_id, models_dir).is_file():
        raise MeshError(f"{model_path(root, obj_id, models_dir)}: model of --object {obj_id} not found")
    meshes = {o: load_bop_model_m(root, o, models_info, models_dir) for o in sorted(objects)}
    say = progress or (lambda _line: None)

    made = [p for p in (out.parent, *out.parent.parents) if not p.exists()]
    # Half-written copies of imports killed on this machine (kill -9, out of memory) go before a new one starts.
    stale = remove_dead_partial_dirs(out, ("partial", "stale"))
    tmp = new_partial_dir(out)
    try:
        name = f"obj_{obj_id:06d}"
        shutil.copyfile(model_path(root, obj_id, models_dir), tmp / f"{name}.ply")
        model = load_object(tmp / f"{name}.ply", scale=0.001)
        field_ = embed(model, dim=descriptor_dim, symmetric=symmetric)
        field_.save(tmp / FIELD_FILE)
        part_renderer = DescriptorRenderer(model.mesh, field_.vertex_descriptors, field_.background)
        depth_renderers = {
            o: DescriptorRenderer(m, np.zeros((len(m[0]), 1), np.float32), np.zeros(1, np.float32))
            for o, m in meshes.items()
        }
        disagreements = symmetry_disagreements(
            model.mesh, field_.vertex_descriptors, models_info.get(obj_id, {}), np.random.default_rng(0)
        )
        notes = [f"removed {len(stale)} half-written copies left beside {out} by killed imports"] if stale else []
        legacy = _legacy_partial_dirs(out)
        if legacy:
            notes.append(
                f"{len(legacy)} hidden copies beside {out} ({legacy[0].name}...) were left by imports of an older "
                "don_gym, whose writer this one cannot tell alive or dead: remove them by hand if no import runs"
            )
        if disagreements:
            notes.append(
                f"object {obj_id}: its BOP symmetries (models_info.json) disagree with the descriptor field's: "
                + "; ".join(disagreements)
            )
        groups: dict[tuple[int, tuple[float, ...]], list[_Image]] = {}
        for image in images:
            groups.setdefault((image.scene_id, tuple(image.camera["cam_K"].ravel())), []).append(image)
        image_size: tuple[int, int] | None = None
        scene_index, frames = 0, 0
        frame_counts = []
        for (scene_id, _), members in groups.items():
            if len(members) < 2:
                notes.append(
                    f"scene {scene_id:06d} image {members[0].im_id}: skipped (no other image of the scene shares its "
                    "cam_K; a don_gym scene needs two views of one camera)"
                )
                continue
            path = scene_dir(tmp, scene_index)
            path.mkdir(parents=True)
            meta = _write_scene(path, members, obj_id, name, part_renderer, depth_renderers, descriptor_dim, image_size)
            size = (meta["intrinsics"].width, meta["intrinsics"].height)
            if image_size is not None and size != image_size:
                raise DatasetError(
                    f"{members[0].rgb_path}: {size[0]}x{size[1]} pixels, other images {image_size[0]}x{image_size[1]}; "
                    "a dataset holds one image size"
                )
            image_size = size
            write_json(
                path / SCENE_FILE,
                {
                    "scene_index": scene_index,
                    "seed": None,
                    "object": name,
                    **{k: v for k, v in meta.items() if k != "intrinsics"},
                    "intrinsics": meta["intrinsics"].as_array(),
                    "T_world_object": np.eye(4),
                    "table_height_m": NO_TABLE_HEIGHT_M,
                    "background": None,
                    "fused_depth": True,
                    "world_frame": "part instance",
                    "bop": {"split": split, "scene_id": scene_id, "im_ids": [m.im_id for m in members]},
                },
            )
            frames += len(members)
            frame_counts.append(len(members))
            scene_index += 1
            say(f"scene {scene_id:06d}: {len(members)} images")
        if scene_index == 0:
            raise DatasetError(
                f"{root / split}: --object {obj_id}: no BOP scene has two images with one cam_K; nothing to import"
            )
        symmetry_axis = _continuous_axis_through_centre(models_info.get(obj_id, {}), model.center_of_mass)
        part = {
            "name": name,
            "object_source": str(model_path(root, obj_id, models_dir).resolve()),
            "object_scale": 0.001,
            "object_signature": model.shape_signature.to_dict(),
            "mesh_hash": model.mesh_hash,
        }
        write_json(
            tmp / DATASET_FILE,
            {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "don_gym_version": __version__,
                "scene_kind": "bop",
                # The model travels with the dataset (object_model() looks beside dataset.json).
                "object": f"{name}.ply",
                "object_scale": 0.001,
                "object_name": name,
                "object_source": part["object_source"],
                "object_signature": part["object_signature"],
                "mesh_hash": part["mesh_hash"],
                "parts": [part],
                "object_symmetry_axis": symmetry_axis,
                "scenes": scene_index,
                "frames_per_scene": max(frame_counts),
                "image_size": list(image_size or (0, 0)),
                "sensor": "bop",
                "renderer": "bop",
                "seed": -1,
                "descriptor_dim": descriptor_dim,
                "symmetric": symmetric,
                "fuse_depth": True,
                "voxel_size_m": None,
                "descriptor_field_hash": field_.field_hash,
                "background_descriptor": field_.background,
                "bop": {
                    "root": str(root.resolve()),
                    "split": split,
                    "obj_id": obj_id,
                    "scenes": sorted({i.scene_id for i in images}),
                    "depth_fused": "rendered from the ground-truth poses of every annotated object",
                },
            },
        )
        if out.exists():  # --overwrite: the old dataset moved aside in one rename, removed once the new one is in
            replaced = new_partial_dir(out, kind="stale")
            os.rename(out, replaced)
            os.rename(tmp, out)
            shutil.rmtree(replaced, ignore_errors=True)
        else:
            os.rename(tmp, out)
        made = []
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        for folder in made:  # the folders made for --out, innermost first: nothing is left behind
            with contextlib.suppress(OSError):
                folder.rmdir()
    return BopImportResult(out, scene_index, frames, notes)


def _legacy_partial_dirs(out: Path) -> list[Path]:
    """Hidden copies beside ``out`` named as imports before don_gym recorded host and pid wrote them
    (``.NAME.partial-`` and eight random characters)."""
    prefix = f".{out.name}.partial-"
    return sorted(
        p
        for p in out.parent.iterdir()
        if p.name.startswith(prefix) and len(p.name) == len(prefix) + 8 and "-" not in p.name[len(prefix) :]
    )


def _write_scene(
    path: Path,
    members: list[_Image],
    obj_id: int,
    part: str,
    part_renderer,
    depth_renderers: dict,
    descriptor_dim: int,
    image_size: tuple[int, int] | None,
) -> dict[str, Any]:
    """Write the frames of one don_gym scene; returns the per-scene metadata they determine. ``image_size``
    (width, height): the size of the images imported before, which every image's header must declare."""
    T_camera_object, T_world_camera, reference, instance_ids = [], [], [], set()
    intrinsics = None
    for f, image in enumerate(members):
        rgb = bop.read_color_image(image.rgb_path, image_size)
        height, width = rgb.shape[:2]
        image_size = (width, height)
        depth_m = bop.read_depth_mm(image.depth_path, image.camera["depth_scale"], image_size) / 1000.0
        intrinsics = _intrinsics(image, width, height)
        # Every annotated object rendered: nearest surface per pixel decides what is visible.
        nearest = np.full((height, width), np.inf)
        owner = np.full((height, width), -1, dtype=np.int64)
        for gt_id, annotation in enumerate(image.annotations):
            hit = depth_renderers[annotation["obj_id"]].render(intrinsics, _pose_m(annotation))
            closer = hit.object_mask & (hit.depth_m < nearest)
            nearest[closer], owner[closer] = hit.depth_m[closer], gt_id
        rendered = np.isfinite(nearest)
        depth_rendered = np.where(rendered, nearest, 0.0)
        poses, instance = {}, np.zeros((height, width), dtype=np.int32)
        descriptor = np.broadcast_to(part_renderer.background, (height, width, descriptor_dim)).copy()
        target_mask = np.zeros((height, width), dtype=bool)
        first = None
        for gt_id, annotation in enumerate(image.annotations):
            if annotation["obj_id"] != obj_id:
                continue
            instance_id = gt_id + 1
            visib_path = bop.mask_path(image.rgb_path.parent.parent, "mask_visib", image.im_id, gt_id)
            visible = bop.read_mask(visib_path, image_size) if visib_path.is_file() else owner == gt_id
            T = _pose_m(annotation)
            target = part_renderer.render(intrinsics, T, visible_mask=visible)
            descriptor[target.object_mask] = target.descriptor_image[target.object_mask]
            target_mask |= target.object_mask
            instance[visible] = instance_id
            poses[str(instance_id)] = T
            instance_ids.add(instance_id)
            if first is None:
                first = (instance_id, T, visible & target.object_mask)
        assert first is not None  # _scan keeps only images annotating the part
        reference.append(first[0])
        T_camera_object.append(poses)
        T_world_camera.append(invert_transform(first[1]))
        write_frame(
            path,
            f,
            {
                "rgb": rgb,
                "depth": depth_m,
                "depth_ideal": np.where(rendered, depth_rendered, depth_m),
                "depth_fused": depth_rendered,
                "mask": instance > 0,
                "mask_fused": first[2],
                "target_mask": target_mask,
                "descriptor": descriptor,
                "instance": instance,
            },
            descriptor_dim,
        )
    poses_world = np.stack(T_world_camera)
    return {
        "intrinsics": intrinsics,
        "instances": [{"instance_id": i, "part": part} for i in sorted(instance_ids)],
        "T_camera_object": T_camera_object,
        "reference_instance": reference,
        "T_world_camera": poses_world,
        "T_world_camera_reported": poses_world,
    }
