"""Distractor objects: coloured primitives scattered on the table around the part.

A network trained on scenes with the part alone can take any compact, contrasting object for the part;
distractors (boxes, cylinders, spheres and capsules, some of the part's own proportions) teach it that
only the part carries the part's descriptors. :class:`Distractors` owns a fixed pool of static bodies
in one scene and, per scene, places some of them (:meth:`scatter`) and parks the rest out of view.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pybullet as p
from scipy.spatial.transform import Rotation

from don_gym.errors import DonGymError
from don_gym.sim.bullet import Bullet
from don_gym.sim.task import TABLE_TOP_Z_M

#: Where distractors may stand (x0, x1, y0, y1 in metres, world frame): the table in front of the robot,
#: clear of its base and of the cradle's far side.
DISTRACTOR_REGION_M = (0.28, 0.78, -0.32, 0.32)
#: Pool bodies per distractor placed in a scene: shapes vary between scenes by which bodies are chosen.
POOL_PER_DISTRACTOR = 3
#: Gap (m) kept between a distractor's footprint and the part's bounding circle, and between distractors.
CLEARANCE_M = 0.015
_PARKED_Z_M = -10.0  # below the floor, out of every camera's view
_SHAPES = ("box", "cylinder", "sphere", "capsule", "rod")
_MAX_PLACEMENT_TRIES = 200


def check_distractor_count(count: int) -> int:
    """``count`` as an int; DonGymError unless it is an integer >= 0."""
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
        raise DonGymError(f"distractors={count!r}: expected an integer >= 0")
    return int(count)


def _random_shape(rng: np.random.Generator) -> dict[str, Any]:
    """Shape parameters (metres): a box, an upright cylinder, a sphere, a lying capsule or a lying rod
    (a thin cylinder of a part's proportions)."""
    kind = str(rng.choice(_SHAPES))
    if kind == "box":
        half = rng.uniform([0.01, 0.01, 0.005], [0.05, 0.04, 0.03])
        return {"kind": kind, "half_extents": half, "footprint_m": float(np.hypot(half[0], half[1]))}
    if kind == "cylinder":
        radius, length = rng.uniform(0.008, 0.035), rng.uniform(0.01, 0.08)
        return {"kind": kind, "radius": radius, "length": length, "footprint_m": radius}
    if kind == "sphere":
        radius = rng.uniform(0.008, 0.03)
        return {"kind": kind, "radius": radius, "footprint_m": radius}
    radius = rng.uniform(0.004, 0.012) if kind == "rod" else rng.uniform(0.008, 0.02)
    length = rng.uniform(0.04, 0.14)
    return {"kind": kind, "radius": radius, "length": length, "footprint_m": 0.5 * length + radius}


def _height_above_table_m(shape: dict[str, Any]) -> float:
    """Height of the body's origin above the table when it stands (box, cylinder) or lies (the rest)."""
    if shape["kind"] == "box":
        return float(shape["half_extents"][2])
    if shape["kind"] == "cylinder":
        return 0.5 * float(shape["length"])
    return float(shape["radius"])


class Distractors:
    """A pool of ``count * POOL_PER_DISTRACTOR`` static primitive bodies in ``sim``'s scene.

    The pool's shapes come from ``shape_seed`` (the same for every scene of a recorder, so scenes stay
    reproducible whatever was recorded before); colours, choice and placement come from each scene's
    generator. Distractors are static: they never move, and the part settles before they are placed
    around it.
    """

    def __init__(self, sim: Bullet, count: int, shape_seed: int = 0) -> None:
        self.sim = sim
        self.count = check_distractor_count(count)
        shape_rng = np.random.default_rng(shape_seed)
        self.shapes = [_random_shape(shape_rng) for _ in range(self.count * POOL_PER_DISTRACTOR)]
        self.body_ids = [self._create(i, shape) for i, shape in enumerate(self.shapes)]

    def _create(self, index: int, shape: dict[str, Any]) -> int:
        client = self.sim.client
        kind = shape["kind"]
        if kind == "box":
            geometry = {"shapeType": p.GEOM_BOX, "halfExtents": [float(v) for v in shape["half_extents"]]}
            collision = client.createCollisionShape(**geometry)
            visual = client.createVisualShape(**geometry)
        elif kind == "sphere":
            geometry = {"shapeType": p.GEOM_SPHERE, "radius": float(shape["radius"])}
            collision = client.createCollisionShape(**geometry)
            visual = client.createVisualShape(**geometry)
        else:
            # PyBullet names a cylinder's or capsule's length "height" for collision and "length" for visuals.
            geometry = {"shapeType": p.GEOM_CAPSULE if kind == "capsule" else p.GEOM_CYLINDER}
            radius, length = float(shape["radius"]), float(shape["length"])
            collision = client.createCollisionShape(**geometry, radius=radius, height=length)
            visual = client.createVisualShape(**geometry, radius=radius, length=length)
        body_id = client.createMultiBody(
            baseMass=0.0,
            baseCollisionShapeIndex=collision,
            baseVisualShapeIndex=visual,
            basePosition=[0.0, 0.0, _PARKED_Z_M - index],
        )
        return self.sim.add_body(f"distractor_{index}", body_id)

    def scatter(self, rng: np.random.Generator, part_xy_m: np.ndarray, part_radius_m: float) -> list[dict[str, Any]]:
        """Place ``count`` pool bodies, chosen, coloured and posed from ``rng``, at free spots of
        :data:`DISTRACTOR_REGION_M` at least :data:`CLEARANCE_M` from the part's bounding circle (centre
        ``part_xy_m``, radius ``part_radius_m``, metres) and from each other; park the rest. A body with no
        free spot after many tries stays parked. Returns what was placed (kind, position, colour)."""
        client = self.sim.client
        chosen = rng.permutation(len(self.body_ids))[: self.count] if self.count else np.array([], int)
        placed: list[dict[str, Any]] = []
        taken: list[tuple[np.ndarray, float]] = [(np.asarray(part_xy_m, float)[:2], float(part_radius_m))]
        x0, x1, y0, y1 = DISTRACTOR_REGION_M
        for index, body_id in enumerate(self.body_ids):
            client.resetBasePositionAndOrientation(body_id, [0.0, 0.0, _PARKED_Z_M - index], [0, 0, 0, 1])
        for index in chosen.tolist():
            shape, body_id = self.shapes[index], self.body_ids[index]
            rgba = [*rng.uniform(0.05, 0.95, size=3), 1.0]
            yaw = rng.uniform(0, 2 * np.pi)
            for _ in range(_MAX_PLACEMENT_TRIES):
                xy = rng.uniform([x0, y0], [x1, y1])
                if all(np.linalg.norm(xy - c) >= r + shape["footprint_m"] + CLEARANCE_M for c, r in taken):
                    break
            else:
                continue
            taken.append((xy, shape["footprint_m"]))
            # Capsules and rods lie on their side (their axis is the body's z); the rest stand upright.
            lying = shape["kind"] in ("capsule", "rod")
            rotation = Rotation.from_euler("yz", [np.pi / 2 if lying else 0.0, yaw])  # extrinsic: lay down, then yaw
            position = [float(xy[0]), float(xy[1]), TABLE_TOP_Z_M + _height_above_table_m(shape)]
            client.resetBasePositionAndOrientation(body_id, position, rotation.as_quat().tolist())
            client.changeVisualShape(body_id, -1, rgbaColor=rgba)
            placed.append({"kind": shape["kind"], "position_m": position, "rgba": rgba})
        return placed
