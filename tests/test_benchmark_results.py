"""Every RESULTS.md section names the commit it was measured on, and whether the code differed from it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from don_gym.learning.checkpoints import read_checkpoint_metadata
from don_gym.zoo import SHIPPED_DIR

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import _results  # noqa: E402


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_section_records_the_commit_and_uncommitted_changes(tmp_path: Path, monkeypatch) -> None:
    def git(*args: str) -> str:
        command = ["git", "-c", "user.email=t@example.com", "-c", "user.name=t", *args]
        return subprocess.run(command, cwd=tmp_path, check=True, capture_output=True, text=True).stdout

    git("init", "-q")
    (tmp_path / "benchmarks" / "figures").mkdir(parents=True)
    for name in ("code.py", "benchmarks/RESULTS.md", "benchmarks/figures/a.png"):
        (tmp_path / name).write_text("1")
    git("add", "-A")
    git("commit", "-qm", "first")
    commit = git("rev-parse", "--short", "HEAD").strip()
    monkeypatch.setattr(_results, "REPO_ROOT", tmp_path)

    # The benchmarks' own outputs and untracked files do not make the code uncommitted ...
    (tmp_path / "benchmarks/figures/a.png").write_text("2")
    (tmp_path / "new.py").write_text("untracked")
    section = _results.record_section("x", "X", "body", path=tmp_path / "benchmarks" / "RESULTS.md")
    assert f"- Commit: {commit}\n" in section
    # ... an edited or renamed tracked file does.
    git("mv", "code.py", "moved.py")
    assert _results.commit_description() == f"{commit} + uncommitted changes"
    # A run that froze the state at its start names that state, whatever it edits afterwards.
    git("mv", "moved.py", "code.py")
    monkeypatch.setattr(_results, "_frozen_commit", None)
    assert _results.freeze_commit_description() == commit
    (tmp_path / "code.py").write_text("edited by the run")
    assert _results.commit_description() == commit
    monkeypatch.setattr(_results, "_frozen_commit", None)

    monkeypatch.setenv("PATH", str(tmp_path / "no-bin"))  # no git at all
    assert _results.commit_description() == "unknown"


def test_replace_block_replaces_between_markers_idempotently(tmp_path: Path) -> None:
    doc = tmp_path / "README.md"
    doc.write_text("# T\n\nbefore\n<!-- begin b:x -->\nold 1\nold 2\n<!-- end b:x -->\nafter\n")
    _results.replace_block(doc, "b:x", "| a | 1 |\n")
    once = doc.read_text()
    assert once == "# T\n\nbefore\n<!-- begin b:x -->\n| a | 1 |\n<!-- end b:x -->\nafter\n"
    _results.replace_block(doc, "b:x", "| a | 1 |")
    assert doc.read_text() == once
    _results.replace_block(doc, "b:x", "| a | 2 |")
    assert doc.read_text() == once.replace("| a | 1 |", "| a | 2 |")


@pytest.mark.parametrize(
    "text",
    [
        "no markers\n",
        "<!-- begin b:x -->\nonly a begin\n",
        "<!-- end b:x -->\n<!-- begin b:x -->\n",  # in the wrong order
        "<!-- begin b:x -->\n<!-- end b:x -->\n<!-- begin b:x -->\n<!-- end b:x -->\n",  # twice
        "<!-- begin b:xy -->\n<!-- end b:xy -->\n",  # another block's
    ],
)
def test_replace_block_refuses_missing_or_repeated_markers(tmp_path: Path, text: str) -> None:
    doc = tmp_path / "doc.md"
    doc.write_text(text)
    with pytest.raises(_results.BlockMarkersError, match=r"doc\.md.*<!-- begin b:x -->"):
        _results.replace_block(doc, "b:x", "new")
    with pytest.raises(_results.BlockMarkersError):
        _results.require_blocks(doc, ["b:x"])
    assert doc.read_text() == text


def test_replace_block_is_atomic(tmp_path: Path, monkeypatch) -> None:
    doc = tmp_path / "doc.md"
    original = "<!-- begin b:x -->\nold\n<!-- end b:x -->\n"
    doc.write_text(original)
    write_text = Path.write_text

    def fail_halfway(self: Path, data: str, *args, **kwargs) -> int:
        write_text(self, data[: len(data) // 2], *args, **kwargs)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", fail_halfway)
    with pytest.raises(OSError, match="No space"):
        _results.replace_block(doc, "b:x", "new " * 100)
    monkeypatch.undo()
    # The document is the old one, whole, and no partial file is left beside it.
    assert doc.read_text() == original
    assert [p.name for p in tmp_path.iterdir()] == ["doc.md"]


def test_a_new_section_goes_after_the_named_one(tmp_path: Path) -> None:
    results = tmp_path / "RESULTS.md"
    results.write_text("# R\n\n<!-- begin a -->\nA\n<!-- end a -->\n\n<!-- begin c -->\nC\n<!-- end c -->\n")
    _results.record_section("b", "B", "body b", path=results, after="a")
    _results.record_section("b", "B", "body b2", path=results, after="a")  # replaced in place
    text = results.read_text()
    assert text.index("<!-- end a -->") < text.index("<!-- begin b -->") < text.index("<!-- begin c -->")
    assert text.count("<!-- begin b -->") == 1 and "body b2" in text and "body b\n" not in text


def test_shipped_table_keeps_the_rows_of_networks_not_retrained(tmp_path: Path) -> None:
    """train_shipped.py's rows of an earlier run, in an older layout (no arch, scenes, commit or lr decay cell;
    every such network decayed its lr every 250 steps) or the current one, are read back with their own arch,
    scenes, schedule and commit."""
    import train_shipped

    results = tmp_path / "RESULTS.md"
    old = (
        "| object | method | steps | minutes | images/s | final loss | MB |\n|---|---|---|---|---|---|---|\n"
        "| shaft | not-shipped | 6000 | 80.8 | 9.9 | 0.067 | 2.5 |\n"
    )
    _results.record_section("shipped-shaft", "S", old, path=results)
    rows = train_shipped.recorded_rows("shipped-shaft", path=results)
    commit = _results.commit_description()
    assert rows == {
        "not-shipped": {
            "object": "shaft", "method": "not-shipped", "steps": "6000", "minutes": "80.8", "images/s": "9.9",
            "final loss": "0.067", "MB": "2.5", "scenes": "n/a", "arch": "n/a", "commit": commit, "data": "n/a",
            "bg crops": "n/a", "lr decay every": "250",
        }
    }  # fmt: skip
    current = "| " + " | ".join(train_shipped.TABLE_COLUMNS) + " |\n|" + "---|" * len(train_shipped.TABLE_COLUMNS)
    data = "6 frames/scene, wide"
    cells = f"shaft | supervised-edge | resnet-lite | 32 | {data} | 0.5 | 18000 | 750 | 40.0 | 20.0 | 0.05 | 2.6 | abc"
    current += f"\n| {cells} |"
    _results.record_section("shipped-shaft", "S", current, path=results)
    row = train_shipped.recorded_rows("shipped-shaft", path=results)["supervised-edge"]
    assert (row["arch"], row["scenes"], row["commit"], row["minutes"]) == ("resnet-lite", "32", "abc", "40.0")
    assert (row["data"], row["bg crops"], row["steps"], row["lr decay every"]) == (data, "0.5", "18000", "750")
    # A row of the older layout for a shipped network takes its arch from the network's metadata.
    _results.record_section("shipped-shaft", "S", old.replace("not-shipped", "supervised-mask"), path=results)
    mask = train_shipped.recorded_rows("shipped-shaft", path=results)["supervised-mask"]
    assert mask["arch"] == "resnet-lite-fine"
    # ... and its data from the metadata's frames per scene: networks of that layout saw the classic scenes.
    metadata = read_checkpoint_metadata(SHIPPED_DIR / "shaft" / "supervised-mask.safetensors")
    frames = metadata.extra["dataset_frames_per_scene"]
    assert mask["data"] == f"{frames} frames/scene, classic backdrops, fixed light"
    assert train_shipped.recorded_rows("shipped-toolcap", path=results) == {}


def test_shipped_runs_trained_on_other_scenes_are_refused(tmp_path: Path) -> None:
    """train_shipped.py does not resume (and ship) a run made on another number of scenes than asked."""
    import train_shipped

    from don_gym.errors import DonGymError
    from don_gym.zoo import SHIPPED_DIR

    network = SHIPPED_DIR / "shaft" / "supervised-edge.safetensors"
    trained_on = train_shipped.read_checkpoint_metadata(network).extra["dataset_scenes"]
    run = tmp_path / "run_shaft_supervised-edge"
    (run / "checkpoints").mkdir(parents=True)
    shutil.copyfile(network, run / "checkpoints" / "step_000100.safetensors")
    train_shipped.check_runs_match(tmp_path, "shaft", ["supervised-edge", "supervised-mask"], trained_on)
    with pytest.raises(DonGymError, match=rf"run_shaft_supervised-edge: a run on {trained_on} scenes, not the 7"):
        train_shipped.check_runs_match(tmp_path, "shaft", ["supervised-edge"], 7)


def test_stage_two_trains_with_the_seed_asked_for_and_its_row_says_so(tmp_path: Path, monkeypatch) -> None:
    """train_shipped.py --fine-tune-seed and --fine-tune-ema reach stage 2's training run and the row's data
    column; seed 0 and no average (the defaults) leave the row as it was."""
    import train_shipped

    from don_gym.learning.train import TrainResult

    base = tmp_path / "base" / "shaft"
    base.mkdir(parents=True)
    shutil.copyfile(SHIPPED_DIR / "shaft" / "supervised-edge.safetensors", base / "supervised-edge.safetensors")
    seen = []

    def fake_train(config, resume):
        seen.append(config)
        return TrainResult(base / "supervised-edge.safetensors", 0.1, config.steps, 60.0, 10.0)

    monkeypatch.setattr(train_shipped, "train", fake_train)
    rows = {}
    for seed, ema in ((3, 0.998), (0, 0.0)):
        args = SimpleNamespace(
            base=str(tmp_path / "base"), fine_tune_steps=10, fine_tune_scenes=2, fine_tune_seed=seed, fine_tune_ema=ema,
            renderer="mixed", batch_size=8, background_crops=0.5, threads=1, workers=0, checkpoint_every=None,
            frames=6, backgrounds="mixed", distractors=4, lighting="random", steps=100, lr_decay_every=750,
        )  # fmt: skip
        rows[seed], _, _ = train_shipped.fine_tune(
            args, tmp_path / f"work{seed}", "shaft", "supervised-edge", "resnet-lite", {"shaft": (128, 128)},
            {"shaft": 256},
        )  # fmt: skip
    assert [(config.seed, config.ema_decay) for config in seen] == [(3, 0.998), (0, 0.0)]
    assert seen[0].init_path == str(base / "supervised-edge.safetensors")
    named = ", training seed 3, weights averaged (EMA 0.998)"
    assert rows[3]["data"].endswith(named)
    assert rows[0]["data"] == rows[3]["data"].removesuffix(named)


@pytest.mark.parametrize(
    ("option", "value", "expected"),
    [
        *[("--fine-tune-seed", seed, "expected a whole number >= 0") for seed in ("-1", "1.5", "x")],
        *[("--fine-tune-ema", decay, "expected a number in [0, 1)") for decay in ("1", "-0.5", "nan")],
    ],
)
def test_a_bad_stage_two_option_is_refused_before_any_work(
    option: str, value: str, expected: str, tmp_path: Path, monkeypatch, capsys
) -> None:
    """Stage 2's seed and moving average are refused while parsing, before the stage-2 dataset build."""
    import train_shipped

    monkeypatch.setattr(sys, "argv", ["train_shipped.py", "--work", str(tmp_path / "w"), option, value])
    with pytest.raises(SystemExit) as exit_info:
        train_shipped.main()
    assert exit_info.value.code == 2
    assert f"argument {option}: {value!r}: {expected}" in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_a_run_of_some_objects_keeps_the_others_marked_with_their_run(tmp_path: Path) -> None:
    """bench_pose.py --objects toolcap (after retraining the toolcap's networks) keeps the shaft's figures, each
    kept part naming the run that measured it, once, however many runs keep it."""
    results = tmp_path / "RESULTS.md"
    first = (
        "Split: test.\n\n### toolcap, depth\n\n| a |\n\ntoolcap: 8 runs\n\n### shaft, depth\n\n| b |\n\nshaft: 8 runs"
    )
    _results.record_section("pose", "Pose", first, path=results)
    date = _results.read_section("pose", results).split("- Date: ")[1].split("\n")[0]
    kept = _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["toolcap"], path=results)
    assert list(kept) == ["shaft"]
    assert kept["shaft"].startswith("### shaft, depth\n\n| b |\n\nshaft: 8 runs\n\n*shaft: kept from the run of")
    assert date in kept["shaft"] and "measured toolcap only" in kept["shaft"] and "| a |" not in kept["shaft"]
    # Kept again by a later run of the toolcap: still the first run's line, not a second one.
    _results.record_section(
        "pose", "Pose", "Split: test.\n\n### toolcap, depth\n\n| c |\n\n" + kept["shaft"], path=results
    )
    again = _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["toolcap"], path=results)
    assert again["shaft"] == kept["shaft"]
    # The toolcap's part ends where the shaft's begins; a measured object or an absent section keeps nothing.
    toolcap = _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["shaft"], path=results)["toolcap"]
    assert "| c |" in toolcap and "shaft" not in toolcap.split("*toolcap: kept")[0]
    assert _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["toolcap", "shaft"], path=results) == {}
    assert _results.kept_object_subsections("absent", ("toolcap",), [], path=results) == {}


