"""Several instances and a hiding object in BOP scenes written here (64 x 48, nothing downloaded): the import
takes occlusion from a z-buffer of every annotated object when the scene has no mask files, reads depth with
its ``depth_scale``, renders the self-supervised method's depth as that z-buffer; pose evaluation scores an
estimate against the instance it found, and drops an instance BOP's 10% visibility rule drops.

The truth every assertion compares with is the scene as :mod:`bop_scenes` rendered it (its z-buffer and
depth in millimetres before they were written to files), never a reader under test."""

from __future__ import annotations

from pathlib import Path

import bop_scenes
import numpy as np
import pytest
import trimesh
from synthetic_scenes import look_at

from don_gym.data import bop
from don_gym.data.dataset import DONDataset, instance_mask
from don_gym.data.import_bop import import_bop
from don_gym.evaluation.pose_evaluation import MIN_VISIBLE_FRACTION, evaluate_pose
from don_gym.geometry import invert_transform, make_transform
from don_gym.perception.descriptor_sources import OracleDescriptors

#: A thin plate (mm) that hides the toolcap in some views.
WALL_MM = (90.0, 90.0, 4.0)
#: Depth PNGs hold depth_mm / DEPTH_SCALE: a reader that ignores the scale is ten times off.
DEPTH_SCALE = 0.1


