"""A rigid part in PyBullet from an :class:`~don_gym.objects.ObjectModel` (:class:`PartBody`).

Its collision shape is a compound of convex pieces (:func:`collision_method`), cached as an OBJ
file under :func:`cache_dir`; mass and inertia come from the model.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p
import trimesh
from scipy.spatial.transform import Rotation

from don_gym.geometry import invert_transform, make_transform, pose_from_transform
from don_gym.io import atomic_path
from don_gym.objects import ObjectModel
from don_gym.sim.bullet import Bullet, silence_c_stdout
from don_gym.sim.pbr import Surface

#: V-HACD parameters; part of the cache key.
VHACD_PARAMS = {"resolution": 200_000, "concavity": 0.0025, "maxNumVerticesPerCH": 64, "minVolumePerCH": 1e-5}
#: Axial slabs: largest deviation (m) of the simplified radius profile, most pieces, and the
#: polygon used for the rings (32 sections: the flats lie 0.07 mm inside a 14 mm radius).
SLAB_TOLERANCE_M = 1e-4
MAX_SLABS = 16
COLLISION_SECTIONS = 32

# Spinning/rolling friction keep a part lying on the table from creeping on its
# faceted hull and twisting in the grasp; values are small (metres of lever arm).
PART_SPINNING_FRICTION = 0.002
PART_ROLLING_FRICTION = 0.0002


def cache_dir() -> Path:
    """Directory for derived meshes: ``$DON_GYM_CACHE`` or ``$XDG_CACHE_HOME/don_gym`` (``~/.cache/don_gym``)."""
    if os.environ.get("DON_GYM_CACHE"):
        return Path(os.environ["DON_GYM_CACHE"]).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME", "~/.cache")).expanduser()
    return base / "don_gym"


def _params_key(method: str) -> str:
    params = (
        VHACD_PARAMS
        if method == "vhacd"
        else {"tolerance": SLAB_TOLERANCE_M, "max": MAX_SLABS, "sections": COLLISION_SECTIONS, "v": 2}
    )
    text = ",".join(f"{k}={v}" for k, v in sorted(params.items())) + f",pybullet={p.getAPIVersion()}"
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def _douglas_peucker(points: np.ndarray, tolerance: float) -> list[int]:
    """Indices of the points kept when simplifying a 2D polyline to ``tolerance``."""
    keep = {0, len(points) - 1}
    stack = [(0, len(points) - 1)]
    while stack:
        first, last = stack.pop()
        if last - first < 2:
            continue
        start, end = points[first], points[last]
        direction = end - start
        length = float(np.linalg.norm(direction))
        inner = points[first + 1 : last] - start
        if length < 1e-15:
            distance = np.linalg.norm(inner, axis=1)
        else:
            distance = np.abs(direction[0] * inner[:, 1] - direction[1] * inner[:, 0]) / length
        worst = int(np.argmax(distance))
        if distance[worst] > tolerance:
            split = first + 1 + worst
            keep.add(split)
            stack += [(first, split), (split, last)]
    return sorted(keep)


def _outer_radius(mesh: trimesh.Trimesh, axis: np.ndarray, t: float) -> float | None:
    """Largest distance from the axis of the mesh's cross-section at ``t`` along it (None: no section)."""
    section = mesh.section(plane_origin=axis * t, plane_normal=axis)
    if section is None:
        return None
    ring = np.asarray(section.vertices)
    return float(np.linalg.norm(ring - np.outer(ring @ axis, axis), axis=1).max())


def radius_profile(mesh: trimesh.Trimesh, axis: np.ndarray) -> np.ndarray:
    """(N, 2) outer radius profile ``(t, r)`` along ``axis`` (through the origin), metres.

    Cross-sections just below and just above every vertex level give both radii where the
    profile steps (a flange), so a step is a vertical segment, not a cone.
    """
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    levels = np.unique(np.round(np.asarray(mesh.vertices) @ axis, 7))
    eps = 1e-6
    points = []
    for i, t in enumerate(levels):
        for side in (-1.0, 1.0):
            if (side < 0 and i == 0) or (side > 0 and i == len(levels) - 1):
                continue
            radius = _outer_radius(mesh, axis, t + side * eps)
            if radius is not None and not (points and points[-1][0] == t and abs(points[-1][1] - radius) < 1e-7):
                points.append((t, radius))
    # The end faces: close the profile on the axis.
    return np.array([(levels[0], 0.0), *points, (levels[-1], 0.0)])


