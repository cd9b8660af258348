"""Rigid transforms, quaternions and pinhole cameras as plain functions on arrays.

Conventions used everywhere in don_gym: ``T_a_b`` (4, 4) maps points in frame ``b`` into frame ``a``
(``p_a = T_a_b @ p_b``; ``T_world_camera`` is the camera pose); camera frames follow OpenCV (x right,
y down, z forward, metres); quaternions are ``(x, y, z, w)``, PyBullet's order, unless a name says
``wxyz``; pixels are ``(u, v)`` = (column, row), pixel ``(u, v)`` covering ``[u - 0.5, u + 0.5)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError

# RealSense D435 colour stream at 640x480 (typical factory calibration): focal lengths
# in pixels and principal point. Used by CameraIntrinsics.d435 and scaled to other
# image sizes.
D435_FX_640 = 615.0
D435_FY_640 = 615.0
D435_CX_640 = 320.0
D435_CY_640 = 240.0


def make_transform(rotation: np.ndarray | None = None, translation: np.ndarray | None = None) -> np.ndarray:
    """Build a (4, 4) float64 transform from a (3, 3) rotation and a (3,) translation (metres)."""
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, dtype=np.float64)
    if translation is not None:
        T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, computed without a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    inverse = np.eye(4)
    inverse[:3, :3] = R.T
    inverse[:3, 3] = -R.T @ T[:3, 3]
    return inverse


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points of shape (..., 3); returns the same shape."""
    points = np.asarray(points, dtype=np.float64)
    return points @ np.asarray(T[:3, :3]).T + np.asarray(T[:3, 3])


