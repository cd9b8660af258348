"""Analytic test scenes: exact z-depth of planes, boxes and spheres by ray casting in numpy.

Shared by the sensor, fusion and correspondence tests, which need depth images whose
true 3D geometry is known exactly (no PyBullet, no mesh renderer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from don_gym.geometry import CameraIntrinsics, invert_transform, make_transform, pixel_rays, transform_points


@dataclass(frozen=True)
class Plane:
    """Infinite plane through ``point`` (3,) with normal ``normal`` (3,), world frame, metres."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]


@dataclass(frozen=True)
class Box:
    """Box with pose ``T_world_box`` (4, 4) and half extents (3,) in metres."""

    T_world_box: np.ndarray
    half_extents: tuple[float, float, float]

    def contains(self, points_world: np.ndarray, margin_m: float = 0.0) -> np.ndarray:
        local = transform_points(invert_transform(self.T_world_box), points_world)
        return np.all(np.abs(local) <= np.asarray(self.half_extents) + margin_m, axis=-1)


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float


Primitive = Plane | Box | Sphere


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_camera`` of an OpenCV camera at ``eye`` looking at ``target`` (z forward, y down)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def _hit_plane(origin: np.ndarray, dirs: np.ndarray, plane: Plane) -> np.ndarray:
    normal = np.asarray(plane.normal, dtype=np.float64)
    denom = dirs @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(plane.point) - origin) @ normal) / denom
    return np.where((np.abs(denom) > 1e-12) & (t > 0), t, np.inf)


def _hit_box(origin: np.ndarray, dirs: np.ndarray, box: Box) -> np.ndarray:
    T_box_world = invert_transform(box.T_world_box)
    o = T_box_world[:3, :3] @ origin + T_box_world[:3, 3]
    d = dirs @ T_box_world[:3, :3].T
    half = np.asarray(box.half_extents, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (t_far >= t_near) & (t_far > 0)
    return np.where(hit, np.where(t_near > 0, t_near, t_far), np.inf)


def _hit_sphere(origin: np.ndarray, dirs: np.ndarray, sphere: Sphere) -> np.ndarray:
    oc = origin - np.asarray(sphere.center)
    a = np.einsum("ij,ij->i", dirs, dirs)
    b = 2.0 * dirs @ oc
    c = oc @ oc - sphere.radius**2
    disc = b * b - 4 * a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    t_near = (-b - root) / (2 * a)
    t_far = (-b + root) / (2 * a)
    t = np.where(t_near > 0, t_near, t_far)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def render_scene(
    intrinsics: CameraIntrinsics, T_world_camera: np.ndarray, primitives: list[Primitive]
) -> tuple[np.ndarray, np.ndarray]:
    """Exact (H, W) float32 z-depth (0 = nothing hit) and (H, W) int32 index of the visible primitive (-1)."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width]
    rays_camera = pixel_rays(intrinsics, np.stack([u.ravel(), v.ravel()], axis=1))
    # Rays have camera z = 1, so the ray parameter t is the z-depth.
    dirs = rays_camera @ T_world_camera[:3, :3].T
    origin = T_world_camera[:3, 3]
    hitters = {Plane: _hit_plane, Box: _hit_box, Sphere: _hit_sphere}
    ts = np.stack([hitters[type(p)](origin, dirs, p) for p in primitives], axis=1)
    t = ts.min(axis=1)
    index = np.where(np.isfinite(t), ts.argmin(axis=1), -1)
    depth = np.where(np.isfinite(t) & (t > 0), t, 0.0)
    shape = (intrinsics.height, intrinsics.width)
    return depth.reshape(shape).astype(np.float32), index.reshape(shape).astype(np.int32)


def world_points(intrinsics: CameraIntrinsics, T_world_camera: np.ndarray, depth_m: np.ndarray, uv: np.ndarray):
    """(N, 3) world points of integer pixels ``uv`` (N, 2) of a depth image."""
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(depth_m, dtype=np.float64)[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    return transform_points(T_world_camera, pixel_rays(intrinsics, uv) * z[:, None])


def fronto_plane_camera(distance_m: float, tilt_rad: float = 0.0) -> list[Primitive]:
    """A plane ``distance_m`` in front of a camera at the world origin (identity pose), tilted about x."""
    normal = (0.0, np.sin(tilt_rad), -np.cos(tilt_rad))
    return [Plane(point=(0.0, 0.0, distance_m), normal=normal)]


def table_scene(box_half_extents: tuple[float, float, float] = (0.05, 0.03, 0.02)) -> tuple[list[Primitive], Box]:
    """A table plane z = 0 with a box standing on it at the origin, rotated 30 degrees about z.

    Returns (primitives, box); primitive index 1 is the box.
    """
    angle = np.deg2rad(30.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    box = Box(make_transform(rotation, (0.0, 0.0, box_half_extents[2])), box_half_extents)
    return [Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0)), box], box


def distance_to_surfaces(points_world: np.ndarray, primitives: list[Primitive]) -> np.ndarray:
    """(N,) unsigned distance in metres from each point to the nearest primitive surface."""
    points_world = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    distances = []
    for primitive in primitives:
        if isinstance(primitive, Plane):
            normal = np.asarray(primitive.normal) / np.linalg.norm(primitive.normal)
            distances.append(np.abs((points_world - np.asarray(primitive.point)) @ normal))
        elif isinstance(primitive, Sphere):
            distances.append(
                np.abs(np.linalg.norm(points_world - np.asarray(primitive.center), axis=1) - primitive.radius)
            )
        else:
            q = np.abs(transform_points(invert_transform(primitive.T_world_box), points_world)) - primitive.half_extents
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
            distances.append(np.abs(outside + np.minimum(q.max(axis=1), 0.0)))
    return np.min(distances, axis=0)
