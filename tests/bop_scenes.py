"""Tiny BOP scene-wise datasets written by the tests themselves (nothing downloaded).

Two objects on a plane, seen by a camera circling them: object 1 is the toolcap (continuous symmetry about
its z axis), object 2 a 40 x 30 x 20 mm box (discrete symmetries: 180 degrees about each axis) that hides
part of the toolcap in some views. Depth and masks come from an exact z-buffer of the meshes; colours are
flat per object with a little shading, over a textured background.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from synthetic_scenes import look_at

from don_gym.data import bop
from don_gym.data.render import DescriptorRenderer
from don_gym.geometry import CameraIntrinsics, invert_transform, make_transform
from don_gym.objects import load_object

WIDTH, HEIGHT = 64, 48
K = np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 23.5], [0.0, 0.0, 1.0]])
DEPTH_SCALE = 0.1
#: Box half extents in mm.
BOX_HALF_MM = (20.0, 15.0, 10.0)


def toolcap_mm() -> tuple[np.ndarray, np.ndarray]:
    mesh = load_object("toolcap").mesh
    return np.asarray(mesh.vertices) * 1000.0, np.asarray(mesh.faces)


def box_mm() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.box(extents=2 * np.asarray(BOX_HALF_MM))
    for _ in range(3):  # enough vertices for a descriptor field
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def box_symmetries() -> list[np.ndarray]:
    return [make_transform(np.diag(d)) for d in ((1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))]


def write_models(folder: Path, toolcap_symmetry: bool = True) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The two models and models_info.json in ``folder`` (``ROOT/models`` in BOP's layout)."""
    models = {1: toolcap_mm(), 2: box_mm()}
    info = {}
    for obj_id, (vertices, faces) in models.items():
        bop.write_ply_model(folder / f"obj_{obj_id:06d}.ply", vertices, faces)
        info[obj_id] = bop.models_info_entry(vertices)
    if toolcap_symmetry:
        info[1]["symmetries_continuous"] = [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    info[2]["symmetries_discrete"] = box_symmetries()
    bop.write_models_info(folder / "models_info.json", info)
    return models


def object_poses_world(second_toolcap: bool = False) -> list[tuple[int, np.ndarray]]:
    """(object id, pose in metres) of the annotated objects: the toolcap upright at the origin, the box beside
    it, and with ``second_toolcap`` another toolcap lying on its side behind them."""
    poses = [
        (1, make_transform(translation=[0.0, 0.0, 0.02])),
        (2, make_transform(trimesh.transformations.rotation_matrix(0.4, [0, 0, 1])[:3, :3], [0.035, 0.0, 0.01])),
    ]
    if second_toolcap:
        lying = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3]
        poses.append((1, make_transform(lying, [-0.03, -0.035, 0.017])))
    return poses


def camera_poses_world(images: int) -> list[np.ndarray]:
    poses = []
    for k in range(images):
        angle = np.radians(-40.0 + 80.0 * k / max(images - 1, 1))
        eye = [0.2 * np.cos(angle), 0.2 * np.sin(angle), 0.13]
        poses.append(look_at(np.array(eye), np.array([0.01, 0.0, 0.02])))
    return poses


def render_image(models, poses_camera: list[tuple[int, np.ndarray]], rng: np.random.Generator, K=K):
    """(rgb uint8, depth mm, per annotation (silhouette, visible mask)) of one view; a plane 0.35 m behind."""
    intrinsics = CameraIntrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], WIDTH, HEIGHT)
    nearest = np.full((HEIGHT, WIDTH), np.inf)
    owner = np.full((HEIGHT, WIDTH), -1, dtype=np.int64)
    silhouettes = []
    for obj_id, T in poses_camera:
        vertices, faces = models[obj_id]
        renderer = DescriptorRenderer((vertices / 1000.0, faces), np.zeros((len(vertices), 1)), np.zeros(1))
        hit = renderer.render(intrinsics, T)
        closer = hit.object_mask & (hit.depth_m < nearest)
        nearest[closer], owner[closer] = hit.depth_m[closer], len(silhouettes)
        silhouettes.append(hit.object_mask)
    depth_mm = np.where(np.isfinite(nearest), nearest * 1000.0, 350.0)
    colours = {1: np.array([200, 200, 210]), 2: np.array([40, 120, 220])}
    rgb = rng.integers(60, 200, size=(HEIGHT, WIDTH, 3))
    shade = np.clip(1.3 - 2.0 * (depth_mm - 150.0) / 1000.0, 0.5, 1.3)[..., None]
    for gt_id, (obj_id, _) in enumerate(poses_camera):
        rgb = np.where((owner == gt_id)[..., None], np.clip(colours[obj_id] * shade, 0, 255), rgb)
    masks = [(silhouettes[g], owner == g) for g in range(len(poses_camera))]
    return rgb.astype(np.uint8), depth_mm, masks


def write_bop_dataset(
    root: Path,
    split: str = "test",
    scene_id: int = 1,
    images: int = 4,
    with_masks: bool = True,
    toolcap_symmetry: bool = True,
    seed: int = 5,
    second_toolcap: bool = False,
    gray_jpeg: bool = False,
    odd_camera: int | None = None,
    models_dir: str = "models",
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Write a one-scene BOP dataset at ``root``; returns the models (vertices mm, faces) by object id.

    ``second_toolcap``: two instances of object 1; ``gray_jpeg``: images in ``gray/`` as JPEG;
    ``odd_camera``: that image gets another camera matrix (zoomed in by 10%)."""
    root = Path(root)
    models = write_models(root / models_dir, toolcap_symmetry)
    rng = np.random.default_rng(seed)
    scene = root / split / f"{scene_id:06d}"
    cameras, gt = {}, {}
    objects = object_poses_world(second_toolcap)
    for im_id, T_world_camera in enumerate(camera_poses_world(images)):
        T_camera_world = invert_transform(T_world_camera)
        poses = [(o, T_camera_world @ T) for o, T in objects]
        camera_K = K * np.array([[1.1], [1.1], [1.0]]) if im_id == odd_camera else K
        rgb, depth_mm, masks = render_image(models, poses, rng, camera_K)
        if gray_jpeg:
            gray = np.repeat(rgb.mean(axis=2, keepdims=True), 3, axis=2)
            bop.write_color_image(scene / "gray" / f"{im_id:06d}.jpg", gray)
        else:
            bop.write_color_image(scene / "rgb" / f"{im_id:06d}.png", rgb)
        bop.write_depth_mm(scene / "depth" / f"{im_id:06d}.png", depth_mm, DEPTH_SCALE)
        cameras[im_id] = {
            "cam_K": camera_K,
            "depth_scale": DEPTH_SCALE,
            "cam_R_w2c": T_camera_world[:3, :3],
            "cam_t_w2c": T_camera_world[:3, 3] * 1000.0,
        }
        gt[im_id] = [{"obj_id": o, "cam_R_m2c": T[:3, :3], "cam_t_m2c": T[:3, 3] * 1000.0} for o, T in poses]
        if with_masks:
            for gt_id, (silhouette, visible) in enumerate(masks):
                bop.write_mask(bop.mask_path(scene, "mask", im_id, gt_id), silhouette)
                bop.write_mask(bop.mask_path(scene, "mask_visib", im_id, gt_id), visible)
    bop.write_scene_camera(scene / "scene_camera.json", cameras)
    bop.write_scene_gt(scene / "scene_gt.json", gt)
    return models
