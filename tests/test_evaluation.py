"""Tracking-error evaluation: metrics on hand-built cases, the oracle on a generated dataset, outputs and CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from synthetic_scenes import Sphere, look_at, render_scene, table_scene

from don_gym.cli import main
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.errors import DonGymError
from don_gym.evaluation.report import per_scene_table
from don_gym.evaluation.splits import seed_split
from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking, reference_edge_distances_px
from don_gym.evaluation.tracking_metrics import (
    FAR_MATCH_M,
    MATCH_CATEGORIES,
    TrackingMatches,
    attribute_matches,
    long_tail_verdict,
    match_descriptors,
    symmetric_distance,
    tail_by_edge_distance,
    tracking_errors,
    visible_projections,
    world_points_at,
    worst_matches,
)
from don_gym.geometry import CameraIntrinsics, invert_transform, make_transform, project_points, transform_points
from don_gym.learning.checkpoints import save_checkpoint
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import DescriptorSource, NetworkDescriptors
from don_gym.plotting import plot_match_gallery

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


def test_a_border_margin_moves_matches_inside_and_counts_only_pixels_there() -> None:
    width, height = 12, 10
    reference = _ramp_image(width, height)[0, 11][None]  # the top-right corner's descriptor
    whole = match_descriptors(_ramp_image(width, height), reference, np.array([[11, 0]]))
    np.testing.assert_array_equal(whole.uv, [[11, 0]])
    inside = match_descriptors(_ramp_image(width, height), reference, np.array([[11, 0]]), border_margin_px=1)
    np.testing.assert_array_equal(inside.uv, [[10, 1]])
    assert inside.distance[0] == pytest.approx(np.sqrt(2.0))
    # Against a true pixel inside, the closer pixels are counted among the inner 10 x 8 only.
    shifted = match_descriptors(
        _ramp_image(width, height, shift_u=2),
        _ramp_image(width, height)[5, 4][None],
        np.array([[4, 5]]),
        border_margin_px=1,
    )
    assert shifted.fraction_closer[0] == pytest.approx(9 / ((width - 2) * (height - 2)))
    # A candidate mask applies within the margin; one entirely inside the margin leaves the margin's region.
    edge_only = np.zeros((height, width), dtype=bool)
    edge_only[0] = True
    fallback = match_descriptors(_ramp_image(width, height), reference, None, edge_only, border_margin_px=1)
    np.testing.assert_array_equal(fallback.uv, [[10, 1]])
    with pytest.raises(DonGymError, match="border_margin_px"):
        TrackingConfig(border_margin_px=-1).validate()
    network = NetworkDescriptors(DenseObjectNet(descriptor_dim=3))
    assert TrackingConfig().border_margin_for(network) == 16
    assert TrackingConfig(border_margin_px=0).border_margin_for(network) == 0


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


def test_any_instance_error_finds_the_point_on_a_twin() -> None:
    T_reference = make_transform(translation=[0.4, 0.1, 0.02])
    T_twin = make_transform(
        rotation=Rotation.from_euler("z", 90, degrees=True).as_matrix(), translation=[0.6, 0.0, 0.02]
    )
    truth = np.array([[0.41, 0.1, 0.025], [0.4, 0.1, 0.03]])
    on_twin = transform_points(T_twin @ invert_transform(T_reference), truth)
    predicted = np.vstack([on_twin[0], [np.nan] * 3])  # the first found on the twin, the second without depth
    axis, origin = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    errors = tracking_errors(predicted, truth, T_reference, origin, axis, [T_twin])
    assert errors["error_3d_m"][0] > 0.15 and errors["symmetric_error_m"][0] > 0.15
    assert errors["error_3d_any_instance_m"][0] == pytest.approx(0.0, abs=1e-12)
    assert errors["symmetric_error_any_instance_m"][0] == pytest.approx(0.0, abs=1e-12)
    assert all(np.isnan(values[1]) for values in errors.values())
    # Without twins the nearest instance is the reference; without a pile (None) there is no such error.
    alone = tracking_errors(predicted, truth, T_reference, origin, axis, [])
    np.testing.assert_array_equal(alone["error_3d_any_instance_m"], alone["error_3d_m"])
    assert set(tracking_errors(predicted, truth, T_reference, origin, None)) == {"error_3d_m", "symmetric_error_m"}


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


def test_reference_edge_distances_are_each_reference_pixels_distance_inside_its_silhouette(
    ideal_dataset: Path,
) -> None:
    """Checked against a brute-force distance to the nearest off-part pixel; references keep the protocol's
    1-pixel erosion, so none lies on the silhouette itself."""
    from don_gym.data.dataset import DONDataset

    result = evaluate_tracking(ideal_dataset, {"oracle": "oracle"}, TrackingConfig(points_per_scene=12), progress=False)
    distances = reference_edge_distances_px(result, "oracle")
    matches = result.matches["oracle"]
    assert distances.shape == matches.error_3d_m.shape and distances.min() >= 2.0 - 1e-6
    data = DONDataset(ideal_dataset)
    for i in np.linspace(0, len(distances) - 1, 7).astype(int):
        mask = np.asarray(data.image(int(matches.scene[i]), int(matches.reference_frame[i]), "mask"), dtype=bool)
        rows, cols = np.nonzero(~mask)
        u, v = matches.reference_uv[i]
        assert mask[v, u]
        assert distances[i] == pytest.approx(np.sqrt((cols - u) ** 2 + (rows - v) ** 2).min(), abs=0.05)
    with pytest.raises(DonGymError, match="'edge'.*oracle"):
        reference_edge_distances_px(result, "edge")


def test_tail_by_edge_distance_counts_each_band() -> None:
    distance = np.array([2.0, 2.5, 3.0, 4.0, 7.0, 12.0, 30.0, 1.5])
    error = np.array([0.2, 0.01, 0.05, 0.01, 0.01, 0.06, 0.0, np.nan])  # the last has no depth
    rows = tail_by_edge_distance(distance, error, tail_m=0.045)
    assert [(r["low_px"], r["high_px"], r["matches"]) for r in rows] == [
        (0.0, 3.0, 3), (3.0, 6.0, 1), (6.0, 10.0, 1), (10.0, np.inf, 2)
    ]  # fmt: skip
    assert [r["tail_share"] for r in rows] == pytest.approx([2 / 3, 0.0, 0.0, 0.5])
    assert [r["far_share"] for r in rows] == pytest.approx([1 / 3, 0.0, 0.0, 0.0])
    assert [r["share"] for r in rows] == pytest.approx([3 / 7, 1 / 7, 1 / 7, 2 / 7])
    assert tail_by_edge_distance(distance, error, 0.045, bands_px=(100.0,))[1]["tail_share"] is None
    with pytest.raises(DonGymError, match="bands_px"):
        tail_by_edge_distance(distance, error, 0.045, bands_px=(6.0, 3.0))
    with pytest.raises(DonGymError, match=r"\(M,\)"):
        tail_by_edge_distance(distance[:3], error, 0.045)


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
    assert "seed 1000 (spent)" in printed and "Per scene:" in printed and "| 1000 | 1 | table " in printed
    summary = json.loads((out / "tracking.json").read_text())
    assert set(summary["methods"]) == {"oracle", str(checkpoint)}
    for method in summary["methods"].values():
        for metric in ("error_3d_mm", "error_3d_symmetric_mm", "pixel_error_px", "fraction_closer"):
            assert set(method[metric]) == {"p50", "p90", "p99", "mean"}
            low, high = method["intervals"][metric]["p50"]
            assert low <= method[metric]["p50"] <= high
        assert method["counts"]["visible_matches"] > 0
        assert len(method["per_scene"]) == 2 and set(method["far_by_category"]) == set(MATCH_CATEGORIES)
    assert summary["methods"][str(checkpoint)]["source"]["method"] == "supervised-edge"
    # Each method's border margin is on record: a network's own, the oracle's whole frame.
    assert summary["methods"][str(checkpoint)]["source"]["border_margin_px"] == 16
    assert summary["methods"]["oracle"]["source"]["border_margin_px"] == 0
    # One part, one instance: no any-instance error in the summary or the report (a pile's, test_bin_data).
    assert not any("any_instance" in key for method in summary["methods"].values() for key in method)
    assert "any instance" not in printed
    assert summary["config"]["depth"] == "ideal" and summary["percentiles"] == [50, 90, 99]
    assert summary["split"] == "spent" and summary["bootstrap"]["unit"] == "scene"
    for name in ("tracking_histogram.png", "tracking_cdf.png", "tracking_worst_matches.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*partial*"))


def test_scenes_of_several_datasets_are_pooled(ideal_dataset: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(ideal_dataset, copy)
    config = TrackingConfig(points_per_scene=6)
    single = evaluate_tracking(ideal_dataset, ["oracle"], config, progress=False).matches["oracle"]
    pooled_result = evaluate_tracking([ideal_dataset, copy], ["oracle"], config, progress=False)
    pooled = pooled_result.matches["oracle"]
    assert len(pooled_result.scenes) == 4 and [s["dataset"] for s in pooled_result.scenes] == [0, 0, 1, 1]
    assert len(pooled.scene_id) == 2 * len(single.scene_id) and pooled.reference_points == 2 * single.reference_points
    # The copy's scenes are the same scenes: the same matches, under their own scene ids.
    second = pooled.dataset == 1
    np.testing.assert_array_equal(pooled.scene_id[second], single.scene_id + 2)
    np.testing.assert_allclose(pooled.error_3d_m[second], single.error_3d_m)
    assert pooled_result.summary()["methods"]["oracle"]["tail"]["far_matches"] == 0
    with pytest.raises(DonGymError, match="each dataset may be given once"):
        evaluate_tracking([ideal_dataset, ideal_dataset], ["oracle"], config, progress=False)


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


def test_far_matches_are_attributed_to_what_their_pixel_shows() -> None:
    """A box (the part, long axis its x) on a table plane, a ball above the table (the robot), a table
    edge and a depth hole; each matched pixel is put where a known surface shows."""
    intrinsics = CameraIntrinsics.d435(160, 120)
    primitives, box = table_scene(box_half_extents=(0.05, 0.02, 0.02))
    primitives.append(Sphere(center=(0.02, 0.12, 0.10), radius=0.03))
    T_world_camera = look_at(eye=(0.25, -0.05, 0.45), target=(0.0, 0.03, 0.0))
    depth, index = render_scene(intrinsics, T_world_camera, primitives)
    object_mask = index == 1
    T_world_object = box.T_world_box

    def pixel(point_world) -> list[int]:
        uv, _ = project_points(intrinsics, transform_points(invert_transform(T_world_camera), np.array([point_world])))
        return [int(round(uv[0, 0])), int(round(uv[0, 1]))]

    def on_box(x_object: float) -> np.ndarray:  # a point on the box's top face, x along its long axis
        return transform_points(T_world_object, np.array([[x_object, 0.0, 0.02]]))[0]

    matched = np.array(
        [
            pixel(on_box(0.035)),  # true point at +0.03: same end
            pixel(on_box(0.035)),  # true point at -0.03: the other end
            pixel((0.12, -0.10, 0.0)),  # table top, inside the bounds
            pixel((-0.06, 0.12, 0.0)),  # the table's plane beyond its edge (bounds below): background
            pixel((0.02, 0.12, 0.13)),  # top of the ball above the table: robot/fixture
            pixel((0.12, 0.02, 0.0)),  # table, but a hole in the depth: background
        ]
    )
    depth[matched[5, 1], matched[5, 0]] = 0.0
    truth = np.array([on_box(0.03), on_box(-0.03), *([on_box(0.03)] * 4)])
    assert object_mask[matched[0, 1], matched[0, 0]] and index[matched[4, 1], matched[4, 0]] == 2
    category = attribute_matches(
        matched,
        truth,
        object_mask,
        depth,
        intrinsics,
        T_world_camera,
        T_world_object,
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        table_height_m=0.0,
        table_bounds_xy_m=(-0.05, 0.5, -0.5, 0.5),
    )
    names = [MATCH_CATEGORIES[k] for k in category]
    assert names == ["part, elsewhere", "part, wrong end", "table", "background", "robot/fixture", "background"]
    # Without bounds the plane beyond the edge counts as table, as in the recorded scenes.
    unbounded = attribute_matches(
        matched, truth, object_mask, depth, intrinsics, T_world_camera, T_world_object, np.zeros(3),
        np.array([1.0, 0.0, 0.0]), table_height_m=0.0,
    )  # fmt: skip
    assert MATCH_CATEGORIES[unbounded[3]] == "table"


def _hand_made_matches() -> TrackingMatches:
    """Three scenes of 10 matches: scene 0 has 4 far matches (2 on the table, 2 on the part's wrong end,
    one of which is far only by its depth), scene 1 none, scene 2 has no depth at all."""
    m = 30
    scene_id = np.repeat([0, 1, 2], 10)
    error = np.full(m, 0.004)
    error[:4] = 0.25
    error[20:] = np.nan
    ideal = np.where(np.isnan(error), 0.004, error)
    ideal[3] = 0.01
    category = np.full(m, MATCH_CATEGORIES.index("part, elsewhere"), dtype=np.int8)
    category[:2] = MATCH_CATEGORIES.index("table")
    category[2:4] = MATCH_CATEGORIES.index("part, wrong end")
    zeros = np.zeros(m, dtype=np.int64)
    return TrackingMatches(
        scene_id=scene_id,
        dataset=zeros,
        scene=scene_id,
        frame=zeros + 1,
        point=np.arange(m),
        reference_frame=zeros,
        reference_uv=np.zeros((m, 2), dtype=np.int64),
        matched_uv=np.zeros((m, 2), dtype=np.int64),
        true_uv=np.zeros((m, 2)),
        pixel_error_px=np.full(m, 3.0),
        error_3d_m=error,
        symmetric_error_m=error / 2,
        fraction_closer=np.full(m, 0.001),
        depth_valid=np.isfinite(error),
        error_3d_ideal_m=ideal,
        category=category,
        reference_points=12,
        scenes_evaluated=3,
    )


def test_summary_gives_tails_categories_and_a_per_scene_table() -> None:
    summary = _hand_made_matches().summary()
    tail = summary["tail"]
    assert tail["far_matches"] == 4 and tail["far_share"] == pytest.approx(4 / 20)
    low, high = tail["far_share_interval"]
    assert low == 0.0 and high > 0.3  # the far matches all sit in one of the two scenes with depth
    # Fewer than half the matches are ever far: the median stays 4 mm; the 99th percentile swings with scene 0.
    assert summary["intervals"]["error_3d_mm"]["p50"] == [pytest.approx(4.0), pytest.approx(4.0)]
    assert summary["intervals"]["error_3d_mm"]["p99"] == [pytest.approx(4.0), pytest.approx(250.0)]
    assert tail["p99_over_p50"] == pytest.approx(62.5) and tail["verdict"] == "not settled"
    assert tail["verdict"] == long_tail_verdict(tail["p99_over_p50_interval"])
    by = summary["far_by_category"]
    assert by["table"]["matches"] == 2 and by["part, wrong end"]["matches"] == 2
    assert by["part, wrong end"]["far_only_from_depth"] == 1 and by["table"]["far_only_from_depth"] == 0
    assert [s["far_matches"] for s in summary["per_scene"]] == [4, 0, 0]
    assert [s["matches_with_depth"] for s in summary["per_scene"]] == [10, 10, 0]
    table = per_scene_table(
        {
            "methods": {"net": summary},
            "scene_list": [
                {"dataset_seed": 4101, "scene_index": k, "background": f"table checks ({k}, 0, 0)"} for k in range(3)
            ],
        }
    )
    rows = table.splitlines()
    assert rows[2] == "| 4101 | 0 | table checks (0, 0, 0) | 4/10 (40.0%) |"
    assert rows[3].endswith("| 0/10 (0.0%) |") and rows[4].endswith("| - |")
    assert FAR_MATCH_M == 0.1 and "> 100 mm" in rows[0]


def test_worst_matches_spread_over_scenes() -> None:
    matches = _hand_made_matches()  # scene 0: four matches 250 mm off
    matches.error_3d_m[15] = 0.2  # scene 1: one 200 mm off
    np.testing.assert_array_equal(worst_matches(matches, 2, per_scene=None), [0, 1])
    np.testing.assert_array_equal(worst_matches(matches, 2), [0, 15])  # one far match per scene first
    np.testing.assert_array_equal(worst_matches(matches, 3), [0, 1, 15])  # then the next worst
    assert not np.isin(worst_matches(matches, 30), np.arange(20, 30)).any()  # never a match without depth


def test_long_tail_verdict_needs_the_whole_interval() -> None:
    assert long_tail_verdict((3.1, 9.9)) == "no long tail"
    assert long_tail_verdict((3.1, 10.0)) == "not settled"  # the sample cannot rule a tail out
    assert long_tail_verdict((10.0, 41.0)) == "long tail"
    assert long_tail_verdict((float("nan"), 4.0)) == "-"
    assert (seed_split(6101), seed_split(3102), seed_split(4101), seed_split(0), seed_split(7)) == (
        "test",
        "dev",
        "spent",
        "training",
        "unlisted",
    )


def test_gallery_figure_is_written(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    entry = {
        "reference_rgb": rng.integers(0, 255, (24, 32, 3), dtype=np.uint8),
        "reference_uv": [5, 6],
        "match_rgb": rng.integers(0, 255, (24, 32, 3), dtype=np.uint8),
        "match_uv": [20, 10],
        "true_uv": [6.5, 7.0],
        "reference_title": "seed 4101 scene 0, frame 2",
        "match_title": "frame 5: 412 mm, table",
    }
    path = plot_match_gallery({"a/supervised-edge": [entry, entry], "a/supervised-mask": [entry]}, tmp_path / "g.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(DonGymError, match="no methods"):
        plot_match_gallery({}, tmp_path / "empty.png")
