"""The tracking protocol's pure core (Kupcsik et al. 2021, Sec. "Quantitative Evaluation of Prediction
Accuracy", with the original DON metrics of Florence et al. 2018): arrays in, arrays out.

Reference pixels and their world points, best matches of reference descriptors, the 3D error and the 3D error
modulo a part's symmetry, where a match lands (:func:`attribute_matches`), and :class:`TrackingMatches`, every
match of one method with its summary: percentiles with 95% intervals from resampling scenes
(:mod:`don_gym.stats`), the tail and the share of far matches. The runner over datasets is
:mod:`don_gym.evaluation.tracking`; the protocol is described in docs/background.md, "Tracking evaluation
protocol".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, invert_transform, project_points, transform_points
from don_gym.objects import ObjectModel
from don_gym.perception.keypoints import descriptor_distances, match_region, project_visible
from don_gym.stats import (
    BOOTSTRAP_RESAMPLES,
    DEFAULT_CONFIDENCE,
    percentile_interval,
    resampled_means,
    resampled_percentiles,
    scene_resample_counts,
)

__all__ = [
    "BOOTSTRAP_SEED",
    "EDGE_BANDS_PX",
    "FAR_MATCH_M",
    "LONG_TAIL_RATIO",
    "MATCH_CATEGORIES",
    "PERCENTILES",
    "PILE_CATEGORY",
    "TABLE_TOLERANCE_M",
    "Matches",
    "TrackingMatches",
    "attribute_matches",
    "far_matches",
    "interval_pair",
    "long_tail_verdict",
    "match_descriptors",
    "part_halves_axis",
    "percentiles",
    "select_reference_pixels",
    "symmetric_distance",
    "tail_by_edge_distance",
    "tracking_errors",
    "usable_reference_mask",
    "visible_projections",
    "world_points_at",
    "worst_matches",
]

#: Percentiles reported for every metric.
PERCENTILES: tuple[int, ...] = (50, 90, 99)

# --- tails ----------------------------------------------------------------------------------------
#: A match further than this from the true point (3D error, metres) is *far*: off the part.
FAR_MATCH_M = 0.100
#: Upper bounds (pixels) of the bands of a reference pixel's distance inside the silhouette that
#: :func:`tail_by_edge_distance` reports: within the edge-blend width of the supervised-edge targets at 640 px
#: (:data:`~don_gym.data.render.EDGE_WIDTH_PX_AT_640`), twice it, and about the network's output stride.
EDGE_BANDS_PX = (3.0, 6.0, 10.0)
#: A 3D error has a long tail when its 99th percentile is at least this many times its median.
LONG_TAIL_RATIO = 10.0
#: Where a match lands (:func:`attribute_matches`), by index.
#: ``another instance``: on another instance of a pile (datasets of bins only; tables of one part leave it out).
MATCH_CATEGORIES: tuple[str, ...] = (
    "part, wrong end",
    "part, elsewhere",
    "table",
    "background",
    "robot/fixture",
    "another instance",
)
#: The category only piles have.
PILE_CATEGORY = "another instance"
#: Where a reference descriptor's best match is searched (:attr:`TrackingConfig.match_within`).
#: fraction of this; the textured quads lie 0.2 mm above the table).
TABLE_TOLERANCE_M = 0.005
#: Seed of the scene bootstrap, so that a summary is the same on every run.
BOOTSTRAP_SEED = 0


def usable_reference_mask(object_mask: np.ndarray, depth_m: np.ndarray, erode_px: int = 1) -> np.ndarray:
    """(H, W) bool: object pixels at least ``erode_px`` pixels inside the mask with depth > 0."""
    mask = np.asarray(object_mask, dtype=bool)
    if erode_px > 0:
        kernel = np.ones((2 * erode_px + 1, 2 * erode_px + 1), dtype=np.uint8)
        mask = cv2.erode(mask.astype(np.uint8), kernel, borderValue=0).astype(bool)
    return mask & (np.asarray(depth_m) > 0)


def select_reference_pixels(usable: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``count`` distinct pixels of the (H, W) bool mask ``usable``, as (N, 2) int64 ``(u, v)``."""
    rows, cols = np.nonzero(usable)
    if len(rows) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pick = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
    return np.stack([cols[pick], rows[pick]], axis=1).astype(np.int64)


