"""Dataset builder: record scenes in simulation and write the targets of both methods.

:func:`build_dataset` records scenes of one object (:mod:`don_gym.sim.recorder`) and writes them in the
format of :mod:`don_gym.data.dataset`, resumably, split over worker processes or shards.
"""

from __future__ import annotations

import contextlib
import functools
import math
import multiprocessing as mp
import os
import shutil
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from tqdm.auto import tqdm

from don_gym import __version__
from don_gym.data.dataset import (
    DATASET_FILE,
    FIELD_FILE,
    FORMAT_NAME,
    FORMAT_VERSION,
    SCENE_FILE,
    DatasetLock,
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
from don_gym.data.fusion import fuse_scene, fused_object_masks
from don_gym.data.render import DescriptorRenderer
from don_gym.descriptors import FIELD_MATCH_ATOL, DescriptorField, embed
from don_gym.errors import DatasetError, DonGymError, SeveralPiecesError
from don_gym.geometry import invert_transform
from don_gym.io import LOCK_FILE
from don_gym.objects import ObjectModel, load_object
from don_gym.processes import end_with_parent

__all__ = [
    "FUSION_MARGIN_M",
    "BaseSceneWriter",
    "BuildReport",
    "DATASET_RENDERERS",
    "DatasetConfig",
    "MIXED_RENDERER",
    "SceneWriter",
    "build_dataset",
    "check_not_foreign",
    "check_run_options",
    "dataset_info",
    "embed_part",
    "join_dataset_dir",
    "parse_shard",
    "part_info",
    "prepare_dataset_dir",
    "recorder_renderer",
    "scene_renderer",
    "scene_seed",
    "single_threaded_children",
    "write_scenes",
]

#: Margin (m) of the TSDF volume around the object's bounding sphere.
FUSION_MARGIN_M = 0.02
#: A dataset of both looks: its odd-numbered scenes path-traced (``"pbr"``), the others TinyRenderer's, so that a
#: network trained on it meets the flat appearance and the physical one in equal shares (docs/background.md,
#: "Training data").
MIXED_RENDERER = "mixed"
#: What ``DatasetConfig.renderer`` accepts: a camera renderer (:data:`~don_gym.sim.camera.RENDERERS`) or
#: :data:`MIXED_RENDERER`.
DATASET_RENDERERS = ("tiny", "egl", "pbr", MIXED_RENDERER)


def scene_renderer(renderer: str, scene_index: int) -> str:
    """The renderer of scene ``scene_index``'s RGB in a dataset built with ``renderer`` (a camera renderer itself,
    or for :data:`MIXED_RENDERER` ``"pbr"`` on odd indices and ``"tiny"`` on even ones)."""
    if renderer != MIXED_RENDERER:
        return renderer
    return "pbr" if scene_index % 2 else "tiny"


def recorder_renderer(renderer: str) -> str:
    """The renderer a dataset built with ``renderer`` opens its simulator with (a ``"pbr"`` one draws both looks)."""
    return "pbr" if renderer == MIXED_RENDERER else renderer


@dataclass(frozen=True)
class DatasetConfig:
    """Everything that defines a dataset's content (stored in ``dataset.json``).

    ``image_size`` is (width, height) in pixels; ``voxel_size_m`` the TSDF voxel edge.
    """

    object: str = "toolcap"
    object_scale: float | None = None
    scenes: int = 4
    frames_per_scene: int = 24
    image_size: tuple[int, int] = (320, 240)
    sensor: str = "d435"
    renderer: str = "tiny"
    seed: int = 0
    descriptor_dim: int = 3
    symmetric: bool = True
    fuse_depth: bool = True
    voxel_size_m: float = 0.002
    backgrounds: str = "classic"
    distractors: int = 0
    lighting: str = "fixed"

    def validate(self) -> None:
        """DatasetError naming the first unusable setting: all that needs neither the mesh, the disk nor
        PyBullet (``renderer``: :func:`prepare_dataset_dir`)."""
        from don_gym.sim.sensor import get_sensor

        if not isinstance(self.object, str) or not self.object:
            raise DatasetError(f"object={self.object!r} (--object): expected a built-in name or a mesh file")
        _check_int("scenes", self.scenes, "--scenes", minimum=1)
        _check_int("frames_per_scene", self.frames_per_scene, "--frames", minimum=2)
        _check_int("seed", self.seed, "--seed", minimum=0)
        _check_int("descriptor_dim", self.descriptor_dim, "--dim", minimum=1)
        size = self.image_size
        if not (isinstance(size, (tuple, list)) and len(size) == 2 and all(_is_int(v) for v in size)):
            raise DatasetError(f"image_size={size!r} (--size): expected (width, height) in pixels")
        width, height = size
        if not (16 <= width <= 1280 and 16 <= height <= 960):
            raise DatasetError(f"image size {width}x{height} (--size) is out of range; expected 16x16 to 1280x960")
        if not isinstance(self.sensor, str):
            raise DatasetError(f"sensor={self.sensor!r} (--sensor): expected a preset name")
        get_sensor(self.sensor)
        for name, value in (("symmetric", self.symmetric), ("fuse_depth", self.fuse_depth)):
            if not isinstance(value, bool):
                raise DatasetError(f"{name}={value!r}: expected True or False")
        if not (_is_number(self.voxel_size_m) and 0 < self.voxel_size_m < 0.1):
            raise DatasetError(f"voxel_size_m={self.voxel_size_m!r}: expected a voxel edge in metres, in (0, 0.1)")
        from don_gym.sim.backdrop import BACKDROP_SETS
        from don_gym.sim.camera import LIGHTING_MODES

        if self.backgrounds not in BACKDROP_SETS:
            raise DatasetError(
                f"backgrounds={self.backgrounds!r} (--backgrounds): expected one of {list(BACKDROP_SETS)}"
            )
        _check_int("distractors", self.distractors, "--distractors", minimum=0)
        if self.lighting not in LIGHTING_MODES:
            raise DatasetError(f"lighting={self.lighting!r} (--lighting): expected one of {list(LIGHTING_MODES)}")
        if self.renderer not in DATASET_RENDERERS:
            raise DatasetError(f"renderer={self.renderer!r} (--renderer): expected one of {list(DATASET_RENDERERS)}")
        scale = self.object_scale
        if scale is not None and not (_is_number(scale) and scale > 0):
            raise DatasetError(f"object_scale={scale!r} (--object-scale): expected a positive, finite factor")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return (
        isinstance(value, (int, float, np.integer, np.floating))
        and not isinstance(value, bool)
        and math.isfinite(value)
    )


def _check_int(name: str, value: Any, option: str, minimum: int) -> None:
    if not _is_int(value) or value < minimum:
        raise DatasetError(f"{name}={value!r} ({option}): expected an integer >= {minimum}")


@dataclass(frozen=True)
class BuildReport:
    """What one call wrote (``scenes_skipped``: already complete, or finished first by another writer)
    and, after it, how many of the dataset's ``scenes_total`` scenes are complete (all shards)."""

    scenes_written: int
    scenes_skipped: int
    frames_written: int
    seconds: float
    scenes_complete: int = 0
    scenes_total: int = 0

    @property
    def frames_per_second(self) -> float:
        return self.frames_written / self.seconds if self.seconds > 0 else 0.0


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> (i, n) with 0 <= i < n."""
    try:
        index, count = (int(v) for v in text.split("/"))
    except ValueError:
        raise DatasetError(f"--shard {text!r}: expected i/n with integers, e.g. 0/4") from None
    if not (count >= 1 and 0 <= index < count):
        raise DatasetError(f"--shard {text!r}: expected 0 <= i < n")
    return index, count


def check_run_options(workers: Any, shard: Any) -> tuple[int, int]:
    """Check ``workers`` (at least one) and ``shard`` (``(i, n)`` with ``0 <= i < n``); returns ``(i, n)``.
    A :class:`DatasetError` names ``--workers`` or ``--shard`` otherwise."""
    if not _is_int(workers) or workers < 1:
        raise DatasetError(f"workers={workers!r} (--workers): expected an integer >= 1")
    if not (isinstance(shard, (tuple, list)) and len(shard) == 2 and all(_is_int(v) for v in shard)):
        raise DatasetError(f"shard={shard!r} (--shard): expected (i, n) with 0 <= i < n")
    index, count = (int(v) for v in shard)
    if not (count >= 1 and 0 <= index < count):
        raise DatasetError(f"shard={shard!r} (--shard): expected (i, n) with 0 <= i < n")
    return index, count


def part_info(model: ObjectModel, scale: float | None) -> dict[str, Any]:
    """A part's entry in ``dataset.json``'s ``parts``."""
    return {
        "name": model.name,
        "object_source": model.source,
        "object_scale": scale,
        "object_signature": model.shape_signature.to_dict(),
        "mesh_hash": model.mesh_hash,
    }


def dataset_info(
    config: DatasetConfig,
    model: ObjectModel,
    field: DescriptorField,
    scene_kind: str = "single",
    parts: list[dict[str, Any]] | None = None,
    background: Any = None,
) -> dict[str, Any]:
    """``dataset.json`` of a dataset whose (primary) part is ``model`` with descriptor field ``field``; a bin
    dataset gives its ``parts`` and the ``background`` descriptor of its space."""
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "don_gym_version": __version__,
        **asdict(config),
        "object_name": model.name,
        "object_signature": model.shape_signature.to_dict(),
        "object_source": model.source,
        "mesh_hash": model.mesh_hash,
        "descriptor_field_hash": field.field_hash,
        "background_descriptor": field.background if background is None else background,
        "scene_kind": scene_kind,
        "parts": [part_info(model, config.object_scale)] if parts is None else parts,
    }


def check_not_foreign(out_dir: Path, also_ours: tuple[str, ...] = ()) -> None:
    """Refuse a directory holding anything but the start of a dataset (a crashed or concurrent build's
    descriptor field, lock file or temporary files, and names starting with ``also_ours``): building would
    mix our files with someone's."""
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a directory; expected a dataset directory")
    if not out_dir.is_dir():
        return
    # Another build's files while it starts, its temporary names included; builds of older don_gym versions
    # stacked a second temporary name on the first ("..descriptor_field.npz.partial-a.npz.partial-b").
    ours = (LOCK_FILE, FIELD_FILE, f"{FIELD_FILE}.partial-", f"{DATASET_FILE}.partial-", *also_ours)
    foreign = sorted(
        p.name for p in out_dir.iterdir() if not (p.name.startswith(ours) or p.name.lstrip(".").startswith(ours))
    )
    if foreign:
        raise DatasetError(
            f"{out_dir}: exists and is not a don_gym dataset (holds {foreign[0]!r}); "
            "use an empty directory or --overwrite"
        )


def _recorded_scenes(recorded: dict[str, Any], out_dir: Path) -> int:
    scenes = recorded.get("scenes")
    if not _is_int(scenes) or scenes < 1:
        raise DatasetError(f"{out_dir / DATASET_FILE}: scenes {scenes!r} is not an integer >= 1; the file is corrupt")
    return int(scenes)


def _resolve_dataset(
    out_dir: Path, config: DatasetConfig, model: ObjectModel, computed: DescriptorField, write: bool
) -> DescriptorField:
    """Check ``out_dir``'s dataset-level files against ``config``, the part ``model`` and ``computed`` (its
    descriptor field computed here), and return the field to render targets with (the recorded one when
    there is one); with ``write``, publish what is missing.

    The one place where a build decides whether it may write into ``out_dir``: called read-only to
    validate before anything is written, then again holding the metadata lock. Files are published
    with an exclusive create, so writers on several machines that race agree on one ``dataset.json``
    and one ``descriptor_field.npz``; a writer whose options differ from them is refused. The part and
    the field are compared by value within tolerances (:func:`~don_gym.data.dataset.check_dataset_identity`):
    machines whose arithmetic differs in the last bits build the same dataset.
    """
    info_path, field_path = out_dir / DATASET_FILE, out_dir / FIELD_FILE
    for _ in range(3):  # another writer may publish a file between our look and our write
        recorded = check_dataset_info(read_json(info_path), info_path) if info_path.is_file() else None
        if recorded is None:
            check_not_foreign(out_dir)
        field = _load_field(field_path) if field_path.is_file() else None
        if field is not None and recorded is None:
            _check_field_fits(field, computed, config, out_dir)
        wanted = dataset_info(config, model, field if field is not None else computed)
        if recorded is not None:
            _check_single_kind(recorded, out_dir)
            check_dataset_identity(recorded, wanted, out_dir, field, computed)
            _check_recorded_field(field, recorded, computed, out_dir)
            scenes = _recorded_scenes(recorded, out_dir)
            if config.scenes < scenes:
                raise DatasetError(
                    f"{out_dir}: records {scenes} scenes and scenes={config.scenes} (--scenes) asks for fewer; "
                    f"scenes are never removed: pass --scenes {scenes} (or more, to add scenes), --overwrite "
                    "to start again, or use another directory"
                )
        if not write:
            return field if field is not None else computed
        try:
            if field is None:
                computed.save(field_path, exclusive=True)
                field = computed
            if recorded is None:
                write_json(info_path, wanted, exclusive=True)
            elif config.scenes > _recorded_scenes(recorded, out_dir):
                write_json(info_path, {**recorded, "scenes": config.scenes})
        except FileExistsError:
            continue
        return field
    raise DatasetError(f"{out_dir}: its dataset.json keeps changing while this build starts; try again")


def _check_single_kind(recorded: dict[str, Any], out_dir: Path) -> None:
    """A one-part build never adds scenes to a dataset of another kind (a bin's piles, a BOP import): their scenes
    hold what its scenes lack (``instance/`` images) and their targets lie in another descriptor space."""
    kind = recorded.get("scene_kind", "single")
    if kind != "single":
        raise DatasetError(
            f"{out_dir}: holds a dataset of scene kind {kind!r}, not one part per scene (--scene single); pass "
            "--overwrite to replace it or use another directory"
        )


def embed_part(model: ObjectModel, config: DatasetConfig, what: str | None = None) -> DescriptorField:
    """The part's descriptor field as computed here (a new dataset's, or what a recorded one must match);
    ``what`` names the part's input in a refusal (default: ``config.object``, --object)."""
    try:
        return embed(model, dim=config.descriptor_dim, symmetric=config.symmetric)
    except SeveralPiecesError as exc:
        what = f"object {config.object!r} (--object)" if what is None else what
        raise DatasetError(
            f"{what}: {exc.detail}; a dataset needs a part in one piece: join the "
            "pieces, or keep only the largest, in the mesh file"
        ) from exc


def _load_field(path: Path) -> DescriptorField:
    try:
        return DescriptorField.load(path)
    except DonGymError as exc:
        raise DatasetError(f"{exc}; pass --overwrite to rebuild the dataset or use another directory") from exc


def _check_recorded_field(
    field: DescriptorField | None, recorded: dict[str, Any], computed: DescriptorField, out_dir: Path
) -> None:
    """``dataset.json`` names its field file's exact content (``descriptor_field_hash``): the targets of
    its scenes were rendered from those bits. A file with other content, or none, is refused, except a
    missing file that the field computed here restores bit for bit."""
    field_path, expected = out_dir / FIELD_FILE, recorded.get("descriptor_field_hash")
    if field is None and computed.field_hash == expected:
        return
    if field is None or field.field_hash != expected:
        found = "is missing" if field is None else f"holds the field {field.field_hash}"
        raise DatasetError(
            f"{field_path}: {found}, but {DATASET_FILE} records the field {expected} its scenes were rendered "
            "from (the file was replaced or deleted); pass --overwrite to rebuild the dataset or use another directory"
        )


def _check_field_fits(field: DescriptorField, computed: DescriptorField, config: DatasetConfig, out_dir: Path) -> None:
    """A descriptor field without ``dataset.json`` (a build that stopped between the two, or one starting
    right now, maybe on another machine): usable only if it is ``computed``, the field these options give
    for this part, within :data:`~don_gym.descriptors.FIELD_MATCH_ATOL`."""
    if (field.dim, field.symmetric) != (config.descriptor_dim, config.symmetric):
        problem = (
            f"dim {field.dim}, symmetric {field.symmetric}; asked: dim {config.descriptor_dim} (--dim), "
            f"symmetric {config.symmetric} (--no-symmetry)"
        )
    elif field.n_vertices != computed.n_vertices:
        problem = f"a mesh of {field.n_vertices} vertices; {config.object!r} (--object) has {computed.n_vertices}"
    else:
        difference = field.max_difference(computed)
        if difference <= FIELD_MATCH_ATOL:
            return
        problem = (
            f"it differs from the field of {config.object!r} (--object) by {difference:.3g}, "
            f"tolerance {FIELD_MATCH_ATOL:g}"
        )
    # Worded like check_dataset_identity's refusal: which of two racing writers loses decides which
    # of the two a user sees, and both say the same thing.
    raise DatasetError(
        f"{out_dir}: holds a different dataset (its {FIELD_FILE} is the descriptor field of another part or "
        f"options: {problem}) and no {DATASET_FILE} yet: another build is starting there or stopped early; "
        "pass --overwrite to replace it or use another directory"
    )


def _check_renderer_available(renderer: str) -> None:
    """A known renderer, and one this machine has: PyBullet falls back from EGL to TinyRenderer with
    a warning, and a dataset must not record one renderer and hold the other's pixels."""
    from don_gym.sim.bullet import Bullet
    from don_gym.sim.camera import check_renderer

    renderer = recorder_renderer(renderer)
    if check_renderer(renderer) == "tiny":
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = Bullet(renderer=renderer)
    try:
        _check_renderer_in_use(sim.renderer, renderer)
    finally:
        sim.close()


def _check_renderer_in_use(in_use: str, wanted: str) -> None:
    if in_use != wanted:
        raise DatasetError(
            f"renderer={wanted!r} (--renderer) is unavailable on this machine (PyBullet would use {in_use!r}); "
            "build where it is available (egl: an EGL driver) or pass --renderer tiny"
        )


def _clear_dir(out_dir: Path) -> None:
    """Everything but the lock file, which other writers must keep finding at the same inode."""
    for path in out_dir.iterdir():
        if path.name == LOCK_FILE:
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def prepare_dataset_dir(
    out_dir: Path, config: DatasetConfig, overwrite: bool
) -> tuple[ObjectModel, DescriptorField, DatasetLock]:
    """Validate everything, then create, replace (``overwrite``) or join the dataset in ``out_dir``.

    Nothing is written before all options, the object and (if there is one) the recorded dataset
    have been checked: a refused build leaves ``out_dir`` as it was. Returns the object, its
    descriptor field and the lock, held shared (the caller closes it when done).
    """
    config.validate()
    model = load_object(config.object, scale=config.object_scale)
    if overwrite and out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a directory; expected a dataset directory")
    computed = embed_part(model, config)
    field, lock = join_dataset_dir(
        out_dir, config, overwrite, lambda write: _resolve_dataset(out_dir, config, model, computed, write)
    )
    return model, field, lock


_Resolved = TypeVar("_Resolved")


def join_dataset_dir(
    out_dir: Path,
    config: DatasetConfig,
    overwrite: bool,
    resolve: Callable[[bool], _Resolved],
    also_ours: tuple[str, ...] = (),
) -> tuple[_Resolved, DatasetLock]:
    """Create, replace (``overwrite``) or join the dataset in ``out_dir``, checked first: returns what
    ``resolve(write=True)`` returns under the metadata lock, and the lock, held shared (the caller closes it).

    ``resolve(write)`` checks ``out_dir``'s dataset-level files against the options (read-only first, so that a
    refused build writes nothing) and, with ``write``, publishes what is missing.
    """
    if not overwrite:
        resolve(False)
    else:
        _check_replaceable(out_dir, also_ours)
    _check_renderer_available(config.renderer)

    out_dir.mkdir(parents=True, exist_ok=True)
    lock = DatasetLock(out_dir)
    try:
        lock.hold_session(exclusive=overwrite)
        if overwrite:
            _clear_dir(out_dir)
            lock.share_session()
        with lock.metadata():
            resolved = resolve(True)
    except BaseException:
        lock.close()
        raise
    return resolved, lock


def _check_replaceable(out_dir: Path, also_ours: tuple[str, ...]) -> None:
    """``--overwrite`` replaces a dataset (or the start of one, ``also_ours`` as for :func:`check_not_foreign`),
    never a directory of someone's other files."""
    if not out_dir.is_dir() or (out_dir / DATASET_FILE).is_file():
        return
    try:
        check_not_foreign(out_dir, also_ours)
    except DatasetError:
        foreign = sorted(p.name for p in out_dir.iterdir())
        raise DatasetError(
            f"{out_dir}: is not a don_gym dataset (holds {foreign[0]!r}, no {DATASET_FILE}); --overwrite replaces a "
            "dataset, never other files: use an empty directory or a new one"
        ) from None


def scene_seed(seed: int, scene_index: int) -> int:
    """Independent, reproducible seed of one scene, whatever the shard or worker."""
    return int(np.random.SeedSequence([seed, scene_index]).generate_state(1)[0])


class BaseSceneWriter:
    """What writing a scene of any kind takes; one per worker process (owns one PyBullet client).

    :meth:`write_scene` records a scene into a temporary directory and publishes it whole. A scene is
    ``frames_per_scene`` wrist-camera frames: per frame RGB, sensor and ideal depth and the kind's targets
    (:meth:`_frame_targets`), rendered from the *reported* camera pose (as a real user would have it); with
    ``fuse_depth``, for the self-supervised method, the sensor depth fused over the scene (TSDF) and re-rendered
    per frame with masks from the fused model (in :meth:`_fusion_region`); ``scene.json`` with every instance's
    part and pose. A kind sets :attr:`recorder` (:meth:`_open_recorder`) and :attr:`part_names` (the primary part
    first).
    """

    recorder: Any
    part_names: list[str]

    def __init__(self, config: DatasetConfig, out_dir: Path, lock: DatasetLock) -> None:
        self.config = config
        self.out_dir = out_dir
        self.lock = lock

    def _recorder_options(self) -> dict[str, Any]:
        """The recorder options every kind takes from the config."""
        config = self.config
        return {
            "image_size": config.image_size,
            "sensor": config.sensor,
            "renderer": recorder_renderer(config.renderer),
            "backgrounds": config.backgrounds,
            "lighting": config.lighting,
        }

    def _open_recorder(self, make_recorder: Callable[[], Any]) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an EGL fallback is refused just below
            self.recorder = make_recorder()
        try:
            _check_renderer_in_use(self.recorder.renderer, recorder_renderer(self.config.renderer))
        except DatasetError:
            self.recorder.close()
            raise

    def write_scene(self, scene_index: int) -> int:
        """Record scene ``scene_index`` into a temporary directory and rename it into place; returns the
        frames written, 0 if the scene was complete already or another writer completed it first."""
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

    def _instances(self, scene: Any) -> list[dict[str, Any]]:
        """``{"instance_id", "part", "T_world_object"}`` of every instance in the recorded ``scene``."""
        raise NotImplementedError

    def _frame_targets(self, scene: Any, instances: list[dict[str, Any]], frame: Any) -> dict[str, np.ndarray]:
        """The images of one frame besides RGB and depth (``mask``, ``target_mask``, ``descriptor``...)."""
        raise NotImplementedError

    def _fusion_region(self, scene: Any) -> tuple[tuple[np.ndarray, np.ndarray], dict[str, Any]]:
        """The TSDF volume's bounds (world, metres) and what :func:`~don_gym.data.fusion.fused_object_masks` keeps
        (its region arguments)."""
        raise NotImplementedError

    def _record(self, path: Path, scene_index: int) -> int:
        config = self.config
        seed = scene_seed(config.seed, scene_index)
        renderer = scene_renderer(config.renderer, scene_index)
        scene = self.recorder.record(seed=seed, num_frames=config.frames_per_scene, renderer=renderer)
        instances = self._instances(scene)
        for f, frame in enumerate(scene.frames):
            write_frame(
                path,
                f,
                {
                    "rgb": frame.rgb,
                    "depth": frame.depth_m,
                    "depth_ideal": frame.depth_ideal_m,
                    **self._frame_targets(scene, instances, frame),
                },
                config.descriptor_dim,
            )
        if config.fuse_depth:
            self._write_fused(path, scene)
        primary = self.part_names[0]
        first = next((i for i in instances if i["part"] == primary), instances[0] if instances else None)
        write_json(
            path / SCENE_FILE,
            {
                "scene_index": scene_index,
                "seed": seed,
                "renderer": renderer,
                "object": primary,
                "intrinsics": scene.intrinsics.as_array(),
                # For readers of one object: the first instance of the primary part.
                "T_world_object": first["T_world_object"] if first is not None else np.eye(4),
                "instances": instances,
                # The truth (true camera poses), for pose evaluation and export; targets use the reported ones.
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

    def _write_fused(self, path: Path, scene: Any) -> None:
        """TSDF-fuse the sensor depth in the kind's region, re-render depth and masks per frame."""
        reported = [fr.T_world_camera_reported for fr in scene.frames]
        bounds, region = self._fusion_region(scene)
        volume = fuse_scene(
            [fr.depth_m for fr in scene.frames],
            scene.intrinsics,
            reported,
            bounds,
            voxel_size_m=self.config.voxel_size_m,
        )
        depths, masks = fused_object_masks(
            volume, scene.intrinsics, reported, table_height_m=scene.table_height_m, **region
        )
        for f, (depth, mask) in enumerate(zip(depths, masks, strict=True)):
            write_frame(path, f, {"depth_fused": depth, "mask_fused": mask}, self.config.descriptor_dim)

    def close(self) -> None:
        self.recorder.close()


class SceneWriter(BaseSceneWriter):
    """Records and writes scenes of one part.

    One scene = the object at one pose on the table, seen by the wrist camera from ``frames_per_scene``
    quasi-random poses. Per frame the targets are the simulator's object mask and the supervised descriptor
    target (:class:`~don_gym.data.render.DescriptorRenderer`); the fused depth is fused around the object.
    """

    def __init__(self, config: DatasetConfig, out_dir: Path, field: DescriptorField, lock: DatasetLock) -> None:
        from don_gym.sim.recorder import SceneRecorder

        super().__init__(config, out_dir, lock)
        self.model = load_object(config.object, scale=config.object_scale)
        self.part_names = [self.model.name]
        self.field = field
        self._open_recorder(
            lambda: SceneRecorder(self.model, distractors=config.distractors, **self._recorder_options())
        )
        self.renderer = DescriptorRenderer(self.model.mesh, field.vertex_descriptors, field.background)

    def _instances(self, scene: Any) -> list[dict[str, Any]]:
        return [{"instance_id": 1, "part": self.model.name, "T_world_object": scene.T_world_object}]

    def _frame_targets(self, scene: Any, instances: list[dict[str, Any]], frame: Any) -> dict[str, np.ndarray]:
        T_camera_object = invert_transform(frame.T_world_camera_reported) @ scene.T_world_object
        target = self.renderer.render(scene.intrinsics, T_camera_object, visible_mask=frame.object_mask)
        return {"mask": frame.object_mask, "target_mask": target.object_mask, "descriptor": target.descriptor_image}

    def _fusion_region(self, scene: Any) -> tuple[tuple[np.ndarray, np.ndarray], dict[str, Any]]:
        # A volume just around the object: the fused depth is only needed there (matches are
        # sampled on the object), and a small volume keeps fusion cheap.
        half = 0.5 * float(np.linalg.norm(self.model.extents_m)) + FUSION_MARGIN_M
        centre = scene.T_world_object[:3, 3]
        bounds_min = np.array([centre[0] - half, centre[1] - half, scene.table_height_m - 0.01])
        bounds_max = np.array([centre[0] + half, centre[1] + half, scene.table_height_m + 2 * half])
        object_radius = 0.5 * float(np.linalg.norm(self.model.extents_m)) + 0.005
        return (bounds_min, bounds_max), {"object_center_world": centre, "object_radius_m": object_radius}


def _open_scene_writer(config: DatasetConfig, out_dir: Path, lock: DatasetLock) -> SceneWriter:
    """A worker's writer: the descriptor field read back from the dataset."""
    return SceneWriter(config, out_dir, DescriptorField.load(out_dir / FIELD_FILE), lock)


_WORKER: BaseSceneWriter | None = None
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def single_threaded_children() -> Iterator[None]:
    """Processes spawned inside inherit one-thread settings for numerical libraries."""
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    os.environ.update({name: "1" for name in _THREAD_VARIABLES})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextlib.contextmanager
def _children_ignore_ctrl_c() -> Iterator[None]:
    """Processes started inside ignore SIGINT from their first instruction (the disposition survives exec),
    not only once their initializer runs; a Ctrl-C that reaches this process meanwhile is dropped."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _worker_init(open_writer: Callable[[Path, DatasetLock], BaseSceneWriter], out_dir: str, owner_pid: int) -> None:
    global _WORKER  # one writer per worker process, created once
    # A build killed with kill -9 takes its workers along: none lives on holding the dataset's lock.
    end_with_parent(owner_pid)
    # Ctrl-C reaches every process of the terminal's process group; the parent stops the pool, and a
    # worker that took it too would print a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    lock = DatasetLock(Path(out_dir))
    # Joins the writers, so that an --overwrite never deletes under a worker that outlives its parent.
    lock.hold_session()
    _WORKER = open_writer(Path(out_dir), lock)


def _worker_write(scene_index: int) -> int:
    assert _WORKER is not None
    return _WORKER.write_scene(scene_index)


def build_dataset(
    config: DatasetConfig,
    out_dir: str | Path,
    workers: int = 1,
    shard: tuple[int, int] = (0, 1),
    overwrite: bool = False,
    progress: bool = True,
) -> BuildReport:
    """Build (or resume) a dataset (what a scene holds: :class:`SceneWriter`). Returns counts and timing.

    Work is split by scene: ``shard=(i, n)`` takes scenes ``i, i+n, i+2n, ...`` (for a job array),
    ``workers`` processes each own one PyBullet client, finished scenes are skipped (resumable)
    and every file is written atomically. Several processes, on one machine or several sharing the
    directory, may build the same dataset at once (shards, or a final unsharded run that checks
    and completes); one with other options is refused (see :func:`prepare_dataset_dir`).
    """
    out_dir = Path(out_dir)
    start = time.perf_counter()
    shard = check_run_options(workers, shard)
    _, field, lock = prepare_dataset_dir(out_dir, config, overwrite)
    return write_scenes(
        config,
        out_dir,
        lock,
        lambda: SceneWriter(config, out_dir, field, lock),
        functools.partial(_open_scene_writer, config),
        workers=workers,
        shard=shard,
        progress=progress,
        start=start,
    )


def write_scenes(
    config: DatasetConfig,
    out_dir: Path,
    lock: DatasetLock,
    open_writer: Callable[[], BaseSceneWriter],
    open_worker_writer: Callable[[Path, DatasetLock], BaseSceneWriter],
    workers: int,
    shard: tuple[int, int],
    progress: bool,
    start: float,
    desc: str = "build-dataset",
) -> BuildReport:
    """Write the shard's unfinished scenes of the prepared dataset in ``out_dir`` (its ``lock``, held shared;
    closed here) by one writer, ``open_writer()``, or by ``workers`` processes, each with the writer
    ``open_worker_writer(out_dir, its lock)`` (picklable: a module-level function, or a partial of one, that
    reads what it needs back from the dataset). ``start``: the build's ``time.perf_counter()`` at its start."""
    shard_index, shard_count = shard
    try:
        todo, skipped = [], 0
        for i in range(shard_index, config.scenes, shard_count):
            if scene_is_complete(scene_dir(out_dir, i)):
                skipped += 1
            else:
                todo.append(i)
        written, frames = 0, 0
        bar = tqdm(total=len(todo) * config.frames_per_scene, unit="frame", desc=desc, disable=not progress)
        try:
            if workers <= 1 or len(todo) <= 1:
                results = _write_in_process(open_writer, todo)
            else:
                results = _write_in_workers(open_worker_writer, out_dir, min(workers, len(todo)), todo)
            with contextlib.closing(results):  # on an error, stop the workers before returning
                for n in results:
                    written, frames, skipped = written + (n > 0), frames + n, skipped + (n == 0)
                    bar.update(n if n > 0 else config.frames_per_scene)
        finally:
            bar.close()
    finally:
        lock.close()
    complete = sum(scene_is_complete(scene_dir(out_dir, i)) for i in range(config.scenes))
    return BuildReport(written, skipped, frames, time.perf_counter() - start, complete, config.scenes)


def _write_in_process(open_writer: Callable[[], BaseSceneWriter], todo: list[int]) -> Iterator[int]:
    if not todo:
        return
    writer = open_writer()
    try:
        for i in todo:
            yield writer.write_scene(i)
    finally:
        writer.close()


def _write_in_workers(
    open_writer: Callable[[Path, DatasetLock], BaseSceneWriter], out_dir: Path, workers: int, todo: list[int]
) -> Iterator[int]:
    pool = ProcessPoolExecutor(
        workers,
        mp_context=mp.get_context("spawn"),
        initializer=_worker_init,
        initargs=(open_writer, str(out_dir), os.getpid()),
    )
    try:
        # Spawned workers start at the first submissions. One BLAS/OpenMP thread each: the workers already
        # fill the cores, and oversubscription makes a 2-worker build slower than a 1-worker one.
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
        # Waits for the workers to exit: no process outlives the build, and no leaked-semaphore warning.
        pool.shutdown(wait=True, cancel_futures=True)
