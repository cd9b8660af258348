"""Object models: the built-in industrial parts and any mesh file a user brings.

An :class:`ObjectModel` is a triangle mesh in metres in the *object frame*, plus what the rest of
don_gym needs to know about the part: its material, symmetry axis and "+axis" (:func:`load_object`).
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from don_gym.errors import MeshError

#: Density of steel in kg/m^3 (carbon steel 7.75-8.05 g/cm^3; 7.85 is the usual design value).
STEEL_DENSITY_KG_M3 = 7850.0

#: Relative tolerance of :meth:`ShapeSignature.differences`: each quantity may differ by this fraction of
#: its size. Far above what single-precision mesh files (~1e-7) or other machines' arithmetic (~1e-12)
#: change, far below a different part's geometry (a 0.1 mm longer 40 mm part changes its volume 2.5e-3).
SHAPE_MATCH_RTOL = 1e-4

#: Largest extent (metres) a mesh may have before ``scale=None`` assumes millimetres.
#: Robot parts picked by a Panda are well under 1 m; a CAD export in millimetres of such
#: a part has extents of tens to hundreds of units.
AUTO_MM_THRESHOLD_M = 1.0


@dataclass(frozen=True)
class Material:
    """Physical and optical properties of a part's material.

    Attributes:
        name: human-readable name.
        density_kg_m3: density in kg/m^3, gives mass and inertia with the mesh volume.
        lateral_friction: Coulomb friction coefficient used in simulation.
        specular: 0 (matte, e.g. plastic) to 1 (polished metal). Drives missing depth
            on the simulated stereo sensor: specular surfaces reflect the projector
            pattern away at oblique incidence.
        rgba: base colour for rendering, each in [0, 1].
        metallic: 0 (dielectric) to 1 (metal): a metal's colour tints its reflections ("pbr" renderer).
        roughness: 0 (mirror polish) to 1 (matte), GGX's perceptual roughness ("pbr" renderer).
    """

    name: str
    density_kg_m3: float
    lateral_friction: float
    specular: float
    rgba: tuple[float, float, float, float]
    metallic: float = 0.0
    roughness: float = 0.5

    def __post_init__(self) -> None:
        for what in ("specular", "metallic", "roughness"):
            value = getattr(self, what)
            if not isinstance(value, (int, float, np.floating)) or not 0.0 <= float(value) <= 1.0:
                raise MeshError(f"material {self.name!r}: {what}={value!r}, expected a number in [0, 1]")
        rgba = np.asarray(self.rgba, dtype=object)
        if rgba.shape != (4,) or not all(isinstance(v, (int, float, np.floating)) and 0.0 <= v <= 1.0 for v in rgba):
            raise MeshError(f"material {self.name!r}: rgba={self.rgba!r}, expected 4 numbers in [0, 1]")


# Steel's base colour is its reflectance at normal incidence (about 0.56-0.58 for iron, a touch bluer);
# roughness 0.3: a turned, not polished, surface.
STEEL = Material(
    "steel",
    STEEL_DENSITY_KG_M3,
    lateral_friction=0.8,
    specular=0.9,
    rgba=(0.72, 0.73, 0.76, 1.0),
    metallic=1.0,
    roughness=0.3,
)
#: ABS-like plastic, for user meshes that say so.
PLASTIC = Material(
    "plastic", 1050.0, lateral_friction=0.9, specular=0.1, rgba=(0.2, 0.35, 0.8, 1.0), metallic=0.0, roughness=0.4
)
MATERIALS = {m.name: m for m in (STEEL, PLASTIC)}


@dataclass(frozen=True)
class ShapeSignature:
    """Identity of a part's geometry that depends neither on float bits, nor on vertex order, nor on where
    the part sits in its file's frame (see docs/reliability.md, "Part identity").

    Attributes:
        n_vertices, n_faces: of the cleaned mesh (exact).
        area_m2: surface area.
        volume_m3: :attr:`ObjectModel.volume_m3`.
        principal_moments_m5: the three principal moments of inertia at unit density, ascending.
        radius_m: largest distance of a vertex from the centre of mass.

    Mirror images share a signature; so do a part and its copy moved in its frame.
    """

    n_vertices: int
    n_faces: int
    area_m2: float
    volume_m3: float
    principal_moments_m5: tuple[float, float, float]
    radius_m: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "n_vertices": self.n_vertices,
            "n_faces": self.n_faces,
            "area_m2": self.area_m2,
            "volume_m3": self.volume_m3,
            "principal_moments_m5": list(self.principal_moments_m5),
            "radius_m": self.radius_m,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "shape signature") -> ShapeSignature:
        """Parse :meth:`to_dict`'s output; MeshError naming ``source`` if it is not one."""
        try:
            moments = tuple(float(v) for v in data["principal_moments_m5"])
            counts = [data["n_vertices"], data["n_faces"]]
            if len(moments) != 3 or any(isinstance(c, bool) or not isinstance(c, int) or c < 1 for c in counts):
                raise ValueError("expected 3 moments and positive integer counts")
            return cls(
                int(counts[0]), int(counts[1]), float(data["area_m2"]), float(data["volume_m3"]), moments,
                float(data["radius_m"]),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError) as exc:
            raise MeshError(f"{source}: not a shape signature ({type(exc).__name__}: {exc})") from exc

    def differences(self, other: ShapeSignature, rtol: float = SHAPE_MATCH_RTOL) -> list[str]:
        """What differs from ``other`` beyond ``rtol`` (counts: at all), as ``"name a vs b"``; empty: the same shape."""
        out = [
            f"{name} {a} vs {b}"
            for name, a, b in (("vertices", self.n_vertices, other.n_vertices), ("faces", self.n_faces, other.n_faces))
            if a != b
        ]
        largest_moment = max(max(self.principal_moments_m5), max(other.principal_moments_m5))
        pairs = [
            ("area_m2", self.area_m2, other.area_m2, max(abs(self.area_m2), abs(other.area_m2))),
            ("volume_m3", self.volume_m3, other.volume_m3, max(abs(self.volume_m3), abs(other.volume_m3))),
            ("radius_m", self.radius_m, other.radius_m, max(self.radius_m, other.radius_m)),
        ] + [
            (f"principal_moment_{i}_m5", a, b, largest_moment)
            for i, (a, b) in enumerate(zip(self.principal_moments_m5, other.principal_moments_m5, strict=True))
        ]
        out += [f"{name} {a:.6g} vs {b:.6g}" for name, a, b, scale in pairs if abs(a - b) > rtol * scale]
        return out