def _models(folder: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    wall = trimesh.creation.box(extents=WALL_MM).subdivide().subdivide()
    models = {1: bop_scenes.toolcap_mm(), 2: (np.asarray(wall.vertices), np.asarray(wall.faces))}
    info = {}
    for obj_id, (vertices, faces) in models.items():
        bop.write_ply_model(folder / f"obj_{obj_id:06d}.ply", vertices, faces)
        info[obj_id] = bop.models_info_entry(vertices)
    info[1]["symmetries_continuous"] = [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]
    bop.write_models_info(folder / "models_info.json", info)
    return models


def _write_scene(root: Path, views: list[list[tuple[int, np.ndarray]]], with_masks: bool) -> list[dict]:
    """One BOP scene of ``views`` (per image the annotated objects' ``T_camera_object`` in metres); per image
    the truth it was rendered with: ``depth_mm`` (z-buffer, 350 mm behind everything) and per annotation
    ``silhouette`` and ``visible`` (the pixels where it is the nearest surface)."""
    models = _models(root / "models")
    scene = root / "test" / "000001"
    rng = np.random.default_rng(3)
    cameras, gt, truths = {}, {}, []
    for im_id, poses in enumerate(views):
        rgb, depth_mm, masks = bop_scenes.render_image(models, poses, rng)
        bop.write_color_image(scene / "rgb" / f"{im_id:06d}.png", rgb)
        bop.write_depth_mm(scene / "depth" / f"{im_id:06d}.png", depth_mm, DEPTH_SCALE)
        cameras[im_id] = {"cam_K": bop_scenes.K, "depth_scale": DEPTH_SCALE}
        gt[im_id] = [{"obj_id": o, "cam_R_m2c": T[:3, :3], "cam_t_m2c": T[:3, 3] * 1000.0} for o, T in poses]
        if with_masks:
            for gt_id, (silhouette, visible) in enumerate(masks):
                bop.write_mask(bop.mask_path(scene, "mask", im_id, gt_id), silhouette)
                bop.write_mask(bop.mask_path(scene, "mask_visib", im_id, gt_id), visible)
        truths.append({"depth_mm": depth_mm, "silhouette": [m[0] for m in masks], "visible": [m[1] for m in masks]})
    bop.write_scene_camera(scene / "scene_camera.json", cameras)
    bop.write_scene_gt(scene / "scene_gt.json", gt)
    return truths


#: The toolcap lying across the view 0.16 m in front of the camera.
TOOLCAP = make_transform(trimesh.transformations.rotation_matrix(1.2, [1, 0.3, 0])[:3, :3], [0.0, 0.0, 0.16])


def _wall(shift_m: float) -> np.ndarray:
    """The plate 4 cm in front of the toolcap, ``shift_m`` to the side (0: right in front of it)."""
    return make_transform(translation=[shift_m, 0.0, 0.12])


def _visible_fraction(shift_m: float) -> float:
    models = {1: bop_scenes.toolcap_mm(), 2: _models_in_memory()[2]}
    _, _, masks = bop_scenes.render_image(models, [(1, TOOLCAP), (2, _wall(shift_m))], np.random.default_rng(0))
    silhouette, visible = masks[0]
    return visible.sum() / silhouette.sum()


def _models_in_memory() -> dict[int, tuple[np.ndarray, np.ndarray]]:
    wall = trimesh.creation.box(extents=WALL_MM).subdivide().subdivide()
    return {2: (np.asarray(wall.vertices), np.asarray(wall.faces))}


@pytest.fixture(scope="module")
def hidden_scene(tmp_path_factory) -> tuple[Path, list[dict], list[float]]:
    """Five views of the toolcap behind the plate, the plate slid from far aside to almost in front: the first
    two show all of the toolcap (the pose evaluation's reference views), then about half, then under 10%
    (a mostly hidden instance BOP's rule drops), then just over 10%."""
    shifts = np.linspace(0.16, 0.0, 161)
    fractions = np.array([_visible_fraction(s) for s in shifts[::4]])
    shifts = shifts[::4]
    chosen = [
        shifts[0],
        shifts[1],
        shifts[np.argmin(np.abs(fractions - 0.5))],
        shifts[np.argmin(np.where(fractions > 0.0, np.abs(fractions - 0.05), np.inf))],
        shifts[np.argmin(np.where(fractions >= 0.13, fractions, np.inf))],
    ]
    root = tmp_path_factory.mktemp("bop_hidden") / "bop"
    # The plate is annotated first: the z-buffer, not the order of drawing, must put it in front.
    truths = _write_scene(root, [[(2, _wall(s)), (1, TOOLCAP)] for s in chosen], with_masks=False)
    out = root.parent / "data"
    import_bop(root, "test", 1, out)
    return out, truths, [t["visible"][1].sum() / t["silhouette"][1].sum() for t in truths]


def test_import_without_mask_files_takes_occlusion_from_the_z_buffer(hidden_scene) -> None:
    out, truths, fractions = hidden_scene
    assert fractions[0] == fractions[1] == 1.0 and 0.3 < fractions[2] < 0.7 and 0.0 < fractions[3] < 0.1
    data = DONDataset(out)
    for frame, truth in enumerate(truths):
        visible, silhouette = truth["visible"][1], truth["silhouette"][1]
        np.testing.assert_array_equal(data.image(0, frame, "mask"), visible)
        np.testing.assert_array_equal(instance_mask(data, 0, frame), np.where(visible, 2, 0))  # BOP gt_id + 1
        # The part's targets only where it is seen: the plate in front of it is background.
        assert not (data.image(0, frame, "target_mask") & ~visible).any()
        assert (data.image(0, frame, "target_mask") & visible).sum() >= 0.9 * visible.sum()
        if frame >= 2:
            assert (silhouette & ~visible).sum() > 20  # the plate does hide part of it here


def test_import_reads_depth_with_its_scale_and_renders_the_z_buffer_for_the_self_supervised_method(
    hidden_scene,
) -> None:
    out, truths, _ = hidden_scene
    data = DONDataset(out)
    for frame, truth in enumerate(truths):
        # The depth the scene was rendered with (mm, before any PNG); a dataset holds whole millimetres.
        np.testing.assert_allclose(data.image(0, frame, "depth"), truth["depth_mm"] / 1000.0, atol=6e-4)
        anything = truth["silhouette"][0] | truth["silhouette"][1]
        fused = data.image(0, frame, "depth_fused")
        # The nearest annotated surface (the plate where it is in front), nothing where no object is.
        np.testing.assert_allclose(fused[anything], truth["depth_mm"][anything] / 1000.0, atol=6e-4)
        assert (fused[~anything] == 0).all()


def test_pose_evaluation_drops_an_instance_under_bops_visibility_rule(hidden_scene) -> None:
    out, _, fractions = hidden_scene
    result = evaluate_pose(out, ["oracle"], depths=("ideal",), progress=False)["ideal"]
    assert result.reference["frames"] == [0, 1]
    scored = [f for f in (2, 3, 4) if fractions[f] >= MIN_VISIBLE_FRACTION]
    assert scored == [2, 4]  # the view showing under 10% of the part has no target: it is not scored
    assert list(result.estimates["oracle"].frame) == scored
    assert result.summary()["methods"]["oracle"]["count"] == len(scored)


# --- two instances ---------------------------------------------------------------------------------


class _OracleOfOneInstance(OracleDescriptors):
    """The optimal descriptors of the instance at ``T_world_instance`` alone (the world of a BOP import is
    its first instance's frame) in every frame but the reference views (cameras ``reference_cameras``), where
    it shows the first instance, as the evaluation's reference views expect: a method that finds another
    instance than the first in the frames it is scored on."""

    def __init__(self, model, T_world_instance: np.ndarray, reference_cameras: list[np.ndarray]) -> None:
        super().__init__(model)
        self.T_world_instance = T_world_instance
        self.reference_cameras = reference_cameras

    def descriptor_image(self, obs, info=None):
        if any(np.allclose(info["T_world_camera"], T) for T in self.reference_cameras):
            return super().descriptor_image(obs, info)
        return super().descriptor_image(obs, dict(info, T_world_object=self.T_world_instance))


@pytest.fixture(scope="module")
def two_toolcaps(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """Two toolcaps side by side, seen from five directions, no mask files; the second's pose in the first's."""
    first = make_transform(translation=[0.0, -0.03, 0.02])
    second = make_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])[:3, :3], [0.0, 0.035, 0.02])
    views = []
    for k in range(5):
        angle = np.radians(-30.0 + 15.0 * k)
        eye = np.array([0.17 * np.cos(angle), 0.17 * np.sin(angle), 0.12])
        T_camera_world = invert_transform(look_at(eye, np.array([0.0, 0.0, 0.02])))
        views.append([(1, T_camera_world @ first), (1, T_camera_world @ second)])
    root = tmp_path_factory.mktemp("bop_two") / "bop"
    _write_scene(root, views, with_masks=False)
    out = root.parent / "data"
    import_bop(root, "test", 1, out)
    return out, invert_transform(first) @ second


