"""The bin-picking task (:class:`BinPickTask`): a tray with walls on the table holding a pile of several
instances of several parts, the same handover cradle as :class:`~don_gym.sim.task.PickPlaceTask`, the
seeded pile, and the bookkeeping of which instance is where: in the bin, in the hand, cleared.

The pure core, :func:`check_bin_parts` and :func:`lying_footprint_m`, decides from the parts' meshes
alone whether a pile fits; the task builds it on a :class:`~don_gym.sim.bullet.Bullet` client.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.geometry import make_transform
from don_gym.objects import ObjectModel
from don_gym.sim.bullet import Bullet
from don_gym.sim.part import PartBody, lying_rotation
from don_gym.sim.robot import MAX_WIDTH_M
from don_gym.sim.task import (
    CRADLE_BASE_HALF_WIDTH_M,
    CRADLE_CENTER_XY_M,
    CRADLE_LENGTH_M,
    LIFT_HEIGHT_M,
    TABLE_BOUNDS_M,
    TABLE_TOP_Z_M,
    WORKSPACE_M,
    PartContacts,
    PickPlaceTask,
    grasp_point_object,
)

#: Centre of the bin's floor (x, y), metres: the workspace centre, under the wrist camera's observation pose.
BIN_CENTER_XY_M = np.array([(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2])
#: Inside of the bin (x along the robot's reach, y across), metres: the table top between the walls. The
#: wrist camera sees it whole from the observation pose (about 0.35 m x 0.47 m of table at 0.45 m).
BIN_INNER_SIZE_M = (0.20, 0.28)
#: Wall height above the table and thickness (m): low enough that the open fingers (8 cm apart) reach
#: a part lying a few centimetres from a wall, high enough to keep a settling pile in.
BIN_WALL_HEIGHT_M = 0.035
BIN_WALL_THICKNESS_M = 0.01
#: The parts' footprints lying down (length x diameter, :func:`lying_footprint_m`) may cover at most this
#: fraction of the bin's floor: a pile about one to two layers deep, below the walls' rim.
BIN_FILL_FRACTION = 0.5
#: Gap (m) kept between a dropped part's bounding box and the walls.
DROP_WALL_MARGIN_M = 0.004
#: Parts are dropped over the middle of the bin, their centres of mass in this fraction of its inside
#: (each axis), so that they land on each other and make a pile rather than a spread.
DROP_ZONE_FRACTION = 0.5
#: Parts are dropped lying on their side, tilted by up to this much (rad) about a random horizontal axis.
DROP_MAX_TILT_RAD = np.deg2rad(20.0)
#: Vertical gap (m) between a dropped part's bounding box and those of the parts dropped before it below it.
DROP_GAP_M = 0.003
#: A pile settles for at least / at most this long (s); calm: every part below 5 mm/s and 0.1 rad/s for
#: three checks 40 ms apart.
PILE_SETTLE_MIN_S = 0.2
PILE_SETTLE_MAX_S = 3.0
#: (linear, angular) velocity damping of the parts while a pile settles (fractions lost per second, as
#: Bullet applies them): round parts dropped on a table roll to the walls undamped, where real parts poured
#: from a box stay heaped; PyBullet's default, restored before the robot moves.
PILE_DAMPING = (0.5, 0.995)
DEFAULT_DAMPING = (0.04, 0.04)
#: A pile in which a part bounced out of the bin is redrawn, at most this many times.
PILE_TRIES = 10
#: Gap (m) between each finger pad and the part as the open fingers come down (:func:`pregrasp_width_m`):
#: room for a grasp point some millimetres off.
PAD_CLEARANCE_M = 0.008
#: Room a top-down grasp needs besides the opening (m, :meth:`BinPickTask.grasp_is_clear`): a finger's
#: thickness outside its pad (with 3 mm margin), half its width along the part's axis (with margin), and
#: the fingertips' depth below the grasp point.
FINGER_OUTSIDE_PAD_M = 0.025
FINGER_HALF_WIDTH_M = 0.016
FINGER_BELOW_GRASP_M = 0.011
#: A neighbour's convex hull is tested against the fingers' footprint at its vertices and at points this far
#: apart (m) along its edges: well under the footprint's width along the axis (2 x FINGER_HALF_WIDTH_M), so a
#: neighbour whose body crosses the footprint between its end rings is never missed.
HULL_EDGE_SPACING_M = 0.004
#: Cleared instances rest on a static shelf far from the scene (out of every camera's view); removing
#: bodies would break the client's snapshot, which every reset restores.
SHELF_CENTER_M = np.array([30.0, 30.0, -5.0])
SHELF_SLOT_M = 0.3

#: The regrasp station (:func:`station_boxes`): a free square of table of this side (m) beside the bin, away from the
#: cradle, centred here by default; on its side towards the bin a low ledge (x, y size and height, m) whose edge
#: faces away from the bin. A part lifted standing is set down on the ledge with its axis beyond the edge by
#: :data:`LEDGE_OVERHANG_RADII` of its radius: it tips over the edge and comes to lie on the table below.
STATION_SIZE_M = 0.14
DEFAULT_STATION_XY_M = (0.45, -0.33)
LEDGE_SIZE_M = (0.06, 0.05, 0.025)
LEDGE_OVERHANG_RADII = 0.6
#: A station centre is within reach when its distance from the robot's base axis lies in this range (m): a
#: top-down grasp at the table and the observation above it.
STATION_REACH_M = (0.30, 0.65)
#: The wrist camera observes the station from this high above the table (m), over the ledge's foot.
STATION_CAMERA_HEIGHT_M = 0.30

DEFAULT_PARTS: dict[str, int] = {"toolcap": 3, "shaft": 2}
DEFAULT_TARGET = "toolcap"


def bin_inner_bounds() -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the bin's inside, metres, world frame."""
    half_x, half_y = BIN_INNER_SIZE_M[0] / 2, BIN_INNER_SIZE_M[1] / 2
    cx, cy = BIN_CENTER_XY_M
    return cx - half_x, cx + half_x, cy - half_y, cy + half_y


