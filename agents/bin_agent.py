"""Agents that pick one part's instances out of a bin (:class:`~don_gym.sim.bin_env.BinPickEnv`), one per step.

Both agents turn what they perceive into the same *instance estimates* (each instance's two axis-end ring
points moved onto its axis, :func:`~don_gym.agents.axis_grasp.surface_to_axis`) and choose among the grasps
of those instances with the same rule (:func:`rank_grasps`):

- :class:`BinAxisGraspAgent` perceives from the descriptor image alone (any descriptor source of the target
  part: the oracle, the part's own network, a network of several parts): for each of the two axis-end
  reference descriptors (:func:`~don_gym.perception.descriptor_sources.axis_end_targets`) the local minima of the
  descriptor distance below a threshold are candidate ring pixels (:func:`~don_gym.perception.keypoints.local_matches`);
  a minus-end and a plus-end candidate make an instance when their axis points lie the part's ring spacing
  apart in 3D (with the observed depth) and the depth between them shows no gap (two rings of neighbouring
  instances have the bin's floor or another part between them) (:func:`pair_ring_candidates`); a part standing
  upright, whose rim both rings' descriptors match at one spot, is found from its top
  (:func:`standing_from_coincident_rings`). When nothing is found, a looser threshold, then one end ring with the
  middle ring (:func:`pair_with_middle_ring`) or a standing part under one ring's match, before the agent gives up.
- :class:`BinOracleAgent` takes the true poses of the target instances the wrist image shows (``info``).

Grasps (:func:`grasp_candidates`): the axis grasp of :class:`~don_gym.agents.AxisGraspAgent` (fingers across
the axis at the part's grasp point); for a part short enough for the opening, also the grasp along its axis
(fingers on the end faces; the action says so, and the env's place turns the hand a further 90 degrees, so
both are placed in the cradle); for a part standing on an end, grasps across it at several yaws (it arrives
upright). Each grasp is checked against the
observed depth (the same point cloud for both agents): no point may lie where the fingers come down
(:func:`finger_obstruction`), and the fingers must stay inside the bin's walls. The preferred grasp: not one
that already failed here, fingers clear, across before along before standing, highest (the top of the pile
first), least occluded.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from don_gym.agents.axis_grasp import AxisGraspAgent, surface_to_axis
from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, backproject_depth, transform_points
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import (
    DEFAULT_AXIS_FRACTIONS,
    AxisEndTargets,
    DescriptorSource,
    PileOracleDescriptors,
    ReferenceFrame,
    axis_end_targets,
    default_reference_descriptors,
    descriptor_field_for,
    load_descriptor_source,
    reference_descriptors_for,
)
from don_gym.perception.keypoints import (
    DEFAULT_SOFT_TEMPERATURE,
    descriptor_distances,
    local_matches,
    robust_point_from_depth,
)
from don_gym.sim.bin_task import (
    BIN_CENTER_XY_M,
    FINGER_BELOW_GRASP_M,
    FINGER_HALF_WIDTH_M,
    FINGER_OUTSIDE_PAD_M,
    bin_inner_bounds,
    grasp_opening_m,
    lying_footprint_m,
    pregrasp_width_m,
)
from don_gym.sim.script import GRASP_KINDS, STEP_KINDS, end_faces_axial_position_m
from don_gym.sim.task import TABLE_TOP_Z_M, grasp_axial_position_m

#: An instance whose +axis is within 45 degrees of vertical stands on an end.
STANDING_AXIS_Z = float(np.sqrt(0.5))
#: Yaws (rad, in [0, pi)) tried for a grasp across a standing instance.
STANDING_YAWS_RAD = tuple(np.linspace(0.0, np.pi, 8, endpoint=False))
#: Room (m) between each finger pad and the part it closes on (end faces of the grasp along the axis).
GRASP_MARGIN_M = 0.003
#: The fingers' footprint is checked from this far (m) inside the open pads, and from this far (m) above the
#: fingertips: the depth sensor's noise and the edges it smears at the part's outline are not obstacles.
PAD_INSET_M = 0.002
NOISE_ABOVE_FINGERTIPS_M = 0.004
#: Share of the fingers' footprint that observed points may cover and still count as clear (stray pixels).
OBSTRUCTION_TOLERANCE = 0.05
#: Share of the fingers' footprint covered beyond which a grasp is tried only after every less crowded one.
CROWDED = 0.3
#: A grasp this close (m) to one that failed, at a yaw this close (rad, modulo pi), counts as tried.
TRIED_RADIUS_M = 0.015
TRIED_YAW_RAD = float(np.deg2rad(25.0))
#: Candidate ring matches: descriptor distance below this fraction of the distance between the two
#: reference descriptors (the two rings), so a match is nearer its own ring than halfway to the other.
DEFAULT_MATCH_FRACTION = 0.4
#: When no instance is found at the match fraction, the search runs once more at this looser one: a pile where the
#: network's matches all fall short would otherwise end with the agent giving up.
DEFAULT_FALLBACK_MATCH_FRACTION = 0.6
#: Two rings pair into an instance when their axis points lie the rings' spacing apart within this
#: fraction of it (or :data:`PAIR_TOLERANCE_MIN_M`, the larger).
PAIR_TOLERANCE_FRACTION = 0.3
PAIR_TOLERANCE_MIN_M = 0.006
#: Depth (m) beyond the two rings' at which a pixel between them is a gap (the pair spans two parts).
GAP_DEPTH_M = 0.015
#: A pixel between the rings this much (m) nearer the camera than both is another part lying on top.
OCCLUDER_DEPTH_M = 0.012
#: Share of the pixels between the rings that may show a gap.
MAX_GAP_FRACTION = 0.2
#: Most candidate pixels per ring kept (the best matches).
MAX_CANDIDATES_PER_RING = 16
#: Both rings' candidates within this fraction of the part's radius of each other mark the top of a part standing
#: upright (a network's matches spread over the rim, the optimal descriptors' coincide); its top's points
#: lie within STANDING_TOP_M (m) of that height, its lower end within STANDING_FLOOR_M (m) of the floor.
COINCIDENT_RADII = 1.0
STANDING_TOP_M = 0.006
STANDING_FLOOR_M = 0.005
#: The top's centre moves to the mean of the points at its height at most this often, until it moves less (m).
STANDING_CENTRE_ITERATIONS = 12
STANDING_CENTRE_SETTLED_M = 0.0005
#: A standing part is also grasped this far (m) below its upper end.
RIM_GRASP_DEPTH_M = 0.012
#: Grasp kinds (:data:`~don_gym.sim.script.GRASP_KINDS`), the preferred first: across the axis, along it (both
#: placed in the cradle: the env's place knows the kind), across a standing part (which arrives upright).
GRASP_KIND_PREFERENCE = ("across", "along", "standing")
#: Axis refinement from the observed surface (:func:`refine_axis_with_depth`): the search's half-ranges of yaw (rad),
#: sideways offset and height (m); below, its steps, the distance (m) from the part's surface within which a point
#: counts as on it, how far above the floor (m) a point must lie, the fewest points near the instance to refine it
#: and the most it uses (an even subset).
REFINE_YAW_RAD = float(np.deg2rad(30.0))
REFINE_OFFSET_M = 0.006
REFINE_HEIGHT_M = 0.004
#: (yaw rad, offset and height m) steps of the coarse search over the whole range, and of the fine one around its
#: best (within one coarse step).
REFINE_COARSE_STEPS = (float(np.deg2rad(6.0)), 0.002)
REFINE_FINE_STEPS = (float(np.deg2rad(2.0)), 0.001)
REFINE_TOLERANCE_M = 0.0015
REFINE_ABOVE_FLOOR_M = 0.003
REFINE_MIN_POINTS = 50
REFINE_MAX_POINTS = 400
#: When the preferred grasp's fingers would reach past the bin's walls (a part lying against a wall, its grasps all
#: blocked), the agent pushes the part away from the wall first (the env's "push" step), at most this many times
#: in a row before it tries the grasp anyway. 0: never push.
MAX_PUSHES_IN_A_ROW = 2
#: A part standing on an end, when it is the preferred grasp, is first toppled where it stands (a push at its top:
#: :func:`topple_standing`), which costs less motion than setting it down at the regrasp station and grasping it
#: there; a standing part whose top lies within TOPPLE_TRIED_RADIUS_M (m) of this many earlier topples goes to the
#: station (the agent's ``max_topples_per_part``). 0: never topple (every standing part goes to the station).
MAX_TOPPLES_PER_PART = 1
TOPPLE_TRIED_RADIUS_M = 0.03
#: The topple presses this many of the part's radii short of its top's centre (on the side it is pushed from), so
#: the fingers drag the top's near half over the far edge of its foot.
TOPPLE_OFFSET_RADII = 0.5


@dataclass(frozen=True)
class InstanceEstimate:
    """One perceived instance of the target part, world frame, metres.

    Attributes:
        axis_points_world: (2, 3) points on the axis at the minus-end and plus-end rings' axial positions.
        occlusion: share (0..1) of the instance's seen stretch between its rings covered by something nearer.
        match_distance: the larger of its two rings' descriptor distances (0 for the oracle).
        instance: the true instance id (oracle), else None.
    """

    axis_points_world: np.ndarray
    occlusion: float = 0.0
    match_distance: float = 0.0
    instance: int | None = None
    #: Indices of the (minus-end, plus-end) ring candidates it was made of (None: not from candidates, or one ring).
    rings: tuple[int | None, int | None] | None = None

    @property
    def upper_axis_point(self) -> np.ndarray:
        """(3,) the higher of the two axis points (the top of a standing instance)."""
        return max(np.asarray(self.axis_points_world, dtype=np.float64), key=lambda p: float(p[2]))

    @property
    def direction(self) -> np.ndarray:
        """(3,) unit +axis direction."""
        d = self.axis_points_world[1] - self.axis_points_world[0]
        return d / max(float(np.linalg.norm(d)), 1e-12)

    @property
    def standing(self) -> bool:
        return abs(float(self.direction[2])) > STANDING_AXIS_Z


@dataclass(frozen=True)
class GraspCandidate:
    """A grasp of one instance estimate: the action ``[x, y, z, yaw, kind]`` (yaw: the direction the env takes for
    the part's +axis; kind: the index of :attr:`kind` in :data:`~don_gym.sim.script.GRASP_KINDS`, the fingers
    closing across the yaw, or along it for ``"along"``), its kind, the share of the fingers' footprint that
    observed points cover (:func:`finger_obstruction`), whether the fingers stay inside the walls, and the
    estimate's index."""

    action: np.ndarray
    kind: str
    obstruction: float
    walls_clear: bool
    estimate_index: int

    @property
    def clear(self) -> bool:
        return self.walls_clear and self.obstruction <= OBSTRUCTION_TOLERANCE


