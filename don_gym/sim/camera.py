"""Pinhole RGB-D rendering with PyBullet from OpenCV intrinsics and a ``T_world_camera`` pose.

:func:`render_camera` is the one place that turns (intrinsics, pose) into PyBullet's OpenGL
matrices and back into metric depth, so the env, the dataset recorder and tests see identical
pixels for identical inputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, make_transform

#: Renderer names accepted by :func:`render_camera` and the env. "tiny": PyBullet's CPU
#: TinyRenderer (``ER_TINY_RENDERER``), always available and the default everywhere in don_gym,
#: because its pixels do not depend on the machine's OpenGL stack. "egl": the ``eglRenderer``
#: plugin (``ER_BULLET_HARDWARE_OPENGL``) loaded per client by :class:`don_gym.sim.bullet.Bullet`,
#: on Mesa's software OpenGL (llvmpipe) without a GPU. Their pixels differ (shading, edge
#: anti-aliasing), so a dataset and a model name the renderer they used. "pbr": path-traced RGB
#: (:mod:`don_gym.sim.pbr`, Mitsuba 3, the ``pbr`` extra) of the same scene: metal that looks like metal,
#: an environment's reflections, soft shadows, a camera's exposure and noise; its depth and segmentation
#: are TinyRenderer's, so masks and targets align to the pixel. Needs a :class:`~don_gym.sim.bullet.Bullet`
#: made with ``renderer="pbr"``.
RENDERERS = ("tiny", "egl", "pbr")

#: Lower 24 bits of a PyBullet segmentation value hold the body id, the upper bits link index + 1.
_BODY_ID_MASK = (1 << 24) - 1

# OpenCV camera (x right, y down, z forward) -> OpenGL camera (x right, y up, z backward).
_T_CV_GL = np.diag([1.0, -1.0, -1.0, 1.0])

# Offset (u, v) in pixels added to the principal point in the OpenGL projection, per
# renderer; see projection_matrix_gl.
_PRINCIPAL_POINT_OFFSET_PX = {"tiny": (0.0, 1.0), "egl": (0.5, 0.5), "pbr": (0.0, 1.0)}

# Fixed light so that renders do not depend on PyBullet's defaults changing between versions.
_LIGHT_DIRECTION = (0.4, -0.3, 1.0)


@dataclass(frozen=True)
class Lighting:
    """The renderer's one directional light: ``direction_world`` points from the scene towards the light
    (world frame, any length), ``colour_rgb`` in [0, 1], the Phong coefficients of ambient, diffuse and
    specular light, and whether shadows are cast. :func:`render_camera` without a lighting uses
    :data:`_LIGHT_DIRECTION` and PyBullet's default coefficients, as every default don_gym render does."""

    direction_world: tuple[float, float, float] = _LIGHT_DIRECTION
    colour_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ambient: float = 0.6
    diffuse: float = 0.35
    specular: float = 0.05
    shadow: bool = False

    def camera_image_arguments(self) -> dict[str, Any]:
        """Keyword arguments of PyBullet's ``getCameraImage`` for this light."""
        return {
            "lightDirection": [float(v) for v in self.direction_world],
            "lightColor": [float(v) for v in self.colour_rgb],
            "lightAmbientCoeff": float(self.ambient),
            "lightDiffuseCoeff": float(self.diffuse),
            "lightSpecularCoeff": float(self.specular),
            "shadow": int(self.shadow),
        }


#: Lighting modes of recorded scenes: one fixed light, or :func:`random_lighting` per scene.
LIGHTING_MODES = ("fixed", "random")


def check_lighting_mode(lighting: str) -> str:
    if lighting not in LIGHTING_MODES:
        raise DonGymError(f"lighting={lighting!r}: expected one of {list(LIGHTING_MODES)}")
    return lighting


def random_lighting(rng: np.random.Generator) -> Lighting:
    """A light from any azimuth, 25-90 degrees above the horizon, slightly tinted, dim to bright, with
    shadows half of the time: the spread of a workshop's lamps and windows over a day."""
    azimuth, elevation = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(25, 90))
    direction = (np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation))
    return Lighting(
        direction_world=tuple(float(v) for v in direction),
        colour_rgb=tuple(float(v) for v in rng.uniform(0.8, 1.0, size=3)),
        ambient=float(rng.uniform(0.3, 0.8)),
        diffuse=float(rng.uniform(0.2, 0.7)),
        specular=float(rng.uniform(0.0, 0.5)),
        shadow=bool(rng.uniform() < 0.5),
    )