def lying_footprint_m(model: ObjectModel) -> tuple[float, float]:
    """(length along the +axis, largest diameter across it) of a part, metres: the rectangle it covers
    lying on its side."""
    relative = np.asarray(model.mesh.vertices, dtype=np.float64) - model.center_of_mass
    along = relative @ model.plus_axis
    radial = np.linalg.norm(relative - np.outer(along, model.plus_axis), axis=1)
    return float(np.ptp(along)), float(2.0 * radial.max())


def pregrasp_width_m(model: ObjectModel, kind: str = "across") -> float:
    """Finger opening (m) on the way down to a grasp of ``model`` of ``kind``
    (:data:`~don_gym.sim.script.GRASP_KINDS`): the width the fingers close on (its diameter; its length for a
    grasp along the axis, which closes on the end faces) plus :data:`PAD_CLEARANCE_M` each side, at most the
    gripper's full opening."""
    length, diameter = lying_footprint_m(model)
    closes_on = length if kind == "along" else diameter
    return float(min(MAX_WIDTH_M, closes_on + 2 * PAD_CLEARANCE_M))


def grasp_opening_m(model: ObjectModel, kind: str, grasp_xy_m: np.ndarray, axis_yaw_rad: float) -> float:
    """Finger opening (m) on the way down to a grasp in the bin of ``model`` of ``kind`` at ``grasp_xy_m`` (2,)
    (world, m) whose believed +axis has yaw ``axis_yaw_rad`` (rad): :func:`pregrasp_width_m`, narrowed as far as
    the part's diameter allows where the open fingers (:data:`FINGER_OUTSIDE_PAD_M` beyond each pad,
    :data:`FINGER_HALF_WIDTH_M` either side) would reach past the bin's walls (outside the bin, as at the regrasp
    station: the narrowest). A grasp along the axis opens for the part's length, room for a grasp point some
    millimetres off along the axis; against a wall it keeps the room the walls leave."""
    widest, narrowest = pregrasp_width_m(model, kind), pregrasp_width_m(model, "across")
    if widest <= narrowest:
        return widest
    axis = np.array([np.cos(axis_yaw_rad), np.sin(axis_yaw_rad)])
    closing = axis if kind == "along" else np.array([-axis[1], axis[0]])
    side = np.array([-closing[1], closing[0]])
    x0, x1, y0, y1 = bin_inner_bounds()
    low, high = np.array([x0, y0]), np.array([x1, y1])
    reach = np.inf  # how far (m) the fingers' outer faces may go from the grasp point along the closing direction
    for sign in (-1.0, 1.0):
        for offset in (-FINGER_HALF_WIDTH_M, FINGER_HALF_WIDTH_M):
            origin = np.asarray(grasp_xy_m, dtype=np.float64)[:2] + offset * side
            direction = sign * closing
            with np.errstate(divide="ignore", invalid="ignore"):
                exits = np.where(direction > 0, (high - origin) / direction, (low - origin) / direction)
            reach = min(reach, float(np.min(np.where(np.abs(direction) > 1e-12, exits, np.inf))))
    return float(np.clip(2.0 * (reach - FINGER_OUTSIDE_PAD_M), narrowest, widest))


