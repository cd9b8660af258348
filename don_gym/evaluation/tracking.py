"""The tracking protocol run over datasets (docs/background.md, section "Tracking evaluation protocol"):
:func:`evaluate_tracking` on one dataset or several pooled ones, :func:`evaluate_tracking_depths` for several
depths in one pass, :func:`evaluate_tracking_per_part` on piles of a bin. The pure steps are in
:mod:`don_gym.evaluation.tracking_metrics`, the tables and figures in :mod:`don_gym.evaluation.report`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym.data.dataset import DONDataset
from don_gym.data.render import distance_inside_px
from don_gym.errors import DonGymError
from don_gym.evaluation.frames import open_datasets, pooled_object, source_info
from don_gym.evaluation.splits import seed_split
from don_gym.evaluation.tracking_metrics import (
    BOOTSTRAP_SEED,
    FAR_MATCH_M,
    LONG_TAIL_RATIO,
    PERCENTILES,
    TrackingMatches,
    part_halves_axis,
)
from don_gym.evaluation.tracking_scene import (
    MATCH_WITHIN,
    TRACKING_DEPTHS,
    PartGeometry,
    TrackingConfig,
    part_instances,
    scene_context,
    scene_entry,
    scene_matches,
)
from don_gym.learning.model import torch_device
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import (
    DescriptorSource,
    NetworkDescriptors,
    PileOracleDescriptors,
    load_descriptor_source,
)
from don_gym.perception.keypoints import match_region
from don_gym.stats import BOOTSTRAP_RESAMPLES, DEFAULT_CONFIDENCE

# TrackingConfig and the depth and match-region names live with the scene's steps; offered here beside the
# runner that takes them.
__all__ = [
    "MATCH_WITHIN",
    "TRACKING_DEPTHS",
    "TrackingConfig",
    "TrackingResult",
    "evaluate_tracking",
    "evaluate_tracking_depths",
    "evaluate_tracking_per_part",
    "methods_for_part",
    "reference_edge_distances_px",
]


@dataclass
class TrackingResult:
    """The matches of every method on the scenes of one or more pooled datasets.

    ``datasets``: the datasets' directories; ``dataset_infos``: their ``dataset.json``; ``scenes``: one
    entry per evaluated scene, in the order of ``TrackingMatches.scene_id``: ``dataset`` (position),
    ``dataset_seed``, ``scene`` (position in its dataset), ``scene_index``, ``scene_seed``, ``frames``,
    ``background`` (:func:`background_description`).
    """

    datasets: list[str]
    config: TrackingConfig
    matches: dict[str, TrackingMatches]
    sources: dict[str, dict[str, Any]]
    dataset_infos: list[dict[str, Any]]
    scenes: list[dict[str, Any]]
    _summary: dict[str, Any] | None = field(default=None, init=False, repr=False, compare=False)

    def summary(self) -> dict[str, Any]:
        """Everything reported, as JSON-ready data (computed once: the bootstrap takes a moment)."""
        if self._summary is not None:
            return self._summary
        infos = self.dataset_infos
        seeds = [info.get("seed") for info in infos]
        splits = [seed_split(seed) if isinstance(seed, int) else "unlisted" for seed in seeds]

        def common(key: str) -> Any:
            values = [info.get(key) for info in infos]
            return values[0] if all(v == values[0] for v in values) else values

        self._summary = {
            "protocol": "kupcsik2021-tracking",
            "datasets": list(self.datasets),
            "dataset_seeds": seeds,
            "split": splits[0] if len(set(splits)) == 1 else "mixed",
            "object": infos[0].get("object") if infos else None,
            "scenes": len(self.scenes),
            "frames_per_scene": common("frames_per_scene"),
            "image_size": common("image_size"),
            "dataset_sensor": common("sensor"),
            "config": asdict(self.config),
            "percentiles": list(PERCENTILES),
            "bootstrap": {
                "unit": "scene",
                "resamples": BOOTSTRAP_RESAMPLES,
                "confidence": DEFAULT_CONFIDENCE,
                "seed": BOOTSTRAP_SEED,
            },
            "far_match_mm": FAR_MATCH_M * 1000.0,
            "long_tail_ratio": LONG_TAIL_RATIO,
            "scene_list": [dict(scene) for scene in self.scenes],
            "methods": {
                name: {"source": self.sources[name], **matches.summary()} for name, matches in self.matches.items()
            },
        }
        return self._summary


def evaluate_tracking(
    dataset: DONDataset | str | Path | Sequence[DONDataset | str | Path],
    methods: Sequence[str] | Mapping[str, str | DescriptorSource],
    config: TrackingConfig = TrackingConfig(),
    progress: bool = True,
    device: str = "cpu",
    batch_size: int | None = None,
) -> TrackingResult:
    """Run the tracking protocol for each method on every scene of ``dataset`` (one, or several whose
    scenes are pooled), with ``config.depth`` for the predicted points.

    The protocol is that of docs/background.md, section "Tracking evaluation protocol". Evaluate on
    scenes the networks were not trained on and no decision has used: datasets of the seeds of
    :data:`SPLIT_SEEDS` (``benchmarks/bench_grasp.py`` pools :data:`SCENES_PER_SEED` scenes of each of the
    :data:`TEST_SEEDS`; the shipped networks were trained on seed 0).

    ``methods``: model references, loaded by
    :func:`don_gym.perception.descriptor_sources.load_descriptor_source` exactly as the env wrappers and
    agents load them: ``"oracle"`` (the object's optimal symmetric descriptors rendered from the
    true poses, the upper bound), shipped network names or checkpoint paths (checked to describe
    the dataset's object); or a mapping from a label to a reference or a ready
    :class:`~don_gym.perception.descriptor_sources.DescriptorSource`. All sources are loaded and checked against the
    datasets' object before any work.

    Networks run on ``device`` (:func:`~don_gym.learning.model.torch_device`: ``"cpu"``, ``"cuda"``, ...), on
    ``batch_size`` frames of a scene at a time (None: 8 on a GPU, one frame at a time on the CPU); the
    results differ from one frame at a time on the CPU only by float rounding.
    """
    config.validate()
    return evaluate_tracking_depths(dataset, methods, config, (config.depth,), progress, device, batch_size)[
        config.depth
    ]


def evaluate_tracking_depths(
    dataset: DONDataset | str | Path | Sequence[DONDataset | str | Path],
    methods: Sequence[str] | Mapping[str, str | DescriptorSource],
    config: TrackingConfig = TrackingConfig(),
    depths: Sequence[str] = TRACKING_DEPTHS,
    progress: bool = True,
    device: str = "cpu",
    batch_size: int | None = None,
    part: str | None = None,
) -> dict[str, TrackingResult]:
    """:func:`evaluate_tracking` for several depths of the predicted points in one pass: ``{depth: result}``,
    each result's config with that depth. The matches depend only on the descriptors, so each method
    runs once per frame whatever the number of depths.

    Datasets of bins (``scene_kind`` "bin") are evaluated for one ``part`` (its name; see
    :func:`evaluate_tracking_per_part`): every instance of the part in a scene has its own reference pixels,
    drawn on its visible pixels (``instance`` images) in the frame showing most of it, followed through the
    frames where the ideal depth shows them (so occlusion by other instances counts), and matched in the whole
    image, among the other instances; the oracle renders every instance of the part
    (:class:`~don_gym.perception.descriptor_sources.PileOracleDescriptors`). The scene list then has one entry per
    instance (its ``instance_id``), the bootstrap's unit. Beside the errors to the reference instance's point,
    the matches of a pile carry the errors to the same point on the nearest instance of the part
    (:func:`tracking_errors`): descriptors of a part cannot tell its identical instances apart."""
    config.validate()
    depths = tuple(dict.fromkeys(depths))
    if not depths or any(d not in TRACKING_DEPTHS for d in depths):
        raise DonGymError(f"depths={list(depths)!r}: expected one or more of {list(TRACKING_DEPTHS)}")
    run_on = torch_device(device)
    batch = _frames_per_batch(batch_size, run_on.type)
    datasets = open_datasets(dataset)
    model, sources, pile = _load_sources(datasets, methods, part)
    for source in sources.values():
        if isinstance(source, NetworkDescriptors):
            source.network.to(run_on)
    _check_border_margins(datasets, sources, config)
    plan = _evaluation_plan(datasets, model, config, pile)
    geometry = PartGeometry(model, *part_halves_axis(model))
    collected: dict[str, list[dict[str, np.ndarray]]] = {name: [] for name in sources}
    scenes: list[dict[str, Any]] = []
    reference_points = 0
    total = len(sources) * sum(datasets[d].scenes[s].num_frames for d, s, _ in plan)
    with tqdm(total=total, unit="frame", desc="evaluate", disable=not progress) as bar:
        for scene_id, (d, scene, instance_id) in enumerate(plan):
            context = scene_context(datasets[d], d, scene, scene_id, instance_id, model, config)
            scenes.append(scene_entry(context))
            reference_points += len(context.reference.uv)
            for name, source in sources.items():
                collected[name] += scene_matches(context, source, geometry, config, depths, batch, bar)
    return _tracking_results(collected, depths, pile, plan, scenes, reference_points, sources, config, datasets, model)


def _frames_per_batch(batch_size: Any, device_type: str) -> int:
    """Frames a network runs on at a time: ``batch_size``, or None for 8 on a GPU and 1 on the CPU."""
    if batch_size is not None and (isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1):
        raise DonGymError(f"batch_size={batch_size!r}: expected an integer >= 1 or None")
    return batch_size if batch_size is not None else (1 if device_type == "cpu" else 8)


def _load_sources(
    datasets: list[DONDataset], methods: Sequence[str] | Mapping[str, str | DescriptorSource], part: str | None
) -> tuple[ObjectModel, dict[str, DescriptorSource], bool]:
    """The part evaluated, every method's descriptor source (loaded and checked against the part before any
    work) and whether the datasets are piles."""
    if not methods:
        raise DonGymError("no methods to evaluate; give 'oracle' and/or network names or checkpoint paths")
    labelled = dict(methods) if isinstance(methods, Mapping) else {str(m): m for m in methods}
    if not isinstance(methods, Mapping) and len(labelled) != len(methods):
        raise DonGymError(f"methods {list(methods)}: each method may be given once")
    pile = any(data.scene_kind == "bin" for data in datasets)
    if pile:
        model = _pile_part(datasets, part)
    else:
        if part is not None:
            raise DonGymError(f"part={part!r}: only datasets of bins hold several parts; these hold one")
        model = pooled_object(datasets)
    sources = {
        name: PileOracleDescriptors(model) if pile and isinstance(ref, str) and ref == "oracle"
        else load_descriptor_source(ref, model)
        for name, ref in labelled.items()
    }  # fmt: skip
    return model, sources, pile


def _check_border_margins(
    datasets: list[DONDataset], sources: Mapping[str, DescriptorSource], config: TrackingConfig
) -> None:
    """A margin that leaves no pixel is refused before any work, not at the first match."""
    for data in datasets:
        for record in data.scenes[:1]:
            for name, source in sources.items():
                try:
                    match_region(record.intrinsics.height, record.intrinsics.width, config.border_margin_for(source))
                except DonGymError as error:
                    raise DonGymError(f"{name} on {data.root}: {error}") from None


def _evaluation_plan(
    datasets: list[DONDataset], model: ObjectModel, config: TrackingConfig, pile: bool
) -> list[tuple[int, int, int | None]]:
    """``(dataset, scene, instance id or None)`` of every evaluated scene, the bootstrap's unit: each scene of
    one part, or each instance of the part in each pile."""
    return [
        (d, s, instance)
        for d, data in enumerate(datasets)
        for s in range(len(data.scenes))[: config.max_scenes]
        for instance in (
            [int(i["instance_id"]) for i in part_instances(data.scenes[s], model.name)] if pile else [None]
        )
    ]


#: The match arrays that do not depend on the depth of the predicted points, and the integer ones.
_COMMON_KEYS = (
    "scene_id",
    "dataset",
    "scene",
    "frame",
    "point",
    "reference_frame",
    "reference_uv",
    "matched_uv",
    "true_uv",
    "pixel_error_px",
    "fraction_closer",
    "error_3d_ideal_m",
    "category",
)
_INTEGER_KEYS = {"scene_id", "dataset", "scene", "frame", "point", "reference_frame", "reference_uv", "matched_uv"}


def _joined(parts: list[dict[str, np.ndarray]], key: str) -> np.ndarray:
    """The entries' arrays of ``key`` concatenated; an empty array of the key's type without entries."""
    if parts:
        return np.concatenate([p[key] for p in parts])
    name = key.split(":")[0]
    dtype = np.int64 if name in _INTEGER_KEYS else {"category": np.int8, "depth_valid": bool}.get(name, np.float64)
    return np.zeros((0, 2) if name.endswith("_uv") else 0, dtype=dtype)


def _tracking_results(
    collected: Mapping[str, list[dict[str, np.ndarray]]],
    depths: Sequence[str],
    pile: bool,
    plan: list[tuple[int, int, int | None]],
    scenes: list[dict[str, Any]],
    reference_points: int,
    sources: Mapping[str, DescriptorSource],
    config: TrackingConfig,
    datasets: list[DONDataset],
    model: ObjectModel,
) -> dict[str, TrackingResult]:
    """One :class:`TrackingResult` per depth from every method's entries."""
    depth_keys = ("error_3d_m", "symmetric_error_m", "depth_valid")
    if pile:
        depth_keys += ("error_3d_any_instance_m", "symmetric_error_any_instance_m")
    sources_info = {name: source_info(source, config.border_margin_for(source)) for name, source in sources.items()}
    results = {}
    for depth_name in depths:
        matches_by_method = {}
        for name, parts in collected.items():
            arrays = {k: _joined(parts, k) for k in _COMMON_KEYS}
            arrays |= {k: _joined(parts, f"{k}:{depth_name}") for k in depth_keys}
            matches_by_method[name] = TrackingMatches(
                **arrays, reference_points=reference_points, scenes_evaluated=len(plan)
            )
        results[depth_name] = TrackingResult(
            datasets=[str(data.root) for data in datasets],
            config=replace(config, depth=depth_name),
            matches=matches_by_method,
            sources=sources_info,
            dataset_infos=[
                dict(data.info)
                | {"scenes_evaluated": len({s for dd, s, _ in plan if dd == k})}
                | ({"object": model.name, "part": model.name} if pile else {})
                for k, data in enumerate(datasets)
            ],
            scenes=scenes,
        )
    return results


