"""One scene of the tracking protocol (docs/background.md, section "Tracking evaluation protocol"): the
protocol's settings, the scene's reference pixels followed through its frames, and one method's matches and
errors in it. :mod:`don_gym.evaluation.tracking` runs these steps over datasets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym.data.dataset import DEPTH_SOURCES, DONDataset, SceneRecord
from don_gym.errors import DonGymError
from don_gym.evaluation.frames import background_description, frame_observation
from don_gym.evaluation.tracking_metrics import (
    attribute_matches,
    match_descriptors,
    select_reference_pixels,
    tracking_errors,
    usable_reference_mask,
    visible_projections,
    world_points_at,
)
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import DescriptorSource, NetworkDescriptors

__all__ = [
    "MATCH_WITHIN",
    "TRACKING_DEPTHS",
    "PartGeometry",
    "SceneContext",
    "SceneReference",
    "TrackingConfig",
    "depth_errors",
    "frame_matches",
    "network_images",
    "part_instances",
    "scene_context",
    "scene_entry",
    "scene_matches",
    "scene_reference",
]

TRACKING_DEPTHS: tuple[str, ...] = ("ideal", "sensor")
MATCH_WITHIN = ("image", "instance")
#: A matched point this close to the table plane lies on the table top (ideal depth is exact to a


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
        match_within: ``"image"`` (the paper's: the best match anywhere in the image, but for the border margin) or
            ``"instance"`` (a diagnostic: only among the pixels the part, in a pile the reference's own instance,
            shows in that frame, so the error says how well a method localises a point on the right instance,
            given it).
        border_margin_px: pixels along each edge of the frame where matches are not searched (None: each
            method's own, :attr:`~don_gym.perception.descriptor_sources.DescriptorSource.border_margin_px`: 16 for a
            network, 0 for the oracle; 0: the whole image, the paper's search).
    """

    points_per_scene: int = 16
    depth: str = "ideal"
    visibility_tolerance_m: float = 0.004
    erode_px: int = 1
    seed: int = 0
    max_scenes: int | None = None
    match_within: str = "image"
    border_margin_px: int | None = None

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
        if self.match_within not in MATCH_WITHIN:
            raise DonGymError(f"match_within={self.match_within!r}: expected one of {list(MATCH_WITHIN)}")
        if self.border_margin_px is not None:
            integer("border_margin_px", 0)

    def border_margin_for(self, source: DescriptorSource) -> int:
        """The border margin (px) the matches of ``source`` are searched with: :attr:`border_margin_px` or, when
        None, the source's own."""
        return source.border_margin_px if self.border_margin_px is None else int(self.border_margin_px)


@dataclass
class SceneReference:
    frame: int
    uv: np.ndarray  # (N, 2) reference pixels in the reference frame
    points_world: np.ndarray  # (N, 3) ground truth
    projections: list[tuple[np.ndarray, np.ndarray]]  # per frame: (uv (N, 2), visible (N,))
    depth_ideal: list[np.ndarray]  # per frame
    masks: list[np.ndarray]  # per frame, the part's pixels
    others: list[np.ndarray] | None = None  # per frame, a pile's other instances' pixels


def scene_reference(
    dataset: DONDataset, scene: int, config: TrackingConfig, instance_id: int | None = None
) -> SceneReference:
    """The reference pixels of a scene's part, or with ``instance_id`` of that instance of a pile (its pixels in
    the ``instance`` images; the frame where it shows most usable pixels is its reference frame)."""
    record: SceneRecord = dataset.scenes[scene]
    depth_ideal = [dataset.image(scene, f, "depth_ideal") for f in range(record.num_frames)]
    others = None
    if instance_id is None:
        masks = [np.asarray(dataset.image(scene, f, "mask"), dtype=bool) for f in range(record.num_frames)]
    else:
        ids = [dataset.image(scene, f, "instance") for f in range(record.num_frames)]
        masks = [frame_ids == instance_id for frame_ids in ids]
        others = [(frame_ids > 0) & (frame_ids != instance_id) for frame_ids in ids]
    usable = [usable_reference_mask(masks[f], depth_ideal[f], config.erode_px) for f in range(record.num_frames)]
    frame = int(np.argmax([u.sum() for u in usable]))
    entropy = [config.seed, record.index] if instance_id is None else [config.seed, record.index, instance_id]
    rng = np.random.default_rng(np.random.SeedSequence(entropy))
    uv = select_reference_pixels(usable[frame], config.points_per_scene, rng)
    points, _ = world_points_at(uv, depth_ideal[frame], record.intrinsics, record.T_world_camera[frame])
    projections = [
        visible_projections(
            points, record.T_world_camera[f], record.intrinsics, depth_ideal[f], config.visibility_tolerance_m
        )
        for f in range(record.num_frames)
    ]
    return SceneReference(frame, uv, points, projections, depth_ideal, masks, others)