def closing_yaw_rad(action: np.ndarray) -> float:
    """The yaw (rad) across which the fingers of a grasp action close: the +axis yaw ``action[3]``, turned 90
    degrees for a grasp along the axis (kind ``action[4]``; a 4-number action is across)."""
    along = len(action) > 4 and GRASP_KINDS[int(round(float(action[4])))] == "along"
    return float(action[3]) + (np.pi / 2 if along else 0.0)


# ------------------------------------------------------------------------------------------------
# Pure core: clearance, grasps, ranking, ring pairing
# ------------------------------------------------------------------------------------------------


def _closing_frame(yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(along, across) unit xy vectors of a grasp whose +axis yaw is ``yaw_rad``: the fingers close along ``across``."""
    along = np.array([np.cos(yaw_rad), np.sin(yaw_rad)])
    return along, np.array([-along[1], along[0]])


def finger_obstruction(points_world: np.ndarray, action: np.ndarray, opening_m: float, pixel_area_m2: float) -> float:
    """Share of the two fingers' footprint (a top-down grasp ``action`` opened to ``opening_m``) that observed
    points (N, 3) cover above the fingertips: points across the axis from the pads (less :data:`PAD_INSET_M`) to
    the fingers' outside (:data:`~don_gym.sim.bin_task.FINGER_OUTSIDE_PAD_M` beyond), within
    :data:`~don_gym.sim.bin_task.FINGER_HALF_WIDTH_M` along it, higher than
    :data:`~don_gym.sim.bin_task.FINGER_BELOW_GRASP_M` below the grasp point (plus the sensor's noise), counted
    against the points the footprint holds at ``pixel_area_m2`` (one pixel's patch of table at the depth seen)."""
    along, across = _closing_frame(closing_yaw_rad(action))
    relative = points_world[:, :2] - np.asarray(action[:2], dtype=np.float64)
    a, c = np.abs(relative @ along), np.abs(relative @ across)
    inner, outer = opening_m / 2 - PAD_INSET_M, opening_m / 2 + FINGER_OUTSIDE_PAD_M
    blocked = (
        (a <= FINGER_HALF_WIDTH_M)
        & (c >= inner)
        & (c <= outer)
        & (points_world[:, 2] > float(action[2]) - FINGER_BELOW_GRASP_M + NOISE_ABOVE_FINGERTIPS_M)
    )
    footprint_points = 2 * (2 * FINGER_HALF_WIDTH_M) * (outer - inner) / max(pixel_area_m2, 1e-12)
    return float(blocked.sum()) / footprint_points


def fingers_inside_walls(action: np.ndarray, opening_m: float) -> bool:
    """Whether the footprint of the open fingers of ``action`` lies inside the bin's walls."""
    along, across = _closing_frame(closing_yaw_rad(action))
    span = opening_m / 2 + FINGER_OUTSIDE_PAD_M
    x0, x1, y0, y1 = bin_inner_bounds()
    for c in (-span, span):
        for a in (-FINGER_HALF_WIDTH_M, FINGER_HALF_WIDTH_M):
            x, y = np.asarray(action[:2], dtype=np.float64) + c * across + a * along
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                return False
    return True


def grasp_candidates(
    estimates: Sequence[InstanceEstimate],
    points_world: np.ndarray,
    object_model: ObjectModel,
    targets: AxisEndTargets,
    grasp_axial_m: float,
    pixel_area_m2: float,
) -> list[GraspCandidate]:
    """Every grasp of every instance estimate (module docstring) with its clearance in the observed point cloud
    (N, 3), world metres, of pixels covering ``pixel_area_m2`` each (:func:`finger_obstruction`)."""
    length, diameter = lying_footprint_m(object_model)
    t1, t2 = (float(t) for t in targets.axial_positions_m)
    axial = (np.asarray(object_model.mesh.vertices, dtype=np.float64) - object_model.center_of_mass) @ np.asarray(
        object_model.plus_axis, dtype=np.float64
    )
    middle_axial = end_faces_axial_position_m(object_model)  # the along grasp's fingers close on the end faces
    along_axis_fits = length + 2 * GRASP_MARGIN_M <= pregrasp_width_m(object_model, "along")
    out: list[GraspCandidate] = []
    for index, estimate in enumerate(estimates):
        q1, q2 = estimate.axis_points_world
        direction = estimate.direction
        grasp = q1 + (grasp_axial_m - t1) / (t2 - t1) * (q2 - q1)
        yaw = float(np.arctan2(direction[1], direction[0]))
        actions: list[tuple[np.ndarray, str]] = []  # [x, y, z, +axis yaw], kind
        if estimate.standing:
            # Across the part at its grasp point, or higher, around the upper rim: the fingertips then stay above
            # the parts lying around it.
            ends = [q1 + (end - t1) / (t2 - t1) * (q2 - q1) for end in (axial.min(), axial.max())]
            top = max(ends, key=lambda p: float(p[2]))
            upward = (top - grasp) / max(float(np.linalg.norm(top - grasp)), 1e-9)
            rim = top - RIM_GRASP_DEPTH_M * upward
            for point in (grasp, rim):
                for standing_yaw in STANDING_YAWS_RAD:
                    actions.append((np.array([*point, standing_yaw], dtype=np.float64), "standing"))
        else:
            actions.append((np.array([*grasp, yaw], dtype=np.float64), "across"))
            if along_axis_fits:
                # Fingers on the end faces, the believed +axis yaw kept: the env turns the hand for the place.
                middle = q1 + (middle_axial - t1) / (t2 - t1) * (q2 - q1)
                actions.append((np.array([*middle, yaw], dtype=np.float64), "along"))
        for pose, kind in actions:
            pose[3] = float(np.arctan2(np.sin(pose[3]), np.cos(pose[3])))
            action = np.append(pose, float(GRASP_KINDS.index(kind)))
            opening = grasp_opening_m(object_model, kind, pose[:2], float(pose[3]))
            out.append(
                GraspCandidate(
                    action=action.astype(np.float32),
                    kind=kind,
                    obstruction=finger_obstruction(points_world, action, opening, pixel_area_m2),
                    walls_clear=fingers_inside_walls(action, opening),
                    estimate_index=index,
                )
            )
    return out


def push_away_from_walls(candidate: GraspCandidate, estimate: InstanceEstimate) -> np.ndarray:
    """The push step (5,) float32 ``[x, y, z, yaw, kind]`` that rolls a lying instance whose ``candidate`` grasp
    is blocked by a wall towards the bin's middle: pressed at the grasp point, pushed across the perceived axis
    (a round part rolls that way), on the side of the bin's centre."""
    point = np.asarray(candidate.action[:3], dtype=np.float64)
    along, across = _closing_frame(float(np.arctan2(estimate.direction[1], estimate.direction[0])))
    towards_middle = BIN_CENTER_XY_M - point[:2]
    direction = across if float(across @ towards_middle) >= 0.0 else -across
    yaw = float(np.arctan2(direction[1], direction[0]))
    return np.array([*point, yaw, float(STEP_KINDS.index("push"))], dtype=np.float32)


def topple_standing(estimate: InstanceEstimate, object_model: ObjectModel) -> np.ndarray:
    """The push step (5,) float32 ``[x, y, z, yaw, kind]`` that topples a standing instance: the closed fingers come
    down on its top :data:`TOPPLE_OFFSET_RADII` radii short of the top's centre and push towards the bin's middle
    (where the part has the most room to fall), at the height of its upper axis point (the env's push comes down
    until it touches)."""
    top = estimate.upper_axis_point
    towards_middle = BIN_CENTER_XY_M - top[:2]
    yaw = float(np.arctan2(towards_middle[1], towards_middle[0]))
    radius = lying_footprint_m(object_model)[1] / 2
    press = top[:2] - TOPPLE_OFFSET_RADII * radius * np.array([np.cos(yaw), np.sin(yaw)])
    return np.array([*press, top[2], yaw, float(STEP_KINDS.index("push"))], dtype=np.float32)


def times_toppled(estimate: InstanceEstimate, topple_actions: Sequence[np.ndarray]) -> int:
    """How many earlier topples (their push actions) pressed within :data:`TOPPLE_TRIED_RADIUS_M` (xy) of the top of
    the standing ``estimate``."""
    top = estimate.upper_axis_point
    return sum(float(np.linalg.norm(top[:2] - np.asarray(a[:2]))) <= TOPPLE_TRIED_RADIUS_M for a in topple_actions)


def times_tried(action: np.ndarray, failed_actions: Sequence[np.ndarray]) -> int:
    """How many failed grasps lie within :data:`TRIED_RADIUS_M` and :data:`TRIED_YAW_RAD` (modulo pi) of a grasp,
    the yaws the fingers close across (:func:`closing_yaw_rad`)."""
    tried = 0
    for failed in failed_actions:
        near = float(np.linalg.norm(np.asarray(action[:3]) - np.asarray(failed[:3]))) <= TRIED_RADIUS_M
        turn = abs(closing_yaw_rad(action) - closing_yaw_rad(failed)) % np.pi
        tried += bool(near and min(turn, np.pi - turn) <= TRIED_YAW_RAD)
    return tried


def rank_grasps(
    candidates: Sequence[GraspCandidate],
    estimates: Sequence[InstanceEstimate],
    failed_actions: Sequence[np.ndarray] = (),
) -> list[GraspCandidate]:
    """The candidates, the preferred first: tried least (:func:`times_tried`), fingers inside the walls, not
    crowded (:data:`CROWDED`), fingers clear, the kind (:data:`GRASP_KIND_PREFERENCE` order), grasp point highest
    (the top of the pile first), least occluded, least of the fingers' footprint covered."""

    def key(candidate: GraspCandidate) -> tuple:
        estimate = estimates[candidate.estimate_index]
        return (
            times_tried(candidate.action, failed_actions),
            not candidate.walls_clear,
            candidate.obstruction > CROWDED,
            # Clear fingers before the kind: on the 16 development piles with a failed lift, a third of the across
            # grasps with a neighbour under a finger (walls clear, obstruction up to CROWDED) failed to lift, while
            # every clear grasp of any kind lifted, and an along grasp is placed as an across one is.
            not candidate.clear,
            GRASP_KIND_PREFERENCE.index(candidate.kind),
            -round(float(candidate.action[2]) * 100.0),  # centimetres: parts at one level rank by what follows
            round(estimate.occlusion, 1),
            round(candidate.obstruction, 2),
        )

    return sorted(candidates, key=key)


def world_point_cloud(depth_m: np.ndarray, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray) -> np.ndarray:
    """(N, 3) world points (metres) of every pixel with a depth return."""
    depth = np.asarray(depth_m, dtype=np.float64)
    points = backproject_depth(intrinsics, depth)[depth > 0]
    return transform_points(np.asarray(T_world_camera, dtype=np.float64), points)


def _segment_depth_shares(
    depth_m: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray, depth_a: float, depth_b: float, samples: int = 12
) -> tuple[float, float]:
    """(gap share, occluder share) of the observed depth on the image segment between two ring pixels: pixels
    :data:`GAP_DEPTH_M` deeper than both rings, and :data:`OCCLUDER_DEPTH_M` nearer than both, among those with
    a return."""
    H, W = depth_m.shape
    t = np.linspace(0.15, 0.85, samples)[:, None]
    uv = np.rint(uv_a[None] + t * (uv_b - uv_a)[None]).astype(int)
    uv[:, 0] = np.clip(uv[:, 0], 0, W - 1)
    uv[:, 1] = np.clip(uv[:, 1], 0, H - 1)
    z = depth_m[uv[:, 1], uv[:, 0]]
    z = z[z > 0]
    if len(z) == 0:
        return 0.0, 0.0
    deep = float(np.mean(z > max(depth_a, depth_b) + GAP_DEPTH_M))
    near = float(np.mean(z < min(depth_a, depth_b) - OCCLUDER_DEPTH_M))
    return deep, near


def _middle_distance(distances: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> float:
    """Smallest distance in a 5 x 5 window around the pixel halfway between two pixels."""
    H, W = distances.shape
    u, v = np.rint((np.asarray(uv_a) + np.asarray(uv_b)) / 2).astype(int)
    window = distances[max(v - 2, 0) : min(v + 3, H), max(u - 2, 0) : min(u + 3, W)]
    return float(window.min()) if window.size else np.inf


def pair_ring_candidates(
    points_world: Sequence[np.ndarray],
    pixels: Sequence[np.ndarray],
    distances: Sequence[np.ndarray],
    depth_m: np.ndarray,
    T_world_camera: np.ndarray,
    targets: AxisEndTargets,
    middle_distances: np.ndarray | None = None,
    middle_threshold: float = np.inf,
    floor_z_m: float | None = None,
) -> list[InstanceEstimate]:
    """Instances from candidate ring matches: ``points_world[k]`` (M_k, 3) world points, ``pixels[k]`` (M_k, 2)
    and ``distances[k]`` (M_k,) of the minus-end (k = 0) and plus-end (k = 1) candidates. A pair is an instance
    when its axis points (:func:`~don_gym.agents.axis_grasp.surface_to_axis`) lie the rings' spacing apart
    (within :data:`PAIR_TOLERANCE_FRACTION`) and at most :data:`MAX_GAP_FRACTION` of the depth between their
    pixels lies deeper than both, and (given ``middle_distances`` (H, W), the descriptor distance to the ring halfway
    between the two) the pixel halfway between them matches that ring within ``middle_threshold`` (two rings of one
    part have the part between them, not another part); pairs are taken best first (spacing error, then descriptor
    distance), each candidate in one instance at most. Given the bin floor's height ``floor_z_m`` (world z, m), both
    axis points must lie at least half a ring radius above it: the rings of a thinner part (another part's surface
    taken for this one's) put the axis into the floor."""
    camera = np.asarray(T_world_camera, dtype=np.float64)[:3, 3]
    depth = np.asarray(depth_m, dtype=np.float64)
    spacing = float(abs(targets.axial_positions_m[1] - targets.axial_positions_m[0]))
    tolerance = max(PAIR_TOLERANCE_FRACTION * spacing, PAIR_TOLERANCE_MIN_M)
    camera_z = [
        np.linalg.norm(np.asarray(p, dtype=np.float64) - camera, axis=1) if len(p) else np.zeros(0)
        for p in points_world
    ]
    pairs = []
    for i in range(len(points_world[0])):
        for j in range(len(points_world[1])):
            ends = np.stack([points_world[0][i], points_world[1][j]])
            try:
                axis_points, _ = surface_to_axis(ends, camera, targets.radii_m)
            except DonGymError:
                continue
            error = abs(float(np.linalg.norm(axis_points[1] - axis_points[0])) - spacing)
            if error > tolerance:
                continue
            if floor_z_m is not None and float(axis_points[:, 2].min()) < floor_z_m + 0.5 * float(
                np.min(targets.radii_m)
            ):
                continue
            gap, occluded = _segment_depth_shares(
                depth, pixels[0][i], pixels[1][j], float(camera_z[0][i]), float(camera_z[1][j])
            )
            if gap > MAX_GAP_FRACTION:
                continue
            if middle_distances is not None and _middle_distance(middle_distances, pixels[0][i], pixels[1][j]) > (
                middle_threshold
            ):
                continue
            score = error / tolerance + max(float(distances[0][i]), float(distances[1][j]))
            pairs.append((score, i, j, axis_points, occluded, max(float(distances[0][i]), float(distances[1][j]))))
    pairs.sort(key=lambda p: p[0])
    used_minus, used_plus, estimates = set(), set(), []
    for _, i, j, axis_points, occluded, distance in pairs:
        if i in used_minus or j in used_plus:
            continue
        used_minus.add(i)
        used_plus.add(j)
        estimates.append(InstanceEstimate(axis_points, occlusion=occluded, match_distance=distance, rings=(i, j)))
    return estimates


def pair_with_middle_ring(
    rings: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    middle: tuple[np.ndarray, np.ndarray, np.ndarray],
    depth_m: np.ndarray,
    T_world_camera: np.ndarray,
    targets: AxisEndTargets,
    floor_z_m: float | None = None,
) -> list[InstanceEstimate]:
    """Instances from one end ring's candidates and the middle ring's (the ring halfway between the two ends,
    :func:`middle_ring_points`), each given as ``(points_world (M, 3), pixels (M, 2), distances (M,))``: the minus
    end (``rings[0]``) then the plus end (``rings[1]``) paired with ``middle`` as :func:`pair_ring_candidates` pairs
    the two ends, at half their spacing, the far end's axis point put as far beyond the middle. A network's matches
    of one end ring can fall short of it, towards the middle (lying toolcaps on the development piles: 4 to 12 mm
    apart where 24 mm was due); the other end and the middle then still give the axis. Pairs of the minus end are
    tried first; each middle candidate serves one instance."""
    a_minus, a_plus = (float(v) for v in targets.axial_positions_m)
    r_minus, r_plus = (float(v) for v in targets.radii_m)
    a_middle, r_middle = (a_minus + a_plus) / 2, float(np.max(targets.radii_m))
    found: list[InstanceEstimate] = []
    used_middle: set[int] = set()
    # (axial positions, radii, candidates) minus-end first as pair_ring_candidates takes them, and which is the end.
    for positions, radii, candidates, end in (
        ((a_minus, a_middle), (r_minus, r_middle), (rings[0], middle), 0),
        ((a_middle, a_plus), (r_middle, r_plus), (middle, rings[1]), 1),
    ):
        half = replace(targets, axial_positions_m=np.asarray(positions), radii_m=np.asarray(radii))
        for estimate in pair_ring_candidates(
            [c[0] for c in candidates], [c[1] for c in candidates], [c[2] for c in candidates],
            depth_m, T_world_camera, half, floor_z_m=floor_z_m,
        ):  # fmt: skip
            middle_index = estimate.rings[1 - end]
            if middle_index in used_middle:
                continue
            used_middle.add(middle_index)
            axis_points = estimate.axis_points_world.copy()
            axis_points[1 - end] = 2.0 * axis_points[1 - end] - axis_points[end]  # the far end, beyond the middle
            found.append(replace(estimate, axis_points_world=axis_points, rings=None))
    return found


def radial_profile_m(object_model: ObjectModel, bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """The part's outer radius along its axis: ``(axial_m (bins,), radius_m (bins,))``, the bins' centres (m from the
    centre of mass along the +axis) and the largest distance of the mesh's vertices in each from the axis (a bin
    without vertices takes its neighbours' larger)."""
    relative = np.asarray(object_model.mesh.vertices, dtype=np.float64) - object_model.center_of_mass
    plus_axis = np.asarray(object_model.plus_axis, dtype=np.float64)
    along = relative @ plus_axis
    radial = np.linalg.norm(relative - np.outer(along, plus_axis), axis=1)
    edges = np.linspace(along.min(), along.max(), bins + 1)
    index = np.clip(np.searchsorted(edges, along, side="right") - 1, 0, bins - 1)
    radius = np.full(bins, np.nan)
    for b in range(bins):
        if (index == b).any():
            radius[b] = radial[index == b].max()
    for b in np.flatnonzero(np.isnan(radius)):
        neighbours = radius[max(b - 1, 0) : b + 2]
        radius[b] = np.nanmax(neighbours) if np.isfinite(neighbours).any() else np.nanmax(radius)
    return (edges[:-1] + edges[1:]) / 2, radius


def refine_axis_with_depth(
    estimate: InstanceEstimate,
    cloud_world: np.ndarray,
    targets: AxisEndTargets,
    profile: tuple[np.ndarray, np.ndarray],
    floor_z_m: float,
) -> InstanceEstimate:
    """A lying instance's axis fitted to the observed surface: the yaw (within :data:`REFINE_YAW_RAD`), the sideways
    offset (within :data:`REFINE_OFFSET_M`) and the height (within :data:`REFINE_HEIGHT_M`) for which the most
    observed points (``cloud_world`` (N, 3), m) between the two rings lie on the part's surface (the radius of
    ``profile``, :func:`radial_profile_m`, within :data:`REFINE_TOLERANCE_M`), the axis's tilt and its length along
    it kept; which end is which stays the descriptors'. A network's ring matches put the axis some degrees off
    (on the development piles, the grasps of ``bin/supervised-edge`` that lifted a toolcap but did not place it were
    mostly 15 to 45 degrees off in yaw); the seen surface of a lying part holds its axis to a degree or two. The
    estimate is kept as it is when it stands, when fewer than :data:`REFINE_MIN_POINTS` points lie near it, or
    when no fit holds more points on the surface than the estimate itself."""
    if estimate.standing:
        return estimate
    axial, radius = profile
    a0, a1 = (float(v) for v in targets.axial_positions_m)
    centre = estimate.axis_points_world.mean(axis=0)
    direction = estimate.direction
    reach = float(np.max(radius)) + REFINE_OFFSET_M + REFINE_TOLERANCE_M
    half = abs(a1 - a0) / 2 + REFINE_OFFSET_M
    cloud = np.asarray(cloud_world, dtype=np.float64).reshape(-1, 3)
    relative = cloud - centre
    near = (
        (np.abs(relative @ direction) < half)
        & (np.linalg.norm(relative - np.outer(relative @ direction, direction), axis=1) < reach)
        & (cloud[:, 2] > floor_z_m + REFINE_ABOVE_FLOOR_M)
    )
    points = cloud[near]
    if len(points) < REFINE_MIN_POINTS:
        return estimate
    # An even subset keeps the search to a few hundredths of a second per instance.
    points = points[:: max(1, len(points) // REFINE_MAX_POINTS)]
    middle_axial = (a0 + a1) / 2
    lo, hi = sorted((a0, a1))

    def surface_counts(centres: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Points on the surface of the part whose axis runs along ``d`` (3,) through each of ``centres`` (K, 3)."""
        rel = points[None] - centres[:, None]
        along = rel @ d
        across = np.linalg.norm(rel - along[..., None] * d, axis=-1)
        position = along + middle_axial
        on = np.abs(across - np.interp(position, axial, radius)) < REFINE_TOLERANCE_M
        return (on & (position >= lo) & (position <= hi)).sum(axis=-1)

    def turned(yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """The estimate's direction turned by ``yaw`` about the vertical (its tilt kept), and the horizontal unit
        vector across it."""
        c, s_ = np.cos(yaw), np.sin(yaw)
        d = np.array([c * direction[0] - s_ * direction[1], s_ * direction[0] + c * direction[1], direction[2]])
        side = np.cross([0.0, 0.0, 1.0], d)
        return d, side / max(float(np.linalg.norm(side)), 1e-12)

    own = int(surface_counts(centre[None], direction)[0])
    best_count, best_yaw, best_shift = own, 0.0, np.zeros(2)
    # Coarse to fine: the whole range at the coarse steps, then the fine steps around the coarse best.
    for (yaw_step, shift_step), (yaw_range, shift_range) in (
        (REFINE_COARSE_STEPS, (REFINE_YAW_RAD, np.array([REFINE_OFFSET_M, REFINE_HEIGHT_M]))),
        (REFINE_FINE_STEPS, (REFINE_COARSE_STEPS[0] - REFINE_FINE_STEPS[0], np.full(2, REFINE_COARSE_STEPS[1]))),
    ):
        yaw_centre, shift_centre = best_yaw, best_shift.copy()
        yaws = yaw_centre + np.arange(-yaw_range, yaw_range + 1e-9, yaw_step)
        offsets = shift_centre[0] + np.arange(-shift_range[0], shift_range[0] + 1e-9, shift_step)
        heights = shift_centre[1] + np.arange(-shift_range[1], shift_range[1] + 1e-9, shift_step)
        shifts = np.stack(np.meshgrid(offsets, heights, indexing="ij"), axis=-1).reshape(-1, 2)
        for yaw in sorted(yaws, key=lambda y: abs(y - yaw_centre)):
            d, side = turned(float(yaw))
            centres = centre + shifts[:, :1] * side + shifts[:, 1:] * np.array([0.0, 0.0, 1.0])
            counts = surface_counts(centres, d)
            k = int(np.argmax(counts))
            if counts[k] > best_count:
                best_count, best_yaw, best_shift = int(counts[k]), float(yaw), shifts[k]
    best_direction, side = turned(best_yaw)
    best_centre = centre + best_shift[0] * side + best_shift[1] * np.array([0.0, 0.0, 1.0])
    if best_count <= own:
        return estimate
    axis_points = np.stack([best_centre + (a - middle_axial) * best_direction for a in (a0, a1)])
    return replace(estimate, axis_points_world=axis_points)


@dataclass(frozen=True)
class _DepthView:
    """What the agents need of one observation's depth, worked out once per ``act``: the depth image
    (H, W) float32 (m), the intrinsics, ``T_world_camera`` (4, 4), the point cloud (N, 3) of every pixel with depth
    (world, m), the median depth (m) and the candidate suppression window (pixels: a ring's diameter at the median
    depth), shared by the descriptor agent's searches and the grasp choice."""

    depth_m: np.ndarray
    intrinsics: CameraIntrinsics
    T_world_camera: np.ndarray
    cloud_world: np.ndarray
    typical_z_m: float
    window_px: float

    @classmethod
    def of(cls, obs: Mapping[str, Any], window_m: float) -> _DepthView:
        depth = np.asarray(obs["depth"], dtype=np.float32)
        intrinsics = CameraIntrinsics.from_array(obs["camera_intrinsics"])
        T_world_camera = np.asarray(obs["camera_pose"], dtype=np.float64)
        valid = depth[depth > 0]
        typical_z = float(np.median(valid)) if len(valid) else 0.45
        # One candidate per ring: minima closer than a ring's diameter are one ring's arc.
        window_px = intrinsics.fx * window_m / typical_z
        cloud = world_point_cloud(depth, intrinsics, T_world_camera)
        return cls(depth, intrinsics, T_world_camera, cloud, typical_z, window_px)


# ------------------------------------------------------------------------------------------------
# Agents
# ------------------------------------------------------------------------------------------------


def _target_model(env: gym.Env) -> ObjectModel:
    base = env.unwrapped
    models, target = getattr(base, "models", None), getattr(base, "target", None)
    if not isinstance(models, Mapping) or target not in models:
        raise DonGymError(
            f"{type(base).__name__} is not a bin env (no models/target); expected a don_gym.sim.bin_env.BinPickEnv"
        )
    return models[target]


class _BinAgentBase:
    """What both agents share: the target part's geometry, the grasp choice and the memory of failed grasps."""

    def _setup_geometry(self, object_model: ObjectModel, targets: AxisEndTargets) -> None:
        self.object_model = object_model
        self.targets = targets
        #: Axial position (m from the centre of mass along +axis) of the axis grasp.
        self.grasp_axial_m = grasp_axial_position_m(object_model)
        #: Actions of this episode's grasps that lifted nothing (tried last).
        self.failed_actions: list[np.ndarray] = []
        self.last_action: np.ndarray | None = None
        #: The last choice: the instance estimates and the ranked grasps.
        self.last_estimates: list[InstanceEstimate] = []
        self.last_ranking: list[GraspCandidate] = []
        #: Pushes in a row allowed before a grasp blocked by a wall is tried anyway (:data:`MAX_PUSHES_IN_A_ROW`).
        self.max_pushes_in_a_row = MAX_PUSHES_IN_A_ROW
        self.pushes_in_a_row = 0
        #: Topples of one standing part before it goes to the station (:data:`MAX_TOPPLES_PER_PART`), and this
        #: episode's topples (their push actions).
        self.max_topples_per_part = MAX_TOPPLES_PER_PART
        self.topple_actions: list[np.ndarray] = []

    def reset(self) -> None:
        """Forget the failed grasps and the topples (call at every env reset)."""
        self.failed_actions = []
        self.last_action = None
        self.pushes_in_a_row = 0
        self.topple_actions = []

    def observe_outcome(self, outcome: str) -> None:
        """Tell the agent the outcome of its last action (``info["outcome"]``): a ``"fail"`` (nothing lifted, as the
        gripper's width tells a real robot) makes that grasp one to try last."""
        if outcome == "fail" and self.last_action is not None:
            self.failed_actions.append(self.last_action)

    def estimates(
        self, obs: Mapping[str, Any], info: Mapping[str, Any] | None, view: _DepthView | None = None
    ) -> list[InstanceEstimate]:
        """The target instances ``obs`` shows (``view``: the observation's depth worked out, when the caller has it)."""
        raise NotImplementedError

    def station_estimates(self, obs: Mapping[str, Any], info: Mapping[str, Any] | None) -> list[InstanceEstimate]:
        raise NotImplementedError

    def act(self, obs: Mapping[str, Any], info: Mapping[str, Any] | None = None) -> np.ndarray:
        """The grasp-mode action (5,) float32 ``[x, y, z, yaw, kind]`` for one observation, the preferred grasp (or a
        push away from a wall that blocks it: :data:`MAX_PUSHES_IN_A_ROW`; or, where it stands on an end, a push
        that topples it: :data:`MAX_TOPPLES_PER_PART`) (``info``: the step's,
        which the oracle and oracle descriptors need, and whose ``phase`` "regrasp" says the observation shows the
        regrasp station: :meth:`station_estimates`). DonGymError when no instance of the target part is found."""
        at_station = info is not None and info.get("phase") == "regrasp"
        view = _DepthView.of(obs, self.targets.window_m)
        estimates = self.station_estimates(obs, info) if at_station else self.estimates(obs, info, view)
        if not estimates:
            raise DonGymError(f"no instance of {self.object_model.name!r} found in the image")
        intrinsics = view.intrinsics
        pixel_area = (view.typical_z_m / intrinsics.fx) * (view.typical_z_m / intrinsics.fy)
        candidates = grasp_candidates(
            estimates, view.cloud_world, self.object_model, self.targets, self.grasp_axial_m, pixel_area
        )
        ranking = rank_grasps(candidates, estimates, self.failed_actions)
        self.last_estimates, self.last_ranking = estimates, ranking
        best = ranking[0]
        estimate = estimates[best.estimate_index]
        blocked = not best.walls_clear and best.kind != "standing" and not at_station
        topple = (
            best.kind == "standing"
            and not at_station
            and times_toppled(estimate, self.topple_actions) < self.max_topples_per_part
        )
        if topple:
            self.last_action = topple_standing(estimate, self.object_model)
            self.topple_actions.append(self.last_action)
        elif blocked and self.pushes_in_a_row < self.max_pushes_in_a_row:
            self.pushes_in_a_row += 1
            self.last_action = push_away_from_walls(best, estimate)
        else:
            self.pushes_in_a_row = 0
            self.last_action = np.asarray(best.action, dtype=np.float32)
        return self.last_action.copy()


class BinOracleAgent(_BinAgentBase):
    """Picks with perfect perception of instances: the true poses of the target instances the wrist image shows
    (``info["instances"]`` with visible pixels), the grasp chosen as :class:`BinAxisGraspAgent` chooses it.

    ``agent = BinOracleAgent(env)``; per episode ``agent.reset()``, then ``action = agent.act(obs, info)`` and
    ``agent.observe_outcome(info["outcome"])`` after each step.
    """

    def __init__(self, env: gym.Env, fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS) -> None:
        object_model = _target_model(env)
        self._setup_geometry(object_model, axis_end_targets(object_model, fractions=fractions))
        self.method = "oracle"

    def estimates(
        self, obs: Mapping[str, Any], info: Mapping[str, Any] | None, view: _DepthView | None = None
    ) -> list[InstanceEstimate]:
        if info is None or "instances" not in info:
            raise DonGymError("the bin oracle needs the step's info with 'instances' (true poses); pass act(obs, info)")
        model = self.object_model
        out = []
        for instance in info["instances"]:
            if instance["part"] != model.name or not instance.get("visible_pixels"):
                continue
            T = np.asarray(instance["T_world_object"], dtype=np.float64)
            local = model.center_of_mass + np.outer(self.targets.axial_positions_m, model.plus_axis)
            out.append(InstanceEstimate(transform_points(T, local), instance=int(instance["instance"])))
        return out

    def station_estimates(self, obs: Mapping[str, Any], info: Mapping[str, Any] | None) -> list[InstanceEstimate]:
        """The true pose of the instance set down at the regrasp station (``info["regrasp_instance"]``)."""
        wanted = None if info is None else info.get("regrasp_instance")
        return [e for e in self.estimates(obs, info) if e.instance == wanted]

    def __repr__(self) -> str:
        return f"BinOracleAgent(part={self.object_model.name!r})"


class BinAxisGraspAgent(_BinAgentBase):
    """Picks the target part's instances from the descriptor image alone (module docstring).

    ``agent = BinAxisGraspAgent(env, model)``; per episode ``agent.reset()``, then ``action = agent.act(obs, info)``
    (``info`` only feeds oracle descriptors) and ``agent.observe_outcome(info["outcome"])`` after each step.

    Args:
        env: a bin env (:class:`~don_gym.sim.bin_env.BinPickEnv`) with images; its target part is the one picked.
        model: ``"oracle"`` (every instance of the part rendered from the true poses,
            :class:`~don_gym.perception.descriptor_sources.PileOracleDescriptors`), a shipped network, a checkpoint
            (of the
            part, or of several parts including it), a DenseObjectNet or a DescriptorSource of the part.
        reference_frame: where a network whose descriptor space is not the optimal field reads its reference
            descriptors (None: a single-part pick env of the target part, reset at the fixed reference pose).
        fractions: axial fractions of the two ring keypoints.
        match_fraction: candidate ring matches lie below this fraction of the distance between the two reference
            descriptors.
        temperature: soft-match weight scale (in the part's own field's descriptor units: a network of several
            parts scales it by :attr:`~don_gym.perception.descriptor_sources.DescriptorSource.descriptor_scale`)
            that moves
            each candidate to its ring's arc middle.
        fallback_match_fraction: when no instance is found, the search is run once more at this looser fraction
            (None: never), before the agent gives up.
        last_resort: when neither search finds an instance, take one from an end ring and the middle ring, or a
            part standing under one ring's match (:meth:`_last_resort_estimates`), before the agent gives up.
        refine_axis: fit each lying instance's axis (yaw, sideways offset, height) to the observed surface
            (:func:`refine_axis_with_depth`; which end is which stays the descriptors'), and set each standing one
            upright through the centre of its top (:func:`upright_axis_from_top`).
    """

    def __init__(
        self,
        env: gym.Env,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        reference_frame: ReferenceFrame | None = None,
        fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS,
        match_fraction: float = DEFAULT_MATCH_FRACTION,
        temperature: float = DEFAULT_SOFT_TEMPERATURE,
        fallback_match_fraction: float | None = DEFAULT_FALLBACK_MATCH_FRACTION,
        last_resort: bool = True,
        refine_axis: bool = True,
    ) -> None:
        object_model = _target_model(env)
        if isinstance(model, (str, Path)) and str(model) == "oracle":
            source: DescriptorSource = PileOracleDescriptors(object_model)
        else:
            source = load_descriptor_source(model, object_model)
        field = source.field if source.reference_from_field else descriptor_field_for(object_model)
        targets = axis_end_targets(object_model, field, fractions)
        if reference_frame is None and not source.reference_from_field:
            reference_frame = single_part_reference_frame(object_model, env)
        reference = default_reference_descriptors(source, targets, None, reference_frame)
        # The ring halfway between the two: a pair of rings is one instance only with it between them.
        middle = reference_descriptors_for(source, [middle_ring_points(object_model, targets)], reference_frame)[0]
        if not (np.isfinite(match_fraction) and 0.0 < match_fraction <= 1.0):
            raise DonGymError(f"match_fraction={match_fraction!r}: expected a fraction in (0, 1]")
        if fallback_match_fraction is not None and not (
            np.isfinite(fallback_match_fraction) and match_fraction < fallback_match_fraction <= 1.0
        ):
            raise DonGymError(
                f"fallback_match_fraction={fallback_match_fraction!r}: expected None or a fraction in "
                f"(match_fraction={match_fraction!r}, 1]"
            )
        self._setup_geometry(object_model, targets)
        self.source = source
        self.reference_descriptors = np.asarray(reference, dtype=np.float32)
        self.middle_descriptor = np.asarray(middle, dtype=np.float32)
        ring_distance = float(np.linalg.norm(self.reference_descriptors[0] - self.reference_descriptors[1]))
        self.match_threshold = float(match_fraction) * ring_distance
        self.fallback_threshold = (
            None if fallback_match_fraction is None else float(fallback_match_fraction) * ring_distance
        )
        self.temperature = float(temperature)
        #: When no instance is found at either threshold, look once more for one end ring with the middle ring, and
        #: for a standing part under a single ring's match, before giving up (:meth:`_last_resort_estimates`).
        self.last_resort = bool(last_resort)
        #: Fit each instance's axis to the observed points (:meth:`_refined`).
        self.refine_axis = bool(refine_axis)
        self._profile = radial_profile_m(object_model)
        self._station_agent: Any = None

    @property
    def method(self) -> str:
        return self.source.method

    def estimates(
        self, obs: Mapping[str, Any], info: Mapping[str, Any] | None, view: _DepthView | None = None
    ) -> list[InstanceEstimate]:
        descriptor_image = self.source.descriptor_image(obs, info)
        # The distances do not depend on the threshold: computed once for both searches.
        distances = descriptor_distances(descriptor_image, self.reference_descriptors)
        middle = descriptor_distances(descriptor_image, self.middle_descriptor[None])[0]
        view = view if view is not None else _DepthView.of(obs, self.targets.window_m)
        found = self._estimates_below(distances, middle, view, self.match_threshold)
        if not found and self.fallback_threshold is not None:
            found = self._estimates_below(distances, middle, view, self.fallback_threshold)
        if not found and self.last_resort:
            found = self._last_resort_estimates(distances, middle, view)
        if found and self.refine_axis:
            parts = view.cloud_world[view.cloud_world[:, 2] > TABLE_TOP_Z_M + REFINE_ABOVE_FLOOR_M]  # not the floor
            found = [self._refined(e, parts) for e in found]
        return found

    def _estimates_below(
        self, distances: np.ndarray, middle: np.ndarray, view: _DepthView, threshold: float
    ) -> list[InstanceEstimate]:
        """The instances whose ring candidates match the reference descriptors closer than ``threshold``, from the
        descriptor distances (2, H, W) to the two rings' references and (H, W) to the middle ring's."""
        points, pixels, match_distances = zip(
            *(self._ring_candidates(distances[k], view, threshold) for k in range(2)), strict=True
        )
        found = pair_ring_candidates(
            points, pixels, match_distances, view.depth_m, view.T_world_camera, self.targets, middle, threshold,
            floor_z_m=TABLE_TOP_Z_M,
        )  # fmt: skip
        if not found:
            # A learned network misses the middle ring's descriptor more often than the rings': rather a grasp
            # than none, the pairs without that check (the spacing, the gap and the floor still hold).
            found = pair_ring_candidates(
                points, pixels, match_distances, view.depth_m, view.T_world_camera, self.targets,
                floor_z_m=TABLE_TOP_Z_M,
            )  # fmt: skip
        standing = standing_from_coincident_rings(
            points, found, view.cloud_world, self.object_model, self.targets, TABLE_TOP_Z_M
        )
        return [*found, *standing]

    def _refined(self, estimate: InstanceEstimate, cloud_world: np.ndarray) -> InstanceEstimate:
        """An estimate fitted to the observed points (``cloud_world`` (N, 3), m): a lying one's axis to its surface
        (:func:`refine_axis_with_depth`); a standing one set upright through the centre of the top seen above its
        upper axis point (:func:`upright_axis_from_top`; a pair of a ring on the top and one at the side gives a
        tilted axis whose foot lies a radius or more off), kept as it is where no standing top is seen there."""
        if not estimate.standing:
            return refine_axis_with_depth(estimate, cloud_world, self.targets, self._profile, TABLE_TOP_Z_M)
        upper = estimate.axis_points_world[int(np.argmax(estimate.axis_points_world[:, 2]))]
        axis_points = upright_axis_from_top(upper, cloud_world, self.object_model, self.targets, TABLE_TOP_Z_M)
        return estimate if axis_points is None else replace(estimate, axis_points_world=axis_points)

    def _ring_candidates(
        self, distances: np.ndarray, view: _DepthView, threshold: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One reference's candidate matches below ``threshold`` in its distance image (H, W): their (M, 3) world
        points, (M, 2) pixels and (M,) distances, those without depth left out."""
        uv, distance = local_matches(
            distances, threshold, view.window_px, self.temperature * self.source.descriptor_scale,
            MAX_CANDIDATES_PER_RING,
        )  # fmt: skip
        if not len(uv):
            return np.zeros((0, 3)), uv, distance
        points_camera, ok = robust_point_from_depth(view.depth_m, view.intrinsics, uv)
        ok = np.asarray(ok, dtype=bool)
        points = transform_points(view.T_world_camera, points_camera[ok]) if ok.any() else np.zeros((0, 3))
        return points, uv[ok], distance[ok]

    def _last_resort_estimates(
        self, distances: np.ndarray, middle: np.ndarray, view: _DepthView
    ) -> list[InstanceEstimate]:
        """When neither search found an instance (:attr:`last_resort`): instances from one end ring and the middle
        ring (:func:`pair_with_middle_ring`), then parts standing under a single ring's match
        (:func:`standing_from_coincident_rings` with ``single_ring=True``), at the fallback threshold (the match
        threshold without one). ``distances`` (2, H, W) to the two rings' references, ``middle`` (H, W) to the
        middle ring's."""
        threshold = self.match_threshold if self.fallback_threshold is None else self.fallback_threshold
        rings = [self._ring_candidates(distances[k], view, threshold) for k in range(2)]
        middle_ring = self._ring_candidates(middle, view, threshold)
        found = pair_with_middle_ring(
            rings, middle_ring, view.depth_m, view.T_world_camera, self.targets, TABLE_TOP_Z_M
        )
        if found:
            return found
        return standing_from_coincident_rings(
            [r[0] for r in rings], [], view.cloud_world, self.object_model, self.targets, TABLE_TOP_Z_M,
            single_ring=True,
        )  # fmt: skip

    def station_estimates(self, obs: Mapping[str, Any], info: Mapping[str, Any] | None) -> list[InstanceEstimate]:
        """The part set down alone at the regrasp station, as the single-part axis agent
        (:class:`~don_gym.agents.AxisGraspAgent`) sees it: its two ring keypoints in the descriptor image, moved onto
        the axis; which end is which is decided here, by the descriptors. None found: no estimate."""
        if self._station_agent is None:
            self._station_agent = AxisGraspAgent.from_parts(
                self.object_model, self.source, self.reference_descriptors, self.targets
            )
        descriptors = self.source.descriptor_image(obs, info)
        points = self._station_agent.keypoints({**obs, "descriptors": descriptors})
        if not np.all(np.isfinite(points)):
            return []
        camera = np.asarray(obs["camera_pose"], dtype=np.float64)[:3, 3]
        try:
            axis_points, _ = surface_to_axis(points, camera, self.targets.radii_m)
        except DonGymError:
            return []
        return [InstanceEstimate(axis_points)]

    def __repr__(self) -> str:
        return f"BinAxisGraspAgent(part={self.object_model.name!r}, method={self.method!r})"


def middle_ring_points(object_model: ObjectModel, targets: AxisEndTargets, count: int = 16) -> np.ndarray:
    """(count, 3) object-frame points of the part's outer surface halfway between the two rings of ``targets``: the
    surface points nearest a circle of the rings' larger radius about the axis (a smooth stretch of the outer
    surface has mesh vertices only at its ends, so a ring is not taken from the vertices here)."""
    import trimesh

    axis = np.asarray(object_model.plus_axis, dtype=np.float64)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    angles = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    centre = object_model.center_of_mass + float(np.mean(targets.axial_positions_m)) * axis
    circle = centre + float(np.max(targets.radii_m)) * (np.outer(np.cos(angles), e1) + np.outer(np.sin(angles), e2))
    return np.asarray(trimesh.proximity.closest_point(object_model.mesh, circle)[0], dtype=np.float64)


def upright_axis_from_top(
    seed_world: np.ndarray,
    cloud_world: np.ndarray,
    object_model: ObjectModel,
    targets: AxisEndTargets,
    floor_z_m: float,
) -> np.ndarray | None:
    """The (2, 3) axis points (world, m, at the rings' axial positions, +axis up) of a part standing upright on the
    floor (world z ``floor_z_m``) whose top is seen near ``seed_world`` (3,): the top's height is the highest of the
    observed points (``cloud_world`` (N, 3)) within the part's radius of the seed (its 95th percentile), its centre
    is found by moving to the mean of the points at that height (within :data:`STANDING_TOP_M`) within the part's
    radius until it settles (a seed on the rim, or at the part's foot, lies up to a radius or more off the centre).
    None when no point lies near the seed or the top is not one part length above the floor (within
    :data:`STANDING_FLOOR_M`): not a standing part."""
    length, diameter = lying_footprint_m(object_model)
    cloud = np.asarray(cloud_world, dtype=np.float64).reshape(-1, 3)
    centre = np.asarray(seed_world, dtype=np.float64)[:2].copy()
    # The seed may lie on the rim or, for a cup open upwards, on its floor inside: the top is the highest of what is
    # seen around it.
    around = np.linalg.norm(cloud[:, :2] - centre, axis=1) < diameter / 2
    if not around.any():
        return None
    top_z = float(np.percentile(cloud[around, 2], 95))
    if abs(top_z - length - floor_z_m) > STANDING_FLOOR_M:
        return None
    near_top = cloud[np.abs(cloud[:, 2] - top_z) < STANDING_TOP_M, :2]
    for _ in range(STANDING_CENTRE_ITERATIONS):
        inside = np.linalg.norm(near_top - centre, axis=1) < diameter / 2
        if not inside.any():
            break
        moved = near_top[inside].mean(axis=0)
        settled = np.linalg.norm(moved - centre) < STANDING_CENTRE_SETTLED_M
        centre = moved
        if settled:
            break
    axial = (np.asarray(object_model.mesh.vertices, dtype=np.float64) - object_model.center_of_mass) @ np.asarray(
        object_model.plus_axis, dtype=np.float64
    )
    heights = top_z - (axial.max() - np.asarray(targets.axial_positions_m, dtype=np.float64))
    return np.array([[centre[0], centre[1], heights[0]], [centre[0], centre[1], heights[1]]])


def standing_from_coincident_rings(
    points_world: Sequence[np.ndarray],
    estimates: Sequence[InstanceEstimate],
    cloud_world: np.ndarray,
    object_model: ObjectModel,
    targets: AxisEndTargets,
    floor_z_m: float,
    single_ring: bool = False,
) -> list[InstanceEstimate]:
    """Parts standing upright on the bin floor, which from above show their upper end and no ring side: there
    both rings' descriptors match the rim at one spot. Each minus-end and plus-end candidate left unpaired by
    ``estimates`` and within :data:`COINCIDENT_RADII` part radii of each other is such a part's top when the
    observed points around it at its height (``cloud_world`` (N, 3)) make a top whose centre, found by moving to the
    mean of those within the part's radius (a few times), lies one part length above the floor (within
    :data:`STANDING_FLOOR_M`). The estimate's axis is vertical through that centre, +axis up (the two ends are not
    told apart: a grasp across a standing part does not need it). ``single_ring``: any one candidate of either
    ring may mark the top (a network's match of the lower ring can lie at the part's foot, seen past the top, or
    nowhere; standing toolcaps on the development piles); the height check alone then tells a standing part from
    a lying one."""
    diameter = lying_footprint_m(object_model)[1]
    used = [{e.rings[k] for e in estimates if e.rings is not None} for k in range(2)]
    minus, plus = (np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points_world)
    out: list[InstanceEstimate] = []

    def add_top(seed: np.ndarray) -> bool:
        """Add the standing part whose top is seen at ``seed`` (3,) unless there is none or it is one already
        found."""
        axis_points = upright_axis_from_top(seed, cloud_world, object_model, targets, floor_z_m)
        if axis_points is None or any(
            np.linalg.norm(e.axis_points_world[0, :2] - axis_points[0, :2]) < diameter / 2 for e in out
        ):
            return False
        out.append(InstanceEstimate(axis_points, match_distance=float(np.inf)))
        return True

    if single_ring:
        # Every candidate left unpaired marks a top alone: the minus ring's first, then the plus ring's.
        for k, candidates in enumerate((minus, plus)):
            for i, seed in enumerate(candidates):
                if i not in used[k]:
                    add_top(seed)
        return out
    for i, a in enumerate(minus):
        if i in used[0]:
            continue
        for j, b in enumerate(plus):
            if j in used[1] or np.linalg.norm(a - b) > COINCIDENT_RADII * diameter / 2:
                continue
            if add_top((a + b) / 2):
                used[1].add(j)
                break
    return out


def single_part_reference_frame(object_model: ObjectModel, env: gym.Env) -> ReferenceFrame:
    """A reference frame of the part alone: a pick env (:class:`~don_gym.sim.env.PickPlaceEnv`) of the part with
    the bin env's camera size and sensor, reset at the fixed reference seed and pose."""
    from don_gym.sim.env import PickPlaceEnv

    base = env.unwrapped
    size = None if base.image_size is None else tuple(base.image_size)
    source = object_model.source
    part = source[len("builtin:") :] if source.startswith("builtin:") else source
    pick = PickPlaceEnv(object=part, control="grasp", image_size=size, sensor=base.sensor)
    try:
        return ReferenceFrame.from_env(pick)
    finally:
        pick.close()
