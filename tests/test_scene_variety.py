"""Training-data variety: backdrop families, distractors and random light in recorded scenes, and the
dataset options that ask for them. The default scenes must stay what they were."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from don_gym.data.build import DatasetConfig, build_dataset
from don_gym.data.dataset import DATASET_FILE, DONDataset
from don_gym.errors import DatasetError, DonGymError
from don_gym.objects import load_object
from don_gym.sim.backdrop import BACKDROP_SETS, backdrop_texture, check_backdrop_set
from don_gym.sim.camera import Lighting, random_lighting, render_camera
from don_gym.sim.recorder import SceneRecorder


@pytest.fixture(scope="module")
def shaft():
    return load_object("shaft")


def test_every_backdrop_family_draws_a_reproducible_texture() -> None:
    seen = {}
    for seed in range(200):
        texture, family = backdrop_texture(np.random.default_rng(seed), BACKDROP_SETS["wide"], size_px=32)
        again, _ = backdrop_texture(np.random.default_rng(seed), BACKDROP_SETS["wide"], size_px=32)
        assert texture.shape == (32, 32, 3) and texture.dtype == np.uint8
        assert np.array_equal(texture, again)
        seen.setdefault(family, texture)
    assert set(seen) == set(BACKDROP_SETS["wide"])
    # Every family but the plain colour has structure; the plain one has none.
    for family, texture in seen.items():
        spread = float(texture.reshape(-1, 3).std(axis=0).max())
        assert (spread == 0.0) == (family == "plain"), family
    classic = {backdrop_texture(np.random.default_rng(s), size_px=16)[1] for s in range(50)}
    assert classic == set(BACKDROP_SETS["classic"])
    with pytest.raises(DonGymError, match="backgrounds='gaudy'"):
        check_backdrop_set("gaudy")


def test_mixed_backdrops_draw_the_classic_families_two_times_in_three() -> None:
    rng = np.random.default_rng(0)
    families = [backdrop_texture(rng, BACKDROP_SETS["mixed"], size_px=8)[1] for _ in range(3000)]
    assert set(families) == set(BACKDROP_SETS["wide"])
    classic_share = np.mean([family in BACKDROP_SETS["classic"] for family in families])
    stripes_share = families.count("stripes") / len(families)
    assert 0.63 < classic_share < 0.70  # half classic plus half of the nine's three classic: 2/3
    assert 0.19 < stripes_share < 0.25  # 2/9, twice the wide set's 1/9


def test_the_cli_offers_every_backdrop_set() -> None:
    """build-dataset lists its --backgrounds choices literally (no simulator import to parse arguments)."""
    from don_gym.cli import build_parser

    for name in BACKDROP_SETS:
        args = build_parser().parse_args(["build-dataset", "--object", "toolcap", "--out", "x", "--backgrounds", name])
        assert args.backgrounds == name


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ({"backgrounds": "gaudy"}, "backgrounds"),
        ({"lighting": "disco"}, "lighting"),
        ({"distractors": -1}, "distractors"),
    ],
)
def test_a_recorder_with_a_bad_option_is_refused_before_it_opens_a_client(shaft, options, says, monkeypatch) -> None:
    import don_gym.sim.recorder as recorder_module

    def no_client(*args, **kwargs):
        raise AssertionError("a PyBullet client was opened before the options were checked")

    monkeypatch.setattr(recorder_module, "Bullet", no_client)
    with pytest.raises(DonGymError, match=says):
        SceneRecorder(shaft, (64, 48), **options)


def test_the_default_light_is_the_renderers_default(shaft) -> None:
    with SceneRecorder(shaft, (64, 48)) as recorder:
        frame = recorder.record(seed=1, num_frames=1).frames[0]
        client, intrinsics = recorder.sim.client, recorder.intrinsics
        default = render_camera(client, intrinsics, frame.T_world_camera)[0]
        explicit = render_camera(client, intrinsics, frame.T_world_camera, lighting=Lighting())[0]
        other = render_camera(
            client, intrinsics, frame.T_world_camera, lighting=random_lighting(np.random.default_rng(5))
        )
    assert np.array_equal(default, frame.rgb) and np.array_equal(default, explicit)
    assert not np.array_equal(default, other[0])


def test_variety_changes_pixels_only_where_it_should(shaft) -> None:
    """Light and distractors come from a second stream of the scene's seed: the part's pose, the camera
    poses and the part's mask where no distractor hides it stay those of the plain scene."""
    with SceneRecorder(shaft, (96, 72)) as recorder:
        plain = recorder.record(seed=5, num_frames=4)
    varied_options = {"backgrounds": "wide", "distractors": 4, "lighting": "random"}
    with SceneRecorder(shaft, (96, 72), **varied_options) as recorder:
        varied = recorder.record(seed=5, num_frames=4)
        distractor_ids = set(recorder.distractors.body_ids)
    # A fresh recorder: a part settled in an earlier scene of the same client can settle differently.
    with SceneRecorder(shaft, (96, 72), **varied_options) as recorder:
        again = recorder.record(seed=5, num_frames=4)
    assert np.array_equal(plain.T_world_object, varied.T_world_object)
    placed = varied.background["distractors"]
    assert len(placed) == 4 and len(distractor_ids) == 4 * 3
    assert {"lighting", "table_texture_family", "floor_texture_family"} <= set(varied.background)
    part_xy = varied.T_world_object[:2, 3]
    extents = load_object("shaft").extents_m
    for distractor in placed:  # clear of the part's bounding circle
        assert np.linalg.norm(np.asarray(distractor["position_m"][:2]) - part_xy) > 0.5 * np.linalg.norm(extents)
    changed_rgb = 0
    for a, b, c in zip(plain.frames, varied.frames, again.frames, strict=True):
        assert np.array_equal(a.T_world_camera, b.T_world_camera)
        assert np.array_equal(b.rgb, c.rgb) and np.array_equal(b.object_mask, c.object_mask)
        # A distractor can only hide the part, never add to it.
        assert not (b.object_mask & ~a.object_mask).any()
        changed_rgb += int(not np.array_equal(a.rgb, b.rgb))
    assert changed_rgb == len(plain.frames)