def axial_slabs(mesh: trimesh.Trimesh, axis: np.ndarray, sections: int = COLLISION_SECTIONS) -> list[np.ndarray]:
    """Convex pieces of a part that is (close to) rotationally symmetric about ``axis`` through the origin.

    The outer radius profile is simplified to :data:`SLAB_TOLERANCE_M` and cut where it turns
    convex (a step up or down onto a thinner section, a waist): between cuts it is concave, so
    the solid of revolution is convex and one piece represents it exactly. Each piece is returned
    as (N, 3) vertices (``sections``-gons on the profile points), object frame. The toolcap
    becomes two pieces (chamfered body, flange), the shaft four; bores are filled, as nothing in
    this task reaches into them.
    """
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    profile = radius_profile(mesh, axis)
    tolerance = SLAB_TOLERANCE_M
    while True:
        simplified = profile[_douglas_peucker(profile, tolerance)]
        direction = np.diff(simplified, axis=0)
        # Left (counter-clockwise) turns of the (t, r) polyline are where it stops being concave.
        turn = direction[:-1, 0] * direction[1:, 1] - direction[:-1, 1] * direction[1:, 0]
        length = np.linalg.norm(direction[:-1], axis=1) * np.linalg.norm(direction[1:], axis=1)
        cuts = [0, *(1 + np.flatnonzero(turn > 1e-6 * np.maximum(length, 1e-30))), len(simplified) - 1]
        if len(cuts) - 1 <= MAX_SLABS:
            break
        tolerance *= 2.0  # very wavy profiles: coarser, never more than MAX_SLABS pieces
    # Orthonormal frame around the axis for the rings.
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angles = 2.0 * np.pi * np.arange(sections) / sections
    ring = np.outer(np.cos(angles), u) + np.outer(np.sin(angles), v)
    pieces = []
    for first, last in zip(cuts[:-1], cuts[1:], strict=True):
        points = []
        for t, r in simplified[first : last + 1]:
            points.append(axis * t + r * ring if r > 0 else (axis * t)[None, :])
        vertices = np.unique(np.concatenate(points), axis=0)
        if len(vertices) >= 4 and np.ptp(vertices @ axis) > 0:
            pieces.append(vertices)
    return pieces


def _write_pieces_obj(path: Path, pieces: list[np.ndarray]) -> None:
    lines, offset = [], 1
    for index, points in enumerate(pieces):
        hull = trimesh.convex.convex_hull(points)
        lines.append(f"o piece{index}")
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in hull.vertices]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in hull.faces]
        offset += len(hull.vertices)
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def collision_method(model: ObjectModel) -> str:
    """ "slabs" for parts with a declared symmetry axis, "vhacd" otherwise.

    Convex pieces make steps and flanges collide like the real part (one convex hull would turn
    the toolcap into a cone and the shaft into a cylinder). "slabs": :func:`axial_slabs`, few
    pieces with few vertices, each exact to the radius profile. "vhacd": PyBullet's V-HACD
    (``p.vhacd``) with :data:`VHACD_PARAMS`, for any other mesh.
    """
    return "slabs" if model.symmetry_axis is not None else "vhacd"


def mesh_files(model: ObjectModel, directory: Path | None = None) -> tuple[Path, Path]:
    """``(visual_obj, collision_obj)`` for ``model``, created on first use and cached.

    The visual OBJ is the model mesh in the object frame; the collision OBJ holds the convex
    pieces (one ``o`` group each), which PyBullet loads as a compound shape. Files are keyed by
    the mesh hash and the collision method's parameters.
    """
    directory = cache_dir() if directory is None else Path(directory)
    key = model.mesh_hash or hashlib.sha256(np.ascontiguousarray(model.mesh.vertices).tobytes()).hexdigest()[:16]
    method = collision_method(model)
    visual = directory / f"{key}_visual.obj"
    collision = directory / f"{key}_{method}_{_params_key(method)}.obj"
    if not visual.exists():
        with atomic_path(visual) as tmp:
            model.mesh.export(str(tmp), file_type="obj", include_normals=True)
    if not collision.exists():
        if method == "slabs":
            # Slabs are about the symmetry axis through the centre of mass.
            centred = model.mesh.copy()
            centred.apply_translation(-model.center_of_mass)
            pieces = [piece + model.center_of_mass for piece in axial_slabs(centred, model.symmetry_axis)]
            _write_pieces_obj(collision, pieces)
        else:
            with atomic_path(collision) as tmp, atomic_path(collision.with_suffix(".log")) as log:
                with silence_c_stdout():
                    p.vhacd(str(visual), str(tmp), str(log), **VHACD_PARAMS)
                if not tmp.exists() or tmp.stat().st_size == 0:
                    raise RuntimeError(f"V-HACD produced no output for {model.name} ({visual})")
    return visual, collision


def principal_frame(model: ObjectModel) -> tuple[np.ndarray, np.ndarray]:
    """``(T_object_inertial (4, 4), principal moments (3,) kg m^2)`` of the part.

    The inertial frame sits at the centre of mass with axes along the principal axes; when the
    inertia tensor is already diagonal in the object frame (the built-ins) its axes are kept.
    """
    inertia = model.inertia_kg_m2
    off_diagonal = inertia - np.diag(np.diag(inertia))
    if np.abs(off_diagonal).max() <= 1e-9 * max(np.abs(inertia).max(), 1e-30):
        rotation, moments = np.eye(3), np.diag(inertia).copy()
    else:
        moments, rotation = np.linalg.eigh(inertia)
        if np.linalg.det(rotation) < 0:
            rotation[:, 2] *= -1.0
    return make_transform(rotation, model.center_of_mass), np.maximum(moments, 1e-12)


