"""Tracking-error evaluation of DONs on recorded scenes (Kupcsik et al. 2021, Sec. "Quantitative
Evaluation of Prediction Accuracy"), with the original DON metrics (Florence et al. 2018).

The protocol is described in docs/background.md, section "Tracking evaluation protocol". The core
functions take and return arrays; :func:`evaluate_tracking` runs the protocol over a dataset.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm.auto import tqdm

from don_gym.dataset import DEPTH_SOURCES, DONDataset, SceneRecord
from don_gym.descriptor_sources import DescriptorSource, NetworkDescriptors, load_descriptor_source
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, invert_transform, project_points, transform_points
from don_gym.keypoints import descriptor_distances, project_visible
from don_gym.model import torch_device
from don_gym.objects import ObjectModel

#: Percentiles reported for every metric.
PERCENTILES: tuple[int, ...] = (50, 90, 99)
#: Depths offered for the predicted 3D points, by their names in :data:`don_gym.dataset.DEPTH_SOURCES`.
TRACKING_DEPTHS: tuple[str, ...] = ("ideal", "sensor")


@dataclass(frozen=True)
class TrackingConfig:
    """Settings of the tracking protocol (docs/background.md, section "Tracking evaluation protocol").

    Attributes:
        points_per_scene: reference pixels per scene (fewer if the object shows fewer usable pixels).
        depth: ``"ideal"`` (simulator depth) or ``"sensor"`` (the dataset's sensor depth) for the
            predicted 3D points. The ground truth always uses ideal depth.
        visibility_tolerance_m: a point is occluded when the ideal depth at its projection is this
            much nearer (or farther) than the point.
        erode_px: reference pixels keep this many pixels from the object silhouette.
        seed: seed of the reference-pixel draw.
        max_scenes: evaluate only the first scenes (None: all).
    """

    points_per_scene: int = 16
    depth: str = "ideal"
    visibility_tolerance_m: float = 0.004
    erode_px: int = 1
    seed: int = 0
    max_scenes: int | None = None

    def validate(self) -> None:
        def integer(name: str, minimum: int) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
                raise DonGymError(f"{name}={value!r}: expected an integer >= {minimum}")

        integer("points_per_scene", 1)
        if self.depth not in TRACKING_DEPTHS:
            raise DonGymError(f"depth={self.depth!r}: expected one of {list(TRACKING_DEPTHS)}")
        tolerance = self.visibility_tolerance_m
        if not (isinstance(tolerance, (int, float, np.number)) and np.isfinite(tolerance) and tolerance > 0):
            raise DonGymError(f"visibility_tolerance_m={tolerance!r}: expected a finite number of metres > 0")
        integer("erode_px", 0)
        integer("seed", 0)
        if self.max_scenes is not None:
            integer("max_scenes", 1)


# --- pure core ----------------------------------------------------------------------------------


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
    descriptor_image: np.ndarray, references: np.ndarray, true_uv: np.ndarray | None = None
) -> Matches:
    """Best match (argmin L2 over the whole image) of each reference descriptor.

    Args:
        descriptor_image: (H, W, D) float descriptors.
        references: (N, D) reference descriptors.
        true_uv: optional (N, 2) integer pixels of the true matches (rows with a negative
            coordinate are skipped) for the fraction of pixels closer than the true match.
    """
    distances = descriptor_distances(descriptor_image, references)  # (N, H, W)
    count, height, width = distances.shape
    flat = distances.reshape(count, height * width)
    best = np.argmin(flat, axis=1)
    uv = np.stack([best % width, best // width], axis=1).astype(np.int64)
    fraction = np.full(count, np.nan)
    if true_uv is not None:
        true_uv = np.asarray(true_uv, dtype=np.int64).reshape(-1, 2)
        ok = (true_uv >= 0).all(axis=1) & (true_uv[:, 0] < width) & (true_uv[:, 1] < height)
        rows = np.flatnonzero(ok)
        at_true = flat[rows, true_uv[rows, 1] * width + true_uv[rows, 0]]
        fraction[rows] = (flat[rows] < at_true[:, None]).sum(axis=1) / float(height * width)
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


def percentiles(values: np.ndarray, which: Sequence[int] = PERCENTILES) -> dict[str, float | None]:
    """``{"p50": ..., "p90": ..., "p99": ..., "mean": ...}`` of the finite values (None if there are none)."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if len(finite) == 0:
        return {**{f"p{p}": None for p in which}, "mean": None}
    return {**{f"p{p}": float(np.percentile(finite, p)) for p in which}, "mean": float(finite.mean())}


# --- descriptor sources ---------------------------------------------------------------------------


def dataset_object(dataset: DONDataset) -> ObjectModel:
    """The object of a dataset, loaded as it was built and checked to be its part (:meth:`DONDataset.object_model`)."""
    return dataset.object_model()


def frame_observation(dataset: DONDataset, scene: int, frame: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A dataset frame as an env observation and info, for :class:`don_gym.descriptor_sources.DescriptorSource`:
    ``rgb``, ``depth`` (the *ideal* depth, so the oracle's occlusion test is exact) and
    ``camera_intrinsics``; info holds the true ``T_world_object`` and ``T_world_camera``."""
    record = dataset.scenes[scene]
    obs = {
        "rgb": dataset.image(scene, frame, "rgb"),
        "depth": dataset.image(scene, frame, "depth_ideal"),
        "camera_intrinsics": record.intrinsics.as_array().astype(np.float32),
    }
    info = {"T_world_object": record.T_world_object, "T_world_camera": record.T_world_camera[frame]}
    return obs, info


def _source_info(source: DescriptorSource) -> dict[str, Any]:
    info: dict[str, Any] = {"method": source.method, "descriptor_dim": source.descriptor_dim}
    metadata = getattr(source, "metadata", None)
    if metadata is not None:
        info |= {
            "arch": metadata.arch,
            "training_image_size": list(metadata.image_size),
            "training_steps": metadata.training_steps,
            "renderer": metadata.renderer,
        }
    return info


# --- protocol over a dataset --------------------------------------------------------------------


@dataclass
class TrackingMatches:
    """All matches of one method, one entry per (scene, frame, reference point) with the point visible.

    Arrays of equal length M: ``scene``, ``frame``, ``point`` (int), ``pixel_error_px``,
    ``error_3d_m`` (NaN where the matched pixel has no depth), ``symmetric_error_m`` (NaN for
    parts without a symmetry axis or without depth), ``fraction_closer``, ``depth_valid`` (bool).
    ``reference_points`` counts the reference pixels chosen over all scenes.
    """

    scene: np.ndarray
    frame: np.ndarray
    point: np.ndarray
    pixel_error_px: np.ndarray
    error_3d_m: np.ndarray
    symmetric_error_m: np.ndarray
    fraction_closer: np.ndarray
    depth_valid: np.ndarray
    reference_points: int = 0

    def summary(self) -> dict[str, Any]:
        valid = self.depth_valid
        return {
            "counts": {
                "reference_points": int(self.reference_points),
                "visible_matches": int(len(self.scene)),
                "matches_with_depth": int(valid.sum()),
                "matches_without_depth": int((~valid).sum()),
            },
            "error_3d_mm": percentiles(self.error_3d_m * 1000.0),
            "error_3d_symmetric_mm": percentiles(self.symmetric_error_m * 1000.0),
            "pixel_error_px": percentiles(self.pixel_error_px),
            "fraction_closer": percentiles(self.fraction_closer),
            "fraction_3d_error_below": {
                f"{int(mm)}mm": (float(np.mean(self.error_3d_m[valid] < mm / 1000.0)) if valid.any() else None)
                for mm in (2.0, 5.0, 10.0, 20.0)
            },
        }


@dataclass
class TrackingResult:
    dataset: str
    config: TrackingConfig
    matches: dict[str, TrackingMatches]
    sources: dict[str, dict[str, Any]]
    dataset_info: dict[str, Any]

    def summary(self) -> dict[str, Any]:
        info = self.dataset_info
        return {
            "protocol": "kupcsik2021-tracking",
            "dataset": self.dataset,
            "object": info.get("object"),
            "scenes": info.get("scenes_evaluated"),
            "frames_per_scene": info.get("frames_per_scene"),
            "image_size": info.get("image_size"),
            "dataset_sensor": info.get("sensor"),
            "dataset_seed": info.get("seed"),
            "config": asdict(self.config),
            "percentiles": list(PERCENTILES),
            "methods": {
                name: {"source": self.sources[name], **matches.summary()} for name, matches in self.matches.items()
            },
        }


@dataclass
class _SceneReference:
    frame: int
    uv: np.ndarray  # (N, 2) reference pixels in the reference frame
    points_world: np.ndarray  # (N, 3) ground truth
    projections: list[tuple[np.ndarray, np.ndarray]]  # per frame: (uv (N, 2), visible (N,))


def _scene_reference(dataset: DONDataset, scene: int, config: TrackingConfig) -> _SceneReference:
    record: SceneRecord = dataset.scenes[scene]
    depth_ideal = [dataset.image(scene, f, "depth_ideal") for f in range(record.num_frames)]
    usable = [
        usable_reference_mask(dataset.image(scene, f, "mask"), depth_ideal[f], config.erode_px)
        for f in range(record.num_frames)
    ]
    frame = int(np.argmax([u.sum() for u in usable]))
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, record.index]))
    uv = select_reference_pixels(usable[frame], config.points_per_scene, rng)
    points, _ = world_points_at(uv, depth_ideal[frame], record.intrinsics, record.T_world_camera[frame])
    projections = [
        visible_projections(
            points, record.T_world_camera[f], record.intrinsics, depth_ideal[f], config.visibility_tolerance_m
        )
        for f in range(record.num_frames)
    ]
    return _SceneReference(frame, uv, points, projections)


def _network_images(
    source: NetworkDescriptors, data: DONDataset, scene: int, frames: Sequence[int], batch_size: int
) -> dict[int, np.ndarray]:
    """Descriptor images of ``frames`` of a scene, the network run on ``batch_size`` frames at a time."""
    images: dict[int, np.ndarray] = {}
    for start in range(0, len(frames), batch_size):
        chunk = frames[start : start + batch_size]
        rgb = np.stack([frame_observation(data, scene, frame)[0]["rgb"] for frame in chunk])
        images.update(zip(chunk, source.descriptor_images(rgb), strict=True))
    return images


def evaluate_tracking(
    dataset: DONDataset | str | Path,
    methods: Sequence[str] | Mapping[str, str | DescriptorSource],
    config: TrackingConfig = TrackingConfig(),
    progress: bool = True,
    device: str = "cpu",
    batch_size: int | None = None,
) -> TrackingResult:
    """Run the tracking protocol for each method on every scene of ``dataset``.

    The protocol is that of docs/background.md, section "Tracking evaluation protocol". Evaluate on
    scenes the networks were not trained on: build a separate dataset with another seed
    (``benchmarks/bench_grasp.py`` uses seed 1000, the shipped networks were trained on seed 0).

    ``methods``: model references, loaded by
    :func:`don_gym.descriptor_sources.load_descriptor_source` exactly as the env wrappers and
    agents load them: ``"oracle"`` (the object's optimal symmetric descriptors rendered from the
    true poses, the upper bound), shipped network names or checkpoint paths (checked to describe
    the dataset's object); or a mapping from a label to a reference or a ready
    :class:`~don_gym.descriptor_sources.DescriptorSource`. All sources are loaded and checked against the
    dataset's object before any work.

    Networks run on ``device`` (:func:`~don_gym.model.torch_device`: ``"cpu"``, ``"cuda"``, ...), on
    ``batch_size`` frames of a scene at a time (None: 8 on a GPU, one frame at a time on the CPU); the
    results differ from one frame at a time on the CPU only by float rounding.
    """
    config.validate()
    run_on = torch_device(device)
    if batch_size is not None and (isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1):
        raise DonGymError(f"batch_size={batch_size!r}: expected an integer >= 1 or None")
    batch = batch_size if batch_size is not None else (1 if run_on.type == "cpu" else 8)
    data = dataset if isinstance(dataset, DONDataset) else DONDataset(dataset)
    if not methods:
        raise DonGymError("no methods to evaluate; give 'oracle' and/or network names or checkpoint paths")
    labelled = dict(methods) if isinstance(methods, Mapping) else {str(m): m for m in methods}
    if not isinstance(methods, Mapping) and len(labelled) != len(methods):
        raise DonGymError(f"methods {list(methods)}: each method may be given once")
    model = dataset_object(data)
    sources = {name: load_descriptor_source(ref, model) for name, ref in labelled.items()}
    for source in sources.values():
        if isinstance(source, NetworkDescriptors):
            source.network.to(run_on)
    axis = model.symmetry_axis
    scenes = list(range(len(data.scenes)))[: config.max_scenes]
    depth_kind, _ = DEPTH_SOURCES[config.depth]
    collected: dict[str, list[dict[str, np.ndarray]]] = {name: [] for name in sources}
    reference_points = 0
    total = len(sources) * sum(data.scenes[s].num_frames for s in scenes)
    with tqdm(total=total, unit="frame", desc="evaluate", disable=not progress) as bar:
        for scene in scenes:
            record = data.scenes[scene]
            reference = _scene_reference(data, scene, config)
            reference_points += len(reference.uv)
            for name, source in sources.items():
                batched: dict[int, np.ndarray] = {}
                if batch > 1 and isinstance(source, NetworkDescriptors):
                    seen = [f for f in range(record.num_frames) if reference.projections[f][1].any()]
                    wanted = [reference.frame] + [f for f in seen if f != reference.frame]
                    batched = _network_images(source, data, scene, wanted, batch)
                ref_image = batched.get(reference.frame)
                if ref_image is None:
                    ref_image = source.descriptor_image(*frame_observation(data, scene, reference.frame))
                ref_descriptors = ref_image[reference.uv[:, 1], reference.uv[:, 0]]
                bar.update(1)
                for frame in range(record.num_frames):
                    if frame == reference.frame:
                        continue
                    true_uv, visible = reference.projections[frame]
                    bar.update(1)
                    rows = np.flatnonzero(visible)
                    if len(rows) == 0:
                        continue
                    image = batched.get(frame)
                    if image is None:
                        image = source.descriptor_image(*frame_observation(data, scene, frame))
                    matches = match_descriptors(image, ref_descriptors[rows], np.rint(true_uv[rows]).astype(np.int64))
                    depth = data.image(scene, frame, depth_kind)
                    predicted, depth_valid = world_points_at(
                        matches.uv, depth, record.intrinsics, record.T_world_camera[frame]
                    )
                    truth = reference.points_world[rows]
                    symmetric = (
                        symmetric_distance(predicted, truth, record.T_world_object, model.center_of_mass, axis)
                        if axis is not None
                        else np.full(len(rows), np.nan)
                    )
                    collected[name].append(
                        {
                            "scene": np.full(len(rows), scene),
                            "frame": np.full(len(rows), frame),
                            "point": rows,
                            "pixel_error_px": np.linalg.norm(matches.uv - true_uv[rows], axis=1),
                            "error_3d_m": np.linalg.norm(predicted - truth, axis=1),
                            "symmetric_error_m": symmetric,
                            "fraction_closer": matches.fraction_closer,
                            "depth_valid": depth_valid,
                        }
                    )
    matches_by_method = {}
    for name, parts in collected.items():
        keys = ("scene", "frame", "point", "pixel_error_px", "error_3d_m", "symmetric_error_m", "fraction_closer")
        arrays = {k: np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in keys}
        valid = np.concatenate([p["depth_valid"] for p in parts]) if parts else np.zeros(0, dtype=bool)
        matches_by_method[name] = TrackingMatches(**arrays, depth_valid=valid, reference_points=reference_points)
    info = dict(data.info) | {"scenes_evaluated": len(scenes)}
    sources_info = {name: _source_info(source) for name, source in sources.items()}
    return TrackingResult(str(data.root), config, matches_by_method, sources_info, info)


# --- reporting ------------------------------------------------------------------------------------


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def tracking_table(summary: Mapping[str, Any]) -> str:
    """Markdown table of a :meth:`TrackingResult.summary`: one row per method."""
    lines = [
        "| method | matches (with depth) | 3D error p50 / p90 / p99 (mm) | 3D error mod symmetry p50 / p90 (mm) "
        "| pixel error p50 / p90 (px) | fraction closer p50 / p90 (%) |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in summary["methods"].items():
        e, s, px, fc = m["error_3d_mm"], m["error_3d_symmetric_mm"], m["pixel_error_px"], m["fraction_closer"]
        counts = m["counts"]
        pct = {k: None if v is None else 100.0 * v for k, v in fc.items()}
        lines.append(
            f"| {name} | {counts['visible_matches']} ({counts['matches_with_depth']}) "
            f"| {_fmt(e['p50'])} / {_fmt(e['p90'])} / {_fmt(e['p99'])} | {_fmt(s['p50'])} / {_fmt(s['p90'])} "
            f"| {_fmt(px['p50'])} / {_fmt(px['p90'])} | {_fmt(pct['p50'], 3)} / {_fmt(pct['p90'], 3)} |"
        )
    return "\n".join(lines)


def write_tracking_outputs(result: TrackingResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``tracking.json`` (summary), ``tracking.md`` (table), ``tracking_histogram.png`` (the
    paper's stacked, normalised log-scale histogram of the 3D error, and of the 3D error modulo
    symmetry for a part with a symmetry axis) and ``tracking_cdf.png`` (CDFs of 3D error,
    3D error modulo symmetry, pixel error and fraction closer) into ``out_dir``."""
    import json

    from don_gym import plotting
    from don_gym.io import check_output_dir, write_text_atomic

    out = check_output_dir(out_dir, "out_dir")
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    paths = {"json": out / "tracking.json", "table": out / "tracking.md"}
    write_text_atomic(paths["json"], json.dumps(summary, indent=1) + "\n")
    write_text_atomic(paths["table"], tracking_table(summary) + "\n")
    matches = result.matches
    name = Path(result.dataset).name
    errors_mm = {k: m.error_3d_m * 1000.0 for k, m in matches.items()}
    symmetric_mm = {k: m.symmetric_error_m * 1000.0 for k, m in matches.items()}
    has_axis = any(np.isfinite(m.symmetric_error_m).any() for m in matches.values())
    histograms = [("3D tracking error (mm)", errors_mm, 0.1)]
    if has_axis:
        histograms.append(("3D tracking error modulo symmetry (mm)", symmetric_mm, 0.1))
    depth = summary["config"]["depth"]
    paths["histogram"] = plotting.plot_error_histograms(
        histograms, out / "tracking_histogram.png", title=f"Tracking error, {summary['object']} ({name}, {depth} depth)"
    )
    panels = [
        ("3D error (mm)", errors_mm, 0.1),
        ("3D error modulo symmetry (mm)", symmetric_mm, 0.1),
        ("pixel error (px)", {k: m.pixel_error_px for k, m in matches.items()}, 0.1),
        (
            "fraction of pixels closer than the true match\n(0 drawn at 1e-5)",
            {k: m.fraction_closer for k, m in matches.items()},
            1e-5,
        ),
    ]
    if not has_axis:
        panels.pop(1)
    paths["cdf"] = plotting.plot_cdfs(
        panels, out / "tracking_cdf.png", title=f"Tracking, {summary['object']} ({name}, {depth} depth)"
    )
    return paths
