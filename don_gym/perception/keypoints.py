"""Keypoints from descriptor images: matching, robust depth and 3D points (pure array functions).

A *keypoint* is a reference descriptor ``d`` (D,) tracked in a descriptor image (H, W, D): its
best-matching pixel, the 3D point there from the depth image, and a match confidence
(:func:`locate_keypoints`), the DON way of finding a point on an object (Florence et al. 2018;
Kupcsik et al. 2021, "Grasp Pose Prediction"). Units and frames as in :mod:`don_gym.geometry`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, pixel_rays, transform_points

__all__ = [
    "DEFAULT_BORDER_MARGIN_PX",
    "DEFAULT_CONFIDENCE_SIGMA",
    "DEFAULT_MAX_RADIUS_PX",
    "DEFAULT_MIN_RADIUS_PX",
    "DEFAULT_SOFT_TEMPERATURE",
    "Keypoints",
    "best_match",
    "descriptor_distances",
    "local_matches",
    "locate_keypoints",
    "match_confidence",
    "match_region",
    "project_visible",
    "robust_depth",
    "robust_point_from_depth",
    "sample_descriptors",
    "soft_match",
]

#: Descriptor distance (descriptor units) at which the match confidence is exp(-1) ~ 0.37.
#: The optimal descriptors span [0, 1] per dimension and the self-supervised DON's non-match
#: margin is 0.5, so 0.1 separates a match from a neighbouring point in both.
DEFAULT_CONFIDENCE_SIGMA = 0.1
#: Temperature (descriptor units) of the soft match's weights. It has to exceed a learned model's
#: descriptor error, or the weights single out the one pixel whose error happens to be smallest, an
#: arbitrary point of the ring's arc: the 640x480 supervised toolcap networks miss the optimal
#: descriptors on the part by a median 0.10 (mask) to 0.18 (edge), and at 0.05 their axis-yaw error
#: was a median 5-16 degrees against 2-5 at 0.15 (random poses, seeds 5000-5015, not the benchmark's
#: fixed poses). Exact (oracle) descriptors change by ~0.05 per 1.5 mm along the toolcap's outer
#: surface, so 0.15 still keeps the weights within ~5 mm of the ring along the axis.
DEFAULT_SOFT_TEMPERATURE = 0.15
#: Pixels along each edge of the frame where a network's best matches are not searched (see
#: :func:`match_region`; docs/background.md, "Matching away from the frame's edge"). A network's output cells
#: at the edge come from features that saw the convolutions' zero padding, not the scene, and there the
#: shipped networks put most of their matches more than 100 mm off on the development scenes; 16 px is two
#: cells of their 8-px output stride. Exact descriptors (the oracle) keep the whole frame.
DEFAULT_BORDER_MARGIN_PX = 16
#: Depth window radii in pixels (see :func:`robust_depth`).
DEFAULT_MIN_RADIUS_PX = 1
DEFAULT_MAX_RADIUS_PX = 8


def _as_descriptor_image(descriptor_image: np.ndarray) -> np.ndarray:
    image = np.asarray(descriptor_image)
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0 or image.shape[2] == 0:
        raise DonGymError(f"descriptor_image: expected an (H, W, D) array, got shape {image.shape}")
    return image.astype(np.float32, copy=False)


def _as_reference(reference: np.ndarray, dim: int) -> np.ndarray:
    reference = np.asarray(reference, dtype=np.float32)
    if reference.ndim == 1:
        reference = reference[None]
    if reference.ndim != 2 or reference.shape[1] != dim or reference.shape[0] == 0:
        raise DonGymError(
            f"reference descriptors: expected shape (K, {dim}) (the descriptor image has {dim} dimensions), "
            f"got {reference.shape}"
        )
    if not np.all(np.isfinite(reference)):
        raise DonGymError("reference descriptors: contain NaN or infinite values")
    return reference


def _as_uv(uv: np.ndarray) -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim == 1:
        uv = uv[None]
    if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
        raise DonGymError(f"uv: expected finite (K, 2) pixel coordinates (u, v), got shape {uv.shape}")
    return uv


def _as_depth(depth_m: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise DonGymError(f"depth_m: expected an (H, W) depth image in metres, got shape {depth.shape}")
    return depth


def descriptor_distances(descriptor_image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Euclidean distance of every pixel's descriptor to each reference descriptor.

    Args:
        descriptor_image: (H, W, D) descriptors.
        reference: (K, D) reference descriptors (a single (D,) one is accepted as K = 1).

    Returns:
        (K, H, W) float32 distances in descriptor units.
    """
    image = _as_descriptor_image(descriptor_image)
    reference = _as_reference(reference, image.shape[2])
    # Differences, not the |a|^2 - 2ab + |b|^2 expansion: exact matches must give exactly 0 so
    # that equal descriptors tie exactly. One image plane at a time into preallocated float32
    # buffers: an order of magnitude faster than reducing an (H, W, D) temporary over its short last axis.
    planes = np.moveaxis(image, 2, 0)
    distances = np.empty((len(reference), *image.shape[:2]), dtype=np.float32)
    term = np.empty(image.shape[:2], dtype=np.float32)
    for total, r in zip(distances, reference, strict=True):
        np.square(np.subtract(planes[0], r[0], out=total), out=total)
        for plane, value in zip(planes[1:], r[1:], strict=True):
            total += np.square(np.subtract(plane, value, out=term), out=term)
        np.sqrt(total, out=total)
    return distances