@dataclass
class PartBody:
    """The simulated part: its PyBullet id and the object <-> inertial frame offset.

    The PyBullet base frame of the body is the part's *inertial* frame (centre of mass, principal
    axes, :func:`principal_frame`), as PyBullet reports it; every method takes and returns the
    *object frame* of the :class:`ObjectModel` (``T_world_object``). Mass and inertia come from the
    model (density x mesh volume), not from PyBullet's bounding-box guess for compound shapes.
    """

    sim: Bullet
    model: ObjectModel
    body_id: int
    T_object_inertial: np.ndarray

    def __post_init__(self) -> None:
        self._T_inertial_object = invert_transform(self.T_object_inertial)

    @classmethod
    def create(cls, sim: Bullet, model: ObjectModel, name: str = "object", directory: Path | None = None) -> PartBody:
        visual_path, collision_path = mesh_files(model, directory)
        client = sim.client
        T_object_inertial, moments = principal_frame(model)
        # The body frame *is* the inertial frame: the shapes are placed at T_inertial_object.
        position_io, quaternion_io = pose_from_transform(invert_transform(T_object_inertial))
        collision = client.createCollisionShape(
            p.GEOM_MESH,
            fileName=str(collision_path),
            collisionFramePosition=list(position_io),
            collisionFrameOrientation=list(quaternion_io),
        )
        visual = client.createVisualShape(
            p.GEOM_MESH,
            fileName=str(visual_path),
            rgbaColor=list(model.material.rgba),
            specularColor=[model.material.specular] * 3,
            visualFramePosition=list(position_io),
            visualFrameOrientation=list(quaternion_io),
        )
        body_id = client.createMultiBody(
            baseMass=model.mass_kg,
            baseCollisionShapeIndex=collision,
            baseVisualShapeIndex=visual,
            basePosition=[0.0, 0.0, 1.0],
        )
        sim.add_body(name, body_id)
        sim.set_surface(body_id, Surface(metallic=model.material.metallic, roughness=model.material.roughness))
        client.changeDynamics(
            body_id,
            -1,
            localInertiaDiagonal=list(moments),
            lateralFriction=model.material.lateral_friction,
            spinningFriction=PART_SPINNING_FRICTION,
            rollingFriction=PART_ROLLING_FRICTION,
        )
        return cls(sim, model, body_id, T_object_inertial)

    @property
    def T_world_object(self) -> np.ndarray:
        """(4, 4) pose of the object frame in the world."""
        return self.sim.base_transform(self.body_id) @ self._T_inertial_object

    def set_pose(self, T_world_object: np.ndarray) -> None:
        """Teleport the part (zero velocity); only for resets, never during an episode."""
        position, quaternion = pose_from_transform(np.asarray(T_world_object) @ self.T_object_inertial)
        self.sim.client.resetBasePositionAndOrientation(self.body_id, list(position), list(quaternion))
        self.sim.client.resetBaseVelocity(self.body_id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])

    @property
    def center_of_mass_world(self) -> np.ndarray:
        return self.sim.base_pose(self.body_id)[0]

    @property
    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """(linear m/s, angular rad/s) of the centre of mass in the world."""
        linear, angular = self.sim.client.getBaseVelocity(self.body_id)
        return np.asarray(linear), np.asarray(angular)

    def plus_axis_world(self) -> np.ndarray:
        """(3,) unit +axis of the part in the world."""
        return self.T_world_object[:3, :3] @ self.model.plus_axis

    def lowest_point_z(self) -> float:
        """World z (m) of the lowest mesh vertex at the current pose."""
        T = self.T_world_object
        return float((self.model.mesh.vertices @ T[:3, :3].T)[:, 2].min() + T[2, 3])


def lying_rotation(model: ObjectModel, yaw_rad: float) -> np.ndarray:
    """(3, 3) rotation laying the part on its side: +axis horizontal at world yaw ``yaw_rad``.

    A fixed object-frame vector orthogonal to the +axis points straight up, so the roll
    about the axis is deterministic (it matters only for parts that are not axisymmetric).
    """
    axis = np.asarray(model.plus_axis, dtype=np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    up = helper - axis * (helper @ axis)
    up /= np.linalg.norm(up)
    side = np.cross(up, axis)
    R_object_lying = np.stack([axis, side, up], axis=1)  # columns: object-frame vectors that become world x, y, z
    R_world_lying = Rotation.from_euler("z", yaw_rad).as_matrix()
    return R_world_lying @ R_object_lying.T
