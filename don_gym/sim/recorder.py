"""Scene recorder (:class:`SceneRecorder`): the paper's static-scene recordings with a wrist
camera, in simulation. Each scene is the object lying on the table, seen from many wrist-camera
poses, with RGB, sensor and ideal depth, object mask and camera poses per frame.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, rotation_angle_rad
from don_gym.io import write_png
from don_gym.objects import ObjectModel
from don_gym.sim.bullet import Bullet
from don_gym.sim.camera import body_mask, look_at_camera_pose, render_camera, specular_map
from don_gym.sim.robot import ARM_HOME_RAD, ARM_JOINTS, ARM_LOWER_RAD, ARM_UPPER_RAD, HAND_LINK, T_HAND_CAMERA, Panda
from don_gym.sim.sensor import get_sensor, sample_calibration_error, simulate_depth
from don_gym.sim.task import TABLE_BOUNDS_M, TABLE_TOP_Z_M, PickPlaceTask

#: Ranges of the quasi-random camera trajectory.
DISTANCE_RANGE_M = (0.25, 0.55)
ELEVATION_RANGE_RAD = (np.deg2rad(40.0), np.deg2rad(88.0))
ROLL_RANGE_RAD = (-np.pi / 3, np.pi / 3)
LOOK_AT_OFFSET_M = 0.06
#: A pose is used when the arm reaches it within these tolerances.
REACH_POSITION_TOLERANCE_M = 0.01
REACH_ROTATION_TOLERANCE_RAD = np.deg2rad(5.0)
#: Height of the floor under the table (m), seen past the table's edges.
FLOOR_Z_M = -0.75
#: Rounds of IK re-solving from the previous solution.
IK_ROUNDS = 12


@dataclass
class RecordedFrame:
    """One wrist-camera frame. Images are (H, W[, 3]); poses (4, 4), metres."""

    rgb: np.ndarray
    depth_m: np.ndarray
    depth_ideal_m: np.ndarray
    object_mask: np.ndarray
    T_world_camera: np.ndarray
    T_world_camera_reported: np.ndarray


@dataclass
class RecordedScene:
    intrinsics: CameraIntrinsics
    T_world_object: np.ndarray
    table_height_m: float
    frames: list[RecordedFrame] = field(default_factory=list)
    background: dict[str, Any] = field(default_factory=dict)


def random_table_texture(rng: np.random.Generator, size_px: int = 128) -> np.ndarray:
    """(size, size, 3) uint8 procedural texture: smooth noise, stripes or checks in two random colours."""
    colour_a, colour_b = rng.uniform(0, 255, size=(2, 3))
    kind = rng.choice(["noise", "stripes", "checks"])
    v, u = np.mgrid[0:size_px, 0:size_px] / size_px
    if kind == "noise":
        cells = int(rng.integers(4, 24))
        coarse = rng.uniform(0, 1, size=(cells, cells)).astype(np.float32)
        weight = cv2.resize(coarse, (size_px, size_px), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    elif kind == "stripes":
        angle = rng.uniform(0, np.pi)
        weight = 0.5 + 0.5 * np.sin(2 * np.pi * rng.integers(3, 12) * (u * np.cos(angle) + v * np.sin(angle)))
    else:
        count = int(rng.integers(3, 10))
        weight = ((np.floor(u * count) + np.floor(v * count)) % 2).astype(np.float64)
    image = colour_a * (1 - weight[..., None]) + colour_b * weight[..., None]
    return image.clip(0, 255).astype(np.uint8)


class SceneRecorder:
    """Records static scenes of one object; owns one PyBullet client (see :class:`Bullet`).

    Per scene the object is put at a pose (from the seed, or given) on the table, then the Panda
    moves the wrist camera through a quasi-random (Halton) set of reachable poses around it:
    distance 0.25-0.55 m, elevation 40-88 degrees, any azimuth, roll, looking at points up to
    6 cm from the object, so it is seen from many sides and not always centred. The arm is put
    at each pose by IK and joint reset; no physics step runs while recording, so the object never
    moves. Per frame it keeps RGB, sensor depth, ideal depth, the object mask from the
    segmentation, the true camera pose and the reported one (the sensor's hand-eye calibration
    error, drawn once per scene as on a real robot). As in the paper, the background is
    randomised per scene: a procedural texture (smooth noise, stripes or checks in two random
    colours) on the table top and the floor, and a random colour on the fixture.

    Args:
        model: the object.
        image_size: (width, height) of the wrist camera in pixels (D435-like intrinsics).
        sensor: depth-sensor preset name or model for ``depth_m``.
        renderer: ``"tiny"`` or ``"egl"``.
    """

    def __init__(
        self, model: ObjectModel, image_size: tuple[int, int] = (320, 240), sensor: str = "d435", renderer: str = "tiny"
    ) -> None:
        self.model = model
        self.sensor = get_sensor(sensor)
        self.intrinsics = CameraIntrinsics.d435(*image_size)
        self.sim = Bullet(renderer=renderer)
        self.robot = Panda(self.sim)
        self.task = PickPlaceTask(self.sim, model)
        self._texture_dir = tempfile.TemporaryDirectory(prefix="don_gym_textures_")
        self._texture_count = 0
        # Box shapes carry no texture coordinates, so textures go on visual-only quads laid
        # over the table top (0.2 mm above it, so the object is never hidden) and on a floor.
        x0, x1, y0, y1 = TABLE_BOUNDS_M
        self.table_surface_id = self._add_quad("table_surface", (x0, x1, y0, y1), TABLE_TOP_Z_M + 0.0002, repeats=3)
        self.floor_id = self._add_quad("floor", (-2.0, 3.0, -2.5, 2.5), FLOOR_Z_M, repeats=6)
        self.sim.take_snapshot()

    @property
    def renderer(self) -> str:
        return self.sim.renderer

    def _add_quad(
        self, name: str, bounds_xy: tuple[float, float, float, float], z: float, repeats: int, cells: int = 12
    ) -> int:
        """A textured horizontal rectangle, split into ``cells`` x ``cells`` squares because
        TinyRenderer maps textures affinely per triangle (large triangles warp visibly)."""
        x0, x1, y0, y1 = bounds_xy
        t = np.linspace(0.0, 1.0, cells + 1)
        tu, tv = np.meshgrid(t, t, indexing="xy")
        vertices = np.stack([x0 + (x1 - x0) * tu, y0 + (y1 - y0) * tv, np.full_like(tu, z)], axis=-1).reshape(-1, 3)
        uvs = (np.stack([tu, tv], axis=-1) * repeats).reshape(-1, 2)
        corner = (np.arange(cells)[None, :] + (cells + 1) * np.arange(cells)[:, None]).ravel()
        indices = np.stack([corner, corner + 1, corner + cells + 2, corner, corner + cells + 2, corner + cells + 1], 1)
        visual = self.sim.client.createVisualShape(
            p.GEOM_MESH,
            vertices=vertices.tolist(),
            indices=indices.ravel().tolist(),
            uvs=uvs.tolist(),
            normals=[[0.0, 0.0, 1.0]] * len(vertices),
        )
        return self.sim.add_body(name, self.sim.client.createMultiBody(baseMass=0.0, baseVisualShapeIndex=visual))

    def _randomise_background(self, rng: np.random.Generator) -> dict[str, Any]:
        client = self.sim.client
        settings: dict[str, Any] = {}
        for name, body_id in (("table", self.table_surface_id), ("floor", self.floor_id)):
            texture = random_table_texture(rng)
            # PyBullet caches textures by file name: every texture needs a new one.
            self._texture_count += 1
            path = Path(self._texture_dir.name) / f"{name}_{self._texture_count}.png"
            write_png(path, cv2.cvtColor(texture, cv2.COLOR_RGB2BGR))  # raises, not a silently missing texture
            client.changeVisualShape(body_id, -1, rgbaColor=[1, 1, 1, 1], textureUniqueId=client.loadTexture(str(path)))
            settings[f"{name}_texture_mean_rgb"] = texture.reshape(-1, 3).mean(axis=0).round(1)
        settings["cradle_rgba"] = [*rng.uniform(0.1, 0.9, size=3), 1.0]
        client.changeVisualShape(self.task.cradle_id, -1, rgbaColor=settings["cradle_rgba"])
        return settings

    def _reach(self, T_world_camera_wanted: np.ndarray) -> np.ndarray | None:
        """Put the arm so the camera is at the wanted pose; returns the true camera pose or None."""
        client = self.sim.client
        T_world_hand = T_world_camera_wanted @ invert_transform(T_HAND_CAMERA)
        position = T_world_hand[:3, 3]
        quat = Rotation.from_matrix(T_world_hand[:3, :3]).as_quat()
        # Start every solve from the home pose: a failed solve can leave the arm folded in a
        # configuration from which PyBullet's IK never recovers.
        for joint, angle in zip(ARM_JOINTS, ARM_HOME_RAD, strict=True):
            client.resetJointState(self.robot.body_id, joint, float(angle))
        lower = [*ARM_LOWER_RAD, 0.0, 0.0]
        upper = [*ARM_UPPER_RAD, 0.04, 0.04]
        # PyBullet's IK linearises at the current joints; re-solving from each solution converges.
        for _ in range(IK_ROUNDS):
            solution = client.calculateInverseKinematics(
                self.robot.body_id,
                HAND_LINK,
                list(position),
                list(quat),
                lowerLimits=lower,
                upperLimits=upper,
                jointRanges=[u - lo for u, lo in zip(upper, lower, strict=True)],
                restPoses=[*ARM_HOME_RAD, 0.04, 0.04],
                maxNumIterations=100,
                residualThreshold=1e-5,
            )
            arm = np.clip(np.asarray(solution[:7]), ARM_LOWER_RAD, ARM_UPPER_RAD)
            for joint, angle in zip(ARM_JOINTS, arm, strict=True):
                client.resetJointState(self.robot.body_id, joint, float(angle))
            T_world_camera = self.robot.camera_pose()
            position_error = np.linalg.norm(T_world_camera[:3, 3] - T_world_camera_wanted[:3, 3])
            rotation_error = rotation_angle_rad(T_world_camera[:3, :3], T_world_camera_wanted[:3, :3])
            converged = position_error < 0.1 * REACH_POSITION_TOLERANCE_M
            if converged and rotation_error < 0.1 * REACH_ROTATION_TOLERANCE_RAD:
                break
        if position_error > REACH_POSITION_TOLERANCE_M or rotation_error > REACH_ROTATION_TOLERANCE_RAD:
            return None
        client.performCollisionDetection()
        for other in (self.task.table_id, self.task.cradle_id, self.task.part.body_id):
            # The base and first link stand on the table by design.
            near = client.getClosestPoints(self.robot.body_id, other, distance=0.005)
            if any(point[3] > 1 for point in near):
                return None
        return T_world_camera

    def record(
        self, seed: int, num_frames: int, T_world_object: np.ndarray | None = None, max_tries_per_frame: int = 20
    ) -> RecordedScene:
        """Record one scene; the same seed gives the same scene, pixel for pixel.

        ``T_world_object`` places the object exactly (no settling); otherwise a random
        lying pose is drawn from the seed and the object settles under gravity.
        """
        if num_frames < 1:
            raise DonGymError(f"num_frames must be >= 1, got {num_frames}")
        rng = np.random.default_rng(seed)
        # Back to the state after construction: bit-identical physics for the same seed,
        # whatever was recorded before.
        self.sim.restore_snapshot()
        self.robot.reset(ARM_HOME_RAD)
        background = self._randomise_background(rng)
        if T_world_object is None:
            self.task.place_part(*self.task.sample_pose(rng))
            self.task.settle()
        else:
            self.task.part.set_pose(np.asarray(T_world_object, dtype=np.float64))
        T_world_object = self.task.part.T_world_object
        scene = RecordedScene(self.intrinsics, T_world_object, TABLE_TOP_Z_M, background=background)
        T_camera_reported = sample_calibration_error(self.sensor, rng)
        halton = qmc.Halton(d=6, seed=rng)
        object_centre = self.task.part.center_of_mass_world
        part_id = self.task.part.body_id
        tries = 0
        while len(scene.frames) < num_frames:
            tries += 1
            if tries > max_tries_per_frame * num_frames:
                raise DonGymError(
                    f"could not reach {num_frames} camera poses around the object at {object_centre.round(3)}; "
                    "is it inside the robot's workspace?"
                )
            s = halton.random(1)[0]
            distance = DISTANCE_RANGE_M[0] + s[0] * (DISTANCE_RANGE_M[1] - DISTANCE_RANGE_M[0])
            elevation = ELEVATION_RANGE_RAD[0] + s[1] * (ELEVATION_RANGE_RAD[1] - ELEVATION_RANGE_RAD[0])
            azimuth = 2 * np.pi * s[2]
            roll = ROLL_RANGE_RAD[0] + s[3] * (ROLL_RANGE_RAD[1] - ROLL_RANGE_RAD[0])
            offset_radius, offset_angle = LOOK_AT_OFFSET_M * np.sqrt(s[4]), 2 * np.pi * s[5]
            target = object_centre + offset_radius * np.array([np.cos(offset_angle), np.sin(offset_angle), 0.0])
            eye = target + distance * np.array(
                [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
            )
            T_world_camera = self._reach(look_at_camera_pose(eye, target, roll))
            if T_world_camera is None:
                continue
            rgb, depth_ideal, segmentation = render_camera(
                self.sim.client, self.intrinsics, T_world_camera, renderer=self.sim.renderer
            )
            specular = specular_map(segmentation, {part_id: self.model.material.specular})
            depth = simulate_depth(depth_ideal, specular, self.intrinsics, self.sensor, rng)
            scene.frames.append(
                RecordedFrame(
                    rgb=rgb,
                    depth_m=depth,
                    depth_ideal_m=depth_ideal,
                    object_mask=body_mask(segmentation, part_id),
                    T_world_camera=T_world_camera,
                    T_world_camera_reported=T_world_camera @ T_camera_reported,
                )
            )
        self.robot.reset(ARM_HOME_RAD)
        return scene

    def close(self) -> None:
        self.sim.close()
        self._texture_dir.cleanup()

    def __enter__(self) -> SceneRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
