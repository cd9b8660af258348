"""A PyBullet physics client owned by one scene (:class:`Bullet`): named bodies, stepping,
snapshots, renderer. Every PyBullet call in ``don_gym.sim`` goes through one, so several envs
live side by side in one process and nothing touches PyBullet's implicit client 0.
"""

from __future__ import annotations

import contextlib
import os
import pkgutil
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pybullet as p
import pybullet_data
from pybullet_utils.bullet_client import BulletClient

from don_gym.errors import DonGymError
from don_gym.sim.camera import check_renderer
from don_gym.sim.pbr import PbrRenderer, Surface, VisualAssets

#: Gravity in m/s^2 along world -z.
GRAVITY_M_S2 = 9.81


@contextlib.contextmanager
def silence_c_stdout(keep: list[str] | None = None) -> Iterator[None]:
    """Redirect the process's file descriptor 1 away from the terminal for the duration.

    PyBullet's C code (V-HACD progress, the EGL plugin's banner) prints straight to fd 1,
    bypassing ``sys.stdout``; benchmark tables and CLI output would drown in it. With ``keep``,
    the lines printed meanwhile are appended to it on exit (else they go to /dev/null).
    """
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):  # no real fd 1 (e.g. some notebook front-ends)
        yield
        return
    sink = tempfile.TemporaryFile() if keep is not None else None
    target = sink.fileno() if sink is not None else os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(target, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        if sink is None:
            os.close(target)
        else:
            sink.seek(0)
            keep.extend(sink.read().decode(errors="replace").splitlines())
            sink.close()


def pose_matrix(position: Sequence[float], quaternion_xyzw: Sequence[float]) -> np.ndarray:
    """(4, 4) transform from a PyBullet (position, quaternion) pair.

    Same result as :func:`don_gym.geometry.transform_from_pose`, via PyBullet's C routine rather
    than scipy's ``Rotation``: the env reads several poses per control step.
    """
    T = np.eye(4)
    T[:3, :3] = np.asarray(p.getMatrixFromQuaternion(quaternion_xyzw), dtype=np.float64).reshape(3, 3)
    T[:3, 3] = position
    return T


class _Client(BulletClient):
    """``BulletClient`` that remembers each bound PyBullet function after its first use.

    ``BulletClient.__getattr__`` builds a new ``functools.partial`` on every call, and the env
    makes a few dozen calls per control step.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        #: What PyBullet does not report back about the visuals (textures, surfaces), recorded by the
        #: methods below for the "pbr" renderer.
        self.assets = VisualAssets()
        #: The path tracer (:class:`~don_gym.sim.pbr.PbrRenderer`) when the world renders with "pbr".
        self.pbr: PbrRenderer | None = None

    def __getattr__(self, name: str):
        attribute = super().__getattr__(name)
        if name != "disconnect" and callable(attribute):
            self.__dict__[name] = attribute
        return attribute

    # PyBullet keeps textures to itself; these record them on their way in.
    def loadTexture(self, path: str, *args, **kwargs) -> int:  # noqa: N802 - PyBullet's name
        texture_id = super().__getattr__("loadTexture")(path, *args, **kwargs)
        self.assets.texture_files[int(texture_id)] = str(path)
        return texture_id

    def changeVisualShape(self, body_id: int, link: int, *args, **kwargs) -> None:  # noqa: N802
        super().__getattr__("changeVisualShape")(body_id, link, *args, **kwargs)
        texture_id = kwargs.get("textureUniqueId")
        if texture_id is not None:
            self.assets.textures.pop((int(body_id), int(link)), None)
            if int(texture_id) >= 0:
                self.assets.textures[(int(body_id), int(link))] = int(texture_id)


class Bullet:
    """One headless PyBullet world.

    Args:
        time_step_s: physics time step in seconds.
        solver_iterations: most constraint-solver iterations per step; small steel parts held
            by two fingers need many more than PyBullet's default of 50 to stay put.
        solver_residual: the solver stops iterating once its least-squares residual is below
            this (PyBullet's default 1e-7 makes it run all iterations nearly always). At 1e-5
            it stops early, and resting and held parts behave the same (same outcomes,
            placement within 0.5 mm in the oracle test).
        renderer: ``"tiny"``, ``"egl"`` or ``"pbr"``; ``"egl"`` loads the eglRenderer plugin on this
            client and falls back to ``"tiny"`` with a warning when that fails; ``"pbr"`` gives the client a
            :class:`~don_gym.sim.pbr.PbrRenderer` (raises a one-line error when Mitsuba is not installed). The renderer
            actually in use is :attr:`renderer`; :attr:`opengl_renderer` names what EGL renders with.
    """

    def __init__(
        self,
        time_step_s: float = 1.0 / 250.0,
        solver_iterations: int = 150,
        solver_residual: float = 1e-5,
        renderer: str = "tiny",
    ):
        check_renderer(renderer)
        with silence_c_stdout():
            self.client = _Client(connection_mode=p.DIRECT)
        self.id: int = self.client._client
        self.time_step_s = float(time_step_s)
        self.bodies: dict[str, int] = {}
        self._snapshot: int | None = None
        self._egl_plugin: int | None = None
        self.client.setAdditionalSearchPath(pybullet_data.getDataPath())
        self.client.setGravity(0.0, 0.0, -GRAVITY_M_S2)
        self.client.setPhysicsEngineParameter(
            fixedTimeStep=self.time_step_s,
            numSolverIterations=int(solver_iterations),
            solverResidualThreshold=float(solver_residual),
            numSubSteps=0,
            # Deterministic broad-phase pair order: same inputs -> same contacts -> same trajectory.
            deterministicOverlappingPairs=1,
        )
        self.renderer = "tiny"
        #: The OpenGL renderer the EGL plugin reported (a GPU's name, or e.g. Mesa's software
        #: ``llvmpipe (LLVM ...)``); None with TinyRenderer or when the plugin did not say.
        self.opengl_renderer: str | None = None
        if renderer == "egl":
            self.renderer = self._load_egl()
        elif renderer == "pbr":
            self.client.pbr = PbrRenderer(self.client.assets)
            self.renderer = "pbr"

    def load_texture(self, path: str | os.PathLike) -> int:
        """Load an image file as a texture; its id for ``changeVisualShape(textureUniqueId=...)``.

        The EGL plugin numbers textures one ahead of the physics server once the Panda has brought textures
        of its own, so the server's id of a texture loaded later shows the texture before it in EGL images
        (the backdrops showed the robot's). Loading the file twice, under two names, and using the second id
        shows the image under either numbering."""
        if self.renderer != "egl":
            return int(self.client.loadTexture(str(path)))
        path = Path(path)
        twin = path.with_name(f"{path.stem}.twin{path.suffix}")
        shutil.copyfile(path, twin)
        self.client.loadTexture(str(path))
        return int(self.client.loadTexture(str(twin)))

    def set_surface(self, body_id: int, surface: Surface) -> None:
        """How body ``body_id`` scatters light in "pbr" renders (others: a rough dielectric)."""
        self.client.assets.surfaces[int(body_id)] = surface

    def _load_egl(self) -> str:
        loader = pkgutil.get_loader("eglRenderer")
        reason = "the eglRenderer module is not installed with pybullet"
        if loader is not None:
            banner: list[str] = []
            with silence_c_stdout(keep=banner):
                plugin = self.client.loadPlugin(loader.get_filename(), "_eglRendererPlugin")
                if plugin >= 0:
                    # The plugin creates its OpenGL context, and prints about it, at the first image.
                    self.client.getCameraImage(8, 8, renderer=p.ER_BULLET_HARDWARE_OPENGL)
            if plugin >= 0:
                self._egl_plugin = plugin
                reported = [line.split("=", 1)[1].strip() for line in banner if line.startswith("GL_RENDERER=")]
                self.opengl_renderer = reported[0] if reported else None
                return "egl"
            reason = "loading the plugin failed (no EGL / OpenGL driver?)"
        warnings.warn(f"renderer='egl' unavailable: {reason}; using 'tiny' (TinyRenderer)", stacklevel=3)
        return "tiny"

    # ----------------------------------------------------------------- bodies
    def body(self, name: str) -> int:
        """PyBullet id of the body registered under ``name``."""
        return self.bodies[name]

    def add_body(self, name: str, body_id: int) -> int:
        if body_id < 0:
            raise DonGymError(f"PyBullet could not create body {name!r}")
        self.bodies[name] = int(body_id)
        return int(body_id)

    def load_urdf(
        self, name: str, path: str, position: Sequence[float], fixed_base: bool = True, flags: int = 0
    ) -> int:
        body_id = self.client.loadURDF(path, basePosition=list(position), useFixedBase=fixed_base, flags=flags)
        return self.add_body(name, body_id)

    def create_static_boxes(
        self,
        name: str,
        boxes: Sequence[tuple[Sequence[float], Sequence[float], Sequence[float]]],
        rgba: Sequence[float],
        lateral_friction: float = 0.6,
    ) -> int:
        """A static body made of boxes, each ``(half_extents, position, quaternion_xyzw)`` in the world."""
        half_extents = [list(map(float, b[0])) for b in boxes]
        positions = [list(map(float, b[1])) for b in boxes]
        orientations = [list(map(float, b[2])) for b in boxes]
        shape_types = [p.GEOM_BOX] * len(boxes)
        collision = self.client.createCollisionShapeArray(
            shapeTypes=shape_types,
            halfExtents=half_extents,
            collisionFramePositions=positions,
            collisionFrameOrientations=orientations,
        )
        visual = self.client.createVisualShapeArray(
            shapeTypes=shape_types,
            halfExtents=half_extents,
            rgbaColors=[list(rgba)] * len(boxes),
            visualFramePositions=positions,
            visualFrameOrientations=orientations,
        )
        body_id = self.client.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=collision, baseVisualShapeIndex=visual
        )
        self.client.changeDynamics(body_id, -1, lateralFriction=lateral_friction)
        return self.add_body(name, body_id)

    # ------------------------------------------------------------- simulation
    def step(self, count: int = 1) -> None:
        step = self.client.stepSimulation
        for _ in range(count):
            step()

    def contact_points(self, body_a: int, body_b: int, link_a: int | None = None) -> list:
        if link_a is None:
            return self.client.getContactPoints(bodyA=body_a, bodyB=body_b)
        return self.client.getContactPoints(bodyA=body_a, bodyB=body_b, linkIndexA=link_a)

    def take_snapshot(self) -> None:
        """Remember the current state (in memory) for :meth:`restore_snapshot`."""
        if self._snapshot is not None:
            self.client.removeState(self._snapshot)
        self._snapshot = self.client.saveState()

    def restore_snapshot(self) -> None:
        """Bit-exact return to the state of :meth:`take_snapshot` (positions, velocities, contacts)."""
        if self._snapshot is None:
            raise RuntimeError("restore_snapshot() before take_snapshot()")
        self.client.restoreState(stateId=self._snapshot)

    def base_pose(self, body_id: int) -> tuple[np.ndarray, np.ndarray]:
        position, quaternion = self.client.getBasePositionAndOrientation(body_id)
        return np.asarray(position, dtype=np.float64), np.asarray(quaternion, dtype=np.float64)

    def base_transform(self, body_id: int) -> np.ndarray:
        """(4, 4) world pose of a body's base (inertial) frame."""
        return pose_matrix(*self.client.getBasePositionAndOrientation(body_id))

    def close(self) -> None:
        """Disconnect the client; safe to call twice."""
        if self.id >= 0:
            with silence_c_stdout():
                if self._egl_plugin is not None:
                    with contextlib.suppress(p.error):
                        self.client.unloadPlugin(self._egl_plugin)
                with contextlib.suppress(p.error):
                    self.client.disconnect()
            self.id = -1
            self.bodies.clear()
            self._snapshot = None
