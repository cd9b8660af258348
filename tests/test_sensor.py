"""The depth-sensor model: noise growth, quantisation, dropout, flying pixels, calibration error."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_scenes import fronto_plane_camera, render_scene

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics
from don_gym.sim.sensor import (
    D435,
    SENSOR_PRESETS,
    get_sensor,
    sample_calibration_error,
    scaled_sensor,
    simulate_depth,
)

SMALL = CameraIntrinsics.d435(160, 120)


def plane_depth(distance_m: float, tilt_deg: float = 0.0, intrinsics: CameraIntrinsics = SMALL) -> np.ndarray:
    depth, _ = render_scene(intrinsics, np.eye(4), fronto_plane_camera(distance_m, np.deg2rad(tilt_deg)))
    return depth


def noise_std(sensor, distance_m: float, intrinsics: CameraIntrinsics = SMALL, seed: int = 0) -> float:
    ideal = plane_depth(distance_m, intrinsics=intrinsics)
    out = simulate_depth(ideal, np.zeros_like(ideal), intrinsics, sensor, np.random.default_rng(seed))
    valid = out > 0
    assert valid.mean() > 0.95
    return float(np.std(out[valid] - ideal[valid]))


def test_ideal_sensor_returns_depth_unchanged_and_identity_calibration():
    ideal = plane_depth(0.6, tilt_deg=40.0)
    ideal[:10] = 0.0
    out = simulate_depth(ideal, np.ones_like(ideal), SMALL, "ideal", np.random.default_rng(0))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, ideal)
    np.testing.assert_array_equal(sample_calibration_error("ideal", np.random.default_rng(0)), np.eye(4))


def test_presets_and_unknown_name():
    assert {"ideal", "d435", "d435-clean", "kinect"} <= set(SENSOR_PRESETS)
    assert get_sensor("d435") is D435
    assert get_sensor(D435) is D435
    with pytest.raises(DonGymError, match="d435"):
        get_sensor("realsense")


def test_d435_noise_grows_with_distance_squared_and_matches_stereo_formula():
    near, far = noise_std("d435", 0.5), noise_std("d435", 1.0)
    assert 3.5 < far / near < 4.5
    # sigma_z = z^2 * subpixel / (f * b): quantisation adds a little on top.
    expected_near = 0.5**2 * D435.stereo_subpixel_rms_px / (SMALL.fx * D435.baseline_m)
    assert expected_near < near < 1.15 * expected_near


def test_lower_resolution_is_noisier_like_a_scaled_stereo_pair():
    large = CameraIntrinsics.d435(640, 480)
    ratio = noise_std("d435", 0.5, SMALL) / noise_std("d435", 0.5, large)
    assert ratio == pytest.approx(large.fx / SMALL.fx, rel=0.12)


def test_kinect_noise_follows_nguyen_model():
    expected = 0.0012 + 0.0019 * (1.0 - 0.4) ** 2
    assert noise_std("kinect", 1.0) == pytest.approx(expected, rel=0.1)


def test_disparity_is_quantised_to_sub_pixel_steps():
    ideal = plane_depth(0.7, tilt_deg=30.0)
    out = simulate_depth(ideal, np.zeros_like(ideal), SMALL, "d435", np.random.default_rng(0))
    valid = out > 0
    steps = SMALL.fx * D435.baseline_m / out[valid].astype(np.float64) / D435.disparity_step_px
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-3)
    # Discrete levels: at most one per step over the disparity range, while the same noisy
    # sensor without quantisation gives (almost) every pixel its own depth.
    disparity_range = round(steps.max() - steps.min())
    assert len(np.unique(out[valid])) <= disparity_range + 1
    unquantised = dataclasses.replace(D435, disparity_step_px=0.0)
    smooth = simulate_depth(ideal, np.zeros_like(ideal), SMALL, unquantised, np.random.default_rng(0))
    assert len(np.unique(smooth[smooth > 0])) > 10 * (disparity_range + 1)


def dropout_fraction(tilt_deg: float, specular: float, seed: int = 0) -> float:
    ideal = plane_depth(0.6, tilt_deg)
    out = simulate_depth(ideal, np.full_like(ideal, specular), SMALL, "d435", np.random.default_rng(seed))
    measured = (ideal > 0.2) & (ideal < 2.0)
    return float((out[measured] == 0).mean())


def test_specular_dropout_grows_with_incidence_angle():
    tilts = [0.0, 35.0, 55.0, 70.0]
    specular = [dropout_fraction(t, 1.0) for t in tilts]
    matte = [dropout_fraction(t, 0.0) for t in tilts]
    assert all(a < b for a, b in zip(specular, specular[1:], strict=False)), specular
    assert specular[0] < 0.1 and specular[-1] > 0.8
    # Matte surfaces only see the small base dropout and speckle, whatever the angle.
    assert max(matte) < 0.02
    assert specular[0] > matte[0]


def test_flying_pixels_only_next_to_depth_step():
    ideal = np.full((SMALL.height, SMALL.width), 0.5, np.float32)
    edge = SMALL.width // 2
    ideal[:, edge:] = 0.8
    out = simulate_depth(ideal, np.zeros_like(ideal), SMALL, "d435", np.random.default_rng(3))
    # Far beyond the noise (sigma ~7 mm at 0.8 m at this resolution).
    flying = (out > 0) & (np.abs(out - ideal) > 0.05)
    rows, cols = np.nonzero(flying)
    assert set(cols.tolist()) <= {edge - 1, edge}
    assert flying.sum() > 0.3 * 2 * SMALL.height  # probability 0.5 on the two edge columns
    assert np.all((out[flying] > 0.49) & (out[flying] < 0.81))


def test_range_limits():
    # The D435's disparity search range sets its minimum range: f * b / 126 = 0.061 m here.
    too_close = plane_depth(0.05)
    assert not simulate_depth(too_close, np.zeros_like(too_close), SMALL, "d435", np.random.default_rng(0)).any()
    for distance in (0.3, 3.5):  # Kinect near mode: 0.4 m to 3 m
        ideal = plane_depth(distance)
        assert not simulate_depth(ideal, np.zeros_like(ideal), SMALL, "kinect", np.random.default_rng(0)).any()


def test_calibration_error_magnitudes():
    rng = np.random.default_rng(0)
    errors = np.stack([sample_calibration_error("d435", rng) for _ in range(3000)])
    rotations = errors[:, :3, :3]
    np.testing.assert_allclose(
        rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape), atol=1e-9
    )
    translation_std = errors[:, :3, 3].std(axis=0)
    np.testing.assert_allclose(translation_std, 0.002, rtol=0.1)
    # Small rotations: the skew part of R holds the rotation-vector components.
    rotvec = np.stack(
        [errors[:, 2, 1] - errors[:, 1, 2], errors[:, 0, 2] - errors[:, 2, 0], errors[:, 1, 0] - errors[:, 0, 1]], 1
    )
    np.testing.assert_allclose(np.degrees(rotvec / 2).std(axis=0), 0.3, rtol=0.1)


def test_same_seed_same_output_and_different_seed_differs():
    ideal = plane_depth(0.6, tilt_deg=50.0)
    specular = np.full_like(ideal, 0.7)
    a = simulate_depth(ideal, specular, SMALL, "d435", np.random.default_rng(42))
    b = simulate_depth(ideal, specular, SMALL, "d435", np.random.default_rng(42))
    c = simulate_depth(ideal, specular, SMALL, "d435", np.random.default_rng(43))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    np.testing.assert_array_equal(
        sample_calibration_error("d435", np.random.default_rng(5)),
        sample_calibration_error("d435", np.random.default_rng(5)),
    )


def test_scaled_sensor_interpolates_from_ideal_to_preset():
    ideal = plane_depth(0.8)
    zero = scaled_sensor("d435", 0.0)
    assert zero.is_ideal
    out = simulate_depth(ideal, np.ones_like(ideal), SMALL, zero, np.random.default_rng(0))
    np.testing.assert_array_equal(out, ideal)
    full = scaled_sensor("d435", 1.0)
    assert dataclasses.replace(full, name="d435") == D435
    half = noise_std(scaled_sensor("d435-clean", 0.5), 0.8) / noise_std("d435-clean", 0.8)
    assert 0.4 < half < 0.6
    with pytest.raises(DonGymError):
        scaled_sensor("d435", 1.5)


def test_input_validation():
    ideal = plane_depth(0.5)
    rng = np.random.default_rng(0)
    with pytest.raises(DonGymError, match="specular"):
        simulate_depth(ideal, np.zeros((10, 10), np.float32), SMALL, "d435", rng)
    with pytest.raises(DonGymError, match="shape"):
        simulate_depth(ideal[:-1], np.zeros_like(ideal[:-1]), SMALL, "d435", rng)
    negative = ideal.copy()
    negative[0, 0] = -0.1
    with pytest.raises(DonGymError, match=">= 0"):
        simulate_depth(negative, np.zeros_like(ideal), SMALL, "d435", rng)
    with pytest.raises(DonGymError, match="specular"):
        simulate_depth(ideal, np.full_like(ideal, 1.5), SMALL, "d435", rng)
    with pytest.raises(DonGymError):
        dataclasses.replace(D435, flying_pixel_probability=2.0)