def world_points_at(
    uv: np.ndarray, depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) metres of integer pixels ``uv`` (N, 2) from a depth image, and (N,) bool
    "depth present". Pixels without depth give NaN points."""
    uv = np.asarray(uv, dtype=np.int64).reshape(-1, 2)
    points = transform_points(T_world_camera, backproject_depth(intrinsics, depth_m, uv))
    valid = np.asarray(depth_m)[uv[:, 1], uv[:, 0]] > 0
    points[~valid] = np.nan
    return points, valid


def visible_projections(
    points_world: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    depth_ideal_m: np.ndarray,
    tolerance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Where world points (N, 3) appear in a frame and whether they are visible there.

    Returns ``(uv, visible)``: (N, 2) float64 true projections (NaN behind the camera) and (N,)
    bool: in front of the camera, the nearest pixel inside the image, and the ideal depth there
    within ``tolerance_m`` of the point's depth (so it is not hidden behind something).
    """
    points_camera = transform_points(invert_transform(T_world_camera), np.asarray(points_world).reshape(-1, 3))
    uv, _ = project_points(intrinsics, points_camera)
    _, visible = project_visible(points_camera, intrinsics, depth_ideal_m, tolerance_m)
    return uv, visible


@dataclass(frozen=True)
class Matches:
    """Best matches of N reference descriptors in one descriptor image.

    Attributes:
        uv: (N, 2) int64 ``(u, v)`` of the closest descriptor.
        distance: (N,) float32 its L2 distance to the reference.
        fraction_closer: (N,) float64 fraction of all image pixels strictly closer to the reference
            than the pixel at ``true_uv`` (NaN where no true pixel was given).
    """

    uv: np.ndarray
    distance: np.ndarray
    fraction_closer: np.ndarray