def transform_from_pose(position: np.ndarray, quaternion_xyzw: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a position (3,) in metres and a quaternion (x, y, z, w)."""
    return make_transform(Rotation.from_quat(np.asarray(quaternion_xyzw, dtype=np.float64)).as_matrix(), position)


def pose_from_transform(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`transform_from_pose`: (position (3,), quaternion (x, y, z, w))."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def rotation_angle_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in radians of the relative rotation between two (3, 3) rotations."""
    cos_angle = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(cos_angle, -1.0, 1.0)))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest (3, 3) rotation taking direction ``a`` onto direction ``b``."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin_angle = np.linalg.norm(axis)
    cos_angle = float(np.dot(a, b))
    if sin_angle < 1e-12:
        if cos_angle > 0:
            return np.eye(3)
        # Antiparallel: rotate by pi about any axis orthogonal to a.
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(a, helper)
        return Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)).as_matrix()
    return Rotation.from_rotvec(axis / sin_angle * np.arctan2(sin_angle, cos_angle)).as_matrix()


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def d435(cls, width: int = 640, height: int = 480) -> CameraIntrinsics:
        """RealSense-D435-like colour intrinsics scaled to ``width`` x ``height``.

        The 640x480 calibration is scaled by ``width / 640`` horizontally and
        ``height / 480`` vertically, with the principal point kept at the same
        relative position (pixel-centre convention).
        """
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        sx, sy = width / 640.0, height / 480.0
        return cls(
            fx=D435_FX_640 * sx,
            fy=D435_FY_640 * sy,
            cx=(D435_CX_640 + 0.5) * sx - 0.5,
            cy=(D435_CY_640 + 0.5) * sy - 0.5,
            width=int(width),
            height=int(height),
        )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def as_array(self) -> np.ndarray:
        """(6,) float64 ``[fx, fy, cx, cy, width, height]``, for observations and files."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.width, self.height], dtype=np.float64)

    @classmethod
    def from_array(cls, values: np.ndarray) -> CameraIntrinsics:
        fx, fy, cx, cy, width, height = (float(v) for v in np.asarray(values).reshape(6))
        return cls(fx, fy, cx, cy, int(round(width)), int(round(height)))

    def window(self, origin_px: tuple[int, int], width: int, height: int) -> CameraIntrinsics:
        """The intrinsics of the ``width`` x ``height`` window of this image whose top-left pixel is
        ``origin_px`` = (u0, v0): the same focal lengths, the principal point shifted by the origin, so that a
        camera rendered at them sees the pixels ``[v0:v0 + height, u0:u0 + width]`` of the full image at its
        scale. The window must lie inside the image (DonGymError otherwise)."""
        u0, v0 = (int(v) for v in origin_px)
        if not (1 <= width <= self.width and 1 <= height <= self.height):
            raise DonGymError(
                f"window of {width}x{height} px: larger than the {self.width}x{self.height} frame; expected at most "
                "the frame's size"
            )
        if not (0 <= u0 <= self.width - width and 0 <= v0 <= self.height - height):
            raise DonGymError(
                f"window origin {(u0, v0)}: a {width}x{height} window leaves the {self.width}x{self.height} frame"
            )
        return CameraIntrinsics(self.fx, self.fy, self.cx - u0, self.cy - v0, int(width), int(height))


def window_origin_px(frame: CameraIntrinsics, window: CameraIntrinsics) -> tuple[int, int]:
    """(u0, v0): the full frame's pixel at a window's top-left pixel, for a window made by
    :meth:`CameraIntrinsics.window` (its principal point shifted by whole pixels)."""
    return int(round(frame.cx - window.cx)), int(round(frame.cy - window.cy))


def image_window(frame: CameraIntrinsics, centre_uv: np.ndarray | None, size_px: int) -> CameraIntrinsics:
    """The ``size_px`` x ``size_px`` window of ``frame`` (:meth:`CameraIntrinsics.window`) centred as near as
    the frame allows on ``centre_uv`` (u, v) pixels (None or not finite: the frame's centre); a window larger
    than the frame is a DonGymError."""
    size = int(size_px)
    if size > frame.width or size > frame.height or size < 1:
        raise DonGymError(
            f"window_px={size_px!r}: larger than the {frame.width}x{frame.height} frame; expected 1.."
            f"{min(frame.width, frame.height)} pixels"
        )
    centre = np.array([(frame.width - 1) / 2, (frame.height - 1) / 2])
    if centre_uv is not None and np.all(np.isfinite(np.asarray(centre_uv, dtype=np.float64))):
        centre = np.asarray(centre_uv, dtype=np.float64).reshape(2)
    u0 = int(np.clip(np.round(centre[0] - (size - 1) / 2), 0, frame.width - size))
    v0 = int(np.clip(np.round(centre[1] - (size - 1) / 2), 0, frame.height - size))
    return frame.window((u0, v0), size, size)


def project_points(intrinsics: CameraIntrinsics, points_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera-frame points to pixels.

    Returns ``(uv, z)``: (N, 2) float64 pixel coordinates (u = column, v = row) and the
    (N,) depth in metres. Points with ``z <= 0`` get NaN pixel coordinates.
    """
    points_camera = np.asarray(points_camera, dtype=np.float64).reshape(-1, 3)
    z = points_camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * points_camera[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * points_camera[:, 1] / z + intrinsics.cy
    uv = np.stack([u, v], axis=1)
    uv[z <= 0] = np.nan
    return uv, z


def pixel_rays(intrinsics: CameraIntrinsics, uv: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame ray directions with z = 1 through pixel coordinates (N, 2)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    return np.stack(
        [(uv[:, 0] - intrinsics.cx) / intrinsics.fx, (uv[:, 1] - intrinsics.cy) / intrinsics.fy, np.ones(len(uv))],
        axis=1,
    )


def backproject_depth(intrinsics: CameraIntrinsics, depth_m: np.ndarray, uv: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame 3D points (metres) from a depth image.

    ``depth_m`` is (H, W) z-depth in metres (0 = no return). With ``uv`` (N, 2) integer
    pixel coordinates, returns (N, 3) for those pixels; otherwise (H, W, 3) for all.
    Pixels without depth give points with z = 0.
    """
    depth_m = np.asarray(depth_m, dtype=np.float64)
    if uv is None:
        v, u = np.mgrid[0 : depth_m.shape[0], 0 : depth_m.shape[1]]
        uv_all = np.stack([u.ravel(), v.ravel()], axis=1)
        z = depth_m.ravel()
        return (pixel_rays(intrinsics, uv_all) * z[:, None]).reshape(depth_m.shape + (3,))
    uv = np.asarray(uv).reshape(-1, 2)
    z = depth_m[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    return pixel_rays(intrinsics, uv) * z[:, None]
