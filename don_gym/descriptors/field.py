"""The per-vertex descriptor field of one mesh (:class:`DescriptorField`), its ``.npz`` file format,
interpolation at surface points, and mesh content hashes."""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh

from don_gym.errors import DonGymError, MeshError
from don_gym.io import atomic_path
from don_gym.objects import ObjectModel

_FORMAT_VERSION = 1

#: Two descriptor fields are the same when no vertex descriptor (nor the background) differs by more
#: than this (max abs difference; descriptors lie in [0, 1]). The same mesh embedded on another machine
#: differs by ~1e-7; the direct and multilevel solvers differ by several 1e-3, which counts as different.
FIELD_MATCH_ATOL = 1e-3


def mesh_arrays(mesh: trimesh.Trimesh | ObjectModel) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertices float64 (N,3), faces int64 (F,3), mesh_hash) of a Trimesh or ObjectModel, validated."""
    if isinstance(mesh, ObjectModel):
        tm, digest = mesh.mesh, mesh.mesh_hash
        what = f"object {mesh.name!r}"
    elif isinstance(mesh, trimesh.Trimesh):
        tm, digest, what = mesh, None, "mesh"
    else:
        raise MeshError(f"expected a trimesh.Trimesh or don_gym.objects.ObjectModel, got {type(mesh).__name__}")
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0 or faces.size == 0:
        raise MeshError(f"{what}: mesh is empty (no vertices or faces); expected a triangle mesh")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise MeshError(f"{what}: faces have shape {faces.shape}; expected (F, 3) triangles")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{what}: faces index vertices outside 0..{len(vertices) - 1}")
    if not np.all(np.isfinite(vertices)):
        bad = int((~np.isfinite(vertices)).any(axis=1).sum())
        raise MeshError(f"{what}: {bad} vertices are NaN or infinite; expected finite coordinates")
    return vertices, faces, digest if digest else mesh_content_hash(vertices, faces)


def mesh_content_hash(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Short content hash of a mesh, the same as :attr:`don_gym.objects.ObjectModel.mesh_hash`."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    return digest.hexdigest()[:16]


def interpolate_field(
    vertex_descriptors: np.ndarray, faces: np.ndarray, triangle_ids: np.ndarray, barycentric: np.ndarray
) -> np.ndarray:
    """Descriptors at surface points given by triangle and barycentric coordinates.

    Args:
        vertex_descriptors: (N, D) per-vertex values.
        faces: (F, 3) vertex indices of the triangles.
        triangle_ids: (M,) index into ``faces`` of each point's triangle.
        barycentric: (M, 3) weights of the triangle's three vertices (rows sum to 1).

    Returns:
        (M, D) float32 descriptors (linear interpolation inside each triangle).
    """
    values = np.asarray(vertex_descriptors)
    faces = np.asarray(faces)
    tri = np.asarray(triangle_ids)
    bary = np.asarray(barycentric, dtype=np.float64)
    if values.ndim != 2 or faces.ndim != 2 or faces.shape[1] != 3:
        raise DonGymError(
            f"vertex_descriptors {values.shape} / faces {faces.shape}: expected (N, D) values and (F, 3) faces"
        )
    if tri.ndim != 1 or bary.shape != (len(tri), 3):
        raise DonGymError(f"triangle_ids {tri.shape} / barycentric {bary.shape}: expected (M,) and (M, 3)")
    if len(tri) and (tri.min() < 0 or tri.max() >= len(faces)):
        raise DonGymError(f"triangle_ids must lie in 0..{len(faces) - 1}; got {tri.min()}..{tri.max()}")
    corners = values[faces[tri]]  # (M, 3, D)
    return np.einsum("mk,mkd->md", bary, corners.astype(np.float64)).astype(np.float32)


@dataclass(frozen=True, eq=False)
class DescriptorField:
    """Optimal descriptors of one mesh (see :func:`embed`).

    Attributes:
        vertex_descriptors: (N, dim) float32, each dimension normalised to [0, 1] over the vertices.
        eigenvalues: (K,) float64 non-zero Laplace-Beltrami eigenvalues, ascending, in 1/(mesh unit)^2
            (1/m^2 for meshes in metres), of eigenpairs 1..K (the constant one excluded), up to the
            last one used.
        groups: ``groups[d]`` = indices into ``eigenvalues`` merged into descriptor dimension ``d``
            (one index: that eigenvector itself, sign fixed; several: sum of their squares).
        background: (dim,) float32 point of the unit cube furthest from all vertex descriptors.
        symmetric: whether symmetric groups were merged (GISIF) or plain Laplacian Eigenmaps used.
        mesh_hash: content hash of the mesh (``ObjectModel.mesh_hash``).
        tolerance: relative eigenvalue tolerance used for grouping.
        solver: ``"direct"``, ``"dense"`` or ``"multilevel"``; ``components`` policy is in
            ``embedded_vertices``.
        embedded_vertices: number of vertices in the embedded component (N if the mesh is one
            piece; otherwise the largest component, see ``embed(components="largest")``).
    """

    vertex_descriptors: np.ndarray
    eigenvalues: np.ndarray
    groups: tuple[tuple[int, ...], ...]
    background: np.ndarray
    symmetric: bool
    mesh_hash: str
    tolerance: float
    solver: str
    embedded_vertices: int

    def __post_init__(self) -> None:
        for name in ("vertex_descriptors", "eigenvalues", "background"):
            array = np.array(getattr(self, name), copy=True)
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def dim(self) -> int:
        return int(self.vertex_descriptors.shape[1])

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_descriptors.shape[0])

    def _meta(self) -> dict:
        return {
            "format_version": _FORMAT_VERSION,
            "dim": self.dim,
            "n_vertices": self.n_vertices,
            "groups": [list(g) for g in self.groups],
            "symmetric": bool(self.symmetric),
            "mesh_hash": self.mesh_hash,
            "tolerance": float(self.tolerance),
            "solver": self.solver,
            "embedded_vertices": int(self.embedded_vertices),
        }

    def max_difference(self, other: DescriptorField) -> float:
        """Largest abs difference of a vertex descriptor or the background from ``other``'s, vertex by vertex
        (inf when their shapes differ); the fields match when it is at most :data:`FIELD_MATCH_ATOL`."""
        if other.vertex_descriptors.shape != self.vertex_descriptors.shape:
            return float("inf")
        return float(
            max(
                np.abs(self.vertex_descriptors.astype(np.float64) - other.vertex_descriptors).max(),
                np.abs(self.background.astype(np.float64) - other.background).max(),
            )
        )

    @cached_property
    def field_hash(self) -> str:
        """Short sha256 of descriptors, eigenvalues, background and metadata: names this exact data (a
        file's content), never a field recomputed elsewhere (compare those with :meth:`max_difference`)."""
        digest = hashlib.sha256()
        digest.update(np.ascontiguousarray(self.vertex_descriptors, dtype="<f4").tobytes())
        digest.update(np.ascontiguousarray(self.eigenvalues, dtype="<f8").tobytes())
        digest.update(np.ascontiguousarray(self.background, dtype="<f4").tobytes())
        digest.update(json.dumps(self._meta(), sort_keys=True).encode())
        return digest.hexdigest()[:16]

    def at(self, mesh: trimesh.Trimesh | ObjectModel, triangle_ids: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """(M, dim) descriptors at surface points of ``mesh`` (the mesh this field was computed on,
        checked by its content hash, which costs a pass over the mesh: in per-frame loops call
        :func:`interpolate_field` with the faces instead)."""
        _, faces, digest = mesh_arrays(mesh)
        if digest != self.mesh_hash:
            raise DonGymError(
                f"descriptor field is for mesh {self.mesh_hash}, but the given mesh is {digest}; "
                "re-run embed for this mesh"
            )
        return interpolate_field(self.vertex_descriptors, faces, triangle_ids, barycentric)

    def save(self, path: str | Path, *, exclusive: bool = False) -> Path:
        """Write the field as ``.npz`` (atomically); returns the path. ``exclusive``: only if ``path``
        does not exist yet, else FileExistsError (of builds racing to create it, one wins)."""
        path = Path(path)
        meta = dict(self._meta(), field_hash=self.field_hash)
        with atomic_path(path, exclusive=exclusive) as tmp:
            with open(tmp, "wb") as f:
                np.savez(
                    f,
                    vertex_descriptors=self.vertex_descriptors.astype(np.float32),
                    eigenvalues=self.eigenvalues.astype(np.float64),
                    background=self.background.astype(np.float32),
                    meta=np.array(json.dumps(meta, sort_keys=True)),
                )
        return path

    @classmethod
    def load(cls, path: str | Path) -> DescriptorField:
        """Read a field written by :meth:`save`; raises DonGymError if the file is missing or not one."""
        path = Path(path)
        if not path.is_file():
            raise DonGymError(f"descriptor file {str(path)!r} does not exist")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise DonGymError(
                f"descriptor file {str(path)!r} is not a readable .npz ({type(exc).__name__}: {exc})"
            ) from exc
        expected = {"vertex_descriptors", "eigenvalues", "background", "meta"}
        if set(arrays) != expected:
            raise DonGymError(
                f"descriptor file {str(path)!r} holds {sorted(arrays)}; expected {sorted(expected)} "
                "(a file written by DescriptorField.save)"
            )
        try:
            meta = json.loads(str(arrays["meta"]))
            groups = tuple(tuple(int(i) for i in g) for g in meta["groups"])
            field_obj = cls(
                vertex_descriptors=arrays["vertex_descriptors"],
                eigenvalues=arrays["eigenvalues"],
                groups=groups,
                background=arrays["background"],
                symmetric=bool(meta["symmetric"]),
                mesh_hash=str(meta["mesh_hash"]),
                tolerance=float(meta["tolerance"]),
                solver=str(meta["solver"]),
                embedded_vertices=int(meta["embedded_vertices"]),
            )
            stored_hash, version = meta["field_hash"], meta["format_version"]
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
            raise DonGymError(f"descriptor file {str(path)!r} has invalid metadata ({exc})") from exc
        if version != _FORMAT_VERSION:
            raise DonGymError(f"descriptor file {str(path)!r} has format {version}; expected {_FORMAT_VERSION}")
        problem = field_obj._validation_problem()
        if problem:
            raise DonGymError(f"descriptor file {str(path)!r} is corrupt: {problem}")
        if stored_hash != field_obj.field_hash:
            raise DonGymError(
                f"descriptor file {str(path)!r} is corrupt: content hash {field_obj.field_hash} "
                f"does not match the stored {stored_hash}"
            )
        return field_obj

    def _validation_problem(self) -> str | None:
        d, e, b = self.vertex_descriptors, self.eigenvalues, self.background
        if d.ndim != 2 or d.shape[0] == 0 or d.shape[1] == 0 or d.dtype != np.float32:
            return f"vertex_descriptors has shape {d.shape} and dtype {d.dtype}; expected (N, dim) float32"
        if not np.all(np.isfinite(d)) or d.min() < 0 or d.max() > 1:
            return "vertex_descriptors are not all finite and within [0, 1]"
        if b.shape != (d.shape[1],) or not np.all(np.isfinite(b)) or b.min() < 0 or b.max() > 1:
            return f"background has shape {b.shape}; expected ({d.shape[1]},) within [0, 1]"
        if e.ndim != 1 or not np.all(np.isfinite(e)) or np.any(np.diff(e) < 0) or (len(e) and e[0] <= 0):
            return "eigenvalues are not a finite, positive, ascending 1-D array"
        if len(self.groups) != d.shape[1]:
            return f"{len(self.groups)} groups for {d.shape[1]} descriptor dimensions"
        used = [i for g in self.groups for i in g]
        if not used or min(used) < 0 or max(used) >= len(e) or len(set(used)) != len(used):
            return "groups do not index distinct eigenvalues"
        if not 0 < self.embedded_vertices <= d.shape[0]:
            return f"embedded_vertices={self.embedded_vertices} is not within 1..{d.shape[0]}"
        return None
