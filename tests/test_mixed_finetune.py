"""Training data of both looks and fine-tuning (issue 56, item 5): a ``mixed`` dataset path-traces its odd scenes
and keeps TinyRenderer's geometry for all of them; ``init_path`` starts a run from a network's weights, refusing a
network of another method, arch or part in one line before anything is written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from don_gym.cli import main as cli_main
from don_gym.data.build import DatasetConfig, build_dataset, scene_renderer
from don_gym.data.dataset import DONDataset, scene_dir
from don_gym.errors import DonGymError
from don_gym.learning.checkpoints import load_checkpoint
from don_gym.learning.train import TrainConfig, train
from don_gym.sim import pbr

SIZE = (64, 48)


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("mixed")
    built = {}
    renderers = ["tiny", "mixed"] if pbr.mitsuba_available() else ["tiny"]
    for renderer in renderers:
        config = DatasetConfig(
            scenes=2, frames_per_scene=2, image_size=SIZE, seed=5, renderer=renderer, fuse_depth=False
        )
        built[renderer] = root / renderer
        build_dataset(config, built[renderer], progress=False)
    return built


def test_scene_renderer_alternates_only_for_mixed():
    assert [scene_renderer("mixed", i) for i in range(4)] == ["tiny", "pbr", "tiny", "pbr"]
    assert {scene_renderer("pbr", i) for i in range(4)} == {"pbr"}
    with pytest.raises(DonGymError, match="renderer='cycles'.*expected one of"):
        DatasetConfig(renderer="cycles").validate()


@pytest.mark.skipif(not pbr.mitsuba_available(), reason="the pbr extra is not installed")
def test_mixed_dataset_path_traces_odd_scenes_over_the_same_geometry(datasets):
    tiny, mixed = DONDataset(str(datasets["tiny"])), DONDataset(str(datasets["mixed"]))
    assert mixed.info["renderer"] == "mixed"
    for index in range(2):
        recorded = json.loads((scene_dir(datasets["mixed"], index) / "scene.json").read_text())
        assert recorded["renderer"] == ("pbr" if index % 2 else "tiny")
        for kind in ("mask", "depth_ideal"):
            np.testing.assert_array_equal(tiny.image(index, 0, kind), mixed.image(index, 0, kind))
        same_rgb = np.array_equal(tiny.image(index, 0, "rgb"), mixed.image(index, 0, "rgb"))
        assert same_rgb == (index % 2 == 0), f"scene {index}: only the odd scene is path-traced"


def _run(data: Path, out: Path, **options) -> TrainConfig:
    settings = dict(method="supervised-edge", data=str(data), out=str(out), steps=2, batch_size=2, crop_size=(32, 32))
    return TrainConfig(**{**settings, **options})


def test_fine_tuning_starts_from_the_checkpoint(datasets, tmp_path):
    first = train(_run(datasets["tiny"], tmp_path / "first", steps=4), progress=False)
    start, _ = load_checkpoint(first.model_path)
    tuned = train(_run(datasets["tiny"], tmp_path / "tuned", init_path=str(first.model_path), lr=1e-9), progress=False)
    fresh = train(_run(datasets["tiny"], tmp_path / "fresh", lr=1e-9, seed=1), progress=False)
    tuned_model, metadata = load_checkpoint(tuned.model_path)
    fresh_model, _ = load_checkpoint(fresh.model_path)
    assert metadata.extra["init"] == "model.safetensors"
    for name, weight in start.state_dict().items():
        if name.endswith(".weight") and weight.ndim == 4:
            assert torch.allclose(tuned_model.state_dict()[name], weight, atol=1e-5), name
            assert not torch.allclose(fresh_model.state_dict()[name], weight, atol=1e-3), name


def test_init_of_another_method_or_arch_is_one_line_and_writes_nothing(datasets, tmp_path, capsys):
    first = train(_run(datasets["tiny"], tmp_path / "first"), progress=False)
    for options, expected in (
        ({"method": "supervised-mask"}, "method is 'supervised-edge', expected 'supervised-mask'"),
        ({"arch": "resnet-lite-fine"}, "arch is 'resnet-lite', this run's 'resnet-lite-fine'"),
    ):
        out = tmp_path / f"refused_{len(expected)}"
        with pytest.raises(DonGymError, match=expected):
            train(_run(datasets["tiny"], out, init_path=str(first.model_path), **options), progress=False)
        assert not out.exists()
    out = tmp_path / "cli"
    code = cli_main(
        ["train", "--method", "supervised-edge", "--data", str(datasets["tiny"]), "--out", str(out), "--steps", "1",
         "--init", str(tmp_path / "missing.safetensors")]
    )  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "missing.safetensors" in err[0] and not out.exists()
    with pytest.raises(DonGymError, match="not both"):
        train(_run(datasets["tiny"], tmp_path / "both", init_path="a", pretrained_path="b"), progress=False)