def _pile_part(datasets: list[DONDataset], part: str | None) -> ObjectModel:
    """The model of ``part`` in datasets of bins, all of which must hold it (by name and shape)."""
    from don_gym.data.bin_dataset import load_part_models

    not_bins = [str(data.root) for data in datasets if data.scene_kind != "bin"]
    if not_bins:
        raise DonGymError(f"datasets {not_bins} are not datasets of bins; pool bin datasets only with each other")
    names = [p["name"] for p in datasets[0].parts]
    if part is None or part not in names:
        raise DonGymError(f"part={part!r}: expected one of the bin dataset's parts {names}")
    model = load_part_models(datasets[0])[part]
    for other in datasets[1:]:
        models = load_part_models(other)
        if part not in models or model.shape_signature.differences(models[part].shape_signature):
            raise DonGymError(f"dataset {other.root} holds no part {part!r} of the shape of {datasets[0].root}'s")
    return model


def reference_edge_distances_px(result: TrackingResult, method: str) -> np.ndarray:
    """(M,) float: for each match of ``method`` in ``result``, the distance (pixels) of its reference pixel inside the
    part's silhouette in the reference frame (:func:`~don_gym.data.render.distance_inside_px` of the dataset's
    ``mask``), for :func:`~don_gym.evaluation.tracking_metrics.tail_by_edge_distance`. Datasets of one part only:
    in a pile the reference lies on one instance among others."""
    if method not in result.matches:
        raise DonGymError(f"method {method!r}: not in this result; it has {sorted(result.matches)}")
    datasets = [DONDataset(path) for path in result.datasets]
    piles = [str(data.root) for data in datasets if data.scene_kind == "bin"]
    if piles:
        raise DonGymError(f"{piles[0]}: a dataset of bins; reference edge distances are for datasets of one part")
    matches = result.matches[method]
    distances = np.zeros(len(matches.reference_frame), dtype=np.float64)
    keys = np.stack([matches.dataset, matches.scene, matches.reference_frame], axis=1)
    for key in np.unique(keys, axis=0):
        rows = np.flatnonzero((keys == key).all(axis=1))
        d, scene, frame = (int(v) for v in key)
        inside = distance_inside_px(np.asarray(datasets[d].image(scene, frame, "mask"), dtype=bool))
        u, v = matches.reference_uv[rows, 0], matches.reference_uv[rows, 1]
        distances[rows] = inside[v, u]
    return distances


