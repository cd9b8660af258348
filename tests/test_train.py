"""Training with both methods end to end on a tiny generated dataset."""

from __future__ import annotations

import csv
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from file_snapshots import snapshot

import don_gym.learning.train as train_module
from don_gym.cli import main as cli_main
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.errors import CheckpointError, DonGymError
from don_gym.learning.augment import AugmentConfig
from don_gym.learning.checkpoints import load_checkpoint, read_checkpoint_metadata
from don_gym.learning.methods import SUPERVISED_TARGET_VARIANT
from don_gym.learning.model import DenseObjectNet
from don_gym.learning.torch_data import CorrespondencePairs, StepBatches, SupervisedFrames, step_loader
from don_gym.learning.train import TRAIN_STATE, TrainConfig, train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("train") / "data"
    config = DatasetConfig(scenes=2, frames_per_scene=4, image_size=(96, 72), sensor="d435", seed=3)
    build_dataset(config, out, progress=False)
    return str(out)


def _losses(run: Path) -> np.ndarray:
    with (run / "losses.csv").open() as f:
        return np.array([float(row["loss"]) for row in csv.DictReader(f)])


def _columns(run: Path) -> dict[str, list[str]]:
    """losses.csv as written, column by column (the text compares runs exactly)."""
    with (run / "losses.csv").open() as f:
        rows = list(csv.DictReader(f))
    return {key: [row[key] for row in rows] for key in rows[0]}


def _config(method: str, data: str, out: Path, steps: int = 30) -> TrainConfig:
    return TrainConfig(
        method=method, data=data, out=str(out), steps=steps, batch_size=2, crop_size=(64, 48), checkpoint_every=15,
        lr=3e-3, augment={"background_probability": 0.5, "brightness": 0.1, "contrast": 0.1, "saturation": 0.1,
                          "hue": 0.0, "noise_std": 0.01},
    )  # fmt: skip


@pytest.mark.parametrize("method", ["supervised-edge", "supervised-mask", "self-supervised"])
def test_thirty_steps_lower_the_loss(method: str, tiny_dataset: str, tmp_path: Path) -> None:
    result = train(_config(method, tiny_dataset, tmp_path / method), progress=False)
    losses = _losses(tmp_path / method)
    assert len(losses) == 30 and np.all(np.isfinite(losses))
    assert losses[-10:].mean() < 0.8 * losses[:5].mean(), losses
    assert (tmp_path / method / "loss_curve.png").stat().st_size > 1000
    model, metadata = load_checkpoint(result.model_path, expect_object="toolcap", expect_method=method)
    assert metadata.training_steps == 30 and metadata.image_size == (96, 72)
    assert metadata.extra["crop_size"] == [64, 48]  # the recipe is in the checkpoint
    if method in SUPERVISED_TARGET_VARIANT:  # the background its targets had, the mask variant's own
        targets_background = SupervisedFrames(tiny_dataset, variant=SUPERVISED_TARGET_VARIANT[method]).background
        np.testing.assert_allclose(metadata.background_descriptor, targets_background, atol=1e-6)
    assert model.descriptor_image(np.zeros((72, 96, 3), np.uint8)).shape == (72, 96, 3)
    with pytest.raises(CheckpointError, match="object_name"):
        load_checkpoint(result.model_path, expect_object="shaft")


