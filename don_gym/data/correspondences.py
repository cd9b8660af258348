"""Pixel correspondences between two views of a scene, for self-supervised DON training.

Matches and non-matches are sampled as in the original DON code (docs/background.md, section
"Self-supervised DON training"); :func:`sample_correspondences` says where don_gym departs from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import (
    CameraIntrinsics,
    backproject_depth,
    invert_transform,
    project_points,
    rotation_angle_rad,
    transform_points,
)

__all__ = [
    "DEFAULT_MAX_NONMATCHES",
    "Correspondences",
    "camera_poses_differ",
    "sample_correspondences",
]

#: Default cap on the total number of non-matches (object + background) per image pair:
#: 150 per match for up to 1000 matches. The original code keeps 150 per match for every
#: match (over a million pairs at 10000 attempts); above the cap, non-matches are spread
#: over the matches at random, which keeps the loss an average over the same distribution.
DEFAULT_MAX_NONMATCHES = 150_000


def _empty_pixels() -> np.ndarray:
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True)
class Correspondences:
    """Pixel (u, v) = (column, row) pairs between image A and image B, int64.

    Attributes:
        matches_a, matches_b: (N, 2): ``matches_a[i]`` in A and ``matches_b[i]`` in B see
            the same surface point.
        nonmatches_object_a, nonmatches_object_b: (M, 2): ``a`` is a match pixel in A,
            ``b`` a pixel on B's object mask away from that match's true pixel in B.
        nonmatches_background_a, nonmatches_background_b: (K, 2): ``a`` is a match pixel
            in A, ``b`` a pixel on B's background (outside B's object mask).
    """

    matches_a: np.ndarray
    matches_b: np.ndarray
    nonmatches_object_a: np.ndarray
    nonmatches_object_b: np.ndarray
    nonmatches_background_a: np.ndarray
    nonmatches_background_b: np.ndarray

    @property
    def num_matches(self) -> int:
        return len(self.matches_a)

    @classmethod
    def empty(cls) -> Correspondences:
        return cls(*(_empty_pixels() for _ in range(6)))


def camera_poses_differ(
    T_world_camera_a: np.ndarray,
    T_world_camera_b: np.ndarray,
    min_translation_m: float = 0.2,
    min_rotation_rad: float = float(np.deg2rad(20.0)),
) -> bool:
    """Pair-selection rule of the original code (docs/background.md, section "Self-supervised DON
    training"): the camera centres are more than ``min_translation_m`` apart or the orientations
    differ by more than ``min_rotation_rad``."""
    T_a = np.asarray(T_world_camera_a, dtype=np.float64)
    T_b = np.asarray(T_world_camera_b, dtype=np.float64)
    translation = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    return translation > min_translation_m or rotation_angle_rad(T_a[:3, :3], T_b[:3, :3]) > min_rotation_rad


def _check_image(array: np.ndarray, name: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(array)
    if array.shape != shape:
        raise DonGymError(f"{name} has shape {array.shape}, expected (H, W) = {shape} from the intrinsics")
    return array


def _pixels_of(flat_indices: np.ndarray, width: int) -> np.ndarray:
    return np.stack([flat_indices % width, flat_indices // width], axis=1).astype(np.int64)


def sample_correspondences(
    depth_a_m: np.ndarray,
    depth_b_m: np.ndarray,
    object_mask_a: np.ndarray,
    object_mask_b: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_world_camera_a: np.ndarray,
    T_world_camera_b: np.ndarray,
    rng: np.random.Generator,
    num_match_attempts: int = 10000,
    nonmatches_per_match: int = 150,
    occlusion_margin_m: float = 0.003,
    max_matches: int | None = None,
    max_nonmatches: int | None = DEFAULT_MAX_NONMATCHES,
    nonmatch_exclusion_px: int = 2,
    max_depth_excess_m: float = 0.005,
) -> Correspondences:
    """Matches and non-matches between two views (depth in metres, 0 = no return).

    Matches: ``num_match_attempts`` pixels drawn uniformly, with replacement, from A's
    object mask; pruned where A has no depth; back-projected, moved into camera B and
    projected (rounded to the nearest pixel); pruned outside B, where B has no depth, and
    where B's depth is less than the projected depth minus ``occlusion_margin_m`` (the point
    is hidden in B). Unlike the original code, also pruned where B's depth exceeds the
    projected depth by more than ``max_depth_excess_m``: rounding to the nearest pixel at a
    silhouette or fold lands on a surface behind, and the original's one-sided test keeps
    such matches with 3D errors of several cm (measured: max 7 cm on ideal depth of a box,
    0.5 m away, at 160x120 to 640x480). 5 mm removes those while keeping most matches on
    noisy sensor depth (on raw D435 depth at 160x120 it keeps 63 % of them, at 320x240 91 %);
    ``np.inf`` restores the original test. B's object mask is not consulted (so a wrong mask
    in B cannot remove a geometrically valid match). ``max_matches`` keeps a random subset.

    Non-matches: ``nonmatches_per_match // 2`` per match on B's object mask (pixels within
    ``nonmatch_exclusion_px`` (Chebyshev) of the match's true pixel in B are redrawn, up to
    a few times, then dropped) and the same number on B's background. When
    ``num_matches * nonmatches_per_match`` exceeds ``max_nonmatches``, that many in total are
    drawn instead, each paired with a match chosen uniformly at random.

    Returns empty (0, 2) arrays where nothing can be sampled (empty masks, no overlap).
    """
    shape = (intrinsics.height, intrinsics.width)
    depth_a = _check_image(depth_a_m, "depth_a_m", shape).astype(np.float64, copy=False)
    depth_b = _check_image(depth_b_m, "depth_b_m", shape).astype(np.float64, copy=False)
    mask_a = _check_image(object_mask_a, "object_mask_a", shape).astype(bool, copy=False)
    mask_b = _check_image(object_mask_b, "object_mask_b", shape).astype(bool, copy=False)
    counts = (num_match_attempts, nonmatches_per_match, occlusion_margin_m, nonmatch_exclusion_px, max_depth_excess_m)
    if min(counts) < 0:
        raise DonGymError(
            "num_match_attempts, nonmatches_per_match, occlusion_margin_m, nonmatch_exclusion_px and "
            f"max_depth_excess_m must be >= 0, got {counts}"
        )
    if max_matches is not None and max_matches < 0:
        raise DonGymError(f"max_matches must be >= 0 or None, got {max_matches}")
    if max_nonmatches is not None and max_nonmatches < 0:
        raise DonGymError(f"max_nonmatches must be >= 0 or None, got {max_nonmatches}")
    height, width = shape

    candidates_a = np.flatnonzero(mask_a)
    if candidates_a.size == 0 or num_match_attempts == 0:
        return Correspondences.empty()
    attempts = candidates_a[rng.integers(0, candidates_a.size, size=num_match_attempts)]
    attempts = attempts[depth_a.reshape(-1)[attempts] > 0]
    uv_a = _pixels_of(attempts, width)

    T_b_a = invert_transform(np.asarray(T_world_camera_b, dtype=np.float64)) @ np.asarray(
        T_world_camera_a, dtype=np.float64
    )
    points_b = transform_points(T_b_a, backproject_depth(intrinsics, depth_a, uv_a))
    uv_b_float, z_b = project_points(intrinsics, points_b)
    in_front = z_b > 0
    uv_b = np.zeros_like(uv_a)
    uv_b[in_front] = np.rint(uv_b_float[in_front]).astype(np.int64)
    inside = in_front & (uv_b[:, 0] >= 0) & (uv_b[:, 0] < width) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < height)
    observed_b = np.zeros(len(uv_a))
    observed_b[inside] = depth_b[uv_b[inside, 1], uv_b[inside, 0]]
    visible = inside & (observed_b > 0) & (observed_b >= z_b - occlusion_margin_m)
    visible &= observed_b <= z_b + max_depth_excess_m
    uv_a, uv_b = uv_a[visible], uv_b[visible]
    if max_matches is not None and len(uv_a) > max_matches:
        # Attempts are i.i.d. draws, so the first max_matches are a uniform random subset.
        uv_a, uv_b = uv_a[:max_matches], uv_b[:max_matches]
    num_matches = len(uv_a)
    if num_matches == 0:
        return Correspondences.empty()

    per_kind = nonmatches_per_match // 2
    total_per_kind = num_matches * per_kind
    if max_nonmatches is not None and 2 * total_per_kind > max_nonmatches:
        total_per_kind = max_nonmatches // 2
        owners_object = rng.integers(0, num_matches, size=total_per_kind)
        owners_background = rng.integers(0, num_matches, size=total_per_kind)
    else:
        owners_object = np.repeat(np.arange(num_matches), per_kind)
        owners_background = owners_object

    # Pixels are handled as separate u and v columns until the end: numpy reduces along a
    # length-2 axis far slower than it compares two 1-D arrays.
    nonmatch_object_a, nonmatch_object_b = _empty_pixels(), _empty_pixels()
    object_v, object_u = np.nonzero(mask_b)
    if object_u.size and owners_object.size:
        drawn = rng.integers(0, object_u.size, size=owners_object.size)
        true_u, true_v = uv_b[owners_object, 0], uv_b[owners_object, 1]

        def near_true_match(drawn: np.ndarray, true_u: np.ndarray, true_v: np.ndarray) -> np.ndarray:
            near_u = np.abs(object_u[drawn] - true_u) <= nonmatch_exclusion_px
            return near_u & (np.abs(object_v[drawn] - true_v) <= nonmatch_exclusion_px)

        # Redraw those too close to the true match a few times, then drop the rest (a tiny
        # object mask may have no pixel far enough).
        close = near_true_match(drawn, true_u, true_v)
        for _ in range(3):
            redo = np.flatnonzero(close)
            if redo.size == 0:
                break
            drawn[redo] = rng.integers(0, object_u.size, size=redo.size)
            close[redo] = near_true_match(drawn[redo], true_u[redo], true_v[redo])
        keep = np.flatnonzero(~close)
        drawn = drawn[keep]
        nonmatch_object_a = uv_a[owners_object[keep]]
        nonmatch_object_b = np.stack([object_u[drawn], object_v[drawn]], axis=1).astype(np.int64)
    nonmatch_background_a, nonmatch_background_b = _empty_pixels(), _empty_pixels()
    background_b = np.flatnonzero(~mask_b.reshape(-1))
    if background_b.size and owners_background.size:
        drawn = background_b[rng.integers(0, background_b.size, size=owners_background.size)]
        nonmatch_background_a, nonmatch_background_b = uv_a[owners_background], _pixels_of(drawn, width)

    return Correspondences(
        matches_a=uv_a,
        matches_b=uv_b,
        nonmatches_object_a=nonmatch_object_a,
        nonmatches_object_b=nonmatch_object_b,
        nonmatches_background_a=nonmatch_background_a,
        nonmatches_background_b=nonmatch_background_b,
    )
