"""Datasets under bad input and faults: nothing lost, nothing mixed, no traceback.

Faults are injected: a full disk (a failing writer, and a real kernel EFBIG from RLIMIT_FSIZE),
concurrent writers (processes), kill -9 mid-build. Tiny sizes keep each test to seconds.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from file_snapshots import snapshot

from don_gym.cli import main
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.data.dataset import DatasetLock, DONDataset
from don_gym.data.export import export_scene_pdc
from don_gym.descriptors import DescriptorField
from don_gym.errors import DatasetError

TINY = DatasetConfig(scenes=2, frames_per_scene=2, image_size=(64, 48), fuse_depth=False, seed=5)
TINY_ARGS = ["--scenes", "2", "--frames", "2", "--size", "64x48", "--no-fusion", "--seed", "5"]


def _leftovers(root: Path) -> list[str]:
    return [str(p.relative_to(root)) for p in root.rglob("*") if ".partial-" in p.name or ".stale-" in p.name]


def _cli_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "don_gym.cli", "build-dataset", *args]


def _assert_one_line_error(returncode: int, stderr: str, *expected: str) -> str:
    assert returncode == 2 and "Traceback" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if line.startswith("don-gym ")]
    assert len(errors) == 1, stderr
    for text in expected:
        assert text in errors[0], errors[0]
    return errors[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """One unsharded build of TINY, built once; tests copy it before changing anything."""
    out = tmp_path_factory.mktemp("reference") / "ds"
    report = build_dataset(TINY, out, progress=False)
    assert (report.scenes_written, report.scenes_complete, report.scenes_total) == (2, 2, 2)
    return out


@pytest.fixture
def dataset(reference: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "ds"
    shutil.copytree(reference, copy)
    return copy


@pytest.fixture(scope="module")
def two_piece_mesh(tmp_path_factory) -> Path:
    a, b = trimesh.creation.box((0.03, 0.03, 0.03)), trimesh.creation.box((0.02, 0.02, 0.02))
    b.apply_translation((0.05, 0.0, 0.0))
    path = tmp_path_factory.mktemp("mesh") / "two_pieces.stl"
    trimesh.util.concatenate([a, b]).export(path)
    return path


def test_overwrite_with_a_bad_option_keeps_the_dataset(dataset: Path, two_piece_mesh: Path, capsys) -> None:
    """Every option is checked before --overwrite deletes anything; each refusal is one line."""
    before = snapshot(dataset)
    bad_options = [
        (["--sensor", "nope"], "nope"),
        (["--dim", "0"], "--dim"),
        (["--frames", "1"], "--frames"),
        (["--size", "8x8"], "--size"),
        (["--seed", "-1"], "--seed"),
        (["--workers", "0"], "--workers"),
        (["--shard", "2/2"], "--shard"),
        (["--object", "no_such_part.stl"], "no_such_part.stl"),
        (["--object", str(two_piece_mesh)], "2 connected components"),  # embed's own message
        (["--object-scale", "-1"], "scale"),
    ]
    for option, expected in bad_options:
        code = main(["build-dataset", *TINY_ARGS, *option, "--overwrite", "--out", str(dataset)])
        _assert_one_line_error(code, capsys.readouterr().err, expected)
        assert snapshot(dataset) == before, option


def test_a_refused_build_leaves_nothing_behind(tmp_path: Path, two_piece_mesh: Path, capsys) -> None:
    """A failed first build writes nothing, so the corrected command is not blocked by it."""
    out = tmp_path / "ds"
    for option in (["--sensor", "nope"], ["--dim", "0"], ["--workers", "-1"], ["--object", str(two_piece_mesh)]):
        code = main(["build-dataset", *TINY_ARGS, *option, "--out", str(out)])
        _assert_one_line_error(code, capsys.readouterr().err)
        assert not out.exists(), option
    assert main(["build-dataset", *TINY_ARGS, "--scenes", "1", "--out", str(out)]) == 0
    assert "1 of 1 scenes complete" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("version", "message"), [(99, "written by a newer don_gym"), ("abc", "not an integer"), (0, "unknown format")]
)
def test_newer_or_corrupt_format_version_is_refused(dataset: Path, version, message: str, capsys) -> None:
    info_path = dataset / "dataset.json"
    info_path.write_text(json.dumps({**json.loads(info_path.read_text()), "version": version}))
    before = snapshot(dataset)
    with pytest.raises(DatasetError, match=message):
        build_dataset(TINY, dataset, progress=False)
    with pytest.raises(DatasetError, match=message):
        DONDataset(dataset)
    _assert_one_line_error(main(["build-dataset", *TINY_ARGS, "--out", str(dataset)]), capsys.readouterr().err, message)
    assert snapshot(dataset) == before  # not rewritten as version 1


def test_resume_refuses_every_option_that_shapes_the_data(dataset: Path) -> None:
    before = snapshot(dataset)
    changes = [
        ("fuse_depth", True, "--no-fusion"),
        ("sensor", "ideal", "--sensor"),
        ("seed", 6, "--seed"),
        ("image_size", (80, 60), "--size"),
        ("frames_per_scene", 3, "--frames"),
        ("descriptor_dim", 4, "--dim"),
        ("symmetric", False, "--no-symmetry"),
        ("object", "shaft", "--object"),
        ("voxel_size_m", 0.003, "voxel_size_m"),
    ]
    for name, value, option in changes:
        config = DatasetConfig(**{**TINY.__dict__, name: value})
        with pytest.raises(DatasetError, match="holds a different dataset") as caught:
            build_dataset(config, dataset, progress=False)
        message = str(caught.value)
        assert option in message and "--overwrite" in message and "another directory" in message, message
        if name != "object":  # shown as the mesh hash, with both object names
            recorded = json.loads((dataset / "dataset.json").read_text())[name]
            asked = list(value) if isinstance(value, tuple) else value
            assert f"{recorded!r} on disk, {asked!r} asked" in message, message
    assert snapshot(dataset) == before


def test_fewer_scenes_are_refused_and_more_are_added(dataset: Path) -> None:
    """The recorded scene count never shrinks below what exists: a smaller --scenes is refused."""
    with pytest.raises(DatasetError, match="records 2 scenes"):
        build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 1}), dataset, progress=False)
    assert json.loads((dataset / "dataset.json").read_text())["scenes"] == 2
    report = build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 3}), dataset, shard=(2, 3), progress=False)
    assert (report.scenes_written, report.scenes_complete, report.scenes_total) == (1, 3, 3)
    assert json.loads((dataset / "dataset.json").read_text())["scenes"] == 3


def test_full_disk_leaves_no_incomplete_file_and_keeps_the_dataset(
    dataset: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    shutil.rmtree(dataset / "scenes" / "scene_000001")
    before = snapshot(dataset)
    real_replace = os.replace
    writes = []

    def full_disk_after_three_files(src, dst):
        writes.append(dst)
        if len(writes) > 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", full_disk_after_three_files)
    with pytest.raises(OSError, match="No space left"):
        build_dataset(TINY, dataset, progress=False)
    writes.clear()
    _assert_one_line_error(
        main(["build-dataset", *TINY_ARGS, "--out", str(dataset)]), capsys.readouterr().err, "No space left", "resume"
    )
    # An encoder that fails (cv2.imwrite/imencode return False instead of raising) is caught too.
    monkeypatch.setattr(os, "replace", real_replace)
    monkeypatch.setattr("cv2.imencode", lambda *args, **kwargs: (False, None))
    with pytest.raises(OSError, match="could not encode PNG"):
        build_dataset(TINY, dataset, progress=False)
    assert snapshot(dataset) == before and not _leftovers(dataset)
    assert not (dataset / "scenes" / "scene_000001").exists()
    monkeypatch.undo()
    assert build_dataset(TINY, dataset, progress=False).scenes_written == 1
    assert len(DONDataset(dataset).scenes) == 2


def test_real_file_size_limit_is_a_one_line_error(tmp_path: Path) -> None:
    """The kernel refuses a frame's write (EFBIG, as ENOSPC would): one line naming the file, and
    nothing incomplete on disk. The limit lets the textures and dataset-level files through (< 60 kB)
    and stops the first 320x240 RGB frame (~100 kB)."""
    out = tmp_path / "ds"

    def limit_file_size() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    result = subprocess.run(
        _cli_command("--scenes", "1", "--frames", "2", "--size", "320x240", "--no-fusion", "--out", str(out)),
        capture_output=True, text=True, timeout=300, preexec_fn=limit_file_size,
    )  # fmt: skip
    _assert_one_line_error(result.returncode, result.stderr, "File too large", "rgb/000000.png", "resume")
    assert sorted(p.name for p in out.iterdir()) == [".lock", "dataset.json", "descriptor_field.npz", "scenes"]
    assert not list((out / "scenes").iterdir())
    # The files written before the fault are whole: the field's hash is the one dataset.json records.
    info = json.loads((out / "dataset.json").read_text())
    assert DescriptorField.load(out / "descriptor_field.npz").field_hash == info["descriptor_field_hash"]


def test_two_writers_of_different_objects_one_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    writers = [
        subprocess.Popen(
            _cli_command(*TINY_ARGS, "--scenes", "1", "--object", name, "--out", str(out)),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for name in ("toolcap", "shaft")
    ]
    results = [(w.wait(timeout=300), w.stderr.read()) for w in writers]
    assert sorted(code for code, _ in results) == [0, 2], results
    _assert_one_line_error(*next(r for r in results if r[0] == 2), "holds a different dataset", "--object")
    data = DONDataset(out)
    assert data.descriptor_field().field_hash == data.info["descriptor_field_hash"]
    assert [scene.metadata["object"] for scene in data.scenes] == [data.info["object"]]
    assert not _leftovers(out)


def test_shards_in_parallel_equal_one_unsharded_build(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "sharded"
    shards = [
        subprocess.Popen(
            _cli_command(*TINY_ARGS, "--shard", shard, "--out", str(out)),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for shard in ("0/2", "1/2")
    ]
    for shard in shards:
        assert shard.wait(timeout=300) == 0, shard.stderr.read()
    sharded, unsharded = snapshot(out), snapshot(reference)
    assert sorted(sharded) == sorted(unsharded)
    for name in ("rgb", "depth", "depth_ideal", "descriptor", "target_mask", "mask"):
        assert any(f"/{name}/" in path for path in sharded), name
    different = [p for p in sharded if sharded[p] != unsharded[p] and p != "dataset.json"]
    assert not different
    assert json.loads((out / "dataset.json").read_text()) == json.loads((reference / "dataset.json").read_text())
    # The final unsharded run checks and completes: nothing left to do here.
    report = build_dataset(TINY, out, progress=False)
    assert (report.scenes_written, report.scenes_skipped, report.scenes_complete) == (0, 2, 2)
    # A shard with other options is refused, naming the option.
    with pytest.raises(DatasetError, match="--seed"):
        build_dataset(DatasetConfig(**{**TINY.__dict__, "seed": 9}), out, shard=(1, 2), progress=False)


def test_killed_build_resumes_to_a_complete_dataset(reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    writer = subprocess.Popen(
        _cli_command(*TINY_ARGS, "--out", str(out)), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 240
    while not list((out / "scenes").glob(".scene_*.partial-*")) and writer.poll() is None:
        assert time.monotonic() < deadline, "the build never started a scene"
        time.sleep(0.01)
    writer.send_signal(signal.SIGKILL)
    assert writer.wait(timeout=30) == -signal.SIGKILL, "the build ended before it could be killed mid-scene"
    assert _leftovers(out)  # the killed scene's temporary directory
    # Whatever is under a final scene name is complete; the rest is a hidden temporary directory.
    for scene in (out / "scenes").glob("scene_*"):
        assert (scene / "scene.json").is_file()
    report = build_dataset(TINY, out, progress=False)
    assert report.scenes_complete == 2 and not _leftovers(out)
    assert snapshot(out) == snapshot(reference)


def test_overwrite_is_refused_while_another_process_writes(dataset: Path) -> None:
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from don_gym.data.dataset import DatasetLock; "
         "DatasetLock(sys.argv[1]).hold_session(); print('held', flush=True); time.sleep(120)", str(dataset)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(dataset)
        with pytest.raises(DatasetError, match="another don-gym process is writing"):
            build_dataset(TINY, dataset, overwrite=True, progress=False)
        assert snapshot(dataset) == before
        # Writers of the same dataset share it: a resume goes ahead.
        assert build_dataset(TINY, dataset, progress=False).scenes_skipped == 2
    finally:
        holder.kill()
        holder.wait()
    lock = DatasetLock(dataset)
    lock.hold_session(exclusive=True)  # released by the holder's death
    lock.close()


def test_export_refuses_a_corrupt_image(dataset: Path, tmp_path: Path, capsys) -> None:
    data = DONDataset(dataset)
    rgb = dataset / "scenes" / "scene_000000" / "rgb" / "000001.png"
    rgb.write_bytes(rgb.read_bytes()[:100])  # truncated, as by a full disk
    before = snapshot(dataset)
    with pytest.raises(DatasetError, match="000001.png"):
        export_scene_pdc(data, 0, tmp_path / "pdc")
    assert not list((tmp_path / "pdc").rglob("*.png"))  # nothing of the scene was written
    assert snapshot(dataset) == before
    code = main(["export", str(dataset), "--scene", "0", "--out", str(tmp_path / "pdc")])
    _assert_one_line_error(code, capsys.readouterr().err, "rgb/000001.png", "not a readable PNG")
    # A readable image of the wrong kind (RGB where 16-bit depth belongs) is refused too.
    depth = dataset / "scenes" / "scene_000001" / "depth" / "000000.png"
    shutil.copyfile(dataset / "scenes" / "scene_000001" / "rgb" / "000000.png", depth)
    with pytest.raises(DatasetError, match="expected uint16"):
        export_scene_pdc(data, 1, tmp_path / "pdc")


def test_writers_check_every_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from don_gym.io import write_png

    image = np.zeros((4, 4, 3), np.uint8)
    write_png(tmp_path / "ok.png", image)
    assert (tmp_path / "ok.png").stat().st_size > 0
    monkeypatch.setattr("cv2.imencode", lambda *args, **kwargs: (False, None))
    with pytest.raises(OSError):
        write_png(tmp_path / "bad.png", image)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.png"]


def test_publishing_is_first_writer_wins_without_locks(tmp_path: Path) -> None:
    """What keeps writers on several machines correct without shared locks: an exclusive create for
    dataset-level files, one rename per scene (a second complete copy is dropped, a legacy
    incomplete scene directory is replaced)."""
    from don_gym.data.dataset import new_scene_tmp_dir, publish_scene, scene_dir
    from don_gym.io import write_text_atomic

    write_text_atomic(tmp_path / "dataset.json", "first", exclusive=True)
    with pytest.raises(FileExistsError):
        write_text_atomic(tmp_path / "dataset.json", "second", exclusive=True)
    assert (tmp_path / "dataset.json").read_text() == "first" and len(list(tmp_path.iterdir())) == 1

    final = scene_dir(tmp_path, 0)
    final.mkdir(parents=True)  # as an older don_gym left an interrupted scene: no scene.json
    copies = []
    for text in ("a", "b"):
        tmp = new_scene_tmp_dir(tmp_path, 0)
        (tmp / "scene.json").write_text(text)
        copies.append((tmp, publish_scene(tmp, final)))
    assert [published for _, published in copies] == [True, False]
    assert (final / "scene.json").read_text() == "a"
    assert sorted(p.name for p in final.parent.iterdir()) == ["scene_000000"]


def _field_as_from_another_machine(path: Path, delta: float) -> str:
    """Rewrite the field file at ``path`` with every vertex descriptor moved by ``delta`` (towards the middle
    of [0, 1], so that it stays a valid field) and another mesh hash, as another machine's arithmetic could
    give (by ~1e-7); returns the new file's content hash."""
    field = DescriptorField.load(path)
    values = field.vertex_descriptors.astype(np.float64)
    moved = (values + np.where(values < 0.5, delta, -delta)).astype(np.float32)
    field = dataclasses.replace(field, vertex_descriptors=moved, mesh_hash="f" * 16)
    field.save(path)
    return field.field_hash