def part_name(name_or_path: str | Path) -> str:
    """The name don_gym records for a part wherever one is written or shown: a built-in's name, else the
    mesh file's stem (``"parts/my_part.stl"`` -> ``"my_part"``), as :attr:`ObjectModel.name`."""
    key = str(name_or_path)
    return key if key in _BUILTINS else Path(key).expanduser().stem


@dataclass(frozen=True, eq=False)
class ObjectModel:
    """A rigid part: mesh in metres in the object frame plus its material and axes.

    Object frame of the built-ins: origin at the centre of mass, symmetry axis along z, "+axis" = +z.
    They are generated procedurally by revolving a (radius, height) profile about z
    (:func:`trimesh.creation.revolve`), so they need no data files.

    Attributes:
        name: short name (:func:`part_name`: the built-in name or the file stem).
        mesh: triangle mesh, vertices in metres, object frame.
        material: see :class:`Material`.
        symmetry_axis: (3,) unit vector of the rotational symmetry axis in the object
            frame, or None when the part has none (or it is not declared).
        plus_axis: (3,) unit vector in the object frame of the part's "+axis", the
            direction the grasp/place task orients. For axisymmetric parts it is the
            symmetry axis with a chosen sign (toolcap: open end -> flange).
        source: ``"builtin:<name>"`` or the resolved file path.
    """

    name: str
    mesh: trimesh.Trimesh
    material: Material
    symmetry_axis: np.ndarray | None
    plus_axis: np.ndarray
    source: str
    _hash: str = field(default="", repr=False)

    @property
    def volume_m3(self) -> float:
        """Enclosed volume in m^3 (convex hull volume when the mesh is not watertight)."""
        return float(self.mesh.volume if self.mesh.is_watertight else self.mesh.convex_hull.volume)

    @property
    def mass_kg(self) -> float:
        return self.volume_m3 * self.material.density_kg_m3

    @property
    def center_of_mass(self) -> np.ndarray:
        """(3,) centre of mass in the object frame, metres."""
        source = self.mesh if self.mesh.is_watertight else self.mesh.convex_hull
        return np.asarray(source.center_mass, dtype=np.float64)

    @property
    def inertia_kg_m2(self) -> np.ndarray:
        """(3, 3) inertia tensor about the centre of mass, object-frame axes, kg m^2."""
        source = self.mesh if self.mesh.is_watertight else self.mesh.convex_hull
        # trimesh reports inertia for unit density about the centre of mass.
        return np.asarray(source.moment_inertia, dtype=np.float64) * self.material.density_kg_m3

    @property
    def extents_m(self) -> np.ndarray:
        """(3,) axis-aligned bounding-box size in the object frame, metres."""
        return np.asarray(self.mesh.extents, dtype=np.float64)

    def axis_endpoints(self) -> tuple[np.ndarray, np.ndarray]:
        """The two points where the +axis line through the centre of mass leaves the
        bounding extent of the mesh: ``(minus_end, plus_end)``, (3,) each, object frame."""
        along = (self.mesh.vertices - self.center_of_mass) @ self.plus_axis
        return (
            self.center_of_mass + along.min() * self.plus_axis,
            self.center_of_mass + along.max() * self.plus_axis,
        )

    @property
    def mesh_hash(self) -> str:
        """Short content hash of the vertex and face bytes: tells this process's meshes apart (caches,
        files written here), not parts across machines (:attr:`shape_signature` does that)."""
        return self._hash

    @cached_property
    def shape_signature(self) -> ShapeSignature:
        """The part's geometric identity (:class:`ShapeSignature`), compared across machines and files."""
        source = self.mesh if self.mesh.is_watertight else self.mesh.convex_hull
        moments = np.linalg.eigvalsh(np.asarray(source.moment_inertia, dtype=np.float64))
        radius = np.linalg.norm(np.asarray(self.mesh.vertices, dtype=np.float64) - self.center_of_mass, axis=1).max()
        return ShapeSignature(
            n_vertices=len(self.mesh.vertices),
            n_faces=len(self.mesh.faces),
            area_m2=float(self.mesh.area),
            volume_m3=self.volume_m3,
            principal_moments_m5=tuple(float(m) for m in np.sort(moments)),
            radius_m=float(radius),
        )


