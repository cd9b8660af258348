"""Bring your own CAD: a mesh file goes through embed, build-dataset, train, evaluate, benchmark grasp and the
wrappers under one name (the file stem) and one identity (its geometry), at tiny sizes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import trimesh

from don_gym.cli import main
from don_gym.cli.benchmark import default_methods
from don_gym.errors import CheckpointError
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import load_descriptor_source
from don_gym.wrappers import DescriptorObservation, KeypointObservation
from don_gym.zoo import read_don_metadata

torch.set_num_threads(1)


def _write_part(path: Path) -> Path:
    """A stepped pin, 40 mm long, 24 mm and 16 mm across: one end unlike the other."""
    profile = np.array([[0.0, 0.0], [0.012, 0.0], [0.012, 0.015], [0.008, 0.015], [0.008, 0.04], [0.0, 0.04]])
    mesh = trimesh.creation.revolve(profile[::-1], sections=20).subdivide()
    mesh.merge_vertices()
    if mesh.volume < 0:
        mesh.invert()
    mesh.export(path)
    return path


@pytest.fixture(scope="module")
def own_part(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("own_part")
    stl = _write_part(root / "my_part.stl")
    data, run = root / "data", root / "run"
    assert main(["embed", str(stl), "--out", str(root / "field.npz")]) == 0
    assert (
        main(
            ["build-dataset", "--object", str(stl), "--scenes", "1", "--frames", "3", "--size", "64x48"]
            + ["--out", str(data), "--workers", "1"]
        )
        == 0
    )
    assert (
        main(
            ["train", "--method", "supervised-edge", "--data", str(data), "--out", str(run), "--steps", "3"]
            + ["--batch-size", "2", "--crop", "none", "--checkpoint-every", "3"]
        )
        == 0
    )
    return {"root": root, "stl": stl, "data": data, "run": run}


def test_one_name_everywhere_and_the_checkpoint_carries_part_and_field(own_part) -> None:
    info = json.loads((own_part["data"] / "dataset.json").read_text())
    assert info["object_name"] == "my_part" and info["object_signature"]["n_vertices"] > 0
    metadata = read_don_metadata(own_part["run"])
    assert metadata.object_name == "my_part"
    assert metadata.object_signature == load_object(own_part["stl"]).shape_signature.to_dict()
    assert metadata.descriptor_field["dim"] == 3
    source = load_descriptor_source(own_part["run"], load_object(own_part["stl"]))
    assert source.reference_from_field


def test_evaluate_and_benchmark_grasp_take_the_own_part_network(own_part) -> None:
    out = own_part["root"] / "evaluation"
    args = ["evaluate", "--data", str(own_part["data"]), "--models", "oracle", str(own_part["run"])]
    assert main([*args, "--points", "4", "--out", str(out), "--no-progress"]) == 0
    assert set(json.loads((out / "tracking.json").read_text())["methods"]) == {"oracle", str(own_part["run"])}
    bench = own_part["root"] / "bench"
    args = ["benchmark", "grasp", "--object", str(own_part["stl"]), "--methods", "oracle", str(own_part["run"])]
    args += ["--poses", "0", "--repeats", "1", "--sensors", "ideal", "--workers", "1", "--no-progress"]
    assert main([*args, "--out", str(bench)]) == 0
    episodes = json.loads((bench / "grasp_episodes.json").read_text())["episodes"]
    assert sorted(e["method"] for e in episodes) == sorted(["oracle", str(own_part["run"])])
    # Without --methods: no shipped network was trained on this part, so the oracle alone.
    assert default_methods(load_object(own_part["stl"])) == ["oracle"]


def test_wrappers_accept_the_part_under_any_file_name_and_refuse_another_shape(own_part) -> None:
    renamed = shutil.copyfile(own_part["stl"], own_part["root"] / "pin_v2.stl")
    env = gym.make("DONPick-v0", object=str(renamed), image_size=(64, 48))
    try:
        wrapped = KeypointObservation(env, model=str(own_part["run"]))
        assert wrapped.source.reference_from_field
        obs, _ = wrapped.reset(seed=0)
        assert obs["descriptors"].shape == (48, 64, 3) and obs["keypoint_points"].shape == (2, 3)
    finally:
        env.close()
    (own_part["root"] / "box").mkdir()
    box = own_part["root"] / "box" / "my_part.stl"  # same name, another shape
    trimesh.creation.box((0.024, 0.024, 0.04)).export(box)
    box_env = gym.make("DONPick-v0", object=str(box), image_size=(64, 48))
    try:
        with pytest.raises(CheckpointError, match="trained on part 'my_part', but part 'my_part' .*another shape"):
            DescriptorObservation(box_env, model=str(own_part["run"]))
    finally:
        box_env.close()
