"""Tracking-error evaluation: metrics on hand-built cases, the oracle on a generated dataset, outputs and CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from don_gym.build import DatasetConfig, build_dataset
from don_gym.checkpoints import save_checkpoint
from don_gym.cli import main
from don_gym.descriptor_sources import DescriptorSource
from don_gym.errors import DonGymError
from don_gym.evaluation import (
    TrackingConfig,
    evaluate_tracking,
    match_descriptors,
    symmetric_distance,
    visible_projections,
    world_points_at,
)
from don_gym.geometry import CameraIntrinsics, make_transform
from don_gym.model import DenseObjectNet
from don_gym.objects import load_object

torch.set_num_threads(1)


def _ramp_image(width: int, height: int, shift_u: int = 0) -> np.ndarray:
    """D = 2 descriptor image whose descriptor is (u - shift_u, v): content moved right by shift_u."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u - shift_u, v], axis=-1).astype(np.float32)


def test_match_on_a_shifted_copy_has_the_known_pixel_error_and_false_positive_fraction() -> None:
    width, height = 12, 10
    reference = _ramp_image(width, height)[5, 4][None]  # descriptor of pixel (u=4, v=5)
    same = match_descriptors(_ramp_image(width, height), reference, np.array([[4, 5]]))
    np.testing.assert_array_equal(same.uv, [[4, 5]])
    assert same.distance[0] == 0.0 and same.fraction_closer[0] == 0.0

    shifted = match_descriptors(_ramp_image(width, height, shift_u=2), reference, np.array([[4, 5]]))
    np.testing.assert_array_equal(shifted.uv, [[6, 5]])  # the point moved 2 px right
    # Descriptor at the true pixel is 2 away; strictly closer are the match and its 8 neighbours.
    assert shifted.fraction_closer[0] == pytest.approx(9 / (width * height))


def test_3d_error_from_depth_and_visibility_on_a_plane() -> None:
    intrinsics = CameraIntrinsics.d435(64, 48)
    T_world_camera = make_transform(translation=[0.1, -0.2, 0.5])
    depth = np.full((48, 64), 0.5, dtype=np.float32)
    truth, ok = world_points_at(np.array([[20, 30]]), depth, intrinsics, T_world_camera)
    matched, _ = world_points_at(np.array([[22, 30]]), depth, intrinsics, T_world_camera)
    assert ok.all()
    assert np.linalg.norm(matched - truth) == pytest.approx(2 * 0.5 / intrinsics.fx, rel=1e-9)
    depth_with_hole = depth.copy()
    depth_with_hole[30, 22] = 0.0
    missing, ok = world_points_at(np.array([[22, 30]]), depth_with_hole, intrinsics, T_world_camera)
    assert not ok[0] and np.isnan(missing).all()

    camera = T_world_camera[:3, 3]
    points = np.vstack(
        [
            truth,  # on the surface: visible
            truth + (truth - camera) * 0.05,  # 2.5 cm behind the surface: occluded
            camera + np.array([0.0, 0.0, -0.3]),  # behind the camera
            camera + np.array([5.0, 0.0, 0.5]),  # outside the image
        ]
    )
    uv, visible = visible_projections(points, T_world_camera, intrinsics, depth, tolerance_m=0.004)
    np.testing.assert_array_equal(visible, [True, False, False, False])
    np.testing.assert_allclose(uv[0], [20, 30], atol=1e-9)


def test_symmetric_distance_ignores_rotation_about_the_axis() -> None:
    T_world_object = make_transform(translation=[0.4, 0.1, 0.02])
    point = np.array([[0.4 + 0.01, 0.1, 0.02 + 0.005]])
    angle = 2.0
    rotated = np.array([[0.4 + 0.01 * np.cos(angle), 0.1 + 0.01 * np.sin(angle), 0.025]])
    axis, origin = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    assert symmetric_distance(point, rotated, T_world_object, origin, axis)[0] == pytest.approx(0.0, abs=1e-12)
    assert np.linalg.norm(point - rotated) > 0.015
    raised = rotated + [0.0, 0.0, 0.003]
    assert symmetric_distance(point, raised, T_world_object, origin, axis)[0] == pytest.approx(0.003)


class NoiseDescriptors(DescriptorSource):
    """Uniform random descriptors: a model that has learned nothing."""

    object_model = None
    method = "noise"
    descriptor_dim = 3

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)

    def descriptor_image(self, obs, info=None) -> np.ndarray:
        return self.rng.random(obs["rgb"].shape[:2] + (3,), dtype=np.float32)


