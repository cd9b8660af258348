"""6D pose of a part in one frame from its descriptor image.

Pixels on the part are matched to the part's surface in descriptor space; the matches give the pose by
3D-3D RANSAC (Kabsch) refined by point-to-point ICP when the frame has depth, or by 2D-3D RANSAC PnP
(OpenCV) when it has not.

What a pixel is matched to (:class:`PoseTargets`) depends on the descriptors. A part with a rotational
symmetry whose descriptors honour it (the optimal symmetric field and networks trained towards it) gives
every point of a ring about the axis one descriptor, so a pixel can only name its ring: its height along
the axis and its distance from it. Then the pose is fitted to rings (the axis line from depth points, or
from the rings' image positions without depth) and is defined up to a rotation about the axis, which the
result says (:attr:`PoseEstimate.defined_up_to`). Otherwise a pixel names a vertex and the pose is
complete. The targets come from the descriptor field (oracle, ``supervised``, ``supervised-edge``) or,
for any other source (``self-supervised``, ``supervised-mask`` whose last channel is a view-dependent
mask, a bare network), from reference frames with known poses, as :mod:`don_gym.perception.descriptor_sources` finds
reference descriptors. Arrays in, arrays out; :func:`pose_targets_for` bridges to descriptor sources.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from don_gym.data.bop import model_diameter
from don_gym.data.render import DescriptorRenderer
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, make_transform, rotation_between, transform_points
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import FIELD_METHODS, DescriptorSource
from don_gym.perception.keypoints import project_visible

__all__ = [
    "FIT_DISTANCE_M",
    "RING_ANGLES",
    "RING_QUANTUM_M",
    "PoseConfig",
    "PoseEstimate",
    "PoseTargets",
    "calibrate_targets",
    "estimate_pose",
    "icp",
    "kabsch",
    "match_to_targets",
    "model_surface_points",
    "part_pixels",
    "pose_targets",
    "pose_targets_for",
    "reference_vertex_descriptors",
]

#: Vertices within this of one another in height along the axis and in distance from it share a ring.
RING_QUANTUM_M = 2.5e-4
#: A depth point within this of the placed model fits it (the end-swap check).
FIT_DISTANCE_M = 0.002
#: Ring angles sampled when a pixel's ring point is chosen for PnP without depth.
RING_ANGLES = 48


@dataclass(frozen=True)
class PoseConfig:
    """Settings of :func:`estimate_pose`.

    Attributes:
        max_pixels: part pixels sampled per frame (at random, seeded) for matching.
        ratio: a match is kept when its descriptor distance is below ``ratio`` times that of the nearest
            target at another place on the part (more than ``distinct_fraction`` of the diameter away).
        distinct_fraction: see ``ratio``.
        max_descriptor_distance: matches further than this in descriptor space are dropped (None: the
            targets' own, :attr:`PoseTargets.max_distance`).
        ransac_iterations: hypotheses of the 3D-3D RANSAC and of OpenCV's PnP RANSAC.
        inlier_threshold_m: a 3D correspondence agrees with a hypothesis within this (depth).
        reprojection_threshold_px: a 2D correspondence agrees within this at 640 px image width, scaled
            with the width.
        icp_iterations: point-to-point ICP iterations on the depth points (0: none).
        icp_max_distance_m: depth points further than this from the placed model are left out of ICP.
        min_inliers: fewer inliers than this: no pose.
        flip_check_ratio: with depth, for a symmetric part, the pose with its ends swapped is refined by ICP
            too and replaces the found one when this many times more depth points lie within
            :data:`FIT_DISTANCE_M` of it (learned descriptors that confuse the ends tend to do so
            consistently); None (default): no check. On development scenes (seed 3102, 2 scenes x 6
            frames per part, D435) 1.05 raised the self-supervised networks' AR (toolcap 0.375 -> 0.45,
            shaft 0.8 -> 0.9) but swapped a right toolcap supervised-edge pose (0.98 -> 0.905): the
            parts' two ends differ too little in depth for the geometry to decide.
        seed: seed of the pixel sample and of RANSAC.
    """

    max_pixels: int = 1500
    ratio: float = 0.9
    distinct_fraction: float = 0.15
    max_descriptor_distance: float | None = None
    ransac_iterations: int = 200
    inlier_threshold_m: float = 0.004
    reprojection_threshold_px: float = 4.0
    icp_iterations: int = 15
    icp_max_distance_m: float = 0.008
    min_inliers: int = 8
    flip_check_ratio: float | None = None
    seed: int = 0


@dataclass(frozen=True, eq=False)
class PoseTargets:
    """What the pixels of a descriptor image are matched to.

    Attributes:
        descriptors: (K, C) float32 descriptors of the targets in the image channels ``channels``.
        points: (K, 3) object-frame point of each target in metres (for rings: the ring's point at angle 0).
        rings: (K, 2) height along the symmetry axis and distance from it (metres) of each ring target,
            or None when the targets are vertices (no symmetry honoured).
        ring_sides: (K,) +1 for a ring on an outer surface (seen from outside), -1 on a bore, 0 on a face
            across the axis; None for vertices.
        channels: descriptor image channels matched.
        background: (D,) descriptor of pixels off the part (None: unknown).
        mask_channel: channel whose value tells the part (above ``mask_threshold``), or None.
        max_distance: default largest descriptor distance of a kept match.
        axis: (3,) object-frame unit symmetry axis, through ``origin``; None without symmetry.
        origin: (3,) object-frame point on the axis (the centre of mass).
        model_points: (N, 3) object-frame surface points for ICP.
        diameter_m: the part's diameter.
        mesh: the part's mesh (object frame, metres).
        mask_threshold: ``mask_channel`` value above which a pixel is on the part.
        background_threshold: distance from ``background`` beyond which a pixel is on the part (None: half
            the distance from the background to the nearest target).
        off_part_descriptors: (M, C) descriptors of pixels off the part in reference views, for a source
            with neither background nor mask channel: a pixel nearer to one of them than to every target is
            off the part. None: not known.
    """

    descriptors: np.ndarray
    points: np.ndarray
    rings: np.ndarray | None
    ring_sides: np.ndarray | None
    channels: tuple[int, ...]
    background: np.ndarray | None
    mask_channel: int | None
    max_distance: float
    axis: np.ndarray | None
    origin: np.ndarray
    model_points: np.ndarray
    diameter_m: float
    mesh: trimesh.Trimesh
    mask_threshold: float = 0.1
    background_threshold: float | None = None
    off_part_descriptors: np.ndarray | None = None

    @property
    def symmetric(self) -> bool:
        return self.rings is not None

    @cached_property
    def tree(self) -> cKDTree:
        """k-d tree of :attr:`descriptors`."""
        return cKDTree(self.descriptors)

    @cached_property
    def model_tree(self) -> cKDTree:
        """k-d tree of :attr:`model_points`."""
        return cKDTree(self.model_points)

    @cached_property
    def off_part_tree(self) -> cKDTree | None:
        """k-d tree of the distinct :attr:`off_part_descriptors` (None without them)."""
        if self.off_part_descriptors is None:
            return None
        # Off-part pixels often share one descriptor (a learned background); a tree of many equal points
        # is slow to query and no more telling than one of them.
        return cKDTree(np.unique(np.round(self.off_part_descriptors, 4), axis=0))

    @property
    def defined_up_to(self) -> str | None:
        if not self.symmetric:
            return None
        ax = ", ".join(f"{v:g}" for v in np.round(self.axis, 4))
        return f"rotation about the object-frame axis ({ax}) through the centre of mass"


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """A part's pose in one frame (:func:`estimate_pose`).

    Attributes:
        T_camera_object: (4, 4) object frame in the camera frame (OpenCV axes, metres); None when no pose
            was found. For a symmetric result any rotation about the axis gives the same part in the image.
        inliers: correspondences that agree with the pose.
        correspondences: matches that passed the ratio and distance tests.
        score: ``inliers / correspondences`` (0 without a pose), for ranking estimates.
        time_s: wall time of the estimate (matching, solving, refining).
        symmetric: whether the pose is defined only up to the part's rotational symmetry.
        defined_up_to: in words, what the pose is defined up to (None: fully).
        solver: with depth ``"kabsch"`` (3D-3D RANSAC on vertices) or ``"rings"`` (RANSAC fit of the axis to
            ring matches), each ``+icp`` when refined; ``"pnp"`` without depth; ``"none"`` without a pose.
    """

    T_camera_object: np.ndarray | None
    inliers: int
    correspondences: int
    score: float
    time_s: float
    symmetric: bool
    defined_up_to: str | None
    solver: str

    @property
    def found(self) -> bool:
        return self.T_camera_object is not None


# --- targets -------------------------------------------------------------------------------------


def model_surface_points(model: ObjectModel) -> np.ndarray:
    """(N, 3) object-frame points for ICP: the mesh's vertices and face centres (metres)."""
    mesh = model.mesh
    return np.concatenate([np.asarray(mesh.vertices), np.asarray(mesh.triangles_center)]).astype(np.float64)


def _ring_table(model: ObjectModel, vertex_descriptors: np.ndarray, valid: np.ndarray) -> dict[str, np.ndarray]:
    """Vertices grouped into rings about the symmetry axis: mean descriptor, (h, r), side, point at angle 0."""
    axis = np.asarray(model.symmetry_axis, dtype=np.float64)
    origin = np.asarray(model.center_of_mass, dtype=np.float64)
    vertices = np.asarray(model.mesh.vertices, dtype=np.float64)
    offset = vertices - origin
    h = offset @ axis
    radial = offset - np.outer(h, axis)
    r = np.linalg.norm(radial, axis=1)
    keys = np.stack([np.rint(h / RING_QUANTUM_M), np.rint(r / RING_QUANTUM_M)], axis=1).astype(np.int64)
    keys, ring_of = np.unique(keys[valid], axis=0, return_inverse=True)
    ring_of = ring_of.ravel()
    count = np.bincount(ring_of, minlength=len(keys)).astype(np.float64)
    descriptors = (
        np.stack(
            [np.bincount(ring_of, vertex_descriptors[valid, c], len(keys)) for c in range(vertex_descriptors.shape[1])],
            axis=1,
        )
        / count[:, None]
    )
    rings = np.stack(
        [np.bincount(ring_of, h[valid], len(keys)) / count, np.bincount(ring_of, r[valid], len(keys)) / count], axis=1
    )
    normals = np.asarray(model.mesh.vertex_normals, dtype=np.float64)[valid]
    with np.errstate(invalid="ignore", divide="ignore"):
        radial_unit = radial[valid] / r[valid, None]
    outward = np.nan_to_num(np.einsum("ij,ij->i", normals, radial_unit))
    mean_outward = np.bincount(ring_of, outward, len(keys)) / count
    sides = np.where(mean_outward > 0.5, 1, np.where(mean_outward < -0.5, -1, 0)).astype(np.int8)
    e1, _ = _perpendicular_basis(axis)
    points = origin + np.outer(rings[:, 0], axis) + np.outer(rings[:, 1], e1)
    return {"descriptors": descriptors.astype(np.float32), "rings": rings, "sides": sides, "points": points}


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def pose_targets(
    model: ObjectModel,
    vertex_descriptors: np.ndarray,
    valid: np.ndarray | None = None,
    symmetric: bool = True,
    background: np.ndarray | None = None,
    channels: Sequence[int] | None = None,
    mask_channel: int | None = None,
    max_distance: float = 0.05,
) -> PoseTargets:
    """Targets from per-vertex descriptors (N, D) of the part's mesh.

    Args:
        model: the part.
        vertex_descriptors: (N, D) descriptors of the mesh vertices, in the descriptor image's channels.
        valid: (N,) bool, vertices whose descriptor is known (None: all).
        symmetric: whether the descriptors honour the part's rotational symmetry (rings are matched; the
            pose is defined up to the symmetry). Ignored for a part without a symmetry axis.
        background: (D,) descriptor off the part, if known.
        channels: channels to match (None: all).
        mask_channel: a channel that tells the part from the rest (``supervised-mask``), or None.
        max_distance: default largest descriptor distance of a kept match.
    """
    vertex_descriptors = np.asarray(vertex_descriptors, dtype=np.float64)
    n = len(model.mesh.vertices)
    if vertex_descriptors.ndim != 2 or len(vertex_descriptors) != n:
        raise DonGymError(
            f"vertex_descriptors: expected ({n}, D) for the part's {n} vertices, got {vertex_descriptors.shape}"
        )
    valid = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid.sum() < 4:
        raise DonGymError(f"only {int(valid.sum())} vertices have a descriptor; pose estimation needs at least 4")
    channels = tuple(range(vertex_descriptors.shape[1])) if channels is None else tuple(int(c) for c in channels)
    chosen = vertex_descriptors[:, channels]
    axis = None if model.symmetry_axis is None else np.asarray(model.symmetry_axis, dtype=np.float64)
    rings = sides = None
    if symmetric and axis is not None:
        table = _ring_table(model, chosen, valid)
        descriptors, points, rings, sides = table["descriptors"], table["points"], table["rings"], table["sides"]
    else:
        descriptors, points = chosen[valid].astype(np.float32), np.asarray(model.mesh.vertices)[valid]
    return PoseTargets(
        descriptors=descriptors,
        points=np.asarray(points, dtype=np.float64),
        rings=rings,
        ring_sides=sides,
        channels=channels,
        background=None if background is None else np.asarray(background, dtype=np.float32),
        mask_channel=mask_channel,
        max_distance=float(max_distance),
        axis=axis if rings is not None else None,
        origin=np.asarray(model.center_of_mass, dtype=np.float64),
        model_points=model_surface_points(model),
        diameter_m=model_diameter(np.asarray(model.mesh.vertices)),
        mesh=model.mesh,
    )


def reference_vertex_descriptors(
    model: ObjectModel,
    references: Sequence[tuple[np.ndarray, CameraIntrinsics, np.ndarray]],
    tolerance_m: float = 0.003,
    margin_px: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex descriptors read from reference descriptor images of known pose.

    Args:
        model: the part.
        references: ``(descriptor_image (H, W, D), intrinsics, T_camera_object (4, 4))`` per reference view.
        tolerance_m: a vertex is seen when the rendered part's depth at its pixel is within this of its own.
        margin_px: seen vertices keep this many pixels inside the part's outline.

    Returns:
        ``(vertex_descriptors (N, D) float32, valid (N,) bool)``: the mean over the views that see a vertex.
    """
    vertices = np.asarray(model.mesh.vertices, dtype=np.float64)
    renderer = DescriptorRenderer(model.mesh, np.zeros((len(vertices), 1), np.float32), np.zeros(1, np.float32))
    total = None
    count = np.zeros(len(vertices))
    for image, intrinsics, T_camera_object in references:
        image = np.asarray(image, dtype=np.float32)
        target = renderer.render(intrinsics, T_camera_object)
        uv, visible = project_visible(
            transform_points(T_camera_object, vertices), intrinsics, target.depth_m, tolerance_m
        )
        if margin_px > 0:
            size = 2 * int(margin_px) + 1
            interior = cv2.erode(target.object_mask.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
            visible[visible] = interior[uv[visible, 1], uv[visible, 0]]
        if total is None:
            total = np.zeros((len(vertices), image.shape[2]))
        total[visible] += image[uv[visible, 1], uv[visible, 0]]
        count[visible] += 1
    if total is None:
        raise DonGymError("no reference view given; reference descriptors need at least one")
    valid = count > 0
    total[valid] /= count[valid, None]
    return total.astype(np.float32), valid


def pose_targets_for(
    source: DescriptorSource,
    references: Sequence[tuple[np.ndarray, CameraIntrinsics, np.ndarray]] = (),
    from_field: bool | None = None,
) -> PoseTargets:
    """The targets of a descriptor source (:mod:`don_gym.perception.descriptor_sources`) for its part.

    From the field (``from_field``; None: for the oracle, and for networks that reproduce the optimal field
    when no reference view is given): the field's vertex descriptors, symmetric as the field is, told from
    the field's background. From ``references`` (every other case): the source's own descriptor images of
    views with known poses (``(descriptor_image, intrinsics, T_camera_object)``) give the seen vertices
    their descriptors (:func:`reference_vertex_descriptors`). A trained network reproduces the field only up
    to an offset that matching an absolute field suffers from (the shipped toolcap supervised-edge network's
    part pixels lie 0.3-0.45 from the nearest field descriptor, measured on development scenes) and its own
    descriptors of a seen view do not. A ``supervised-mask`` network's last channel is its mask (not
    matched; it tells the part), and a part with a symmetry axis is matched by rings (learned descriptors
    cannot tell the points of a ring apart either). With references the targets are calibrated on them
    (:func:`calibrate_targets`).
    """
    model = source.object_model
    if model is None:
        raise DonGymError("pose estimation needs the source's object_model")
    if from_field is None:
        from_field = source.method == "oracle" or (
            not references and source.reference_from_field and source.method in FIELD_METHODS
        )
    if from_field and not (source.reference_from_field and source.field is not None):
        raise DonGymError(f"a {source.method!r} model has no descriptor field to match; give reference views")
    if from_field:
        field_ = source.field
        targets = pose_targets(
            model,
            field_.vertex_descriptors,
            symmetric=field_.symmetric,
            background=field_.background,
            max_distance=0.05,
        )
    else:
        if not references:
            raise DonGymError(
                f"a {source.method!r} model needs reference views with known poses for pose estimation; "
                "its descriptor space is not the optimal field"
            )
        descriptors, valid = reference_vertex_descriptors(model, references)
        dim = descriptors.shape[1]
        mask_channel = dim - 1 if source.method == "supervised-mask" and dim > 1 else None
        channels = [c for c in range(dim) if c != mask_channel]
        targets = pose_targets(model, descriptors, valid, symmetric=True, channels=channels, mask_channel=mask_channel)
    if references:
        targets = calibrate_targets(targets, references)
    return targets


def _separating_threshold(inside: np.ndarray, outside: np.ndarray) -> float:
    """The value ``c`` that best tells ``inside`` (``> c``) from ``outside`` (``<= c``): fewest errors, each
    side weighted by its share; the middle of the values that do it best. Candidates come from both sides'
    quantiles and the midpoints between them, so a side of few values (a small part in a large image) is
    not drowned by the other."""
    q = np.linspace(0.0, 1.0, 101)
    values = np.unique(np.concatenate([np.quantile(inside, q), np.quantile(outside, q)]))
    candidates = np.concatenate([values, (values[1:] + values[:-1]) / 2.0])
    errors = np.array([(inside <= c).mean() + (outside > c).mean() for c in candidates])
    # The middle of the best: as far from both sides as they allow.
    return float(np.median(candidates[errors <= errors.min() + 1e-12]))


def calibrate_targets(
    targets: PoseTargets,
    references: Sequence[tuple[np.ndarray, CameraIntrinsics, np.ndarray]],
    quantile: float = 0.9,
    floor: float = 0.01,
) -> PoseTargets:
    """``targets`` tuned to a source on reference views of known pose: ``max_distance``, the ``quantile`` of
    the descriptor distances from the part's pixels (rendered mask) to the nearest target (at least
    ``floor``); ``background_threshold`` and ``mask_threshold``, the distance to the background and the mask
    channel's value that best tell the part's pixels (2 px inside its outline) from the rest."""
    tree = cKDTree(targets.descriptors)
    renderer = DescriptorRenderer(
        targets.mesh, np.zeros((len(targets.mesh.vertices), 1), np.float32), np.zeros(1, np.float32)
    )
    distances, inside, outside, mask_inside, mask_outside, off_part = [], [], [], [], [], []
    channels = list(targets.channels)
    for image, intrinsics, T_camera_object in references:
        image = np.asarray(image, dtype=np.float32)
        mask = renderer.render(intrinsics, T_camera_object).object_mask
        if not mask.any():
            continue
        distances.append(tree.query(image[mask][:, channels], k=1)[0])
        # Off the part, well clear of its outline (whose pixels mix the part with the rest).
        clear = ~cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        off_part.append(image[clear][:, channels])
        interior = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        if interior.any() and targets.background is not None:
            to_background = np.linalg.norm(image[..., channels] - targets.background[channels], axis=2)
            inside.append(to_background[interior])
            outside.append(to_background[~mask])
        if interior.any() and targets.mask_channel is not None:
            mask_inside.append(image[..., targets.mask_channel][interior])
            mask_outside.append(image[..., targets.mask_channel][~mask])
    changes: dict[str, float] = {}
    if distances:
        changes["max_distance"] = max(float(np.quantile(np.concatenate(distances), quantile)), floor)
    if inside:
        changes["background_threshold"] = _separating_threshold(np.concatenate(inside), np.concatenate(outside))
    if mask_inside:
        changes["mask_threshold"] = _separating_threshold(np.concatenate(mask_inside), np.concatenate(mask_outside))
    rest = np.concatenate(off_part) if off_part else np.zeros((0, len(channels)), np.float32)
    if len(rest) and targets.background is None and targets.mask_channel is None:
        # A sample is enough to describe what the rest of a view looks like in descriptor space.
        keep = np.random.default_rng(0).choice(len(rest), min(len(rest), 20000), replace=False)
        changes["off_part_descriptors"] = rest[keep]
    return replace(targets, **changes)


# --- matching ------------------------------------------------------------------------------------


def part_pixels(
    descriptor_image: np.ndarray, targets: PoseTargets, object_mask: np.ndarray | None = None
) -> np.ndarray:
    """(H, W) bool pixels taken to show the part: ``object_mask`` when given; else the mask channel above
    its threshold; else pixels whose descriptor lies further from the background than
    ``targets.background_threshold``; else pixels nearer to a target than to every off-part descriptor of the
    reference views; else (no background known) every pixel."""
    image = np.asarray(descriptor_image)
    if object_mask is not None:
        mask = np.asarray(object_mask, dtype=bool)
        if mask.shape != image.shape[:2]:
            raise DonGymError(
                f"object_mask has shape {mask.shape}; expected {image.shape[:2]} like the descriptor image"
            )
        return mask
    if targets.mask_channel is not None:
        return image[..., targets.mask_channel] > targets.mask_threshold
    if targets.background is not None:
        background = targets.background[list(targets.channels)]
        threshold = targets.background_threshold
        if threshold is None:
            threshold = 0.5 * float(np.min(np.linalg.norm(targets.descriptors - background, axis=1)))
        return np.linalg.norm(image[..., list(targets.channels)] - background, axis=2) > threshold
    if targets.off_part_descriptors is not None:
        pixels = image[..., list(targets.channels)].reshape(-1, len(targets.channels))
        to_part = targets.tree.query(pixels, k=1)[0]
        to_rest = targets.off_part_tree.query(pixels, k=1)[0]
        return (to_part < to_rest).reshape(image.shape[:2])
    return np.ones(image.shape[:2], dtype=bool)


def match_to_targets(
    descriptors: np.ndarray, targets: PoseTargets, config: PoseConfig = PoseConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest target of each descriptor (M, C), kept when unambiguous.

    A match is kept when its distance is at most the maximum descriptor distance and below ``config.ratio``
    times the distance to the nearest target at another place on the part (rings: more than
    ``distinct_fraction`` of the diameter apart in (height, radius); vertices: in space), since nearby
    targets share descriptors by design. Returns ``(kept (M,) bool, target index (M,))``.
    """
    descriptors = np.asarray(descriptors, dtype=np.float32)
    k = min(16, len(targets.descriptors))
    distances, indices = targets.tree.query(descriptors, k=k)
    distances, indices = distances.reshape(len(descriptors), k), indices.reshape(len(descriptors), k)
    places = targets.rings if targets.rings is not None else targets.points
    apart = (
        np.linalg.norm(places[indices] - places[indices[:, :1]], axis=2) > config.distinct_fraction * targets.diameter_m
    )
    second = np.where(apart, distances, np.inf).min(axis=1)
    limit = targets.max_distance if config.max_descriptor_distance is None else config.max_descriptor_distance
    kept = (distances[:, 0] <= limit) & (distances[:, 0] < config.ratio * second)
    return kept, indices[:, 0]