def test_dataset_options_are_recorded_checked_and_default_for_old_datasets(tmp_path: Path) -> None:
    config = DatasetConfig(scenes=1, frames_per_scene=2, image_size=(64, 48), seed=3, fuse_depth=False)
    varied = DatasetConfig(**{**config.__dict__, "backgrounds": "wide", "distractors": 2, "lighting": "random"})
    build_dataset(varied, tmp_path / "varied", progress=False)
    info = json.loads((tmp_path / "varied" / DATASET_FILE).read_text())
    assert (info["backgrounds"], info["distractors"], info["lighting"]) == ("wide", 2, "random")
    assert len(DONDataset(tmp_path / "varied").scenes) == 1
    with pytest.raises(DatasetError, match="distractors"):
        build_dataset(DatasetConfig(**{**varied.__dict__, "distractors": 3}), tmp_path / "varied", progress=False)

    # A dataset written before the options existed reads as the classic scenes.
    build_dataset(config, tmp_path / "old", progress=False)
    path = tmp_path / "old" / DATASET_FILE
    info = json.loads(path.read_text())
    for key in ("backgrounds", "distractors", "lighting"):
        del info[key]
    path.write_text(json.dumps(info))
    report = build_dataset(DatasetConfig(**{**config.__dict__, "scenes": 2}), tmp_path / "old", progress=False)
    assert report.scenes_written == 1 and report.scenes_skipped == 1

    for bad, match in (
        ({"backgrounds": "gaudy"}, "backgrounds='gaudy' \\(--backgrounds\\)"),
        ({"distractors": -1}, "distractors=-1 \\(--distractors\\)"),
        ({"lighting": "disco"}, "lighting='disco' \\(--lighting\\)"),
    ):
        with pytest.raises(DatasetError, match=match):
            DatasetConfig(**{**config.__dict__, **bad}).validate()


def test_cli_build_dataset_takes_the_variety_options(tmp_path: Path) -> None:
    command = [
        sys.executable,
        "-m",
        "don_gym.cli",
        "build-dataset",
        "--scenes",
        "1",
        "--frames",
        "2",
        "--size",
        "48x32",
    ]
    done = subprocess.run(
        [*command, "--no-fusion", "--backgrounds", "wide", "--distractors", "1", "--lighting", "random",
         "--out", str(tmp_path / "d")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    info = json.loads((tmp_path / "d" / DATASET_FILE).read_text())
    assert (info["backgrounds"], info["distractors"], info["lighting"]) == ("wide", 1, "random")
    refused = subprocess.run(
        [*command, "--lighting", "disco", "--out", str(tmp_path / "e")], capture_output=True, text=True
    )
    assert refused.returncode == 2 and "disco" in refused.stderr and "Traceback" not in refused.stderr
    assert not (tmp_path / "e").exists()
