"""BOP in and out: the file readers and writers (don_gym.data.bop), don-gym import-bop and export --format bop, on
tiny BOP datasets the tests write themselves (tests/bop_scenes.py)."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import bop_scenes
import numpy as np
import pytest

from don_gym.cli import main
from don_gym.data import bop
from don_gym.data.dataset import DATASET_FILE, SCENE_FILE, DONDataset, instance_mask
from don_gym.data.render import DescriptorRenderer
from don_gym.descriptors import DescriptorField
from don_gym.errors import DatasetError, MeshError
from don_gym.geometry import CameraIntrinsics, backproject_depth, invert_transform, transform_points


@pytest.fixture(scope="module")
def bop_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bop") / "tiny"
    bop_scenes.write_bop_dataset(root)
    return root


@pytest.fixture(scope="module")
def imported(bop_root: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("imported") / "toolcap"
    assert main(["import-bop", str(bop_root), "--split", "test", "--object", "1", "--out", str(out)]) == 0
    return out


def _copy(root: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "bop"
    shutil.copytree(root, copy)
    return copy


# --- file formats -------------------------------------------------------------------------------


def test_pose_results_round_trip_and_layout(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rows = [{"scene_id": 3, "im_id": 7, "obj_id": 2, "score": 0.25, "R": R, "t": [1.5, -2.0, 300.0], "time": 0.125}]
    path = tmp_path / "pose_oracle.csv"
    bop.write_pose_results(path, rows)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    fields = lines[1].split(",")  # as BOP's load_bop_results splits them
    assert len(fields) == 7 and len(fields[4].split()) == 9 and len(fields[5].split()) == 3
    np.testing.assert_array_equal(np.array(fields[4].split(), float).reshape(3, 3), R)  # row-major
    (back,) = bop.read_pose_results(path)
    np.testing.assert_array_equal(back["R"], R)
    np.testing.assert_array_equal(back["t"], [1.5, -2.0, 300.0])
    assert (back["scene_id"], back["im_id"], back["obj_id"], back["score"], back["time"]) == (3, 7, 2, 0.25, 0.125)
    assert not list(tmp_path.glob(".*partial*"))
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,2,3,0.5,1 0 0,0 0 0,1\n")
    with pytest.raises(DatasetError, match="line 2"):
        bop.read_pose_results(path)


def _parse_ply_as_bop_does(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The subset of BOP's PLY reader our files need: header properties, then binary records of the types
    its reader knows (float, double, int, uint, uchar)."""
    formats = {"float": ("f", 4), "double": ("d", 8), "int": ("i", 4), "uint": ("I", 4), "uchar": ("B", 1)}
    with path.open("rb") as f:
        vertex_props, face_props, section, counts = [], [], None, {}
        while (line := f.readline().decode().strip()) != "end_header":
            words = line.split()
            if words[0] == "format":
                assert words[1] == "binary_little_endian"
            if words[0] == "element":
                section, counts[words[1]] = words[1], int(words[2])
            elif words[0] == "property" and section == "vertex":
                vertex_props.append(formats[words[1]])
            elif words[:2] == ["property", "list"] and section == "face":
                assert words[-1] == "vertex_indices"
                face_props = [formats[words[2]]] + [formats[words[3]]] * 3
        vertices = [[struct.unpack(c, f.read(n))[0] for c, n in vertex_props] for _ in range(counts["vertex"])]
        faces = [[struct.unpack(c, f.read(n))[0] for c, n in face_props] for _ in range(counts["face"])]
    faces = np.array(faces)
    assert np.all(faces[:, 0] == 3)
    return np.array(vertices), faces[:, 1:]


