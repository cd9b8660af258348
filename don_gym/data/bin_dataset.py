"""Datasets of bins (``scene_kind`` "bin"): piles of several parts' instances, their targets in one descriptor
space, and what training and evaluation read back from them.

:func:`build_bin_dataset` records piles (:class:`~don_gym.sim.bin_recorder.BinSceneRecorder`) and writes them in
the format of :mod:`don_gym.data.dataset`, version 2: every instance with its part and pose, the visible instance per
pixel (``instance/``), descriptor targets of every instance in its part's region of the dataset's
:class:`~don_gym.descriptors.multi_part.PartSpace` (``part_space.json``, each part's own field in
``part_fields/``), exact occlusion between instances, and fused depth over the bin for the self-supervised
method. :class:`BinTargets` turns a frame into the training target of a supervised variant. Layout:
docs/dataset_format.md, section "Bins of several parts".
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.data.build import (
    BaseSceneWriter,
    BuildReport,
    DatasetConfig,
    check_not_foreign,
    check_run_options,
    embed_part,
    join_dataset_dir,
    part_info,
    write_scenes,
)
from don_gym.data.build import dataset_info as _dataset_info_of_part
from don_gym.data.correspondences import Correspondences
from don_gym.data.dataset import (
    DATASET_FILE,
    FIELD_FILE,
    DatasetLock,
    DONDataset,
    SceneRecord,
    check_dataset_identity,
    check_dataset_info,
    read_json,
    write_json,
)
from don_gym.data.render import MultiPartDescriptorRenderer, default_edge_width_px, make_instances_target
from don_gym.descriptors import FIELD_MATCH_ATOL, DescriptorField
from don_gym.descriptors.multi_part import (
    DEFAULT_PART_GAP,
    IDENTITY_LAYOUT,
    PartSpace,
    build_part_space,
    part_space_for,
    training_layout,
)
from don_gym.errors import DatasetError, DonGymError
from don_gym.geometry import invert_transform
from don_gym.io import write_text_atomic
from don_gym.objects import ObjectModel, ShapeSignature, builtin_names, load_object, part_name

__all__ = [
    "BIN_FUSION_MARGIN_M",
    "BIN_MASK_WALL_MARGIN_M",
    "PART_FIELDS_DIR",
    "PART_SPACE_FILE",
    "BinSceneWriter",
    "BinTargets",
    "build_bin_dataset",
    "dataset_info",
    "filter_correspondences_by_instance",
    "instance_parts",
    "is_multi_part",
    "load_part_fields",
    "load_part_models",
    "load_part_space",
    "parse_parts",
    "prepare_bin_dataset_dir",
    "resolve_bin_parts",
]

#: The dataset's descriptor space (:meth:`PartSpace.to_dict`) and each part's own optimal field.
PART_SPACE_FILE = "part_space.json"
PART_FIELDS_DIR = "part_fields"
#: Margin (m) of the TSDF volume around the bin's inside.
BIN_FUSION_MARGIN_M = 0.02
#: The fused masks keep points this far (m) inside the bin's walls: the walls are not a part.
BIN_MASK_WALL_MARGIN_M = 0.004


def parse_parts(text: str) -> dict[str, int]:
    """``"toolcap:3,shaft:2"`` -> ``{"toolcap": 3, "shaft": 2}`` (counts checked later, by the bin's checks)."""
    parts: dict[str, int] = {}
    for item in str(text).split(","):
        name, sep, count = item.strip().rpartition(":")
        try:
            value = int(count)
        except ValueError:
            value = None
        if not sep or not name or value is None:
            raise DatasetError(f"--parts {text!r}: expected PART:COUNT[,PART:COUNT...], e.g. toolcap:3,shaft:2")
        if name in parts:
            raise DatasetError(f"--parts {text!r}: part {name!r} is given twice")
        parts[name] = value
    return parts


def resolve_bin_parts(parts: Mapping[str, int]) -> tuple[dict[str, ObjectModel], dict[str, int]]:
    """Models and counts (by part name) of the parts, checked as the bin env checks them (unknown part, more parts
    than fit the bin) and every count at least 1: DatasetError naming the input."""
    from don_gym.sim.bin_env import resolve_parts

    if not isinstance(parts, Mapping) or not parts:
        raise DatasetError(f"parts={parts!r} (--parts): expected PART:COUNT pairs, e.g. toolcap:3,shaft:2")
    for key, count in parts.items():
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise DatasetError(
                f"parts={dict(parts)!r} (--parts): part {key!r} has count {count!r}; expected a count of at least 1 "
                "(leave out a part the piles should not hold)"
            )
    present = list(parts)
    try:
        models, counts, _ = resolve_parts(dict(parts), present[0] if present else next(iter(parts)), None)
    except DonGymError as exc:
        raise DatasetError(f"{exc} (--parts)") from None
    if not any(counts.values()):
        raise DatasetError(f"parts={dict(parts)!r} (--parts): expected at least one instance in the bin")
    keep = [name for name in models if counts[name] > 0]
    return {n: models[n] for n in keep}, {n: counts[n] for n in keep}


def dataset_info(
    config: DatasetConfig,
    models: Mapping[str, ObjectModel],
    counts: Mapping[str, int],
    keys: Mapping[str, str],
    fields: Mapping[str, DescriptorField],
    space: PartSpace,
) -> dict[str, Any]:
    primary = next(iter(models))
    parts = [{**part_info(models[name], None), "key": keys[name]} for name in models]
    return {
        **_dataset_info_of_part(
            replace(config, object=keys[primary], object_scale=None),
            models[primary],
            fields[primary],
            scene_kind="bin",
            parts=parts,
            background=space.background,
        ),
        "bin_parts": dict(counts),
        "part_gap": space.gap,
        "part_space_file": PART_SPACE_FILE,
    }


def _check_bin_identity(recorded: dict[str, Any], wanted: dict[str, Any], out_dir: Path) -> None:
    """The single-part identity checks (settings, primary part), then the pile: parts and counts, by shape."""
    if recorded.get("scene_kind") != "bin":
        raise DatasetError(
            f"{out_dir}: holds a dataset of scene kind {recorded.get('scene_kind', 'single')!r}, not bins; "
            "pass --overwrite to replace it or use another directory"
        )
    check_dataset_identity(recorded, wanted, out_dir)
    problems = []
    if recorded.get("bin_parts") != wanted["bin_parts"]:
        problems.append(f"parts {recorded.get('bin_parts')} on disk, {wanted['bin_parts']} asked")
    else:
        for on_disk, asked in zip(recorded.get("parts", []), wanted["parts"], strict=False):
            signature = ShapeSignature.from_dict(asked["object_signature"])
            differences = signature.differences(ShapeSignature.from_dict(on_disk["object_signature"]))
            if differences:
                problems.append(f"part {asked['name']!r}: {', '.join(differences[:2])}")
    if recorded.get("part_gap") != wanted["part_gap"]:
        problems.append(f"part gap {recorded.get('part_gap')} on disk, {wanted['part_gap']} asked")
    if problems:
        raise DatasetError(
            f"{out_dir}: holds a different pile ({'; '.join(problems)}) (--parts); pass --overwrite to replace it "
            "or use another directory"
        )


def _field_path(out_dir: Path, name: str) -> Path:
    return out_dir / PART_FIELDS_DIR / f"{name}.npz"


def _resolve(
    out_dir: Path,
    config: DatasetConfig,
    models: dict[str, ObjectModel],
    counts: dict[str, int],
    keys: dict[str, str],
    computed: dict[str, DescriptorField],
    gap: float,
    write: bool,
) -> tuple[dict[str, DescriptorField], PartSpace]:
    """The fields and space to render targets with (the recorded ones when there are), after checking
    ``out_dir``'s dataset against the options; with ``write``, publish what is missing."""
    info_path = out_dir / DATASET_FILE
    recorded = check_dataset_info(read_json(info_path), info_path) if info_path.is_file() else None
    if recorded is None:
        check_not_foreign(out_dir, (PART_SPACE_FILE, PART_FIELDS_DIR))
    fields = {}
    for name, field in computed.items():
        path = _field_path(out_dir, name)
        stored = DescriptorField.load(path) if (recorded is not None and path.is_file()) else None
        if stored is not None and (
            stored.n_vertices != field.n_vertices or stored.max_difference(field) > FIELD_MATCH_ATOL
        ):
            raise DatasetError(
                f"{path}: is not part {name!r}'s field with these options; pass --overwrite to rebuild the dataset"
            )
        fields[name] = stored if stored is not None else field
    space = part_space_for([models[n] for n in models], [fields[n] for n in models], gap=gap)
    wanted = dataset_info(config, models, counts, keys, fields, space)
    if recorded is not None:
        _check_bin_identity(recorded, wanted, out_dir)
        recorded_space = PartSpace.from_dict(read_json(out_dir / PART_SPACE_FILE), str(out_dir / PART_SPACE_FILE))
        if config.scenes < int(recorded["scenes"]):
            raise DatasetError(
                f"{out_dir}: records {recorded['scenes']} scenes and scenes={config.scenes} (--scenes) asks for "
                f"fewer; pass --scenes {recorded['scenes']} (or more), --overwrite, or use another directory"
            )
        if write and config.scenes > int(recorded["scenes"]):
            write_json(info_path, {**recorded, "scenes": config.scenes})
        return fields, recorded_space
    if write:
        (out_dir / PART_FIELDS_DIR).mkdir(parents=True, exist_ok=True)
        for name in models:
            if not _field_path(out_dir, name).is_file():
                fields[name].save(_field_path(out_dir, name))
        primary = next(iter(models))
        if not (out_dir / FIELD_FILE).is_file():
            fields[primary].save(out_dir / FIELD_FILE)
        write_text_atomic(out_dir / PART_SPACE_FILE, json.dumps(space.to_dict(), indent=1) + "\n")
        write_json(info_path, wanted)  # last: a dataset.json means the dataset-level files are all there
    return fields, space


@dataclass(frozen=True)
class _Prepared:
    models: dict[str, ObjectModel]
    counts: dict[str, int]
    fields: dict[str, DescriptorField]
    space: PartSpace


def prepare_bin_dataset_dir(
    out_dir: Path, config: DatasetConfig, parts: Mapping[str, int], overwrite: bool, gap: float = DEFAULT_PART_GAP
) -> tuple[_Prepared, DatasetLock]:
    """Validate everything, then create, replace (``overwrite``) or join the bin dataset in ``out_dir``; nothing
    is written before every option and the recorded dataset (if any) have been checked."""
    config.validate()
    if config.distractors:
        raise DatasetError(
            f"distractors={config.distractors} (--distractors): a bin scene has no distractors "
            "(the pile is the clutter)"
        )
    if config.object_scale is not None:
        raise DatasetError(
            f"object_scale={config.object_scale!r} (--object-scale): a bin's parts are built-in parts or mesh "
            "files in metres (--parts); scale a mesh file to metres first"
        )
    models, counts = resolve_bin_parts(parts)
    keys = {part_name(str(key)): str(key) for key in parts if part_name(str(key)) in models}
    config = replace(config, object=keys[next(iter(models))], object_scale=None)
    computed = {name: embed_part(model, config, f"part {model.name!r} (--parts)") for name, model in models.items()}
    if overwrite and out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a directory; expected a dataset directory")
    (fields, space), lock = join_dataset_dir(
        out_dir,
        config,
        overwrite,
        lambda write: _resolve(out_dir, config, models, counts, keys, computed, gap, write),
        (PART_SPACE_FILE, PART_FIELDS_DIR),
    )
    return _Prepared(models, counts, fields, space), lock


class BinSceneWriter(BaseSceneWriter):
    """Records and writes bin scenes (the machinery: :class:`~don_gym.data.build.BaseSceneWriter`).

    Per frame the targets are ``instance`` (the simulator's segmentation: visible instance id per pixel),
    ``mask`` (pixels of any instance), the descriptor target of every instance in its part's region of the
    space, with exact occlusion between instances (:class:`~don_gym.data.render.MultiPartDescriptorRenderer`; a pixel
    keeps its hit where the segmentation names the same instance), and ``target_mask`` (the pixels with a part
    target). The fused depth is fused over the bin, ``mask_fused`` the fused points inside the bin's walls.
    """

    def __init__(self, config: DatasetConfig, out_dir: Path, prepared: _Prepared, lock: DatasetLock) -> None:
        from don_gym.sim.bin_recorder import BinSceneRecorder

        super().__init__(config, out_dir, lock)
        self.prepared = prepared
        self.names = self.part_names = list(prepared.models)
        self._open_recorder(lambda: BinSceneRecorder(prepared.models, prepared.counts, **self._recorder_options()))
        space = prepared.space
        self.renderer = MultiPartDescriptorRenderer(
            [prepared.models[n].mesh for n in self.names],
            [space.map_descriptors(n, prepared.fields[n].vertex_descriptors) for n in self.names],
            space.background,
        )

    def _instances(self, scene: Any) -> list[dict[str, Any]]:
        return scene.instances

    def _frame_targets(self, scene: Any, instances: list[dict[str, Any]], frame: Any) -> dict[str, np.ndarray]:
        T_camera_world = invert_transform(frame.T_world_camera_reported)
        rendered = self.renderer.render(
            scene.intrinsics,
            [(self.names.index(i["part"]), T_camera_world @ i["T_world_object"]) for i in instances],
            instance_ids=[i["instance_id"] for i in instances],
            visible_instance_ids=frame.instance_ids,
        )
        return {
            "mask": frame.instance_ids > 0,
            "instance": frame.instance_ids,
            "target_mask": rendered.object_mask,
            "descriptor": rendered.descriptor_image,
        }

    def _fusion_region(self, scene: Any) -> tuple[tuple[np.ndarray, np.ndarray], dict[str, Any]]:
        from don_gym.sim.bin_recorder import bin_region_world

        T_box, half = bin_region_world()
        centre = T_box[:3, 3]
        margin = np.array([BIN_FUSION_MARGIN_M, BIN_FUSION_MARGIN_M, 0.0])
        bounds_min = centre - half - margin
        bounds_max = centre + half + margin
        bounds_min[2] = scene.table_height_m - 0.01
        return (bounds_min, bounds_max), {"object_region_world": bin_region_world(BIN_MASK_WALL_MARGIN_M)}


def build_bin_dataset(
    config: DatasetConfig,
    parts: Mapping[str, int],
    out_dir: str | Path,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
    overwrite: bool = False,
    progress: bool = True,
    gap: float = DEFAULT_PART_GAP,
) -> BuildReport:
    """Build (or resume) a dataset of bins: ``parts`` maps a part (built-in name or mesh file) to its instances
    per pile; ``config`` as for :func:`~don_gym.data.build.build_dataset` (its ``object`` is ignored; no distractors).
    Scene ``i`` is the pile of seed ``SeedSequence([seed, i])``; ``shard=(i, n)`` takes scenes ``i, i+n, ...``;
    finished scenes are skipped; ``workers`` processes each own one PyBullet client."""
    out_dir = Path(out_dir)
    start = time.perf_counter()
    shard = check_run_options(workers, shard)
    prepared, lock = prepare_bin_dataset_dir(out_dir, config, parts, overwrite, gap)
    config = replace(config, object=str(read_json(out_dir / DATASET_FILE)["object"]), object_scale=None)
    return write_scenes(
        config,
        out_dir,
        lock,
        lambda: BinSceneWriter(config, out_dir, prepared, lock),
        functools.partial(_open_bin_writer, config, dict(parts)),
        workers=workers,
        shard=shard,
        progress=progress,
        start=start,
        desc="build-dataset (bin)",
    )


def _open_bin_writer(config: DatasetConfig, parts: dict[str, int], out_dir: Path, lock: DatasetLock) -> BinSceneWriter:
    """A worker's writer: the parts' fields and the space read back from the dataset."""
    models, counts = resolve_bin_parts(parts)
    fields = {name: DescriptorField.load(_field_path(out_dir, name)) for name in models}
    space = PartSpace.from_dict(read_json(out_dir / PART_SPACE_FILE), str(out_dir / PART_SPACE_FILE))
    return BinSceneWriter(config, out_dir, _Prepared(models, counts, fields, space), lock)


# --- reading ------------------------------------------------------------------------------------------------


def is_multi_part(data: DONDataset) -> bool:
    """Whether ``data`` stores its targets in a multi-part space (a bin dataset)."""
    return (data.root / PART_SPACE_FILE).is_file() and data.scene_kind == "bin"


def load_part_space(data: DONDataset) -> PartSpace:
    """The descriptor space a bin dataset's ``descriptor/`` targets lie in."""
    path = data.root / PART_SPACE_FILE
    try:
        return PartSpace.from_dict(read_json(path), str(path))
    except DonGymError as exc:
        raise DatasetError(str(exc)) from None


def load_part_fields(data: DONDataset) -> dict[str, DescriptorField]:
    """Each part's own optimal field, by name, in the order of :attr:`DONDataset.parts`."""
    fields = {}
    for part in data.parts:
        path = data.root / PART_FIELDS_DIR / f"{part['name']}.npz"
        try:
            fields[part["name"]] = DescriptorField.load(path)
        except DonGymError as exc:
            raise DatasetError(f"{path}: {exc}") from None
    return fields


def load_part_models(data: DONDataset) -> dict[str, ObjectModel]:
    """Each part's model, by name, checked to be the recorded part (by shape signature)."""
    models = {}
    for part in data.parts:
        spec = part.get("key") or part["name"]
        source = part.get("object_source")
        if not Path(str(spec)).exists() and spec not in builtin_names() and source and Path(source).is_file():
            spec = source
        try:
            model = load_object(str(spec), scale=part.get("object_scale"))
        except DonGymError as exc:
            raise DatasetError(f"{data.root}: part {part['name']!r} cannot be loaded: {exc}") from None
        if part.get("object_signature"):
            differences = model.shape_signature.differences(ShapeSignature.from_dict(part["object_signature"]))
            if differences:
                raise DatasetError(
                    f"{data.root}: part {part['name']!r} differs from the one it was built from "
                    f"({', '.join(differences[:3])})"
                )
        models[part["name"]] = model
    return models


def instance_parts(record: SceneRecord) -> dict[int, str]:
    """Instance id -> part name of a scene."""
    return {int(i["instance_id"]): str(i["part"]) for i in record.instances}


def _own_descriptors(space: PartSpace, descriptor_image: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The inverse of :meth:`PartSpace.map_descriptor_image` on labelled pixels: (H, W, F) each part's own field
    values (F = :attr:`PartSpace.field_dim`), 0 off every part."""
    out = np.zeros((*descriptor_image.shape[:2], space.field_dim), dtype=np.float32)
    for k in range(len(space.parts)):
        on = labels == k + 1
        if on.any():
            out[on] = np.clip(space.own_descriptors(k, descriptor_image[on]), 0.0, 1.0)
    return out


class BinTargets:
    """Training targets of a bin dataset for a supervised variant (``make_instances_target`` of each frame).

    ``layout`` (:data:`~don_gym.descriptors.multi_part.TRAINING_LAYOUT_CHOICES`, resolved by
    :func:`~don_gym.descriptors.multi_part.training_layout`): ``"identity"`` trains ``"geometric"`` and ``"edge"``
    in the identity layout of the dataset's fields (one dimension more: each part's whole field plus its identity
    coordinate), the stored targets moved into it; it refuses ``"mask"``. ``"dataset"`` trains them in the
    dataset's own space (``part_space.json``). ``"auto"`` is ``"identity"`` wherever it applies. ``"mask"`` trains
    in a space built from the same fields with the last dimension left to the mask channel
    (:func:`~don_gym.descriptors.multi_part.build_part_space` with ``mask_dim=-1``), the stored targets moved
    into it. :attr:`space` is the one the network learns (its checkpoint records it; the network outputs its
    :attr:`~PartSpace.dim` channels), :attr:`background` its background (the targets' off every instance).
    """

    def __init__(
        self, data: DONDataset, variant: str, edge_width_px: float | None = None, layout: str = "auto"
    ) -> None:
        if layout == IDENTITY_LAYOUT and variant == "mask":
            raise DatasetError(
                "part layout 'identity' does not support the mask variant (supervised-mask), whose mask channel "
                "would replace a descriptor dimension; use supervised or supervised-edge, or part layout 'auto'"
            )
        self.data = data
        self.variant = variant
        self.stored_space = load_part_space(data)
        if layout == IDENTITY_LAYOUT and len(self.stored_space.parts) < 2:
            raise DatasetError(
                f"part layout 'identity' (--part-layout) is for several parts; {data.root} holds one part "
                f"({self.stored_space.names[0]!r}), which trains in its own space (--part-layout auto)"
            )
        try:
            #: The layout the targets are in: ``"identity"`` or ``"dataset"``.
            self.layout = training_layout(layout, self.stored_space.names, self.stored_space.gap, variant == "mask")
        except DonGymError as exc:
            raise DatasetError(str(exc)) from None
        if variant == "mask" or self.layout == IDENTITY_LAYOUT:
            fields = load_part_fields(data)
            self.space = build_part_space(
                list(self.stored_space.names),
                [fields[n].vertex_descriptors for n in self.stored_space.names],
                [p.signature for p in self.stored_space.parts],
                gap=self.stored_space.gap,
                mask_dim=-1 if variant == "mask" else None,
                layout=IDENTITY_LAYOUT if self.layout == IDENTITY_LAYOUT else "auto",
            )
        else:
            self.space = self.stored_space
        self.background = np.asarray(self.space.background, dtype=np.float32)
        width = data.scenes[0].intrinsics.width
        self.edge_width_px = default_edge_width_px(width) if edge_width_px is None else float(edge_width_px)

    def frame(self, scene: int, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(target (H, W, D) float32 (D = :attr:`space`'s), object_mask (H, W) bool)`` of one frame."""
        mask = self.data.image(scene, frame, "target_mask")
        ids = np.where(mask, self.data.image(scene, frame, "instance"), 0).astype(np.int32)
        descriptor = self.data.image(scene, frame, "descriptor")
        if self.space is not self.stored_space:
            labels = self.stored_space.part_image(ids, instance_parts(self.data.scenes[scene]))
            descriptor = self.space.map_descriptor_image(
                _own_descriptors(self.stored_space, descriptor, labels), labels
            )
        target = make_instances_target(self.variant, descriptor, ids, self.background, self.edge_width_px, mask_dim=-1)
        return target, mask


def filter_correspondences_by_instance(
    correspondences: Correspondences,
    instance_ids_a: np.ndarray,
    instance_ids_b: np.ndarray,
    part_of_instance: Mapping[int, str],
) -> Correspondences:
    """Correspondences of a pile for the self-supervised method, as the original multi-object DON training keeps
    objects apart: matches only within one instance; non-matches on the same instance or on another part, or
    off every instance, never on another instance of the same part (whose descriptors the network should give
    alike, a part's descriptors being the part's and not the instance's).

    Args:
        correspondences: sampled on the pile's fused depth and masks (pixels (u, v) of full images).
        instance_ids_a, instance_ids_b: (H, W) int the visible instance per pixel of each image (0 = none).
        part_of_instance: instance id -> part name.
    """
    parts = {0: ""} | {int(k): str(v) for k, v in part_of_instance.items()}
    lookup = np.full(max(parts) + 1, -1, dtype=np.int64)
    names = sorted(set(parts.values()))
    for instance, name in parts.items():
        lookup[instance] = names.index(name) if instance else -1

    def ids(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
        return np.asarray(image)[uv[:, 1], uv[:, 0]].astype(np.int64)

    def keep_nonmatches(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        id_a, id_b = ids(instance_ids_a, a), ids(instance_ids_b, b)
        same_instance = (id_a == id_b) & (id_a > 0)
        same_part = (lookup[id_a] == lookup[id_b]) & (id_a > 0) & (id_b > 0)
        return same_instance | ~same_part

    c = correspondences
    match_a, match_b = ids(instance_ids_a, c.matches_a), ids(instance_ids_b, c.matches_b)
    keep_match = (match_a == match_b) & (match_a > 0)
    keep_object = keep_nonmatches(c.nonmatches_object_a, c.nonmatches_object_b)
    keep_background = keep_nonmatches(c.nonmatches_background_a, c.nonmatches_background_b)
    return Correspondences(
        matches_a=c.matches_a[keep_match],
        matches_b=c.matches_b[keep_match],
        nonmatches_object_a=c.nonmatches_object_a[keep_object],
        nonmatches_object_b=c.nonmatches_object_b[keep_object],
        nonmatches_background_a=c.nonmatches_background_a[keep_background],
        nonmatches_background_b=c.nonmatches_background_b[keep_background],
    )
