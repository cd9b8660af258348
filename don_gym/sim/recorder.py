"""Scene recorder (:class:`SceneRecorder`): the paper's static-scene recordings with a wrist
camera, in simulation. Each scene is the object lying on the table, seen from many wrist-camera
poses, with RGB, sensor and ideal depth, object mask and camera poses per frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import qmc

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, rotation_angle_rad
from don_gym.objects import ObjectModel
from don_gym.sim.backdrop import BACKDROP_SETS, Backdrop, check_backdrop_set
from don_gym.sim.bullet import Bullet
from don_gym.sim.camera import (
    body_mask,
    check_lighting_mode,
    look_at_camera_pose,
    random_lighting,
    render_camera,
    specular_map,
)
from don_gym.sim.distractors import Distractors, check_distractor_count
from don_gym.sim.robot import ARM_HOME_RAD, ARM_JOINTS, ARM_LOWER_RAD, ARM_UPPER_RAD, HAND_LINK, T_HAND_CAMERA, Panda
from don_gym.sim.sensor import get_sensor, sample_calibration_error, simulate_depth
from don_gym.sim.task import TABLE_TOP_Z_M, PickPlaceTask

#: Ranges of the quasi-random camera trajectory.
DISTANCE_RANGE_M = (0.25, 0.55)
ELEVATION_RANGE_RAD = (np.deg2rad(40.0), np.deg2rad(88.0))
ROLL_RANGE_RAD = (-np.pi / 3, np.pi / 3)
LOOK_AT_OFFSET_M = 0.06
#: A pose is used when the arm reaches it within these tolerances.
REACH_POSITION_TOLERANCE_M = 0.01
REACH_ROTATION_TOLERANCE_RAD = np.deg2rad(5.0)
#: Second random stream of a scene's seed: lighting and distractors.
VARIETY_STREAM = 1
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
        renderer: ``"tiny"``, ``"egl"`` or ``"pbr"`` (:data:`~don_gym.sim.camera.RENDERERS`).
        backgrounds: the set of backdrop texture families (:data:`~don_gym.sim.backdrop.BACKDROP_SETS`):
            ``"classic"`` (the three above), ``"wide"`` (nine families) or ``"mixed"`` (half classic, half wide).
        distractors: coloured primitives placed on the table around the object per scene
            (:class:`~don_gym.sim.distractors.Distractors`), never touching it.
        lighting: ``"fixed"`` (the renderer's default light) or ``"random"`` (a light drawn per scene:
            direction, tint, ambient, diffuse and specular strength, shadows; :func:`random_lighting`).

    The default options record exactly what don_gym always recorded; the other options draw their
    random numbers from a second generator of the scene's seed, so the object pose, camera poses and
    sensor noise of a scene do not change with them.
    """

    def __init__(
        self,
        model: ObjectModel,
        image_size: tuple[int, int] = (320, 240),
        sensor: str = "d435",
        renderer: str = "tiny",
        backgrounds: str = "classic",
        distractors: int = 0,
        lighting: str = "fixed",
    ) -> None:
        self.model = model
        # Every option is checked before the PyBullet client exists: a refused recorder leaves nothing open.
        self._set_camera_options(image_size, sensor, backgrounds, lighting)
        distractor_count = check_distractor_count(distractors)
        self.sim = Bullet(renderer=renderer)
        self._scene_renderer = self.sim.renderer
        self.robot = Panda(self.sim)
        self.task = PickPlaceTask(self.sim, model)
        self.backdrop = Backdrop(self.sim, cradle_id=self.task.cradle_id)
        self.distractors = Distractors(self.sim, distractor_count)
        self.sim.take_snapshot()

    def _set_camera_options(self, image_size: tuple[int, int], sensor: str, backgrounds: str, lighting: str) -> None:
        """Check and keep the options of the camera and the scene's looks (no PyBullet needed)."""
        self.sensor = get_sensor(sensor)
        self.intrinsics = CameraIntrinsics.d435(*image_size)
        self.backdrop_families = check_backdrop_set(backgrounds)
        self.lighting_mode = check_lighting_mode(lighting)

    @property
    def renderer(self) -> str:
        return self.sim.renderer

    def _obstacle_ids(self) -> tuple[int, ...]:
        """Bodies the arm must keep clear of at a camera pose."""
        return (self.task.table_id, self.task.cradle_id, self.task.part.body_id, *self.distractors.body_ids)

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
        for other in self._obstacle_ids():
            # The base and first link stand on the table by design.
            near = client.getClosestPoints(self.robot.body_id, other, distance=0.005)
            if any(point[3] > 1 for point in near):
                return None
        return T_world_camera

    def record(
        self,
        seed: int,
        num_frames: int,
        T_world_object: np.ndarray | None = None,
        max_tries_per_frame: int = 20,
        renderer: str | None = None,
    ) -> RecordedScene:
        """Record one scene; the same seed gives the same scene, pixel for pixel.

        ``T_world_object`` places the object exactly (no settling); otherwise a random
        lying pose is drawn from the seed and the object settles under gravity. ``renderer`` draws this
        scene's RGB (:meth:`frame_renderer`); depth, masks and poses do not depend on it.
        """
        rng, background = self._start_scene(seed, num_frames, renderer)
        if T_world_object is None:
            self.task.place_part(*self.task.sample_pose(rng))
            self.task.settle()
        else:
            self.task.part.set_pose(np.asarray(T_world_object, dtype=np.float64))
        T_world_object = self.task.part.T_world_object
        variety_rng, lighting = self._vary_scene(seed, background)
        if self.distractors.count:
            # Clear of the part's bounding sphere about its origin too: the self-supervised targets' fused
            # object masks take everything within it for the part.
            centre_m = self.task.part.center_of_mass_world
            origin_offset_m = float(np.linalg.norm(T_world_object[:2, 3] - centre_m[:2]))
            part_radius_m = 0.5 * float(np.linalg.norm(self.model.extents_m)) + origin_offset_m + 0.005
            background["distractors"] = self.distractors.scatter(variety_rng, centre_m[:2], part_radius_m)
        scene = RecordedScene(self.intrinsics, T_world_object, TABLE_TOP_Z_M, background=background)
        part_id = self.task.part.body_id
        views = self._views(
            rng, self.task.part.center_of_mass_world, num_frames, max_tries_per_frame, lighting,
            {part_id: self.model.material.specular}, "the object",
        )  # fmt: skip
        for segmentation, frame in views:
            scene.frames.append(RecordedFrame(object_mask=body_mask(segmentation, part_id), **frame))
        self.robot.reset(ARM_HOME_RAD)
        return scene

    def frame_renderer(self, renderer: str | None) -> str:
        """The renderer a scene's RGB is drawn with: ``renderer``, or the recorder's own for None. TinyRenderer
        draws with any client, so a ``"pbr"`` recorder can record a dataset of both (a ``"mixed"`` dataset);
        another renderer than those two needs a recorder made with it."""
        if renderer is None or renderer == self.sim.renderer:
            return self.sim.renderer
        if renderer != "tiny":
            raise DonGymError(
                f"renderer={renderer!r}: this recorder was made with renderer={self.sim.renderer!r}; it draws a scene "
                "with that one or 'tiny'"
            )
        return renderer

    def _start_scene(
        self, seed: int, num_frames: int, renderer: str | None = None
    ) -> tuple[np.random.Generator, dict[str, Any]]:
        """The scene's main random stream and, drawn from it, the classic backdrop, once the simulation is back to
        its state after construction (bit-identical physics for the same seed, whatever was recorded before); sets
        the renderer of the scene's frames (:meth:`frame_renderer`)."""
        if num_frames < 1:
            raise DonGymError(f"num_frames must be >= 1, got {num_frames}")
        self._scene_renderer = self.frame_renderer(renderer)
        rng = np.random.default_rng(seed)
        self.robot.reset(ARM_HOME_RAD)
        self.task.forget_contacts()
        self.sim.restore_snapshot()
        self.robot.reset(ARM_HOME_RAD)
        return rng, self.backdrop.randomise(rng, BACKDROP_SETS["classic"])

    def _vary_scene(self, seed: int, background: dict[str, Any]) -> tuple[np.random.Generator, Any]:
        """The scene's second random stream (for what the options add) and the lighting drawn from it (None:
        fixed); the other backdrop families and the lighting are added to ``background``."""
        variety_rng = np.random.default_rng([seed, VARIETY_STREAM])
        if self.backdrop_families != BACKDROP_SETS["classic"]:
            # Over the classic backdrop, whose draws keep the main stream (and so the part's pose) as it was.
            background.update(self.backdrop.randomise(variety_rng, self.backdrop_families))
        lighting = random_lighting(variety_rng) if self.lighting_mode == "random" else None
        if lighting is not None:
            background["lighting"] = asdict(lighting)
        return variety_rng, lighting

    def _views(
        self,
        rng: np.random.Generator,
        look_at_world: np.ndarray,
        num_frames: int,
        max_tries_per_frame: int,
        lighting: Any,
        specular_by_body: dict[int, float],
        what: str,
    ) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
        """``num_frames`` reachable wrist-camera views around ``look_at_world`` (3,), drawn from ``rng`` (the
        trajectory of the class docstring, after the scene's hand-eye calibration error): ``(segmentation,
        frame)`` each, ``frame`` the fields of a frame (``rgb``, ``depth_m``, ``depth_ideal_m``,
        ``T_world_camera``, ``T_world_camera_reported``); ``what`` names the thing looked at in the refusal when
        too few poses are reachable."""
        T_camera_reported = sample_calibration_error(self.sensor, rng)
        halton = qmc.Halton(d=6, seed=rng)
        object_centre = np.asarray(look_at_world, dtype=np.float64)
        tries = found = 0
        while found < num_frames:
            tries += 1
            if tries > max_tries_per_frame * num_frames:
                raise DonGymError(
                    f"could not reach {num_frames} camera poses around {what} at {object_centre.round(3)}; "
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
                self.sim.client, self.intrinsics, T_world_camera, renderer=self._scene_renderer, lighting=lighting
            )
            specular = specular_map(segmentation, specular_by_body)
            depth = simulate_depth(depth_ideal, specular, self.intrinsics, self.sensor, rng)
            found += 1
            yield (
                segmentation,
                {
                    "rgb": rgb,
                    "depth_m": depth,
                    "depth_ideal_m": depth_ideal,
                    "T_world_camera": T_world_camera,
                    "T_world_camera_reported": T_world_camera @ T_camera_reported,
                },
            )

    def close(self) -> None:
        self.sim.close()
        self.backdrop.close()

    def __enter__(self) -> SceneRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