def test_an_estimate_is_scored_against_the_instance_it_found(two_toolcaps) -> None:
    out, T_first_second = two_toolcaps
    data = DONDataset(out)
    assert [i["instance_id"] for i in data.scenes[0].instances] == [1, 2]
    first = evaluate_pose(out, ["oracle"], depths=("ideal",), progress=False)["ideal"]
    references = [data.scenes[0].T_world_camera[f] for f in first.reference["frames"]]
    second = _OracleOfOneInstance(data.object_model(), T_first_second, references)
    result = evaluate_pose(out, {"first": "oracle", "second": second}, depths=("ideal",), progress=False)["ideal"]
    diameter = result.diameter_m
    for name in ("first", "second"):
        e = result.estimates[name]
        assert len(e.frame) == 3 and e.found.all(), name
        # Each method finds its own instance: every error is measured against that one, and small.
        assert (e.mssd_m < 0.1 * diameter).all() and (e.adds_m < 0.1 * diameter).all(), (name, e.mssd_m, e.adds_m)
        assert (e.mspd_px < 5.0).all(), (name, e.mspd_px)
    # The two instances are apart: the second's estimates are far from the first instance's pose.
    first_T = np.stack([data.scenes[0].T_camera_object(int(f))[1] for f in result.estimates["second"].frame])
    offsets = np.linalg.norm(result.estimates["second"].T_camera_object[:, :3, 3] - first_T[:, :3, 3], axis=1)
    assert (offsets > 0.05).all()