def test_a_kept_part_names_the_seeds_it_was_measured_on(tmp_path: Path) -> None:
    """Once the test seeds are renewed, a run of one object writes the new seeds into the section's split line:
    the other object's kept figures say which seeds they came from."""
    results = tmp_path / "RESULTS.md"
    body = "Split `test`: dataset seeds 4101, 4102, 4103 (test).\n\n### toolcap\n\n| a |\n\n### shaft\n\n| b |"
    _results.record_section("pose", "Pose", body, path=results)
    kept = _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["toolcap"], path=results)
    assert "on dataset seeds 4101, 4102, 4103; the run above measured toolcap only" in kept["shaft"]
    _results.record_section("pose", "Pose", "Split: test.\n\n### toolcap\n\n| a |", path=results)
    # A section whose split line names no seeds: the note names none either.
    unnamed = _results.kept_object_subsections("pose", ("toolcap", "shaft"), ["shaft"], path=results)["toolcap"]
    assert "kept from the run of" in unnamed and "dataset seeds" not in unnamed


def test_the_split_line_reads_back_its_seeds() -> None:
    """The three benchmarks that record a split write it with one formatter, and the kept-part note reads the
    seeds back from it: writer and reader agree for either split, with or without the training-seed remark."""
    test = _results.split_line("test", (6101, 6102, 6103), (1000, 4101))
    assert test.startswith("Split `test`: dataset seeds 6101, 6102, 6103 (the test seeds")
    assert test.endswith("spent: 1000, 4101; the shipped networks were trained on seed 0)")
    dev = _results.split_line("dev", (3101,), (1000,), trained_on_seed_0=False)
    assert "development seeds" in dev and dev.endswith("spent: 1000)")
    assert _results.split_seeds(f"# Tracking\n\n{test}, 8 scenes x 12 frames each.") == "6101, 6102, 6103"
    assert _results.split_seeds(dev + ", 4 piles") == "3101"
    assert _results.split_seeds("No split here; dataset seeds 1, 2 in passing.") is None


