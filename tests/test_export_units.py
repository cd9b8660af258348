"""Units and conventions on the way out. A part whose centre of mass is off its origin (a BOP model in
millimetres, imported) exports with its symmetry's offset in millimetres and its poses as they came in;
a pose results file holds the rotation of the pose it came from, row-major, and the translation in
millimetres. Each file is read here as BOP's own tools read it, not with the writer's counterpart."""

from __future__ import annotations

import json
from pathlib import Path

import bop_scenes
import numpy as np
import pytest
import trimesh
from synthetic_scenes import look_at

from don_gym.data import bop
from don_gym.data.dataset import DONDataset
from don_gym.data.export import export_bop
from don_gym.data.import_bop import import_bop
from don_gym.evaluation.pose_evaluation import OBJECT_ID, PoseEstimates
from don_gym.evaluation.pose_metrics import bop_symmetries
from don_gym.geometry import invert_transform, make_transform

#: Where the model file's origin is NOT: its centre of mass sits here in the file's frame (mm).
CENTRE_MM = np.array([21.0, -13.0, 34.0])


def _write_off_centre_scene(root: Path) -> list[np.ndarray]:
    """A one-scene BOP dataset of the toolcap whose model file has its origin 44 mm from its centre of mass;
    the annotated poses (model frame in the camera frame, metres) of its three images."""
    vertices, faces = bop_scenes.toolcap_mm()
    vertices = vertices + CENTRE_MM
    models = {1: (vertices, faces)}
    bop.write_ply_model(root / "models" / "obj_000001.ply", vertices, faces)
    info = {1: bop.models_info_entry(vertices)}
    info[1]["symmetries_continuous"] = [{"axis": [0.0, 0.0, 1.0], "offset": list(CENTRE_MM)}]
    bop.write_models_info(root / "models" / "models_info.json", info)
    # The part lying tilted, its centre of mass 2 cm above the world origin.
    R = trimesh.transformations.rotation_matrix(0.9, [1.0, 0.2, 0.0])[:3, :3]
    T_world_model = make_transform(R, np.array([0.0, 0.0, 0.02]) - R @ (CENTRE_MM / 1000.0))
    scene = root / "test" / "000001"
    cameras, gt, poses = {}, {}, []
    rng = np.random.default_rng(1)
    for im_id, angle in enumerate(np.radians([-25.0, 0.0, 25.0])):
        eye = np.array([0.17 * np.cos(angle), 0.17 * np.sin(angle), 0.12])
        T = invert_transform(look_at(eye, np.array([0.0, 0.0, 0.02]))) @ T_world_model
        rgb, depth_mm, _ = bop_scenes.render_image(models, [(1, T)], rng)
        bop.write_color_image(scene / "rgb" / f"{im_id:06d}.png", rgb)
        bop.write_depth_mm(scene / "depth" / f"{im_id:06d}.png", depth_mm, 1.0)
        cameras[im_id] = {"cam_K": bop_scenes.K, "depth_scale": 1.0}
        gt[im_id] = [{"obj_id": 1, "cam_R_m2c": T[:3, :3], "cam_t_m2c": T[:3, 3] * 1000.0}]
        poses.append(T)
    bop.write_scene_camera(scene / "scene_camera.json", cameras)
    bop.write_scene_gt(scene / "scene_gt.json", gt)
    return poses


def test_a_part_off_its_origin_exports_its_symmetry_and_poses_in_millimetres(tmp_path: Path) -> None:
    poses = _write_off_centre_scene(tmp_path / "bop")
    import_bop(tmp_path / "bop", "test", 1, tmp_path / "data")
    data = DONDataset(tmp_path / "data")
    model = data.object_model()
    np.testing.assert_allclose(model.center_of_mass, CENTRE_MM / 1000.0, atol=1e-4)
    np.testing.assert_allclose(model.symmetry_axis, [0.0, 0.0, 1.0])
    out = tmp_path / "export"
    export_bop(data, out, split="test")
    raw = json.loads((out / "models" / "models_info.json").read_text())["1"]
    (continuous,) = raw["symmetries_continuous"]
    np.testing.assert_allclose(continuous["offset"], CENTRE_MM, atol=0.1)  # millimetres, as BOP reads it
    # As BOP's tools turn it into transforms: every one keeps the part where it is (its centre of mass fixed).
    centre_m = CENTRE_MM / 1000.0
    symmetries = bop_symmetries(raw)
    assert len(symmetries) > 10
    for S in symmetries:
        np.testing.assert_allclose(S[:3, :3] @ centre_m + S[:3, 3], centre_m, atol=1e-6)
    vertices_mm, _ = bop.read_ply_model(out / "models" / "obj_000001.ply")
    np.testing.assert_allclose(vertices_mm.mean(axis=0), (model.mesh.vertices * 1000.0).mean(axis=0), atol=1e-3)
    assert raw["diameter"] == pytest.approx(bop.model_diameter(vertices_mm), rel=1e-6) and 40 < raw["diameter"] < 60
    # The exported poses are the annotated ones: same model frame, millimetres.
    exported = json.loads((out / "test" / "000000" / "scene_gt.json").read_text())
    for im_id, T in enumerate(poses):
        (entry,) = exported[str(im_id)]
        np.testing.assert_allclose(np.reshape(entry["cam_R_m2c"], (3, 3)), T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(entry["cam_t_m2c"], T[:3, 3] * 1000.0, atol=1e-6)


def test_a_results_file_holds_the_pose_it_came_from(tmp_path: Path) -> None:
    R = trimesh.transformations.rotation_matrix(0.7, [0.3, -0.5, 0.8])[:3, :3]
    T = make_transform(R, [0.012, -0.034, 0.456])
    none = np.full((4, 4), np.nan)
    estimates = PoseEstimates(
        scene_id=np.array([3, 3]),
        dataset=np.array([0, 0]),
        scene=np.array([3, 3]),
        frame=np.array([5, 6]),
        found=np.array([True, False]),
        T_camera_object=np.stack([T, none]),
        score=np.array([0.75, 0.0]),
        time_s=np.array([0.25, 0.1]),
        inliers=np.array([40, 0]),
        mssd_m=np.array([0.001, np.inf]),
        mspd_px=np.array([1.0, np.inf]),
        adds_m=np.array([0.001, np.inf]),
        image_width=np.array([640, 640]),
    )
    path = tmp_path / "pose_oracle.csv"
    bop.write_pose_results(path, estimates.bop_rows())
    header, *lines = path.read_text().splitlines()
    assert header == "scene_id,im_id,obj_id,score,R,t,time" and len(lines) == 1  # no row without an estimate
    scene_id, im_id, obj_id, score, R_text, t_text, seconds = lines[0].split(",")
    assert (int(scene_id), int(im_id), int(obj_id)) == (3, 5, OBJECT_ID)
    assert float(score) == 0.75 and float(seconds) == 0.25
    # BOP's results format: R row-major (r11 r12 r13 r21 ...), t in millimetres.
    np.testing.assert_allclose(np.array(R_text.split(), dtype=float).reshape(3, 3), R, atol=1e-12)
    np.testing.assert_allclose(np.array(t_text.split(), dtype=float), [12.0, -34.0, 456.0], atol=1e-9)
