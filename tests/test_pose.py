"""Pose from descriptors (don_gym.perception.pose) and the BOP metrics (don_gym.evaluation.pose_metrics): known
answers on tiny images."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from don_gym.data.render import DescriptorRenderer
from don_gym.errors import DonGymError
from don_gym.evaluation.pose_metrics import (
    MSPD_THRESHOLDS_PX,
    MSSD_THRESHOLDS,
    adds,
    bop_symmetries,
    model_diameter,
    mspd,
    mssd,
    object_symmetries,
    pose_recalls,
    recall_curve,
    symmetry_transformations,
)
from don_gym.geometry import CameraIntrinsics, make_transform, rotation_angle_rad
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import OracleDescriptors
from don_gym.perception.pose import (
    PoseConfig,
    estimate_pose,
    pose_targets,
    pose_targets_for,
    reference_vertex_descriptors,
)

CUBE = np.array([[x, y, z] for x in (-0.01, 0.01) for y in (-0.01, 0.01) for z in (-0.02, 0.02)])
K = CameraIntrinsics.d435(160, 120)
T_GT = make_transform(Rotation.from_euler("xyz", [0.3, -0.5, 1.0]).as_matrix(), [0.01, -0.02, 0.4])


# --- metrics -------------------------------------------------------------------------------------


def test_identity_pose_has_no_error():
    syms = symmetry_transformations()
    assert syms.shape == (1, 4, 4)
    assert mssd(T_GT, T_GT, CUBE, syms) == pytest.approx(0.0, abs=1e-12)
    assert mspd(T_GT, T_GT, K.K, CUBE, syms) == pytest.approx(0.0, abs=1e-9)
    assert adds(T_GT, T_GT, CUBE) == pytest.approx(0.0, abs=1e-12)


def test_known_translation_offset_gives_known_errors():
    offset = np.array([0.005, 0.0, 0.0])  # 5 mm along the camera's x
    T_est = T_GT.copy()
    T_est[:3, 3] += offset
    syms = symmetry_transformations()
    assert mssd(T_est, T_GT, CUBE, syms) == pytest.approx(0.005, rel=1e-9)
    # Every point moves 5 mm sideways: its image moves fx * 5 mm / z; the nearest point moves most.
    z = (CUBE @ T_GT[:3, :3].T + T_GT[:3, 3])[:, 2]
    assert mspd(T_est, T_GT, K.K, CUBE, syms) == pytest.approx(K.fx * 0.005 / z.min(), rel=1e-9)
    assert 0.0 < adds(T_est, T_GT, CUBE) <= 0.005 + 1e-12


def test_pose_rotated_by_a_symmetry_has_no_mssd_but_a_plain_error():
    model = load_object("toolcap")
    points = np.asarray(model.mesh.vertices)
    syms = object_symmetries(model)
    assert len(syms) == 315  # ceil(pi / 0.01) rotations over a turn, as BOP discretises
    turn = make_transform(Rotation.from_rotvec([0.0, 0.0, 2.0 * np.pi * 40 / 315]).as_matrix())
    T_est = T_GT @ turn  # the same part in the image
    assert mssd(T_est, T_GT, points, syms) < 1e-9
    assert mspd(T_est, T_GT, K.K, points, syms) < 1e-6
    assert mssd(T_est, T_GT, points, symmetry_transformations()) > 0.01  # without the symmetry: centimetres
    # A turn between two discretised rotations costs at most the furthest point's half-step travel.
    half = make_transform(Rotation.from_rotvec([0.0, 0.0, np.pi / 315]).as_matrix())
    radius = np.linalg.norm(points[:, :2], axis=1).max()
    assert mssd(T_GT @ half, T_GT, points, syms) == pytest.approx(radius * 2 * np.sin(np.pi / 630), rel=1e-6)


def test_bop_symmetries_in_millimetres_become_metres():
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip[:3, 3] = [10.0, 0.0, 0.0]  # mm: a half turn about z through x = 5 mm
    syms = bop_symmetries({"symmetries_discrete": [flip.ravel().tolist()]})
    assert syms.shape == (2, 4, 4)
    assert syms[1][:3, 3] == pytest.approx([0.010, 0.0, 0.0])
    continuous = bop_symmetries({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [5.0, 0, 0]}]})
    # Every rotation keeps the axis through (5 mm, 0, 0) in place.
    on_axis = np.array([0.005, 0.0, 0.03, 1.0])
    assert np.allclose(continuous @ on_axis, on_axis)


def test_recalls_and_average_recall():
    assert recall_curve([0.0, np.inf, np.nan, 0.2], [0.1, 0.3]).tolist() == [0.25, 0.5]
    diameter = 0.1
    # MSSD 0.012 m = 0.12 diameters: correct from threshold 0.15 on (8 of 10 thresholds).
    # MSPD 12 px at 1280 px width = 6 px at 640: correct from 10 px on (9 of 10).
    result = pose_recalls([0.012, np.nan], [12.0, np.nan], [0.005, np.nan], diameter, 1280)
    assert result["mssd_recall"] == pytest.approx([0.0, 0.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5])
    assert result["ar_mssd"] == pytest.approx(0.4)
    assert result["ar_mspd"] == pytest.approx(0.45)
    assert result["ar"] == pytest.approx(0.425)
    assert result["adds_share"] == pytest.approx(0.5)
    assert len(MSSD_THRESHOLDS) == len(MSPD_THRESHOLDS_PX) == 10
    assert model_diameter(CUBE) == pytest.approx(np.sqrt(0.02**2 + 0.02**2 + 0.04**2))
    with pytest.raises(DonGymError, match="diameter_m"):
        pose_recalls([0.0], [0.0], [0.0], 0.0, 640)


# --- pose ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def toolcap():
    return load_object("toolcap")


@pytest.fixture(scope="module")
def oracle(toolcap):
    return OracleDescriptors(toolcap)


def _view(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_transform(
        Rotation.random(random_state=seed).as_matrix(), [rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), 0.4]
    )


@pytest.mark.parametrize("with_depth", [True, False])
def test_oracle_pose_of_a_symmetric_part_is_right_up_to_its_symmetry(toolcap, oracle, with_depth):
    targets = pose_targets_for(oracle)
    assert targets.symmetric and "rotation about" in targets.defined_up_to
    points = np.asarray(toolcap.mesh.vertices)
    syms = object_symmetries(toolcap)
    for seed in range(3):
        T = _view(seed)
        view = oracle.render(K, T)
        estimate = estimate_pose(view.descriptor_image, targets, K, view.depth_m if with_depth else None)
        assert estimate.found and estimate.symmetric and estimate.solver == ("rings+icp" if with_depth else "pnp")
        assert estimate.inliers >= 0.9 * estimate.correspondences > 50
        assert 0.9 <= estimate.score <= 1.0 and estimate.time_s > 0
        # Inside BOP's tightest thresholds (5% of the 49 mm diameter, 5 px); depth within 1 mm.
        tolerance = 0.02 if with_depth else 0.05
        assert mssd(estimate.T_camera_object, T, points, syms) < tolerance * targets.diameter_m
        assert mspd(estimate.T_camera_object, T, K.K, points, syms) < 1.0


def _coordinate_descriptors(model) -> np.ndarray:
    """Descriptors that name every vertex: its coordinates scaled into [0, 1] (no symmetry honoured)."""
    vertices = np.asarray(model.mesh.vertices)
    return ((vertices - vertices.min(0)) / np.ptp(vertices, axis=0)).astype(np.float32)


@pytest.mark.parametrize("with_depth", [True, False])
def test_descriptors_that_name_vertices_give_the_full_pose(toolcap, with_depth):
    descriptors = _coordinate_descriptors(toolcap)
    background = np.array([1.0, 1.0, 1.0], np.float32) * 3.0
    targets = pose_targets(toolcap, descriptors, symmetric=False, background=background, max_distance=0.02)
    assert not targets.symmetric and targets.defined_up_to is None
    renderer = DescriptorRenderer(toolcap.mesh, descriptors, background)
    T = _view(4)
    view = renderer.render(K, T)
    estimate = estimate_pose(view.descriptor_image, targets, K, view.depth_m if with_depth else None)
    assert estimate.found and not estimate.symmetric
    assert estimate.solver == ("kabsch+icp" if with_depth else "pnp")
    # The whole rotation, about the axis too: the plain (non-symmetric) MSSD is small.
    assert rotation_angle_rad(estimate.T_camera_object[:3, :3], T[:3, :3]) < np.radians(3.0)
    assert mssd(estimate.T_camera_object, T, np.asarray(toolcap.mesh.vertices), symmetry_transformations()) < 0.002


def test_reference_views_give_targets_for_any_source(toolcap, oracle):
    references = [(oracle.render(K, _view(s)).descriptor_image, K, _view(s)) for s in (10, 11)]
    descriptors, valid = reference_vertex_descriptors(toolcap, references)
    assert 0 < valid.sum() < len(valid)  # two views see part of the part
    field = oracle.field.vertex_descriptors
    # Each seen vertex reads its pixel's descriptor: the field's, up to the pixel's offset from the vertex.
    assert np.median(np.abs(descriptors[valid] - field[valid])) < 0.02
    targets = pose_targets(toolcap, descriptors, valid, symmetric=True)
    T = _view(5)
    view = oracle.render(K, T)
    estimate = estimate_pose(view.descriptor_image, targets, K, view.depth_m, object_mask=view.object_mask)
    assert estimate.found
    assert mssd(estimate.T_camera_object, T, np.asarray(toolcap.mesh.vertices), object_symmetries(toolcap)) < 0.003


class _MaskOracle(OracleDescriptors):
    """The oracle's two first dimensions and a mask channel: a perfect ``supervised-mask`` network."""

    @property
    def method(self) -> str:
        return "supervised-mask"

    @property
    def reference_from_field(self) -> bool:
        return False

    def view(self, T: np.ndarray) -> np.ndarray:
        from don_gym.data.render import make_target, mask_background

        rendered = self.render(K, T)
        background = mask_background(self.field.vertex_descriptors)
        return make_target("mask", rendered.descriptor_image, rendered.object_mask, background)


