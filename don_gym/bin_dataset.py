"""Datasets of bins (``scene_kind`` "bin"): piles of several parts' instances, their targets in one descriptor
space, and what training and evaluation read back from them.

:func:`build_bin_dataset` records piles (:class:`~don_gym.sim.bin_recorder.BinSceneRecorder`) and writes them in
the format of :mod:`don_gym.dataset`, version 2: every instance with its part and pose, the visible instance per
pixel (``instance/``), descriptor targets of every instance in its part's region of the dataset's
:class:`~don_gym.descriptors.multi_part.PartSpace` (``part_space.json``, each part's own field in
``part_fields/``), exact occlusion between instances, and fused depth over the bin for the self-supervised
method. :class:`BinTargets` turns a frame into the training target of a supervised variant. Layout:
docs/dataset_format.md, section "Bins of several parts".
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import shutil
import signal
import time
import warnings
from collections.abc import Iterator, Mapping
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym import __version__
from don_gym.build import (
    DatasetConfig,
    _check_renderer_available,
    _check_run_options,
    _children_ignore_ctrl_c,
    _clear_dir,
    scene_seed,
    single_threaded_children,
)
from don_gym.correspondences import Correspondences
from don_gym.dataset import (
    DATASET_FILE,
    FIELD_FILE,
    FORMAT_NAME,
    FORMAT_VERSION,
    SCENE_FILE,
    DatasetLock,
    DONDataset,
    SceneRecord,
    check_dataset_identity,
    check_dataset_info,
    new_scene_tmp_dir,
    publish_scene,
    read_json,
    remove_stale_scene_dirs,
    scene_dir,
    scene_is_complete,
    write_frame,
    write_json,
)
from don_gym.descriptors import FIELD_MATCH_ATOL, DescriptorField, embed
from don_gym.descriptors.multi_part import DEFAULT_PART_GAP, PartSpace, build_part_space, part_space_for
from don_gym.errors import DatasetError, DonGymError, SeveralPiecesError
from don_gym.fusion import fuse_scene, fused_object_masks
from don_gym.geometry import invert_transform
from don_gym.io import LOCK_FILE, write_text_atomic
from don_gym.objects import ObjectModel, ShapeSignature, builtin_names, load_object, part_name
from don_gym.render import MultiPartDescriptorRenderer, default_edge_width_px, make_instances_target

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
    """Models and counts (by part name) of the parts with at least one instance, checked as the bin env checks
    them (unknown part, negative count, more parts than fit the bin): DatasetError naming the input."""
    from don_gym.sim.bin_env import _resolve_parts

    if not isinstance(parts, Mapping) or not parts:
        raise DatasetError(f"parts={parts!r} (--parts): expected PART:COUNT pairs, e.g. toolcap:3,shaft:2")
    present = [key for key, count in parts.items() if isinstance(count, int) and count > 0]
    try:
        models, counts, _ = _resolve_parts(dict(parts), present[0] if present else next(iter(parts)), None)
    except DonGymError as exc:
        raise DatasetError(f"{exc} (--parts)") from None
    if not any(counts.values()):
        raise DatasetError(f"parts={dict(parts)!r} (--parts): expected at least one instance in the bin")
    keep = [name for name in models if counts[name] > 0]
    return {n: models[n] for n in keep}, {n: counts[n] for n in keep}


def _embed(model: ObjectModel, config: DatasetConfig) -> DescriptorField:
    try:
        return embed(model, dim=config.descriptor_dim, symmetric=config.symmetric)
    except SeveralPiecesError as exc:
        raise DatasetError(f"part {model.name!r} (--parts): {exc.detail}; a dataset needs parts in one piece") from exc


def _part_record(model: ObjectModel, key: str) -> dict[str, Any]:
    return {
        "name": model.name,
        "object_source": model.source,
        "object_scale": None,
        "object_signature": model.shape_signature.to_dict(),
        "mesh_hash": model.mesh_hash,
        "key": key,
    }


def _dataset_info(
    config: DatasetConfig,
    models: Mapping[str, ObjectModel],
    counts: Mapping[str, int],
    keys: Mapping[str, str],
    fields: Mapping[str, DescriptorField],
    space: PartSpace,
) -> dict[str, Any]:
    primary = next(iter(models))
    model = models[primary]
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "don_gym_version": __version__,
        **asdict(replace(config, object=keys[primary], object_scale=None)),
        "object_name": model.name,
        "object_signature": model.shape_signature.to_dict(),
        "object_source": model.source,
        "mesh_hash": model.mesh_hash,
        "descriptor_field_hash": fields[primary].field_hash,
        "background_descriptor": space.background,
        "scene_kind": "bin",
        "parts": [_part_record(models[name], keys[name]) for name in models],
        "bin_parts": dict(counts),
        "part_gap": space.gap,
        "part_space_file": PART_SPACE_FILE,
    }


def _check_not_foreign(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a directory; expected a dataset directory")
    if not out_dir.is_dir():
        return
    ours = (LOCK_FILE, FIELD_FILE, PART_SPACE_FILE, PART_FIELDS_DIR, f"{DATASET_FILE}.partial-")
    foreign = sorted(
        p.name for p in out_dir.iterdir() if not (p.name.startswith(ours) or p.name.lstrip(".").startswith(ours))
    )
    if foreign:
        raise DatasetError(
            f"{out_dir}: exists and is not a don_gym dataset (holds {foreign[0]!r}); "
            "use an empty directory or --overwrite"
        )


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
        _check_not_foreign(out_dir)
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
    wanted = _dataset_info(config, models, counts, keys, fields, space)
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
    computed = {name: _embed(model, config) for name, model in models.items()}
    if overwrite and out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a directory; expected a dataset directory")
    if not overwrite:
        _resolve(out_dir, config, models, counts, keys, computed, gap, write=False)
    _check_renderer_available(config.renderer)
    out_dir.mkdir(parents=True, exist_ok=True)
    lock = DatasetLock(out_dir)
    try:
        lock.hold_session(exclusive=overwrite)
        if overwrite:
            _clear_dir(out_dir)
            lock.share_session()
        with lock.metadata():
            fields, space = _resolve(out_dir, config, models, counts, keys, computed, gap, write=True)
    except BaseException:
        lock.close()
        raise
    return _Prepared(models, counts, fields, space), lock


class BinSceneWriter:
    """Records and writes bin scenes; owns one PyBullet client.

    Per frame: RGB, sensor and ideal depth, ``instance`` (the simulator's segmentation: visible instance id per
    pixel), ``mask`` (pixels of any instance), the descriptor target of every instance in its part's region of
    the space, rendered from the *reported* camera pose with exact occlusion between instances
    (:class:`~don_gym.render.MultiPartDescriptorRenderer`; a pixel keeps its hit where the segmentation names
    the same instance), and ``target_mask`` (the pixels with a part target). With ``fuse_depth`` the sensor depth
    fused over the bin, re-rendered per frame, and ``mask_fused`` (fused points inside the bin's walls).
    """

    def __init__(self, config: DatasetConfig, out_dir: Path, prepared: _Prepared, lock: DatasetLock) -> None:
        from don_gym.sim.bin_recorder import BinSceneRecorder

        self.config = config
        self.out_dir = out_dir
        self.lock = lock
        self.prepared = prepared
        self.names = list(prepared.models)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.recorder = BinSceneRecorder(
                prepared.models,
                prepared.counts,
                config.image_size,
                sensor=config.sensor,
                renderer=config.renderer,
                backgrounds=config.backgrounds,
                lighting=config.lighting,
            )
        space = prepared.space
        self.renderer = MultiPartDescriptorRenderer(
            [prepared.models[n].mesh for n in self.names],
            [space.map_descriptors(n, prepared.fields[n].vertex_descriptors) for n in self.names],
            space.background,
        )

    def write_scene(self, scene_index: int) -> int:
        final = scene_dir(self.out_dir, scene_index)
        with self.lock.scene(scene_index):
            if scene_is_complete(final):
                return 0
            remove_stale_scene_dirs(self.out_dir, scene_index)
            tmp = new_scene_tmp_dir(self.out_dir, scene_index)
            try:
                frames = self._record(tmp, scene_index)
                return frames if publish_scene(tmp, final) else 0
            finally:
                if tmp.exists():
                    shutil.rmtree(tmp, ignore_errors=True)

    def _record(self, path: Path, scene_index: int) -> int:
        config = self.config
        seed = scene_seed(config.seed, scene_index)
        scene = self.recorder.record(seed=seed, num_frames=config.frames_per_scene)
        instances = scene.instances
        ids = [i["instance_id"] for i in instances]
        part_index = [self.names.index(i["part"]) for i in instances]
        for f, frame in enumerate(scene.frames):
            T_camera_world = invert_transform(frame.T_world_camera_reported)
            rendered = self.renderer.render(
                scene.intrinsics,
                [(k, T_camera_world @ i["T_world_object"]) for k, i in zip(part_index, instances, strict=True)],
                instance_ids=ids,
                visible_instance_ids=frame.instance_ids,
            )
            write_frame(
                path,
                f,
                {
                    "rgb": frame.rgb,
                    "depth": frame.depth_m,
                    "depth_ideal": frame.depth_ideal_m,
                    "mask": frame.instance_ids > 0,
                    "instance": frame.instance_ids,
                    "target_mask": rendered.object_mask,
                    "descriptor": rendered.descriptor_image,
                },
                config.descriptor_dim,
            )
        if config.fuse_depth:
            self._write_fused(path, scene)
        primary = self.names[0]
        first = next((i for i in instances if i["part"] == primary), instances[0] if instances else None)
        write_json(
            path / SCENE_FILE,
            {
                "scene_index": scene_index,
                "seed": seed,
                "object": primary,
                "intrinsics": scene.intrinsics.as_array(),
                # For readers of one object: the first instance of the primary part.
                "T_world_object": first["T_world_object"] if first is not None else np.eye(4),
                "instances": instances,
                "T_camera_object": [
                    {
                        str(i["instance_id"]): invert_transform(fr.T_world_camera) @ i["T_world_object"]
                        for i in instances
                    }
                    for fr in scene.frames
                ],
                "T_world_camera": np.stack([fr.T_world_camera for fr in scene.frames]),
                "T_world_camera_reported": np.stack([fr.T_world_camera_reported for fr in scene.frames]),
                "table_height_m": scene.table_height_m,
                "background": scene.background,
                "fused_depth": config.fuse_depth,
            },
        )
        return len(scene.frames)

    def _write_fused(self, path: Path, scene) -> None:
        from don_gym.sim.bin_recorder import bin_region_world

        reported = [fr.T_world_camera_reported for fr in scene.frames]
        T_box, half = bin_region_world()
        centre = T_box[:3, 3]
        margin = np.array([BIN_FUSION_MARGIN_M, BIN_FUSION_MARGIN_M, 0.0])
        bounds_min = centre - half - margin
        bounds_max = centre + half + margin
        bounds_min[2] = scene.table_height_m - 0.01
        volume = fuse_scene(
            [fr.depth_m for fr in scene.frames],
            scene.intrinsics,
            reported,
            (bounds_min, bounds_max),
            voxel_size_m=self.config.voxel_size_m,
        )
        depths, masks = fused_object_masks(
            volume,
            scene.intrinsics,
            reported,
            bin_region_world(BIN_MASK_WALL_MARGIN_M),
            table_height_m=scene.table_height_m,
        )
        for f, (depth, mask) in enumerate(zip(depths, masks, strict=True)):
            write_frame(path, f, {"depth_fused": depth, "mask_fused": mask}, self.config.descriptor_dim)

    def close(self) -> None:
        self.recorder.close()


@dataclass(frozen=True)
class BinBuildReport:
    scenes_written: int
    scenes_skipped: int
    frames_written: int
    seconds: float
    scenes_complete: int = 0
    scenes_total: int = 0

    @property
    def frames_per_second(self) -> float:
        return self.frames_written / self.seconds if self.seconds > 0 else 0.0


def build_bin_dataset(
    config: DatasetConfig,
    parts: Mapping[str, int],
    out_dir: str | Path,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
    overwrite: bool = False,
    progress: bool = True,
    gap: float = DEFAULT_PART_GAP,
) -> BinBuildReport:
    """Build (or resume) a dataset of bins: ``parts`` maps a part (built-in name or mesh file) to its instances
    per pile; ``config`` as for :func:`~don_gym.build.build_dataset` (its ``object`` is ignored; no distractors).
    Scene ``i`` is the pile of seed ``SeedSequence([seed, i])``; ``shard=(i, n)`` takes scenes ``i, i+n, ...``;
    finished scenes are skipped; ``workers`` processes each own one PyBullet client."""
    out_dir = Path(out_dir)
    start = time.perf_counter()
    shard_index, shard_count = _check_run_options(workers, shard)
    prepared, lock = prepare_bin_dataset_dir(out_dir, config, parts, overwrite, gap)
    config = replace(config, object=str(read_json(out_dir / DATASET_FILE)["object"]), object_scale=None)
    written = skipped = frames = 0
    try:
        todo = []
        for i in range(shard_index, config.scenes, shard_count):
            if scene_is_complete(scene_dir(out_dir, i)):
                skipped += 1
            else:
                todo.append(i)
        if todo:
            if workers > 1 and len(todo) > 1:
                results = _write_in_workers(config, dict(parts), out_dir, min(workers, len(todo)), todo)
            else:
                results = _write_in_process(config, out_dir, prepared, lock, todo)
            with (
                contextlib.closing(results),
                tqdm(total=len(todo), unit="scene", desc="build-dataset (bin)", disable=not progress) as bar,
            ):
                for n in results:
                    written, frames, skipped = written + (n > 0), frames + n, skipped + (n == 0)
                    bar.update(1)
    finally:
        lock.close()
    complete = sum(scene_is_complete(scene_dir(out_dir, i)) for i in range(config.scenes))
    return BinBuildReport(written, skipped, frames, time.perf_counter() - start, complete, config.scenes)


def _write_in_process(
    config: DatasetConfig, out_dir: Path, prepared: _Prepared, lock: DatasetLock, todo: list[int]
) -> Iterator[int]:
    writer = BinSceneWriter(config, out_dir, prepared, lock)
    try:
        for i in todo:
            yield writer.write_scene(i)
    finally:
        writer.close()


_WORKER: BinSceneWriter | None = None


def _worker_init(config: DatasetConfig, parts: dict[str, int], out_dir: str) -> None:
    global _WORKER  # one writer per worker process, created once
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool on Ctrl-C
    root = Path(out_dir)
    lock = DatasetLock(root)
    lock.hold_session()
    models, counts = resolve_bin_parts(parts)
    fields = {name: DescriptorField.load(_field_path(root, name)) for name in models}
    space = PartSpace.from_dict(read_json(root / PART_SPACE_FILE), str(root / PART_SPACE_FILE))
    _WORKER = BinSceneWriter(config, root, _Prepared(models, counts, fields, space), lock)


def _worker_write(scene_index: int) -> int:
    assert _WORKER is not None
    return _WORKER.write_scene(scene_index)


def _write_in_workers(
    config: DatasetConfig, parts: dict[str, int], out_dir: Path, workers: int, todo: list[int]
) -> Iterator[int]:
    pool = ProcessPoolExecutor(
        workers, mp_context=mp.get_context("spawn"), initializer=_worker_init, initargs=(config, parts, str(out_dir))
    )
    try:
        with single_threaded_children(), _children_ignore_ctrl_c():
            pending = {pool.submit(_worker_write, i) for i in todo}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
    except BrokenProcessPool:
        raise DatasetError(
            f"{out_dir}: a worker process died while writing scenes (killed, or out of memory?); finished "
            "scenes are kept: run the same command again to resume"
        ) from None
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


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
    """The inverse of :meth:`PartSpace.map_descriptor_image` on labelled pixels (each part's own field values)."""
    out = np.zeros_like(descriptor_image, dtype=np.float32)
    dims = space.separated_dims
    for k, region in enumerate(space.parts):
        on = labels == k + 1
        if on.any():
            values = descriptor_image[on].astype(np.float64)
            values[:, dims] = (values[:, dims] - region.offset[dims]) / region.scale
            out[on] = np.clip(values, 0.0, 1.0)
    return out


class BinTargets:
    """Training targets of a bin dataset for a supervised variant (``make_instances_target`` of each frame).

    ``"geometric"`` and ``"edge"`` train in the dataset's space (``part_space.json``). ``"mask"`` trains in a
    space built from the same fields with the last dimension left to the mask channel
    (:func:`~don_gym.descriptors.multi_part.build_part_space` with ``mask_dim=-1``), the stored targets moved
    into it. :attr:`space` is the one the network learns (its checkpoint records it), :attr:`background` its
    background (the targets' off every instance).
    """

    def __init__(self, data: DONDataset, variant: str, edge_width_px: float | None = None) -> None:
        self.data = data
        self.variant = variant
        self.stored_space = load_part_space(data)
        if variant == "mask":
            fields = load_part_fields(data)
            self.space = build_part_space(
                list(self.stored_space.names),
                [fields[n].vertex_descriptors for n in self.stored_space.names],
                [p.signature for p in self.stored_space.parts],
                gap=self.stored_space.gap,
                mask_dim=-1,
            )
        else:
            self.space = self.stored_space
        self.background = np.asarray(self.space.background, dtype=np.float32)
        width = data.scenes[0].intrinsics.width
        self.edge_width_px = default_edge_width_px(width) if edge_width_px is None else float(edge_width_px)

    def frame(self, scene: int, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(target (H, W, D) float32, object_mask (H, W) bool)`` of one frame."""
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