def methods_for_part(methods: Sequence[str], part: ObjectModel) -> list[str]:
    """The model references of ``methods`` that describe ``part``: ``"oracle"`` and the networks trained on it
    (a network of several parts for each of them, :func:`~don_gym.learning.checkpoints.part_mismatch`)."""
    from don_gym.learning.checkpoints import part_mismatch
    from don_gym.zoo import read_don_metadata

    kept = []
    for method in methods:
        if method == "oracle" or part_mismatch(read_don_metadata(method), part) is None:
            kept.append(method)
    return kept


def evaluate_tracking_per_part(
    dataset: DONDataset | str | Path | Sequence[DONDataset | str | Path],
    methods: Sequence[str],
    config: TrackingConfig = TrackingConfig(),
    progress: bool = True,
    device: str = "cpu",
    batch_size: int | None = None,
) -> dict[str, TrackingResult]:
    """The tracking protocol on datasets of bins, per part: ``{part name: result}``, each part evaluated with
    the methods of ``methods`` that describe it (:func:`methods_for_part`: the oracle, its own networks, the
    networks of several parts that include it). A method that describes none of the parts is refused."""
    config.validate()
    datasets = open_datasets(dataset)
    if not methods:
        raise DonGymError("no methods to evaluate; give 'oracle' and/or network names or checkpoint paths")
    first = datasets[0]
    if first.scene_kind != "bin":
        raise DonGymError(f"{first.root}: not a dataset of bins (scene_kind {first.scene_kind!r})")
    from don_gym.data.bin_dataset import load_part_models

    models = load_part_models(first)
    per_part = {name: methods_for_part(methods, model) for name, model in models.items()}
    unused = [m for m in methods if not any(m in kept for kept in per_part.values())]
    if unused:
        raise DonGymError(
            f"model {unused[0]!r} describes none of the dataset's parts {list(models)}; "
            "give networks trained on one of them"
        )
    return {
        name: evaluate_tracking_depths(
            datasets, kept, config, (config.depth,), progress, device, batch_size, part=name
        )[config.depth]
        for name, kept in per_part.items()
    }