def network_images(
    source: NetworkDescriptors, data: DONDataset, scene: int, frames: Sequence[int], batch_size: int
) -> dict[int, np.ndarray]:
    """Descriptor images of ``frames`` of a scene, the network run on ``batch_size`` frames at a time."""
    images: dict[int, np.ndarray] = {}
    for start in range(0, len(frames), batch_size):
        chunk = frames[start : start + batch_size]
        rgb = np.stack([frame_observation(data, scene, frame)[0]["rgb"] for frame in chunk])
        images.update(zip(chunk, source.descriptor_images(rgb), strict=True))
    return images


@dataclass(frozen=True)
class PartGeometry:
    """The evaluated part and the plane between its halves (:func:`part_halves_axis`)."""

    model: ObjectModel
    halves_point: np.ndarray
    halves_axis: np.ndarray


@dataclass
class SceneContext:
    """One evaluated scene (or instance of a pile): where it is, its reference pixels, the true poses and the
    depth images read so far (per depth name, per frame)."""

    data: DONDataset
    dataset: int
    scene: int
    scene_id: int
    instance_id: int | None
    record: SceneRecord
    reference: SceneReference
    T_world_object: np.ndarray
    T_world_twins: list[np.ndarray] | None
    table_height_m: float
    depth_images: dict[str, dict[int, np.ndarray]] = field(default_factory=dict)


def scene_context(
    data: DONDataset,
    d: int,
    scene: int,
    scene_id: int,
    instance_id: int | None,
    model: ObjectModel,
    config: TrackingConfig,
) -> SceneContext:
    """What the tracking protocol needs of scene ``scene`` of dataset ``data`` (number ``d`` among the pooled
    datasets, ``scene_id`` in the results): the part's pose (of instance ``instance_id`` in a pile, None for a
    one-part scene) and its twins' poses (the part's other instances), and the reference frame ``config``
    chooses."""
    record = data.scenes[scene]
    T_world_object, T_world_twins = record.T_world_object, None
    if instance_id is not None:
        instances = part_instances(record, model.name)
        T_world_object = next(i["T_world_object"] for i in instances if i["instance_id"] == instance_id)
        # Descriptors of a part are alike on all its instances: a match on the same point of a twin is right.
        T_world_twins = [i["T_world_object"] for i in instances if i["instance_id"] != instance_id]
    return SceneContext(
        data=data,
        dataset=d,
        scene=scene,
        scene_id=scene_id,
        instance_id=instance_id,
        record=record,
        reference=scene_reference(data, scene, config, instance_id),
        T_world_object=T_world_object,
        T_world_twins=T_world_twins,
        table_height_m=float(record.metadata.get("table_height_m", 0.0)),
    )


def scene_entry(context: SceneContext) -> dict[str, Any]:
    """The scene's entry in :attr:`TrackingResult.scenes`."""
    record = context.record
    return {
        "dataset": context.dataset,
        "dataset_seed": context.data.info.get("seed"),
        "scene": context.scene,
        "scene_index": record.index,
        "scene_seed": record.metadata.get("seed"),
        "frames": record.num_frames,
        "background": background_description(record.metadata.get("background")),
        **({} if context.instance_id is None else {"instance_id": context.instance_id}),
    }


