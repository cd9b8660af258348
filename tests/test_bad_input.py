"""Bad inputs, table-driven: every one is refused with a message naming it, before any work.

Through the command line (``don_gym.cli.main`` in-process): exactly one line on stderr, a non-zero
exit, no traceback. Through the Python API: a :class:`~don_gym.errors.DonGymError`. Cases marked
``before_work`` replace the command's computation with a function that fails the test, so they
show that a bad output is refused before the work, not after it. Faults of the file system (a
read-only or full disk) and Ctrl-C are tested after the table. docs/reliability.md cites the number
of cases (:data:`BAD_INPUTS`); ``test_the_docs_cite_the_number_of_cases`` keeps it true.
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

import don_gym  # noqa: F401 - registers the envs
from don_gym.cli import error_line, main
from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.data.dataset import DONDataset
from don_gym.descriptors import embed
from don_gym.errors import DonGymError
from don_gym.evaluation.grasp_benchmark import GraspBenchmarkConfig, run_grasp_benchmark
from don_gym.evaluation.grasp_report import write_grasp_outputs
from don_gym.evaluation.report import write_tracking_outputs
from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking
from don_gym.io import check_output_dir, check_output_file
from don_gym.learning.checkpoints import save_checkpoint
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import load_descriptor_source
from don_gym.zoo import load_don

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------- the CLI table
@dataclass(frozen=True)
class Cli:
    """``argv`` (``{name}`` fields filled from the workspace) must fail in one line containing ``says``."""

    argv: tuple[str, ...]
    says: str
    #: ``module:function`` doing the command's work; the case fails if it is called.
    before_work: str | None = None


def cli(*argv: str, says: str, before_work: str | None = None) -> Cli:
    return Cli(tuple(argv), says, before_work)


EVAL = ("evaluate", "--data", "{data}", "--no-progress")
GRASP = ("benchmark", "grasp", "--no-progress", "--workers", "1", "--image-size", "64x48")
BUILD = ("build-dataset", "--out", "{tmp}/new_data")
TRAIN = ("train", "--method", "supervised", "--data", "{data}", "--crop", "none")
SELF_SUPERVISED = ("train", "--method", "self-supervised", "--data", "{data}")
EVAL_WORK = "don_gym.evaluation.tracking:evaluate_tracking"
GRASP_WORK = "don_gym.evaluation.grasp_benchmark:run_grasp_benchmark"
EMBED_WORK = "don_gym.descriptors:embed"

CLI_CASES: dict[str, Cli] = {
    # embed
    "embed missing mesh": cli("embed", "{tmp}/missing.stl", says="missing.stl"),
    "embed directory as mesh": cli("embed", "{folder}", says="is a directory"),
    "embed wrong extension": cli("embed", "{tmp}/part.txt", says="part.txt"),
    "embed unreadable mesh": cli("embed", "{tmp}/part.stl", says="part.stl"),
    "embed unknown name": cli("embed", "teapot", says="'teapot'"),
    "embed dim 0": cli("embed", "toolcap", "--dim", "0", says="dim=0"),
    "embed dim not a number": cli("embed", "toolcap", "--dim", "two", says="--dim"),
    "embed scale NaN": cli("embed", "toolcap", "--scale", "nan", says="scale=nan"),
    "embed scale inf": cli("embed", "toolcap", "--scale", "inf", says="scale=inf"),
    "embed scale negative": cli("embed", "toolcap", "--scale", "-2", says="scale=-2"),
    "embed tolerance NaN": cli("embed", "toolcap", "--tolerance", "nan", says="tolerance=nan"),
    "embed unknown method": cli("embed", "toolcap", "--method", "fast", says="--method"),
    "embed --out not .npz": cli("embed", "toolcap", "--out", "{tmp}/field.txt", says=".npz", before_work=EMBED_WORK),
    "embed --out a directory": cli(
        "embed", "toolcap", "--out", "{tmp}/field.npz", says="is a directory", before_work=EMBED_WORK
    ),
    "embed --out under a file": cli(
        "embed", "toolcap", "--out", "{file}/field.npz", says="file.txt", before_work=EMBED_WORK
    ),
    "embed --plot unknown format": cli(
        "embed", "toolcap", "--plot", "{tmp}/picture.bmp", says=".png", before_work=EMBED_WORK
    ),
    "embed --plot under a file": cli(
        "embed", "toolcap", "--plot", "{file}/picture.png", says="file.txt", before_work=EMBED_WORK
    ),
    # evaluate
    "evaluate missing data": cli("evaluate", "--data", "{tmp}/missing", "--out", "{tmp}/o", says="missing"),
    "evaluate data is a file": cli("evaluate", "--data", "{file}", "--out", "{tmp}/o", says="file.txt"),
    "evaluate data is an empty directory": cli("evaluate", "--data", "{folder}", "--out", "{tmp}/o", says="folder"),
    "evaluate points 0": cli(*EVAL, "--out", "{tmp}/o", "--points", "0", says="points_per_scene=0"),
    "evaluate points negative": cli(*EVAL, "--out", "{tmp}/o", "--points", "-3", says="points_per_scene=-3"),
    "evaluate points not an integer": cli(*EVAL, "--out", "{tmp}/o", "--points", "2.5", says="--points"),
    "evaluate tolerance NaN": cli(
        *EVAL, "--out", "{tmp}/o", "--visibility-tolerance-mm", "nan", says="visibility_tolerance_m=nan"
    ),
    "evaluate tolerance inf": cli(
        *EVAL, "--out", "{tmp}/o", "--visibility-tolerance-mm", "inf", says="visibility_tolerance_m=inf"
    ),
    "evaluate tolerance negative": cli(
        *EVAL, "--out", "{tmp}/o", "--visibility-tolerance-mm", "-4", says="visibility_tolerance_m=-0.004"
    ),
    "evaluate max scenes 0": cli(*EVAL, "--out", "{tmp}/o", "--max-scenes", "0", says="max_scenes=0"),
    "evaluate threads 0": cli(*EVAL, "--out", "{tmp}/o", "--threads", "0", says="--threads 0"),
    "evaluate seed negative": cli(*EVAL, "--out", "{tmp}/o", "--seed", "-1", says="seed=-1"),
    "evaluate border margin negative": cli(
        *EVAL, "--out", "{tmp}/o", "--border-margin", "-1", says="border_margin_px=-1"
    ),
    "evaluate border margin wider than the frame": cli(
        *EVAL, "--out", "{tmp}/o", "--border-margin", "5000", says="border_margin_px=5000"
    ),
    "evaluate unknown depth": cli(*EVAL, "--out", "{tmp}/o", "--depth", "fused", says="--depth"),
    "evaluate unknown network": cli(*EVAL, "--out", "{tmp}/o", "--models", "toolcap/nonsense", says="nonsense"),
    "evaluate missing checkpoint": cli(
        *EVAL, "--out", "{tmp}/o", "--models", "{tmp}/net.safetensors", says="net.safetensors"
    ),
    "evaluate network of another object": cli(*EVAL, "--out", "{tmp}/o", "--models", "{shaft_net}", says="shaft"),
    "evaluate a method twice": cli(*EVAL, "--out", "{tmp}/o", "--models", "oracle", "oracle", says="once"),
    "evaluate --out an existing file": cli(*EVAL, "--out", "{file}", says="file.txt", before_work=EVAL_WORK),
    "evaluate --out under a file": cli(*EVAL, "--out", "{file}/eval", says="file.txt", before_work=EVAL_WORK),
    # benchmark grasp
    "grasp --out an existing file": cli(*GRASP, "--out", "{file}", says="file.txt", before_work=GRASP_WORK),
    "grasp --out under a file": cli(*GRASP, "--out", "{file}/bench", says="file.txt", before_work=GRASP_WORK),
    "grasp pose 8": cli(*GRASP, "--poses", "8", says="pose ids 0..7"),
    "grasp pose negative": cli(*GRASP, "--poses", "-1", says="poses [-1]"),
    "grasp pose not an integer": cli(*GRASP, "--poses", "x", says="--poses"),
    "grasp repeats 0": cli(*GRASP, "--repeats", "0", says="repeats=0"),
    "grasp workers 0": cli("benchmark", "grasp", "--workers", "0", says="--workers 0"),
    "grasp unknown sensor": cli(*GRASP, "--sensors", "lidar", says="'lidar'"),
    "grasp severity out of range": cli(*GRASP, "--sensors", "d435@2", says="sensor 'd435@2'"),
    "grasp severity NaN": cli(*GRASP, "--sensors", "d435@nan", says="sensor 'd435@nan'"),
    "grasp image size 0x0": cli("benchmark", "grasp", "--image-size", "0x0", says="--image-size '0x0'"),
    "grasp image size malformed": cli("benchmark", "grasp", "--image-size", "big", says="--image-size 'big'"),
    "grasp unknown renderer": cli(*GRASP, "--renderer", "vulkan", says="renderer='vulkan'"),
    "grasp unknown backgrounds": cli(*GRASP, "--methods", "oracle", "--backgrounds", "wood", says="backgrounds='wood'"),
    "grasp unknown object": cli(*GRASP, "--object", "teapot", "--methods", "oracle", says="'teapot'"),
    "grasp unknown network": cli(*GRASP, "--methods", "toolcap/nonsense", says="nonsense"),
    "grasp seed negative": cli(*GRASP, "--methods", "oracle", "--seed", "-1", says="seed=-1"),
    "grasp a method twice": cli(*GRASP, "--methods", "oracle", "oracle", says="once"),
    # export
    "export missing data": cli("export", "{tmp}/missing", "--out", "{tmp}/pdc", says="missing"),
    "export scene out of range": cli("export", "{data}", "--scene", "5", "--out", "{tmp}/pdc", says="--scene 5"),
    "export scene negative": cli("export", "{data}", "--scene", "-1", "--out", "{tmp}/pdc", says="--scene -1"),
    "export unknown format": cli("export", "{data}", "--format", "ros", "--out", "{tmp}/pdc", says="--format"),
    "export --out an existing file": cli(
        "export", "{data}", "--out", "{file}", says="file.txt", before_work="don_gym.data.export:export_scene_pdc"
    ),
    # build-dataset
    "build workers 0": cli(*BUILD, "--workers", "0", says="--workers"),
    "build scenes 0": cli(*BUILD, "--scenes", "0", says="--scenes"),
    "build frames 1": cli(*BUILD, "--frames", "1", says="--frames"),
    "build size 0x0": cli(*BUILD, "--size", "0x0", says="--size"),
    "build distractors negative": cli(*BUILD, "--distractors", "-1", says="--distractors"),
    "build unknown sensor": cli(*BUILD, "--sensor", "lidar", says="'lidar'"),
    "build missing mesh": cli(*BUILD, "--object", "{tmp}/missing.stl", says="missing.stl"),
    "build object scale NaN": cli(*BUILD, "--object-scale", "nan", says="--object-scale"),
    "build shard out of range": cli(*BUILD, "--shard", "2/2", says="2/2"),
    "build dim 0": cli(*BUILD, "--dim", "0", says="--dim"),
    "build seed negative": cli(*BUILD, "--seed", "-1", says="--seed"),
    "build --out an existing file": cli("build-dataset", "--out", "{file}", says="file.txt"),
    # train
    "train batch size 0": cli(*TRAIN, "--out", "{tmp}/run", "--batch-size", "0", says="batch_size"),
    "train checkpoint every 0": cli(*TRAIN, "--out", "{tmp}/run", "--checkpoint-every", "0", says="checkpoint_every"),
    "train pattern backgrounds above 1": cli(
        *TRAIN, "--out", "{tmp}/run", "--pattern-backgrounds", "1.5", says="pattern_probability"
    ),
    "train pattern backgrounds NaN": cli(*TRAIN, "--out", "{tmp}/run", "--pattern-backgrounds", "nan", says="pattern"),
    "train threads 0": cli(*TRAIN, "--out", "{tmp}/run", "--threads", "0", says="threads"),
    "train lr NaN": cli(*TRAIN, "--out", "{tmp}/run", "--lr", "nan", says="lr"),
    "train lr negative": cli(*TRAIN, "--out", "{tmp}/run", "--lr", "-1", says="lr"),
    "train steps 0": cli(*TRAIN, "--out", "{tmp}/run", "--steps", "0", says="steps"),
    "train device tpu": cli(*TRAIN, "--out", "{tmp}/run", "--device", "tpu", says="tpu"),
    "train workers negative": cli(*TRAIN, "--out", "{tmp}/run", "--workers", "-1", says="workers"),
    "train crop 0x0": cli(*TRAIN, "--out", "{tmp}/run", "--crop", "0x0", says="--crop"),
    "train background crops 1.5": cli(
        *TRAIN, "--out", "{tmp}/run", "--background-crops", "1.5", says="background_crop_probability"
    ),
    "train unknown arch": cli(*TRAIN, "--out", "{tmp}/run", "--arch", "resnet1000", says="resnet1000"),
    "train unknown method": cli("train", "--method", "magic", "--data", "{data}", "--out", "{tmp}/run", says="magic"),
    "train missing data": cli(
        "train", "--method", "supervised", "--data", "{tmp}/missing", "--out", "{tmp}/run", says="missing"
    ),
    "train missing pretrained weights": cli(
        *TRAIN, "--out", "{tmp}/run", "--arch", "resnet18", "--pretrained", "{tmp}/imagenet.pt", says="imagenet.pt"
    ),
    "train --out an existing file": cli(
        *TRAIN, "--out", "{file}", says="file.txt", before_work="don_gym.learning.train:train"
    ),
    "train self-supervised on data built with --no-fusion": cli(
        *SELF_SUPERVISED, "--out", "{tmp}/run", says="--no-fusion", before_work="don_gym.learning.train:_train"
    ),
    "train resume from a corrupt train_state.pt": cli(
        *TRAIN, "--out", "{corrupt_run}", "--steps", "2", "--resume", says="train_state.pt"
    ),
    # the command line itself
    "no command": cli(says="COMMAND"),
    "unknown command": cli("fly", says="'fly'"),
}


# ---------------------------------------------------------------------------------------- the API table
@dataclass(frozen=True)
class Api:
    """``call(workspace)`` must raise a DonGymError whose message contains ``says``."""

    call: Callable[[Workspace], Any]
    says: str


def make(**kwargs: Any) -> Callable[[Workspace], Any]:
    return lambda ws: gym.make("DONPick-v0", **({"object": "toolcap"} | kwargs))


TOOLCAP = "toolcap"
API_CASES: dict[str, Api] = {
    # the env's arguments
    "env max_steps 'a'": Api(make(max_steps="a"), "max_steps='a'"),
    "env max_steps 0": Api(make(max_steps=0), "max_steps=0"),
    "env max_steps 2.5": Api(make(max_steps=2.5), "max_steps=2.5"),
    "env image_size (0, 0)": Api(make(image_size=(0, 0)), "image_size=(0, 0)"),
    "env image_size a string": Api(make(image_size="160x120"), "image_size='160x120'"),
    "env image_size not integers": Api(make(image_size=(160.5, 120)), "image_size=(160.5, 120)"),
    "env image_size three numbers": Api(make(image_size=(160, 120, 3)), "image_size=(160, 120, 3)"),
    "env render_size None": Api(make(render_size=None), "render_size=None"),
    "env sensor a number": Api(make(sensor=3), "depth sensor 3"),
    "env unknown sensor": Api(make(sensor="lidar"), "'lidar'"),
    "env unknown renderer": Api(make(renderer="vulkan"), "renderer='vulkan'"),
    "env renderer a list": Api(make(renderer=["tiny"]), "renderer=['tiny']"),
    "env unknown control": Api(make(control="joints"), "control='joints'"),
    "env control None": Api(make(control=None), "control=None"),
    "env reward_type a number": Api(make(reward_type=1), "reward_type=1"),
    "env unknown background": Api(make(background="wood"), "background='wood'"),
    "env render_mode ansi": Api(make(render_mode="ansi"), "render_mode='ansi'"),
    "env observe_images a string": Api(make(observe_images="no"), "observe_images='no'"),
    "env object a number": Api(make(object=3), "object=3"),
    "env object missing": Api(lambda ws: make(object=str(ws.tmp / "missing.stl"))(ws), "missing.stl"),
    "env object_scale 'a'": Api(make(object_scale="a"), "object_scale='a'"),
    "env object_scale NaN": Api(make(object_scale=math.nan), "object_scale=nan"),
    "env object_scale 0": Api(make(object_scale=0), "object_scale=0"),
    # step and reset
    "step strings": Api(lambda ws: ws.env.step(["a", "b", "c", "d"]), "action ['a', 'b', 'c', 'd']"),
    "step a dict": Api(lambda ws: ws.env.step({"x": 1}), "action {'x': 1}"),
    "step NaN": Api(lambda ws: ws.env.step([0.5, 0.0, math.nan, 0.0]), "NaN"),
    "step wrong shape": Api(lambda ws: ws.env.step(np.zeros(3)), "shape (3,)"),
    "reset options a list": Api(lambda ws: ws.env.reset(options=[1, 2]), "options=[1, 2]"),
    "reset pose_id 8": Api(lambda ws: ws.env.reset(options={"pose_id": 8}), "pose_id']=8"),
    "reset pose_id a string": Api(lambda ws: ws.env.reset(options={"pose_id": "3"}), "pose_id']='3'"),
    "reset pose_id a float": Api(lambda ws: ws.env.reset(options={"pose_id": 2.0}), "pose_id']=2.0"),
    "reset unknown option": Api(lambda ws: ws.env.reset(options={"pose": 3}), "['pose']"),
    "reset seed negative": Api(lambda ws: ws.env.reset(seed=-1), "seed=-1"),
    "reset seed a string": Api(lambda ws: ws.env.reset(seed="a"), "seed='a'"),
    # objects and descriptors
    "load_object missing": Api(lambda ws: load_object(ws.tmp / "missing.stl"), "missing.stl"),
    "load_object a directory": Api(lambda ws: load_object(ws.folder), "is a directory"),
    "load_object unreadable": Api(lambda ws: load_object(ws.tmp / "part.stl"), "part.stl"),
    "load_object scale 0": Api(lambda ws: load_object(TOOLCAP, scale=0), "scale=0"),
    "load_object scale NaN": Api(lambda ws: load_object(TOOLCAP, scale=math.nan), "scale=nan"),
    "load_object unknown material": Api(lambda ws: load_object(TOOLCAP, material="gold"), "'gold'"),
    "embed dim 0": Api(lambda ws: embed(load_object(TOOLCAP), 0), "dim=0"),
    "embed dim a string": Api(lambda ws: embed(load_object(TOOLCAP), "3"), "dim='3'"),
    "embed tolerance NaN": Api(lambda ws: embed(load_object(TOOLCAP), tolerance=math.nan), "tolerance=nan"),
    "embed unknown method": Api(lambda ws: embed(load_object(TOOLCAP), method="fast"), "method='fast'"),
    "embed unknown components": Api(lambda ws: embed(load_object(TOOLCAP), components="all"), "components='all'"),
    "embed dim negative": Api(lambda ws: embed(load_object(TOOLCAP), -2), "dim=-2"),
    "embed tolerance a string": Api(lambda ws: embed(load_object(TOOLCAP), tolerance="a"), "tolerance='a'"),
    "embed tolerance None": Api(lambda ws: embed(load_object(TOOLCAP), tolerance=None), "tolerance=None"),
    "embed symmetric a string": Api(lambda ws: embed(load_object(TOOLCAP), symmetric="yes"), "symmetric='yes'"),
    "embed method a number": Api(lambda ws: embed(load_object(TOOLCAP), method=3), "method=3"),
    "embed components None": Api(lambda ws: embed(load_object(TOOLCAP), components=None), "components=None"),
    "embed a name instead of a mesh": Api(lambda ws: embed(TOOLCAP), "got str"),
    # networks
    "load_don missing": Api(lambda ws: load_don(ws.tmp / "net.safetensors"), "net.safetensors"),
    "load_don unreadable": Api(lambda ws: load_don(ws.file), "file.txt"),
    "load_don a directory without a model": Api(lambda ws: load_don(ws.folder), "folder"),
    "load_don unknown name": Api(lambda ws: load_don("toolcap/nonsense"), "nonsense"),
    "load_don another object": Api(lambda ws: load_don(ws.shaft_net, expect_object="toolcap"), "shaft"),
    "descriptor source unknown": Api(lambda ws: load_descriptor_source("magic", load_object(TOOLCAP)), "'magic'"),
    "descriptor source another object": Api(
        lambda ws: load_descriptor_source(str(ws.shaft_net), load_object(TOOLCAP)), "shaft"
    ),
    # evaluation and the grasp benchmark
    "tracking points 0": Api(lambda ws: TrackingConfig(points_per_scene=0).validate(), "points_per_scene=0"),
    "tracking tolerance inf": Api(
        lambda ws: TrackingConfig(visibility_tolerance_m=math.inf).validate(), "visibility_tolerance_m=inf"
    ),
    "tracking seed negative": Api(lambda ws: TrackingConfig(seed=-1).validate(), "seed=-1"),
    "tracking unknown depth": Api(lambda ws: TrackingConfig(depth="fused").validate(), "depth='fused'"),
    "evaluate no methods": Api(lambda ws: evaluate_tracking(ws.data, [], progress=False), "no methods"),
    "evaluate missing dataset": Api(lambda ws: evaluate_tracking(ws.tmp / "missing", ["oracle"]), "missing"),
    "grasp config pose 8": Api(lambda ws: GraspBenchmarkConfig(poses=(8,)).validate(), "pose ids 0..7"),
    "grasp config seed negative": Api(lambda ws: GraspBenchmarkConfig(seed=-1).validate(), "seed=-1"),
    "grasp config severity NaN": Api(lambda ws: GraspBenchmarkConfig(sensors=("d435@nan",)).validate(), "'d435@nan'"),
    "grasp config image size 0x0": Api(lambda ws: GraspBenchmarkConfig(image_size=(0, 0)).validate(), "0x0"),
    "grasp config image size a string": Api(
        lambda ws: GraspBenchmarkConfig(image_size="64x48").validate(), "image_size='64x48'"
    ),
    "grasp workers 0": Api(lambda ws: run_grasp_benchmark(GraspBenchmarkConfig(), workers=0), "workers=0"),
    # datasets and outputs
    "dataset missing": Api(lambda ws: DONDataset(ws.tmp / "missing"), "missing"),
    "dataset a file": Api(lambda ws: DONDataset(ws.file), "file.txt: is a file, not a dataset directory"),
    "output dir is a file": Api(lambda ws: check_output_dir(ws.file), "file.txt"),
    "output file is a directory": Api(lambda ws: check_output_file(ws.folder), "is a directory"),
    "output file is a device": Api(lambda ws: check_output_file("/dev/null"), "not a regular file"),
    # The outputs are checked before the results are looked at: no result is needed to show it.
    "tracking outputs into a file": Api(
        lambda ws: write_tracking_outputs(None, ws.file), "file.txt: exists and is not a directory"
    ),
    "grasp outputs under a file": Api(lambda ws: write_grasp_outputs(None, ws.file / "bench"), "file.txt is a file"),
}

#: The number of bad inputs checked here; docs/reliability.md cites it.
BAD_INPUTS = len(CLI_CASES) + len(API_CASES)


# ------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bad_input") / "data"
    config = DatasetConfig(
        scenes=1, frames_per_scene=2, image_size=(64, 48), sensor="ideal", seed=1000, fuse_depth=False
    )
    build_dataset(config, out, progress=False)
    return out


@pytest.fixture(scope="module")
def shaft_net(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    obj = load_object("shaft")
    meta = {"method": "supervised-edge", "object_name": obj.name, "object_mesh_hash": obj.mesh_hash}
    path = tmp_path_factory.mktemp("nets") / "shaft.safetensors"
    save_checkpoint(path, DenseObjectNet(descriptor_dim=3), meta | {"image_size": (64, 48)})
    return path


@pytest.fixture(scope="module")
def trained_run(dataset: Path, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("runs") / "run"
    argv = [*TRAIN, "--out", str(run), "--steps", "1", "--checkpoint-every", "1", "--threads", "1"]
    assert main([a.format(data=dataset) for a in argv]) == 0
    return run


class Workspace:
    """Files and folders the cases name (``{file}``, ``ws.file``, ...); the costly ones made on first use."""

    def __init__(self, tmp: Path, data: Path, request: pytest.FixtureRequest) -> None:
        self.tmp, self.data, self._request = tmp, data, request
        self.file, self.folder = tmp / "file.txt", tmp / "folder"
        self.file.write_text("not what was asked for\n")
        self.folder.mkdir()
        (tmp / "field.npz").mkdir()
        (tmp / "part.txt").write_text("hello\n")
        (tmp / "part.stl").write_bytes(b"solid nonsense\nthis is not an stl\n")

    @property
    def shaft_net(self) -> Path:
        return self._request.getfixturevalue("shaft_net")

    @property
    def env(self) -> gym.Env:
        return self._request.getfixturevalue("api_env")

    @property
    def corrupt_run(self) -> Path:
        run = self.tmp / "corrupt_run"
        if not run.exists():
            shutil.copytree(self._request.getfixturevalue("trained_run"), run)
            (run / "train_state.pt").write_bytes(b"\x00" * 100)
        return run

    def fill(self, argv: tuple[str, ...]) -> list[str]:
        return [a.format_map(_Fields(self)) for a in argv]


class _Fields(dict):
    def __init__(self, ws: Workspace) -> None:
        super().__init__()
        self.ws = ws

    def __missing__(self, key: str) -> Any:
        return getattr(self.ws, key)


@pytest.fixture
def workspace(tmp_path: Path, dataset: Path, request: pytest.FixtureRequest) -> Workspace:
    return Workspace(tmp_path, dataset, request)


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """Exit status, stdout and stderr of ``don-gym ARGV`` run in this process."""
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def one_error_line(code: int, err: str) -> str:
    lines = err.strip().splitlines()
    assert code not in (0, None), err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("don-gym") and ": error: " in lines[0], lines[0]
    return lines[0]


def _work_must_not_run(*args, **kwargs):
    raise AssertionError("the work started although an input was bad")


# ---------------------------------------------------------------------------------------------- tests
@pytest.mark.parametrize("name", list(CLI_CASES))
def test_cli_refuses_a_bad_input_in_one_line(name: str, workspace, monkeypatch, capsys) -> None:
    case = CLI_CASES[name]
    if case.before_work is not None:
        module, function = case.before_work.split(":")
        monkeypatch.setattr(f"{module}.{function}", _work_must_not_run)
    code, _, err = run_cli(workspace.fill(case.argv), capsys)
    assert case.says in one_error_line(code, err)


@pytest.mark.parametrize("name", list(API_CASES))
@pytest.mark.filterwarnings("ignore:.*render_mode")  # gymnasium's own warning before the env refuses
def test_api_refuses_a_bad_input_with_a_dongymerror(name: str, workspace) -> None:
    case = API_CASES[name]
    with pytest.raises(DonGymError, match=re.escape(case.says)):
        case.call(workspace)


def test_a_damaged_train_state_is_a_short_line_that_says_what_to_do(workspace, capsys) -> None:
    code, _, err = run_cli(workspace.fill((*TRAIN, "--out", "{corrupt_run}", "--steps", "2", "--resume")), capsys)
    line = one_error_line(code, err)
    assert "train_state.pt: cannot be read, the file is damaged" in line and "corrupt_run" in line, line
    assert "delete it" in line and "new --out" in line, line
    assert "weights_only" not in line and len(line) < 400, line  # PyTorch's paragraph about it is left out


def test_self_supervised_on_data_without_fusion_says_how_and_trains_from_sensor_depth(workspace, capfd) -> None:
    """The dataset fixture is built with --no-fusion. Captured at the file descriptors: OpenCV writes its
    warnings (a PNG it cannot open) there, past Python's sys.stderr."""
    argv = ["train", "--method", "self-supervised", "--data", str(workspace.data), "--crop", "none", "--threads", "1"]
    code = main([*argv, "--out", str(workspace.tmp / "fused")])
    line = one_error_line(code, capfd.readouterr().err)
    assert str(workspace.data) in line and "rebuild it without --no-fusion" in line, line
    assert "--depth-source sensor" in line, line
    assert not (workspace.tmp / "fused").exists()
    assert main([*argv, "--out", str(workspace.tmp / "sensor"), "--steps", "1", "--depth-source", "sensor"]) == 0
    captured = capfd.readouterr()
    assert "model.safetensors: 1 steps" in captured.out
    assert "WARN" not in captured.err and "Warning" not in captured.err, captured.err