def test_other_process_load_counts_other_processes_not_this_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """The load meter that the timing benchmarks print beside their times: the machine's busy CPU time less this
    process's own, over the wall time of the block."""
    machine_busy_s = iter([100.0, 103.0])  # all processes' busy CPU seconds at the block's start and end
    own_times = iter([(10.0, 1.0, 0.0, 0.0, 0.0), (11.5, 1.5, 0.0, 0.0, 0.0)])  # this process: 2 s of its own
    wall_s = iter([50.0, 52.0])
    monkeypatch.setattr(_results, "_machine_busy_seconds", lambda: next(machine_busy_s))
    # Only the meter's module sees these clocks (pytest itself reads the real ones meanwhile).
    monkeypatch.setattr(_results, "os", SimpleNamespace(times=lambda: next(own_times)))
    monkeypatch.setattr(_results, "time", SimpleNamespace(perf_counter=lambda: next(wall_s)))
    with _results.OtherProcessLoad() as load:
        pass
    assert load.cores == pytest.approx(0.5) and load.describe() == "0.50"  # (3 s - 2 s) / 2 s
    # Where /proc/stat cannot be read, the load is unknown rather than zero.
    monkeypatch.setattr(_results, "_machine_busy_seconds", lambda: None)
    monkeypatch.setattr(_results, "os", os)
    monkeypatch.setattr(_results, "time", time)
    with _results.OtherProcessLoad() as unknown:
        pass
    assert unknown.cores is None and unknown.describe() == "unknown"


