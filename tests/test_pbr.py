"""The physically based renderer (``renderer="pbr"``): geometry that aligns to the pixel with the ray cast,
metal that reflects, the same image for the same scene, backdrops with every renderer, and bad input."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest

import don_gym  # noqa: F401 - registers the envs
from don_gym.data.render import DescriptorRenderer
from don_gym.errors import DonGymError, MeshError
from don_gym.geometry import invert_transform
from don_gym.objects import Material
from don_gym.sim import pbr
from don_gym.sim.bullet import Bullet
from don_gym.sim.camera import render_camera
from don_gym.sim.pbr import PbrSettings, Surface, environment_map, expose, fov_and_principal_point

pytestmark = pytest.mark.skipif(not pbr.mitsuba_available(), reason="the pbr extra is not installed")


def _pick_env(renderer: str, size=(320, 240), background: str = "plain"):
    env = gym.make("DONToolcapPick-v0", image_size=size, renderer=renderer, background=background)
    env.reset(seed=5, options={"pose_id": 3})
    return env


def test_part_silhouette_matches_the_ray_cast_mask():
    """The part alone (everything else hidden): the pixels the path tracer finds more than half covered by the
    part are the pixels whose centre ray hits the mesh (IoU >= 0.99), and they show the part's colour."""
    env = _pick_env("pbr")
    try:
        sim, part = env.unwrapped.sim, env.unwrapped.task.part
        for body_id in sim.bodies.values():
            if body_id != part.body_id:
                for data in sim.client.getVisualShapeData(body_id):
                    sim.client.changeVisualShape(body_id, data[1], rgbaColor=[1, 1, 1, 0])
        sim.client.changeVisualShape(part.body_id, -1, rgbaColor=[1, 0, 0, 1])
        sim.set_surface(part.body_id, Surface(metallic=0.0, roughness=1.0))
        intrinsics, T_world_camera = env.unwrapped.intrinsics, env.unwrapped.robot.camera_pose()
        layers = sim.client.pbr.render_layers(
            sim.client, intrinsics, T_world_camera, samples_per_pixel=64, hide_environment=True
        )
        pbr_mask = layers["coverage"][..., 0] > 0.5
        redness = layers["radiance"][..., 0] - layers["radiance"][..., 1:3].max(axis=-1)
        assert np.median(redness[pbr_mask]) > 0.05 and np.abs(np.median(redness[~pbr_mask])) < 0.02
        model = env.unwrapped.model
        ray_cast = DescriptorRenderer(model.mesh, np.zeros((len(model.mesh.vertices), 1)), np.zeros(1)).render(
            intrinsics, invert_transform(T_world_camera) @ part.T_world_object
        )
        truth = ray_cast.object_mask
        assert truth.sum() > 300, "the part should fill a few hundred pixels at this size"
        iou = (pbr_mask & truth).sum() / (pbr_mask | truth).sum()
        assert iou >= 0.99, f"silhouette IoU {iou:.4f}"
    finally:
        env.close()


def test_same_scene_same_image_and_metal_reflects():
    """Two envs, same seed and pose: identical PBR images. The steel part mirrors its bright and dark
    surroundings: the spread of its pixels is far wider than that of the same part made matte."""
    images = []
    for _ in range(2):
        env = _pick_env("pbr")
        images.append(env.unwrapped._observation()["rgb"])
        env.close()
    np.testing.assert_array_equal(images[0], images[1])
    env = _pick_env("pbr")
    part, unwrapped = _part_mask(env), env.unwrapped
    spreads = {}
    for name, surface in (("steel", Surface(metallic=1.0, roughness=0.3)), ("matte", Surface(0.0, 0.9))):
        unwrapped.sim.set_surface(unwrapped.task.part.body_id, surface)
        luminance = unwrapped._observation()["rgb"].astype(float).mean(axis=-1)[part]
        spreads[name] = np.percentile(luminance, 95) - np.percentile(luminance, 5)
    env.close()
    assert spreads["steel"] > 2 * spreads["matte"], spreads


def _part_mask(env) -> np.ndarray:
    unwrapped = env.unwrapped
    with unwrapped.robot.hidden():
        _, _, segmentation = render_camera(
            unwrapped.sim.client, unwrapped.intrinsics, unwrapped.robot.camera_pose(), renderer="tiny"
        )
    return (segmentation & ((1 << 24) - 1)) == unwrapped.task.part.body_id