def look_at_camera_pose(eye_world: np.ndarray, target_world: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """(4, 4) OpenCV ``T_world_camera`` at ``eye_world`` looking at ``target_world``.

    With zero roll the image's "up" (-y) points as close to world +z as possible; ``roll_rad``
    rotates the camera about its optical axis.
    """
    z_axis = np.asarray(target_world, float) - np.asarray(eye_world, float)
    z_axis /= np.linalg.norm(z_axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z_axis[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
    x_axis = np.cross(z_axis, helper)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    R = np.stack([x_axis, y_axis, z_axis], axis=1) @ Rotation.from_euler("z", roll_rad).as_matrix()
    return make_transform(R, eye_world)


def check_renderer(renderer: str) -> str:
    if renderer not in RENDERERS:
        raise DonGymError(f"renderer={renderer!r} is unknown; expected one of {list(RENDERERS)}")
    return renderer


def projection_matrix_gl(
    intrinsics: CameraIntrinsics, near_m: float, far_m: float, renderer: str = "tiny"
) -> np.ndarray:
    """(4, 4) OpenGL projection matrix for pinhole ``intrinsics`` and clip planes in metres.

    The principal point is offset so that a point rendered here lands on the pixel that
    :func:`don_gym.geometry.project_points` predicts (pixel centres at integer coordinates).
    The offset depends on the renderer and was measured against Embree ray casting through
    pixel centres (:mod:`don_gym.data.render`): the EGL plugin follows OpenGL, whose NDC spans pixel
    edges, so it needs ``(+0.5, +0.5)``; TinyRenderer rasterises rows from the bottom and needs
    ``(0, +1)``. With these, object masks agree at IoU 0.99-1.0 and depth to 0.02 mm; with the
    other renderer's offset only at 0.89-0.95. ``tests/test_render.py`` and
    ``tests/test_dataset.py`` check the agreement.
    """
    if not (0.0 < near_m < far_m):
        raise DonGymError(f"camera clip planes must satisfy 0 < near < far, got near={near_m}, far={far_m}")
    W, H = float(intrinsics.width), float(intrinsics.height)
    offset_u, offset_v = _PRINCIPAL_POINT_OFFSET_PX[check_renderer(renderer)]
    cx, cy = intrinsics.cx + offset_u, intrinsics.cy + offset_v
    n, f = float(near_m), float(far_m)
    return np.array(
        [
            [2.0 * intrinsics.fx / W, 0.0, 1.0 - 2.0 * cx / W, 0.0],
            [0.0, 2.0 * intrinsics.fy / H, 2.0 * cy / H - 1.0, 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2.0 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


def view_matrix_gl(T_world_camera: np.ndarray) -> np.ndarray:
    """(4, 4) OpenGL view matrix (world -> OpenGL camera) for an OpenCV camera pose."""
    return invert_transform(np.asarray(T_world_camera, dtype=np.float64) @ _T_CV_GL)


def _gl_list(M: np.ndarray) -> list[float]:
    # PyBullet takes OpenGL matrices as 16 floats in column-major order.
    return [float(x) for x in np.asarray(M, dtype=np.float64).T.reshape(16)]


def depth_from_zbuffer(zbuffer: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """Metric z-depth (float32, metres) from OpenGL depth-buffer values in [0, 1].

    Pixels at the far plane (nothing hit) get 0, the "no return" value of a depth sensor.
    """
    zbuffer = np.asarray(zbuffer, dtype=np.float64)
    depth = far_m * near_m / (far_m - (far_m - near_m) * zbuffer)
    depth[zbuffer >= 1.0 - 1e-7] = 0.0
    return depth.astype(np.float32)


def render_camera(
    client,
    intrinsics: CameraIntrinsics,
    T_world_camera: np.ndarray,
    near_m: float = 0.05,
    far_m: float = 3.0,
    renderer: str = "tiny",
    lighting: Lighting | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render RGB, ideal metric depth and segmentation from a pinhole camera.

    Args:
        client: a ``pybullet_utils.bullet_client.BulletClient`` (or anything with PyBullet's
            ``getCameraImage``); for ``renderer="egl"`` the eglRenderer plugin must be loaded
            on it (see :class:`don_gym.sim.bullet.Bullet`), otherwise PyBullet silently uses
            TinyRenderer.
        intrinsics: pinhole intrinsics; the image is ``intrinsics.width`` x ``intrinsics.height``.
        T_world_camera: (4, 4) OpenCV camera pose (x right, y down, z forward) in the world.
        near_m, far_m: clip planes in metres; surfaces beyond ``far_m`` read as depth 0.
        renderer: ``"tiny"``, ``"egl"`` or ``"pbr"`` (``client`` made by a ``Bullet(renderer="pbr")``:
            TinyRenderer's depth and segmentation, path-traced RGB).
        lighting: the light (:class:`Lighting`); None, the fixed default light.

    Returns:
        ``rgb`` (H, W, 3) uint8, ``depth_m`` (H, W) float32 z-depth along the optical axis in
        metres (0 = nothing hit), ``segmentation`` (H, W) int32 PyBullet values with
        ``ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX``: -1 for background, otherwise
        ``body_id + ((link_index + 1) << 24)`` (see :func:`decode_segmentation`).
    """
    check_renderer(renderer)
    pbr = getattr(client, "pbr", None) if renderer == "pbr" else None
    if renderer == "pbr" and pbr is None:
        raise DonGymError("renderer='pbr' needs a client made by don_gym.sim.bullet.Bullet(renderer='pbr')")
    W, H = intrinsics.width, intrinsics.height
    _, _, rgba, zbuffer, seg = client.getCameraImage(
        W,
        H,
        viewMatrix=_gl_list(view_matrix_gl(T_world_camera)),
        projectionMatrix=_gl_list(projection_matrix_gl(intrinsics, near_m, far_m, renderer)),
        **(
            lighting.camera_image_arguments()
            if lighting is not None
            else {"lightDirection": _LIGHT_DIRECTION, "shadow": 0}
        ),
        flags=p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
        renderer=p.ER_BULLET_HARDWARE_OPENGL if renderer == "egl" else p.ER_TINY_RENDERER,
    )
    if pbr is not None:
        rgb = pbr.render(client, intrinsics, T_world_camera, lighting)
    else:
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(H, W, 4)[:, :, :3].copy()
    depth_m = depth_from_zbuffer(np.asarray(zbuffer, dtype=np.float32).reshape(H, W), near_m, far_m)
    segmentation = np.asarray(seg, dtype=np.int32).reshape(H, W)
    return rgb, depth_m, segmentation


def decode_segmentation(segmentation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split PyBullet segmentation values into ``(body_id, link_index)`` int32 arrays.

    Background pixels (-1) give body id -1 and link index -2.
    """
    segmentation = np.asarray(segmentation, dtype=np.int64)
    background = segmentation < 0
    body_id = np.where(background, -1, segmentation & _BODY_ID_MASK).astype(np.int32)
    link_index = np.where(background, -2, (segmentation >> 24) - 1).astype(np.int32)
    return body_id, link_index


def body_mask(segmentation: np.ndarray, body_id: int) -> np.ndarray:
    """(H, W) bool mask of the pixels showing body ``body_id`` (any of its links)."""
    return decode_segmentation(segmentation)[0] == int(body_id)


def specular_map(segmentation: np.ndarray, specular_by_body: dict[int, float]) -> np.ndarray:
    """(H, W) float32 specularity in [0, 1] per pixel, for the depth-sensor model.

    Pixels of a body listed in ``specular_by_body`` get its value, all others 0 (the table,
    the robot and the fixture are treated as matte).
    """
    body_id = decode_segmentation(segmentation)[0]
    out = np.zeros(body_id.shape, dtype=np.float32)
    for body, value in specular_by_body.items():
        out[body_id == int(body)] = float(np.clip(value, 0.0, 1.0))
    return out
