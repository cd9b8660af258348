"""Depth fusion of a scene: a TSDF volume, depth re-rendering and object masks from the fused model.

The original DON pipeline's depth preprocessing for self-supervised training (docs/background.md,
section "TSDF fusion"): :func:`fuse_scene` builds a :class:`TSDFVolume`, :func:`fused_object_masks`
re-renders its depth per frame and takes the object masks from it. Vectorised numpy throughout.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.ndimage import binary_dilation
from tqdm import tqdm

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, invert_transform, pixel_rays, transform_points

__all__ = [
    "MAX_VOXELS",
    "ObjectRegion",
    "TSDFVolume",
    "fuse_scene",
    "fused_object_masks",
    "object_mask_from_depth",
    "render_fused_depths",
]

#: Largest volume accepted, in voxels: two float32 grids of this size are 512 MB.
MAX_VOXELS = 64_000_000

#: Voxels handled per vectorised chunk in :meth:`TSDFVolume.integrate`: big enough to amortise
#: Python overhead, small enough that the temporaries (~10 arrays) stay in cache-friendly sizes.
_INTEGRATE_CHUNK_VOXELS = 1 << 16

#: Coarse ray-marching samples evaluated per ray per vectorised block in ``render_depth``.
_MARCH_BLOCK_STEPS = 8

#: Edge in voxels of the blocks used to skip empty space when rendering.
_SKIP_BLOCK_VOXELS = 8

#: Object regions: a predicate on (N, 3) world points, or a box (T_world_box (4, 4), half_extents_m (3,)).
ObjectRegion = Callable[[np.ndarray], np.ndarray] | tuple[np.ndarray, np.ndarray]


def _as_transform(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise DonGymError(f"{name} must be a finite (4, 4) transform, got shape {T.shape}")
    return T


def _as_depth(depth_m: np.ndarray, intrinsics: CameraIntrinsics, name: str = "depth_m") -> np.ndarray:
    depth = np.asarray(depth_m, dtype=np.float32)
    expected = (intrinsics.height, intrinsics.width)
    if depth.shape != expected:
        raise DonGymError(f"{name} has shape {depth.shape}, expected (H, W) = {expected} from the intrinsics")
    if not np.isfinite(depth).all() or depth.min(initial=0.0) < 0:
        raise DonGymError(f"{name} must be finite and >= 0 (metres, 0 = no return)")
    return depth


def _any_per_row(flags: np.ndarray) -> np.ndarray:
    """``flags.any(axis=1)`` for a C-contiguous (M, 8) bool array, read as one uint64 per row (much faster)."""
    if flags.shape[1] == 8 and flags.flags.c_contiguous:
        return flags.view(np.uint64)[:, 0] != 0
    return flags.any(axis=1)


class TSDFVolume:
    """A dense TSDF voxel grid over the world-frame box ``[bounds_min, bounds_max]``.

    Each voxel stores the projective signed distance to the surface along the camera's optical
    axis, truncated to ``[-truncation_m, truncation_m]`` and divided by it (positive in front of
    the surface), and the accumulated weight.

    Args:
        bounds_min, bounds_max: (3,) corners of the volume in world metres.
        voxel_size_m: edge of a voxel in metres.
        truncation_m: truncation distance in metres; defaults to 4 voxels. It must exceed
            one voxel and should be at least ~3 times the depth noise std (a D435 at 0.7 m
            has 1.3 mm at 640x480 but 5 mm at 160x120, see ``don_gym.sim.sensor``).
        max_weight: cap on the accumulated weight per voxel (``inf`` = plain average).

    Attributes:
        tsdf: (nx, ny, nz) float32 truncated signed distance / truncation_m, in [-1, 1].
        weight: (nx, ny, nz) float32 accumulated weight, 0 = unobserved.
        origin: (3,) world position of the corner ``bounds_min``; voxel (i, j, k) has its
            centre at ``origin + (i, j, k) * voxel_size_m + voxel_size_m / 2``.

    Change ``tsdf`` and ``weight`` only through :meth:`integrate`: rendering caches what it
    derives from them until the next integration.
    """

    def __init__(
        self,
        bounds_min: np.ndarray,
        bounds_max: np.ndarray,
        voxel_size_m: float,
        truncation_m: float | None = None,
        max_weight: float = float("inf"),
    ) -> None:
        lo = np.asarray(bounds_min, dtype=np.float64).reshape(-1)
        hi = np.asarray(bounds_max, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise DonGymError(f"TSDF bounds must be finite (3,) points, got {lo} and {hi}")
        if not np.all(hi > lo):
            raise DonGymError(f"TSDF bounds_max {hi} must exceed bounds_min {lo} on every axis")
        if not voxel_size_m > 0:
            raise DonGymError(f"voxel_size_m must be > 0, got {voxel_size_m}")
        truncation_m = 4.0 * voxel_size_m if truncation_m is None else float(truncation_m)
        if not truncation_m > voxel_size_m:
            raise DonGymError(f"truncation_m ({truncation_m}) must exceed voxel_size_m ({voxel_size_m})")
        if not max_weight > 0:
            raise DonGymError(f"max_weight must be > 0, got {max_weight}")
        shape = tuple(int(n) for n in np.ceil((hi - lo) / voxel_size_m - 1e-9))
        if int(np.prod(shape)) > MAX_VOXELS:
            raise DonGymError(
                f"TSDF volume of {shape} voxels ({np.prod(shape):.3g}) exceeds {MAX_VOXELS:.3g}: "
                f"use larger voxels than {voxel_size_m} m or a smaller workspace"
            )
        self.origin = lo
        self.voxel_size_m = float(voxel_size_m)
        self.truncation_m = truncation_m
        self.max_weight = float(max_weight)
        self.shape = shape
        self.tsdf = np.zeros(shape, np.float32)
        self.weight = np.zeros(shape, np.float32)
        # Bumped by integrate(); render_depth caches what it derives from the grids per version.
        self._version = 0
        self._blocks_cache: tuple[int, np.ndarray, tuple[int, int, int]] | None = None
        self._field_cache: tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    @property
    def bounds_max(self) -> np.ndarray:
        """(3,) world corner opposite ``origin`` (``bounds_max`` rounded up to whole voxels)."""
        return self.origin + np.asarray(self.shape) * self.voxel_size_m

    def _axis_centres(self, axis: int) -> np.ndarray:
        return self.origin[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_size_m

    def integrate(
        self,
        depth_m: np.ndarray,
        intrinsics: CameraIntrinsics,
        T_world_camera: np.ndarray,
        weight: float = 1.0,
    ) -> None:
        """Fuse one (H, W) depth image (metres, 0 = no return) seen from ``T_world_camera``.

        Every voxel centre is projected into the image (nearest pixel). Voxels with a
        depth reading whose signed distance ``sdf = depth - z_voxel`` is above
        ``-truncation_m`` are updated with ``min(sdf / truncation_m, 1)`` by a weighted
        running average, which also carves free space in front of the surface.
        """
        depth = _as_depth(depth_m, intrinsics)
        T_camera_world = invert_transform(_as_transform(T_world_camera, "T_world_camera"))
        if not weight > 0:
            raise DonGymError(f"integration weight must be > 0, got {weight}")
        height, width = depth.shape
        self._version += 1
        # A one-pixel border of zeros: voxels projecting outside the image are clipped onto it
        # and read "no return", which is cheaper than testing the image bounds.
        padded = np.zeros((height + 2, width + 2), np.float32)
        padded[1:-1, 1:-1] = depth
        depth_flat = padded.reshape(-1)

        # Rows of P = K' [R | t] give (z * (u + 1.5), z * (v + 1.5), z) for a world point: the
        # 0.5 turns truncation into rounding to the nearest pixel and the 1 is the border, so
        # that astype(int) (truncation toward zero) is exact for every in-image coordinate.
        K_shifted = np.array(
            [
                [intrinsics.fx, 0.0, intrinsics.cx + 1.5],
                [0.0, intrinsics.fy, intrinsics.cy + 1.5],
                [0.0, 0.0, 1.0],
            ]
        )
        P = K_shifted @ T_camera_world[:3, :]
        xs, ys, zs = (self._axis_centres(a) for a in range(3))
        # Affine in each axis: row r of P applied to (x, y, z) = P[r,0] x + P[r,1] y + P[r,2] z + P[r,3].
        yz_terms = [(P[r, 1] * ys[:, None] + P[r, 2] * zs[None, :] + P[r, 3]).astype(np.float32) for r in range(3)]
        x_terms = [(P[r, 0] * xs).astype(np.float32) for r in range(3)]

        nx, ny, nz = self.shape
        slab = max(1, _INTEGRATE_CHUNK_VOXELS // (ny * nz))
        trunc = np.float32(self.truncation_m)
        tsdf_flat = self.tsdf.reshape(-1)
        weight_flat = self.weight.reshape(-1)
        for i0 in range(0, nx, slab):
            i1 = min(nx, i0 + slab)
            if not self._slab_visible(P, xs[i0], xs[i1 - 1], ys, zs, width, height):
                continue
            z = x_terms[2][i0:i1, None, None] + yz_terms[2][None]
            with np.errstate(divide="ignore", invalid="ignore"):
                inv_z = np.float32(1.0) / z
                u = x_terms[0][i0:i1, None, None] + yz_terms[0][None]
                u *= inv_z
                v = x_terms[1][i0:i1, None, None] + yz_terms[1][None]
                v *= inv_z
                # Out-of-range (and NaN, from voxels on the camera plane) casts end up on the border.
                pixel = np.clip(v.astype(np.int32), 0, height + 1)
                pixel *= width + 2
                pixel += np.clip(u.astype(np.int32), 0, width + 1)
            observed_depth = depth_flat[pixel]
            sdf = observed_depth - z
            # Voxels behind the camera can project into the image too: keep only those in front.
            update = observed_depth > 0
            update &= sdf >= -trunc
            update &= z > 1e-6
            idx = np.flatnonzero(update)
            if idx.size == 0:
                continue
            new_value = np.minimum(sdf.reshape(-1)[idx] / trunc, np.float32(1.0))
            idx += i0 * ny * nz
            w_old = weight_flat[idx]
            w_new = w_old + np.float32(weight)
            tsdf_flat[idx] = (tsdf_flat[idx] * w_old + new_value * np.float32(weight)) / w_new
            weight_flat[idx] = np.minimum(w_new, np.float32(self.max_weight))

    def _slab_visible(
        self, P: np.ndarray, x0: float, x1: float, ys: np.ndarray, zs: np.ndarray, width: int, height: int
    ) -> bool:
        """False only if the slab's voxel centres certainly all project outside the image."""
        corners = np.array([[x, y, z, 1.0] for x in (x0, x1) for y in (ys[0], ys[-1]) for z in (zs[0], zs[-1])])
        projected = corners @ P.T
        z = projected[:, 2]
        if np.all(z <= 1e-6):
            return False
        if np.any(z <= 1e-6):
            return True  # Straddles the camera plane: projection of the box is unbounded.
        u1, v1 = projected[:, 0] / z, projected[:, 1] / z
        # The projection of a box in front of the camera lies in the hull of its projected corners.
        return not (u1.max() < 1 or u1.min() >= width + 1 or v1.max() < 1 or v1.min() >= height + 1)

    def field(self) -> np.ndarray:
        """(nx, ny, nz) float32 TSDF with NaN where unobserved."""
        return np.where(self.weight > 0, self.tsdf, np.float32(np.nan))

    def _padded_field(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The TSDF with a one-voxel unobserved border, flattened, for ray marching.

        Returns ``(values, pairs, strides)``: values (N,) float32 with NaN where unobserved
        (rounding just outside the volume reads "unobserved"); pairs (N,) complex64 holding
        ``tsdf * observed + 1j * observed``, so that one gather and one weighted sum give
        both the numerator and the normaliser of a NaN-free trilinear interpolation (numpy
        gathers a 1-D complex array several times faster than rows of a 2-D one); and the
        int32 strides of the padded (nx + 2, ny + 2, nz + 2) grid. Cached until the next
        :meth:`integrate`.
        """
        if self._field_cache is not None and self._field_cache[0] == self._version:
            return self._field_cache[1]
        nx, ny, nz = self.shape
        values = np.full((nx + 2, ny + 2, nz + 2), np.nan, np.float32)
        np.copyto(values[1:-1, 1:-1, 1:-1], self.tsdf, where=self.weight > 0)
        values = values.reshape(-1)
        observed = np.isfinite(values)
        pairs = np.where(observed, values, np.float32(0.0)) + 1j * observed.astype(np.float32)
        result = (values, pairs.astype(np.complex64), np.array([(ny + 2) * (nz + 2), nz + 2, 1], dtype=np.int32))
        self._field_cache = (self._version, result)
        return result

    def _flagged_blocks(self) -> tuple[np.ndarray, tuple[int, int, int]]:
        """Flat bool grid of blocks that hold, or neighbour a block that holds, an observed negative voxel."""
        if self._blocks_cache is not None and self._blocks_cache[0] == self._version:
            return self._blocks_cache[1], self._blocks_cache[2]
        B = _SKIP_BLOCK_VOXELS
        counts = tuple(-(-n // B) for n in self.shape)
        padded = np.zeros([c * B for c in counts], dtype=bool)
        np.less(self.tsdf, 0, out=padded[: self.shape[0], : self.shape[1], : self.shape[2]], where=self.weight > 0)
        blocks = padded.reshape(counts[0], B, counts[1], B, counts[2], B).any(axis=(1, 3, 5))
        flagged = binary_dilation(blocks, structure=np.ones((3, 3, 3), dtype=bool)).reshape(-1)
        self._blocks_cache = (self._version, flagged, counts)
        return flagged, counts

    @staticmethod
    def _sample_nearest(
        flat: np.ndarray, strides: np.ndarray, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray
    ) -> np.ndarray:
        """Values of the nearest voxels at ``origin + t * dirs`` (padded grid units); t (m, K), dirs (m, 3)."""
        index = np.rint(t * dirs[:, 0:1] + origin[0]).astype(np.int32) * strides[0]
        index += np.rint(t * dirs[:, 1:2] + origin[1]).astype(np.int32) * strides[1]
        index += np.rint(t * dirs[:, 2:3] + origin[2]).astype(np.int32)
        return flat[index]

    def _sample_trilinear(self, pairs: np.ndarray, strides: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of the padded field at (M, 3) padded grid coordinates.

        Unobserved corners are left out and the remaining weights renormalised (see
        :meth:`_padded_field`), so values near the edge of the observed region stay
        defined; NaN where all 8 corners are unobserved.
        """
        points = np.maximum(points, 0.0)
        np.minimum(points, np.asarray(self.shape, dtype=np.float64) + 1.0 - 1e-4, out=points)
        base = np.floor(points).astype(np.int32)
        frac = (points - base).astype(np.float32)
        corners = np.array([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], dtype=np.int32)
        corner_pairs = np.take(pairs, (base @ strides)[:, None] + corners @ strides)  # (M, 8)
        wx, wy, wz = (np.stack([1.0 - frac[:, a], frac[:, a]], axis=1) for a in range(3))
        weights = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
        summed = np.einsum("mc,mc->m", weights, corner_pairs)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(summed.imag > 1e-6, summed.real / summed.imag, np.nan)

    def render_depth(
        self, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray, step_fraction: float = 0.5
    ) -> np.ndarray:
        """(H, W) float32 z-depth (metres, 0 = no surface) of the fused surface seen from a camera.

        All pixel rays are marched together. Empty space is skipped first: rays advance in
        steps of ``_SKIP_BLOCK_VOXELS - 1`` voxels through a grid of blocks that flags the
        blocks near any observed negative TSDF value, and stop at the first flagged block.
        From there they march in steps of ``step_fraction * truncation_m`` sampling the
        nearest voxel; the first change from an observed positive to an observed negative
        value brackets the surface. The bracket is re-sampled with trilinear interpolation
        and the zero crossing found by linear interpolation and one regula-falsi step.
        """
        T_world_camera = _as_transform(T_world_camera, "T_world_camera")
        if not 0 < step_fraction <= 0.9:
            raise DonGymError(f"step_fraction must be in (0, 0.9], got {step_fraction}")
        height, width = intrinsics.height, intrinsics.width
        # Only pixels inside the volume's projected bounding box can see the fused surface;
        # a small volume (one object) then costs a fraction of the image.
        u0, u1, v0, v1 = self._projected_box(intrinsics, T_world_camera)
        if u0 > u1 or v0 > v1:
            return np.zeros((height, width), dtype=np.float32)
        v, u = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
        box_height, box_width = v.shape
        rays_camera = pixel_rays(intrinsics, np.stack([u.ravel(), v.ravel()], axis=1))
        # Camera-frame rays have z = 1, so the ray parameter t is the z-depth. Positions are
        # in padded grid units: voxel (i, j, k) has its centre at (i + 1, j + 1, k + 1).
        origin_grid = (T_world_camera[:3, 3] - self.origin) / self.voxel_size_m + 0.5
        dirs_grid = rays_camera @ T_world_camera[:3, :3].T / self.voxel_size_m
        # Column-wise: numpy reduces along a length-3 axis much slower than it combines columns.
        voxels_per_t = np.sqrt(dirs_grid[:, 0] ** 2 + dirs_grid[:, 1] ** 2 + dirs_grid[:, 2] ** 2)

        # Ray-box intersection (slab method) with the box of voxel centres, one axis at a time.
        t_enter = np.full(len(dirs_grid), 1e-3)
        t_exit = np.full(len(dirs_grid), np.inf)
        for axis in range(3):
            lo, hi, start, direction = 1.0, float(self.shape[axis]), origin_grid[axis], dirs_grid[:, axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                t_lo, t_hi = (lo - start) / direction, (hi - start) / direction
            parallel = np.abs(direction) < 1e-12
            inside_slab = lo <= start <= hi
            t_enter = np.maximum(
                t_enter, np.where(parallel, -np.inf if inside_slab else np.inf, np.minimum(t_lo, t_hi))
            )
            t_exit = np.minimum(t_exit, np.where(parallel, np.inf if inside_slab else -np.inf, np.maximum(t_lo, t_hi)))

        depth = np.zeros(box_height * box_width)
        rays = np.flatnonzero(t_exit > t_enter)
        rays, t_start = self._skip_empty_space(rays, origin_grid, dirs_grid, voxels_per_t, t_enter, t_exit)

        flat, pairs, strides = self._padded_field()
        origin32 = origin_grid.astype(np.float32)
        dirs32 = dirs_grid.astype(np.float32)
        step_t = (step_fraction * self.truncation_m / self.voxel_size_m / voxels_per_t).astype(np.float32)
        t_start = t_start.astype(np.float32)
        t_stop = t_exit.astype(np.float32)
        previous = np.full(rays.size, np.nan, np.float32)
        offsets = np.arange(_MARCH_BLOCK_STEPS, dtype=np.float32)
        k0 = 0
        while rays.size:
            t = t_start[:, None] + (k0 + offsets)[None, :] * step_t[rays, None]
            beyond = t > t_stop[rays, None]
            np.minimum(t, t_stop[rays, None], out=t)
            values = self._sample_nearest(flat, strides, origin32, dirs32[rays], t)
            values[beyond] = np.nan
            crossing = np.empty(values.shape, dtype=bool)
            np.greater(previous, 0, out=crossing[:, 0])
            np.greater(values[:, :-1], 0, out=crossing[:, 1:])
            crossing &= values < 0
            hit = _any_per_row(crossing)
            if hit.any():
                hit_rays = rays[hit]
                t1 = t_start[hit] + (k0 + crossing[hit].argmax(axis=1)) * step_t[hit_rays]
                t0 = t1 - step_t[hit_rays]
                depth[hit_rays] = self._refine_crossing(pairs, strides, origin_grid, dirs_grid[hit_rays], t0, t1)
            k0 += _MARCH_BLOCK_STEPS
            still = ~hit & (t_start + k0 * step_t[rays] <= t_stop[rays])
            rays, t_start, previous = rays[still], t_start[still], values[still, -1]
        image = np.zeros((height, width), dtype=np.float32)
        image[v0 : v1 + 1, u0 : u1 + 1] = depth.reshape(box_height, box_width)
        return image

    def _projected_box(self, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray) -> tuple[int, int, int, int]:
        """Inclusive pixel box ``(u0, u1, v0, v1)`` covering the volume's projection, clipped
        to the image (empty when u0 > u1); the whole image when the volume reaches behind the camera."""
        lo, hi = self.origin, self.bounds_max
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        corners_camera = transform_points(invert_transform(T_world_camera), corners)
        if np.any(corners_camera[:, 2] <= 1e-6):
            return 0, intrinsics.width - 1, 0, intrinsics.height - 1
        u = intrinsics.fx * corners_camera[:, 0] / corners_camera[:, 2] + intrinsics.cx
        v = intrinsics.fy * corners_camera[:, 1] / corners_camera[:, 2] + intrinsics.cy
        u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 1, intrinsics.width - 1)
        v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 1, intrinsics.height - 1)
        return u0, u1, v0, v1

    def _skip_empty_space(
        self,
        rays: np.ndarray,
        origin_grid: np.ndarray,
        dirs_grid: np.ndarray,
        voxels_per_t: np.ndarray,
        t_enter: np.ndarray,
        t_exit: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rays that reach a block near a surface, and the ray parameter to start marching at.

        Blocks are ``B = _SKIP_BLOCK_VOXELS`` voxels a side and flagged when they or a
        neighbour hold an observed negative voxel, so every point whose nearest voxel is
        negative has at least ``B - 0.5`` voxels of flagged space before it along any ray.
        Coarse samples ``B - 1`` voxels apart cannot jump over that, and marching from the
        sample before the first flagged one misses no sign change.
        """
        B = _SKIP_BLOCK_VOXELS
        flagged, (_, by, bz) = self._flagged_blocks()
        # Block of a padded grid position g: floor((g - 1 + 0.5) / B).
        origin_blocks = ((origin_grid - 0.5) / B).astype(np.float32)
        dirs_blocks = (dirs_grid / B).astype(np.float32)
        coarse_t = ((B - 1.0) / voxels_per_t).astype(np.float32)
        t_enter32, t_exit32 = t_enter.astype(np.float32), t_exit.astype(np.float32)
        t_start = np.full(rays.size, np.nan)
        pending = np.arange(rays.size)
        offsets = np.arange(_MARCH_BLOCK_STEPS, dtype=np.float32)
        k0 = 0
        while pending.size:
            r = rays[pending]
            t = t_enter32[r, None] + (k0 + offsets)[None, :] * coarse_t[r, None]
            beyond = t > t_exit32[r, None]
            np.minimum(t, t_exit32[r, None], out=t)
            index = np.floor(t * dirs_blocks[r, 0:1] + origin_blocks[0]).astype(np.int32) * (by * bz)
            index += np.floor(t * dirs_blocks[r, 1:2] + origin_blocks[1]).astype(np.int32) * bz
            index += np.floor(t * dirs_blocks[r, 2:3] + origin_blocks[2]).astype(np.int32)
            near_surface = flagged[np.clip(index, 0, flagged.size - 1)]
            # The sample clamped to the exit point still counts; later ones repeat it.
            near_surface[:, 1:] &= ~beyond[:, :-1]
            found = _any_per_row(near_surface)
            first = k0 + near_surface[found].argmax(axis=1)
            rf = r[found]
            t_start[pending[found]] = t_enter[rf] + np.maximum(first - 1, 0) * coarse_t[rf]
            k0 += _MARCH_BLOCK_STEPS
            still = ~found & ~beyond[:, -1]
            pending = pending[still]
        reached = np.isfinite(t_start)
        return rays[reached], t_start[reached]

    def _refine_crossing(
        self,
        pairs: np.ndarray,
        strides: np.ndarray,
        origin_grid: np.ndarray,
        dirs_grid: np.ndarray,
        t0: np.ndarray,
        t1: np.ndarray,
    ) -> np.ndarray:
        """Zero crossing of the trilinear TSDF near the coarse bracket [t0, t1] of each ray."""
        t0, t1 = t0.astype(np.float64), t1.astype(np.float64)
        step = t1 - t0

        def sample(t: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
            return self._sample_trilinear(pairs, strides, origin_grid + t[:, None] * dirs_grid[rows])

        a_t, b_t = t0.copy(), t1.copy()
        a_f, b_f = sample(a_t), sample(b_t)
        # The nearest-voxel bracket can be off by up to a voxel; where the trilinear values do
        # not bracket zero, move the bracket one step back (or forward) and sample once more.
        back = np.flatnonzero(~(a_f > 0))
        t_back = a_t[back] - step[back]
        f_back = sample(t_back, back)
        b_t[back], b_f[back] = a_t[back], a_f[back]
        a_t[back], a_f[back] = t_back, f_back
        forward = np.flatnonzero((a_f > 0) & (b_f > 0))
        t_forward = b_t[forward] + step[forward]
        a_t[forward], a_f[forward] = b_t[forward], b_f[forward]
        b_t[forward], b_f[forward] = t_forward, sample(t_forward, forward)
        found = (a_f > 0) & (b_f <= 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t_mid = np.where(found, a_t + a_f / (a_f - b_f) * (b_t - a_t), 0.5 * (t0 + t1))
            # One regula-falsi step: the TSDF is only piecewise linear along the ray.
            f_mid = sample(t_mid)
            upper = f_mid > 0
            a_t, a_f = np.where(upper, t_mid, a_t), np.where(upper, f_mid, a_f)
            b_t, b_f = np.where(upper, b_t, t_mid), np.where(upper, b_f, f_mid)
            t_refined = a_t + a_f / (a_f - b_f) * (b_t - a_t)
        # Without a trilinear sign change, the coarse bracket's midpoint is the best estimate.
        return np.where(found & np.isfinite(t_refined), t_refined, t_mid)

    def extract_points(self) -> np.ndarray:
        """(N, 3) world points on the fused surface: zero crossings between neighbouring voxels.

        For each pair of observed neighbours (along x, y and z) whose TSDF changes sign,
        the crossing is placed by linear interpolation. A point cloud, not a mesh (no
        marching cubes without scikit-image).
        """
        field = self.field()
        points = []
        centre = self.origin + 0.5 * self.voxel_size_m
        for axis in range(3):
            a = np.take(field, np.arange(field.shape[axis] - 1), axis=axis)
            b = np.take(field, np.arange(1, field.shape[axis]), axis=axis)
            sign_change = ((a > 0) & (b <= 0)) | ((a <= 0) & (b > 0))
            idx = np.argwhere(sign_change)
            if idx.size == 0:
                continue
            fa, fb = a[sign_change], b[sign_change]
            position = idx.astype(np.float64)
            position[:, axis] += fa / (fa - fb)
            points.append(centre + position * self.voxel_size_m)
        return np.concatenate(points) if points else np.zeros((0, 3))


def fuse_scene(
    depths_m: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics | Sequence[CameraIntrinsics],
    T_world_cameras: Sequence[np.ndarray],
    bounds: tuple[np.ndarray, np.ndarray] | np.ndarray,
    voxel_size_m: float = 0.003,
    truncation_m: float | None = None,
    weights: Sequence[float] | None = None,
    progress: bool = False,
) -> TSDFVolume:
    """Fuse all depth frames of a scene into a :class:`TSDFVolume`.

    Args:
        depths_m: (H, W) depth images in metres (0 = no return), e.g. sensor depth.
        intrinsics: one camera for all frames, or one per frame.
        T_world_cameras: (4, 4) camera poses, one per frame: the *reported* poses when
            the sensor has a calibration error, as a real pipeline would have.
        bounds: ``(bounds_min, bounds_max)`` world corners of the workspace, or a (2, 3) array.
        voxel_size_m: voxel edge; 3 mm gives 200 x 200 x 67 voxels for a 0.6 x 0.6 x 0.2 m
            workspace (2.7 M voxels, 22 MB).
        truncation_m: defaults to 4 voxels.
        weights: per-frame weights (default 1 each).
        progress: show a tqdm bar over frames.
    """
    if len(depths_m) != len(T_world_cameras):
        raise DonGymError(f"got {len(depths_m)} depth images but {len(T_world_cameras)} camera poses")
    if isinstance(intrinsics, CameraIntrinsics):
        intrinsics = [intrinsics] * len(depths_m)
    if len(intrinsics) != len(depths_m):
        raise DonGymError(f"got {len(depths_m)} depth images but {len(intrinsics)} intrinsics")
    weights = [1.0] * len(depths_m) if weights is None else list(weights)
    if len(weights) != len(depths_m):
        raise DonGymError(f"got {len(depths_m)} depth images but {len(weights)} weights")
    bounds = np.asarray(bounds, dtype=np.float64)
    if bounds.shape != (2, 3):
        raise DonGymError(f"bounds must be (bounds_min, bounds_max), two (3,) points; got shape {bounds.shape}")
    volume = TSDFVolume(bounds[0], bounds[1], voxel_size_m, truncation_m)
    frames = zip(depths_m, intrinsics, T_world_cameras, weights, strict=True)
    for depth, camera, T_world_camera, weight in tqdm(
        frames, total=len(depths_m), desc="TSDF fusion", disable=not progress, unit="frame"
    ):
        volume.integrate(depth, camera, T_world_camera, weight)
    return volume


def _region_predicate(
    object_region_world: ObjectRegion | None,
    object_center_world: np.ndarray | None,
    object_radius_m: float | None,
    margin_m: float,
) -> Callable[[np.ndarray], np.ndarray]:
    """One predicate on (N, 3) world points from the ways a caller may describe the object's region."""
    sphere = object_center_world is not None or object_radius_m is not None
    if (object_region_world is None) == (not sphere):
        raise DonGymError(
            "give the object's region either as object_region_world (a predicate on (N, 3) world points or "
            "(T_world_box, half_extents_m)) or as object_center_world and object_radius_m, not both"
        )
    if not margin_m >= 0:
        raise DonGymError(f"margin_m must be >= 0, got {margin_m}")
    if sphere:
        if object_center_world is None or object_radius_m is None or not object_radius_m > 0:
            raise DonGymError("a spherical object region needs object_center_world (3,) and object_radius_m > 0")
        centre = np.asarray(object_center_world, dtype=np.float64).reshape(3)
        radius = float(object_radius_m) + margin_m

        def in_sphere(points_world: np.ndarray) -> np.ndarray:
            return np.sum((points_world - centre) ** 2, axis=-1) <= radius**2

        return in_sphere
    if callable(object_region_world):
        return object_region_world
    try:
        T_world_box, half_extents = object_region_world
    except (TypeError, ValueError) as error:
        raise DonGymError(
            "object_region_world must be a predicate on (N, 3) world points or (T_world_box, half_extents_m)"
        ) from error
    T_box_world = invert_transform(_as_transform(T_world_box, "T_world_box"))
    half = np.asarray(half_extents, dtype=np.float64).reshape(-1)
    if half.shape != (3,) or np.any(half < 0):
        raise DonGymError(f"box half_extents_m must be three non-negative lengths, got {half_extents}")
    limit = half + margin_m

    def in_box(points_world: np.ndarray) -> np.ndarray:
        return np.all(np.abs(transform_points(T_box_world, points_world)) <= limit, axis=-1)

    return in_box


def object_mask_from_depth(
    depth_m: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_world_camera: np.ndarray,
    object_region_world: ObjectRegion | None = None,
    *,
    object_center_world: np.ndarray | None = None,
    object_radius_m: float | None = None,
    margin_m: float = 0.0,
    table_height_m: float | None = None,
    min_height_above_table_m: float = 0.004,
) -> np.ndarray:
    """(H, W) bool mask of pixels whose 3D point lies in the object's region of the world.

    As the original pipeline crops the fused model to the object: a pixel is on the object
    when it has depth, its back-projected world point is inside the region and, when
    ``table_height_m`` is given, more than ``min_height_above_table_m`` above the table
    plane ``z = table_height_m`` (world z up), which removes the table inside the region.

    The region is either ``object_region_world`` (a predicate on (N, 3) world points, or a
    box ``(T_world_box, half_extents_m)``) or a sphere ``object_center_world`` (3,) with
    ``object_radius_m``. Boxes and spheres are grown by ``margin_m`` (e.g. a box fitted
    tightly to the object needs ~1 cm, as the fused surface is smoothed at the edges).
    """
    depth = _as_depth(depth_m, intrinsics)
    T_world_camera = _as_transform(T_world_camera, "T_world_camera")
    inside = _region_predicate(object_region_world, object_center_world, object_radius_m, margin_m)
    valid = depth > 0
    uv = np.argwhere(valid)[:, ::-1]
    points_world = transform_points(T_world_camera, backproject_depth(intrinsics, depth, uv))
    keep = np.asarray(inside(points_world), dtype=bool)
    if table_height_m is not None:
        keep &= points_world[:, 2] > table_height_m + min_height_above_table_m
    mask = np.zeros(depth.shape, dtype=bool)
    mask[uv[keep, 1], uv[keep, 0]] = True
    return mask


def fused_object_masks(
    volume: TSDFVolume,
    intrinsics: CameraIntrinsics,
    T_world_cameras: Sequence[np.ndarray],
    object_region_world: ObjectRegion | None = None,
    *,
    object_center_world: np.ndarray | None = None,
    object_radius_m: float | None = None,
    margin_m: float = 0.0,
    table_height_m: float | None = None,
    min_height_above_table_m: float = 0.004,
    depths_m: Sequence[np.ndarray] | None = None,
    progress: bool = False,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Depth re-rendered from the fused model for each camera, and the object masks from it.

    Returns ``(depths, masks)``: (H, W) float32 metres and (H, W) bool per camera pose. The
    region arguments are those of :func:`object_mask_from_depth`. ``depths_m``, when given,
    are depths already rendered from ``volume`` for these cameras (:func:`render_fused_depths`).
    """
    if depths_m is None:
        depths_m = render_fused_depths(volume, intrinsics, T_world_cameras, progress=progress)
    if len(depths_m) != len(T_world_cameras):
        raise DonGymError(f"got {len(depths_m)} depth images but {len(T_world_cameras)} camera poses")
    masks = [
        object_mask_from_depth(
            depth,
            intrinsics,
            T,
            object_region_world,
            object_center_world=object_center_world,
            object_radius_m=object_radius_m,
            margin_m=margin_m,
            table_height_m=table_height_m,
            min_height_above_table_m=min_height_above_table_m,
        )
        for depth, T in zip(depths_m, T_world_cameras, strict=True)
    ]
    return [np.asarray(depth, dtype=np.float32) for depth in depths_m], masks


def render_fused_depths(
    volume: TSDFVolume, intrinsics: CameraIntrinsics, T_world_cameras: Sequence[np.ndarray], progress: bool = False
) -> list[np.ndarray]:
    """Re-render the fused surface's depth (H, W) float32 metres for each camera pose."""
    return [
        volume.render_depth(intrinsics, T)
        for T in tqdm(T_world_cameras, desc="TSDF rendering", disable=not progress, unit="frame")
    ]