def test_the_machine_busy_time_includes_this_process() -> None:
    """On Linux the machine's busy time (/proc/stat) grows at least by what this process spends, whatever else
    runs beside it, so subtracting it leaves the others' share."""
    before = _results._machine_busy_seconds()
    if before is None:
        pytest.skip("no /proc/stat on this platform")
    own_before = sum(os.times()[:2])
    end = time.perf_counter() + 0.5
    while time.perf_counter() < end:
        pass
    own_s = sum(os.times()[:2]) - own_before
    assert _results._machine_busy_seconds() - before >= 0.8 * own_s > 0


def test_fine_tune_table_of_where_the_tail_comes_from(tmp_path: Path) -> None:
    """bench_fine_tune.py's edge table: one row per network (the oracle left out, candidates by their label), one
    column per band, each cell the band's tail and far shares and its share of the matches (here the oracle's
    descriptors under a candidate's name: no tail)."""
    import bench_fine_tune

    from don_gym.data.build import DatasetConfig, build_dataset
    from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking

    data = tmp_path / "data"
    build_dataset(DatasetConfig(scenes=1, frames_per_scene=3, image_size=(128, 96), sensor="ideal", seed=1000,
                                fuse_depth=False), data, progress=False)  # fmt: skip

    result = evaluate_tracking(data, {"oracle": "oracle", "/x/cand.safetensors": "oracle"},
                               TrackingConfig(points_per_scene=8), progress=False)  # fmt: skip
    table = bench_fine_tune.edge_table(result, {"/x/cand.safetensors": "toolcap/supervised-edge (mixed fine-tune)"}, 45)
    lines = table.splitlines()
    assert "more than 45 mm (the p99 target) / more than 100 mm off" in lines[0]
    assert lines[2] == "| network | 0-3 px | 3-6 px | 6-10 px | > 10 px |"
    rows = [line for line in lines if line.startswith("| toolcap/")]
    assert len(rows) == 1 and "oracle" not in table.split("\n\n", 1)[1]
    cells = rows[0].strip("| ").split(" | ")[1:]
    shares = [float(c.split("(")[1].rstrip("%)")) for c in cells if c != "-"]
    assert abs(sum(shares) - 100) <= 2  # the bands split every match with depth (rounded to whole percent)
    assert all(c == "-" or c.startswith("0.0% / 0.0%") for c in cells)  # the oracle's matches are exact
