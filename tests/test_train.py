"""Training with both methods end to end on a tiny generated dataset."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from don_gym.build import DatasetConfig, build_dataset
from don_gym.checkpoints import load_checkpoint
from don_gym.errors import CheckpointError, DonGymError
from don_gym.train import TrainConfig, train


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("train") / "data"
    config = DatasetConfig(scenes=2, frames_per_scene=4, image_size=(96, 72), sensor="d435", seed=3)
    build_dataset(config, out, progress=False)
    return str(out)


def _losses(run: Path) -> np.ndarray:
    with (run / "losses.csv").open() as f:
        return np.array([float(row["loss"]) for row in csv.DictReader(f)])


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
    assert model.descriptor_image(np.zeros((72, 96, 3), np.uint8)).shape == (72, 96, 3)
    with pytest.raises(CheckpointError, match="object_name"):
        load_checkpoint(result.model_path, expect_object="shaft")


def test_same_seed_same_curve_and_exact_resume(tiny_dataset: str, tmp_path: Path) -> None:
    config = _config("supervised", tiny_dataset, tmp_path / "a", steps=8)
    config = replace(config, checkpoint_every=4)
    train(config, progress=False)
    train(replace(config, out=str(tmp_path / "b")), progress=False)
    np.testing.assert_array_equal(_losses(tmp_path / "a"), _losses(tmp_path / "b"))
    # Interrupted after step 4 (its checkpoint), then resumed: the same curve.
    first = train(replace(config, out=str(tmp_path / "c"), steps=4), progress=False)
    with pytest.raises(DonGymError, match="different configuration.*lr"):
        train(replace(config, out=str(tmp_path / "c"), lr=1e-2), resume=True, progress=False)
    resumed = train(replace(config, out=str(tmp_path / "c")), resume=True, progress=False)
    np.testing.assert_allclose(_losses(tmp_path / "c"), _losses(tmp_path / "a"), rtol=1e-5)
    # The reported time covers both sessions; resuming a finished run reports the same run.
    assert first.seconds is not None and resumed.seconds is not None and resumed.seconds > first.seconds
    again = train(replace(config, out=str(tmp_path / "c")), resume=True, progress=False)
    assert again.seconds == pytest.approx(resumed.seconds, rel=0.05) and again.final_loss == resumed.final_loss
    with pytest.raises(DonGymError, match="already holds"):
        train(config, progress=False)