def test_a_dataset_from_another_machine_resumes_and_another_field_is_refused(
    dataset: Path, reference: Path, tmp_path: Path, capsys
) -> None:
    """The part is compared by shape signature and the descriptor field by value (FIELD_MATCH_ATOL = 1e-3),
    never by hashes of float bits: shards built on machines whose arithmetic differs share one dataset."""
    info_path, field_path = dataset / "dataset.json", dataset / "descriptor_field.npz"
    info = json.loads(info_path.read_text())
    info["descriptor_field_hash"] = _field_as_from_another_machine(field_path, 1e-6)
    info["mesh_hash"] = "f" * 16
    info["object_signature"]["area_m2"] *= 1 + 1e-7
    info_path.write_text(json.dumps(info))
    more = DatasetConfig(**{**TINY.__dict__, "scenes": 3})
    report = build_dataset(more, dataset, progress=False)
    assert (report.scenes_written, report.scenes_complete) == (1, 3)
    resumed = json.loads(info_path.read_text())
    assert resumed == {**info, "scenes": 3}  # the recorded part and field stay the dataset's
    assert DONDataset(dataset).descriptor_field().field_hash == info["descriptor_field_hash"]

    info["descriptor_field_hash"] = _field_as_from_another_machine(field_path, 1e-2)
    info_path.write_text(json.dumps({**info, "scenes": 3}))
    before = snapshot(dataset)
    code = main(["build-dataset", *TINY_ARGS, "--scenes", "4", "--out", str(dataset)])
    _assert_one_line_error(code, capsys.readouterr().err, "descriptor field", "by 0.01", "tolerance 0.001")
    assert snapshot(dataset) == before

    # A field file published by another machine's build that has not written dataset.json yet is joined.
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    shutil.copyfile(reference / "descriptor_field.npz", fresh / "descriptor_field.npz")
    published = _field_as_from_another_machine(fresh / "descriptor_field.npz", 1e-6)
    assert build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 1}), fresh, progress=False).scenes_written == 1
    assert json.loads((fresh / "dataset.json").read_text())["descriptor_field_hash"] == published


