"""Supervised training targets: descriptor images, object masks and view-dependent descriptors.

:class:`DescriptorRenderer` projects an object's optimal per-vertex descriptors into a camera image by
ray casting (docs/background.md, section "Rendering descriptor targets"); :func:`make_target` builds the
paper's "geometric", "edge" and "mask" target variants (Kupcsik et al. 2021, "View-dependent Descriptors").
:class:`MultiPartDescriptorRenderer` renders several instances of several parts in one view, the nearest
surface winning at each pixel, and :func:`make_instances_target` builds the variants per instance
(docs/background.md, "Several parts in one descriptor space").
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh

from don_gym.descriptors import background_descriptor, interpolate_field
from don_gym.errors import DonGymError, MeshError
from don_gym.geometry import CameraIntrinsics, invert_transform, pixel_rays, project_points, transform_points

__all__ = [
    "EDGE_WIDTH_PX_AT_640",
    "INTERSECTORS",
    "TARGET_VARIANTS",
    "DescriptorRenderer",
    "MultiPartDescriptorRenderer",
    "RenderedInstances",
    "RenderedTarget",
    "default_edge_width_px",
    "distance_inside_px",
    "edge_blend",
    "embree_available",
    "make_instances_target",
    "make_target",
    "mask_background",
    "mask_channel",
    "render_descriptor_image",
    "render_instances",
]

try:  # embreex is an optional accelerator; trimesh's own intersector is the fallback.
    from trimesh.ray.ray_pyembree import RayMeshIntersector as _EmbreeIntersector
except ImportError:  # pragma: no cover - depends on the platform's wheels
    _EmbreeIntersector = None

#: Accepted values of ``intersector``.
INTERSECTORS = ("auto", "embree", "triangle")
#: Target variants accepted by :func:`make_target` (paper, Sec. "View-dependent Descriptors").
TARGET_VARIANTS = ("geometric", "edge", "mask")
#: Default edge-blend width in pixels for a 640-pixel-wide image; scaled with the image width.
EDGE_WIDTH_PX_AT_640 = 3.0

#: Hull vertices closer to the camera plane than this (metres) make the projected hull unbounded,
#: so the whole image is cast instead.
_NEAR_PLANE_M = 1e-6
#: Hits on triangles seen this close to edge-on (|cos| of the ray-normal angle) are dropped: the
#: ray-plane distance is ill-conditioned there and such a hit lies on an edge shared with a
#: neighbour that the ray also reaches.
_MIN_ABS_COS = 1e-9
_CACHE_SIZE = 8
#: Sub-pixel bits of the projected hull polygon given to cv2.fillConvexPoly, and the largest
#: coordinate (pixels) that stays within its int32 fixed-point range with margin.
_POLYGON_SHIFT_BITS = 8
_MAX_POLYGON_PX = 1e6


def embree_available() -> bool:
    """True when ``embreex`` imports, i.e. ``intersector="auto"`` uses Embree."""
    return _EmbreeIntersector is not None


@dataclass
class RenderedTarget:
    """One rendered frame of the object model.

    Attributes:
        descriptor_image: (H, W, D) float32, interpolated object descriptors on ``object_mask``,
            the background descriptor elsewhere.
        object_mask: (H, W) bool, pixels whose centre ray hits the mesh (and that are visible
            when a ``visible_mask`` was given).
        depth_m: (H, W) float32 camera-frame z of the hit in metres, 0 off the object.
        triangle_ids: (H, W) int32 index into ``mesh.faces`` of the hit triangle, -1 off the object.
    """

    descriptor_image: np.ndarray
    object_mask: np.ndarray
    depth_m: np.ndarray
    triangle_ids: np.ndarray


@dataclass
class _RayHits:
    """First hits of the rays cast for one frame: flat pixel index ``v * W + u``, hit triangle,
    barycentrics (M, 3) and depth (M,) in metres."""

    pixels: np.ndarray
    triangle_ids: np.ndarray
    barycentric: np.ndarray
    depth_m: np.ndarray

    def subset(self, keep: np.ndarray) -> _RayHits:
        return _RayHits(self.pixels[keep], self.triangle_ids[keep], self.barycentric[keep], self.depth_m[keep])


def _face_data(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F, 13) float64 per face: unit normal n (3), plane offset n.a (1), first vertex a (3) and
    the dual basis g1 (3), g2 (3) of the edges e1 = b - a, e2 = c - a.

    For a point p on the face's plane, p - a = u e1 + v e2 with u = g1.(p - a), v = g2.(p - a),
    so its barycentric coordinates are (1 - u - v, u, v): the least-squares solution that
    ``trimesh.triangles.points_to_barycentric`` computes per query, here precomputed once per face
    because it dominated the per-frame cost.
    """
    triangles = np.asarray(mesh.triangles, dtype=np.float64)
    a = triangles[:, 0]
    e1, e2 = triangles[:, 1] - a, triangles[:, 2] - a
    d00 = np.einsum("ij,ij->i", e1, e1)
    d01 = np.einsum("ij,ij->i", e1, e2)
    d11 = np.einsum("ij,ij->i", e2, e2)
    denominator = d00 * d11 - d01**2
    # Zero-area faces cannot be hit by a ray except along an edge; give them (1, 0, 0).
    inverse = np.divide(1.0, denominator, out=np.zeros_like(denominator), where=denominator > 0)[:, None]
    g1 = (d11[:, None] * e1 - d01[:, None] * e2) * inverse
    g2 = (d00[:, None] * e2 - d01[:, None] * e1) * inverse
    normals = np.asarray(mesh.face_normals, dtype=np.float64)
    offsets = np.einsum("ij,ij->i", normals, a)[:, None]
    return np.ascontiguousarray(np.hstack([normals, offsets, a, g1, g2]))