@pytest.fixture(scope="module")
def api_env():
    """A made env in mid-episode: the bad steps and resets are refused without ending it."""
    env = gym.make("DONToolcapPick-v0", image_size=None, sensor="ideal")
    env.reset(seed=0, options={"pose_id": 0})
    yield env
    env.close()


def test_the_docs_cite_the_number_of_cases() -> None:
    assert BAD_INPUTS >= 40
    text = (ROOT / "docs" / "reliability.md").read_text()
    for cited in (f"{BAD_INPUTS} bad inputs", f"{len(CLI_CASES)} through the command", f"{len(API_CASES)} through the"):
        assert cited in text, (
            f"docs/reliability.md should say '{cited}' (section 'Evaluation, benchmarks, env and CLI')"
        )


# ------------------------------------------------------------------------------------ faults and Ctrl-C
#: Each command that writes outputs, its output option pointing into ``{out}``, and the function doing its work.
WRITERS = {
    "evaluate": ((*EVAL, "--out", "{out}/eval"), EVAL_WORK),
    "benchmark grasp": ((*GRASP, "--out", "{out}/bench"), GRASP_WORK),
    "embed --out": (("embed", "toolcap", "--out", "{out}/field.npz"), EMBED_WORK),
    "embed --plot": (("embed", "toolcap", "--plot", "{out}/picture.png"), EMBED_WORK),
    "export": (("export", "{data}", "--out", "{out}/pdc"), "don_gym.data.export:export_scene_pdc"),
    "train": ((*TRAIN, "--out", "{out}/run"), "don_gym.learning.train:train"),
}


