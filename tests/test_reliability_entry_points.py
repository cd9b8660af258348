"""The entry points added with bins and BOP under bad input and faults (docs/reliability.md): bin builds' options,
scene kinds that must not mix, BOP export of several parts and into a folder that holds other data, damaged
meshes, an import killed part-way, and frames whose header declares another size. Each is one line on stderr,
exit status 2, with nothing half-written or lost."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zlib
from pathlib import Path

import bop_scenes
import numpy as np
import pytest
from file_snapshots import snapshot

from don_gym.cli import main
from don_gym.data import bop
from don_gym.data import dataset as dataset_module
from don_gym.data.bin_dataset import build_bin_dataset
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.data.dataset import DONDataset, frame_path, png_size
from don_gym.errors import DatasetError, MeshError
from don_gym.objects import load_object

TINY = DatasetConfig(scenes=1, frames_per_scene=2, image_size=(64, 48), fuse_depth=False, seed=5)
TINY_BIN = DatasetConfig(scenes=1, frames_per_scene=2, image_size=(48, 32), fuse_depth=False, seed=7)


def _one_line_error(code: int, stderr: str, *expected: str) -> str:
    assert code == 2 and "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("don-gym ")]  # progress bars aside
    assert len(lines) == 1, stderr
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def bin_dataset(tmp_path_factory) -> Path:
    """A pile of one toolcap and one shaft, one scene of two frames; tests copy it before changing anything."""
    out = tmp_path_factory.mktemp("bin") / "pile"
    build_bin_dataset(TINY_BIN, {"toolcap": 1, "shaft": 1}, out, progress=False)
    return out


@pytest.fixture(scope="module")
def single_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("single") / "ds"
    build_dataset(TINY, out, progress=False)
    return out


# --- 2: bin builds' options -------------------------------------------------------------------------------------


def test_a_bin_build_refuses_object_and_a_count_of_zero(tmp_path: Path, capsys) -> None:
    out = tmp_path / "data"
    bin_build = ["build-dataset", "--scene", "bin", "--out", str(out)]
    code = main([*bin_build, "--object", "my_part.stl", "--parts", "toolcap:3"])
    _one_line_error(code, capsys.readouterr().err, "--object 'my_part.stl'", "--parts")
    code = main(["build-dataset", "--scene", "bin", "--parts", "toolcap:0", "--out", str(out)])
    line = _one_line_error(code, capsys.readouterr().err, "'toolcap'", "at least 1")
    assert "not among the parts" not in line
    code = main(["build-dataset", "--scene", "bin", "--parts", "toolcap:2,shaft:0", "--out", str(out)])
    _one_line_error(code, capsys.readouterr().err, "'shaft'", "at least 1")
    # The reverse: --parts without --scene bin is not ignored either.
    code = main(["build-dataset", "--parts", "shaft:2", "--out", str(out)])
    _one_line_error(code, capsys.readouterr().err, "--parts 'shaft:2'", "--scene bin")
    assert not out.exists()


# --- 3: scene kinds do not mix ------------------------------------------------------------------------------------


def test_a_one_part_build_into_a_bin_dataset_is_refused(bin_dataset: Path, tmp_path: Path, capsys) -> None:
    pile = tmp_path / "pile"
    shutil.copytree(bin_dataset, pile)
    before = snapshot(pile)
    with pytest.raises(DatasetError, match="scene kind 'bin'"):
        build_dataset(DatasetConfig(**{**TINY_BIN.__dict__, "scenes": 3}), pile, progress=False)
    args = ["--scenes", "3", "--frames", "2", "--size", "48x32", "--no-fusion", "--seed", "7", "--out", str(pile)]
    code = main(["build-dataset", "--object", "toolcap", *args])
    _one_line_error(code, capsys.readouterr().err, str(pile), "scene kind 'bin'", "--overwrite")
    assert snapshot(pile) == before


# --- 4, 5: BOP export of several parts, into a folder that holds other data ---------------------------------------


def _gt_obj_ids(scene: Path) -> dict[int, list[int]]:
    return {int(k): [e["obj_id"] for e in v] for k, v in json.loads((scene / "scene_gt.json").read_text()).items()}


def test_bop_export_gives_every_part_its_own_object(bin_dataset: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "bop"
    assert main(["export", str(bin_dataset), "--format", "bop", "--split", "train", "--out", str(out)]) == 0
    assert "toolcap = obj_id 1, shaft = obj_id 2" in capsys.readouterr().out
    info = bop.read_models_info(out / "models" / "models_info.json")
    assert sorted(info) == [1, 2]
    for obj_id, part in ((1, "toolcap"), (2, "shaft")):
        model = load_object(out / "models" / f"obj_{obj_id:06d}.ply", scale=0.001)
        assert not model.shape_signature.differences(load_object(part).shape_signature), part
    data = DONDataset(bin_dataset)
    record = data.scenes[0]
    parts = {int(i["instance_id"]): i["part"] for i in record.instances}
    scene = out / "train" / f"{record.index:06d}"
    shaft_pixels = 0
    for frame, obj_ids in _gt_obj_ids(scene).items():
        instance_ids = sorted(record.T_camera_object(frame))
        assert obj_ids == [{"toolcap": 1, "shaft": 2}[parts[i]] for i in instance_ids]
        instances = data.image(0, frame, "instance")
        for gt_id, instance_id in enumerate(instance_ids):
            visible = bop.read_mask(bop.mask_path(scene, "mask_visib", frame, gt_id))
            assert not (visible & (instances != instance_id)).any()  # its own pixels, with its own model's silhouette
            shaft_pixels += int(visible.sum()) if parts[instance_id] == "shaft" else 0
    assert shaft_pixels > 0
    # The shaft comes back as the shaft.
    back = tmp_path / "shaft"
    assert main(["import-bop", str(out), "--split", "train", "--object", "2", "--out", str(back)]) == 0
    assert not DONDataset(back).object_model().shape_signature.differences(load_object("shaft").shape_signature)


def test_bop_export_into_a_folder_with_other_models_adds_and_changes_nothing(
    single_dataset: Path, bin_dataset: Path, tmp_path: Path, capsys
) -> None:
    out = tmp_path / "bop"
    bop_scenes.write_models(out / "models")  # object 1 the toolcap, object 2 a box: another dataset's
    before = snapshot(out)
    assert main(["export", str(single_dataset), "--format", "bop", "--split", "train", "--out", str(out)]) == 0
    # The toolcap is object 1 there already: its model and models_info.json stay as they were.
    assert {k: v for k, v in snapshot(out).items() if k.startswith("models/")} == before
    assert set(sum(_gt_obj_ids(next((out / "train").iterdir())).values(), [])) == {1}
    train = snapshot(out / "train")
    info = json.loads((out / "models" / "models_info.json").read_text())
    assert main(["export", str(bin_dataset), "--format", "bop", "--split", "test", "--out", str(out)]) == 0
    # The shaft is new: object 3, added beside the others, which stay untouched.
    after = snapshot(out)
    assert all(after[name] == digest for name, digest in before.items() if name.endswith(".ply"))
    assert snapshot(out / "train") == train
    now = json.loads((out / "models" / "models_info.json").read_text())
    assert {k: now[k] for k in info} == info and sorted(now) == ["1", "2", "3"]
    shaft = load_object(out / "models" / "obj_000003.ply", scale=0.001)
    assert not shaft.shape_signature.differences(load_object("shaft").shape_signature)
    assert set(sum(_gt_obj_ids(next((out / "test").iterdir())).values(), [])) == {1, 3}
    # A split that is there is refused in one line, and nothing changes.
    everything = snapshot(out)
    code = main(["export", str(bin_dataset), "--format", "bop", "--split", "test", "--out", str(out)])
    _one_line_error(code, capsys.readouterr().err, "test", "exists")
    assert snapshot(out) == everything
    # Models without their models_info.json are another's data we cannot read: refused, nothing written.
    (out / "models" / "models_info.json").unlink()
    other = out / "train"
    shutil.rmtree(other)
    everything = snapshot(out)
    code = main(["export", str(single_dataset), "--format", "bop", "--split", "train", "--out", str(out)])
    _one_line_error(code, capsys.readouterr().err, "models_info.json")
    assert snapshot(out) == everything and not other.exists()


# --- 6: damaged meshes --------------------------------------------------------------------------------------------


def _damaged_ply(path: Path, vertex: int = 9999) -> Path:
    vertices = np.asarray(bop_scenes.box_mm()[0][:14])
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", "element face 4", "property list uchar int vertex_indices", "end_header"]  # fmt: skip
    lines += [" ".join(f"{v:.3f}" for v in p) for p in vertices]
    lines += ["3 0 1 2", "3 0 2 3", f"3 1 2 {vertex}", "3 0 1 3"]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_damaged_mesh_is_one_line_naming_the_file(tmp_path: Path, capsys) -> None:
    damaged = _damaged_ply(tmp_path / "parts" / "bad part.ply")
    for vertex in (9999, -1):
        _damaged_ply(damaged, vertex)
        with pytest.raises(MeshError, match=f"vertex {vertex}"):
            load_object(damaged)
    _damaged_ply(damaged)
    code = main(["embed", str(damaged)])
    _one_line_error(code, capsys.readouterr().err, "bad part.ply", "vertex 9999", "14 vertices")
    code = main(["build-dataset", "--object", str(damaged), "--out", str(tmp_path / "data")])
    _one_line_error(code, capsys.readouterr().err, "bad part.ply", "vertex 9999")
    assert not (tmp_path / "data").exists()
    # import-bop: the damaged model is the part's.
    root = tmp_path / "bop"
    bop_scenes.write_bop_dataset(root, images=2, with_masks=False)
    _damaged_ply(root / "models" / "obj_000001.ply")
    code = main(["import-bop", str(root), "--split", "test", "--object", "1", "--out", str(tmp_path / "imported")])
    _one_line_error(code, capsys.readouterr().err, "obj_000001.ply", "vertex 9999")
    assert not (tmp_path / "imported").exists() and not list(tmp_path.glob(".imported.partial-*"))


# --- 7: an import killed part-way ---------------------------------------------------------------------------------


def test_a_killed_import_leaves_a_copy_the_rerun_removes(tmp_path: Path, capsys) -> None:
    root = tmp_path / "BOP daten"
    bop_scenes.write_bop_dataset(root, images=6)
    out = tmp_path / "Ausgabe für Tests" / "my data"
    out.parent.mkdir()
    command = [sys.executable, "-m", "don_gym.cli", "import-bop", str(root), "--split", "test", "--object", "1",
               "--out", str(out)]  # fmt: skip
    importer = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240

    def partial_with_scene() -> list[Path]:
        return [p for p in out.parent.glob(".my data.partial-*") if (p / "scenes").is_dir()]

    while not partial_with_scene():
        assert importer.poll() is None, importer.stderr.read().decode()
        assert time.monotonic() < deadline, "the import never started writing"
        time.sleep(0.005)
    importer.send_signal(signal.SIGKILL)
    importer.wait(timeout=30)
    left = partial_with_scene()
    assert left and not out.exists()
    # Beside it: a copy of a live import (this process) and one of another host, which the rerun leaves alone.
    live = out.parent / f".my data.partial-{dataset_module._HOST}-{os.getpid()}-abcd"
    other_host = out.parent / f".my data.partial-another-host-{importer.pid}-abcd"
    legacy = out.parent / ".my data.partial-x1y2z3w4"  # an older don_gym's name: no host, no pid
    for folder in (live, other_host, legacy):
        folder.mkdir()
    code = main(["import-bop", str(root), "--split", "test", "--object", "1", "--out", str(out)])
    assert code == 0
    notes = capsys.readouterr().out
    assert "removed 1 half-written" in notes and "1 hidden copies" in notes and legacy.is_dir()
    assert not any(p.exists() for p in left), "the killed import's copy is still there"
    assert live.is_dir() and other_host.is_dir()
    assert len(DONDataset(out).scenes) == 1


# --- 8: a frame whose header declares another size ----------------------------------------------------------------


def _huge_png(width: int, height: int) -> bytes:
    """A real RGB PNG of ``width`` x ``height`` black pixels, compressed row by row (about 0.5 MB for 16000x12000)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    compressor, rows = zlib.compressobj(9), bytes((3 * width + 1) * 500)
    body = b"".join(compressor.compress(rows) for _ in range(height // 500)) + compressor.flush()
    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    return dataset_module.PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", body) + chunk(b"IEND", b"")


def test_training_refuses_a_frame_of_another_size_without_decoding_it(
    single_dataset: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    data = tmp_path / "ds"
    shutil.copytree(single_dataset, data)
    record = DONDataset(data).scenes[0]
    huge = _huge_png(16000, 12000)
    assert png_size(huge) == (16000, 12000) and len(huge) < 2_000_000
    for frame in range(record.num_frames):
        frame_path(record.path, "rgb", frame).write_bytes(huge)
    before = snapshot(data)
    decoded: list[int] = []
    real_decode = dataset_module.decode_png
    monkeypatch.setattr(dataset_module, "decode_png", lambda b, *a: decoded.append(len(b)) or real_decode(b, *a))
    run = tmp_path / "run"
    code = main(["train", "--method", "supervised", "--data", str(data), "--out", str(run), "--steps", "2",
                 "--batch-size", "1", "--crop", "none", "--threads", "1"])  # fmt: skip
    _one_line_error(code, capsys.readouterr().err, "/rgb/00000", "16000x12000", "expected 64x48")
    assert len(huge) not in decoded, "the frame was decoded"
    assert snapshot(data) == before and not (run / "train_state.pt").exists()
    # Every reader of a dataset's frames checks the header: also the other kinds, and export.
    depth = frame_path(record.path, "depth", 0)
    depth.write_bytes(_huge_png(640, 480))
    with pytest.raises(DatasetError, match="640x480"):
        DONDataset(data).image(0, 0, "depth")
    code = main(["export", str(data), "--out", str(tmp_path / "pdc")])
    _one_line_error(code, capsys.readouterr().err, "16000x12000")
    assert not list((tmp_path / "pdc").rglob("*.png"))


def test_bop_import_checks_every_image_header_before_decoding(tmp_path: Path, capsys) -> None:
    root = tmp_path / "bop"
    bop_scenes.write_bop_dataset(root, images=3)
    scene = root / "test" / "000001"
    out = tmp_path / "imported"
    argv = ["import-bop", str(root), "--split", "test", "--object", "1", "--out", str(out)]
    expected = f"{bop_scenes.WIDTH}x{bop_scenes.HEIGHT}"
    for path, declared, says in (
        (scene / "rgb" / "000001.png", (16000, 12000), f"expected {expected}"),  # not the first image's size
        (scene / "depth" / "000000.png", (640, 480), f"expected {expected}"),  # not its colour image's
        (bop.mask_path(scene, "mask_visib", 0, 0), (640, 480), f"expected {expected}"),
        (scene / "rgb" / "000000.png", (16000, 12000), "more than the"),  # the first: the size limit
    ):
        original = path.read_bytes()
        path.write_bytes(_huge_png(*declared))
        code = main(argv)
        _one_line_error(code, capsys.readouterr().err, path.name, f"{declared[0]}x{declared[1]}", says)
        assert not out.exists() and not list(tmp_path.glob(".imported.partial-*"))
        path.write_bytes(original)
    assert main(argv) == 0


def test_pdc_export_never_writes_into_a_scene_directory_that_is_there(single_dataset: Path, tmp_path: Path, capsys):
    out = tmp_path / "pdc"
    assert main(["export", str(single_dataset), "--out", str(out)]) == 0
    scene = next(out.iterdir())
    extra = scene / "processed" / "images" / "000099_rgb.png"  # another dataset's frame, more than ours
    extra.write_bytes(b"another dataset's")
    before = snapshot(out)
    code = main(["export", str(single_dataset), "--out", str(out)])
    _one_line_error(code, capsys.readouterr().err, scene.name, "exists")
    assert snapshot(out) == before and not list(out.glob(".*partial-*"))


def test_pose_reference_frames_of_a_pile_show_the_primary_part(bin_dataset: Path, tmp_path: Path) -> None:
    """Not the frame where the pile covers most pixels: one where the primary part (the toolcap) shows most."""
    from don_gym.data.dataset import write_frame
    from don_gym.evaluation import pose_evaluation

    pile = tmp_path / "pile"
    shutil.copytree(bin_dataset, pile)
    data = DONDataset(pile)
    record = data.scenes[0]
    shaft = next(int(i["instance_id"]) for i in record.instances if i["part"] == "shaft")
    toolcap = next(int(i["instance_id"]) for i in record.instances if i["part"] == "toolcap")
    assert np.count_nonzero(data.image(0, 1, "instance") == toolcap) > 0
    size = (record.intrinsics.height, record.intrinsics.width)
    # Frame 0: the shaft fills the whole image, so the pile's mask is largest there, yet no toolcap shows.
    write_frame(record.path, 0, {"mask": np.ones(size, bool), "instance": np.full(size, shaft)}, data.descriptor_dim)
    assert pose_evaluation._reference_frames(DONDataset(pile), count=1) == [1]


@pytest.mark.parametrize("scene", ["single", "bin"])
def test_overwrite_never_deletes_a_directory_that_is_no_dataset(scene: str, tmp_path: Path, capsys) -> None:
    folder = tmp_path / "my documents"
    (folder / "thesis").mkdir(parents=True)
    (folder / "thesis" / "chapter1.tex").write_text("months of work")
    (folder / "notes.txt").write_text("more")
    before = snapshot(folder)
    kind = ["--scene", "bin", "--parts", "toolcap:1"] if scene == "bin" else []
    code = main(["build-dataset", *kind, "--scenes", "1", "--frames", "2", "--size", "32x24", "--overwrite",
                 "--out", str(folder)])  # fmt: skip
    _one_line_error(code, capsys.readouterr().err, str(folder), "not a don_gym dataset", "--overwrite")
    assert snapshot(folder) == before and sorted(p.name for p in folder.iterdir()) == ["notes.txt", "thesis"]


def test_parsing_the_command_line_imports_no_pipeline_stage() -> None:
    """`don-gym --help` and argument errors answer at once: building the parser imports neither the dataset
    builder, OpenCV, torch nor PyBullet, and build-dataset's renderer choices are DatasetConfig's."""
    code = (
        "import sys; from don_gym.cli import build_parser; build_parser(); "
        "print([m for m in ('don_gym.data.build', 'cv2', 'torch', 'pybullet') if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
    from don_gym.cli.build_dataset import RENDERER_CHOICES
    from don_gym.data.build import DATASET_RENDERERS

    assert RENDERER_CHOICES == DATASET_RENDERERS