def test_ply_model_is_written_as_bop_reads_it_and_a_point_cloud_is_refused(tmp_path: Path) -> None:
    vertices, faces = bop_scenes.box_mm()
    path = tmp_path / "obj_000002.ply"
    bop.write_ply_model(path, vertices, faces)
    parsed_vertices, parsed_faces = _parse_ply_as_bop_does(path)
    np.testing.assert_allclose(parsed_vertices, vertices, atol=1e-4)
    np.testing.assert_array_equal(parsed_faces, faces)
    read_vertices, read_faces = bop.read_ply_model(path)
    np.testing.assert_allclose(read_vertices, vertices, atol=1e-4)
    np.testing.assert_array_equal(read_faces, faces)
    cloud = tmp_path / "cloud.ply"
    cloud.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n10 0 0\n0 10 0\n"
    )
    with pytest.raises(MeshError, match="cloud.ply: a PLY without faces"):
        bop.read_ply_model(cloud)


def test_json_files_round_trip_with_bop_types(tmp_path: Path) -> None:
    K = bop_scenes.K
    bop.write_scene_camera(tmp_path / "scene_camera.json", {0: {"cam_K": K, "depth_scale": 0.1}})
    raw = json.loads((tmp_path / "scene_camera.json").read_text())
    assert list(raw) == ["0"] and len(raw["0"]["cam_K"]) == 9 and raw["0"]["depth_scale"] == 0.1
    camera = bop.read_scene_camera(tmp_path / "scene_camera.json")[0]
    np.testing.assert_array_equal(camera["cam_K"], K)
    info = bop.models_info_entry(bop_scenes.box_mm()[0], symmetries_discrete=bop_scenes.box_symmetries())
    assert info["diameter"] == pytest.approx(2 * np.linalg.norm(bop_scenes.BOX_HALF_MM))
    bop.write_models_info(tmp_path / "models_info.json", {2: info})
    raw = json.loads((tmp_path / "models_info.json").read_text())
    assert len(raw["2"]["symmetries_discrete"]) == 3 and len(raw["2"]["symmetries_discrete"][0]) == 16
    back = bop.read_models_info(tmp_path / "models_info.json")[2]
    np.testing.assert_array_equal(back["symmetries_discrete"][2], bop_scenes.box_symmetries()[2])


# --- import ---------------------------------------------------------------------------------------


def test_import_writes_version_2_with_true_poses_occlusion_and_targets(bop_root: Path, imported: Path) -> None:
    data = DONDataset(imported)
    assert data.info["version"] == 2 and data.scene_kind == "bop"
    assert [p["name"] for p in data.parts] == ["obj_000001"] and data.parts[0]["object_scale"] == 0.001
    field = DescriptorField.load(imported / "descriptor_field.npz")
    model = data.object_model()
    np.testing.assert_allclose(model.symmetry_axis, [0.0, 0.0, 1.0])  # models_info.json's continuous symmetry
    renderer = DescriptorRenderer(model.mesh, field.vertex_descriptors, field.background)
    gt = bop.read_scene_gt(bop_root / "test" / "000001" / "scene_gt.json")
    record = data.scenes[0]
    assert record.num_frames == 4 and record.instances == [{"instance_id": 1, "part": "obj_000001"}]
    occluded = 0
    for frame in range(record.num_frames):
        truth = gt[frame][0]
        pose = record.T_camera_object(frame)[1]
        np.testing.assert_allclose(pose[:3, :3], truth["cam_R_m2c"], atol=1e-12)
        np.testing.assert_allclose(pose[:3, 3] * 1000.0, truth["cam_t_m2c"], atol=1e-9)
        # The scene frame is the part's: the camera pose follows from the part's pose alone.
        np.testing.assert_allclose(record.T_world_camera[frame], invert_transform(pose), atol=1e-12)
        visible = bop.read_mask(bop.mask_path(bop_root / "test" / "000001", "mask_visib", frame, 0))
        silhouette = bop.read_mask(bop.mask_path(bop_root / "test" / "000001", "mask", frame, 0))
        occluded += int((silhouette & ~visible).sum())
        mask, target_mask = data.image(0, frame, "mask"), data.image(0, frame, "target_mask")
        np.testing.assert_array_equal(mask, visible)
        np.testing.assert_array_equal(target_mask, visible & renderer.render(record.intrinsics, pose).object_mask)
        np.testing.assert_array_equal(instance_mask(data, 0, frame), np.where(mask, 1, 0))
        expected = renderer.render(record.intrinsics, pose, visible_mask=visible).descriptor_image
        np.testing.assert_allclose(data.image(0, frame, "descriptor"), expected, atol=1e-4)
        depth_mm = bop.read_depth_mm(
            bop_root / "test" / "000001" / "depth" / f"{frame:06d}.png", bop_scenes.DEPTH_SCALE
        )
        np.testing.assert_allclose(data.image(0, frame, "depth"), depth_mm / 1000.0, atol=6e-4)
    assert occluded > 20, "the box should hide part of the toolcap in some views"