# --- solvers -------------------------------------------------------------------------------------


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform T minimising ``sum |T source_i - target_i|^2`` for (N, 3) point pairs, N >= 3."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - mu_s).T @ (target - mu_t))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_transform(R, mu_t - R @ mu_s)


def _end_swap(targets: PoseTargets) -> np.ndarray:
    """(4, 4) object-frame half turn about an axis across the symmetry axis through the middle of the
    part's extent along it: the part with its ends swapped, in about the same place."""
    along = (targets.model_points - targets.origin) @ targets.axis
    middle = targets.origin + 0.5 * (along.min() + along.max()) * targets.axis
    e1, _ = _perpendicular_basis(targets.axis)
    R = 2.0 * np.outer(e1, e1) - np.eye(3)  # half turn about e1
    return make_transform(R, middle - R @ middle)


def icp(
    T_camera_object: np.ndarray,
    points_camera: np.ndarray,
    model_points: np.ndarray,
    iterations: int,
    max_distance_m: float,
) -> tuple[np.ndarray, int]:
    """Point-to-point ICP of depth points (N, 3, camera frame) onto model points (object frame): the refined
    (4, 4) pose and the number of depth points within ``max_distance_m`` of the placed model."""
    T = np.asarray(T_camera_object, dtype=np.float64).copy()
    tree = cKDTree(model_points)
    close = np.zeros(len(points_camera), dtype=bool)
    for _ in range(iterations):
        in_object = transform_points(np.linalg.inv(T), points_camera)
        distances, nearest = tree.query(in_object, k=1)
        close = distances < max_distance_m
        if close.sum() < 3:
            break
        T = kabsch(model_points[nearest[close]], points_camera[close])
    in_object = transform_points(np.linalg.inv(T), points_camera)
    return T, int((tree.query(in_object, k=1)[0] < max_distance_m).sum())