def longest_part_m() -> float:
    """The longest part (m) the bin takes: one that lies across its narrow side with room at both walls."""
    return min(BIN_INNER_SIZE_M) - 2 * DROP_WALL_MARGIN_M


def hull_outline_points(model: ObjectModel, spacing_m: float = HULL_EDGE_SPACING_M) -> np.ndarray:
    """(N, 3) object-frame points (m) of a part's convex hull: its vertices and points at most ``spacing_m``
    apart along each of its edges. A round part's hull vertices sit on a few rings, centimetres apart along its
    axis; the edges between them carry the hull's sides."""
    hull = model.mesh.convex_hull
    vertices = np.asarray(hull.vertices, dtype=np.float64)
    points = [vertices]
    for a, b in np.asarray(hull.edges_unique):
        steps = int(np.ceil(np.linalg.norm(vertices[b] - vertices[a]) / spacing_m))
        if steps > 1:
            t = np.arange(1, steps)[:, None] / steps
            points.append(vertices[a] + t * (vertices[b] - vertices[a]))
    return np.concatenate(points)


def check_bin_parts(counts: Mapping[str, int], models: Mapping[str, ObjectModel]) -> None:
    """DonGymError unless every part fits in the bin and together they cover at most :data:`BIN_FILL_FRACTION`
    of its floor lying down. ``counts``: instances per part key, ``models``: the part of each key."""
    floor_m2 = BIN_INNER_SIZE_M[0] * BIN_INNER_SIZE_M[1]
    allowed_m2 = BIN_FILL_FRACTION * floor_m2
    bin_text = f"the bin ({BIN_INNER_SIZE_M[0]:g} x {BIN_INNER_SIZE_M[1]:g} m inside)"
    covered_m2, footprints = 0.0, {}
    for key, count in counts.items():
        length, diameter = lying_footprint_m(models[key])
        if count > 0 and length > longest_part_m():
            raise DonGymError(
                f"parts: {key!r} is {length:.3f} m long; {bin_text} takes parts up to {longest_part_m():.3f} m long"
            )
        footprints[key] = length * diameter
        covered_m2 += count * length * diameter
    if covered_m2 > allowed_m2:
        alone = ", ".join(f"{int(allowed_m2 // area)} {key}" for key, area in footprints.items())
        raise DonGymError(
            f"parts={dict(counts)!r}: more parts than fit in {bin_text}; they cover {covered_m2 * 1e4:.0f} cm^2 "
            f"lying down, expected at most {allowed_m2 * 1e4:.0f} cm^2 (half its floor; e.g. at most {alone} alone)"
        )


def _overlap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    """Whether two (x_min, x_max, y_min, y_max) rectangles overlap."""
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def station_bounds(station_xy_m: np.ndarray) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the station's square of table, world metres."""
    x, y, half = float(station_xy_m[0]), float(station_xy_m[1]), STATION_SIZE_M / 2
    return x - half, x + half, y - half, y + half