def test_import_correspondences_follow_the_part(imported: Path) -> None:
    from don_gym.learning.torch_data import CorrespondencePairs

    data = DONDataset(imported)
    record = data.scenes[0]
    pairs = CorrespondencePairs(str(imported), length=4, seed=2)
    for i in range(4):
        _, a, b = pairs._pick_pair(np.random.default_rng([2, i]))
        matches = pairs[i]["correspondences"]
        assert matches.num_matches > 100
        points = []
        for frame, uv in ((a, matches.matches_a), (b, matches.matches_b)):
            camera_points = backproject_depth(record.intrinsics, data.image(0, frame, "depth_fused"), uv)
            points.append(transform_points(invert_transform(record.T_camera_object(frame)[1]), camera_points))
        error = np.linalg.norm(points[0] - points[1], axis=1)
        # One pixel at this distance is about 3 mm; a wrong pose would be centimetres off.
        assert np.median(error) < 0.003 and np.max(error) < 0.01


def test_import_of_two_instances_gray_jpeg_another_camera_and_models_dir(tmp_path: Path) -> None:
    from don_gym.data.import_bop import import_bop
    from don_gym.learning.torch_data import CorrespondencePairs

    root = tmp_path / "bop"
    bop_scenes.write_bop_dataset(
        root, images=5, second_toolcap=True, gray_jpeg=True, odd_camera=2, models_dir="models_cad", with_masks=False
    )
    result = import_bop(root, "test", 1, tmp_path / "data", models_dir="models_cad")
    assert result.frames == 4 and any("image 2: skipped" in note for note in result.notes), result.notes
    data = DONDataset(tmp_path / "data")
    record = data.scenes[0]
    assert record.metadata["bop"]["im_ids"] == [0, 1, 3, 4]
    assert [i["instance_id"] for i in record.instances] == [1, 3]  # BOP's gt_id + 1: the box is gt_id 1
    field = DescriptorField.load(tmp_path / "data" / "descriptor_field.npz")
    renderer = DescriptorRenderer(data.object_model().mesh, field.vertex_descriptors, field.background)
    for frame in range(record.num_frames):
        rgb = data.image(0, frame, "rgb")
        assert np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 1], rgb[..., 2])
        instances = instance_mask(data, 0, frame)
        assert (instances == 1).sum() > 20 and (instances == 3).sum() > 20
        np.testing.assert_array_equal(data.image(0, frame, "mask"), instances > 0)
        descriptor = data.image(0, frame, "descriptor")
        for instance_id, pose in record.T_camera_object(frame).items():
            expected = renderer.render(record.intrinsics, pose, visible_mask=instances == instance_id)
            np.testing.assert_allclose(
                descriptor[expected.object_mask], expected.descriptor_image[expected.object_mask], atol=1e-4
            )
        # The self-supervised matches are drawn on the reference instance only, whose pose defines the frame.
        assert not (data.image(0, frame, "mask_fused") & (instances != 1)).any()
    pairs = CorrespondencePairs(str(tmp_path / "data"), length=2, seed=1)
    for i in range(2):
        _, a, _ = pairs._pick_pair(np.random.default_rng([1, i]))
        uv = pairs[i]["correspondences"].matches_a
        assert len(uv) and np.all(instance_mask(data, 0, a)[uv[:, 1], uv[:, 0]] == 1)