def test_same_seed_same_curve_and_exact_resume(tiny_dataset: str, tmp_path: Path) -> None:
    # The learning rate decays after steps 3 and 6: the resume at step 4 lies between two decays, so a
    # resume that lost the scheduler's state (or the optimiser's) would decay at another step.
    config = replace(_config("supervised", tiny_dataset, tmp_path / "a", steps=8), checkpoint_every=4, lr_decay_every=3)
    train(config, progress=False)
    train(replace(config, out=str(tmp_path / "b")), progress=False)
    straight = _columns(tmp_path / "a")
    assert straight == _columns(tmp_path / "b")
    assert straight["lr"] == ["0.003"] * 2 + ["0.0027"] * 3 + ["0.00243"] * 3, straight["lr"]
    # Interrupted after step 4 (its checkpoint), then resumed: the same curve, bit for bit.
    first = train(replace(config, out=str(tmp_path / "c"), steps=4), progress=False)
    with pytest.raises(DonGymError, match="different configuration.*lr"):
        train(replace(config, out=str(tmp_path / "c"), lr=1e-2), resume=True, progress=False)
    resumed = train(replace(config, out=str(tmp_path / "c")), resume=True, progress=False)
    assert _columns(tmp_path / "c") == straight
    # The reported time covers both sessions; resuming a finished run reports the same run.
    assert first.seconds is not None and resumed.seconds is not None and resumed.seconds > first.seconds
    again = train(replace(config, out=str(tmp_path / "c")), resume=True, progress=False)
    assert again.seconds == resumed.seconds and again.final_loss == resumed.final_loss
    with pytest.raises(DonGymError, match="already holds"):
        train(config, progress=False)


# --- data loading in worker processes ----------------------------------------------------------


def _batches(loader) -> list[dict]:
    return [batch for batch in loader]


def test_a_steps_batch_depends_only_on_seed_and_step(tiny_dataset: str) -> None:
    """Whatever the number of worker processes, the starting step or the number of training
    processes, step s gets the same images, crops and augmentation."""
    augment = AugmentConfig()
    frames = SupervisedFrames(tiny_dataset, variant="edge", crop_size=(40, 32), seed=1)
    whole = StepBatches(frames, steps=5, batch_size=4, seed=1, augment_config=augment)
    in_loop = _batches(step_loader(whole, 0, workers=0))
    in_workers = _batches(step_loader(whole, 2, workers=2))
    assert len(in_loop) == 5 and len(in_workers) == 3
    for a, b in zip(in_loop[2:], in_workers, strict=True):
        for key in ("rgb", "target", "object_mask"):
            assert torch.equal(a[key], b[key]), key
    assert in_loop[0]["rgb"].shape == (4, 3, 32, 40) and not torch.equal(in_loop[0]["rgb"], in_loop[1]["rgb"])
    shares = [StepBatches(frames, 5, 4, 1, augment, rank=r, world_size=2)[3] for r in (0, 1)]
    for key in ("rgb", "target", "object_mask"):
        assert torch.equal(torch.cat([s[key] for s in shares]), in_loop[3][key]), key
    pairs = CorrespondencePairs(tiny_dataset, depth_source="ideal", seed=1, crop_size=(40, 32))
    pair_batches = StepBatches(pairs, steps=2, batch_size=2, seed=1, augment_config=augment)
    first, again = _batches(step_loader(pair_batches, 1, workers=1))[0], pair_batches[1]
    assert torch.equal(first["rgb_b"], again["rgb_b"]) and len(first["correspondences"]) == 2
    np.testing.assert_array_equal(first["correspondences"][1].matches_a, again["correspondences"][1].matches_a)
    with pytest.raises(DonGymError, match="multiple"):
        StepBatches(frames, 5, 3, 1, augment, rank=0, world_size=2)


def test_workers_train_the_same_curve(tiny_dataset: str, tmp_path: Path) -> None:
    config = replace(_config("supervised-mask", tiny_dataset, tmp_path / "w0", steps=3), checkpoint_every=3)
    train(config, progress=False)
    train(replace(config, out=str(tmp_path / "w2"), workers=2), progress=False)
    np.testing.assert_array_equal(_losses(tmp_path / "w0"), _losses(tmp_path / "w2"))