def _finish(name: str, mesh: trimesh.Trimesh, material: Material, symmetry_axis, plus_axis, source: str) -> ObjectModel:
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    unit = None if symmetry_axis is None else np.asarray(symmetry_axis, float) / np.linalg.norm(symmetry_axis)
    plus = np.asarray(plus_axis, float) / np.linalg.norm(plus_axis)
    return ObjectModel(name, mesh, material, unit, plus, source, digest.hexdigest()[:16])


def _resample_profile(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Insert points along each segment of a 2D polyline so no segment exceeds ``spacing_m``.

    Revolved meshes with long thin triangles give poorer Laplacians; near-uniform
    sampling of the profile keeps triangles close to the size of the angular sections.
    """
    out = [points[0]]
    for start, end in zip(points[:-1], points[1:], strict=True):
        count = max(1, int(np.ceil(np.linalg.norm(end - start) / spacing_m)))
        for k in range(1, count + 1):
            out.append(start + (end - start) * k / count)
    return np.asarray(out)


def _revolve(profile_r_z_m: np.ndarray, sections: int, spacing_m: float) -> trimesh.Trimesh:
    """Revolve a closed (radius, height) profile that starts and ends on the axis."""
    profile = _resample_profile(np.asarray(profile_r_z_m, dtype=np.float64), spacing_m)
    mesh = trimesh.creation.revolve(profile, sections=sections)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    if mesh.volume < 0:
        mesh.invert()
    # Origin at the centre of mass; symmetric about z so only z shifts.
    mesh.apply_translation([0.0, 0.0, -mesh.center_mass[2]])
    return mesh


def toolcap_mesh(sections: int = 64) -> trimesh.Trimesh:
    """Steel tool cap, 40 mm long: a 28 mm body with a 34 mm flange on the closed end and
    an 18 mm bore, 24 mm deep, in the open end. Built with z from the open end (z<0)
    towards the flange (z>0). Units: metres."""
    length, body_r, flange_r, flange_t, bore_r, bore_depth = 0.040, 0.014, 0.017, 0.006, 0.009, 0.024
    chamfer = 0.001
    profile = np.array(
        [
            [0.0, length],  # flange face centre (closed end)
            [flange_r - chamfer, length],
            [flange_r, length - chamfer],
            [flange_r, length - flange_t],
            [body_r, length - flange_t],
            [body_r, chamfer],
            [body_r - chamfer, 0.0],  # open end rim, outer edge
            [bore_r, 0.0],  # open end rim, inner edge
            [bore_r, bore_depth],  # bore wall
            [0.0, bore_depth],  # bore floor centre
        ]
    )
    return _revolve(profile[::-1], sections, spacing_m=0.0015)


def shaft_mesh(sections: int = 48) -> trimesh.Trimesh:
    """Stepped steel shaft, 120 mm long: 10 mm journal (22 mm), 16 mm collar (38 mm),
    13 mm body (40 mm), 12 mm journal (20 mm), with 0.5 mm chamfers. Built along z
    from the 10 mm end (z<0) to the 12 mm end (z>0). Units: metres."""
    steps = [(0.005, 0.022), (0.008, 0.038), (0.0065, 0.040), (0.006, 0.020)]  # (radius, length)
    c = 0.0005
    profile = [[0.0, 0.0], [steps[0][0] - c, 0.0], [steps[0][0], c]]
    z = 0.0
    for i, (radius, length) in enumerate(steps):
        if i > 0:
            profile.append([radius, z])
        z += length
        if i + 1 < len(steps):
            profile.append([radius, z])
        else:
            profile += [[radius, z - c], [radius - c, z], [0.0, z]]
    return _revolve(np.asarray(profile)[::-1], sections, spacing_m=0.002)


_BUILTINS = {
    "toolcap": (toolcap_mesh, "Steel tool cap, 28 mm body, 34 mm flange, 40 mm long; +axis: open end -> flange."),
    "shaft": (shaft_mesh, "Stepped steel shaft, 120 mm long, 10-16 mm diameters; +axis: 10 mm end -> 12 mm end."),
}


def builtin_names() -> list[str]:
    """Names accepted by :func:`load_object` besides file paths."""
    return sorted(_BUILTINS)


def describe_builtin(name: str) -> str:
    return _BUILTINS[name][1]


def _principal_axis(mesh: trimesh.Trimesh) -> np.ndarray:
    """Long axis of a mesh (inertia axis with the smallest moment), signed so that the
    third moment of the surface about the centroid along it is positive (the +axis then
    points towards the end with more surface far out), which depends on the shape only."""
    values, vectors = np.linalg.eigh(mesh.convex_hull.moment_inertia if not mesh.is_watertight else mesh.moment_inertia)
    axis = vectors[:, int(np.argmin(values))]
    along = (mesh.triangles_center - mesh.centroid) @ axis
    skew = float(np.sum(mesh.area_faces * along**3))
    return axis if skew >= 0 else -axis


def check_faces(faces: np.ndarray, vertex_count: int, what: str) -> None:
    """MeshError naming ``what`` unless ``faces`` is (M, 3) triangles of vertex indices in 0..vertex_count-1: a
    damaged file's face may name a vertex it does not hold."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not (faces.size == 0 or np.issubdtype(faces.dtype, np.integer)):
        raise MeshError(f"{what}: faces of shape {faces.shape} ({faces.dtype}); expected triangles of vertex indices")
    if faces.size and (faces.min() < 0 or faces.max() >= vertex_count):
        bad = int(faces.max()) if faces.max() >= vertex_count else int(faces.min())
        raise MeshError(
            f"{what}: a face names vertex {bad}, but the mesh has {vertex_count} vertices (0..{vertex_count - 1}); "
            "the file is damaged"
        )


def clean_mesh(mesh: trimesh.Trimesh, what: str) -> trimesh.Trimesh:
    """Validate and clean a mesh: finite vertices, merged duplicates, no degenerate or
    duplicate faces, no unreferenced vertices. ``what`` names the input in errors."""
    vertices = np.asarray(mesh.vertices)
    if len(vertices) == 0 or len(mesh.faces) == 0:
        raise MeshError(f"{what}: mesh is empty (no vertices or faces); expected a triangle mesh")
    if not np.all(np.isfinite(vertices)):
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        raise MeshError(f"{what}: {bad} vertices are NaN or infinite; expected finite coordinates")
    check_faces(mesh.faces, len(vertices), what)
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise MeshError(f"{what}: every face is degenerate (zero area); expected a triangle mesh")
    return mesh


def load_object(
    name_or_path: str | Path,
    scale: float | None = None,
    material: str | Material = "steel",
    plus_axis: np.ndarray | None = None,
) -> ObjectModel:
    """Load a built-in part by name or any mesh file trimesh reads.

    Args:
        name_or_path: ``"toolcap"``, ``"shaft"``, or a path to STL, OBJ, PLY, OFF, GLB...
        scale: factor from file units to metres (e.g. 0.001 for a CAD file in mm).
            None: built-ins are already in metres; files whose largest extent exceeds
            ``AUTO_MM_THRESHOLD_M`` (1 m) are taken to be in millimetres and scaled by
            0.001 with a warning, everything else is taken as metres.
        material: a :class:`Material` or a name from ``MATERIALS`` ("steel", "plastic").
        plus_axis: (3,) +axis in the file's object frame. None: built-ins declare theirs;
            a file gets its principal (long) inertia axis, signed by a shape-only rule.

    Returns:
        An :class:`ObjectModel`. Files keep their own frame (after scaling); their
        symmetry axis is None (undeclared).

    Raises:
        MeshError: unknown name, missing or unreadable file, empty mesh, non-finite
            vertices, or a non-positive scale.
    """
    if isinstance(material, str):
        if material not in MATERIALS:
            raise MeshError(f"material {material!r} is unknown; expected one of {sorted(MATERIALS)}")
        material = MATERIALS[material]
    if scale is not None and not (np.isfinite(scale) and scale > 0):
        raise MeshError(f"scale={scale!r}: expected a positive, finite factor from file units to metres")

    key = str(name_or_path)
    if key in _BUILTINS:
        mesh = _BUILTINS[key][0]()
        if scale is not None:
            mesh.apply_scale(scale)
        axis = np.array([0.0, 0.0, 1.0])
        return _finish(key, mesh, material, axis, axis if plus_axis is None else plus_axis, f"builtin:{key}")

    path = Path(name_or_path).expanduser()
    if not path.suffix and not path.exists():
        raise MeshError(
            f"object {key!r} is neither a built-in ({', '.join(builtin_names())}) nor an existing mesh file"
        )
    if path.is_dir():
        raise MeshError(f"mesh file {str(path)!r} is a directory; expected a mesh file (STL, OBJ, PLY, OFF, GLB)")
    if not path.is_file():
        raise MeshError(f"mesh file {str(path)!r} does not exist")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(f"mesh file {str(path)!r} could not be read ({type(exc).__name__}: {exc})") from exc
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"mesh file {str(path)!r} holds no triangle mesh (got {type(loaded).__name__})")
    mesh = clean_mesh(loaded, f"mesh file {str(path)!r}")
    if scale is None:
        largest = float(mesh.extents.max())
        if largest > AUTO_MM_THRESHOLD_M:
            warnings.warn(
                f"{path.name}: largest extent {largest:g} > {AUTO_MM_THRESHOLD_M} m, assuming millimetres; "
                "pass scale= to override",
                stacklevel=2,
            )
            scale = 0.001
    if scale is not None:
        mesh.apply_scale(scale)
    axis = _principal_axis(mesh) if plus_axis is None else np.asarray(plus_axis, dtype=np.float64)
    return _finish(part_name(path), mesh, material, None, axis, str(path.resolve()))