def match_descriptors(
    descriptor_image: np.ndarray,
    references: np.ndarray,
    true_uv: np.ndarray | None = None,
    candidates: np.ndarray | None = None,
    border_margin_px: int = 0,
) -> Matches:
    """Best match (argmin L2 over the image, but for a margin along its edges) of each reference descriptor.

    Args:
        descriptor_image: (H, W, D) float descriptors.
        references: (N, D) reference descriptors.
        true_uv: optional (N, 2) integer pixels of the true matches (rows with a negative
            coordinate are skipped) for the fraction of pixels closer than the true match.
        candidates: optional (H, W) bool, the only pixels a match may land on (and that count as closer);
            None or an empty mask: every pixel.
        border_margin_px: matches land and count only in :func:`~don_gym.perception.keypoints.match_region` of this
            margin (0: the whole image), and within ``candidates`` there unless none of them is.
    """
    distances = descriptor_distances(descriptor_image, references)  # (N, H, W)
    count, height, width = distances.shape
    flat = distances.reshape(count, height * width)
    allowed = match_region(height, width, border_margin_px)
    if candidates is not None:
        within = allowed & np.asarray(candidates, dtype=bool)
        if within.any():
            allowed = within
    allowed = allowed.reshape(-1)
    pixels = int(allowed.sum())
    if pixels < allowed.size:
        flat = np.where(allowed[None], flat, np.inf)
    best = np.argmin(flat, axis=1)
    uv = np.stack([best % width, best // width], axis=1).astype(np.int64)
    fraction = np.full(count, np.nan)
    if true_uv is not None:
        true_uv = np.asarray(true_uv, dtype=np.int64).reshape(-1, 2)
        ok = (true_uv >= 0).all(axis=1) & (true_uv[:, 0] < width) & (true_uv[:, 1] < height)
        rows = np.flatnonzero(ok)
        at_true = flat[rows, true_uv[rows, 1] * width + true_uv[rows, 0]]
        fraction[rows] = (flat[rows] < at_true[:, None]).sum(axis=1) / float(pixels)
    return Matches(uv, flat[np.arange(count), best], fraction)


def symmetric_distance(
    points_a_world: np.ndarray,
    points_b_world: np.ndarray,
    T_world_object: np.ndarray,
    axis_point_object: np.ndarray,
    axis_object: np.ndarray,
) -> np.ndarray:
    """(N,) distance (m) between the rings that points a and b sweep about a symmetry axis.

    The axis passes through ``axis_point_object`` along ``axis_object`` (object frame). Each point
    becomes (height along the axis, distance from the axis); the result is the Euclidean distance
    in that plane: the smallest distance between a and any rotation of b about the axis.
    """
    axis = np.asarray(axis_object, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    T_object_world = invert_transform(T_world_object)

    def height_radius(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = transform_points(T_object_world, np.asarray(points).reshape(-1, 3)) - axis_point_object
        height = local @ axis
        return height, np.linalg.norm(local - height[:, None] * axis, axis=1)

    h_a, r_a = height_radius(points_a_world)
    h_b, r_b = height_radius(points_b_world)
    return np.hypot(h_a - h_b, r_a - r_b)


def tracking_errors(
    predicted_world: np.ndarray,
    truth_world: np.ndarray,
    T_world_object: np.ndarray,
    axis_point_object: np.ndarray,
    axis_object: np.ndarray | None,
    T_world_twins: Sequence[np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """3D errors (metres, (N,) each) of predicted world points (N, 3) against the true points (N, 3) of the
    object at ``T_world_object``, by their :class:`TrackingMatches` names.

    ``error_3d_m``: the distance; ``symmetric_error_m``: modulo the symmetry axis through ``axis_point_object``
    along ``axis_object`` (object frame; :func:`symmetric_distance`), NaN for ``axis_object`` None. With
    ``T_world_twins``, the poses of the other instances of the same part in a pile (possibly none), also
    ``error_3d_any_instance_m`` and ``symmetric_error_any_instance_m``: the smallest of the two errors over the
    object and each twin, the true point carried along with the instance (``T_twin @ inv(T_world_object)``).
    A predicted point of NaN (no depth) gives NaN errors.
    """
    predicted = np.asarray(predicted_world, dtype=np.float64).reshape(-1, 3)

    def errors(truth: np.ndarray, T_world_instance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        plain = np.linalg.norm(predicted - truth, axis=1)
        if axis_object is None:
            return plain, np.full(len(predicted), np.nan)
        return plain, symmetric_distance(predicted, truth, T_world_instance, axis_point_object, axis_object)

    truth = np.asarray(truth_world, dtype=np.float64).reshape(-1, 3)
    plain, symmetric = errors(truth, T_world_object)
    out = {"error_3d_m": plain, "symmetric_error_m": symmetric}
    if T_world_twins is None:
        return out
    plain_any, symmetric_any = plain, symmetric
    T_object_world = invert_transform(T_world_object)
    for T_world_twin in T_world_twins:
        twin = np.asarray(T_world_twin, dtype=np.float64)
        plain_twin, symmetric_twin = errors(transform_points(twin @ T_object_world, truth), twin)
        plain_any, symmetric_any = np.minimum(plain_any, plain_twin), np.minimum(symmetric_any, symmetric_twin)
    return out | {"error_3d_any_instance_m": plain_any, "symmetric_error_any_instance_m": symmetric_any}


def far_matches(error_3d_m: np.ndarray) -> np.ndarray:
    """(M,) bool: a 3D error (metres) above :data:`FAR_MATCH_M` (False where NaN: no depth)."""
    error = np.asarray(error_3d_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(error) & (error > FAR_MATCH_M)


def tail_by_edge_distance(
    edge_distance_px: np.ndarray,
    error_3d_m: np.ndarray,
    tail_m: float,
    bands_px: Sequence[float] = EDGE_BANDS_PX,
) -> list[dict[str, Any]]:
    """Where a tail comes from: the matches grouped by how far their reference pixel lies inside the part's
    silhouette in the reference frame.

    Args:
        edge_distance_px: (M,) distance (pixels) of each match's reference pixel from the silhouette (the
            reference frame's :func:`~don_gym.data.render.distance_inside_px`).
        error_3d_m: (M,) 3D errors (metres); NaN (no depth) is left out.
        tail_m: the tail's threshold (metres), e.g. a p99 target.
        bands_px: increasing upper bounds (pixels) of the bands; a last band takes everything beyond.

    Returns:
        One dict per band: ``low_px``, ``high_px`` (inf for the last), ``matches`` (with depth),
        ``share`` of all matches with depth, ``tail_share`` (over ``tail_m``) and ``far_share`` (over
        :data:`FAR_MATCH_M`) among the band's matches (None for an empty band).
    """
    distance = np.asarray(edge_distance_px, dtype=np.float64)
    error = np.asarray(error_3d_m, dtype=np.float64)
    if distance.shape != error.shape or distance.ndim != 1:
        raise DonGymError(
            f"tail_by_edge_distance: edge_distance_px and error_3d_m must both be (M,), got {distance.shape} and "
            f"{error.shape}"
        )
    edges = [float(b) for b in bands_px]
    if not edges or any(b <= 0 or not np.isfinite(b) for b in edges) or edges != sorted(set(edges)):
        raise DonGymError(f"bands_px {list(bands_px)}: expected increasing positive pixel distances")
    valid = np.isfinite(error)
    total = int(valid.sum())
    rows = []
    for low, high in zip([0.0, *edges], [*edges, np.inf], strict=True):
        band = valid & (distance > low) & (distance <= high)
        count = int(band.sum())
        rows.append(
            {
                "low_px": low,
                "high_px": high,
                "matches": count,
                "share": count / total if total else None,
                "tail_share": float(np.mean(error[band] > tail_m)) if count else None,
                "far_share": float(np.mean(error[band] > FAR_MATCH_M)) if count else None,
            }
        )
    return rows


def percentiles(values: np.ndarray, which: Sequence[int] = PERCENTILES) -> dict[str, float | None]:
    """``{"p50": ..., "p90": ..., "p99": ..., "mean": ...}`` of the finite values (None if there are none)."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if len(finite) == 0:
        return {**{f"p{p}": None for p in which}, "mean": None}
    return {**{f"p{p}": float(np.percentile(finite, p)) for p in which}, "mean": float(finite.mean())}


def part_halves_axis(model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
    """The line that splits a part into its two ends: ``(point, axis)`` (3,) each, object frame, metres.

    Along the part's +axis (the symmetry axis of an axisymmetric part), through the middle of its
    extent along that axis (not its centre of mass: the toolcap's flange would move the split
    towards the flange end)."""
    minus_end, plus_end = model.axis_endpoints()
    return 0.5 * (minus_end + plus_end), np.asarray(model.plus_axis, dtype=np.float64)


def attribute_matches(
    matched_uv: np.ndarray,
    true_points_world: np.ndarray,
    object_mask: np.ndarray,
    depth_ideal_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_world_camera: np.ndarray,
    T_world_object: np.ndarray,
    halves_point_object: np.ndarray,
    halves_axis_object: np.ndarray,
    table_height_m: float,
    table_bounds_xy_m: tuple[float, float, float, float] | None = None,
    table_tolerance_m: float = TABLE_TOLERANCE_M,
    other_instances_mask: np.ndarray | None = None,
) -> np.ndarray:
    """Where each match of one frame lands: (N,) int8 index into :data:`MATCH_CATEGORIES`.

    Args:
        matched_uv: (N, 2) integer ``(u, v)`` of the best matches in this frame.
        true_points_world: (N, 3) the true points (world, metres) the matches should have found.
        object_mask: (H, W) bool, the part's pixels in this frame.
        depth_ideal_m: (H, W) ideal (simulator) depth of this frame, 0 where nothing was hit.
        intrinsics, T_world_camera: the frame's camera and its *true* pose.
        T_world_object: the part's pose.
        halves_point_object, halves_axis_object: the line splitting the part into its two ends, object
            frame (:func:`part_halves_axis`).
        table_height_m: z (world, up) of the table top.
        table_bounds_xy_m: (x_min, x_max, y_min, y_max) of the table top, or None when nothing but the
            table top lies on its plane in view (as in the recorded scenes, whose floor is far below).
        table_tolerance_m: how close to the table plane a point counts as on it.
        other_instances_mask: (H, W) bool, in a pile the pixels of every other instance (of any part), or None.

    Categories, first that applies: on the part's mask and on the other side of the split from the
    true point (``part, wrong end``), on the part otherwise (``part, elsewhere``); the matched
    pixel's world point (ideal depth, true camera pose) within ``table_tolerance_m`` of the table
    plane and inside its bounds (``table``); above the table (``robot/fixture``: arm, gripper, cradle,
    distractor objects); no depth, below the table top or beside it (``background``: floor, beyond the
    table).
    """
    uv = np.asarray(matched_uv, dtype=np.int64).reshape(-1, 2)
    on_part = np.asarray(object_mask, dtype=bool)[uv[:, 1], uv[:, 0]]
    points, has_depth = world_points_at(uv, depth_ideal_m, intrinsics, T_world_camera)
    axis = np.asarray(halves_axis_object, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    T_object_world = invert_transform(T_world_object)

    def side(points_world: np.ndarray) -> np.ndarray:
        local = transform_points(T_object_world, np.asarray(points_world, dtype=np.float64).reshape(-1, 3))
        return np.sign((local - np.asarray(halves_point_object, dtype=np.float64)) @ axis)

    with np.errstate(invalid="ignore"):
        wrong_end = on_part & has_depth & (side(points) * side(true_points_world) < 0)
        height = points[:, 2] - table_height_m
        on_plane = has_depth & (np.abs(height) <= table_tolerance_m)
        if table_bounds_xy_m is not None:
            x0, x1, y0, y1 = table_bounds_xy_m
            on_plane &= (points[:, 0] >= x0) & (points[:, 0] <= x1) & (points[:, 1] >= y0) & (points[:, 1] <= y1)
        above = has_depth & (height > table_tolerance_m)
    index = {name: np.int8(k) for k, name in enumerate(MATCH_CATEGORIES)}
    category = np.full(len(uv), index["background"], dtype=np.int8)
    category[above] = index["robot/fixture"]
    category[on_plane] = index["table"]
    if other_instances_mask is not None:
        category[np.asarray(other_instances_mask, dtype=bool)[uv[:, 1], uv[:, 0]]] = index[PILE_CATEGORY]
    category[on_part] = index["part, elsewhere"]
    category[wrong_end] = index["part, wrong end"]
    return category


def long_tail_verdict(ratio_interval: Sequence[float], threshold: float = LONG_TAIL_RATIO) -> str:
    """Verdict on a 3D error's tail from the interval of its p99 / median: ``"no long tail"`` only when
    the whole interval lies below ``threshold``, ``"long tail"`` when it lies at or above it,
    ``"not settled"`` when it straddles it (the sample cannot tell) and ``"-"`` without an interval."""
    low, high = (float("nan"), float("nan")) if ratio_interval is None else map(float, ratio_interval)
    if np.isnan(low) or np.isnan(high):
        return "-"
    if high < threshold:
        return "no long tail"
    if low >= threshold:
        return "long tail"
    return "not settled"


def interval_pair(bounds: np.ndarray) -> list[float] | None:
    """``[low, high]`` for JSON, None when the interval is undefined."""
    low, high = (float(b) for b in bounds)
    return None if not (np.isfinite(low) and np.isfinite(high)) else [low, high]


@dataclass
class TrackingMatches:
    """All matches of one method, one entry per (scene, frame, reference point) with the point visible.

    Arrays of equal length M:

    - where: ``scene_id`` (the scene's position in :attr:`TrackingResult.scenes`, the unit the
      bootstrap resamples), ``dataset`` (position in :attr:`TrackingResult.datasets`), ``scene``
      (position in that dataset), ``frame``, ``point`` (reference point of the scene);
    - pixels: ``reference_frame``, ``reference_uv`` (M, 2) int, ``matched_uv`` (M, 2) int, ``true_uv``
      (M, 2) float (the true projection in ``frame``);
    - metrics: ``pixel_error_px``, ``error_3d_m`` (NaN where the matched pixel has no depth),
      ``symmetric_error_m`` (NaN for parts without a symmetry axis or without depth),
      ``fraction_closer``, ``depth_valid`` (bool);
    - tails: ``error_3d_ideal_m``, the 3D error with the matched pixel's ideal depth (equal to
      ``error_3d_m`` with ideal depth; with sensor depth it tells a far match the depth made from one the
      descriptors made), ``category`` int8 index into :data:`MATCH_CATEGORIES` (:func:`attribute_matches`);
    - piles only (None on datasets of one part, where they would equal the errors above):
      ``error_3d_any_instance_m`` and ``symmetric_error_any_instance_m``, the 3D error and the 3D error modulo
      symmetry to the same point on the nearest instance of the part in the scene (:func:`tracking_errors`).

    ``reference_points`` counts the reference pixels chosen over all scenes, ``scenes_evaluated`` the scenes.
    """

    scene_id: np.ndarray
    dataset: np.ndarray
    scene: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    reference_frame: np.ndarray
    reference_uv: np.ndarray
    matched_uv: np.ndarray
    true_uv: np.ndarray
    pixel_error_px: np.ndarray
    error_3d_m: np.ndarray
    symmetric_error_m: np.ndarray
    fraction_closer: np.ndarray
    depth_valid: np.ndarray
    error_3d_ideal_m: np.ndarray
    category: np.ndarray
    reference_points: int = 0
    scenes_evaluated: int = 0
    error_3d_any_instance_m: np.ndarray | None = None
    symmetric_error_any_instance_m: np.ndarray | None = None

    @property
    def far(self) -> np.ndarray:
        """(M,) bool: 3D error above :data:`FAR_MATCH_M` (False without depth)."""
        return far_matches(self.error_3d_m)

    def summary(
        self,
        resamples: int = BOOTSTRAP_RESAMPLES,
        confidence: float = DEFAULT_CONFIDENCE,
        seed: int = BOOTSTRAP_SEED,
    ) -> dict[str, Any]:
        """Counts, percentiles and their intervals (scene bootstrap, :mod:`don_gym.stats`), the tail (p99 /
        median, share of far matches, verdict), far matches by category and per scene.

        With the any-instance errors (piles) also their percentiles (``error_3d_any_instance_mm``,
        ``error_3d_symmetric_any_instance_mm``), ``tail_any_instance`` (far matches by the any-instance 3D
        error: count, share and its interval) and, per category, ``matches_any_instance``."""
        valid = self.depth_valid
        n_scenes = max(int(self.scenes_evaluated), int(self.scene_id.max()) + 1 if len(self.scene_id) else 1)
        # The same counts for every method of a result (same scenes, same seed): their intervals are paired.
        counts = scene_resample_counts(n_scenes, resamples, seed)
        metrics = {
            "error_3d_mm": self.error_3d_m * 1000.0,
            "error_3d_symmetric_mm": self.symmetric_error_m * 1000.0,
            "pixel_error_px": self.pixel_error_px,
            "fraction_closer": self.fraction_closer,
        }
        any_instance = self.error_3d_any_instance_m is not None
        if any_instance:
            metrics["error_3d_any_instance_mm"] = self.error_3d_any_instance_m * 1000.0
        if self.symmetric_error_any_instance_m is not None:
            metrics["error_3d_symmetric_any_instance_mm"] = self.symmetric_error_any_instance_m * 1000.0
        intervals: dict[str, dict[str, list[float] | None]] = {}
        replicates_3d = np.full((len(counts), len(PERCENTILES)), np.nan)
        for name, values in metrics.items():
            replicates = resampled_percentiles(values, self.scene_id, counts, PERCENTILES)
            if name == "error_3d_mm":
                replicates_3d = replicates
            bounds = percentile_interval(
                np.column_stack([replicates, resampled_means(values, self.scene_id, counts)]), confidence
            )
            keys = [*(f"p{p}" for p in PERCENTILES), "mean"]
            intervals[name] = {key: interval_pair(b) for key, b in zip(keys, bounds, strict=True)}
        p50, p99 = percentiles(metrics["error_3d_mm"])["p50"], percentiles(metrics["error_3d_mm"])["p99"]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio_replicates = replicates_3d[:, PERCENTILES.index(99)] / replicates_3d[:, PERCENTILES.index(50)]
        ratio_interval = interval_pair(percentile_interval(ratio_replicates, confidence))

        def far_share(error_m: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
            far = far_matches(error_m)
            far_or_nan = np.where(valid & np.isfinite(error_m), far.astype(np.float64), np.nan)
            return far, {
                "far_matches": int(far.sum()),
                "far_share": float(far.sum() / valid.sum()) if valid.any() else None,
                "far_share_interval": interval_pair(
                    percentile_interval(resampled_means(far_or_nan, self.scene_id, counts), confidence)
                ),
            }

        far, far_tail = far_share(self.error_3d_m)
        far_any, tail_any = far_share(self.error_3d_any_instance_m) if any_instance else (None, None)
        with np.errstate(invalid="ignore"):
            from_depth = far & (self.error_3d_ideal_m <= FAR_MATCH_M)
        per_scene_visible = np.bincount(self.scene_id, minlength=n_scenes)
        per_scene_depth = np.bincount(self.scene_id[valid], minlength=n_scenes)
        per_scene_far = np.bincount(self.scene_id[far], minlength=n_scenes)
        return {
            "counts": {
                "reference_points": int(self.reference_points),
                "visible_matches": int(len(self.scene_id)),
                "matches_with_depth": int(valid.sum()),
                "matches_without_depth": int((~valid).sum()),
            },
            **{name: percentiles(values) for name, values in metrics.items()},
            "fraction_3d_error_below": {
                f"{int(mm)}mm": (float(np.mean(self.error_3d_m[valid] < mm / 1000.0)) if valid.any() else None)
                for mm in (2.0, 5.0, 10.0, 20.0)
            },
            "intervals": intervals,
            "tail": {
                "p99_over_p50": None if p50 is None or p99 is None or p50 <= 0 else p99 / p50,
                "p99_over_p50_interval": ratio_interval,
                "verdict": long_tail_verdict(ratio_interval if ratio_interval is not None else (np.nan, np.nan)),
                **far_tail,
            },
            **({} if tail_any is None else {"tail_any_instance": tail_any}),
            "far_by_category": {
                name: {
                    "matches": int((far & (self.category == k)).sum()),
                    "far_only_from_depth": int((from_depth & (self.category == k)).sum()),
                    **(
                        {} if far_any is None else {"matches_any_instance": int((far_any & (self.category == k)).sum())}
                    ),
                }
                for k, name in enumerate(MATCH_CATEGORIES)
            },
            "per_scene": [
                {"visible_matches": int(v), "matches_with_depth": int(d), "far_matches": int(f)}
                for v, d, f in zip(per_scene_visible, per_scene_depth, per_scene_far, strict=True)
            ],
        }


def worst_matches(matches: TrackingMatches, count: int, per_scene: int | None = 1) -> np.ndarray:
    """Indices of ``count`` matches with the largest 3D error, worst first; matches without depth are never
    picked. Far matches (:data:`FAR_MATCH_M`) are taken at most ``per_scene`` from one scene (one bad scene
    would fill a gallery with near copies); the rest of ``count`` are the next worst whatever their scene."""
    error = np.where(np.isfinite(matches.error_3d_m), matches.error_3d_m, -np.inf)
    order = np.argsort(-error, kind="stable")
    order = order[np.isfinite(error[order])]
    if per_scene is None:
        return order[:count]
    picked: list[int] = []
    taken: dict[int, int] = {}
    for i in order[error[order] > FAR_MATCH_M]:
        scene = int(matches.scene_id[i])
        if taken.get(scene, 0) < per_scene and len(picked) < count:
            picked.append(int(i))
            taken[scene] = taken.get(scene, 0) + 1
    chosen = set(picked)
    picked += [int(i) for i in order if int(i) not in chosen][: count - len(picked)]
    picked_array = np.array(picked, dtype=np.int64)
    return picked_array[np.argsort(-error[picked_array], kind="stable")]