def test_another_parts_field_without_dataset_json_is_refused_like_a_different_dataset(tmp_path: Path, capsys) -> None:
    """The window in which a racing build of another part has published its field but not yet its
    dataset.json: the refusal says what the other one says (the two writers' test sees either)."""
    from don_gym.descriptors import embed
    from don_gym.objects import load_object

    out = tmp_path / "ds"
    out.mkdir()
    embed(load_object("shaft"), dim=3, symmetric=True).save(out / "descriptor_field.npz")
    before = snapshot(out)
    code = main(["build-dataset", *TINY_ARGS, "--object", "toolcap", "--out", str(out)])
    _assert_one_line_error(code, capsys.readouterr().err, "holds a different dataset", "--object", "no dataset.json")
    assert snapshot(out) == before


def test_another_builds_temporary_files_are_not_foreign(tmp_path: Path) -> None:
    """A parallel shard's temporary names while it publishes the field (a temporary name of a temporary
    name included, as builds of older don_gym versions stacked one on the other) leave the directory ours."""
    out = tmp_path / "ds"
    out.mkdir()
    for name in ("..descriptor_field.npz.partial-a1.npz.partial-b2.npz", ".dataset.json.partial-c3"):
        (out / name).write_bytes(b"")
    assert build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 1}), out, progress=False).scenes_written == 1
    other = tmp_path / "other"
    other.mkdir()
    (other / "..descriptor_field.npz.partial-a1.npz.partial-b2.npz").write_bytes(b"")
    (other / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="notes.txt"):
        build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 1}), other, progress=False)