def _check_border_margin(border_margin_px: int, height: int, width: int) -> int:
    if isinstance(border_margin_px, bool) or not isinstance(border_margin_px, (int, np.integer)):
        raise DonGymError(f"border_margin_px={border_margin_px!r}: expected an integer number of pixels >= 0")
    if border_margin_px < 0 or 2 * border_margin_px >= min(height, width):
        raise DonGymError(
            f"border_margin_px={border_margin_px}: expected >= 0 and leaving pixels in a {width}x{height} frame "
            f"(below {(min(height, width) + 1) // 2})"
        )
    return int(border_margin_px)


def match_region(height: int, width: int, border_margin_px: int = DEFAULT_BORDER_MARGIN_PX) -> np.ndarray:
    """(H, W) bool, the pixels a best match may land on: all but the outer ``border_margin_px`` pixels of
    each edge (see :data:`DEFAULT_BORDER_MARGIN_PX` for why). 0 gives every pixel."""
    margin = _check_border_margin(border_margin_px, height, width)
    region = np.zeros((height, width), dtype=bool)
    region[margin : height - margin, margin : width - margin] = True
    return region


def _best_from_distances(distances: np.ndarray, border_margin_px: int = 0) -> tuple[np.ndarray, np.ndarray]:
    K, H, W = distances.shape
    margin = _check_border_margin(border_margin_px, H, W)
    inner = distances[:, margin : H - margin, margin : W - margin]
    inner_w = W - 2 * margin
    index = np.argmin(inner.reshape(K, -1), axis=1)
    uv = np.stack([index % inner_w + margin, index // inner_w + margin], axis=1).astype(np.int64)
    return uv, distances[np.arange(K), uv[:, 1], uv[:, 0]].astype(np.float32)


def best_match(
    descriptor_image: np.ndarray, reference: np.ndarray, border_margin_px: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel of smallest Euclidean descriptor distance for each reference descriptor, as in the
    original DON evaluation.

    Args:
        descriptor_image: (H, W, D) descriptors.
        reference: (K, D) reference descriptors.
        border_margin_px: search only :func:`match_region` of this margin (0: the whole image, the
            original DON's search; the protocol and the agents use :data:`DEFAULT_BORDER_MARGIN_PX`).

    Returns:
        ``(uv, distance)``: (K, 2) int64 pixel coordinates (u = column, v = row) and the (K,) float32
        descriptor distance there. Ties go to the first pixel in row-major order.
    """
    return _best_from_distances(descriptor_distances(descriptor_image, reference), border_margin_px)


def _soft_from_distances(
    distances: np.ndarray, best_uv: np.ndarray, best_distance: np.ndarray, window_px: np.ndarray, temperature: float
) -> np.ndarray:
    K, H, W = distances.shape
    uv = best_uv.astype(np.float64)
    for k in range(K):
        radius = float(window_px[k])
        if radius < 1.0:
            continue
        u0, v0 = int(best_uv[k, 0]), int(best_uv[k, 1])
        r = int(np.ceil(radius))
        u_lo, u_hi, v_lo, v_hi = max(u0 - r, 0), min(u0 + r + 1, W), max(v0 - r, 0), min(v0 + r + 1, H)
        vv, uu = np.mgrid[v_lo:v_hi, u_lo:u_hi]
        inside = (uu - u0) ** 2 + (vv - v0) ** 2 <= radius**2
        d = distances[k, v_lo:v_hi, u_lo:u_hi].astype(np.float64)
        # Relative to the best distance: the weights then do not depend on how well the model
        # reproduces the reference descriptor, only on how much worse each pixel matches.
        weight = np.where(inside, np.exp(-(d**2 - float(best_distance[k]) ** 2) / temperature**2), 0.0)
        total = weight.sum()
        uv[k] = (np.sum(weight * uu) / total, np.sum(weight * vv) / total)
    return uv


def soft_match(
    descriptor_image: np.ndarray,
    reference: np.ndarray,
    window_px: float | np.ndarray,
    temperature: float = DEFAULT_SOFT_TEMPERATURE,
    border_margin_px: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Best match refined to the descriptor-weighted mean pixel around it.

    The mean over a disc of ``window_px`` pixels around the best match, weights
    ``exp(-(d^2 - d_best^2) / temperature^2)``. Why: on a part with a symmetry axis the optimal
    (GISIF) descriptors are equal all around a ring about the axis, so the whole visible arc of
    that ring matches equally well and the best match is an arbitrary pixel of it, anywhere across
    the part. The weighted mean of the arc is its middle, the pixel over the axis, which is what a
    grasp needs.

    Args:
        descriptor_image: (H, W, D) descriptors.
        reference: (K, D) reference descriptors.
        window_px: radius in pixels of the disc around each best match that is averaged, a scalar
            or (K,); below 1 the best match itself is returned.
        temperature: weight scale in descriptor units (> 0).
        border_margin_px: the best match is searched in :func:`match_region` of this margin (0: everywhere).

    Returns:
        ``(uv, distance)``: (K, 2) float64 sub-pixel coordinates (u, v) and the (K,) float32 best-match
        distance.
    """
    if not (np.isfinite(temperature) and temperature > 0):
        raise DonGymError(f"temperature={temperature!r}: expected a positive number (descriptor units)")
    distances = descriptor_distances(descriptor_image, reference)
    window = np.broadcast_to(np.asarray(window_px, dtype=np.float64), (distances.shape[0],))
    if not np.all(np.isfinite(window)):
        raise DonGymError(f"window_px={window_px!r}: expected finite radii in pixels")
    best_uv, best_distance = _best_from_distances(distances, border_margin_px)
    return _soft_from_distances(distances, best_uv, best_distance, window, temperature), best_distance


def local_matches(
    distances: np.ndarray,
    threshold: float,
    window_px: float,
    temperature: float = DEFAULT_SOFT_TEMPERATURE,
    max_matches: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Every place one reference descriptor matches, for scenes with several instances of a part: the local
    minima of its distance image below ``threshold``, at least ``window_px`` apart (the best first), each
    refined to the descriptor-weighted mean pixel of a ``window_px`` disc around it as :func:`soft_match` does.

    Args:
        distances: (H, W) descriptor distances to one reference descriptor (:func:`descriptor_distances`).
        threshold: largest distance of a match (descriptor units).
        window_px: suppression and soft-match radius in pixels (a ring's diameter: one match per ring).
        temperature: soft-match weight scale (descriptor units).
        max_matches: keep at most this many, the best (None: all).

    Returns:
        ``(uv, distance)``: (M, 2) float64 sub-pixel coordinates (u, v) and the (M,) float32 distances at the
        minima, best first.
    """
    from scipy.ndimage import minimum_filter

    d = np.asarray(distances, dtype=np.float32)
    if d.ndim != 2:
        raise DonGymError(f"distances: expected an (H, W) distance image, got shape {d.shape}")
    size = 2 * max(1, int(round(window_px))) + 1
    lowest = minimum_filter(d, size=size, mode="nearest")
    v, u = np.nonzero((d <= lowest) & (d < threshold))
    order = np.argsort(d[v, u], kind="stable")
    kept: list[tuple[int, int]] = []
    for index in order:
        if max_matches is not None and len(kept) >= max_matches:
            break
        # Plateaus (equal minima, e.g. along a ring's arc) give several pixels: one per window.
        if all((u[index] - ku) ** 2 + (v[index] - kv) ** 2 > window_px**2 for ku, kv in kept):
            kept.append((int(u[index]), int(v[index])))
    best_uv = np.array(kept, dtype=np.int64).reshape(-1, 2)
    best = d[best_uv[:, 1], best_uv[:, 0]].astype(np.float32)
    if len(best_uv) == 0:
        return np.zeros((0, 2)), best
    K = len(best_uv)
    stacked = np.broadcast_to(d, (K, *d.shape))
    uv = _soft_from_distances(stacked, best_uv, best, np.full(K, float(window_px)), temperature)
    return uv, best


def match_confidence(distance: np.ndarray, sigma: float = DEFAULT_CONFIDENCE_SIGMA) -> np.ndarray:
    """Confidence in [0, 1] of a match at descriptor distance ``distance``: ``exp(-(d / sigma)^2)``.

    1 for an exact match, decreasing strictly with the distance. Returns float32 of ``distance``'s shape.
    """
    if not (np.isfinite(sigma) and sigma > 0):
        raise DonGymError(f"sigma={sigma!r}: expected a positive descriptor distance")
    d = np.asarray(distance, dtype=np.float64)
    return np.exp(-np.square(d / sigma)).astype(np.float32)


def robust_depth(
    depth_m: np.ndarray,
    uv: np.ndarray,
    min_radius_px: int = DEFAULT_MIN_RADIUS_PX,
    max_radius_px: int = DEFAULT_MAX_RADIUS_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth at pixels despite holes: median of the valid depths in a growing window.

    Metal parts give holes (zero depth) in stereo depth. The depth of a pixel is the median of
    the valid depths (> 0, finite) in a square window of radius ``min_radius_px`` around it, the
    window grown one pixel at a time up to ``max_radius_px`` until it holds a valid depth.

    Args:
        depth_m: (H, W) depth in metres, 0 (or NaN/inf) where the sensor had no return.
        uv: (K, 2) pixel coordinates (u, v), rounded to the nearest pixel; they may lie outside
            the image (the window is clipped to it).
        min_radius_px: radius of the first square window (0: the pixel alone).
        max_radius_px: largest radius tried.

    Returns:
        ``(depth, valid)``: (K,) float32 metres (0 where not valid) and (K,) bool, False when no
        valid depth lies within ``max_radius_px``.
    """
    depth = _as_depth(depth_m)
    uv = np.rint(_as_uv(uv)).astype(np.int64)
    if not (0 <= int(min_radius_px) <= int(max_radius_px)):
        raise DonGymError(
            f"min_radius_px={min_radius_px!r}, max_radius_px={max_radius_px!r}: expected 0 <= min <= max pixels"
        )
    H, W = depth.shape
    good = np.isfinite(depth) & (depth > 0)
    out = np.zeros(len(uv), dtype=np.float32)
    valid = np.zeros(len(uv), dtype=bool)
    for k, (u, v) in enumerate(uv):
        for radius in range(int(min_radius_px), int(max_radius_px) + 1):
            v_lo, v_hi, u_lo, u_hi = (
                max(v - radius, 0),
                min(v + radius + 1, H),
                max(u - radius, 0),
                min(u + radius + 1, W),
            )
            if v_lo >= v_hi or u_lo >= u_hi:
                continue
            window_good = good[v_lo:v_hi, u_lo:u_hi]
            if window_good.any():
                out[k] = float(np.median(depth[v_lo:v_hi, u_lo:u_hi][window_good]))
                valid[k] = True
                break
    return out, valid


def robust_point_from_depth(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    uv: np.ndarray,
    min_radius_px: int = DEFAULT_MIN_RADIUS_PX,
    max_radius_px: int = DEFAULT_MAX_RADIUS_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame 3D points at (sub-)pixels, with the depth of :func:`robust_depth`.

    Args:
        depth_m: (H, W) z-depth in metres, 0 = no return.
        intrinsics: the camera's pinhole intrinsics.
        uv: (K, 2) pixel coordinates (u, v); the ray goes through the exact (sub-pixel) coordinates.
        min_radius_px, max_radius_px: see :func:`robust_depth`.

    Returns:
        ``(points_camera, valid)``: (K, 3) float64 metres, OpenCV camera frame (the camera centre,
        zeros, where not valid) and (K,) bool. To the world: ``transform_points(T_world_camera, p)``.
    """
    uv = _as_uv(uv)
    depth, valid = robust_depth(depth_m, uv, min_radius_px, max_radius_px)
    return pixel_rays(intrinsics, uv) * depth[:, None].astype(np.float64), valid


def sample_descriptors(descriptor_image: np.ndarray, uv: np.ndarray, radius_px: int = 1) -> np.ndarray:
    """Per-dimension median descriptor in a square window of ``radius_px`` around each pixel.

    Args:
        descriptor_image: (H, W, D) descriptors.
        uv: (N, 2) pixel coordinates (u, v) inside the image (rounded to the nearest pixel).
        radius_px: window radius (0: the pixel itself); the window is clipped to the image.

    Returns:
        (N, D) float32 descriptors.
    """
    image = _as_descriptor_image(descriptor_image)
    uv = np.rint(_as_uv(uv)).astype(np.int64)
    H, W, D = image.shape
    if np.any((uv[:, 0] < 0) | (uv[:, 0] >= W) | (uv[:, 1] < 0) | (uv[:, 1] >= H)):
        raise DonGymError(f"uv: every pixel must lie inside the {W}x{H} image")
    out = np.empty((len(uv), D), dtype=np.float32)
    r = int(radius_px)
    for n, (u, v) in enumerate(uv):
        window = image[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1].reshape(-1, D)
        out[n] = np.median(window, axis=0)
    return out


def project_visible(
    points_camera: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray, tolerance_m: float = 0.003
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of camera-frame points and whether each is visible in a depth image.

    Args:
        points_camera: (N, 3) points in metres, OpenCV camera frame.
        intrinsics: pinhole intrinsics of the image.
        depth_m: (H, W) depth of the surfaces seen (e.g. a rendered object depth); 0 = nothing.
        tolerance_m: a point is visible when it lies in front of the camera, inside the image, and
            the depth at its (nearest) pixel is within this of its own z.

    Returns:
        ``(uv, visible)``: (N, 2) int64 nearest pixels (-1 where the point is behind the camera)
        and (N,) bool.
    """
    depth = _as_depth(depth_m)
    points = np.asarray(points_camera, dtype=np.float64).reshape(-1, 3)
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * points[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * points[:, 1] / z + intrinsics.cy
    in_front = z > 0
    uv = np.full((len(points), 2), -1, dtype=np.int64)
    uv[in_front] = np.rint(np.stack([u[in_front], v[in_front]], axis=1)).astype(np.int64)
    H, W = depth.shape
    inside = in_front & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    visible = np.zeros(len(points), dtype=bool)
    seen = depth[uv[inside, 1], uv[inside, 0]]
    visible[inside] = (seen > 0) & (np.abs(seen - z[inside]) <= tolerance_m)
    return uv, visible


@dataclass(frozen=True)
class Keypoints:
    """K keypoints found in one frame (see :func:`locate_keypoints`).

    Attributes:
        pixels: (K, 2) float64 (u, v) soft-match pixels.
        points_camera: (K, 3) float64 metres, camera frame (zeros where ``depth_valid`` is False).
        points_world: (K, 3) float64 metres, world frame (the camera centre where not depth-valid).
        distance: (K,) float32 best-match descriptor distance.
        confidence: (K,) float32 in [0, 1], :func:`match_confidence` of ``distance``, 0 without depth.
        depth_valid: (K,) bool, a valid depth was found near the pixel.
    """

    pixels: np.ndarray
    points_camera: np.ndarray
    points_world: np.ndarray
    distance: np.ndarray
    confidence: np.ndarray
    depth_valid: np.ndarray


def locate_keypoints(
    descriptor_image: np.ndarray,
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_world_camera: np.ndarray,
    reference: np.ndarray,
    window_m: float | np.ndarray = 0.0,
    temperature: float = DEFAULT_SOFT_TEMPERATURE,
    sigma: float = DEFAULT_CONFIDENCE_SIGMA,
    min_radius_px: int = DEFAULT_MIN_RADIUS_PX,
    max_radius_px: int = DEFAULT_MAX_RADIUS_PX,
    border_margin_px: int = 0,
) -> Keypoints:
    """Match reference descriptors and lift them to 3D: best match, soft match, robust depth, world.

    Args:
        descriptor_image: (H, W, D) descriptors of the frame.
        depth_m: (H, W) depth in metres of the same frame (0 = no return).
        intrinsics: pinhole intrinsics of the frame (H x W).
        T_world_camera: (4, 4) camera pose in the world.
        reference: (K, D) reference descriptors.
        window_m: soft-match disc radius in metres (scalar or (K,)), converted to pixels with the
            depth at each best match (``fx * window_m / z``); 0 keeps the best match.
        temperature: soft-match weight scale (descriptor units).
        sigma: confidence scale (descriptor units), see :func:`match_confidence`.
        min_radius_px, max_radius_px: depth windows, see :func:`robust_depth`.
        border_margin_px: best matches are searched in :func:`match_region` of this margin (0: everywhere;
            a descriptor source's own is
            :attr:`~don_gym.perception.descriptor_sources.DescriptorSource.border_margin_px`).

    Returns:
        :class:`Keypoints`.
    """
    image = _as_descriptor_image(descriptor_image)
    depth = _as_depth(depth_m)
    if depth.shape != image.shape[:2]:
        raise DonGymError(f"depth_m {depth.shape} and descriptor_image {image.shape[:2]}: expected the same (H, W)")
    T = np.asarray(T_world_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DonGymError(f"T_world_camera: expected a finite (4, 4) transform, got shape {T.shape}")
    distances = descriptor_distances(image, reference)
    best_uv, best_distance = _best_from_distances(distances, border_margin_px)
    window_m = np.broadcast_to(np.asarray(window_m, dtype=np.float64), (len(best_uv),))
    if np.any(window_m > 0):
        z_best, z_valid = robust_depth(depth, best_uv, min_radius_px, max_radius_px)
        with np.errstate(divide="ignore", invalid="ignore"):
            window_px = np.where(z_valid, intrinsics.fx * window_m / np.maximum(z_best, 1e-6), 0.0)
        pixels = _soft_from_distances(distances, best_uv, best_distance, window_px, temperature)
    else:
        pixels = best_uv.astype(np.float64)
    points_camera, depth_valid = robust_point_from_depth(depth, intrinsics, pixels, min_radius_px, max_radius_px)
    confidence = np.where(depth_valid, match_confidence(best_distance, sigma), 0.0).astype(np.float32)
    return Keypoints(
        pixels=pixels,
        points_camera=points_camera,
        points_world=transform_points(T, points_camera),
        distance=best_distance,
        confidence=confidence,
        depth_valid=depth_valid,
    )