def test_version_1_scenes_read_as_one_instance(imported: Path, tmp_path: Path) -> None:
    copy = tmp_path / "v1"
    shutil.copytree(imported, copy)
    info = json.loads((copy / DATASET_FILE).read_text())
    for key in ("parts", "scene_kind"):
        info.pop(key)
    info["version"] = 1
    (copy / DATASET_FILE).write_text(json.dumps(info))
    scene_file = copy / "scenes" / "scene_000000" / SCENE_FILE
    meta = json.loads(scene_file.read_text())
    recorded = meta.pop("T_camera_object")
    meta.pop("instances")
    scene_file.write_text(json.dumps(meta))
    (copy / "scenes" / "scene_000000" / "instance").rename(copy / "scenes" / "scene_000000" / "gone")
    data = DONDataset(copy)
    assert data.parts[0]["name"] == "obj_000001" and data.parts[0]["mesh_hash"] == info["mesh_hash"]
    (instance,) = data.scenes[0].instances
    assert instance["instance_id"] == 1 and instance["part"] == "obj_000001"
    for frame in range(data.scenes[0].num_frames):
        np.testing.assert_allclose(data.scenes[0].T_camera_object(frame)[1], recorded[frame]["1"], atol=1e-9)
        np.testing.assert_array_equal(instance_mask(data, 0, frame), np.where(data.image(0, frame, "mask"), 1, 0))
    with pytest.raises(DatasetError, match="no instance image"):
        data.image(0, 0, "instance")