def test_data_wait_fraction_is_the_share_of_step_time_spent_waiting_for_batches(
    tiny_dataset: str, tmp_path: Path, monkeypatch
) -> None:
    """A loader slowed by 0.5 s a batch: the two steps after the first wait at least 1 s, so the fraction is at
    least 1 s over the whole session's time, and above the same run's without the delay."""
    config = replace(_config("supervised-edge", tiny_dataset, tmp_path / "fast", steps=3), checkpoint_every=3)
    fast = train(config, progress=False)
    batch = StepBatches.__getitem__

    def slow_batch(self, step):
        time.sleep(0.5)
        return batch(self, step)

    monkeypatch.setattr(StepBatches, "__getitem__", slow_batch)
    slow = train(replace(config, out=str(tmp_path / "slow")), progress=False)
    assert fast.data_wait_fraction is not None and slow.data_wait_fraction is not None and slow.seconds is not None
    assert 1.0 / slow.seconds <= slow.data_wait_fraction < 1.0, (slow.data_wait_fraction, slow.seconds)
    assert slow.data_wait_fraction > fast.data_wait_fraction


# --- configuration and run-directory errors ----------------------------------------------------


@pytest.mark.parametrize(
    "change, message",
    [
        ({"batch_size": 0}, "batch_size"),
        ({"checkpoint_every": 0}, "checkpoint_every"),
        ({"threads": 0}, "threads"),
        ({"workers": -1}, "workers"),
        ({"lr": float("nan")}, "lr"),
        ({"lr": 1e30}, "lr"),
        ({"steps": 0}, "steps"),
        ({"seed": -1}, "seed"),
        ({"weight_decay": float("inf")}, "weight_decay"),
        ({"crop_size": (0, 8)}, "crop_size"),
        ({"augment": {"blur": 1.0}}, "augment"),
        ({"augment": {"hue": 0.9}}, "hue"),
        ({"device": "tpu"}, "tpu"),
        ({"precision": "int8"}, "precision"),
        ({"backend": "mpi"}, "backend"),
        ({"arch": "resnet50"}, "resnet50"),
        ({"method": "magic"}, "magic"),
        ({"depth_source": "lidar"}, "lidar"),
        ({"pretrained_path": "x.pth"}, "no ImageNet layout"),
        ({"data": "/no/such/dataset"}, "does not exist"),
        ({"hard_object_fraction": 0.9}, "hard_object_fraction"),
        ({"hard_background_fraction": -0.1}, "hard_background_fraction"),
        ({"method": "self-supervised", "hard_object_fraction": 0.1}, "no per-pixel targets"),
        ({"ema_decay": 1.0}, "ema_decay"),
        ({"ema_decay": float("nan")}, "ema_decay"),
    ],
)
def test_bad_settings_are_refused_before_anything_is_written(
    change: dict, message: str, tiny_dataset: str, tmp_path: Path
) -> None:
    config = replace(_config("supervised", tiny_dataset, tmp_path / "run"), **change)
    with pytest.raises(DonGymError, match=message):
        train(config, progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
def test_cuda_without_a_gpu_is_one_line(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    args = ["train", "--method", "supervised", "--data", tiny_dataset, "--out", str(tmp_path / "run")]
    for extra in (["--device", "cuda"], ["--precision", "fp16"], ["--workers", "-1"], ["--lr", "nan"]):
        assert cli_main([*args, *extra]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "run").exists()


def test_lr_decay_every_from_the_cli(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    """--lr-decay-every reaches the schedule: the lr column (the rate after the step) drops by x0.9 every 2 steps,
    and 0 is refused in one line."""
    argv = ["train", "--method", "supervised", "--data", tiny_dataset, "--batch-size", "1", "--crop", "32x32",
            "--lr", "1e-3", "--threads", "1", "--workers", "0", "--device", "cpu"]  # fmt: skip
    assert cli_main([*argv, "--out", str(tmp_path / "run"), "--steps", "5", "--lr-decay-every", "2"]) == 0
    lrs = [float(x) for x in _columns(tmp_path / "run")["lr"]]
    assert np.allclose(lrs, [1e-3, 9e-4, 9e-4, 8.1e-4, 8.1e-4], rtol=1e-3), lrs
    capsys.readouterr()
    assert cli_main([*argv, "--out", str(tmp_path / "bad"), "--steps", "1", "--lr-decay-every", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "lr_decay_every" in err and not (tmp_path / "bad").exists(), err


def test_hard_pixel_fractions_from_the_cli(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    """--hard-object / --hard-background reach the run (its config.json and the checkpoint's metadata) and change
    what a step computes; a fraction out of range is one line with nothing written."""
    argv = ["train", "--method", "supervised", "--data", tiny_dataset, "--batch-size", "1", "--crop", "32x32",
            "--threads", "1", "--workers", "0", "--device", "cpu", "--steps", "2"]  # fmt: skip
    assert cli_main([*argv, "--out", str(tmp_path / "plain")]) == 0
    hard = [*argv, "--out", str(tmp_path / "hard"), "--hard-object", "0.1", "--hard-background", "0.01"]
    assert cli_main(hard) == 0
    saved = json.loads((tmp_path / "hard" / "config.json").read_text())
    assert (saved["hard_object_fraction"], saved["hard_background_fraction"]) == (0.1, 0.01)
    extra = read_checkpoint_metadata(tmp_path / "hard" / "model.safetensors").extra
    assert (extra["hard_object_fraction"], extra["hard_background_fraction"]) == (0.1, 0.01)
    # Same seed and batches: the first step's loss differs only by the added terms, which are positive.
    assert float(_columns(tmp_path / "hard")["loss"][0]) > float(_columns(tmp_path / "plain")["loss"][0])
    capsys.readouterr()
    assert cli_main([*argv, "--out", str(tmp_path / "bad"), "--hard-object", "0.7"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "hard_object_fraction" in err and not (tmp_path / "bad").exists(), err


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)[0].state_dict()


def test_ema_saves_the_weights_moving_average_and_resumes_it(tiny_dataset: str, tmp_path: Path) -> None:
    """With ema_decay the checkpoint holds the average, not the last weights: after one step (decay 1/10 then)
    0.1 x the first weights + 0.9 x the trained ones, exactly as a run without the average trains them; an
    interrupted run resumes its average; a resume that changes the decay is refused."""
    plain = replace(_config("supervised", tiny_dataset, tmp_path / "plain", steps=1), checkpoint_every=1)
    averaged = replace(plain, out=str(tmp_path / "ema"), ema_decay=0.99)
    train(plain, progress=False)
    train(averaged, progress=False)
    assert _columns(tmp_path / "plain") == _columns(tmp_path / "ema")  # the average does not change training
    torch.manual_seed(plain.seed)
    first = DenseObjectNet(plain.arch, 3).state_dict()
    trained, average = (
        _weights(tmp_path / "plain" / "model.safetensors"),
        _weights(tmp_path / "ema" / "model.safetensors"),
    )
    moved = 0
    for name, value in trained.items():
        if value.is_floating_point():
            torch.testing.assert_close(average[name], 0.1 * first[name] + 0.9 * value, rtol=1e-5, atol=1e-6)
            moved += not torch.equal(first[name], value)
    assert moved > 10  # the step changed the weights, so the test tells the average from either end
    state = torch.load(tmp_path / "ema" / TRAIN_STATE, weights_only=True)
    assert torch.equal(state["model"]["head.weight"], trained["head.weight"])
    assert torch.equal(state["ema"]["head.weight"], average["head.weight"])
    assert read_checkpoint_metadata(tmp_path / "ema" / "model.safetensors").extra["ema_decay"] == 0.99

    # Five steps straight, or two then resumed: the same average, bit for bit.
    five = replace(averaged, out=str(tmp_path / "five"), steps=5)
    train(five, progress=False)
    train(replace(five, out=str(tmp_path / "resumed"), steps=2), progress=False)
    train(replace(five, out=str(tmp_path / "resumed")), resume=True, progress=False)
    straight, resumed = (
        _weights(tmp_path / "five" / "model.safetensors"),
        _weights(tmp_path / "resumed" / "model.safetensors"),
    )
    assert all(torch.equal(straight[name], resumed[name]) for name in straight)
    with pytest.raises(DonGymError, match="different configuration.*ema_decay"):
        train(replace(five, out=str(tmp_path / "resumed"), ema_decay=0.9, steps=6), resume=True, progress=False)


def test_ema_decay_from_the_cli(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    argv = ["train", "--method", "supervised", "--data", tiny_dataset, "--batch-size", "1", "--crop", "32x32",
            "--threads", "1", "--workers", "0", "--device", "cpu", "--steps", "1"]  # fmt: skip
    assert cli_main([*argv, "--out", str(tmp_path / "run"), "--ema-decay", "0.999"]) == 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["ema_decay"] == 0.999
    capsys.readouterr()
    for bad in ("1", "-0.1", "nan", "x"):
        with pytest.raises(SystemExit) as refused:  # refused while parsing, as argparse does
            cli_main([*argv, "--out", str(tmp_path / "bad"), "--ema-decay", bad])
        assert refused.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--ema-decay" in err and repr(bad) in err, err
    assert not (tmp_path / "bad").exists()


def test_train_cli_defaults_are_train_configs() -> None:
    """The CLI lists its defaults literally (no torch import to parse arguments); they must be TrainConfig's."""
    from don_gym.cli import build_parser

    args = build_parser().parse_args(["train", "--method", "supervised", "--data", "d", "--out", "o"])
    assert args.lr_decay_every == TrainConfig.lr_decay_every
    assert args.checkpoint_every == TrainConfig.checkpoint_every
    assert args.hard_object == TrainConfig.hard_object_fraction
    assert args.hard_background == TrainConfig.hard_background_fraction
    assert args.ema_decay == TrainConfig.ema_decay


def test_part_layout_identity_on_a_dataset_of_one_part_is_one_line(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    argv = ["train", "--method", "supervised-edge", "--data", tiny_dataset, "--out", str(tmp_path / "run")]
    assert cli_main([*argv, "--part-layout", "identity", "--steps", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert "part layout 'identity' (--part-layout) is for bin datasets of several parts" in err, err
    assert len(err.splitlines()) == 1 and not (tmp_path / "run").exists()


def test_out_that_is_a_file_and_failed_writes(tiny_dataset: str, tmp_path: Path, monkeypatch, capsys) -> None:
    (tmp_path / "file").write_text("not a run")
    with pytest.raises(DonGymError, match="is a file"):
        train(_config("supervised", tiny_dataset, tmp_path / "file"), progress=False)
    assert (tmp_path / "file").read_text() == "not a run"
    config = replace(_config("supervised", tiny_dataset, tmp_path / "run", steps=2), checkpoint_every=1)

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    # A full file system at the first checkpoint: one line; the run directory stays usable.
    monkeypatch.setattr(train_module, "save_checkpoint", full_disk)
    with pytest.raises(DonGymError, match="cannot write .*step_000001.safetensors: No space left"):
        train(config, progress=False)
    assert list(snapshot(tmp_path / "run")) == ["config.json"]  # nothing half-written, no state
    monkeypatch.undo()

    # A read-only file system from the start: the CLI prints one line.
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(train_module, "write_text_atomic", read_only)
    args = ["train", "--method", "supervised", "--data", tiny_dataset, "--out", str(tmp_path / "ro"), "--steps", "1"]
    assert cli_main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Read-only file system" in err, err
    monkeypatch.undo()
    # A config.json without progress (the run above failed before its first state) blocks nothing.
    assert (tmp_path / "run" / "config.json").is_file()
    train(config, progress=False)
    assert len(_losses(tmp_path / "run")) == 2


def test_two_trainings_into_one_run_directory_one_is_refused(tiny_dataset: str, tmp_path: Path) -> None:
    """A job launched twice: while the first run trains, the same command into its directory is refused in
    one line naming it, before it writes anything. The lock goes with the first run's process (kill -9),
    and the directory then trains again."""
    out = tmp_path / "run"
    command = [
        sys.executable, "-m", "don_gym.cli", "train", "--method", "supervised", "--data", tiny_dataset, "--out",
        str(out), "--steps", "100000", "--checkpoint-every", "100000", "--batch-size", "2", "--crop", "64x48",
        "--threads", "1",
    ]  # fmt: skip
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=environment)
    try:
        deadline = time.monotonic() + 120
        while not (out / "config.json").exists():  # written under the lock
            assert first.poll() is None and time.monotonic() < deadline, "the first run never started"
            time.sleep(0.05)
        first.send_signal(signal.SIGSTOP)  # mid-run, holding the lock, off the CPU the others need
        before = snapshot(out)
        second = subprocess.run(command, capture_output=True, text=True, timeout=120, env=environment)
        lines = second.stderr.strip().splitlines()
        assert second.returncode == 2 and len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
        assert f"{out}: another training run is writing this run directory" in lines[0], lines[0]
        with pytest.raises(DonGymError, match="another training run is writing"):  # --resume alike
            train(_config("supervised", tiny_dataset, out, steps=2), resume=True, progress=False)
        assert snapshot(out) == before
        assert first.poll() is None  # the two overlapped
    finally:
        first.kill()
        first.wait()
    train(_config("supervised", tiny_dataset, out, steps=2), progress=False)
    assert len(_losses(out)) == 2


def test_loss_that_becomes_nan_is_one_line(tiny_dataset: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(train_module, "supervised_l2_loss", lambda pred, *a: pred.sum() * float("nan"))
    with pytest.raises(DonGymError, match="loss became nan at step 1.*lower --lr"):
        train(_config("supervised", tiny_dataset, tmp_path / "run", steps=2), progress=False)


def test_resume_does_not_depend_on_path_spelling(tiny_dataset: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    # Every session saves its state when it ends; checkpoints in between would only cost time.
    config = replace(_config("supervised", tiny_dataset, Path("run"), steps=2), checkpoint_every=100, lr_decay_every=2)
    train(config, progress=False)
    train(replace(config, out="./run", steps=3), resume=True, progress=False)
    train(replace(config, out=str(tmp_path / "run"), steps=4), resume=True, progress=False)
    shutil.move(tmp_path / "run", tmp_path / "moved")
    shutil.copytree(tiny_dataset, tmp_path / "data_copy")  # the same dataset elsewhere
    train(replace(config, out="moved", data="data_copy", steps=5), resume=True, progress=False)
    reference = train(replace(config, out="straight", steps=5), progress=False)
    assert _columns(tmp_path / "moved") == _columns(tmp_path / "straight")
    assert "/" not in json.loads((tmp_path / "moved" / "config.json").read_text())["out"]
    assert reference.steps == 5


def test_resume_reads_a_missing_augmentation_setting_as_its_default(tiny_dataset: str, tmp_path: Path) -> None:
    # A run saved before AugmentConfig.pattern_probability existed has no such key in its config.json.
    config = replace(_config("supervised", tiny_dataset, tmp_path / "run", steps=1), checkpoint_every=1)
    train(config, progress=False)
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    saved["augment"].pop("pattern_probability", None)
    (tmp_path / "run" / "config.json").write_text(json.dumps(saved))
    full = {**config.augment, "pattern_probability": 0.0}
    assert train(replace(config, steps=2, augment=full), resume=True, progress=False).steps == 2
    with pytest.raises(DonGymError, match="augment"):
        train(replace(config, steps=3, augment={**full, "pattern_probability": 0.5}), resume=True, progress=False)


def test_damaged_run_directory_is_one_line(tiny_dataset: str, tmp_path: Path) -> None:
    config = replace(_config("supervised", tiny_dataset, tmp_path / "run", steps=1), checkpoint_every=1)
    train(config, progress=False)
    more = replace(config, steps=2)
    state = (tmp_path / "run" / TRAIN_STATE).read_bytes()
    (tmp_path / "run" / TRAIN_STATE).write_bytes(state[: len(state) // 2])
    damaged = snapshot(tmp_path / "run")
    with pytest.raises(DonGymError, match=f"{TRAIN_STATE}: cannot be read"):
        train(more, resume=True, progress=False)
    assert snapshot(tmp_path / "run") == damaged  # the refusal changed nothing: the checkpoint is still there
    (tmp_path / "run" / TRAIN_STATE).write_bytes(state)
    (tmp_path / "run" / "config.json").write_text("{not json")
    damaged = snapshot(tmp_path / "run")
    with pytest.raises(DonGymError, match="config.json: cannot be read as JSON"):
        train(more, resume=True, progress=False)
    assert snapshot(tmp_path / "run") == damaged
    (tmp_path / "run" / "config.json").unlink()
    damaged = snapshot(tmp_path / "run")
    with pytest.raises(DonGymError, match="config.json: missing"):
        train(more, resume=True, progress=False)
    assert snapshot(tmp_path / "run") == damaged


# --- pretrained weights and the GPU path ---------------------------------------------------------


def test_pretrained_encoder_from_a_torchvision_layout_file(tiny_dataset: str, tmp_path: Path, capsys) -> None:
    torch.manual_seed(5)
    source = DenseObjectNet("resnet18").encoder.state_dict()
    state = {k: v for k, v in source.items() if not k.endswith("num_batches_tracked")}
    state |= {"fc.weight": torch.zeros(1000, 512), "fc.bias": torch.zeros(1000)}  # torchvision's classifier
    torch.save(state, tmp_path / "resnet18.pth")
    config = replace(
        _config("supervised", tiny_dataset, tmp_path / "run", steps=1), arch="resnet18", lr=1e-7, batch_size=1,
        crop_size=(32, 32), checkpoint_every=1, pretrained_path=str(tmp_path / "resnet18.pth"),
    )  # fmt: skip
    model, _ = load_checkpoint(train(config, progress=False).model_path)
    trained = model.encoder.state_dict()
    assert torch.allclose(trained["layer3.1.conv2.weight"], state["layer3.1.conv2.weight"], atol=1e-5)
    state["layer2.0.downsample.0.weight"] = torch.zeros(128, 64, 3, 3)
    torch.save(state, tmp_path / "bad_shape.pth")
    torch.save({"weights": [1, 2]}, tmp_path / "not_a_state_dict.pth")
    args = ["train", "--method", "supervised", "--data", tiny_dataset, "--arch", "resnet18", "--steps", "1"]
    for name, expected in (("bad_shape", "layer2.0.downsample.0.weight: file (128, 64, 3, 3)"),
                           ("not_a_state_dict", "'weights' is a list")):  # fmt: skip
        out = tmp_path / f"run_{name}"
        assert cli_main([*args, "--out", str(out), "--pretrained", str(tmp_path / f"{name}.pth")]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and expected in err, err
        assert not out.exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU; this machine has none")
def test_cuda_mixed_precision_follows_fp32(tiny_dataset: str, tmp_path: Path) -> None:
    config = replace(_config("supervised-edge", tiny_dataset, tmp_path / "fp32", steps=4), device="cuda")
    train(replace(config, precision="fp32"), progress=False)
    train(replace(config, out=str(tmp_path / "amp"), precision="auto", workers=1), progress=False)
    train(replace(config, out=str(tmp_path / "fp16"), precision="fp16"), progress=False)
    train(replace(config, out=str(tmp_path / "cpu"), device="cpu"), progress=False)
    fp32 = _losses(tmp_path / "fp32")
    np.testing.assert_allclose(fp32, _losses(tmp_path / "cpu"), rtol=1e-3)
    np.testing.assert_allclose(_losses(tmp_path / "amp"), fp32, rtol=0.05)
    np.testing.assert_allclose(_losses(tmp_path / "fp16"), fp32, rtol=0.05)
