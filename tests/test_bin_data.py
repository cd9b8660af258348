"""Datasets of bins (issue 33): piles of several parts written in format v2, one network trained on all the
parts, loaded for each of them, and the tracking protocol per part on the piles."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from don_gym.cli import main
from don_gym.data.bin_dataset import (
    PART_FIELDS_DIR,
    PART_SPACE_FILE,
    BinTargets,
    build_bin_dataset,
    instance_parts,
    load_part_space,
)
from don_gym.data.build import DatasetConfig
from don_gym.data.dataset import DONDataset
from don_gym.errors import CheckpointError, DatasetError, DonGymError
from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking_per_part
from don_gym.geometry import invert_transform
from don_gym.learning.checkpoints import read_checkpoint_metadata
from don_gym.learning.torch_data import CorrespondencePairs
from don_gym.learning.train import TrainConfig, train
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import load_descriptor_source

CONFIG = DatasetConfig(scenes=2, frames_per_scene=3, image_size=(64, 48), seed=17)
PARTS = {"toolcap": 2, "shaft": 1}
#: Descriptors are stored as 16-bit PNG: within this of the rendered value.
QUANTUM = 1.0 / 65535.0


@pytest.fixture(scope="module")
def bin_data(tmp_path_factory) -> DONDataset:
    out = tmp_path_factory.mktemp("bin") / "data"
    report = build_bin_dataset(CONFIG, PARTS, out, progress=False)
    assert (report.scenes_written, report.frames_written) == (2, 6)
    return DONDataset(out)


@pytest.fixture(scope="module")
def multi_part_net(bin_data, tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("run") / "edge"
    config = TrainConfig(
        method="supervised-edge", data=str(bin_data.root), out=str(out), steps=2, batch_size=2, crop_size=(64, 48),
        device="cpu", threads=1, checkpoint_every=100, part_layout="dataset",
    )  # fmt: skip
    train(config, progress=False)
    return str(out / "model.safetensors")


def test_bin_dataset_records_parts_instances_and_poses(bin_data):
    info = bin_data.info
    assert (info["version"], bin_data.scene_kind, info["bin_parts"]) == (2, "bin", PARTS)
    assert [p["name"] for p in bin_data.parts] == ["toolcap", "shaft"]
    assert (bin_data.root / PART_SPACE_FILE).is_file()
    assert sorted(p.name for p in (bin_data.root / PART_FIELDS_DIR).iterdir()) == ["shaft.npz", "toolcap.npz"]
    for record in bin_data.scenes:
        parts = instance_parts(record)
        assert sorted(parts.values()) == ["shaft", "toolcap", "toolcap"]
        assert sorted(parts) == [1, 2, 3]
        poses = {i["instance_id"]: i["T_world_object"] for i in record.instances}
        assert len({tuple(np.round(T[:3, 3], 4)) for T in poses.values()}) == 3  # three places in the bin
        for frame in range(record.num_frames):
            truth = record.T_camera_object(frame)
            assert sorted(truth) == [1, 2, 3]
            for k, T in truth.items():
                np.testing.assert_allclose(T, invert_transform(record.T_world_camera[frame]) @ poses[k], atol=1e-9)


def test_instance_images_agree_with_the_targets_of_each_part(bin_data):
    space = load_part_space(bin_data)
    seen = {"toolcap": 0, "shaft": 0}
    for s, record in enumerate(bin_data.scenes):
        parts = instance_parts(record)
        for f in range(record.num_frames):
            ids = bin_data.image(s, f, "instance")
            target_mask = bin_data.image(s, f, "target_mask")
            descriptor = bin_data.image(s, f, "descriptor")
            np.testing.assert_array_equal(bin_data.image(s, f, "mask"), ids > 0)
            assert not (target_mask & (ids == 0)).any()
            np.testing.assert_allclose(descriptor[~target_mask], np.broadcast_to(space.background, (
                int((~target_mask).sum()), space.dim)), atol=QUANTUM)  # fmt: skip
            for instance, part in parts.items():
                pixels = descriptor[target_mask & (ids == instance)]
                low, high = space.region_bounds(part)
                assert np.all((pixels >= low - QUANTUM) & (pixels <= high + QUANTUM)), (s, f, instance, part)
                seen[part] += len(pixels)
    assert min(seen.values()) > 20, seen
    # The regions, and so the two parts' targets, lie at least the space's gap apart.
    between, to_background = space.region_distances()
    assert between[0, 1] >= space.gap - 1e-9 and to_background.min() >= space.gap - 1e-9


def test_mask_variant_trains_in_a_space_with_the_mask_channel_left_out(bin_data):
    targets = BinTargets(bin_data, "mask")
    space = targets.space
    assert space.mask_dim == space.dim - 1 and space.names == ("toolcap", "shaft")
    target, mask = targets.frame(0, 0)
    ids = np.where(mask, bin_data.image(0, 0, "instance"), 0)
    for instance, part in instance_parts(bin_data.scenes[0]).items():
        pixels = target[ids == instance]
        low, high = space.region_bounds(part)
        assert np.all((pixels >= low - 1e-4) & (pixels <= high + 1e-4))
    np.testing.assert_allclose(target[~mask], np.broadcast_to(targets.background, target[~mask].shape), atol=1e-6)


@pytest.mark.parametrize(
    "parts, expected",
    [
        ("bolt:2", "'bolt' is neither a built-in part"),
        ("toolcap:-1", "count -1"),
        ("toolcap:40,shaft:30", "more parts"),
    ],
)
def test_bad_parts_are_refused_in_one_line(parts, expected, tmp_path, capsys):
    out = tmp_path / "data"
    argv = ["build-dataset", "--scene", "bin", "--parts", parts, "--scenes", "1", "--frames", "2", "--size", "64x48"]
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and "--parts" in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.fixture(scope="module")
def identity_net(bin_data, tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("run") / "identity"
    config = TrainConfig(
        method="supervised-edge", data=str(bin_data.root), out=str(out), steps=2, batch_size=2, crop_size=(64, 48),
        device="cpu", threads=1, checkpoint_every=100, part_layout="identity",
    )  # fmt: skip
    train(config, progress=False)
    return str(out / "model.safetensors")


def test_identity_layout_targets_keep_each_parts_whole_field(bin_data):
    stored = load_part_space(bin_data)
    targets = BinTargets(bin_data, "geometric", layout="identity")
    space = targets.space
    # "auto" is the identity layout for the supervised variants of several parts; "dataset" and the mask variant
    # keep the dataset's corners.
    auto = BinTargets(bin_data, "edge")
    assert (auto.layout, auto.space.layout, auto.space.dim) == ("identity", "identity", 4)
    assert BinTargets(bin_data, "edge", layout="dataset").space.layout == stored.layout == "corners"
    assert BinTargets(bin_data, "mask").space.layout == "corners"
    assert (space.layout, space.dim, space.field_dim, space.names) == ("identity", 4, 3, ("toolcap", "shaft"))
    target, mask = targets.frame(0, 0)
    assert target.shape == (48, 64, 4)
    ids = np.where(mask, bin_data.image(0, 0, "instance"), 0)
    descriptor = bin_data.image(0, 0, "descriptor")
    for instance, part in instance_parts(bin_data.scenes[0]).items():
        on = ids == instance
        k = space.index(part)
        np.testing.assert_array_equal(target[on][:, 3], np.float32((k + 1) / 2))
        # The first three dimensions are the part's own field: the stored target moved out of its region.
        own = np.clip(stored.own_descriptors(part, descriptor[on]), 0, 1)
        np.testing.assert_allclose(target[on][:, :3], own, atol=1e-6)
        assert stored.parts[k].scale < 0.5  # ... which the dataset's corners layout shrank
    np.testing.assert_array_equal(target[~mask], np.broadcast_to(space.background, target[~mask].shape))


def test_identity_layout_network_loads_for_either_part(bin_data, identity_net, multi_part_net, tmp_path):
    from don_gym.agents import BinAxisGraspAgent
    from don_gym.learning.checkpoints import checkpoint_part_space
    from don_gym.sim.bin_env import BinPickEnv

    metadata = read_checkpoint_metadata(identity_net)
    space = checkpoint_part_space(metadata)
    assert (metadata.descriptor_dim, space.layout, space.dim, space.field_dim) == (4, "identity", 4, 3)
    rgb = bin_data.image(0, 0, "rgb")
    for k, name in enumerate(("toolcap", "shaft")):
        part = load_object(name)
        source = load_descriptor_source(identity_net, part)
        assert source.descriptor_dim == 4 and source.descriptor_image({"rgb": rgb}).shape == (48, 64, 4)
        assert source.descriptor_scale == 1.0  # every part keeps its field at full scale
        descriptors = source.field.vertex_descriptors
        np.testing.assert_array_equal(descriptors[:, 3], np.float32((k + 1) / 2))
        np.testing.assert_allclose(descriptors[:, :3], load_descriptor_source("oracle", part).field.vertex_descriptors)
        env = BinPickEnv(parts=PARTS, target=name, image_size=(64, 48))
        try:
            obs, info = env.reset(seed=1)
            agent = BinAxisGraspAgent(env, model=identity_net)
            assert isinstance(agent.estimates(obs, info), list)  # runs on the 4-channel image (2 steps find none)
            corners = BinAxisGraspAgent(env, model=multi_part_net)
        finally:
            env.close()
        # The axis ends' reference descriptors: in the part's identity, as far apart as in its own field, which
        # is 1 / scale (2.3 for two parts in D = 3) times as far as in the dataset's corners layout.
        reference = agent.reference_descriptors
        assert reference.shape == (2, 4) and np.all(reference[:, 3] == np.float32((k + 1) / 2))
        ratio = np.linalg.norm(reference[0] - reference[1]) / np.linalg.norm(
            corners.reference_descriptors[0] - corners.reference_descriptors[1]
        )
        assert ratio == pytest.approx(1 / load_part_space(bin_data).parts[k].scale, rel=1e-4)
    out = tmp_path / "eval"
    argv = ["evaluate", "--data", str(bin_data.root), "--models", identity_net, "--points", "2", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    for name in ("toolcap", "shaft"):
        report = json.loads((out / name / "tracking.json").read_text())
        assert report["object"] == name and identity_net in report["methods"]


@pytest.mark.parametrize(
    "method, expected",
    [("supervised-mask", "does not support supervised-mask"), ("self-supervised", "is for the supervised methods")],
)
def test_part_layout_refusals_are_one_line(bin_data, tmp_path, capsys, method, expected):
    out = tmp_path / "run"
    argv = ["train", "--method", method, "--data", str(bin_data.root), "--out", str(out), "--part-layout", "identity"]
    assert main([*argv, "--steps", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert expected in err and len(err.splitlines()) == 1
    assert not out.exists()
    with pytest.raises(DatasetError, match="does not support the mask variant"):
        BinTargets(bin_data, "mask", layout="identity")
    config = TrainConfig(method="supervised-edge", data=str(bin_data.root), out=str(out), part_layout="corners")
    with pytest.raises(
        DonGymError, match=r"part_layout 'corners' is unknown; expected one of \['auto', 'identity', 'dataset'\]"
    ):
        train(config, progress=False)
    assert not out.exists()


def test_one_network_for_both_parts(bin_data, multi_part_net, tmp_path):
    metadata = read_checkpoint_metadata(multi_part_net)
    assert [p["name"] for p in metadata.part_space["parts"]] == ["toolcap", "shaft"]
    assert all(p["signature"] for p in metadata.part_space["parts"])
    space = load_part_space(bin_data)
    for name in ("toolcap", "shaft"):
        source = load_descriptor_source(multi_part_net, load_object(name))
        assert source.object_model.name == name
        # Reference descriptors come from the part's field in its own region of the space.
        low, high = space.region_bounds(name)
        descriptors = source.field.vertex_descriptors
        assert np.all((descriptors >= low - 1e-6) & (descriptors <= high + 1e-6))
        np.testing.assert_allclose(source.field.background, space.background, atol=1e-6)
        # Distance scales tuned on the part's own field (soft-match temperature) shrink with its region.
        assert source.descriptor_scale == pytest.approx(space.parts[space.index(name)].scale)
        assert 0.0 < source.descriptor_scale < 1.0
    assert load_descriptor_source("toolcap/supervised-edge", load_object("toolcap")).descriptor_scale == 1.0
    box = tmp_path / "bracket.stl"
    trimesh.creation.box((0.04, 0.02, 0.01)).export(box)
    with pytest.raises(CheckpointError) as refused:
        load_descriptor_source(multi_part_net, load_object(str(box)))
    message = str(refused.value)
    assert "'bracket'" in message and "['toolcap', 'shaft']" in message and "\n" not in message


def test_self_supervised_pairs_match_within_an_instance(bin_data, tmp_path):
    pairs = CorrespondencePairs(str(bin_data.root), seed=3)
    assert pairs.part_space is not None
    for i in range(3):
        item = pairs[i]
        scene, a, b = pairs._pick_pair(np.random.default_rng([3, i]))
        ids_a, ids_b = bin_data.image(scene, a, "instance"), bin_data.image(scene, b, "instance")
        parts = {0: ""} | instance_parts(bin_data.scenes[scene])
        c = item["correspondences"]
        assert c.num_matches > 0
        match_a = ids_a[c.matches_a[:, 1], c.matches_a[:, 0]]
        np.testing.assert_array_equal(match_a, ids_b[c.matches_b[:, 1], c.matches_b[:, 0]])
        assert (match_a > 0).all()
        owner = ids_a[c.nonmatches_object_a[:, 1], c.nonmatches_object_a[:, 0]]
        other = ids_b[c.nonmatches_object_b[:, 1], c.nonmatches_object_b[:, 0]]
        same_part_other_instance = [
            parts[int(x)] == parts[int(y)] and x != y and x > 0 and y > 0 for x, y in zip(owner, other, strict=True)
        ]
        assert not any(same_part_other_instance)
    out = tmp_path / "ss"
    config = TrainConfig(
        method="self-supervised", data=str(bin_data.root), out=str(out), steps=1, batch_size=2, crop_size=(64, 48),
        device="cpu", threads=1,
    )  # fmt: skip
    train(config, progress=False)
    assert [p["name"] for p in read_checkpoint_metadata(out / "model.safetensors").part_space["parts"]] == [
        "toolcap",
        "shaft",
    ]


def test_evaluate_tracks_each_part_among_the_instances(bin_data, multi_part_net, tmp_path, capsys):
    results = evaluate_tracking_per_part(
        bin_data, ["oracle", multi_part_net], TrackingConfig(points_per_scene=4), progress=False
    )
    assert list(results) == ["toolcap", "shaft"]
    for part, result in results.items():
        summary = result.summary()
        assert summary["object"] == part and set(summary["methods"]) == {"oracle", multi_part_net}
        instances = [scene["instance_id"] for scene in summary["scene_list"]]
        assert len(instances) == 2 * PARTS[part]
        assert result.matches["oracle"].error_3d_m.size > 0
    # The oracle renders every shaft: its matches land on the shaft seen (here the only one), within millimetres.
    assert np.median(results["shaft"].matches["oracle"].symmetric_error_m) < 0.005
    # Searched on the reference's own instance only, the oracle finds the toolcaps' points too.
    within = evaluate_tracking_per_part(
        bin_data, ["oracle"], TrackingConfig(points_per_scene=4, match_within="instance"), progress=False
    )
    assert np.median(within["toolcap"].matches["oracle"].symmetric_error_m) < 0.005
    # Searched in the whole image, the oracle lands on the same point of the other toolcap as often as on the
    # reference's: far off by the reference instance, within millimetres of the nearest instance's point.
    toolcap = results["toolcap"].matches["oracle"]
    assert np.nanmax(toolcap.symmetric_error_m) > 0.05
    assert np.percentile(toolcap.symmetric_error_any_instance_m, 90) < 0.004
    assert (toolcap.error_3d_any_instance_m <= toolcap.error_3d_m).all()
    toolcap_summary = results["toolcap"].summary()["methods"]["oracle"]
    assert toolcap_summary["tail_any_instance"]["far_matches"] == 0
    assert toolcap_summary["intervals"]["error_3d_symmetric_any_instance_mm"]["p50"][1] < 4.0
    # One shaft per pile: the nearest instance is the reference, the errors are the same.
    shaft = results["shaft"].matches["oracle"]
    np.testing.assert_array_equal(shaft.error_3d_any_instance_m, shaft.error_3d_m)
    np.testing.assert_array_equal(shaft.symmetric_error_any_instance_m, shaft.symmetric_error_m)
    out = tmp_path / "eval"
    argv = ["evaluate", "--data", str(bin_data.root), "--models", "oracle", multi_part_net, "--points", "2"]
    assert main([*argv, "--no-progress", "--out", str(out)]) == 0
    assert "## part toolcap" in capsys.readouterr().out
    assert json.loads((out / "shaft" / "tracking.json").read_text())["object"] == "shaft"
    # Far matches on the pile's other instances have a category of their own.
    report = (out / "toolcap" / "tracking.md").read_text()
    assert "another instance" in report
    assert "3D error mod symmetry, any instance p50 / p90 (mm)" in report and "| oracle, any instance |" in report