@pytest.fixture
def read_only_dir(tmp_path: Path):
    """A directory on a read-only file system (a tmpfs mounted read-only); skips where mounting is not allowed."""
    where = tmp_path / "read_only"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(where)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip("cannot mount a read-only file system here (needs root)")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=True)


@pytest.mark.parametrize("command", list(WRITERS))
def test_a_read_only_output_is_one_line_before_the_work(command: str, read_only_dir, workspace, monkeypatch, capsys):
    argv, work = WRITERS[command]
    module, function = work.split(":")
    monkeypatch.setattr(f"{module}.{function}", _work_must_not_run)
    code, _, err = run_cli([a.format(out=read_only_dir, data=workspace.data) for a in argv], capsys)
    line = one_error_line(code, err)
    assert str(read_only_dir) in line and "Read-only file system" in line


@pytest.mark.parametrize("command", list(WRITERS))
def test_no_permission_for_the_output_is_one_line_before_the_work(command: str, workspace, monkeypatch, capsys):
    # Root ignores file modes, so the refusal of the file system is simulated where the check asks it.
    argv, work = WRITERS[command]
    module, function = work.split(":")
    monkeypatch.setattr(f"{module}.{function}", _work_must_not_run)

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", kwargs.get("dir"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    code, _, err = run_cli([a.format(out=workspace.tmp / "locked", data=workspace.data) for a in argv], capsys)
    line = one_error_line(code, err)
    assert str(workspace.tmp) in line and "Permission denied" in line
    assert not (workspace.tmp / "locked").exists()  # nothing written