@pytest.fixture(scope="module")
def ideal_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("eval") / "data"
    config = DatasetConfig(
        scenes=2, frames_per_scene=3, image_size=(128, 96), sensor="ideal", seed=1000, fuse_depth=False
    )
    build_dataset(config, out, progress=False)
    return out


def test_oracle_tracks_with_near_zero_error_and_noise_does_not(ideal_dataset: Path) -> None:
    config = TrackingConfig(points_per_scene=12)
    methods = {"oracle": "oracle", "noise": NoiseDescriptors()}
    result = evaluate_tracking(ideal_dataset, methods, config, progress=False)
    oracle, random = result.matches["oracle"], result.matches["noise"]
    assert oracle.reference_points == 24 and len(oracle.scene) >= 20
    assert oracle.depth_valid.all()  # ideal depth: every matched pixel has depth
    # The toolcap's symmetric descriptors are constant on rings about its axis, so the oracle is
    # exact up to that ring (and a pixel of ~3 mm at this size); plain 3D error stays within the part.
    assert np.median(oracle.symmetric_error_m) < 0.0015
    assert np.percentile(oracle.symmetric_error_m, 90) < 0.004
    assert np.nanmax(oracle.error_3d_m) < 0.05
    assert np.median(oracle.fraction_closer) < 0.002
    # Random descriptors match anywhere in the image: errors of centimetres to decimetres.
    assert np.nanmedian(random.error_3d_m) > 0.03
    assert np.median(random.pixel_error_px) > 10
    # Same reference points and visibility for every method.
    np.testing.assert_array_equal(oracle.frame, random.frame)
    np.testing.assert_array_equal(oracle.point, random.point)


def _tiny_checkpoint(path: Path, object_name: str) -> Path:
    torch.manual_seed(0)
    model = DenseObjectNet(descriptor_dim=3)
    obj = load_object(object_name)
    meta = {
        "method": "supervised-edge",
        "object_name": obj.name,
        "object_mesh_hash": obj.mesh_hash,
        "image_size": (128, 96),
    }
    save_checkpoint(path, model, meta)
    return path


def test_cli_writes_json_table_and_plots(ideal_dataset: Path, tmp_path: Path, capsys) -> None:
    checkpoint = _tiny_checkpoint(tmp_path / "net.safetensors", "toolcap")
    out = tmp_path / "out"
    code = main(
        ["evaluate", "--data", str(ideal_dataset), "--models", "oracle", str(checkpoint)]
        + ["--points", "6", "--out", str(out), "--no-progress"]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "| oracle |" in printed and "net.safetensors" in printed
    summary = json.loads((out / "tracking.json").read_text())
    assert set(summary["methods"]) == {"oracle", str(checkpoint)}
    for method in summary["methods"].values():
        for metric in ("error_3d_mm", "error_3d_symmetric_mm", "pixel_error_px", "fraction_closer"):
            assert set(method[metric]) == {"p50", "p90", "p99", "mean"}
        assert method["counts"]["visible_matches"] > 0
    assert summary["methods"][str(checkpoint)]["source"]["method"] == "supervised-edge"
    assert summary["config"]["depth"] == "ideal" and summary["percentiles"] == [50, 90, 99]
    for name in ("tracking_histogram.png", "tracking_cdf.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*partial*"))


def test_bad_inputs_are_clear_errors(ideal_dataset: Path, tmp_path: Path, capsys) -> None:
    with pytest.raises(DonGymError, match="'toolcap/nonsense' is neither 'oracle'"):
        evaluate_tracking(ideal_dataset, ["toolcap/nonsense"], progress=False)
    shaft_net = _tiny_checkpoint(tmp_path / "shaft.safetensors", "shaft")
    with pytest.raises(DonGymError, match="object_name is 'shaft', expected 'toolcap'"):
        evaluate_tracking(ideal_dataset, [str(shaft_net)], progress=False)
    with pytest.raises(DonGymError, match="does not exist"):
        evaluate_tracking(tmp_path / "missing", ["oracle"], progress=False)
    with pytest.raises(DonGymError, match="depth="):
        evaluate_tracking(ideal_dataset, ["oracle"], TrackingConfig(depth="fused"), progress=False)
    capsys.readouterr()
    for argv in (
        ["--data", str(tmp_path / "missing"), "--models", "oracle"],
        ["--data", str(ideal_dataset), "--models", str(shaft_net)],
        ["--data", str(ideal_dataset), "--models", "oracle", "--points", "0"],
    ):
        assert main(["evaluate", *argv, "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("don-gym evaluate: error: ") and err.count("\n") == 1
