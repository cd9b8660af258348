"""Randomised backdrops: procedural textures on the table top and the floor.

The paper randomises the background of its recordings per scene; a network that has only seen a
few kinds of background can take an unseen, high-contrast one for the part. :func:`backdrop_texture`
draws one texture of a *family* (the pure core: a generator in, an image out) and :class:`Backdrop`
lays textured quads over the table top and the floor of a scene and re-textures them (and recolours the
handover cradle). Its users: the dataset recorder (:class:`~don_gym.sim.recorder.SceneRecorder`) and the
env's ``background="random"`` (:class:`~don_gym.sim.env.PickPlaceEnv`).

Families (:data:`BACKDROP_SETS`): ``"classic"`` is the recorder's original three (smooth two-colour
noise, stripes, checks); ``"wide"`` adds plain colours, gradients, many-colour noise, dots, scattered
rectangles (printed clutter) and wood-like grain; ``"mixed"`` draws half of its backdrops from the classic
three and half from all nine, so that data with the wide variety still shows the classic families (the
default scenes, and the env's ``background="random"``) twice as often as ``"wide"`` does.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pybullet as p

from don_gym.errors import DonGymError
from don_gym.io import write_png, write_text_atomic
from don_gym.sim.bullet import Bullet
from don_gym.sim.task import TABLE_BOUNDS_M, TABLE_TOP_Z_M

#: Texture families by set name; the first three are the recorder's originals, in their original order.
BACKDROP_SETS: dict[str, tuple[str, ...]] = {
    "classic": ("noise", "stripes", "checks"),
    "wide": ("noise", "stripes", "checks", "plain", "gradient", "palette", "dots", "rectangles", "grain"),
}
# A family is drawn uniformly from the tuple, so repeating the classic three weights them: 12 of 18 entries
# (2/3) are classic, which is half classic plus half drawn from all nine.
BACKDROP_SETS["mixed"] = BACKDROP_SETS["classic"] * 3 + BACKDROP_SETS["wide"]
#: Height of the floor under the table (m), seen past the table's edges.
FLOOR_Z_M = -0.75


def check_backdrop_set(name: str) -> tuple[str, ...]:
    """The families of the set ``name``; DonGymError naming the sets for an unknown one."""
    if not isinstance(name, str) or name not in BACKDROP_SETS:
        raise DonGymError(f"backgrounds={name!r}: expected one of {list(BACKDROP_SETS)}")
    return BACKDROP_SETS[name]


def _smooth_noise(rng: np.random.Generator, size_px: int, cells: int, channels: int = 1) -> np.ndarray:
    coarse = rng.uniform(0, 1, size=(cells, cells, channels)).astype(np.float32)
    smooth = cv2.resize(coarse, (size_px, size_px), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    return smooth.reshape(size_px, size_px, channels)


def backdrop_texture(
    rng: np.random.Generator, families: tuple[str, ...] = BACKDROP_SETS["classic"], size_px: int = 128
) -> tuple[np.ndarray, str]:
    """One procedural texture: ``(size_px, size_px, 3)`` uint8 RGB and the family it was drawn from.

    The family is drawn uniformly from ``families``. The generator's draws for the classic families are
    the recorder's original ones, so a classic backdrop is the same, pixel for pixel, for the same seed.
    """
    colour_a, colour_b = rng.uniform(0, 255, size=(2, 3))
    kind = str(rng.choice(list(families)))
    v, u = np.mgrid[0:size_px, 0:size_px] / size_px
    if kind == "noise":
        weight = _smooth_noise(rng, size_px, int(rng.integers(4, 24)))[..., 0]
    elif kind == "stripes":
        angle = rng.uniform(0, np.pi)
        weight = 0.5 + 0.5 * np.sin(2 * np.pi * rng.integers(3, 12) * (u * np.cos(angle) + v * np.sin(angle)))
    elif kind == "checks":
        count = int(rng.integers(3, 10))
        weight = ((np.floor(u * count) + np.floor(v * count)) % 2).astype(np.float64)
    elif kind == "plain":
        weight = np.zeros_like(u)
    elif kind == "gradient":
        angle = rng.uniform(0, 2 * np.pi)
        along = u * np.cos(angle) + v * np.sin(angle)
        weight = (along - along.min()) / max(float(np.ptp(along)), 1e-9)
    elif kind == "palette":
        # Smooth noise in every channel: many colours at once, as a cluttered or printed surface.
        image = 255 * _smooth_noise(rng, size_px, int(rng.integers(3, 16)), channels=3)
        return image.clip(0, 255).astype(np.uint8), kind
    elif kind == "dots":
        count, radius = int(rng.integers(3, 9)), rng.uniform(0.15, 0.4)
        cell_u, cell_v = (u * count) % 1 - 0.5, (v * count) % 1 - 0.5
        weight = (np.hypot(cell_u, cell_v) < radius).astype(np.float64)
    elif kind == "rectangles":
        image = np.empty((size_px, size_px, 3))
        image[:] = colour_a
        for _ in range(int(rng.integers(4, 16))):
            u0, v0 = rng.uniform(-0.2, 1.0, size=2)
            width, height = rng.uniform(0.05, 0.5, size=2)
            inside = (u >= u0) & (u < u0 + width) & (v >= v0) & (v < v0 + height)
            image[inside] = rng.uniform(0, 255, size=3)
        return image.clip(0, 255).astype(np.uint8), kind
    elif kind == "grain":
        warp = _smooth_noise(rng, size_px, int(rng.integers(3, 8)))[..., 0]
        rings = rng.uniform(8, 30)
        weight = 0.5 + 0.5 * np.sin(2 * np.pi * (rings * v + 3.0 * warp))
    else:
        raise DonGymError(f"backdrop family {kind!r} is unknown; expected one of {BACKDROP_SETS['wide']}")
    image = colour_a * (1 - weight[..., None]) + colour_b * weight[..., None]
    return image.clip(0, 255).astype(np.uint8), kind


class Backdrop:
    """Textured quads over the table top and the floor of ``sim``'s scene, re-textured by :meth:`randomise`.

    Box shapes carry no texture coordinates, so the textures go on visual-only quads: one laid over the
    table top (0.2 mm above it, so nothing on the table is ever hidden) and one floor at :data:`FLOOR_Z_M`.
    The quads have no collision shape: they change pixels only, never physics. ``cradle_id``: the handover
    cradle's body, which :meth:`randomise` also gives a random colour (None: left as it is).
    """

    def __init__(self, sim: Bullet, cradle_id: int | None = None) -> None:
        self.sim = sim
        self.cradle_id = cradle_id
        self._texture_dir = tempfile.TemporaryDirectory(prefix="don_gym_textures_")
        self._texture_count = 0
        x0, x1, y0, y1 = TABLE_BOUNDS_M
        self.table_surface_id = self._add_quad("table_surface", (x0, x1, y0, y1), TABLE_TOP_Z_M + 0.0002, repeats=3)
        self.floor_id = self._add_quad("floor", (-2.0, 3.0, -2.5, 2.5), FLOOR_Z_M, repeats=6)

    def _add_quad(
        self, name: str, bounds_xy: tuple[float, float, float, float], z: float, repeats: int, cells: int = 12
    ) -> int:
        """A textured horizontal rectangle, split into ``cells`` x ``cells`` squares because
        TinyRenderer maps textures affinely per triangle (large triangles warp visibly). It goes through an
        OBJ file: the EGL renderer draws only meshes it can read from a file (one given as arrays is skipped,
        and the table would show bare)."""
        x0, x1, y0, y1 = bounds_xy
        t = np.linspace(0.0, 1.0, cells + 1)
        tu, tv = np.meshgrid(t, t, indexing="xy")
        vertices = np.stack([x0 + (x1 - x0) * tu, y0 + (y1 - y0) * tv, np.full_like(tu, z)], axis=-1).reshape(-1, 3)
        uvs = (np.stack([tu, tv], axis=-1) * repeats).reshape(-1, 2)
        corner = (np.arange(cells)[None, :] + (cells + 1) * np.arange(cells)[:, None]).ravel()
        indices = np.stack([corner, corner + 1, corner + cells + 2, corner, corner + cells + 2, corner + cells + 1], 1)
        path = Path(self._texture_dir.name) / f"{name}.obj"
        lines = [f"v {x:.9g} {y:.9g} {zz:.9g}" for x, y, zz in vertices]
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in uvs]
        lines.append("vn 0 0 1")
        lines += ["f " + " ".join(f"{i + 1}/{i + 1}/1" for i in face) for face in indices.reshape(-1, 3)]
        write_text_atomic(path, "\n".join(lines) + "\n")
        visual = self.sim.client.createVisualShape(p.GEOM_MESH, fileName=str(path))
        return self.sim.add_body(name, self.sim.client.createMultiBody(baseMass=0.0, baseVisualShapeIndex=visual))

    def randomise(
        self, rng: np.random.Generator, families: tuple[str, ...] = BACKDROP_SETS["classic"]
    ) -> dict[str, Any]:
        """New textures on the table top, then the floor, then the cradle's colour, from ``rng``; returns what
        was drawn (each surface's family and mean colour, ``cradle_rgba``), for the scene's record."""
        client = self.sim.client
        settings: dict[str, Any] = {}
        for name, body_id in (("table", self.table_surface_id), ("floor", self.floor_id)):
            texture, family = backdrop_texture(rng, families)
            # PyBullet caches textures by file name: every texture needs a new one.
            self._texture_count += 1
            path = Path(self._texture_dir.name) / f"{name}_{self._texture_count}.png"
            write_png(path, cv2.cvtColor(texture, cv2.COLOR_RGB2BGR))  # raises, not a silently missing texture
            client.changeVisualShape(body_id, -1, rgbaColor=[1, 1, 1, 1], textureUniqueId=self.sim.load_texture(path))
            settings[f"{name}_texture_mean_rgb"] = texture.reshape(-1, 3).mean(axis=0).round(1)
            settings[f"{name}_texture_family"] = family
        if self.cradle_id is not None:
            settings["cradle_rgba"] = [*rng.uniform(0.1, 0.9, size=3), 1.0]
            client.changeVisualShape(self.cradle_id, -1, rgbaColor=settings["cradle_rgba"])
        return settings

    def close(self) -> None:
        self._texture_dir.cleanup()