def test_a_replaced_field_file_is_refused(dataset: Path) -> None:
    """dataset.json names its field file's exact content: the scenes' targets were rendered from it."""
    from don_gym.descriptors import embed
    from don_gym.objects import load_object

    embed(load_object("toolcap"), dim=3, symmetric=True, tolerance=0.02).save(dataset / "descriptor_field.npz")
    with pytest.raises(DatasetError, match="the file was replaced or deleted"):
        build_dataset(TINY, dataset, progress=False)


def test_a_part_in_pieces_is_refused_with_advice_for_build_dataset(tmp_path: Path, two_piece_mesh: Path, capsys):
    code = main(["build-dataset", *TINY_ARGS, "--object", str(two_piece_mesh), "--out", str(tmp_path / "ds")])
    line = _assert_one_line_error(code, capsys.readouterr().err, "2 connected components", "one piece")
    assert "--components" not in line and "components=" not in line, line  # options build-dataset does not have


def test_ctrl_c_during_a_build_on_workers_prints_no_traceback(tmp_path: Path, ctrl_c_reaches_children) -> None:
    """The terminal sends SIGINT to the command and its worker processes alike: one line, status 130, no
    worker traceback, nothing half-written, and the same build then completes the dataset."""
    out = tmp_path / "ds"
    process = subprocess.Popen(
        _cli_command(*TINY_ARGS, "--scenes", "6", "--workers", "2", "--out", str(out)),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not list((out / "scenes").glob(".scene_*.partial-*")) and process.poll() is None:
            assert time.monotonic() < deadline, "the build never started a scene"
            time.sleep(0.01)
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and stderr.rstrip().endswith("don-gym build-dataset: interrupted"), stderr
    assert not _leftovers(out)
    before = snapshot(out)
    report = build_dataset(DatasetConfig(**{**TINY.__dict__, "scenes": 6}), out, progress=False)
    assert report.scenes_complete == 6 and report.scenes_written < 6 and not _leftovers(out)
    # Every file complete at Ctrl-C (the scenes finished before it, the dataset's own files) is kept as it was.
    after = snapshot(out)
    assert {path: after.get(path) for path in before} == before