def test_a_mask_channel_tells_the_part_and_is_not_matched(toolcap):
    source = _MaskOracle(toolcap)
    targets = pose_targets_for(source, [(source.view(_view(s)), K, _view(s)) for s in (10, 11)])
    assert targets.mask_channel == 2 and targets.channels == (0, 1) and targets.symmetric
    assert 0.0 < targets.mask_threshold < 0.5  # calibrated between the background's 0 and the part's inside
    T = _view(6)
    estimate = estimate_pose(source.view(T), targets, K, source.render(K, T).depth_m)
    assert estimate.found
    assert mssd(estimate.T_camera_object, T, np.asarray(toolcap.mesh.vertices), object_symmetries(toolcap)) < 0.003


def test_no_part_in_view_gives_no_pose_and_bad_shapes_are_refused(oracle):
    targets = pose_targets_for(oracle)
    empty = np.broadcast_to(oracle.background, (K.height, K.width, 3)).copy()
    estimate = estimate_pose(empty, targets, K, np.zeros((K.height, K.width)))
    assert not estimate.found and estimate.T_camera_object is None and estimate.solver == "none"
    assert estimate.score == 0.0
    with pytest.raises(DonGymError, match="descriptor_image"):
        estimate_pose(empty[:10], targets, K)
    with pytest.raises(DonGymError, match="depth_m"):
        estimate_pose(empty, targets, K, np.zeros((3, 3)))
    assert PoseConfig().min_inliers >= 6