def _closest_ring_points_3d(
    targets: PoseTargets, T: np.ndarray, points: np.ndarray, rings: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per camera-frame point (n, 3) the nearest point of its ring (n, 2) under pose T: object-frame points
    (n, 3) and distances (n,) in metres."""
    in_object = transform_points(np.linalg.inv(T), points) - targets.origin
    h = in_object @ targets.axis
    radial = in_object - np.outer(h, targets.axis)
    norm = np.linalg.norm(radial, axis=1, keepdims=True)
    e1, _ = _perpendicular_basis(targets.axis)
    unit = np.where(norm > 1e-9, radial / np.maximum(norm, 1e-12), e1)
    ring_points = targets.origin + np.outer(rings[:, 0], targets.axis) + rings[:, 1, None] * unit
    return ring_points, np.linalg.norm(ring_points - targets.origin - in_object, axis=1)


def _refine_rings_3d(
    targets: PoseTargets, T: np.ndarray, points: np.ndarray, rings: np.ndarray, threshold: float, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Alternate each point's nearest ring point and Kabsch on the agreeing pairs; (pose, inliers)."""
    for step in range(iterations):
        model, distance = _closest_ring_points_3d(targets, T, points, rings)
        use = distance < max(threshold, threshold * 4.0 / (step + 1))
        if use.sum() < 3:
            break
        T = kabsch(model[use], points[use])
    _, distance = _closest_ring_points_3d(targets, T, points, rings)
    return T, distance < threshold


def _pose_from_axis(targets: PoseTargets, axis_camera: np.ndarray, zero_camera: np.ndarray) -> np.ndarray:
    R = rotation_between(targets.axis, axis_camera)
    return make_transform(R, zero_camera - R @ targets.origin)


def _rings_ransac_3d(
    targets: PoseTargets, points: np.ndarray, rings: np.ndarray, config: PoseConfig, rng: np.random.Generator
) -> tuple[np.ndarray | None, np.ndarray]:
    """Pose from depth points of known rings: each hypothesis takes the axis through two matched points far
    apart in height (shifted back from the camera by their mean radius) and refines it twice by nearest ring
    points and Kabsch; the best is refined to convergence."""
    best, best_inliers = None, np.zeros(len(points), dtype=bool)
    h = rings[:, 0]
    span = float(h.max() - h.min())
    if span <= 0:
        return None, best_inliers
    for _ in range(config.ransac_iterations):
        i, j = rng.choice(len(points), 2, replace=False)
        if abs(h[j] - h[i]) < 0.25 * span:
            continue
        axis = (points[j] - points[i]) * np.sign(h[j] - h[i])
        axis /= np.linalg.norm(axis)
        zero = points[i] - h[i] * axis
        away = zero / np.linalg.norm(zero)
        zero = zero + 0.5 * (rings[i, 1] + rings[j, 1]) * (away - (away @ axis) * axis)
        T, inliers = _refine_rings_3d(
            targets, _pose_from_axis(targets, axis, zero), points, rings, config.inlier_threshold_m, 2
        )
        if inliers.sum() > best_inliers.sum():
            best, best_inliers = T, inliers
    if best is not None:
        best, best_inliers = _refine_rings_3d(targets, best, points, rings, config.inlier_threshold_m, 10)
    return best, best_inliers


def _kabsch_ransac(
    model: np.ndarray, camera: np.ndarray, config: PoseConfig, rng: np.random.Generator
) -> tuple[np.ndarray | None, np.ndarray]:
    best, best_inliers = None, np.zeros(len(model), dtype=bool)
    for _ in range(config.ransac_iterations):
        idx = rng.choice(len(model), 3, replace=False)
        T = kabsch(model[idx], camera[idx])
        inliers = np.linalg.norm(transform_points(T, model) - camera, axis=1) < config.inlier_threshold_m
        if inliers.sum() > best_inliers.sum():
            best, best_inliers = T, inliers
    if best is not None and best_inliers.sum() >= 3:
        best = kabsch(model[best_inliers], camera[best_inliers])
        best_inliers = np.linalg.norm(transform_points(best, model) - camera, axis=1) < config.inlier_threshold_m
    return best, best_inliers


def _ring_points(targets: PoseTargets, rings: np.ndarray) -> np.ndarray:
    """(n, A, 3) object-frame points of each ring at :data:`RING_ANGLES` angles."""
    e1, e2 = _perpendicular_basis(targets.axis)
    angles = np.linspace(0.0, 2.0 * np.pi, RING_ANGLES, endpoint=False)
    circle = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2  # (A, 3)
    centre = targets.origin + np.outer(rings[:, 0], targets.axis)
    return centre[:, None, :] + rings[:, 1, None, None] * circle[None]


def _closest_ring_points(
    targets: PoseTargets, T: np.ndarray, rings: np.ndarray, sides: np.ndarray, uv: np.ndarray, K: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the point of its ring, on the side the camera sees, whose projection under T lies nearest:
    object-frame points (n, 3) and their pixel distances (n,)."""
    points = _ring_points(targets, rings)  # (n, A, 3)
    camera = points @ T[:3, :3].T + T[:3, 3]
    centre_camera = (targets.origin + np.outer(rings[:, 0], targets.axis)) @ T[:3, :3].T + T[:3, 3]
    facing = np.einsum("naj,naj->na", camera - centre_camera[:, None], -camera) * sides[:, None] > 0
    facing |= (sides == 0)[:, None]
    facing[~facing.any(axis=1)] = True
    with np.errstate(divide="ignore", invalid="ignore"):
        projected = camera[..., :2] / camera[..., 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    distance = np.linalg.norm(projected - uv[:, None, :], axis=2)
    distance = np.where(facing & (camera[..., 2] > 0), distance, np.inf)
    best = np.argmin(distance, axis=1)
    rows = np.arange(len(uv))
    return points[rows, best], distance[rows, best]


def _rings_pnp(
    targets: PoseTargets,
    uv: np.ndarray,
    rings: np.ndarray,
    sides: np.ndarray,
    intrinsics: CameraIntrinsics,
    config: PoseConfig,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Pose from pixels of known rings without depth: the axis's image line and scale from the pixels'
    heights and spread give two initial poses (axis tilted towards or away from the camera); each is refined
    by alternating the ring point nearest each pixel with OpenCV's RANSAC PnP; the one with more inliers wins."""
    K = intrinsics.K
    threshold = config.reprojection_threshold_px * intrinsics.width / 640.0
    h, r = rings[:, 0], rings[:, 1]
    keep = np.ones(len(uv), dtype=bool)
    for _ in range(3):  # the image of the axis: uv = m0 + h m1, robustly
        A = np.stack([np.ones(keep.sum()), h[keep]], axis=1)
        (m0, m1), *_ = np.linalg.lstsq(A, uv[keep], rcond=None)
        residual = np.linalg.norm(uv - m0 - np.outer(h, m1), axis=1)
        keep = residual <= 3.0 * np.median(residual[keep]) + 1.0
    length = float(np.linalg.norm(m1))
    if length == 0:
        return None, np.zeros(len(uv), dtype=bool)
    direction = m1 / length
    across = np.abs((uv - m0 - np.outer(h, m1)) @ np.array([-direction[1], direction[0]]))
    wide = keep & (r > 0.3 * r.max())
    pixels_per_m = float(np.quantile(across[wide] / r[wide], 0.9) / 0.9) if wide.sum() >= 5 else length
    pixels_per_m = max(pixels_per_m, length)
    depth = 0.5 * (K[0, 0] + K[1, 1]) / pixels_per_m
    ray = np.array([(m0[0] - K[0, 2]) / K[0, 0], (m0[1] - K[1, 2]) / K[1, 1], 1.0])
    zero = ray * depth
    cos_tilt = min(length / pixels_per_m, 1.0)
    sin_tilt = float(np.sqrt(1.0 - cos_tilt**2))
    best, best_inliers = None, np.zeros(len(uv), dtype=bool)
    for sign in (1.0, -1.0) if sin_tilt > 1e-3 else (1.0,):
        axis = np.array([cos_tilt * direction[0], cos_tilt * direction[1], sign * sin_tilt])
        T = _pose_from_axis(targets, axis, zero)
        inliers = np.zeros(len(uv), dtype=bool)
        for step in range(8):
            model, distance = _closest_ring_points(targets, T, rings, sides, uv, K)
            limit = max(threshold, threshold * 8.0 / (step + 1))
            use = distance < limit
            if use.sum() < 6:
                break
            rvec, _ = cv2.Rodrigues(T[:3, :3])
            ok, rvec, tvec = cv2.solvePnP(
                model[use],
                uv[use],
                K,
                None,
                rvec,
                T[:3, 3].copy(),
                useExtrinsicGuess=True,
                flags=cv2.SOLVEPNP_ITERATIVE,
            )
            if not ok:
                break
            T = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
        model, distance = _closest_ring_points(targets, T, rings, sides, uv, K)
        inliers = distance < threshold
        # OpenCV's RANSAC PnP on the final ring points, kept when more pixels agree with its pose.
        ok, rvec, tvec, found = cv2.solvePnPRansac(
            model,
            uv,
            K,
            None,
            iterationsCount=config.ransac_iterations,
            reprojectionError=threshold,
            confidence=0.99,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if ok and found is not None and tvec.ravel()[2] > 0:
            T_ransac = make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel())
            _, distance_ransac = _closest_ring_points(targets, T_ransac, rings, sides, uv, K)
            if (distance_ransac < threshold).sum() > inliers.sum():
                T, inliers = T_ransac, distance_ransac < threshold
        if inliers.sum() > best_inliers.sum() and T[2, 3] > 0:
            best, best_inliers = T, inliers
    return best, best_inliers


# --- the estimate --------------------------------------------------------------------------------


def estimate_pose(
    descriptor_image: np.ndarray,
    targets: PoseTargets,
    intrinsics: CameraIntrinsics,
    depth_m: np.ndarray | None = None,
    object_mask: np.ndarray | None = None,
    config: PoseConfig = PoseConfig(),
) -> PoseEstimate:
    """The part's pose in one frame.

    Args:
        descriptor_image: (H, W, D) float32 descriptors of the frame.
        targets: what pixels are matched to (:func:`pose_targets_for`).
        intrinsics: the frame's pinhole intrinsics (image of ``intrinsics.width`` x ``height``).
        depth_m: (H, W) depth in metres (0: none), or None for RGB-only PnP.
        object_mask: (H, W) bool pixels of the part, if known (else :func:`part_pixels`).
        config: settings.

    Returns:
        A :class:`PoseEstimate`; its ``T_camera_object`` is None when too few matches agree.
    """
    start = time.perf_counter()
    image = np.asarray(descriptor_image, dtype=np.float32)
    if image.ndim != 3 or image.shape[:2] != (intrinsics.height, intrinsics.width):
        raise DonGymError(
            f"descriptor_image has shape {image.shape}; expected ({intrinsics.height}, {intrinsics.width}, D) "
            "like the intrinsics"
        )
    if depth_m is not None:
        depth_m = np.asarray(depth_m, dtype=np.float64)
        if depth_m.shape != image.shape[:2]:
            raise DonGymError(
                f"depth_m has shape {depth_m.shape}; expected {image.shape[:2]} like the descriptor image"
            )
    rng = np.random.default_rng(config.seed)
    mask = part_pixels(image, targets, object_mask)
    if depth_m is not None:
        mask = mask & (depth_m > 0)
    v, u = np.nonzero(mask)
    # Pixels within the distance limit of some target first (without a mask that is every pixel, of
    # which the part may be a small share), then a sample of them for the ratio test.
    limit = targets.max_distance if config.max_descriptor_distance is None else config.max_descriptor_distance
    near = targets.tree.query(image[v, u][:, list(targets.channels)], k=1)[0] <= limit
    v, u = v[near], u[near]
    on_part = np.zeros_like(mask)
    on_part[v, u] = True
    if len(u) > config.max_pixels:
        chosen = rng.choice(len(u), config.max_pixels, replace=False)
        u, v = u[chosen], v[chosen]
    kept, index = match_to_targets(image[v, u][:, list(targets.channels)], targets, config)
    uv = np.stack([u, v], axis=1)[kept].astype(np.float64)
    index = index[kept]

    def result(T: np.ndarray | None, inliers: int, solver: str) -> PoseEstimate:
        found = T is not None and inliers >= config.min_inliers
        return PoseEstimate(
            T_camera_object=T if found else None,
            inliers=int(inliers) if found else 0,
            correspondences=len(uv),
            score=float(inliers / len(uv)) if found and len(uv) else 0.0,
            time_s=time.perf_counter() - start,
            symmetric=targets.symmetric,
            defined_up_to=targets.defined_up_to,
            solver=solver if found else "none",
        )

    if len(uv) < max(config.min_inliers, 6):
        return result(None, 0, "none")
    if depth_m is None:
        if targets.symmetric:
            T, inliers = _rings_pnp(targets, uv, targets.rings[index], targets.ring_sides[index], intrinsics, config)
            return result(T, int(inliers.sum()), "pnp")
        threshold = config.reprojection_threshold_px * intrinsics.width / 640.0
        ok, rvec, tvec, found = cv2.solvePnPRansac(
            targets.points[index],
            uv,
            intrinsics.K,
            None,
            iterationsCount=config.ransac_iterations,
            reprojectionError=threshold,
            confidence=0.99,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok or found is None or len(found) < 4:
            return result(None, 0, "none")
        found = found.ravel()
        ok, rvec, tvec = cv2.solvePnP(
            targets.points[index][found],
            uv[found],
            intrinsics.K,
            None,
            rvec,
            tvec,
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        return result(make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()), len(found), "pnp")
    points = backproject_depth(intrinsics, depth_m, uv.astype(np.int64))
    if targets.symmetric:
        T, inliers = _rings_ransac_3d(targets, points, targets.rings[index], config, rng)
    else:
        T, inliers = _kabsch_ransac(targets.points[index], points, config, rng)
    if T is None or inliers.sum() < config.min_inliers:
        return result(None, 0, "none")
    if config.icp_iterations <= 0:
        return result(T, int(inliers.sum()), "rings" if targets.symmetric else "kabsch")
    # ICP on all the part's depth points (not only the matched ones): the geometry refines what the
    # descriptors located, and points off the part stay beyond max_distance of the placed model.
    dv, du = np.nonzero(on_part)
    if len(du) > config.max_pixels:
        chosen = rng.choice(len(du), config.max_pixels, replace=False)
        du, dv = du[chosen], dv[chosen]
    cloud = backproject_depth(intrinsics, depth_m, np.stack([du, dv], axis=1))
    refined, _ = icp(T, cloud, targets.model_points, config.icp_iterations, config.icp_max_distance_m)
    if targets.symmetric and config.flip_check_ratio is not None:
        flipped, _ = icp(
            T @ _end_swap(targets), cloud, targets.model_points, config.icp_iterations, config.icp_max_distance_m
        )
        tree = targets.model_tree
        fits = [
            int((tree.query(transform_points(np.linalg.inv(X), cloud), k=1)[0] < FIT_DISTANCE_M).sum())
            for X in (refined, flipped)
        ]
        if fits[1] > config.flip_check_ratio * fits[0]:
            refined = flipped
    T = refined
    return result(T, int(inliers.sum()), ("rings" if targets.symmetric else "kabsch") + "+icp")