@pytest.mark.parametrize("renderer", ["egl", "pbr"])
def test_random_backdrop_shows_with_every_renderer(renderer):
    """The random backdrop's texture on the table: the table region's colour spread and its pixel pattern
    follow TinyRenderer's (same seed), far from the plain table's (a spread of a few grey levels)."""
    tiny = _pick_env("tiny", size=(160, 120), background="random")
    reference = tiny.unwrapped._observation()["rgb"].astype(float)
    table = ~_part_mask(tiny)
    tiny.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # EGL falls back to TinyRenderer with a warning where it is missing
        other_env = _pick_env(renderer, size=(160, 120), background="random")
    if other_env.unwrapped.renderer != renderer:
        other_env.close()
        pytest.skip(f"{renderer} is unavailable on this machine")
    other = other_env.unwrapped._observation()["rgb"].astype(float)
    other_env.close()
    spread, reference_spread = other[table].std(axis=0).mean(), reference[table].std(axis=0).mean()
    assert spread > 0.5 * reference_spread and reference_spread > 15
    correlation = np.mean([np.corrcoef(other[table][:, c], reference[table][:, c])[0, 1] for c in range(3)])
    assert correlation > 0.8, f"{renderer}'s table pattern correlates {correlation:.2f} with TinyRenderer's"
    if renderer == "egl":  # same pixels up to shading: the colours agree too
        assert np.abs(other[table].mean(axis=0) - reference[table].mean(axis=0)).max() < 10


# --------------------------------------------------------------------- pure parts
def test_intrinsics_to_mitsuba_camera():
    from don_gym.geometry import CameraIntrinsics

    intrinsics = CameraIntrinsics(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)
    fov, offset_x, offset_y = fov_and_principal_point(intrinsics)
    assert fov == pytest.approx(np.degrees(2 * np.arctan(160 / 300)))
    assert offset_x == pytest.approx(0.0) and offset_y == pytest.approx(0.0)  # pixel centres: +0.5
    with pytest.raises(DonGymError, match="square pixels"):
        fov_and_principal_point(CameraIntrinsics(300.0, 330.0, 160.0, 120.0, 320, 240))


def test_environment_maps():
    fixed = environment_map(0)
    assert fixed.shape == (128, 256, 3) and fixed.dtype == np.float32 and (fixed >= 0).all()
    np.testing.assert_array_equal(environment_map(7), environment_map(7))
    assert not np.allclose(environment_map(7), environment_map(8))
    assert fixed.max() > 5 * np.median(fixed), "windows much brighter than the room: highlights on metal"


def test_exposure_and_noise():
    settings = PbrSettings()
    grey = np.full((200, 200, 3), 3.7, np.float32)  # any level: auto exposure maps it to the key grey
    image = expose(grey, settings, np.random.default_rng(0))
    srgb_key = 1.055 * settings.exposure_key ** (1 / 2.4) - 0.055
    assert abs(image.mean() / 255.0 - srgb_key) < 0.01
    assert 0.5 < image.astype(float).std() < 4.0, "shot and read noise of a few grey levels"
    np.testing.assert_array_equal(image, expose(grey, settings, np.random.default_rng(0)))


# --------------------------------------------------------------------- bad input
def test_bad_input_is_refused_in_one_line(tmp_path):
    with pytest.raises(DonGymError, match="renderer='cycles' is unknown"):
        gym.make("DONToolcapPick-v0", renderer="cycles")
    with pytest.raises(MeshError, match="roughness=1.5"):
        Material("brushed", 7850.0, 0.8, 0.9, (0.7, 0.7, 0.7, 1.0), metallic=1.0, roughness=1.5)
    with pytest.raises(MeshError, match="rgba"):
        Material("neon", 1000.0, 0.8, 0.1, (1.2, 0.2, 0.2, 1.0))
    with pytest.raises(DonGymError, match="roughness"):
        Surface(metallic=0.0, roughness=-0.1)
    with pytest.raises(DonGymError, match="samples_per_pixel"):
        PbrSettings(samples_per_pixel=0)


def test_missing_mitsuba_says_how_to_install(monkeypatch):
    monkeypatch.setattr(pbr, "mitsuba_available", lambda: False)
    with pytest.raises(DonGymError, match=r'pip install -e "\.\[pbr\]"'):
        Bullet(renderer="pbr")


def test_pbr_build_into_a_dataset_of_another_renderer_is_refused(tmp_path):
    out = tmp_path / "data"
    common = ["--object", "toolcap", "--frames", "2", "--size", "32x24", "--out", str(out)]
    build = [sys.executable, "-m", "don_gym.cli", "build-dataset", "--scenes", "1", *common]
    subprocess.run(build, check=True, capture_output=True)
    listing = sorted(p.relative_to(out) for p in out.rglob("*"))
    result = subprocess.run([*build, "--renderer", "pbr"], capture_output=True, text=True)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "renderer" in lines[0] and "'tiny' on disk" in lines[0], result.stderr
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == listing, "nothing written"