class _MeshRaycaster:
    """Geometry side of rendering: a private copy of the mesh, its ray intersector and bounds."""

    def __init__(self, mesh: trimesh.Trimesh, intersector: str) -> None:
        # A copy, so that a caller editing their mesh in place cannot desynchronise the BVH from
        # the triangle arrays below. process=False keeps the vertex order the descriptors index.
        self.mesh = trimesh.Trimesh(
            vertices=np.array(mesh.vertices, dtype=np.float64),
            faces=np.array(mesh.faces, dtype=np.int64),
            process=False,
        )
        if intersector == "auto":
            intersector = "embree" if embree_available() else "triangle"
        if intersector == "embree":
            if _EmbreeIntersector is None:
                raise DonGymError("intersector='embree' but the embreex package does not import; use 'auto'")
            self.intersector = _EmbreeIntersector(self.mesh)
        else:
            self.intersector = trimesh.ray.ray_triangle.RayMeshIntersector(self.mesh)
        self.name = intersector
        self.faces = self.mesh.faces.copy()
        self.face_data = _face_data(self.mesh)
        # The projected convex hull bounds the silhouette tightly; a flat mesh has no 3D hull, so
        # its axis-aligned box corners (also a valid bound) are used then.
        try:
            self.bound_points = np.asarray(self.mesh.convex_hull.vertices, dtype=np.float64)
        except Exception:  # qhull raises its own error types on degenerate input
            self.bound_points = np.asarray(trimesh.bounds.corners(self.mesh.bounds), dtype=np.float64)

    def candidate_pixels(
        self, intrinsics: CameraIntrinsics, T_camera_object: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(rows, cols)`` whose centre rays can hit the mesh (a superset of the hits).

        The silhouette lies inside the projection of the convex hull, so only pixels of the
        projected hull polygon, dilated by one pixel against rounding in the polygon fill and
        clipped to the image, are cast: about 70% of the bounding box's pixels for the toolcap.
        """
        none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        points = transform_points(T_camera_object, self.bound_points)
        z = points[:, 2]
        if z.max() <= 0.0:
            return none  # entirely behind the camera
        W, H = intrinsics.width, intrinsics.height
        if z.min() <= _NEAR_PLANE_M:
            # Part of the hull is at or behind the camera plane: its projection is unbounded.
            rows, cols = np.mgrid[0:H, 0:W]
            return rows.ravel(), cols.ravel()
        uv, _ = project_points(intrinsics, points)
        # A pixel centre (integer coordinate) is inside iff it lies in [min, max]; one pixel of
        # margin absorbs rounding in the projection.
        u0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
        u1 = min(int(np.ceil(uv[:, 0].max())) + 1, W - 1)
        v0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
        v1 = min(int(np.ceil(uv[:, 1].max())) + 1, H - 1)
        if u0 > u1 or v0 > v1:
            return none  # off image
        local = uv - (u0, v0)
        if np.abs(local).max() < _MAX_POLYGON_PX:
            canvas = np.zeros((v1 - v0 + 1, u1 - u0 + 1), dtype=np.uint8)
            hull = cv2.convexHull(local.astype(np.float32))
            fixed_point = np.round(hull * (1 << _POLYGON_SHIFT_BITS)).astype(np.int32)
            cv2.fillConvexPoly(canvas, fixed_point, 1, lineType=cv2.LINE_8, shift=_POLYGON_SHIFT_BITS)
            canvas = cv2.dilate(canvas, np.ones((3, 3), dtype=np.uint8))
            rows, cols = np.nonzero(canvas)
        else:  # hull vertices so near the camera plane that the fixed-point polygon would overflow
            rows, cols = np.mgrid[0 : v1 - v0 + 1, 0 : u1 - u0 + 1]
            rows, cols = rows.ravel(), cols.ravel()
        return rows + v0, cols + u0

    def cast(self, intrinsics: CameraIntrinsics, T_camera_object: np.ndarray) -> _RayHits:
        rows, cols = self.candidate_pixels(intrinsics, T_camera_object)
        if len(rows) == 0:
            return _RayHits(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
        # Camera-frame directions with z = 1, so the ray parameter of a hit is its depth.
        directions_camera = pixel_rays(intrinsics, np.stack([cols, rows], axis=1))
        T_object_camera = invert_transform(T_camera_object)
        directions = directions_camera @ T_object_camera[:3, :3].T
        origin = T_object_camera[:3, 3]
        origins = np.broadcast_to(origin, directions.shape)
        first_hit = np.asarray(self.intersector.intersects_first(origins, directions), dtype=np.int64)
        ray_ids = np.flatnonzero(first_hit >= 0)
        triangle_ids = first_hit[ray_ids]
        directions = directions[ray_ids]

        # Depth and barycentrics in float64 from the hit triangle's plane (Embree works in float32).
        face = self.face_data[triangle_ids]
        normals, plane_offset, first_vertex = face[:, 0:3], face[:, 3], face[:, 4:7]
        normal_dot_direction = np.einsum("ij,ij->i", normals, directions)
        # |direction| is 1 to ~1.5 within a camera's field of view, so this thresholds |cos| too.
        usable = np.abs(normal_dot_direction) > _MIN_ABS_COS
        depth = (plane_offset - normals @ origin) / np.where(usable, normal_dot_direction, 1.0)
        usable &= depth > 0.0
        if not usable.all():
            ray_ids, triangle_ids, directions = ray_ids[usable], triangle_ids[usable], directions[usable]
            face, first_vertex, depth = face[usable], first_vertex[usable], depth[usable]
        offset = origin + depth[:, None] * directions - first_vertex
        barycentric = np.empty((len(depth), 3))
        barycentric[:, 1] = np.einsum("ij,ij->i", face[:, 7:10], offset)
        barycentric[:, 2] = np.einsum("ij,ij->i", face[:, 10:13], offset)
        barycentric[:, 0] = 1.0 - barycentric[:, 1] - barycentric[:, 2]
        # Float32 hits right on an edge can land a hair outside the triangle in float64; clamping
        # keeps interpolated descriptors inside the convex hull of the vertex descriptors.
        np.clip(barycentric, 0.0, 1.0, out=barycentric)
        barycentric /= barycentric.sum(axis=1, keepdims=True)
        pixels = rows[ray_ids] * intrinsics.width + cols[ray_ids]
        return _RayHits(pixels, triangle_ids, barycentric, depth)


# Values hold the mesh object too, so that its id cannot be reused by another object while cached.
_RAYCASTERS: OrderedDict[tuple[int, int, str], tuple[_MeshRaycaster, trimesh.Trimesh]] = OrderedDict()


def _raycaster_for(mesh: trimesh.Trimesh, intersector: str) -> _MeshRaycaster:
    """Cached raycaster per mesh: building the BVH costs far more than rendering a frame.

    Keyed on the mesh object's id and its content hash (an in-place edit changes the hash).
    """
    key = (id(mesh), hash(mesh), intersector)
    entry = _RAYCASTERS.get(key)
    if entry is None:
        entry = (_MeshRaycaster(mesh, intersector), mesh)
        _RAYCASTERS[key] = entry
        while len(_RAYCASTERS) > _CACHE_SIZE:
            _RAYCASTERS.popitem(last=False)
    else:
        _RAYCASTERS.move_to_end(key)
    return entry[0]


def _as_trimesh(mesh: trimesh.Trimesh | tuple[np.ndarray, np.ndarray]) -> trimesh.Trimesh:
    if isinstance(mesh, trimesh.Trimesh):
        result = mesh
    else:
        try:
            vertices, faces = mesh
        except (TypeError, ValueError) as exc:
            raise MeshError(f"mesh: expected a trimesh.Trimesh or a (vertices, faces) pair, got {type(mesh)}") from exc
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise MeshError(f"mesh: expected vertices (N, 3) and faces (F, 3), got {vertices.shape} and {faces.shape}")
        result = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if len(result.vertices) == 0 or len(result.faces) == 0:
        raise MeshError("mesh: empty (no vertices or faces); expected a triangle mesh")
    if not np.all(np.isfinite(result.vertices)):
        raise MeshError("mesh: vertices are NaN or infinite; expected finite coordinates in metres")
    return result


def _check_transform(T_camera_object: np.ndarray) -> np.ndarray:
    T = np.asarray(T_camera_object, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DonGymError(f"T_camera_object: expected a finite (4, 4) transform, got shape {T.shape}")
    return T


def _check_mask(mask: np.ndarray, shape: tuple[int, int], what: str) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise DonGymError(f"{what}: expected shape {shape} (height, width), got {mask.shape}")
    return mask.astype(bool, copy=False)


def _check_background(background: np.ndarray, dims: int) -> np.ndarray:
    background = np.asarray(background, dtype=np.float32)
    if background.shape != (dims,) or not np.all(np.isfinite(background)):
        raise DonGymError(f"background: expected a finite ({dims},) descriptor, got shape {background.shape}")
    return background


class DescriptorRenderer:
    """Renders descriptor target images of one mesh with fixed vertex descriptors.

    One ray through each pixel centre (OpenCV pinhole model, :func:`don_gym.geometry.pixel_rays`)
    that can reach the object (pixels of its projected convex hull, clipped to the image), first hit
    on the mesh, and barycentric interpolation of the vertex descriptors over the hit triangle
    (:func:`don_gym.descriptors.interpolate_field`). Depth and barycentrics are recomputed in float64
    on the hit triangle, since Embree works in float32. Rays are cast in the object frame, so the
    acceleration structure (BVH) is built once per mesh and cached.

    Args:
        mesh: the object mesh in metres, object frame (a ``trimesh.Trimesh`` or a
            ``(vertices (N, 3), faces (F, 3))`` pair). Its vertex order must match
            ``vertex_descriptors``; it is copied, so later edits to it do not affect the renderer.
        vertex_descriptors: (N, D) descriptor of each vertex, normally in [0, 1].
        background: (D,) descriptor of pixels off the object.
        intersector: ``"auto"`` (Embree when ``embreex`` imports, else trimesh's ``ray_triangle``),
            ``"embree"`` or ``"triangle"`` (the slower pure-numpy fallback; same hits).

    The ray intersector (BVH) is shared between renderers of the same mesh object through a small
    cache, so creating renderers for new descriptors of a mesh is cheap.
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh | tuple[np.ndarray, np.ndarray],
        vertex_descriptors: np.ndarray,
        background: np.ndarray,
        intersector: str = "auto",
    ) -> None:
        if intersector not in INTERSECTORS:
            raise DonGymError(f"intersector={intersector!r}: expected one of {list(INTERSECTORS)}")
        mesh = _as_trimesh(mesh)
        descriptors = np.asarray(vertex_descriptors, dtype=np.float32)
        if descriptors.ndim != 2 or descriptors.shape[0] != len(mesh.vertices) or descriptors.shape[1] == 0:
            raise DonGymError(
                f"vertex_descriptors: expected shape ({len(mesh.vertices)}, D) (one row per mesh vertex), "
                f"got {descriptors.shape}"
            )
        if not np.all(np.isfinite(descriptors)):
            raise DonGymError("vertex_descriptors: contains NaN or infinite values")
        self.vertex_descriptors = descriptors
        self.background = _check_background(background, descriptors.shape[1])
        self._raycaster = _raycaster_for(mesh, intersector)

    @property
    def intersector_name(self) -> str:
        """``"embree"`` or ``"triangle"``: the intersector actually used."""
        return self._raycaster.name

    @property
    def descriptor_dim(self) -> int:
        return int(self.vertex_descriptors.shape[1])

    def render(
        self,
        intrinsics: CameraIntrinsics,
        T_camera_object: np.ndarray,
        visible_mask: np.ndarray | None = None,
    ) -> RenderedTarget:
        """Render the descriptor image, mask, depth and triangle ids of one frame.

        Render from the camera pose the dataset *reports*, i.e. pass
        ``T_camera_object = inv(T_world_camera_reported) @ T_world_object``, so that a target matches
        what the recorded pose says the camera saw (pose errors then show up as with a real robot).

        The ray cast knows only the object, so pixels hidden by the gripper or anything else come
        from ``visible_mask``: the final object mask is ``ray-cast hit AND visible_mask``. The ray
        cast samples exactly the pixel centre while a rasteriser has its own coverage rule, so the
        two disagree on about one pixel along parts of the silhouette; the AND drops those pixels
        from the object (it never adds any), and the mask is not eroded or dilated further.

        Args:
            intrinsics: pinhole intrinsics; the image is ``intrinsics.height`` x ``intrinsics.width``.
            T_camera_object: (4, 4) object pose in the (OpenCV) camera frame, from the *reported*
                camera pose.
            visible_mask: (H, W) bool segmentation of the object by the simulator; object pixels
                outside it (occluded) become background. None: no occlusion.

        Returns:
            A :class:`RenderedTarget`; all four images agree on the final object mask. An object
            off the image or behind the camera gives an all-background image.
        """
        T_camera_object = _check_transform(T_camera_object)
        H, W = intrinsics.height, intrinsics.width
        hits = self._raycaster.cast(intrinsics, T_camera_object)
        if visible_mask is not None:
            visible = _check_mask(visible_mask, (H, W), "visible_mask")
            hits = hits.subset(visible.ravel()[hits.pixels])

        descriptor_image = _filled_image(H, W, self.background).reshape(H * W, self.descriptor_dim)
        object_mask = np.zeros(H * W, dtype=bool)
        depth_m = np.zeros(H * W, dtype=np.float32)
        triangle_ids = np.full(H * W, -1, dtype=np.int32)
        if len(hits.pixels):
            descriptor_image[hits.pixels] = self._interpolate(hits.triangle_ids, hits.barycentric)
            object_mask[hits.pixels] = True
            depth_m[hits.pixels] = hits.depth_m
            triangle_ids[hits.pixels] = hits.triangle_ids
        return RenderedTarget(
            descriptor_image.reshape(H, W, -1),
            object_mask.reshape(H, W),
            depth_m.reshape(H, W),
            triangle_ids.reshape(H, W),
        )

    def _interpolate(self, triangle_ids: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        return np.asarray(
            interpolate_field(self.vertex_descriptors, self._raycaster.faces, triangle_ids, barycentric),
            dtype=np.float32,
        )


def render_descriptor_image(
    mesh: trimesh.Trimesh | tuple[np.ndarray, np.ndarray],
    vertex_descriptors: np.ndarray,
    background: np.ndarray,
    intrinsics: CameraIntrinsics,
    T_camera_object: np.ndarray,
    visible_mask: np.ndarray | None = None,
    intersector: str = "auto",
) -> RenderedTarget:
    """Convenience wrapper: ``DescriptorRenderer(mesh, ...).render(...)``.

    The BVH is cached per mesh object, so calling this per frame is nearly as cheap as keeping a
    :class:`DescriptorRenderer`; see there and :meth:`DescriptorRenderer.render` for the arguments.
    """
    renderer = DescriptorRenderer(mesh, vertex_descriptors, background, intersector=intersector)
    return renderer.render(intrinsics, T_camera_object, visible_mask)


def default_edge_width_px(image_width: int) -> float:
    """Edge-blend width for an image ``image_width`` pixels wide: 3 px at 640, proportional."""
    return EDGE_WIDTH_PX_AT_640 * image_width / 640.0


def _check_mask_dim(mask_dim: int, dims: int) -> None:
    if not -dims <= mask_dim < dims:
        raise DonGymError(f"mask_dim={mask_dim}: expected a dimension index in [{-dims}, {dims - 1}]")


def _filled_image(height: int, width: int, descriptor: np.ndarray) -> np.ndarray:
    """(height, width, D) float32 image of one descriptor."""
    # Copying one tiled row into every row is ~20x faster than broadcasting a (D,) vector.
    image = np.empty((height, width * len(descriptor)), dtype=np.float32)
    image[:] = np.tile(np.asarray(descriptor, dtype=np.float32), width)
    return image.reshape(height, width, len(descriptor))


def _mask_box(mask: np.ndarray) -> tuple[slice, slice] | None:
    """Slices of the mask's bounding box grown by one pixel (clipped to the image), or None if empty.

    Distance transforms on this crop equal those on the whole image: for any off-object pixel
    outside the crop, clamping its coordinates into the crop gives an off-object pixel of the
    one-pixel ring that is no farther from any pixel of the box (or lies beyond the image border,
    as the original does).
    """
    rows = np.flatnonzero(mask.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    height, width = mask.shape
    return (
        slice(max(rows[0] - 1, 0), min(rows[-1] + 2, height)),
        slice(max(cols[0] - 1, 0), min(cols[-1] + 2, width)),
    )


def distance_inside_px(object_mask: np.ndarray) -> np.ndarray:
    """(H, W) float32: Euclidean distance (pixels) from each pixel centre of the (H, W) bool ``object_mask`` to the
    nearest off-object pixel centre; 0 off the object. Pixels beyond the image border count as far away (OpenCV's
    rule): the image border is not a silhouette."""
    return cv2.distanceTransform(object_mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def edge_blend(
    descriptor_image: np.ndarray,
    object_mask: np.ndarray,
    background: np.ndarray,
    width_px: float | None = None,
) -> np.ndarray:
    """Blend object pixels near the mask edge towards the background descriptor.

    The weight of the object descriptor is ``clip(d / width_px, 0, 1)`` with ``d`` the distance
    from the pixel centre to the mask boundary, taken as the distance transform to the nearest
    off-object pixel centre minus half a pixel (the boundary lies between the two pixels). So it is
    0 at the boundary and rises linearly to 1 at ``width_px`` inside; an edge pixel keeps
    ``0.5 / width_px`` of its descriptor. The image border is not an object edge: objects cut by it
    are not blended there.

    Args:
        descriptor_image: (H, W, D) descriptors.
        object_mask: (H, W) bool.
        background: (D,) background descriptor.
        width_px: blend width in pixels (> 0); None: :func:`default_edge_width_px` of the image width.

    Returns:
        (H, W, D) float32, a new array; the background descriptor off the object.
    """
    descriptor_image = np.asarray(descriptor_image, dtype=np.float32)
    if descriptor_image.ndim != 3:
        raise DonGymError(f"descriptor_image: expected (H, W, D), got shape {descriptor_image.shape}")
    height, width, dims = descriptor_image.shape
    mask = _check_mask(object_mask, (height, width), "object_mask")
    background = _check_background(background, dims)
    if width_px is None:
        width_px = default_edge_width_px(width)
    if not (np.isfinite(width_px) and width_px > 0):
        raise DonGymError(f"width_px={width_px!r}: expected a positive number of pixels")
    blended = _filled_image(height, width, background)
    box = _mask_box(mask)
    if box is None:
        return blended
    crop = mask[box]
    rows, cols = np.nonzero(crop)
    weight = np.clip((distance_inside_px(crop)[rows, cols] - 0.5) / np.float32(width_px), 0.0, 1.0)[:, None]
    blended[box][rows, cols] = background + weight * (descriptor_image[box][rows, cols] - background)
    return blended


def mask_channel(object_mask: np.ndarray) -> np.ndarray:
    """View-dependent mask descriptor: 0 off the object rising to 1 at its centre.

    The Euclidean distance transform of the mask divided by its maximum over the whole image, so
    with several connected components only the largest reaches 1. Here the image border counts as
    off-object, so the channel describes the visible part of an object cut by the border.

    Args:
        object_mask: (H, W) bool.

    Returns:
        (H, W) float32 in [0, 1]; all zeros for an empty mask.
    """
    mask = np.asarray(object_mask)
    if mask.ndim != 2:
        raise DonGymError(f"object_mask: expected (H, W), got shape {mask.shape}")
    mask = mask.astype(bool, copy=False)
    channel = np.zeros(mask.shape, dtype=np.float32)
    box = _mask_box(mask)
    if box is None:
        return channel
    distance = distance_inside_px(np.pad(mask[box], 1, constant_values=False))[1:-1, 1:-1]
    channel[box] = distance / distance.max()
    return channel


def mask_background(vertex_descriptors: np.ndarray, mask_dim: int = -1) -> np.ndarray:
    """Background descriptor of the ``"mask"`` target variant: (D,) float32.

    The paper's rule for the background (the point of the unit cube furthest from every object
    descriptor) applied to the descriptors this variant trains towards. Its mask channel is 0 off
    the object and close to 0 just inside the outline, so the background can only be told from
    the outline by the other dimensions: they take the point of the unit cube furthest from the
    object's descriptors in those dimensions (:func:`~don_gym.descriptors.background_descriptor`),
    and ``mask_dim`` is 0. The full field's background projected onto those dimensions can lie
    close to, or on, an object descriptor (the shaft's 0.34 away, the toolcap's on one).

    Args:
        vertex_descriptors: (N, D) optimal descriptors in [0, 1] of the mesh vertices, D >= 2.
        mask_dim: the dimension the mask channel replaces (negative counts from the end).
    """
    descriptors = np.asarray(vertex_descriptors, dtype=np.float64)
    if descriptors.ndim != 2 or descriptors.shape[1] < 2 or len(descriptors) == 0:
        raise DonGymError(f"vertex_descriptors: expected (N, D) with N >= 1 and D >= 2, got shape {descriptors.shape}")
    dims = descriptors.shape[1]
    _check_mask_dim(mask_dim, dims)
    kept = np.delete(np.arange(dims), mask_dim)
    background = np.zeros(dims, dtype=np.float32)
    background[kept] = background_descriptor(descriptors[:, kept])
    return background


def make_target(
    variant: str,
    descriptor_image: np.ndarray,
    object_mask: np.ndarray,
    background: np.ndarray,
    edge_width_px: float | None = None,
    mask_dim: int = -1,
) -> np.ndarray:
    """Training target of one frame for a target variant of the paper.

    Args:
        variant: ``"geometric"`` (the optimal descriptors as rendered), ``"edge"`` (object edges
            blended towards the background, :func:`edge_blend`) or ``"mask"`` (dimension
            ``mask_dim`` replaced by :func:`mask_channel`; with D = 3 and the default last
            dimension this is the paper's two geometric dimensions plus the mask).
        descriptor_image: (H, W, D) geometric target, e.g. ``RenderedTarget.descriptor_image``
            or one read back from a dataset.
        object_mask: (H, W) bool object pixels of that target.
        background: (D,) the target's background descriptor, written off the object by ``"edge"``
            and ``"mask"``: for ``"edge"`` the one used for rendering, for ``"mask"``
            :func:`mask_background` (its ``mask_dim`` entry is ignored: the mask channel is 0 there).
        edge_width_px: blend width for ``"edge"``; None: :func:`default_edge_width_px`.
        mask_dim: dimension replaced for ``"mask"`` (negative counts from the end).

    Returns:
        (H, W, D) float32, a new array.
    """
    if variant not in TARGET_VARIANTS:
        raise DonGymError(f"target variant {variant!r} is unknown; expected one of {list(TARGET_VARIANTS)}")
    image = np.asarray(descriptor_image, dtype=np.float32)
    if variant == "geometric":
        return image.copy()
    if variant == "edge":
        return edge_blend(image, object_mask, background, edge_width_px)
    dims = image.shape[2]
    _check_mask_dim(mask_dim, dims)
    height, width = image.shape[:2]
    mask = _check_mask(object_mask, (height, width), "object_mask")
    target = _filled_image(height, width, _check_background(background, dims))
    box = _mask_box(mask)
    if box is not None:
        target[box][mask[box]] = image[box][mask[box]]
    target[..., mask_dim] = mask_channel(mask)
    return target


@dataclass
class RenderedInstances:
    """One rendered frame of several object instances, occluding each other.

    Attributes:
        descriptor_image: (H, W, D) float32, at each pixel the interpolated descriptor of the nearest
            surface among all instances, the background descriptor off every instance.
        instance_ids: (H, W) int32, the id of the instance seen at each pixel, 0 off every instance.
        depth_m: (H, W) float32 camera-frame z of the nearest hit in metres, 0 off every instance.
        triangle_ids: (H, W) int32 index into the seen instance's mesh faces, -1 off every instance.
        ids: (K,) int32 the instances' ids, in the order they were given.
    """

    descriptor_image: np.ndarray
    instance_ids: np.ndarray
    depth_m: np.ndarray
    triangle_ids: np.ndarray
    ids: np.ndarray

    @property
    def object_mask(self) -> np.ndarray:
        """(H, W) bool, pixels of any instance."""
        return self.instance_ids > 0

    @property
    def visible_masks(self) -> np.ndarray:
        """(K, H, W) bool, each instance's visible pixels (in the order of :attr:`ids`)."""
        return self.instance_ids[None] == self.ids[:, None, None]


def _check_instance_ids(instance_ids: object, count: int) -> np.ndarray:
    if instance_ids is None:
        return np.arange(1, count + 1, dtype=np.int32)
    ids = np.asarray(instance_ids)
    if (
        ids.shape != (count,)
        or not np.issubdtype(ids.dtype, np.integer)
        or (count and ids.min() < 1)
        or len(np.unique(ids)) != count
        or (count and ids.max() > np.iinfo(np.int32).max)
    ):
        raise DonGymError(f"instance_ids: expected {count} distinct integers >= 1 (one per instance), got {ids!r}")
    return ids.astype(np.int32)


def _render_instances(
    renderers: list[DescriptorRenderer],
    poses: list[np.ndarray],
    ids: np.ndarray,
    background: np.ndarray,
    intrinsics: CameraIntrinsics,
    visible_instance_ids: np.ndarray | None,
) -> RenderedInstances:
    """The ray cast of each instance (:meth:`_MeshRaycaster.cast`), the nearest hit per pixel kept."""
    H, W = intrinsics.height, intrinsics.width
    dims = len(background)
    all_hits = [renderer._raycaster.cast(intrinsics, pose) for renderer, pose in zip(renderers, poses, strict=True)]
    pixels = np.concatenate([hits.pixels for hits in all_hits] + [np.zeros(0, np.int64)])
    depth = np.concatenate([hits.depth_m for hits in all_hits] + [np.zeros(0)])
    owner = np.concatenate(
        [np.full(len(hits.pixels), k, np.int64) for k, hits in enumerate(all_hits)] + [np.zeros(0, np.int64)]
    )
    # Nearest hit per pixel; an exact tie goes to the instance given first.
    order = np.lexsort((owner, depth, pixels))
    first = np.ones(len(order), dtype=bool)
    first[1:] = pixels[order[1:]] != pixels[order[:-1]]
    winner = np.zeros(len(pixels), dtype=bool)
    winner[order[first]] = True
    if visible_instance_ids is not None:
        # As for one instance: the ray cast's nearest hit AND the simulator's segmentation says that instance.
        segmentation = np.asarray(visible_instance_ids)
        if segmentation.shape != (H, W) or not np.issubdtype(segmentation.dtype, np.integer):
            raise DonGymError(
                f"visible_instance_ids: expected integer instance ids of shape {(H, W)}, got {segmentation.shape}"
            )
        winner &= segmentation.ravel()[pixels] == ids[owner]

    descriptor_image = _filled_image(H, W, background).reshape(H * W, dims)
    instance_image = np.zeros(H * W, dtype=np.int32)
    depth_m = np.zeros(H * W, dtype=np.float32)
    triangle_ids = np.full(H * W, -1, dtype=np.int32)
    start = 0
    for k, (renderer, hits) in enumerate(zip(renderers, all_hits, strict=True)):
        keep = winner[start : start + len(hits.pixels)]
        start += len(hits.pixels)
        if not keep.any():
            continue
        hits = hits.subset(keep)
        descriptor_image[hits.pixels] = renderer._interpolate(hits.triangle_ids, hits.barycentric)
        instance_image[hits.pixels] = ids[k]
        depth_m[hits.pixels] = hits.depth_m
        triangle_ids[hits.pixels] = hits.triangle_ids
    return RenderedInstances(
        descriptor_image.reshape(H, W, dims),
        instance_image.reshape(H, W),
        depth_m.reshape(H, W),
        triangle_ids.reshape(H, W),
        ids,
    )


class MultiPartDescriptorRenderer:
    """Renders descriptor target images of several parts' instances in one view, with exact occlusion.

    Each instance is ray cast as :class:`DescriptorRenderer` casts one object (same rays, same cached BVH
    per mesh, same float64 depth and barycentrics); every pixel keeps the hit of smallest depth among all
    instances, so an instance in front hides the ones behind it exactly at the pixel centres.

    Args:
        meshes: one mesh per part (see :class:`DescriptorRenderer`), metres, object frame.
        vertex_descriptors: one (N_i, D) array per part, the part's descriptors in the shared space (e.g.
            :meth:`don_gym.descriptors.multi_part.PartSpace.map_descriptors` of its field).
        background: (D,) descriptor of pixels off every instance.
        intersector: as for :class:`DescriptorRenderer`.
    """

    def __init__(
        self,
        meshes: list[trimesh.Trimesh | tuple[np.ndarray, np.ndarray]],
        vertex_descriptors: list[np.ndarray],
        background: np.ndarray,
        intersector: str = "auto",
    ) -> None:
        if len(meshes) == 0:
            raise DonGymError("meshes: expected at least one part's mesh, got none")
        if len(vertex_descriptors) != len(meshes):
            raise DonGymError(
                f"vertex_descriptors: {len(vertex_descriptors)} arrays for {len(meshes)} meshes; expected one per mesh"
            )
        shapes = [np.shape(d) for d in vertex_descriptors]
        if any(len(shape) != 2 for shape in shapes) or len({shape[1] for shape in shapes}) != 1:
            raise DonGymError(
                f"vertex_descriptors: expected one (N_i, D) array per part with one D for all, got shapes {shapes}"
            )
        self.background = _check_background(background, shapes[0][1])
        self.parts = [
            DescriptorRenderer(mesh, descriptors, self.background, intersector)
            for mesh, descriptors in zip(meshes, vertex_descriptors, strict=True)
        ]

    @property
    def descriptor_dim(self) -> int:
        return int(self.background.shape[0])

    def render(
        self,
        intrinsics: CameraIntrinsics,
        instances: list[tuple[int, np.ndarray]],
        instance_ids: list[int] | np.ndarray | None = None,
        visible_instance_ids: np.ndarray | None = None,
    ) -> RenderedInstances:
        """Render one frame of instances of the parts.

        Args:
            intrinsics: pinhole intrinsics; the image is ``intrinsics.height`` x ``intrinsics.width``.
            instances: ``(part_index, T_camera_object)`` per instance: the index into the parts given to
                the constructor and the (4, 4) instance pose in the (OpenCV) camera frame, from the
                *reported* camera pose (as :meth:`DescriptorRenderer.render`).
            instance_ids: K distinct ids >= 1, one per instance; None: 1..K in the order given.
            visible_instance_ids: (H, W) int segmentation by the simulator, the id of the instance seen at
                each pixel (0 or any other id: none of these). A pixel keeps its nearest hit only when the
                segmentation names the same instance (things other than the instances, such as the
                gripper or a bin's wall, hide them this way); None: the instances hide only each other.

        Returns:
            A :class:`RenderedInstances`. With one instance its descriptor image, depth and triangle ids
            are those of :meth:`DescriptorRenderer.render` (with ``visible_mask = segmentation == id``).
        """
        poses, renderers = [], []
        for k, instance in enumerate(instances):
            try:
                part, pose = instance
            except (TypeError, ValueError) as exc:
                raise DonGymError(f"instances[{k}]: expected a (part_index, T_camera_object) pair") from exc
            if isinstance(part, (bool, np.bool_)) or not isinstance(part, (int, np.integer)):
                raise DonGymError(f"instances[{k}]: part index {part!r} is not an integer")
            if not 0 <= part < len(self.parts):
                raise DonGymError(f"instances[{k}]: part index {part} is outside 0..{len(self.parts) - 1}")
            renderers.append(self.parts[int(part)])
            poses.append(_check_transform(pose))
        ids = _check_instance_ids(instance_ids, len(instances))
        return _render_instances(renderers, poses, ids, self.background, intrinsics, visible_instance_ids)


def render_instances(
    instances: list[tuple[trimesh.Trimesh | tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]],
    background: np.ndarray,
    intrinsics: CameraIntrinsics,
    instance_ids: list[int] | np.ndarray | None = None,
    visible_instance_ids: np.ndarray | None = None,
    intersector: str = "auto",
) -> RenderedInstances:
    """Convenience wrapper of :class:`MultiPartDescriptorRenderer` for ``(mesh, vertex_descriptors,
    T_camera_object)`` per instance (the BVH is cached per mesh object, as for one object)."""
    if len(instances) == 0:
        raise DonGymError("instances: expected at least one (mesh, vertex_descriptors, T_camera_object), got none")
    try:
        meshes, descriptors, poses = zip(*instances, strict=True)
    except (TypeError, ValueError) as exc:
        raise DonGymError("instances: expected (mesh, vertex_descriptors, T_camera_object) triples") from exc
    renderer = MultiPartDescriptorRenderer(list(meshes), list(descriptors), background, intersector)
    return renderer.render(
        intrinsics, list(enumerate(poses)), instance_ids=instance_ids, visible_instance_ids=visible_instance_ids
    )


def make_instances_target(
    variant: str,
    descriptor_image: np.ndarray,
    instance_ids: np.ndarray,
    background: np.ndarray,
    edge_width_px: float | None = None,
    mask_dim: int = -1,
) -> np.ndarray:
    """:func:`make_target` for a frame of several instances, each treated as its own object.

    - ``"geometric"``: the rendered descriptors as they are.
    - ``"edge"``: every instance blended towards the background near its own visible outline
      (:func:`edge_blend` of its mask), also where it borders another instance: the network sees a
      boundary there as it does at a border with the background.
    - ``"mask"``: dimension ``mask_dim`` is each instance's own :func:`mask_channel`, 0 at its visible
      outline (also towards another instance) rising to 1 at its own centre; the other dimensions keep
      the descriptors, the background (:func:`mask_background` of the space) off every instance.

    With one instance each variant equals :func:`make_target` of its mask.

    Args:
        variant: ``"geometric"``, ``"edge"`` or ``"mask"``.
        descriptor_image: (H, W, D), e.g. ``RenderedInstances.descriptor_image``.
        instance_ids: (H, W) int, the instance seen per pixel, 0 off every instance.
        background: (D,) the target's background descriptor (see :func:`make_target`).
        edge_width_px: blend width for ``"edge"``; None: :func:`default_edge_width_px`.
        mask_dim: dimension replaced for ``"mask"``.

    Returns:
        (H, W, D) float32, a new array.
    """
    if variant not in TARGET_VARIANTS:
        raise DonGymError(f"target variant {variant!r} is unknown; expected one of {list(TARGET_VARIANTS)}")
    image = np.asarray(descriptor_image, dtype=np.float32)
    if image.ndim != 3:
        raise DonGymError(f"descriptor_image: expected (H, W, D), got shape {image.shape}")
    height, width, dims = image.shape
    labels = np.asarray(instance_ids)
    if labels.shape != (height, width) or not np.issubdtype(labels.dtype, np.integer):
        raise DonGymError(f"instance_ids: expected integer ids of shape {(height, width)}, got {labels.shape}")
    if variant == "geometric":
        return image.copy()
    background = _check_background(background, dims)
    if variant == "mask":
        _check_mask_dim(mask_dim, dims)
    target = _filled_image(height, width, background)
    channel = np.zeros((height, width), dtype=np.float32)
    for instance in np.unique(labels[labels != 0]):
        mask = labels == instance
        if variant == "edge":
            target[mask] = edge_blend(image, mask, background, edge_width_px)[mask]
        else:
            target[mask] = image[mask]
            channel[mask] = mask_channel(mask)[mask]
    if variant == "mask":
        target[..., mask_dim] = channel
    return target
