"""Dataset builder: record scenes in simulation and write the targets of both methods.

One scene = the object at one pose on the table, seen by the wrist camera from
``frames_per_scene`` quasi-random poses (:mod:`don_gym.sim.recorder`). For each scene the
builder writes, per frame, RGB, sensor and ideal depth, the simulator's object mask, the
supervised descriptor target rendered from the *reported* camera pose (as a real user
would have it) and, for the self-supervised method, the sensor depth fused over the
scene (TSDF) and re-rendered per frame with object masks from the fused model.

Work is split by scene: ``shard=(i, n)`` takes scenes ``i, i+n, i+2n, ...`` (for a job
array), ``workers`` processes each own one PyBullet client, finished scenes are skipped
(resumable) and every file is written atomically (see :mod:`don_gym.dataset`).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym import __version__
from don_gym.dataset import (
    DATASET_FILE,
    FIELD_FILE,
    FORMAT_NAME,
    FORMAT_VERSION,
    SCENE_FILE,
    check_dataset_identity,
    read_json,
    scene_dir,
    write_frame,
    write_json,
)
from don_gym.descriptors import DescriptorField, embed
from don_gym.errors import DatasetError
from don_gym.fusion import fuse_scene, fused_object_masks
from don_gym.geometry import invert_transform
from don_gym.objects import ObjectModel, load_object
from don_gym.render import DescriptorRenderer

#: Margin (m) of the TSDF volume around the object's bounding sphere.
FUSION_MARGIN_M = 0.02


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

    def validate(self) -> None:
        if self.scenes < 1 or self.frames_per_scene < 2:
            raise DatasetError(
                f"need at least 1 scene and 2 frames per scene, got {self.scenes} x {self.frames_per_scene}"
            )
        width, height = self.image_size
        if not (16 <= width <= 1280 and 16 <= height <= 960):
            raise DatasetError(f"image size {width}x{height} is out of range; expected 16x16 to 1280x960")


@dataclass(frozen=True)
class BuildReport:
    scenes_written: int
    scenes_skipped: int
    frames_written: int
    seconds: float

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


def _dataset_info(config: DatasetConfig, model: ObjectModel, field: DescriptorField) -> dict[str, Any]:
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "don_gym_version": __version__,
        **asdict(config),
        "object_source": model.source,
        "mesh_hash": model.mesh_hash,
        "descriptor_field_hash": field.field_hash,
        "background_descriptor": field.background,
    }


def prepare_dataset_dir(out_dir: Path, config: DatasetConfig, overwrite: bool) -> tuple[ObjectModel, DescriptorField]:
    """Create or validate ``out_dir``; returns the object and its descriptor field.

    Refuses a directory holding a different dataset (or anything else that is not
    empty) unless ``overwrite``, which deletes it first.
    """
    config.validate()
    model = load_object(config.object, scale=config.object_scale)
    info_path = out_dir / DATASET_FILE
    if out_dir.exists() and overwrite:
        shutil.rmtree(out_dir)
    field_path = out_dir / FIELD_FILE
    if info_path.is_file():
        existing = read_json(info_path)
        field = (
            DescriptorField.load(field_path)
            if field_path.is_file()
            else embed(model, dim=config.descriptor_dim, symmetric=config.symmetric)
        )
        check_dataset_identity(existing, _dataset_info(config, model, field), out_dir)
    else:
        if out_dir.exists() and any(out_dir.iterdir()):
            raise DatasetError(f"{out_dir}: exists and is not a don_gym dataset; use an empty directory or --overwrite")
        field = embed(model, dim=config.descriptor_dim, symmetric=config.symmetric)
        out_dir.mkdir(parents=True, exist_ok=True)
    if not field_path.is_file():
        field.save(field_path)
    write_json(info_path, _dataset_info(config, model, field))
    return model, field


def scene_seed(seed: int, scene_index: int) -> int:
    """Independent, reproducible seed of one scene, whatever the shard or worker."""
    return int(np.random.SeedSequence([seed, scene_index]).generate_state(1)[0])


class SceneWriter:
    """Records and writes scenes; one per worker process (owns one PyBullet client)."""

    def __init__(self, config: DatasetConfig, out_dir: Path, field: DescriptorField) -> None:
        from don_gym.sim.recorder import SceneRecorder

        self.config = config
        self.out_dir = out_dir
        self.model = load_object(config.object, scale=config.object_scale)
        self.field = field
        self.recorder = SceneRecorder(self.model, config.image_size, sensor=config.sensor, renderer=config.renderer)
        self.renderer = DescriptorRenderer(self.model.mesh, field.vertex_descriptors, field.background)

    def write_scene(self, scene_index: int) -> int:
        config = self.config
        path = scene_dir(self.out_dir, scene_index)
        seed = scene_seed(config.seed, scene_index)
        scene = self.recorder.record(seed=seed, num_frames=config.frames_per_scene)
        intrinsics = scene.intrinsics
        for f, frame in enumerate(scene.frames):
            T_camera_object = invert_transform(frame.T_world_camera_reported) @ scene.T_world_object
            target = self.renderer.render(intrinsics, T_camera_object, visible_mask=frame.object_mask)
            write_frame(
                path,
                f,
                {
                    "rgb": frame.rgb,
                    "depth": frame.depth_m,
                    "depth_ideal": frame.depth_ideal_m,
                    "mask": frame.object_mask,
                    "target_mask": target.object_mask,
                    "descriptor": target.descriptor_image,
                },
                config.descriptor_dim,
            )
        if config.fuse_depth:
            self._write_fused(path, scene)
        write_json(
            path / SCENE_FILE,
            {
                "scene_index": scene_index,
                "seed": seed,
                "object": self.model.name,
                "intrinsics": intrinsics.as_array(),
                "T_world_object": scene.T_world_object,
                "T_world_camera": np.stack([fr.T_world_camera for fr in scene.frames]),
                "T_world_camera_reported": np.stack([fr.T_world_camera_reported for fr in scene.frames]),
                "table_height_m": scene.table_height_m,
                "background": scene.background,
                "fused_depth": config.fuse_depth,
            },
        )
        return len(scene.frames)

    def _write_fused(self, path: Path, scene) -> None:
        """TSDF-fuse the sensor depth around the object, re-render depth and masks per frame."""
        reported = [fr.T_world_camera_reported for fr in scene.frames]
        # A volume just around the object: the fused depth is only needed there (matches are
        # sampled on the object), and a small volume keeps fusion cheap.
        half = 0.5 * float(np.linalg.norm(self.model.extents_m)) + FUSION_MARGIN_M
        centre = scene.T_world_object[:3, 3]
        bounds_min = np.array([centre[0] - half, centre[1] - half, scene.table_height_m - 0.01])
        bounds_max = np.array([centre[0] + half, centre[1] + half, scene.table_height_m + 2 * half])
        volume = fuse_scene(
            [fr.depth_m for fr in scene.frames],
            scene.intrinsics,
            reported,
            (bounds_min, bounds_max),
            voxel_size_m=self.config.voxel_size_m,
        )
        object_radius = 0.5 * float(np.linalg.norm(self.model.extents_m)) + 0.005
        depths, masks = fused_object_masks(
            volume,
            scene.intrinsics,
            reported,
            object_center_world=centre,
            object_radius_m=object_radius,
            table_height_m=scene.table_height_m,
        )
        for f, (depth, mask) in enumerate(zip(depths, masks, strict=True)):
            write_frame(path, f, {"depth_fused": depth, "mask_fused": mask}, self.config.descriptor_dim)

    def close(self) -> None:
        self.recorder.close()


_WORKER: SceneWriter | None = None
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


def _worker_init(config: DatasetConfig, out_dir: str, field_path: str) -> None:
    global _WORKER  # one writer per worker process, created once
    _WORKER = SceneWriter(config, Path(out_dir), DescriptorField.load(field_path))


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
    """Build (or resume) a dataset; see the module docstring. Returns counts and timing."""
    out_dir = Path(out_dir)
    start = time.perf_counter()
    _, field = prepare_dataset_dir(out_dir, config, overwrite)
    shard_index, shard_count = shard
    todo, skipped = [], 0
    for i in range(shard_index, config.scenes, shard_count):
        if (scene_dir(out_dir, i) / SCENE_FILE).is_file():
            skipped += 1
        else:
            todo.append(i)
    frames = 0
    bar = tqdm(total=len(todo) * config.frames_per_scene, unit="frame", desc="build-dataset", disable=not progress)
    try:
        if workers <= 1 or len(todo) <= 1:
            writer = SceneWriter(config, out_dir, field)
            try:
                for i in todo:
                    n = writer.write_scene(i)
                    frames += n
                    bar.update(n)
            finally:
                writer.close()
        else:
            context = mp.get_context("spawn")
            # One BLAS/OpenMP thread per worker: the workers already fill the cores, and
            # oversubscription makes a 2-worker build slower than a 1-worker one.
            with (
                single_threaded_children(),
                context.Pool(
                    min(workers, len(todo)),
                    initializer=_worker_init,
                    initargs=(config, str(out_dir), str(out_dir / FIELD_FILE)),
                ) as pool,
            ):
                for n in pool.imap_unordered(_worker_write, todo):
                    frames += n
                    bar.update(n)
                # A clean shutdown: the with-block alone terminates the workers, which leaves the
                # pool's semaphores to the resource tracker's "leaked semaphore" warning.
                pool.close()
                pool.join()
    finally:
        bar.close()
    return BuildReport(len(todo), skipped, frames, time.perf_counter() - start)
