"""Networks of the tracking evaluation and the grasp benchmark on a chosen device, on batches of frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from don_gym.cli import main
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.errors import DonGymError
from don_gym.evaluation.grasp_benchmark import GraspBenchmarkConfig, run_grasp_benchmark
from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking
from don_gym.learning.model import DenseObjectNet, torch_device
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import NetworkDescriptors


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("device") / "data"
    config = DatasetConfig(scenes=1, frames_per_scene=4, image_size=(64, 48), sensor="ideal", seed=7, fuse_depth=False)
    build_dataset(config, out, progress=False)
    return out


def _network() -> NetworkDescriptors:
    torch.manual_seed(0)
    return NetworkDescriptors(DenseObjectNet(descriptor_dim=3), None, load_object("toolcap"), "a random network")


def _evaluate(dataset: Path, **options):
    config = TrackingConfig(points_per_scene=8)
    return evaluate_tracking(dataset, {"net": _network()}, config, progress=False, **options).matches["net"]


def test_batches_of_frames_match_one_frame_at_a_time(dataset: Path, monkeypatch) -> None:
    one = _evaluate(dataset)
    batch_sizes = []
    batch_pass = NetworkDescriptors.descriptor_images

    def counted(self, rgb):
        batch_sizes.append(len(rgb))
        return batch_pass(self, rgb)

    monkeypatch.setattr(NetworkDescriptors, "descriptor_images", counted)
    batched = _evaluate(dataset, batch_size=3)
    assert batch_sizes and max(batch_sizes) == 3 and sum(batch_sizes) <= 4  # the scene's 4 frames, at most
    np.testing.assert_array_equal(one.frame, batched.frame)
    # The same descriptors up to float rounding; a near tie may pick a neighbouring pixel.
    assert np.mean(one.pixel_error_px == batched.pixel_error_px) > 0.9
    np.testing.assert_allclose(np.median(one.pixel_error_px), np.median(batched.pixel_error_px), atol=1.5)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_a_device_that_is_not_there_is_refused_before_the_work(dataset: Path, tmp_path: Path, capsys) -> None:
    with pytest.raises(DonGymError, match="device 'cuda'"):
        _evaluate(dataset, device="cuda")
    with pytest.raises(DonGymError, match="batch_size"):
        _evaluate(dataset, batch_size=0)
    with pytest.raises(DonGymError, match="device 'tpu'"):
        run_grasp_benchmark(GraspBenchmarkConfig(poses=(0,), repeats=1), workers=1, progress=False, device="tpu")
    for argv in (
        ["evaluate", "--data", str(dataset), "--models", "oracle", "--out", str(tmp_path / "e"), "--device", "cuda"],
        ["benchmark", "grasp", "--methods", "oracle", "--out", str(tmp_path / "b"), "--device", "cuda:3"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "device 'cuda" in err, err
    assert not (tmp_path / "e").exists() and not (tmp_path / "b").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU; this machine has none")
def test_evaluation_on_the_gpu_follows_the_cpu(dataset: Path) -> None:
    cpu, gpu = _evaluate(dataset), _evaluate(dataset, device="cuda")
    assert torch_device("cuda").type == "cuda"
    np.testing.assert_array_equal(cpu.frame, gpu.frame)
    assert np.mean(cpu.pixel_error_px == gpu.pixel_error_px) > 0.9