def test_symmetry_disagreement_is_one_note_that_says_how(bop_root: Path, tmp_path: Path, capsys) -> None:
    capsys.readouterr()
    # The box: BOP declares its three 180-degree turns; the descriptor field tells them apart.
    out = tmp_path / "box"
    assert main(["import-bop", str(bop_root), "--split", "test", "--object", "2", "--out", str(out)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "object 2" in notes[0] and notes[0].count("180 deg about") == 3, notes
    assert "tell apart poses that BOP scores as equal" in notes[0]
    assert DONDataset(out).scenes[0].num_frames == 4
    # The toolcap without its declared continuous symmetry: the field cannot tell turns about its axis apart.
    root = tmp_path / "undeclared"
    bop_scenes.write_bop_dataset(root, images=2, with_masks=False, toolcap_symmetry=False)
    assert main(["import-bop", str(root), "--split", "test", "--object", "1", "--out", str(tmp_path / "t")]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "does not declare" in notes[0] and "[0.0, 0.0, 1.0]" in notes[0].replace("-", "")


def test_training_and_evaluation_run_on_an_import(imported: Path, tmp_path: Path) -> None:
    for method in ("supervised-edge", "self-supervised"):
        argv = ["train", "--method", method, "--data", str(imported), "--out", str(tmp_path / method)]
        assert main([*argv, "--steps", "2", "--batch-size", "2", "--crop", "none", "--threads", "1"]) == 0
    models = ["oracle", str(tmp_path / "supervised-edge" / "model.safetensors")]
    argv = ["evaluate", "--data", str(imported), "--models", *models, "--out", str(tmp_path / "eval")]
    assert main([*argv, "--no-progress"]) == 0
    summary = json.loads((tmp_path / "eval" / "tracking.json").read_text())
    oracle = summary["methods"]["oracle"]
    # The part's points are tracked through the import's poses: modulo the symmetry that models_info.json
    # declares (the toolcap's symmetric points share descriptors), the oracle's matches are exact to a pixel.
    assert oracle["counts"]["matches_with_depth"] > 20 and oracle["error_3d_symmetric_mm"]["p50"] < 2.0


# --- bad input: one line naming the file, nothing written ---------------------------------------------


def _break_scene_camera(root: Path, change) -> None:
    path = root / "test" / "000001" / "scene_camera.json"
    cameras = json.loads(path.read_text())
    for entry in cameras.values():
        change(entry)
    path.write_text(json.dumps(cameras))


def _metres_model(root: Path) -> None:
    vertices, faces = bop_scenes.toolcap_mm()
    bop.write_ply_model(root / "models" / "obj_000001.ply", vertices / 1000.0, faces)


def _point_cloud(root: Path) -> None:
    (root / "models" / "obj_000002.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n10 0 0\n0 10 0\n"
    )


BAD_INPUTS = {
    "no scene_camera.json": (
        lambda r: (r / "test/000001/scene_camera.json").unlink(),
        [],
        "scene_camera.json: not found",
    ),
    "no model": (lambda r: (r / "models/obj_000002.ply").unlink(), [], "obj_000002.ply: model"),
    "object absent": (lambda r: None, ["--object", "9"], "--object 9 is annotated in no image"),
    "PLY without faces": (_point_cloud, [], "obj_000002.ply: a PLY without faces"),
    "no depth_scale": (lambda r: _break_scene_camera(r, lambda e: e.pop("depth_scale")), [], "has no depth_scale"),
    "model in metres": (_metres_model, [], "obj_000001.ply: diameter 0.0494"),
    "image larger than cam_K": (
        lambda r: _break_scene_camera(r, lambda e: e.update(cam_K=[600, 0, 319.5, 0, 600, 239.5, 0, 0, 1])),
        [],
        "rgb/000000.png: a 64x48 image does not fit cam_K",
    ),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_one_line_naming_the_file_and_nothing_is_written(
    case: str, bop_root: Path, tmp_path: Path, capsys
) -> None:
    root = _copy(bop_root, tmp_path)
    breaks, extra, message = BAD_INPUTS[case]
    breaks(root)
    out = tmp_path / "out" / "data"
    argv = ["import-bop", str(root), "--split", "test", "--object", "1", "--out", str(out), *extra]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert message in err, err
    assert not out.parent.exists()


# --- export -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    from don_gym.data.build import DatasetConfig, build_dataset

    out = tmp_path_factory.mktemp("sim") / "data"
    config = DatasetConfig(scenes=1, frames_per_scene=3, image_size=(64, 48), sensor="ideal", seed=3, fuse_depth=False)
    build_dataset(config, out, progress=False)
    return out


def test_build_dataset_writes_version_2_keys(simulated: Path) -> None:
    data = DONDataset(simulated)
    assert data.info["version"] == 2 and data.scene_kind == "single"
    (part,) = data.parts
    assert part["name"] == data.info["object_name"] and part["mesh_hash"] == data.info["mesh_hash"]
    record = data.scenes[0]
    (instance,) = record.instances
    np.testing.assert_array_equal(instance["T_world_object"], record.T_world_object)
    for frame in range(record.num_frames):
        expected = invert_transform(record.T_world_camera[frame]) @ record.T_world_object
        np.testing.assert_allclose(record.T_camera_object(frame)[1], expected, atol=1e-12)


def test_export_is_read_as_bop_reads_it_and_imports_back(simulated: Path, tmp_path: Path) -> None:
    out = tmp_path / "bop"
    assert main(["export", str(simulated), "--format", "bop", "--split", "test", "--out", str(out)]) == 0
    data = DONDataset(simulated)
    record = data.scenes[0]
    scene = out / "test" / f"{record.index:06d}"
    # Keys and types as BOP's inout reads them (keys_to_int, cam_K 3x3, R 3x3, t 3x1).
    cameras = {int(k): v for k, v in json.loads((scene / "scene_camera.json").read_text()).items()}
    gt = {int(k): v for k, v in json.loads((scene / "scene_gt.json").read_text()).items()}
    info = {int(k): v for k, v in json.loads((scene / "scene_gt_info.json").read_text()).items()}
    models = {int(k): v for k, v in json.loads((out / "models" / "models_info.json").read_text()).items()}
    assert sorted(cameras) == sorted(gt) == sorted(info) == list(range(record.num_frames))
    np.testing.assert_allclose(np.reshape(cameras[0]["cam_K"], (3, 3)), record.intrinsics.K)
    assert cameras[0]["depth_scale"] == 1.0 and len(cameras[0]["cam_t_w2c"]) == 3
    (symmetry,) = models[1]["symmetries_continuous"]
    np.testing.assert_allclose(symmetry["axis"], [0, 0, 1])
    vertices, _ = _parse_ply_as_bop_does(out / "models" / "obj_000001.ply")
    assert (
        models[1]["diameter"] == pytest.approx(bop.model_diameter(vertices), rel=1e-5)
        and 30 < models[1]["diameter"] < 100
    )
    for frame in range(record.num_frames):
        (entry,) = gt[frame]
        assert entry["obj_id"] == 1 and len(entry["cam_R_m2c"]) == 9 and len(entry["cam_t_m2c"]) == 3
        (entry_info,) = info[frame]
        visible = bop.read_mask(bop.mask_path(scene, "mask_visib", frame, 0))
        assert entry_info["px_count_visib"] == visible.sum() > 0
        assert entry_info["bbox_visib"] == bop.bbox_of(visible)
        assert 0 < entry_info["visib_fract"] <= 1 and entry_info["px_count_all"] >= entry_info["px_count_visib"]
        depth = bop.read_depth_mm(scene / "depth" / f"{frame:06d}.png", cameras[frame]["depth_scale"])
        np.testing.assert_allclose(depth / 1000.0, data.image(0, frame, "depth"), atol=1e-6)
    again = tmp_path / "again"
    assert main(["import-bop", str(out), "--split", "test", "--object", "1", "--out", str(again)]) == 0
    back = DONDataset(again)
    for frame in range(record.num_frames):
        np.testing.assert_allclose(
            back.scenes[0].T_camera_object(frame)[1], record.T_camera_object(frame)[1], atol=1e-9
        )
        for kind in ("mask", "target_mask"):
            np.testing.assert_array_equal(back.image(0, frame, kind), data.image(0, frame, kind))
        both = back.image(0, frame, "target_mask")
        difference = np.abs(back.image(0, frame, "descriptor") - data.image(0, frame, "descriptor"))[both]
        assert difference.max() < 0.01
    # A second export of the same split is refused, and leaves the first alone.
    assert main(["export", str(simulated), "--format", "bop", "--split", "test", "--out", str(out)]) == 2
    assert (scene / "scene_gt.json").is_file()


def test_intrinsics_check_uses_the_image_size() -> None:
    from don_gym.data.import_bop import _Image, _intrinsics

    image = _Image(1, 0, Path("rgb/000000.png"), Path("depth/000000.png"), {"cam_K": bop_scenes.K}, [])
    assert _intrinsics(image, 64, 48) == CameraIntrinsics(70.0, 70.0, 31.5, 23.5, 64, 48)
    with pytest.raises(DatasetError, match="does not fit cam_K"):
        _intrinsics(image, 30, 20)


def test_overwrite_replaces_a_dataset_and_nothing_else(bop_root: Path, tmp_path: Path, capsys) -> None:
    argv = ["import-bop", str(bop_root), "--split", "test", "--object", "2", "--out"]
    other = tmp_path / "notes"
    other.mkdir()
    (other / "mine.txt").write_text("keep")
    for extra in ([], ["--overwrite"]):
        assert main([*argv, str(other), *extra]) == 2
        assert "mine.txt" not in capsys.readouterr().err and (other / "mine.txt").read_text() == "keep"
    data = tmp_path / "data"
    assert main([*argv, str(data)]) == 0
    assert main([*argv, str(data)]) == 2 and "--overwrite" in capsys.readouterr().err
    (data / "stale.txt").write_text("from before")
    assert main([*argv, str(data), "--overwrite"]) == 0
    assert not (data / "stale.txt").exists() and DONDataset(data).info["bop"]["obj_id"] == 2