def test_a_disk_full_after_the_work_is_one_line_and_the_results_are_printed(workspace, monkeypatch, capsys):
    import don_gym.io

    def full(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(don_gym.io, "write_text_atomic", full)
    out = workspace.tmp / "eval"
    code, stdout, err = run_cli([*workspace.fill(EVAL), "--models", "oracle", "--out", str(out)], capsys)
    line = one_error_line(code, err)
    assert line == f"don-gym evaluate: error: {out / 'tracking.json'}: No space left on device"
    assert "| oracle |" in stdout  # the table came before the write that failed
    assert not list(out.rglob("*"))  # the results' first file: nothing partial left


def test_a_real_full_disk_is_one_line_naming_the_file(workspace, tmp_path: Path, capsys):
    where = tmp_path / "small"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip("cannot mount a small file system here (needs root)")
    try:
        (where / "filler").write_bytes(b"\xff" * 60_000)  # leaves less than a picture needs
        code, _, err = run_cli(["embed", "toolcap", "--plot", str(where / "toolcap.png")], capsys)
        line = one_error_line(code, err)
        assert "No space left on device" in line and str(where) in line
        assert sorted(p.name for p in where.iterdir()) == ["filler"]  # no partial file left
        assert (where / "filler").read_bytes() == b"\xff" * 60_000  # what was there is whole
    finally:
        subprocess.run(["umount", str(where)], check=True)


def test_ctrl_c_is_one_line_with_status_130(workspace, monkeypatch, capsys) -> None:
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("don_gym.evaluation.tracking.evaluate_tracking", interrupted)
    code, _, err = run_cli([*workspace.fill(EVAL), "--out", str(workspace.tmp / "o")], capsys)
    assert code == 130 and err == "don-gym evaluate: interrupted\n"
    assert not (workspace.tmp / "o").exists()  # nothing written


def test_error_line_names_the_file_of_an_os_error() -> None:
    assert error_line(OSError(errno.EROFS, "Read-only file system", "/data/x.png")) == (
        "/data/x.png: Read-only file system"
    )
    assert error_line(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")) == (
        "/a -> /b: Invalid cross-device link"
    )
    assert error_line(DonGymError("first\nsecond")) == "first second"


def test_ctrl_c_during_a_grasp_benchmark_on_workers_prints_no_traceback(
    tmp_path: Path, ctrl_c_reaches_children
) -> None:
    """The terminal sends SIGINT to the command and its worker processes alike."""
    argv = [sys.executable, "-m", "don_gym.cli", "benchmark", "grasp", "--methods", "oracle", "--sensors", "ideal"]
    argv += ["--poses", "0", "1", "2", "3", "4", "5", "6", "7", "--repeats", "2", "--image-size", "64x48"]
    argv += ["--workers", "2", "--out", str(tmp_path / "bench")]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    process = subprocess.Popen(argv, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                               start_new_session=True)  # fmt: skip
    stderr = ""
    try:
        deadline = time.monotonic() + 240
        while "1/16" not in stderr and process.poll() is None and time.monotonic() < deadline:
            if select.select([process.stderr], [], [], 1.0)[0]:
                stderr += os.read(process.stderr.fileno(), 4096).decode(errors="replace")
        assert "1/16" in stderr, stderr
        time.sleep(1.0)  # both workers in the middle of an episode
        os.killpg(process.pid, signal.SIGINT)
        _, rest = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    stderr += rest
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr and stderr.rstrip().endswith("don-gym benchmark: interrupted"), stderr
    assert not (tmp_path / "bench").exists()