def check_station(station_xy_m: Any) -> np.ndarray:
    """The regrasp station's centre (2,) world metres, checked: a pair of finite numbers, its square
    (:data:`STATION_SIZE_M`) on the table, clear of the bin (walls included) and of the cradle, its centre within
    the robot's reach (:data:`STATION_REACH_M` from the base axis). DonGymError naming it otherwise."""
    text = f"regrasp_station={station_xy_m!r}"
    try:
        xy = np.asarray(station_xy_m, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        xy = np.zeros(0)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise DonGymError(f"{text}: expected None or (x, y), the station's centre on the table in metres")
    bounds = station_bounds(xy)
    x0, x1, y0, y1 = TABLE_BOUNDS_M
    if not (x0 <= bounds[0] and bounds[1] <= x1 and y0 <= bounds[2] and bounds[3] <= y1):
        raise DonGymError(f"{text}: its {STATION_SIZE_M:g} m square leaves the table {TABLE_BOUNDS_M}")
    reach = float(np.linalg.norm(xy))
    if not STATION_REACH_M[0] <= reach <= STATION_REACH_M[1]:
        raise DonGymError(
            f"{text} is out of reach: {reach:.2f} m from the robot's base, expected {STATION_REACH_M[0]:g} to "
            f"{STATION_REACH_M[1]:g} m"
        )
    bx0, bx1, by0, by1 = bin_inner_bounds()
    wall = BIN_WALL_THICKNESS_M
    if _overlap(bounds, (bx0 - wall, bx1 + wall, by0 - wall, by1 + wall)):
        raise DonGymError(f"{text}: its square {np.round(bounds, 3).tolist()} overlaps the bin; expected free table")
    cx, cy = CRADLE_CENTER_XY_M
    cradle = (cx - CRADLE_LENGTH_M / 2, cx + CRADLE_LENGTH_M / 2, cy - CRADLE_BASE_HALF_WIDTH_M - 0.02, cy + 0.045)
    if _overlap(bounds, cradle):
        raise DonGymError(f"{text}: its square is occupied by the cradle; expected free table")
    return xy


def station_ledge(station_xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ledge of a station (:data:`LEDGE_SIZE_M`): (3,) centre of its box, world m; (2,) midpoint of its free
    edge on the table plane; (2,) unit direction from the ledge over that edge (away from the bin), the way a part
    set down over the edge tips."""
    xy = np.asarray(station_xy_m, dtype=np.float64)
    away = np.array([0.0, 1.0 if xy[1] > BIN_CENTER_XY_M[1] else -1.0])
    size_x, size_y, height = LEDGE_SIZE_M
    edge = xy + 0.01 * -away  # the edge a centimetre from the centre, towards the bin
    centre = np.array([*(edge - away * size_y / 2), TABLE_TOP_Z_M + height / 2])
    return centre, edge, away


@dataclass
class Instance:
    """One part instance of the pile: its id (its index in :attr:`BinPickTask.instances`), the part's name
    (:attr:`~don_gym.objects.ObjectModel.name`), its body, its centre-of-mass height at the last settle
    (m, for "lifted"), and whether it is still in play (False once cleared onto the shelf)."""

    instance_id: int
    part: str
    body: PartBody
    rest_com_z_m: float = TABLE_TOP_Z_M
    in_play: bool = True
    #: ee mode: lifted by the gripper since it was last at rest in the bin.
    lifted: bool = False

    @property
    def model(self) -> ObjectModel:
        return self.body.model


class BinPickTask(PickPlaceTask):
    """Table, cradle and a bin with a pile of part instances; samples piles, tracks and clears instances.

    The world, table and cradle are those of :class:`~don_gym.sim.task.PickPlaceTask`; the bin stands on
    the table over the workspace, its walls static boxes, the table top its floor. Everything the parent
    judges about "the part" (contacts, lifted, placement, outcome) is about the *focus* instance
    (:meth:`set_focus`), so the scripted grasp (:class:`~don_gym.sim.script.GraspPlaceScript`) runs
    unchanged: the env focuses the instance the grasp aims at, and when the script asks after the lift
    whether the part is held (:meth:`is_held`), the focus moves to the instance actually in the hand.

    Args:
        sim: the client.
        models: part name -> model, in instance order.
        counts: part name -> number of instances (>= 0).
        target: the part name to pick.
        grasp_points_object: part name -> :func:`~don_gym.sim.task.grasp_point_object` of its model, as
            :attr:`grasp_points_object` of a task of the same models (None: computed, which takes a while).
    """

    def __init__(
        self,
        sim: Bullet,
        models: Mapping[str, ObjectModel],
        counts: Mapping[str, int],
        target: str,
        grasp_points_object: Mapping[str, np.ndarray] | None = None,
        station_xy_m: np.ndarray | None = None,
    ):
        self.sim = sim
        self.models = dict(models)
        self.target = target
        self.table_id = self._build_table()
        self.cradle_id = self._build_cradle()
        self.bin_id = self._build_bin()
        self.shelf_id = self._build_shelf()
        #: Centre (2,) of the regrasp station (:func:`check_station`), None without one; its ledge's body id.
        self.station_xy_m = None if station_xy_m is None else np.asarray(station_xy_m, dtype=np.float64)
        self.ledge_id = None if self.station_xy_m is None else self._build_ledge()
        self.instances: list[Instance] = []
        for name, model in self.models.items():
            for _ in range(int(counts[name])):
                index = len(self.instances)
                body = PartBody.create(sim, model, name=f"instance{index}")
                self.instances.append(Instance(index, name, body))
        self._by_body = {instance.body.body_id: instance for instance in self.instances}
        # grasp_point_object cuts the mesh into sections: once per part, not per query (nor per world).
        if grasp_points_object is None:
            grasp_points_object = {name: grasp_point_object(model) for name, model in self.models.items()}
        #: Part name -> (3,) object-frame grasp point (:func:`~don_gym.sim.task.grasp_point_object`), metres.
        self.grasp_points_object = {name: np.asarray(grasp_points_object[name]) for name in self.models}
        self._hull_points = {name: hull_outline_points(m) for name, m in self.models.items()}
        self._focus = next(i for i in self.instances if i.part == target)
        self._gripper: tuple[int, tuple[int, int]] | None = None
        for instance in self.instances:
            self.clear(instance)

    # ------------------------------------------------------------ the scene
    def _build_bin(self) -> int:
        x0, x1, y0, y1 = bin_inner_bounds()
        t, h = BIN_WALL_THICKNESS_M, BIN_WALL_HEIGHT_M
        z = TABLE_TOP_Z_M + h / 2
        cx, cy = BIN_CENTER_XY_M
        long_x = (x1 - x0) / 2 + t  # the x walls run past the corners, closing them
        boxes = [
            ([t / 2, (y1 - y0) / 2, h / 2], [x0 - t / 2, cy, z], (0, 0, 0, 1)),
            ([t / 2, (y1 - y0) / 2, h / 2], [x1 + t / 2, cy, z], (0, 0, 0, 1)),
            ([long_x, t / 2, h / 2], [cx, y0 - t / 2, z], (0, 0, 0, 1)),
            ([long_x, t / 2, h / 2], [cx, y1 + t / 2, z], (0, 0, 0, 1)),
        ]
        return self.sim.create_static_boxes("bin", boxes, rgba=(0.35, 0.38, 0.45, 1.0), lateral_friction=0.5)

    def _build_ledge(self) -> int:
        centre, _, _ = station_ledge(self.station_xy_m)
        half = [LEDGE_SIZE_M[0] / 2, LEDGE_SIZE_M[1] / 2, LEDGE_SIZE_M[2] / 2]
        return self.sim.create_static_boxes("ledge", [(half, centre, (0, 0, 0, 1))], rgba=(0.35, 0.38, 0.45, 1.0))

    def at_station(self, instance: Instance) -> bool:
        """Its centre of mass lies over the station's square, below 5 cm above the table (not in the hand)."""
        if self.station_xy_m is None:
            return False
        x0, x1, y0, y1 = station_bounds(self.station_xy_m)
        com = instance.body.center_of_mass_world
        return bool(x0 <= com[0] <= x1 and y0 <= com[1] <= y1 and com[2] < TABLE_TOP_Z_M + 0.05)

    def check_station_free(self) -> None:
        """DonGymError when an instance in play lies on the regrasp station (a pile must leave it free)."""
        occupants = [i.instance_id for i in self.in_play() if self.at_station(i)]
        if occupants:
            raise DonGymError(
                f"regrasp_station={self.station_xy_m.tolist()}: its area is occupied by instance(s) {occupants} of "
                "the pile; expected free table"
            )

    def _build_shelf(self) -> int:
        half = [5.0, 5.0, 0.05]
        centre = SHELF_CENTER_M - np.array([0.0, 0.0, 0.05])
        return self.sim.create_static_boxes("shelf", [(half, centre, (0, 0, 0, 1))], rgba=(0.5, 0.5, 0.5, 1.0))

    def attach_gripper(self, robot_id: int, finger_links: tuple[int, int]) -> None:
        """The robot whose fingers :meth:`is_held` looks at when it searches the hand for another instance."""
        self._gripper = (int(robot_id), tuple(finger_links))

    # ---------------------------------------------------------------- focus
    @property
    def part(self) -> PartBody:  # type: ignore[override]
        return self._focus.body

    @property
    def model(self) -> ObjectModel:  # type: ignore[override]
        return self._focus.model

    @property
    def rest_com_z_m(self) -> float:  # type: ignore[override]
        return self._focus.rest_com_z_m

    @property
    def focus(self) -> Instance:
        return self._focus

    def set_focus(self, instance: Instance) -> None:
        self._focus = instance

    # ------------------------------------------------------------ instances
    def in_play(self) -> list[Instance]:
        """The instances not cleared yet, in id order."""
        return [instance for instance in self.instances if instance.in_play]

    def instance_of_body(self, body_id: int) -> Instance | None:
        return self._by_body.get(int(body_id))

    def in_bin(self, instance: Instance) -> bool:
        """Its centre of mass lies inside the bin's walls, below the rim plus 5 cm (a part in the hand
        above the bin is not in it)."""
        x0, x1, y0, y1 = bin_inner_bounds()
        com = instance.body.center_of_mass_world
        return bool(x0 <= com[0] <= x1 and y0 <= com[1] <= y1 and com[2] < TABLE_TOP_Z_M + BIN_WALL_HEIGHT_M + 0.05)

    def targets_left(self) -> int:
        """Target instances still in play."""
        return sum(1 for instance in self.in_play() if instance.part == self.target)

    def clear(self, instance: Instance) -> None:
        """Take an instance out of play: onto its slot on the shelf, lying, at rest."""
        slot = SHELF_CENTER_M + np.array([SHELF_SLOT_M * instance.instance_id, 0.0, 0.0])
        R = lying_rotation(instance.model, 0.0)
        lowest = float((instance.model.mesh.vertices @ R.T)[:, 2].min())
        T = make_transform(R, slot - R @ instance.model.center_of_mass)
        T[2, 3] = slot[2] + 0.0005 - lowest
        instance.body.set_pose(T)
        instance.in_play = False
        instance.lifted = False

    def stand(self, instance: Instance, xy_m: Iterable[float], plus_up: bool = True, turn_rad: float = 0.0) -> None:
        """Put an instance standing on an end over world ``xy_m`` (its +axis up, or down), turned by ``turn_rad``
        about its axis, its lowest point 1 mm above the table, and let the scene settle (tests and the regrasp
        benchmark: a standing part on demand)."""
        model = instance.model
        up = np.array([0.0, 0.0, 1.0 if plus_up else -1.0])
        R = (
            Rotation.from_rotvec(float(turn_rad) * up).as_matrix()
            @ Rotation.align_vectors([up], [model.plus_axis])[0].as_matrix()
        )
        lowest = float(((np.asarray(model.mesh.vertices) - model.center_of_mass) @ R.T)[:, 2].min())
        com = np.array([*list(xy_m)[:2], TABLE_TOP_Z_M - lowest + 0.001])
        instance.body.set_pose(make_transform(R, com - R @ model.center_of_mass))
        instance.in_play = True
        self.settle()

    def grasp_point_world(self, instance: Instance) -> np.ndarray:
        """(3,) world point of :func:`~don_gym.sim.task.grasp_point_object` of an instance."""
        T = instance.body.T_world_object
        return T[:3, :3] @ self.grasp_points_object[instance.part] + T[:3, 3]

    def nearest_instance(self, point_world: np.ndarray, part: str | None = None) -> Instance | None:
        """The instance in play (of ``part``, default any) whose axis segment passes closest to a world point."""
        point = np.asarray(point_world, dtype=np.float64)
        best, best_distance = None, np.inf
        for instance in self.in_play():
            if part is not None and instance.part != part:
                continue
            T = instance.body.T_world_object
            a, b = (T[:3, :3] @ end + T[:3, 3] for end in instance.model.axis_endpoints())
            t = float(np.clip((point - a) @ (b - a) / max(float((b - a) @ (b - a)), 1e-12), 0.0, 1.0))
            distance = float(np.linalg.norm(point - (a + t * (b - a))))
            if distance < best_distance:
                best, best_distance = instance, distance
        return best

    def grasp_is_clear(self, instance: Instance, neighbours: bool = True) -> bool:
        """Whether a top-down grasp across the instance's axis at its grasp point finds room: the footprint
        of the fingers opened to :func:`pregrasp_width_m` (and :data:`FINGER_OUTSIDE_PAD_M` beyond each pad)
        across the axis and :data:`FINGER_HALF_WIDTH_M` along it lies inside the walls, and no other instance
        in play reaches into it above the fingertips' depth (:data:`FINGER_BELOW_GRASP_M` below the grasp point;
        ``neighbours=False``: the walls only)."""
        T = instance.body.T_world_object
        axis = T[:3, :3] @ instance.model.plus_axis
        along = axis[:2] / max(float(np.linalg.norm(axis[:2])), 1e-9)
        across = np.array([-along[1], along[0]])
        point = self.grasp_point_world(instance)
        span = pregrasp_width_m(instance.model) / 2 + FINGER_OUTSIDE_PAD_M
        x0, x1, y0, y1 = bin_inner_bounds()
        corners = np.array(
            [point[:2] + c * across + a * FINGER_HALF_WIDTH_M * along for c in (-span, span) for a in (-1.0, 1.0)]
        )
        inside = (corners[:, 0] >= x0) & (corners[:, 0] <= x1) & (corners[:, 1] >= y0) & (corners[:, 1] <= y1)
        if not inside.all():
            return False
        if not neighbours:
            return True
        for other in self.in_play():
            if other is instance:
                continue
            T_other = other.body.T_world_object
            vertices = self._hull_points[other.part] @ T_other[:3, :3].T + T_other[:3, 3]
            relative = vertices[:, :2] - point[:2]
            blocked = (
                (np.abs(relative @ along) <= FINGER_HALF_WIDTH_M)
                & (np.abs(relative @ across) <= span)
                & (vertices[:, 2] > point[2] - FINGER_BELOW_GRASP_M)
            )
            if blocked.any():
                return False
        return True

    def top_instance(self, part: str | None = None, exclude: Iterable[int] = ()) -> Instance | None:
        """The instance in play (of ``part``, default any) an oracle picks first: the highest grasp point of
        those with room for the fingers (:meth:`grasp_is_clear`), else of those whose fingers at least clear the
        walls (they may push a neighbour aside), else of all; lying (+axis within 45 degrees of horizontal)
        before standing at each stage. Instances whose ids are in ``exclude`` come last (e.g. one just failed)."""
        excluded = {int(i) for i in exclude}
        candidates = [i for i in self.in_play() if part is None or i.part == part]
        if not candidates:
            return None

        def preference(instance: Instance) -> tuple[bool, bool, bool, bool, float, int]:
            axis = instance.body.T_world_object[:3, :3] @ instance.model.plus_axis
            lying = abs(float(axis[2])) < np.sqrt(0.5)
            height = float(self.grasp_point_world(instance)[2])
            walls = self.grasp_is_clear(instance, neighbours=False)
            fresh = instance.instance_id not in excluded
            return fresh, walls and self.grasp_is_clear(instance), walls, lying, height, -instance.instance_id

        return max(candidates, key=preference)

    # ----------------------------------------------------------- the pile
    def forget_contacts(self) -> None:
        """As :meth:`PickPlaceTask.forget_contacts`, for every instance (each parked apart from the others)."""
        for instance in self.instances:
            instance.body.set_pose(make_transform(translation=[2.0 * instance.instance_id, 0.0, 50.0]))
        self.sim.client.performCollisionDetection()

    def _drop_pose(self, model: ObjectModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A lying, tilted pose over the bin (lowest point at z = 0) and its world bounding box (2, 3)."""
        yaw, roll = rng.uniform(-np.pi, np.pi, size=2)
        tilt, tilt_direction = rng.uniform(0.0, DROP_MAX_TILT_RAD), rng.uniform(-np.pi, np.pi)
        R = (
            Rotation.from_rotvec(tilt * np.array([np.cos(tilt_direction), np.sin(tilt_direction), 0.0])).as_matrix()
            @ lying_rotation(model, float(yaw))
            @ Rotation.from_rotvec(float(roll) * model.plus_axis).as_matrix()
        )
        relative = (np.asarray(model.mesh.vertices) - model.center_of_mass) @ R.T
        low, high = relative.min(axis=0), relative.max(axis=0)
        x0, x1, y0, y1 = bin_inner_bounds()
        m = DROP_WALL_MARGIN_M
        # The zone's centre-of-mass range, narrowed where the part would otherwise reach past the walls.
        zone_x = (
            BIN_CENTER_XY_M[0] - DROP_ZONE_FRACTION * (x1 - x0) / 2,
            BIN_CENTER_XY_M[0] + DROP_ZONE_FRACTION * (x1 - x0) / 2,
        )
        zone_y = (
            BIN_CENTER_XY_M[1] - DROP_ZONE_FRACTION * (y1 - y0) / 2,
            BIN_CENTER_XY_M[1] + DROP_ZONE_FRACTION * (y1 - y0) / 2,
        )
        lo_x, hi_x = max(zone_x[0], x0 + m - low[0]), min(zone_x[1], x1 - m - high[0])
        lo_y, hi_y = max(zone_y[0], y0 + m - low[1]), min(zone_y[1], y1 - m - high[1])
        com = np.array([rng.uniform(lo_x, max(lo_x, hi_x)), rng.uniform(lo_y, max(lo_y, hi_y)), -low[2]])
        T = make_transform(R, com - R @ model.center_of_mass)
        return T, np.stack([com + low, com + high])

    def drop_pile(self, rng: np.random.Generator) -> None:
        """Put every instance back in play and drop them into the bin in a random order, each above the ones
        dropped before it beneath it (no two overlap at the start), then let the pile settle. A pile from which
        a part bounced out is drawn again (at most :data:`PILE_TRIES` times). Deterministic given ``rng``'s state."""
        for _ in range(PILE_TRIES):
            boxes: list[np.ndarray] = []
            for index in rng.permutation(len(self.instances)):
                instance = self.instances[int(index)]
                T, box = self._drop_pose(instance.model, rng)
                base = TABLE_TOP_Z_M + 0.002
                for other in boxes:
                    if np.all(box[0, :2] < other[1, :2] + DROP_GAP_M) and np.all(
                        other[0, :2] < box[1, :2] + DROP_GAP_M
                    ):
                        base = max(base, float(other[1, 2]) + DROP_GAP_M)
                T[2, 3] += base
                box[:, 2] += base
                boxes.append(box)
                instance.body.set_pose(T)
                instance.in_play, instance.lifted = True, False
            self._set_damping(PILE_DAMPING)
            self.settle()
            self._set_damping(DEFAULT_DAMPING)
            if all(self.in_bin(instance) for instance in self.instances):
                return
        for instance in self.instances:  # rare: keep the pile, without the parts that left the bin
            if not self.in_bin(instance):
                self.clear(instance)

    def _set_damping(self, damping: tuple[float, float]) -> None:
        for instance in self.instances:
            self.sim.client.changeDynamics(
                instance.body.body_id, -1, linearDamping=damping[0], angularDamping=damping[1]
            )

    def settle(self, max_s: float = PILE_SETTLE_MAX_S) -> None:
        """Let the instances in play come to rest and remember their heights. Deterministic: how long it
        runs depends on the simulated state only."""
        chunk = max(1, int(round(0.04 / self.sim.time_step_s)))
        elapsed, calm = 0.0, 0
        while elapsed < max_s:
            self.sim.step(chunk)
            elapsed += chunk * self.sim.time_step_s
            still = True
            for instance in self.in_play():
                linear, angular = instance.body.velocity
                if np.linalg.norm(linear) >= 0.005 or np.linalg.norm(angular) >= 0.1:
                    still = False
                    break
            calm = calm + 1 if still else 0
            if calm >= 3 and elapsed >= PILE_SETTLE_MIN_S:
                break
        for instance in self.in_play():
            instance.rest_com_z_m = float(instance.body.center_of_mass_world[2])

    # ------------------------------------------------------------ judging
    def instance_contacts(self, instance: Instance, robot_id: int, finger_links: tuple[int, int]) -> PartContacts:
        """What an instance touches: each finger, the table or the bin (``table``: resting), the cradle."""
        body = instance.body.body_id
        fingers = tuple(bool(self.sim.contact_points(robot_id, body, link_a=link)) for link in finger_links)
        resting = bool(self.sim.contact_points(body, self.table_id) or self.sim.contact_points(body, self.bin_id))
        return PartContacts(fingers=fingers, table=resting, cradle=bool(self.sim.contact_points(body, self.cradle_id)))

    def contacts(self, robot_id: int, finger_links: tuple[int, int]) -> PartContacts:
        return self.instance_contacts(self._focus, robot_id, finger_links)

    def instance_held(self, instance: Instance, contacts: PartContacts) -> bool:
        """Lifted: touched by both fingers, off the table and the bin, its centre of mass raised by
        :data:`~don_gym.sim.task.LIFT_HEIGHT_M` above its height at the last settle."""
        if not all(contacts.fingers) or contacts.table:
            return False
        return float(instance.body.center_of_mass_world[2]) > instance.rest_com_z_m + LIFT_HEIGHT_M

    def is_held(self, contacts: PartContacts) -> bool:
        """Whether the focus is lifted; if it is not but another instance in play is (the fingers closed on
        a neighbour), that one becomes the focus and the answer is True."""
        if self.instance_held(self._focus, contacts):
            return True
        if self._gripper is None:
            return False
        for instance in self.in_play():
            if instance is not self._focus and self.instance_held(
                instance, self.instance_contacts(instance, *self._gripper)
            ):
                self._focus = instance
                return True
        return False

    def instance_poses(self, visible_pixels: Mapping[int, int] | None = None) -> list[dict[str, Any]]:
        """The instances in play: ``instance`` (id), ``part``, ``T_world_object`` (4, 4), ``grasp_point_world``
        (3,), ``in_bin`` and ``visible_pixels`` (from ``visible_pixels``, instance id -> pixel count; None
        without one)."""
        poses = []
        for instance in self.in_play():
            poses.append(
                {
                    "instance": instance.instance_id,
                    "part": instance.part,
                    "T_world_object": instance.body.T_world_object,
                    "grasp_point_world": self.grasp_point_world(instance),
                    "in_bin": self.in_bin(instance),
                    "visible_pixels": None
                    if visible_pixels is None
                    else int(visible_pixels.get(instance.instance_id, 0)),
                }
            )
        return poses