def scene_matches(
    context: SceneContext,
    source: DescriptorSource,
    geometry: PartGeometry,
    config: TrackingConfig,
    depths: Sequence[str],
    batch: int,
    bar: tqdm,
) -> list[dict[str, np.ndarray]]:
    """The matches of one method in one scene, one entry per frame where a reference point is visible: the
    reference descriptors from the reference frame, matched in every other frame."""
    data, scene, reference, record = context.data, context.scene, context.reference, context.record
    batched: dict[int, np.ndarray] = {}
    if batch > 1 and isinstance(source, NetworkDescriptors):
        seen = [f for f in range(record.num_frames) if reference.projections[f][1].any()]
        wanted = [reference.frame] + [f for f in seen if f != reference.frame]
        batched = network_images(source, data, scene, wanted, batch)
    ref_image = batched.get(reference.frame)
    if ref_image is None:
        ref_image = source.descriptor_image(*frame_observation(data, scene, reference.frame))
    ref_descriptors = ref_image[reference.uv[:, 1], reference.uv[:, 0]]
    bar.update(1)
    entries = []
    for frame in range(record.num_frames):
        if frame == reference.frame:
            continue
        bar.update(1)
        rows = np.flatnonzero(reference.projections[frame][1])
        if len(rows) == 0:
            continue
        image = batched.get(frame)
        if image is None:
            image = source.descriptor_image(*frame_observation(data, scene, frame))
        entry = frame_matches(context, image, ref_descriptors, rows, frame, geometry, config, source)
        for depth_name in depths:
            entry |= depth_errors(context, entry["matched_uv"], rows, frame, depth_name, geometry)
        entries.append(entry)
    return entries


def frame_matches(
    context: SceneContext,
    image: np.ndarray,
    ref_descriptors: np.ndarray,
    rows: np.ndarray,
    frame: int,
    geometry: PartGeometry,
    config: TrackingConfig,
    source: DescriptorSource,
) -> dict[str, np.ndarray]:
    """The matches in one frame of the reference points ``rows`` (the visible ones), with the errors that do
    not depend on the depth of the predicted points."""
    reference, record = context.reference, context.record
    true_uv = reference.projections[frame][0]
    candidates = reference.masks[frame] if config.match_within == "instance" else None
    matches = match_descriptors(
        image,
        ref_descriptors[rows],
        np.rint(true_uv[rows]).astype(np.int64),
        candidates,
        config.border_margin_for(source),
    )
    truth = reference.points_world[rows]
    T_world_camera = record.T_world_camera[frame]
    ideal_points, _ = world_points_at(matches.uv, reference.depth_ideal[frame], record.intrinsics, T_world_camera)
    n = len(rows)
    return {
        "scene_id": np.full(n, context.scene_id),
        "dataset": np.full(n, context.dataset),
        "scene": np.full(n, context.scene),
        "frame": np.full(n, frame),
        "point": rows,
        "reference_frame": np.full(n, reference.frame),
        "reference_uv": reference.uv[rows],
        "matched_uv": matches.uv,
        "true_uv": true_uv[rows],
        "pixel_error_px": np.linalg.norm(matches.uv - true_uv[rows], axis=1),
        "fraction_closer": matches.fraction_closer,
        "error_3d_ideal_m": np.linalg.norm(ideal_points - truth, axis=1),
        "category": attribute_matches(
            matches.uv,
            truth,
            reference.masks[frame],
            reference.depth_ideal[frame],
            record.intrinsics,
            T_world_camera,
            context.T_world_object,
            geometry.halves_point,
            geometry.halves_axis,
            context.table_height_m,
            # The recorded scenes show nothing else on the table's plane (their floor lies 0.75 m below), and
            # the bounds live with PyBullet, which evaluation does not load.
            table_bounds_xy_m=None,
            other_instances_mask=None if reference.others is None else reference.others[frame],
        ),
    }


def depth_errors(
    context: SceneContext,
    matched_uv: np.ndarray,
    rows: np.ndarray,
    frame: int,
    depth_name: str,
    geometry: PartGeometry,
) -> dict[str, np.ndarray]:
    """The errors of the matches' points predicted from ``depth_name``'s depth, keyed ``name:depth``."""
    images = context.depth_images.setdefault(depth_name, {})
    depth = images.get(frame)
    if depth is None:
        depth = context.data.image(context.scene, frame, DEPTH_SOURCES[depth_name][0])
        images[frame] = depth
    record = context.record
    predicted, depth_valid = world_points_at(matched_uv, depth, record.intrinsics, record.T_world_camera[frame])
    model = geometry.model
    errors = tracking_errors(
        predicted,
        context.reference.points_world[rows],
        context.T_world_object,
        model.center_of_mass,
        model.symmetry_axis,
        context.T_world_twins,
    )
    return {f"{key}:{depth_name}": values for key, values in errors.items()} | {
        f"depth_valid:{depth_name}": depth_valid
    }


def part_instances(record: SceneRecord, part: str) -> list[dict[str, Any]]:
    """The instances of ``part`` in a pile's record that have a pose (dicts of :attr:`SceneRecord.instances`)."""
    return [i for i in record.instances if i["part"] == part and "T_world_object" in i]