# --- evaluation and CLI --------------------------------------------------------------------------


class _RelabelledOracle(OracleDescriptors):
    """The oracle presented as a learned model: its targets must come from the reference view."""

    @property
    def method(self) -> str:
        return "self-supervised"

    @property
    def reference_from_field(self) -> bool:
        return False


class _NoiseDescriptors(OracleDescriptors):
    """Uniform random descriptors: a model that has learned nothing."""

    @property
    def method(self) -> str:
        return "noise"

    @property
    def reference_from_field(self) -> bool:
        return False

    def descriptor_image(self, obs, info=None) -> np.ndarray:
        return np.random.default_rng(int(obs["rgb"].sum()) % 1000).random(obs["rgb"].shape[:2] + (3,), np.float32)


@pytest.fixture(scope="module")
def pose_dataset(tmp_path_factory):
    from don_gym.data.build import DatasetConfig, build_dataset

    out = tmp_path_factory.mktemp("pose") / "data"
    config = DatasetConfig(
        scenes=2, frames_per_scene=3, image_size=(128, 96), sensor="ideal", seed=1000, fuse_depth=False
    )
    build_dataset(config, out, progress=False)
    return out


def test_evaluate_pose_scores_the_oracle_high_and_noise_low(pose_dataset, toolcap):
    from don_gym.evaluation.pose_evaluation import evaluate_pose

    methods = {"oracle": "oracle", "learned": _RelabelledOracle(toolcap), "noise": _NoiseDescriptors(toolcap)}
    results = evaluate_pose(pose_dataset, methods, depths=("ideal", "none"), progress=False)
    assert set(results) == {"ideal", "none"}
    ideal = results["ideal"].summary()
    assert ideal["symmetric"] and ideal["diameter_mm"] == pytest.approx(49.4, abs=0.1)
    for name in ("oracle", "learned"):
        assert ideal["methods"][name]["count"] == 4  # 6 frames, the two reference views left out
        assert ideal["methods"][name]["ar"] >= 0.9, name
        assert ideal["methods"][name]["adds_share"] == 1.0
    assert ideal["methods"]["noise"]["ar"] < 0.3
    assert results["none"].summary()["methods"]["oracle"]["ar_mspd"] >= 0.9  # RGB-only PnP, in the image
    estimates = results["ideal"].estimates["oracle"]
    assert estimates.found.all() and np.all(estimates.time_s > 0)
    assert len(estimates.bop_rows()) == 4