# --- two parts ---------------------------------------------------------------------------------------


class _OracleAt(OracleDescriptors):
    """The part's optimal descriptors rendered at ``T_world_at`` (without the occlusion check) in every frame but
    the reference views (cameras ``reference_cameras``), where they are rendered at ``T_world_reference``."""

    def __init__(self, model, T_world_at, T_world_reference, reference_cameras) -> None:
        super().__init__(model, occlusion_check=False)
        self.T_world_at, self.T_world_reference, self.reference_cameras = (
            T_world_at,
            T_world_reference,
            reference_cameras,
        )

    def descriptor_image(self, obs, info=None):
        reference = any(np.allclose(info["T_world_camera"], T) for T in self.reference_cameras)
        return super().descriptor_image(
            obs, dict(info, T_world_object=self.T_world_reference if reference else self.T_world_at)
        )


def test_an_estimate_on_another_parts_instance_is_not_a_pose_of_the_part(tmp_path: Path) -> None:
    from don_gym.data.bin_dataset import build_bin_dataset
    from don_gym.data.build import DatasetConfig

    config = DatasetConfig(scenes=1, frames_per_scene=4, image_size=(96, 72), seed=17, sensor="ideal")
    build_bin_dataset(config, {"toolcap": 1, "shaft": 1}, tmp_path / "bin", progress=False)
    data = DONDataset(tmp_path / "bin")
    record = data.scenes[0]
    poses = {i["part"]: np.asarray(i["T_world_object"]) for i in record.instances}
    first = evaluate_pose(data, ["oracle"], depths=("none",), progress=False)["none"]
    references = [record.T_world_camera[f] for f in first.reference["frames"]]
    methods = {
        "on the toolcap": _OracleAt(data.object_model(), poses["toolcap"], poses["toolcap"], references),
        "on the shaft": _OracleAt(data.object_model(), poses["shaft"], poses["toolcap"], references),
    }
    result = evaluate_pose(data, methods, depths=("none",), progress=False)["none"]
    diameter = result.diameter_m
    on_part, on_other = result.estimates["on the toolcap"], result.estimates["on the shaft"]
    assert on_part.found.all() and on_other.found.all()
    assert (on_part.mssd_m < 0.1 * diameter).all()
    # The estimate does sit on the shaft's instance, but the shaft is another part: no target of the toolcap's.
    shaft_camera = np.stack([np.linalg.inv(record.T_world_camera[f]) @ poses["shaft"] for f in on_other.frame])
    assert (np.linalg.norm(on_other.T_camera_object[:, :3, 3] - shaft_camera[:, :3, 3], axis=1) < 0.01).all()
    assert (on_other.mssd_m > 0.3 * diameter).all(), on_other.mssd_m


def test_pooled_datasets_keep_their_scenes_apart_in_the_results(hidden_scene, two_toolcaps, tmp_path: Path) -> None:
    from don_gym.evaluation.pose_evaluation import SCENE_ID_STRIDE, write_pose_outputs

    result = evaluate_pose([hidden_scene[0], two_toolcaps[0]], ["oracle"], depths=("ideal",), progress=False)["ideal"]
    e = result.estimates["oracle"]
    assert set(e.dataset) == {0, 1}
    np.testing.assert_array_equal(e.scene_id, SCENE_ID_STRIDE * e.dataset + e.scene)
    paths = write_pose_outputs(result, tmp_path)
    rows = bop.read_pose_results(paths["csv:oracle"])
    assert {(r["scene_id"], r["im_id"]) for r in rows} == {
        (int(s), int(f)) for s, f, ok in zip(e.scene_id, e.frame, e.found, strict=True) if ok
    }
    assert len({r["scene_id"] for r in rows}) == 2
