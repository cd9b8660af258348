"""Depth-sensor models: what a real depth camera (D435, Kinect) makes of the ideal rendered depth
(:func:`simulate_depth`), and the hand-eye calibration error of its reported pose
(:func:`sample_calibration_error`). Presets: :data:`SENSOR_PRESETS`; the facts behind their
numbers: ``docs/background.md``, section "Depth sensors".
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, make_transform

_DEG = np.pi / 180.0


@dataclass(frozen=True)
class SensorModel:
    """Parameters of a depth sensor, SI units. Defaults give the ideal sensor.

    Attributes:
        name: preset name, shown in logs and results.
        baseline_m: stereo baseline in metres. D435: 50 mm (Intel D400 datasheet; docs/background.md, "Depth sensors").
            Kinect v1: 75 mm (projector-to-camera, Khoshelham & Elberink 2012).
        stereo_subpixel_rms_px: RMS disparity error of the stereo matcher in pixels at the
            simulated resolution; 0 disables. D435: 0.08, within Intel's typical subpixel RMS
            of 0.05-0.1 (docs/background.md, "Depth sensors").
        disparity_step_px: disparity quantisation step in pixels; 0 disables. D435: 1/32,
            the 5-bit sub-pixel resolution of the D4 vision processor's disparity output.
        max_disparity_px: disparity search range in pixels; nearer points (larger disparity)
            return no depth. This is the D435's minimum range: ``z_min = f * b / 126``, which
            is 0.24 m at fx = 615 px and about 0.28 m at the 1280x720 depth focal length
            (datasheet Min-Z at maximum resolution ~0.28 m), falling at lower resolution.
            D435: 126 (D400 disparity search range). ``inf`` disables.
        noise_correlation_px: std (pixels) of the Gaussian that spatially correlates the
            noise field; 0 gives white noise. D435: 1.0 px, a modelling choice (matching
            windows of a few pixels correlate neighbours); no datasheet figure.
        axial_sigma_const_m, axial_sigma_quadratic_per_m, axial_sigma_z0_m: depth-space
            axial noise ``sigma_z = const + quadratic * (z - z0)^2`` in metres, added to the
            stereo term. Kinect: 0.0012, 0.0019, 0.4 (Nguyen et al. 2012; docs/background.md, "Depth sensors").
        axial_sigma_angle_coeff_m: incidence term of Nguyen et al. 2012 added beyond 60
            degrees: ``coeff / sqrt(z) * theta^2 / (pi/2 - theta)^2`` (theta in radians, clipped
            at 88 degrees); Kinect: 0.0001. It gives the noise's fast growth beyond 60 degrees
            (docs/background.md, "Depth sensors").
        flying_pixel_probability: probability that a pixel next to a depth jump becomes a
            flying pixel. D435: 0.5, a modelling choice (the D435 shows flying pixels at
            depth edges, docs/background.md, "Depth sensors"; their rate depends on the scene).
        flying_pixel_min_jump_m: depth jump (metres) within a pixel's neighbourhood that
            counts as an edge. D435: 0.015 m, a modelling choice: above the slope-induced
            depth change between neighbours on ordinary surfaces at table-top range.
        flying_pixel_radius_px: neighbourhood radius in pixels (1 = 3x3).
        specular_dropout_max: missing-depth probability on a fully specular surface
            (``specular = 1``) at grazing incidence. D435: 1.0 (zero depth on specular metal,
            docs/background.md, "Depth sensors"; the Material.specular of the object scales it).
        specular_dropout_mid_angle_rad, specular_dropout_width_rad: centre and scale of
            the logistic in incidence angle: 50 degrees and 6.8 degrees put the rise between
            about 30 degrees (5 %) and 70 degrees (95 %). Modelling choice: a specular surface
            returns the projected pattern to the cameras only near normal incidence.
        base_dropout_probability: missing-depth probability on any surface. D435: 0.002,
            a modelling choice for the odd unmatched pixel.
        speckle_seed_probability: probability per pixel of a hole seed; each seed removes
            a disc of ``speckle_radius_px``. D435: 0.0005 with radius 1 (~0.4 % of pixels in
            small clusters), a modelling choice for the texture-less patches that the
            matcher rejects.
        speckle_radius_px: radius in pixels of each speckle hole.
        min_range_m, max_range_m: depths outside return 0. D435: 0 (the minimum range comes
            from ``max_disparity_px``) and 10 m (datasheet "approx. 10 m", depending on the
            scene). Kinect v1 near mode: 0.4 m to 3.0 m.
        calibration_translation_std_m, calibration_rotation_std_rad: std per axis of the
            hand-eye calibration error of the reported camera pose (translation, rotation
            vector components): 2 mm and 0.3 degrees, typical residuals of a hand-eye
            calibration of a wrist camera. Used by :func:`sample_calibration_error`.
    """

    name: str
    baseline_m: float = 0.0
    stereo_subpixel_rms_px: float = 0.0
    disparity_step_px: float = 0.0
    max_disparity_px: float = float("inf")
    noise_correlation_px: float = 0.0
    axial_sigma_const_m: float = 0.0
    axial_sigma_quadratic_per_m: float = 0.0
    axial_sigma_z0_m: float = 0.0
    axial_sigma_angle_coeff_m: float = 0.0
    flying_pixel_probability: float = 0.0
    flying_pixel_min_jump_m: float = 0.015
    flying_pixel_radius_px: int = 1
    specular_dropout_max: float = 0.0
    specular_dropout_mid_angle_rad: float = 50.0 * _DEG
    specular_dropout_width_rad: float = 6.8 * _DEG
    base_dropout_probability: float = 0.0
    speckle_seed_probability: float = 0.0
    speckle_radius_px: int = 1
    min_range_m: float = 0.0
    max_range_m: float = float("inf")
    calibration_translation_std_m: float = 0.0
    calibration_rotation_std_rad: float = 0.0

    def __post_init__(self) -> None:
        probabilities = (
            "flying_pixel_probability",
            "specular_dropout_max",
            "base_dropout_probability",
            "speckle_seed_probability",
        )
        for name in probabilities:
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise DonGymError(f"SensorModel.{name} must be in [0, 1], got {value}")
        non_negative = (
            "baseline_m",
            "stereo_subpixel_rms_px",
            "disparity_step_px",
            "noise_correlation_px",
            "axial_sigma_const_m",
            "axial_sigma_quadratic_per_m",
            "axial_sigma_angle_coeff_m",
            "flying_pixel_min_jump_m",
            "flying_pixel_radius_px",
            "speckle_radius_px",
            "min_range_m",
            "calibration_translation_std_m",
            "calibration_rotation_std_rad",
        )
        for name in non_negative:
            value = getattr(self, name)
            if not value >= 0.0:
                raise DonGymError(f"SensorModel.{name} must be >= 0, got {value}")
        if not self.max_disparity_px > 0 or not self.max_range_m > self.min_range_m:
            raise DonGymError(
                f"SensorModel {self.name!r}: need max_disparity_px > 0 and max_range_m > min_range_m, got "
                f"{self.max_disparity_px}, [{self.min_range_m}, {self.max_range_m}]"
            )
        if self.specular_dropout_width_rad <= 0:
            raise DonGymError(
                f"SensorModel.specular_dropout_width_rad must be > 0, got {self.specular_dropout_width_rad}"
            )
        uses_stereo = (
            self.stereo_subpixel_rms_px > 0 or self.disparity_step_px > 0 or np.isfinite(self.max_disparity_px)
        )
        if uses_stereo and self.baseline_m <= 0:
            raise DonGymError(f"SensorModel {self.name!r}: stereo noise, quantisation or range need baseline_m > 0")

    @property
    def is_ideal(self) -> bool:
        """True when :func:`simulate_depth` returns its input unchanged."""
        return _scaled_fields(self, 0.0) == _scaled_fields(self, 1.0)


IDEAL = SensorModel(name="ideal")

D435 = SensorModel(
    name="d435",
    baseline_m=0.050,
    stereo_subpixel_rms_px=0.08,
    disparity_step_px=1.0 / 32.0,
    max_disparity_px=126.0,
    noise_correlation_px=1.0,
    flying_pixel_probability=0.5,
    flying_pixel_min_jump_m=0.015,
    flying_pixel_radius_px=1,
    specular_dropout_max=1.0,
    base_dropout_probability=0.002,
    speckle_seed_probability=0.0005,
    speckle_radius_px=1,
    min_range_m=0.0,
    max_range_m=10.0,
    calibration_translation_std_m=0.002,
    calibration_rotation_std_rad=0.3 * _DEG,
)

#: The D435's noise, quantisation, flying pixels and range, but no missing depth on
#: surfaces (no specular, base or speckle dropout): separates "noisy" from "holes".
D435_CLEAN = dataclasses.replace(
    D435, name="d435-clean", specular_dropout_max=0.0, base_dropout_probability=0.0, speckle_seed_probability=0.0
)

#: Kinect v1 (structured light) in near mode. Its noise is Nguyen et al. 2012's measured
#: model, which already contains its 1/8-pixel disparity quantisation, so no separate
#: quantisation is applied.
KINECT = SensorModel(
    name="kinect",
    baseline_m=0.075,
    axial_sigma_const_m=0.0012,
    axial_sigma_quadratic_per_m=0.0019,
    axial_sigma_z0_m=0.4,
    axial_sigma_angle_coeff_m=0.0001,
    noise_correlation_px=1.0,
    flying_pixel_probability=0.5,
    flying_pixel_min_jump_m=0.015,
    specular_dropout_max=1.0,
    base_dropout_probability=0.002,
    speckle_seed_probability=0.0005,
    min_range_m=0.4,
    max_range_m=3.0,
    calibration_translation_std_m=0.002,
    calibration_rotation_std_rad=0.3 * _DEG,
)

SENSOR_PRESETS: dict[str, SensorModel] = {s.name: s for s in (IDEAL, D435, D435_CLEAN, KINECT)}


def get_sensor(name_or_model: str | SensorModel) -> SensorModel:
    """The preset called ``name_or_model``, or the model itself if one is given."""
    if isinstance(name_or_model, SensorModel):
        return name_or_model
    if isinstance(name_or_model, str) and name_or_model in SENSOR_PRESETS:
        return SENSOR_PRESETS[name_or_model]
    raise DonGymError(f"unknown depth sensor {name_or_model!r}; expected one of {sorted(SENSOR_PRESETS)}")


# Fields that measure how bad a sensor is: scaled linearly by scaled_sensor. Ranges and the
# search range are scaled in 1/value so that severity 0 gives "no limit".
_LINEAR_FIELDS = (
    "stereo_subpixel_rms_px",
    "disparity_step_px",
    "axial_sigma_const_m",
    "axial_sigma_quadratic_per_m",
    "axial_sigma_angle_coeff_m",
    "flying_pixel_probability",
    "specular_dropout_max",
    "base_dropout_probability",
    "speckle_seed_probability",
    "min_range_m",
    "calibration_translation_std_m",
    "calibration_rotation_std_rad",
)
_INVERSE_FIELDS = ("max_disparity_px", "max_range_m")


def _scaled_fields(sensor: SensorModel, severity: float) -> dict[str, float]:
    values = {name: getattr(sensor, name) * severity for name in _LINEAR_FIELDS}
    for name in _INVERSE_FIELDS:
        inverse = severity / getattr(sensor, name)
        values[name] = float("inf") if inverse == 0 else 1.0 / inverse
    return values


def scaled_sensor(sensor: str | SensorModel, severity: float) -> SensorModel:
    """Interpolate between the ideal sensor (``severity = 0``) and ``sensor`` (``severity = 1``).

    Noise std, quantisation step, dropout and flying-pixel probabilities, minimum range and
    calibration error scale linearly; the disparity search range and maximum range scale as
    ``1 / value`` (so severity 0 has no limit). Shape parameters (baseline, correlation
    width, edge threshold, logistic centre and width) stay those of ``sensor``. Used for the
    benchmark's sweep from ideal depth to the D435.
    """
    sensor = get_sensor(sensor)
    severity = float(severity)
    if not 0.0 <= severity <= 1.0:
        raise DonGymError(f"sensor severity must be in [0, 1], got {severity}")
    return dataclasses.replace(sensor, name=f"{sensor.name}@{severity:.2f}", **_scaled_fields(sensor, severity))


def depth_range_m(sensor: str | SensorModel, intrinsics: CameraIntrinsics) -> tuple[float, float]:
    """(nearest, farthest) z-depth in metres that :func:`simulate_depth` returns for ``sensor`` in a camera of
    ``intrinsics``: ``[min_range_m, max_range_m]``, and for a stereo sensor no nearer than the depth of its largest
    disparity, ``fx * baseline_m / max_disparity_px`` (the D435 at 640x480: 615 px x 0.05 m / 126 px = 0.244 m;
    ``fx`` is the simulated image's, as in :func:`simulate_depth`). "ideal": (0, inf)."""
    sensor = get_sensor(sensor)
    if sensor.is_ideal:
        return 0.0, float("inf")
    nearest = float(sensor.min_range_m)
    if sensor.baseline_m > 0 and np.isfinite(sensor.max_disparity_px):
        nearest = max(nearest, float(intrinsics.fx) * sensor.baseline_m / float(sensor.max_disparity_px))
    return nearest, float(sensor.max_range_m)


def sample_calibration_error(sensor: str | SensorModel, rng: np.random.Generator) -> np.ndarray:
    """(4, 4) ``T_camera_reportedcamera``: the hand-eye calibration error of one camera.

    The reported camera pose is ``T_world_camera_reported = T_world_camera @ this``. The
    translation is ``N(0, calibration_translation_std_m^2)`` per axis and the rotation a
    rotation vector with ``N(0, calibration_rotation_std_rad^2)`` per component. Identity for
    a sensor without calibration error (e.g. "ideal"); draws nothing from ``rng`` then.
    """
    sensor = get_sensor(sensor)
    if sensor.calibration_translation_std_m == 0 and sensor.calibration_rotation_std_rad == 0:
        return np.eye(4)
    translation = rng.normal(0.0, sensor.calibration_translation_std_m, size=3)
    rotvec = rng.normal(0.0, sensor.calibration_rotation_std_rad, size=3)
    return make_transform(Rotation.from_rotvec(rotvec).as_matrix(), translation)


def _validate_inputs(
    depth_ideal_m: np.ndarray, specular: np.ndarray, intrinsics: CameraIntrinsics
) -> tuple[np.ndarray, np.ndarray]:
    depth = np.asarray(depth_ideal_m)
    spec = np.asarray(specular)
    expected = (intrinsics.height, intrinsics.width)
    if depth.shape != expected:
        raise DonGymError(f"depth_ideal_m has shape {depth.shape}, expected (H, W) = {expected} from the intrinsics")
    if spec.shape != expected:
        raise DonGymError(f"specular has shape {spec.shape}, expected the depth image's shape {expected}")
    depth = depth.astype(np.float32, copy=False)
    spec = spec.astype(np.float32, copy=False)
    if not np.isfinite(depth).all() or depth.min(initial=0.0) < 0:
        raise DonGymError("depth_ideal_m must be finite and >= 0 (metres, 0 = no return)")
    if not np.isfinite(spec).all() or spec.min(initial=0.0) < 0 or spec.max(initial=0.0) > 1:
        raise DonGymError("specular must be in [0, 1]")
    return depth, spec


def _cos_incidence(depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """Cosine of the angle between the viewing ray and the surface normal, (H, W) float32.

    With P(u, v) = z(u, v) * r(u, v), r = ((u - cx)/fx, (v - cy)/fy, 1), the normal
    dP/du x dP/dv is proportional to n = (-fx z_u, -fy z_v, fx z_u r_x + fy z_v r_y + z) and
    n . r = z, so cos(theta) = z / (|n| |r|) needs only the depth gradient.
    """
    height, width = depth.shape
    rx = ((np.arange(width, dtype=np.float32) - intrinsics.cx) / intrinsics.fx)[None, :]
    ry = ((np.arange(height, dtype=np.float32) - intrinsics.cy) / intrinsics.fy)[:, None]
    dz_dv, dz_du = np.gradient(depth)
    g_u = np.float32(intrinsics.fx) * dz_du
    g_v = np.float32(intrinsics.fy) * dz_dv
    n_z = g_u * rx + g_v * ry + depth
    norm_sq = (g_u * g_u + g_v * g_v + n_z * n_z) * (rx * rx + ry * ry + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_theta = depth / np.sqrt(norm_sq)
    return np.nan_to_num(cos_theta, nan=0.0, posinf=0.0, neginf=0.0).clip(0.0, 1.0)


def _unit_normal_field(shape: tuple[int, int], correlation_px: float, rng: np.random.Generator) -> np.ndarray:
    """Standard-normal (H, W) float32 field, Gaussian-correlated over ``correlation_px``."""
    noise = rng.standard_normal(shape, dtype=np.float32)
    if correlation_px <= 0:
        return noise
    radius = max(1, int(np.ceil(3.0 * correlation_px)))
    kernel = cv2.getGaussianKernel(2 * radius + 1, correlation_px, cv2.CV_32F)
    blurred = cv2.sepFilter2D(noise, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT)
    # Blurring white noise scales its std by the L2 norm of the (separable) kernel; undo it.
    return blurred / np.float32(np.sum(kernel.astype(np.float64) ** 2))


def _disc(radius_px: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))


def _flying_pixels(depth: np.ndarray, valid: np.ndarray, sensor: SensorModel, rng: np.random.Generator) -> np.ndarray:
    kernel = np.ones((2 * int(sensor.flying_pixel_radius_px) + 1,) * 2, np.uint8)
    far = np.float32(1e9)
    local_max = cv2.dilate(depth, kernel, borderType=cv2.BORDER_REPLICATE)
    local_min = cv2.erode(np.where(valid, depth, far), kernel, borderType=cv2.BORDER_REPLICATE)
    # No-return neighbours (depth 0) are neither fore- nor background: nothing to mix with.
    edge = valid & (local_min < far) & (local_max - local_min > sensor.flying_pixel_min_jump_m)
    chosen = edge & (rng.random(depth.shape, dtype=np.float32) < sensor.flying_pixel_probability)
    out = depth.copy()
    mix = rng.random(int(chosen.sum()), dtype=np.float32)
    out[chosen] = local_min[chosen] + mix * (local_max[chosen] - local_min[chosen])
    return out


def simulate_depth(
    depth_ideal_m: np.ndarray,
    specular: np.ndarray,
    intrinsics: CameraIntrinsics,
    sensor: str | SensorModel,
    rng: np.random.Generator,
) -> np.ndarray:
    """What ``sensor`` returns for a scene whose exact z-depth is ``depth_ideal_m``.

    Effects, applied in this order (all vectorised, one pass over the image):

    1. **Flying pixels** at depth edges: a pixel whose 3x3 neighbourhood spans a depth jump
       larger than ``flying_pixel_min_jump_m`` gets, with ``flying_pixel_probability``, a depth
       drawn uniformly between the fore- and background depth (stereo matching windows that
       straddle an edge mix both surfaces).
    2. **Axial noise** in disparity space for a stereo sensor: ``d = f * b / z``, ``d += N(0,
       subpixel^2)``, back to depth; to first order ``sigma_z = z^2 * subpixel / (f * b)``
       (docs/background.md, "Depth sensors"). The noise field is spatially correlated by a Gaussian blur of width
       ``noise_correlation_px`` (stereo block matching correlates neighbours) and rescaled so the
       per-pixel std is unchanged. An optional depth-space term ``sigma_z = c + q (z - z0)^2``
       (+ an incidence term) models structured light (Kinect).
    3. **Disparity quantisation** to ``disparity_step_px`` sub-pixel steps, then back to depth:
       depth takes discrete levels whose spacing grows like ``z^2``.
    4. **Range limits**: disparities above the matcher's search range ``max_disparity_px``
       (too close) and depths outside ``[min_range_m, max_range_m]`` return 0.
    5. **Missing depth**: per pixel with probability ``base + specular * specular_dropout_max *
       logistic((theta - mid) / width)``, ``theta`` the incidence angle between the viewing ray
       and the surface normal estimated from the ideal depth by finite differences; plus a
       random speckle of small holes.

    The stereo terms use ``f = intrinsics.fx``, the focal length in pixels *at the simulated
    resolution*: a lower resolution has fewer pixels per radian, so the same sub-pixel matching
    error is a larger angle and depth is noisier and coarser, as for a real stereo pair scaled
    down. With the D435 colour intrinsics ``sigma_z(0.5 m)`` is 0.65 mm at 640x480 (fx = 615 px)
    and 2.6 mm at 160x120 (fx = 154 px); the D435's "about 1 mm at 0.5 m" corresponds to
    f of about 400 px, its depth imager's wider field of view at 640 px width.

    Every random draw comes from ``rng``, in a fixed order: the same seed gives bit-identical output.

    Args:
        depth_ideal_m: (H, W) z-depth in metres, 0 = no surface (no return).
        specular: (H, W) in [0, 1], the specularity of the surface seen at each pixel
            (``Material.specular`` of the object, 0 for matte background).
        intrinsics: the depth camera; its ``fx`` sets the stereo noise and quantisation.
        sensor: a :class:`SensorModel` or preset name (see :data:`SENSOR_PRESETS`).
        rng: source of all randomness.

    Returns:
        (H, W) float32 depth in metres, 0 = no return. "ideal" returns an exact copy.
    """
    sensor = get_sensor(sensor)
    depth, spec = _validate_inputs(depth_ideal_m, specular, intrinsics)
    if sensor.is_ideal:
        return depth.copy()
    valid = depth > 0
    shape = depth.shape

    out = _flying_pixels(depth, valid, sensor, rng) if sensor.flying_pixel_probability > 0 else depth.copy()

    wants_specular = sensor.specular_dropout_max > 0 and bool(spec.max(initial=0.0) > 0)
    theta = None
    if wants_specular or sensor.axial_sigma_angle_coeff_m > 0:
        theta = np.arccos(_cos_incidence(depth, intrinsics))

    has_axial = sensor.axial_sigma_const_m > 0 or sensor.axial_sigma_quadratic_per_m > 0
    has_axial = has_axial or sensor.axial_sigma_angle_coeff_m > 0
    noise = None
    if sensor.stereo_subpixel_rms_px > 0 or has_axial:
        noise = _unit_normal_field(shape, sensor.noise_correlation_px, rng)

    keep = valid
    if sensor.baseline_m > 0 and (
        sensor.stereo_subpixel_rms_px > 0 or sensor.disparity_step_px > 0 or np.isfinite(sensor.max_disparity_px)
    ):
        focal_baseline = np.float32(intrinsics.fx * sensor.baseline_m)
        with np.errstate(divide="ignore"):
            disparity_px = focal_baseline / np.where(valid, out, np.float32(np.inf))
        if sensor.stereo_subpixel_rms_px > 0:
            disparity_px += np.float32(sensor.stereo_subpixel_rms_px) * noise
        if sensor.disparity_step_px > 0:
            step = np.float32(sensor.disparity_step_px)
            disparity_px = np.round(disparity_px / step) * step
        keep = keep & (disparity_px > 0) & (disparity_px <= sensor.max_disparity_px)
        with np.errstate(divide="ignore"):
            out = np.where(keep, focal_baseline / disparity_px, np.float32(0.0))

    if has_axial:
        sigma = sensor.axial_sigma_const_m + sensor.axial_sigma_quadratic_per_m * (out - sensor.axial_sigma_z0_m) ** 2
        if sensor.axial_sigma_angle_coeff_m > 0:
            # Nguyen et al. add this term only beyond 60 degrees; it diverges at 90 degrees, so
            # clip where a surface is seen edge-on (such pixels are mostly dropped anyway).
            grazing = np.minimum(theta, np.float32(88.0 * _DEG))
            angle_term = np.where(theta > 60.0 * _DEG, grazing**2 / (np.float32(np.pi / 2) - grazing) ** 2, 0.0)
            sigma = sigma + sensor.axial_sigma_angle_coeff_m / np.sqrt(np.maximum(out, 1e-6)) * angle_term
        out = out + sigma.astype(np.float32) * noise
        keep = keep & (out > 0)

    drop_probability = np.full(shape, sensor.base_dropout_probability, np.float32)
    if wants_specular:
        logistic = 1.0 / (
            1.0 + np.exp(-(theta - sensor.specular_dropout_mid_angle_rad) / sensor.specular_dropout_width_rad)
        )
        drop_probability += spec * np.float32(sensor.specular_dropout_max) * logistic.astype(np.float32)
    if wants_specular or sensor.base_dropout_probability > 0:
        keep = keep & (rng.random(shape, dtype=np.float32) >= drop_probability)
    if sensor.speckle_seed_probability > 0:
        seeds = (rng.random(shape, dtype=np.float32) < sensor.speckle_seed_probability).astype(np.uint8)
        keep = keep & (cv2.dilate(seeds, _disc(int(sensor.speckle_radius_px))) == 0)

    keep = keep & (out >= sensor.min_range_m) & (out <= sensor.max_range_m)
    return np.where(keep, out, np.float32(0.0)).astype(np.float32, copy=False)