def test_cli_pose_writes_bop_results_bop_reads(pose_dataset, tmp_path, capsys):
    from don_gym.cli import main
    from don_gym.data.bop import read_pose_results

    out = tmp_path / "out"
    argv = ["evaluate", "--data", str(pose_dataset), "--models", "oracle", "--pose", "--pose-depth", "ideal"]
    assert main([*argv, "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "| oracle |" in printed and "AR_VSD, not computed" in printed
    summary = __import__("json").loads((out / "pose.json").read_text())
    assert summary["methods"]["oracle"]["mssd_thresholds"][0] == pytest.approx(0.05)
    assert (out / "pose_recall.png").stat().st_size > 0
    # --pose adds the pose figures to the tracking evaluation, which runs as without it.
    tracked = __import__("json").loads((out / "tracking.json").read_text())
    assert "oracle" in tracked["methods"] and "3D error p50 (mm)" in printed
    from don_gym.evaluation.pose_evaluation import method_file_name

    assert method_file_name("toolcap/supervised-edge") == "toolcap-supervised-edge"
    rows = read_pose_results(out / "pose_oracle.csv")
    assert len(rows) == 4 and {r["obj_id"] for r in rows} == {1}
    # t in millimetres: the part lies some 0.3-0.6 m from the camera.
    assert all(200.0 < r["t"][2] < 800.0 for r in rows)
    # --pose-depth without --pose: one line, nothing written.
    tracking = ["evaluate", "--data", str(pose_dataset), "--models", "oracle", "--pose-depth", "none"]
    assert main([*tracking, "--out", str(tmp_path / "o"), "--no-progress"]) != 0
    assert "only with --pose" in capsys.readouterr().err and not (tmp_path / "o").exists()


# --- grasping from a pose ------------------------------------------------------------------------


def test_pose_grasp_agent_beside_the_axis_agent_in_the_grasp_benchmark():
    from don_gym.evaluation.grasp_benchmark import GraspBenchmarkConfig, agent_model, run_grasp_benchmark

    assert agent_model("pose:toolcap/supervised-edge") == ("pose", "toolcap/supervised-edge")
    assert agent_model("oracle") == ("axis", "oracle")
    config = GraspBenchmarkConfig(
        methods=("oracle", "pose:oracle"), poses=(0, 3), repeats=1, sensors=("ideal",), image_size=(160, 120)
    )
    result = run_grasp_benchmark(config, workers=1, progress=False)
    assert result.method_info["pose:oracle"]["method"] == "pose:oracle"
    assert result.method_info["pose:oracle"]["agent"] == "pose"
    by_method = {m: [e for e in result.episodes if e["method"] == m] for m in config.methods}
    # Perfect descriptors and exact depth: the pose's grasp lands within millimetres, the +axis the right way.
    for episode in by_method["pose:oracle"]:
        assert episode["outcome"] == "grasp_and_place", episode
        assert episode["position_error_m"] < 0.004 and episode["yaw_error_rad"] < np.radians(3.0)
    assert len(by_method["oracle"]) == 2


def test_end_swap_check_turns_a_swapped_pose_back(toolcap, oracle):
    from don_gym.perception.pose import _end_swap

    targets = pose_targets_for(oracle)
    swap = _end_swap(targets)
    points = np.asarray(toolcap.mesh.vertices)
    assert mssd(T_GT @ swap, T_GT, points, object_symmetries(toolcap)) > 0.3 * targets.diameter_m
    assert np.allclose(swap @ swap, np.eye(4))
    # Descriptors that name the ends the wrong way round: the field of the part turned end over end.
    T = _view(7)
    swapped_view = oracle.render(K, T @ swap)
    view = oracle.render(K, T)
    image = swapped_view.descriptor_image
    config = PoseConfig(flip_check_ratio=1.02)
    for check in (None, config):
        estimate = estimate_pose(
            image, targets, K, view.depth_m, object_mask=view.object_mask, config=check or PoseConfig()
        )
        error = mssd(estimate.T_camera_object, T, points, object_symmetries(toolcap))
        assert (error < 0.003) == (check is not None), error
