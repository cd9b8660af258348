"""Recorder of static bin scenes (:class:`BinSceneRecorder`): a settled pile of part instances in the bin of
:class:`~don_gym.sim.bin_task.BinPickTask`, seen by the wrist camera from the views of
:class:`~don_gym.sim.recorder.SceneRecorder`, with the visible instance per pixel from the segmentation.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics
from don_gym.objects import ObjectModel
from don_gym.sim.backdrop import Backdrop
from don_gym.sim.bin_task import BIN_CENTER_XY_M, BIN_INNER_SIZE_M, BIN_WALL_HEIGHT_M, BinPickTask
from don_gym.sim.bullet import Bullet
from don_gym.sim.camera import decode_segmentation
from don_gym.sim.distractors import Distractors
from don_gym.sim.env import SOLVER_ITERATIONS, TIME_STEP_S
from don_gym.sim.recorder import SceneRecorder
from don_gym.sim.robot import ARM_HOME_RAD, Panda
from don_gym.sim.task import TABLE_TOP_Z_M

#: The camera looks at points around this height (m) above the bin's floor centre: about a pile's middle.
LOOK_AT_HEIGHT_M = 0.02


@dataclass
class BinFrame:
    """One wrist-camera frame of a pile. Images are (H, W[, 3]); poses (4, 4), metres.

    ``instance_ids``: (H, W) int32, the visible instance per pixel (its id in :attr:`BinScene.instances`,
    >= 1), 0 where no instance is seen."""

    rgb: np.ndarray
    depth_m: np.ndarray
    depth_ideal_m: np.ndarray
    instance_ids: np.ndarray
    T_world_camera: np.ndarray
    T_world_camera_reported: np.ndarray


@dataclass
class BinScene:
    """A recorded pile: ``instances`` is a list of ``{"instance_id" (>= 1), "part", "T_world_object"}`` of
    the instances in the bin (a part that bounced out of it is not in the scene)."""

    intrinsics: CameraIntrinsics
    instances: list[dict[str, Any]]
    table_height_m: float
    frames: list[BinFrame] = field(default_factory=list)
    background: dict[str, Any] = field(default_factory=dict)


class BinSceneRecorder(SceneRecorder):
    """Records static scenes of a pile; owns one PyBullet client.

    Per scene every instance is dropped into the bin from the scene's seed
    (:meth:`~don_gym.sim.bin_task.BinPickTask.drop_pile`, with the bin env's physics settings) and the pile
    settles; then the wrist camera moves through the views of :class:`SceneRecorder` around a point
    :data:`LOOK_AT_HEIGHT_M` above the bin's centre, no physics step running meanwhile, so nothing moves.
    Backdrops, lighting, depth sensor and hand-eye calibration error as there; no distractors (the pile is
    the clutter). Instance ids in the scene are the task's instance index plus 1 (0 = no instance).

    Args:
        models: part name -> model, in the order of the dataset's parts.
        counts: part name -> instances (checked by the caller, e.g. the bin env's part checks).
        image_size, sensor, renderer, backgrounds, lighting: as for :class:`SceneRecorder`.
    """

    def __init__(
        self,
        models: Mapping[str, ObjectModel],
        counts: Mapping[str, int],
        image_size: tuple[int, int] = (320, 240),
        sensor: str = "d435",
        renderer: str = "tiny",
        backgrounds: str = "classic",
        lighting: str = "fixed",
    ) -> None:
        present = [name for name in models if counts.get(name, 0) > 0]
        if not present:
            raise DonGymError(f"parts={dict(counts)!r}: expected at least one instance in the bin")
        self.models = dict(models)
        self.model = self.models[present[0]]
        self._set_camera_options(image_size, sensor, backgrounds, lighting)
        self.sim = Bullet(time_step_s=TIME_STEP_S, solver_iterations=SOLVER_ITERATIONS, renderer=renderer)
        self.robot = Panda(self.sim)
        self.task = BinPickTask(self.sim, self.models, counts, present[0])
        self.backdrop = Backdrop(self.sim, cradle_id=self.task.cradle_id)
        self.distractors = Distractors(self.sim, 0)
        self._instance_of_body = np.zeros(self.sim.client.getNumBodies() + 1, dtype=np.int32)
        for instance in self.task.instances:
            self._instance_of_body[instance.body.body_id] = instance.instance_id + 1
        self._specular = {i.body.body_id: i.model.material.specular for i in self.task.instances}
        self.sim.take_snapshot()

    def _obstacle_ids(self) -> tuple[int, ...]:
        bodies = [instance.body.body_id for instance in self.task.in_play()]
        return (self.task.table_id, self.task.cradle_id, self.task.bin_id, *bodies)

    def instance_image(self, segmentation: np.ndarray) -> np.ndarray:
        """(H, W) int32 instance ids (index + 1) of a PyBullet segmentation, 0 off every instance."""
        body = decode_segmentation(segmentation)[0]
        known = (body >= 0) & (body < len(self._instance_of_body))
        return np.where(known, self._instance_of_body[np.clip(body, 0, len(self._instance_of_body) - 1)], 0).astype(
            np.int32
        )

    def record(  # type: ignore[override]
        self, seed: int, num_frames: int, max_tries_per_frame: int = 20, renderer: str | None = None
    ) -> BinScene:
        """Record one pile; the same seed gives the same scene, pixel for pixel; ``renderer`` as for
        :meth:`SceneRecorder.record`."""
        rng, background = self._start_scene(seed, num_frames, renderer)
        self.task.drop_pile(rng)
        _, lighting = self._vary_scene(seed, background)
        instances = [
            {"instance_id": i.instance_id + 1, "part": i.part, "T_world_object": i.body.T_world_object}
            for i in self.task.in_play()
        ]
        scene = BinScene(self.intrinsics, instances, TABLE_TOP_Z_M, background=background)
        look_at = np.array([*BIN_CENTER_XY_M, TABLE_TOP_Z_M + LOOK_AT_HEIGHT_M])
        views = self._views(rng, look_at, num_frames, max_tries_per_frame, lighting, self._specular, "the bin")
        for segmentation, frame in views:
            scene.frames.append(BinFrame(instance_ids=self.instance_image(segmentation), **frame))
        self.robot.reset(ARM_HOME_RAD)
        return scene


def bin_region_world(margin_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(T_world_box, half_extents_m)``: the inside of the bin from its floor to the walls' rim plus 3 cm,
    shrunk by ``margin_m`` sideways (a region for :func:`~don_gym.data.fusion.object_mask_from_depth`)."""
    height = BIN_WALL_HEIGHT_M + 0.03
    T = np.eye(4)
    T[:3, 3] = [BIN_CENTER_XY_M[0], BIN_CENTER_XY_M[1], TABLE_TOP_Z_M + height / 2]
    half = np.array([BIN_INNER_SIZE_M[0] / 2 - margin_m, BIN_INNER_SIZE_M[1] / 2 - margin_m, height / 2])
    return T, half
