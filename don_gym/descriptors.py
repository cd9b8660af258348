"""Optimal descriptors: Laplacian Eigenmaps of an object mesh, with symmetric eigenfunctions merged.

Kupcsik et al. (AAAI 2021), Secs. "Embedding Object Models using Laplacian Eigenmaps" and
"Handling Symmetry". The mesh is a Riemannian manifold; its Laplace-Beltrami operator,
discretised as the intrinsic-Delaunay Laplacian ``L`` and lumped mass matrix ``M`` of
``robust_laplacian`` (Sharp & Crane 2020), gives the generalised eigenproblem
``L y = lambda M y``. The eigenvectors of the smallest non-zero eigenvalues are the smoothest
functions on the surface and embed it optimally into a ``dim``-dimensional descriptor space.

Symmetry (GISIF, Wang et al. 2014): a rotationally symmetric part has repeated eigenvalues, and
any basis of such an eigenspace is arbitrary (it depends on vertex order and rounding). Consecutive
eigenvalues equal within a *relative* tolerance form a group, replaced by the sum of squares of its
M-orthonormal eigenvectors: that function does not depend on the basis or the signs, and it is
invariant under the symmetry. Each group fills one descriptor dimension, so more eigenpairs are
computed until ``dim`` groups are closed (the last one's end confirmed by a following, different
eigenvalue).

Reproducibility: the mesh is centred and scaled to unit area before the Laplacian is built, so
descriptors do not depend on the mesh's size or position and the eigenvalue tolerance is relative;
reported eigenvalues are converted back to the mesh's units (1/m^2 for a mesh in metres). The sign
of a single eigenvector is fixed by shape alone (see :func:`_fix_sign`), so permuting vertices does
not change the descriptor of a surface point.

Speed. ``method="direct"`` builds robust_laplacian's Laplacian of the whole mesh and runs
shift-invert Lanczos (``scipy.sparse.linalg.eigsh``, SuperLU) on it. ``method="multilevel"`` (the
default above :data:`DIRECT_MAX_VERTICES` vertices) solves on a coarser mesh and transfers:

1. *Coarse mesh by vertex clustering.* Vertices are grouped by a voxel grid (about
   :data:`_CLUSTER_SIZE` per cluster, fewer where that would leave under
   :data:`_MIN_COARSE_VERTICES` clusters), split into connected pieces inside each voxel (so two
   sheets of a thin wall never merge). Each cluster's vertex nearest to its centroid becomes a
   coarse vertex; every fine face whose three vertices lie in three clusters becomes a coarse face.
   Coarse meshes above :data:`_COARSEST_VERTICES` vertices are coarsened again.
2. *The coarse eigenproblem* uses robust_laplacian's intrinsic-Delaunay Laplacian of the coarse
   mesh: clustered meshes are badly shaped (slivers, folds, non-manifold edges), which is what it is
   made for. The coarsest one is solved directly.
3. *Linear prolongation* ``P`` (fine x coarse): each fine vertex takes the barycentric coordinates
   of its projection onto the coarse face (around its cluster's coarse vertex) it lies most inside
   of. These piecewise linear "hat" functions approximate smooth eigenfunctions to second order.
4. *Refinement on the fine mesh*: the prolonged eigenvectors start a block LOBPCG (Knyazev 2001),
   preconditioned by a two-grid cycle (Jacobi smoothing + exact solve with the coarse Laplacian),
   in single precision. It stops when the estimated remaining error of every needed eigenvector is
   below :data:`_REFINE_TOL` (M-norm), typically after 2-3 iterations; if it does not converge, the
   direct solver is used instead.

   The fine-level operator is the cotangent Laplacian (:func:`cotan_laplacian`) when the mesh meets
   the maximum-angle condition (no angle above 170 degrees, no edge in three faces): that is the
   intrinsic-Delaunay Laplacian on meshes that are already intrinsically Delaunay, and on the others
   a consistent discretisation of the same operator (in the benchmark, descriptors refined with
   either differ from the direct solver's by the same 0.004-0.006). Otherwise robust_laplacian's
   Laplacian of the whole mesh is built, as for the direct solver, and costs about as much as the
   rest of the multilevel solve.

Measured (``benchmarks/bench_descriptors.py``, RESULTS.md, 2-core CPU): descriptors within 0.01 of
the direct solver's and over 5x faster from 38k vertices up.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np
import robust_laplacian
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from don_gym.errors import DonGymError, MeshError
from don_gym.io import atomic_path
from don_gym.objects import ObjectModel

#: Default relative tolerance under which consecutive eigenvalues count as equal (one symmetry group).
DEFAULT_TOLERANCE = 1e-2
#: ``method="auto"`` solves meshes with fewer vertices than this directly (multilevel above).
DIRECT_MAX_VERTICES = 10_000
#: Mollification of robust_laplacian, relative to the mean edge length (NOTES.md, Sharp & Crane 2020).
MOLLIFY_FACTOR = 1e-5
#: A merged group whose function varies by less than this fraction of its mean is taken as
#: constant and skipped: on a sphere the sum of squares of all spherical harmonics of one degree is
#: constant, and on a triangulated sphere what is left (1-9 % on icospheres) is the pattern of the
#: triangulation, which normalisation to [0, 1] would blow up into meaningless descriptors.
CONSTANT_GROUP_RTOL = 0.1

_FORMAT_VERSION = 1
# Multilevel solver settings (see module docstring).
_COARSEST_VERTICES = 8000  # solve directly at or below this size
_CLUSTER_SIZE = 24.0  # target fine vertices per coarse vertex (voxel area in units of vertex area)
_MIN_COARSE_VERTICES = 2000  # smaller clusters where 24 would give fewer coarse vertices
_REFINE_TOL = 2e-3  # stop refining when each needed eigenvector's estimated error is below (M-norm)
_REFINE_TOL_COARSE = 1e-2  # the same on intermediate levels, which only give starting vectors
_REFINE_MAXITER = 12
_COTAN_MAX_ANGLE = math.radians(170.0)  # finest-level operator: cotangent Laplacian below this
_JACOBI_OMEGA = 2.0 / 3.0
# The refinement needs eigenvectors to ~1e-3: single precision halves the memory traffic of its
# sparse and dense products; Rayleigh-Ritz matrices are solved in double precision.
_REFINE_DTYPE = np.float32
_GRAM_RTOL = 1e-6  # Rayleigh-Ritz drops directions whose Gram eigenvalue is below this (relative)
_PRECONDITIONER_SHIFT = 1.0  # sigma of L + sigma*M on unit-area meshes (lambda_1 ~ 0.3-25)
_MAX_RATE = 0.9  # cap of the estimated LOBPCG convergence rate (error estimate <= 9 x last step)
_GUARD = 4
#: embed gives up (MeshError) when this many eigenpairs (or 8 * dim) still do not close dim groups.
_MAX_EIGENPAIRS = 64


def _as_mesh(mesh: trimesh.Trimesh | ObjectModel) -> tuple[np.ndarray, np.ndarray, str]:
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


# --------------------------------------------------------------------------------------------
# Descriptor field
# --------------------------------------------------------------------------------------------


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

    @cached_property
    def field_hash(self) -> str:
        """Short sha256 of descriptors, eigenvalues, background and metadata (stable across runs)."""
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
        _, faces, digest = _as_mesh(mesh)
        if digest != self.mesh_hash:
            raise DonGymError(
                f"descriptor field is for mesh {self.mesh_hash}, but the given mesh is {digest}; "
                "re-run embed for this mesh"
            )
        return interpolate_field(self.vertex_descriptors, faces, triangle_ids, barycentric)

    def save(self, path: str | Path) -> Path:
        """Write the field as ``.npz`` (atomically); returns the path."""
        path = Path(path)
        meta = dict(self._meta(), field_hash=self.field_hash)
        with atomic_path(path) as tmp:
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


# --------------------------------------------------------------------------------------------
# Laplacian and eigenpairs
# --------------------------------------------------------------------------------------------


def normalize_to_unit_area(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre the vertices on their area-weighted centroid and scale the surface to unit area.

    Returns ``(vertices_normalized, area)`` where ``area`` is the original surface area; eigenvalues
    of the normalised mesh divided by ``area`` are those of the original one.
    """
    tri = vertices[faces]
    face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    area = float(face_area.sum())
    if not area > 0 or not np.isfinite(area):
        raise MeshError(f"mesh has surface area {area:g}; expected a positive area (all faces are degenerate)")
    face_centroid = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3.0  # = tri.mean(axis=1), bit for bit, faster
    centroid = (face_area[:, None] * face_centroid).sum(axis=0) / area
    return (vertices - centroid) / math.sqrt(area), area


def mesh_laplacian(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Intrinsic-Delaunay Laplacian ``L`` (positive semi-definite, CSR) and lumped mass diagonal ``M``
    (N,) from ``robust_laplacian.mesh_laplacian`` (mollify factor :data:`MOLLIFY_FACTOR`)."""
    L, M = robust_laplacian.mesh_laplacian(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        mollify_factor=MOLLIFY_FACTOR,
    )
    mass = np.asarray(M.diagonal(), dtype=np.float64)
    if not np.all(mass > 0):
        # Unreferenced vertices get zero mass: the eigenproblem would be singular.
        raise MeshError(f"{int((mass <= 0).sum())} vertices have zero area (unreferenced or isolated)")
    return sp.csr_matrix(L), mass


def cotan_laplacian(
    vertices: np.ndarray, faces: np.ndarray, max_angle: float = _COTAN_MAX_ANGLE
) -> tuple[sp.csr_matrix, np.ndarray] | None:
    """Cotangent Laplacian ``L`` (N, N) CSR and barycentric lumped mass ``M`` (N,) (a third of the
    area of each face at a vertex), in the units of ``vertices`` (L is scale-free, M in unit^2);
    None when the cotangent Laplacian is not reliable for this mesh: an angle above ``max_angle``
    (radians), a face of zero area, or an edge in more than two faces.

    On a mesh that is already intrinsically Delaunay this is the pair :func:`mesh_laplacian`
    (robust_laplacian) returns, up to its mollification (~1e-5 relative). On other meshes that meet
    the maximum-angle condition, under which linear finite elements, hence this Laplacian, converge
    (Babuska & Aziz 1976), both are consistent discretisations of the Laplace-Beltrami operator
    and their smallest eigenvectors agree closely; it is built without robust_laplacian's intrinsic
    edge flips, so much faster. Needles, caps, folds and non-manifold edges are what
    robust_laplacian is made for.
    """
    n = len(vertices)
    corners = np.ascontiguousarray(vertices.T)[:, faces]  # (3 coordinates, F, 3 corners)
    # Edge k is opposite corner k; its squared length and the face's doubled area give the
    # cotangent at corner k: (|a|^2 + |b|^2 - |e_k|^2) / (4 area) for its two other edges a, b.
    edge = [corners[:, :, (k + 2) % 3] - corners[:, :, (k + 1) % 3] for k in range(3)]
    length2 = [np.einsum("ij,ij->j", e, e) for e in edge]
    normal = np.cross(edge[2], edge[1], axis=0)
    twice_area = np.sqrt(np.einsum("ij,ij->j", normal, normal))
    if not np.all(twice_area > 0):
        return None
    lowest_cot = 1.0 / math.tan(max_angle) if max_angle < math.pi else -np.inf
    rows, cols, weights = [], [], []
    for k in range(3):
        cot = (length2[(k + 1) % 3] + length2[(k + 2) % 3] - length2[k]) / (2.0 * twice_area)
        if not np.all(cot >= lowest_cot):  # also catches non-finite values
            return None
        weights.append(0.5 * cot)  # half the cotangent of the angle at corner k weighs the opposite edge
        rows.append(faces[:, (k + 1) % 3])
        cols.append(faces[:, (k + 2) % 3])
    i, j, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    low, high = np.minimum(i, j), np.maximum(i, j)
    faces_per_edge = sp.csr_matrix((np.ones(len(w)), (low, high)), shape=(n, n))
    if faces_per_edge.nnz and faces_per_edge.data.max() > 2:
        return None
    upper = sp.csr_matrix((-w, (low, high)), shape=(n, n))
    off = upper + upper.T
    L = sp.csr_matrix(off - sp.diags(np.asarray(off.sum(axis=1)).ravel()))
    mass = np.bincount(faces.ravel(), np.repeat(twice_area / 6.0, 3), minlength=n)
    return L, mass


def _direct_eigenpairs(
    L: sp.spmatrix, mass: np.ndarray, count: int, shift: float = 1e-6, factor: object | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest ``count`` non-constant eigenpairs of ``L y = lambda M y`` (``mass`` the diagonal of M)
    for a connected mesh normalised to unit area (eigenvalues O(1-100)).

    Shift-invert Lanczos about ``-shift``; ``factor`` is a factorisation of ``L + shift * M`` (its
    ``solve``) when the caller has one, else it is computed.
    """
    n = L.shape[0]
    Bm = sp.diags(mass)
    if n <= 100 or count + 1 >= n - 1:
        # Tiny, or every eigenpair wanted: dense generalised symmetric eigensolver.
        w, Y = scipy.linalg.eigh(L.toarray(), Bm.toarray())
    else:
        # L + shift*M is symmetric positive definite (L alone is singular on constants). A fixed
        # start vector (ARPACK's default is random) makes results, and so field hashes, reproducible.
        factor = factor if factor is not None else _factorize_spd(L + shift * Bm)
        solve = spla.LinearOperator((n, n), matvec=factor.solve, dtype=np.float64)
        start = 1.0 + 0.5 * np.sin(np.arange(n, dtype=np.float64))
        w, Y = spla.eigsh(
            sp.csc_matrix(L), k=count + 1, M=sp.csc_matrix(Bm), sigma=-shift, which="LM", OPinv=solve, v0=start
        )
        order = np.argsort(w)
        w, Y = w[order], Y[:, order]
    return w[1 : count + 1], Y[:, 1 : count + 1]


def _factorize_spd(A: sp.spmatrix):
    """Sparse LU of a symmetric positive definite matrix without pivoting. Minimum degree on
    A + A^T gives about half the fill of SuperLU's default COLAMD and is faster up to ~20k
    unknowns, but its ordering time grows steeply beyond (1.3 s at 38k vs 0.3 s for COLAMD)."""
    spec = "MMD_AT_PLUS_A" if A.shape[0] <= 20_000 else "COLAMD"
    return spla.splu(sp.csc_matrix(A), permc_spec=spec, diag_pivot_thresh=0.0, options={"SymmetricMode": True})


# -- multilevel ------------------------------------------------------------------------------


def _cluster(vertices: np.ndarray, edges: np.ndarray, voxel: float) -> tuple[int, np.ndarray]:
    """Labels (N,) of voxel clusters split into connected pieces; ``edges`` (E, 2) vertex pairs."""
    cell = np.floor((vertices - vertices.min(axis=0)) / voxel).astype(np.int64)
    key = (cell[:, 0] << 42) + (cell[:, 1] << 21) + cell[:, 2]
    _, voxel_id = np.unique(key, return_inverse=True)
    voxel_id = voxel_id.ravel()
    inside = voxel_id[edges[:, 0]] == voxel_id[edges[:, 1]]
    return _connected_pieces(len(vertices), edges[inside])


def _coarsen(vertices: np.ndarray, faces: np.ndarray, cluster_size: float):
    """One coarse level: (coarse vertices, coarse faces, prolongation P (n_fine, n_coarse) CSR)."""
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    # Mean vertex area is 1/n on a unit-area mesh; a voxel that cuts a patch of ~cluster_size vertices.
    n_coarse, label = _cluster(vertices, edges, math.sqrt(cluster_size / n))
    count = np.bincount(label, minlength=n_coarse)
    centroid = np.stack([np.bincount(label, vertices[:, d], minlength=n_coarse) for d in range(3)], 1)
    centroid /= count[:, None]
    # Coarse vertex = the cluster's vertex nearest its centroid (lies on the surface).
    offset = vertices - centroid[label]
    dist2 = np.einsum("ij,ij->i", offset, offset)
    by_cluster = np.argsort(label, kind="stable")
    group_start = np.concatenate([[0], np.cumsum(count)[:-1]])
    nearest = np.minimum.reduceat(dist2[by_cluster], group_start)
    # First vertex (in vertex order, for ties) of each cluster at its smallest distance.
    candidate = by_cluster[dist2[by_cluster] == np.repeat(nearest, count)]
    first = np.ones(len(candidate), dtype=bool)
    first[1:] = label[candidate][1:] != label[candidate][:-1]
    representative = np.empty(n_coarse, dtype=np.int64)
    representative[label[candidate[first]]] = candidate[first]
    coarse_vertices = vertices[representative]

    corner = label[faces]
    spans3 = (corner[:, 0] != corner[:, 1]) & (corner[:, 1] != corner[:, 2]) & (corner[:, 0] != corner[:, 2])
    coarse_faces = corner[spans3]
    ordered = np.sort(coarse_faces, axis=1)
    key = (ordered[:, 0] * n_coarse + ordered[:, 1]) * n_coarse + ordered[:, 2]  # < 2^63 below 2M coarse
    _, unique_rows = np.unique(key, return_index=True)
    coarse_faces = coarse_faces[np.sort(unique_rows)]

    # Coarse faces around each coarse vertex (CSR-like incidence lists).
    inc_vertex = coarse_faces.ravel()
    inc_face = np.repeat(np.arange(len(coarse_faces)), 3)
    by_vertex = np.argsort(inc_vertex, kind="stable")
    inc_face = inc_face[by_vertex]
    degree = np.bincount(inc_vertex, minlength=n_coarse)
    start = np.concatenate([[0], np.cumsum(degree)[:-1]])

    # Barycentric coordinates of each fine vertex projected onto the planes of the coarse faces
    # around its cluster's coarse vertex; the face it is most inside of (largest smallest
    # coordinate) wins, and negative coordinates are clipped. Per-face terms are precomputed.
    origin = coarse_vertices[coarse_faces[:, 0]]
    e1 = coarse_vertices[coarse_faces[:, 1]] - origin
    e2 = coarse_vertices[coarse_faces[:, 2]] - origin
    d11, d12, d22 = np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2)
    with np.errstate(divide="ignore"):
        inv_det = 1.0 / (d11 * d22 - d12 * d12)
    inv_det[~np.isfinite(inv_det)] = 0.0  # degenerate coarse face: all weight on its first vertex
    # Coordinates 2 and 3 are affine in the point: x . g - o.
    g1 = (d22[:, None] * e1 - d12[:, None] * e2) * inv_det[:, None]
    g2 = (d11[:, None] * e2 - d12[:, None] * e1) * inv_det[:, None]
    o1, o2 = np.einsum("ij,ij->i", origin, g1), np.einsum("ij,ij->i", origin, g2)
    # Fine vertices sorted by the number of candidate faces, so that pass j works on a prefix.
    vertex_degree = degree[label]
    by_degree = np.argsort(-vertex_degree, kind="stable")
    sorted_degree = vertex_degree[by_degree]
    first_face = start[label[by_degree]]
    points = vertices[by_degree]
    best_inside = np.full(n, -np.inf)
    best_v, best_w = np.zeros(n), np.zeros(n)
    best_face = np.full(n, -1, dtype=np.int64)
    for j in range(int(degree.max()) if len(degree) else 0):
        m = int(np.searchsorted(-sorted_degree, -j, side="left"))  # vertices with more than j faces
        face = inc_face[first_face[:m] + j]
        p = points[:m]
        v = np.einsum("ij,ij->i", p, g1[face]) - o1[face]
        w = np.einsum("ij,ij->i", p, g2[face]) - o2[face]
        inside = np.minimum(np.minimum(v, w), 1.0 - v - w)
        better = inside > best_inside[:m]
        for best, new in ((best_inside, inside), (best_v, v), (best_w, w), (best_face, face)):
            np.copyto(best[:m], new, where=better)
    best_bary = np.empty((n, 3))
    best_bary[by_degree] = np.stack([1.0 - best_v - best_w, best_v, best_w], axis=1)
    face_of_vertex = np.empty_like(best_face)
    face_of_vertex[by_degree] = best_face
    best_face = face_of_vertex
    np.clip(best_bary, 0.0, None, out=best_bary)
    total = best_bary.sum(axis=1, keepdims=True)
    best_bary = np.divide(best_bary, total, out=np.tile([[1.0, 0.0, 0.0]], (n, 1)), where=total > 0)

    has_face = best_face >= 0
    rows_f = np.flatnonzero(has_face)
    rows_c = np.flatnonzero(~has_face)  # clusters without coarse faces: constant on the cluster
    P = sp.csr_matrix(
        (
            np.concatenate([best_bary[rows_f].ravel(), np.ones(len(rows_c))]),
            (
                np.concatenate([np.repeat(rows_f, 3), rows_c]),
                np.concatenate([coarse_faces[best_face[rows_f]].ravel(), label[rows_c]]),
            ),
        ),
        shape=(n, n_coarse),
    )
    P.sum_duplicates()
    P.eliminate_zeros()
    return coarse_vertices, coarse_faces, P


def _drop_unreferenced(
    vertices: np.ndarray, faces: np.ndarray, P: sp.csr_matrix
) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
    """Remove coarse vertices in no coarse face (they would get zero mass); the fine vertices that
    followed one follow the nearest remaining coarse vertex instead."""
    referenced = np.zeros(len(vertices), dtype=bool)
    referenced[faces.ravel()] = True
    if referenced.all():
        return vertices, faces, P
    kept = np.flatnonzero(referenced)
    column = np.empty(len(vertices), dtype=np.int64)
    column[kept] = np.arange(len(kept))
    column[~referenced] = cKDTree(vertices[kept]).query(vertices[~referenced])[1]
    P = sp.csr_matrix((P.data, column[P.indices], P.indptr), shape=(P.shape[0], len(kept)))
    P.sum_duplicates()
    return vertices[kept], column[faces], P


class _Level:
    """One mesh of the nested solver: its Laplacian ``L`` and lumped mass, and above
    :data:`_COARSEST_VERTICES` vertices the next coarser mesh (vertex clustering) with its
    prolongation ``P`` and its own intrinsic-Delaunay Laplacian. Clustered meshes are badly shaped
    (slivers, folds, non-manifold edges), which is what robust_laplacian is made for."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, L: sp.csr_matrix, mass: np.ndarray):
        self.L, self.mass = L, mass
        self.coarse: _Level | None = None
        self.P = self.PT = None  # prolongation from the coarse level and its transpose
        self.iterations: list[int] = []  # LOBPCG iterations of the last solve, finest level last
        self._coarse_lu = None  # splu of the coarse level's L + sigma*M
        if L.shape[0] <= _COARSEST_VERTICES:
            return
        # Fewer than ~2000 coarse vertices resolve a block of ~10 eigenvectors too poorly: the
        # refinement then takes 8-10 iterations instead of 2-3.
        cluster_size = min(_CLUSTER_SIZE, L.shape[0] / _MIN_COARSE_VERTICES)
        coarse_vertices, coarse_faces, P = _coarsen(vertices, faces, cluster_size)
        if P.shape[1] > 0.5 * P.shape[0] or len(coarse_faces) == 0:
            raise _CoarseningFailed(f"coarsening {P.shape[0]} -> {P.shape[1]} vertices")
        coarse_vertices, coarse_faces, P = _drop_unreferenced(coarse_vertices, coarse_faces, P)
        if _components(len(coarse_vertices), coarse_faces)[0] > 1:
            raise _CoarseningFailed("the coarse mesh falls apart into several pieces")
        self.P, self.PT = P, sp.csr_matrix(P.T)
        self.coarse = _Level(coarse_vertices, coarse_faces, *mesh_laplacian(coarse_vertices, coarse_faces))

    @property
    def size(self) -> int:
        return self.L.shape[0]

    def _refines(self, block: int) -> bool:
        # The coarse level must still resolve the block (8 vertices per vector).
        return self.coarse is not None and self.coarse.size >= 8 * block

    def _prepare(self) -> None:
        # L + sigma*M is positive definite (L is singular on constants); the same factorisation of
        # the coarse one serves the coarse eigensolve and the coarse correction.
        shifted = sp.csr_matrix(self.L + sp.diags(_PRECONDITIONER_SHIFT * self.mass))
        self._shifted = shifted.astype(_REFINE_DTYPE)
        self._jacobi = (_JACOBI_OMEGA / shifted.diagonal()).astype(_REFINE_DTYPE)[:, None]
        self._P_single, self._PT_single = self.P.astype(_REFINE_DTYPE), self.PT.astype(_REFINE_DTYPE)
        coarse = self.coarse
        self._coarse_lu = _factorize_spd(coarse.L + sp.diags(_PRECONDITIONER_SHIFT * coarse.mass))

    def _precondition(self, R: np.ndarray) -> np.ndarray:
        # Symmetric two-grid cycle for (L + sigma M)^-1: Jacobi, coarse correction, Jacobi.
        A, d = self._shifted, self._jacobi
        X = d * R
        coarse_residual = np.asarray(self._PT_single @ (R - A @ X), dtype=np.float64)
        X += self._P_single @ self._coarse_lu.solve(coarse_residual).astype(_REFINE_DTYPE)
        X += d * (R - A @ X)
        return X

    def eigenpairs(
        self, count: int, block: int | None = None, tol: float = _REFINE_TOL
    ) -> tuple[np.ndarray, np.ndarray]:
        """Smallest ``block`` non-constant eigenpairs, of which the first ``count`` are converged
        to ``tol``: solved on the coarse level (recursively), prolonged, and refined here by
        preconditioned LOBPCG."""
        # Guard vectors: the last wanted eigenpairs converge at the rate of their gap to the block's end.
        block = block or count + max(_GUARD, count // 2)
        if not self._refines(block):
            raise _CoarseningFailed(f"{block} eigenvectors need a coarse level of at least {8 * block} vertices")
        coarse = self.coarse
        if self._coarse_lu is None:
            self._prepare()
        if coarse._refines(block):
            w, Y = coarse.eigenpairs(count, block, _REFINE_TOL_COARSE)
            self.iterations = coarse.iterations
        else:
            w, Y = _direct_eigenpairs(coarse.L, coarse.mass, block, _PRECONDITIONER_SHIFT, self._coarse_lu)
            self.iterations = []
        w, Y, iterations = _lobpcg(self.L, self.mass, self.P @ Y, self._precondition, count, tol)
        self.iterations = [*self.iterations, iterations]
        return w, Y


class _CoarseningFailed(RuntimeError):
    pass


class _NotConverged(RuntimeError):
    pass


def _rayleigh_ritz(S: np.ndarray, AS: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Ritz values (m,) and coefficients (k, m) of the m smallest Ritz pairs of a symmetric ``A`` in
    the span of the columns of ``S`` (n, k), given ``A S``; near-dependent directions are dropped
    (orthogonalisation by eigendecomposition of the Gram matrix, which stays stable when LOBPCG's
    blocks become nearly dependent)."""
    G, H = (S.T @ S).astype(np.float64), (S.T @ AS).astype(np.float64)
    G, H = (G + G.T) / 2, (H + H.T) / 2
    scale = np.sqrt(np.abs(np.diag(G)))
    scale[scale == 0] = 1.0
    G = G / scale[:, None] / scale[None, :]
    H = H / scale[:, None] / scale[None, :]
    g, U = np.linalg.eigh(G)
    keep = g > _GRAM_RTOL * g.max()
    T = U[:, keep] / np.sqrt(g[keep])
    lam, V = np.linalg.eigh(T.T @ H @ T)
    return lam[:m], (T @ V[:, :m]) / scale[:, None]


def _lobpcg(
    A: sp.csr_matrix,
    mass: np.ndarray,
    X0: np.ndarray,
    precond: Callable[[np.ndarray], np.ndarray],
    n_check: int,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Block LOBPCG (Knyazev 2001) for the smallest eigenpairs of ``A x = lambda M x`` (``mass`` the
    diagonal of M) orthogonal to constants, from the start block ``X0`` (n, m); ``precond``
    approximates ``(A + sigma M)^-1``. Converged when the estimated remaining error of each of the
    first ``n_check`` Ritz vectors is below ``tol`` (M-norm); raises _NotConverged after
    :data:`_REFINE_MAXITER` iterations.

    Returns ``(Ritz values (m,), Ritz vectors (n, m) M-orthonormal, iterations)``."""
    n, m = X0.shape
    # Solved for z = M^(1/2) x, an ordinary symmetric eigenproblem (M is diagonal): no M-products
    # to carry along, and the M-norm of x is the 2-norm of z.
    root = np.sqrt(mass).astype(_REFINE_DTYPE)[:, None]
    A = A.astype(_REFINE_DTYPE)

    def apply_A(Z: np.ndarray) -> np.ndarray:
        return (A @ (Z / root)) / root

    constant = root / np.float32(math.sqrt(float(mass.sum())))

    def deflate(Z: np.ndarray) -> np.ndarray:
        return Z - constant @ (constant.T @ Z)

    # The blocks X, W (preconditioned residuals) and P (last step) sit side by side in one array,
    # and their A-products in another, so that the Rayleigh-Ritz matrices and the updates are
    # single matrix products.
    S, AS = np.empty((n, 3 * m), _REFINE_DTYPE), np.empty((n, 3 * m), _REFINE_DTYPE)
    S[:, :m] = deflate(root * X0.astype(_REFINE_DTYPE))
    AS[:, :m] = apply_A(S[:, :m])
    lam, C = _rayleigh_ritz(S[:, :m], AS[:, :m], m)
    for block in (S, AS):
        block[:, :m] = block[:, :m] @ C.astype(_REFINE_DTYPE)
    width = 2 * m  # no P block before the first step
    previous_step = None
    remaining = np.inf
    for iteration in range(1, _REFINE_MAXITER + 1):
        residual = AS[:, :m] - S[:, :m] * lam.astype(_REFINE_DTYPE)
        W = deflate(root * precond(root * residual))
        S[:, m : 2 * m], AS[:, m : 2 * m] = W, apply_A(W)
        lam, C = _rayleigh_ritz(S[:, :width], AS[:, :width], m)
        # A-products are updated with the same coefficients as the vectors (dense products)
        # instead of being recomputed with the sparse matrix.
        C = C.astype(_REFINE_DTYPE)
        for block in (S, AS):
            new_x = block[:, :width] @ C
            block[:, 2 * m :] = block[:, m:width] @ C[m:]
            block[:, :m] = new_x
        width = 3 * m
        # Size of this step outside the previous subspace (X is orthonormal), per needed vector.
        # Convergence is linear, so the remaining error is the geometric tail step * r / (1 - r)
        # with the rate r estimated from the last two steps.
        step_needed = S[:, 2 * m : 2 * m + n_check]
        step = np.sqrt(np.einsum("ij,ij->j", step_needed, step_needed, dtype=np.float64))
        if previous_step is not None:
            rate = np.minimum(step / np.maximum(previous_step, 1e-300), _MAX_RATE)
            remaining = float(np.max(step * rate / (1.0 - rate)))
            if remaining < tol:
                return lam, (S[:, :m] / root).astype(np.float64), iteration
        previous_step = step
    raise _NotConverged(f"LOBPCG did not converge in {_REFINE_MAXITER} iterations (error estimate {remaining:.1e})")


def laplacian_eigenpairs(
    vertices: np.ndarray,
    faces: np.ndarray,
    count: int,
    method: Literal["auto", "direct", "multilevel"] = "auto",
) -> tuple[np.ndarray, np.ndarray, str]:
    """Smallest ``count`` non-constant eigenpairs of ``L y = lambda M y`` of a connected mesh.

    Args:
        vertices: (N, 3) float, any unit (solved on a copy scaled to unit area).
        faces: (F, 3) int, every vertex referenced.
        count: number of eigenpairs after the constant one.
        method: ``"direct"`` (robust_laplacian + shift-invert Lanczos; dense up to 100 vertices),
            ``"multilevel"`` (module docstring) or ``"auto"`` (direct below
            :data:`DIRECT_MAX_VERTICES` vertices).

    Returns:
        ``(eigenvalues (count,) ascending in 1/unit^2, eigenvectors (N, count) M-orthonormal for
        the lumped mass matrix of the Laplacian the solver used, solver name)``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    normalized, area = normalize_to_unit_area(np.asarray(vertices, dtype=np.float64), faces)
    w, Y, _, solver = _eigenpairs(normalized, faces, count, method, {})
    return w / area, Y / math.sqrt(area), solver


def _eigenpairs(
    vertices: np.ndarray, faces: np.ndarray, count: int, method: str, cache: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(eigenvalues, eigenvectors, lumped mass, solver) of a connected unit-area mesh; ``cache``
    keeps Laplacians and the multilevel hierarchy between calls with growing ``count``."""
    n = len(vertices)
    if count > n - 1:
        raise MeshError(f"mesh has {n} vertices, so at most {n - 1} non-constant eigenpairs; {count} needed")
    use_multilevel = method == "multilevel" or (method == "auto" and n >= DIRECT_MAX_VERTICES)
    if use_multilevel and n > _COARSEST_VERTICES and not cache.get("multilevel_failed"):
        try:
            if "hierarchy" not in cache:
                operator = cotan_laplacian(vertices, faces) or _robust(vertices, faces, cache)
                cache["hierarchy"] = _Level(vertices, faces, *operator)
            hierarchy = cache["hierarchy"]
            w, Y = hierarchy.eigenpairs(count)
            return w[:count], Y[:, :count], hierarchy.mass, "multilevel"
        except (_CoarseningFailed, _NotConverged, MeshError, RuntimeError, np.linalg.LinAlgError):
            # Unusual meshes (clusters that do not coarsen, a coarse vertex with zero area, many
            # eigenpairs on a small mesh, no convergence): the direct solver always works, and
            # raises for a mesh that is itself bad.
            cache["multilevel_failed"] = True
    L, mass = _robust(vertices, faces, cache)
    w, Y = _direct_eigenpairs(L, mass, count)
    return w, Y, mass, "dense" if n <= 100 or count + 1 >= n - 1 else "direct"


def _robust(vertices: np.ndarray, faces: np.ndarray, cache: dict) -> tuple[sp.csr_matrix, np.ndarray]:
    if "robust" not in cache:
        cache["robust"] = mesh_laplacian(vertices, faces)
    return cache["robust"]


def group_eigenvalues(eigenvalues: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> list[tuple[int, ...]]:
    """Split ascending eigenvalues into runs in which each is within ``tolerance`` (relative) of the
    previous one: ``|l[i+1] - l[i]| <= tolerance * l[i]``. Returns lists of indices."""
    groups: list[list[int]] = []
    for i, value in enumerate(np.asarray(eigenvalues, dtype=np.float64)):
        if groups and abs(value - eigenvalues[i - 1]) <= tolerance * abs(eigenvalues[i - 1]):
            groups[-1].append(i)
        else:
            groups.append([i])
    return [tuple(g) for g in groups]


# --------------------------------------------------------------------------------------------
# Descriptors from eigenpairs
# --------------------------------------------------------------------------------------------

# A fixed generic direction for the sign fall-back (no symmetry plane of common parts contains it).
_GENERIC_DIRECTION = np.array([1.0, math.sqrt(2.0), math.sqrt(3.0)]) / math.sqrt(6.0)


def _fix_sign(y: np.ndarray, mass: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Sign of an eigenvector fixed by the shape only (independent of vertex order).

    1. the integral of y^3 over the surface (skewness) is made positive;
    2. if that vanishes (y is odd under a reflection of the part), the integral of y times the
       coordinate along a fixed generic direction is made positive;
    3. otherwise the value at the vertex furthest along that direction is made positive.
    """
    weighted_square = mass * y * y
    skew = float(weighted_square @ y)
    if abs(skew) > 1e-6 * float(weighted_square @ np.abs(y)):
        return y if skew > 0 else -y
    along = vertices @ _GENERIC_DIRECTION
    moment = float((mass * y) @ along)
    if abs(moment) > 1e-6 * float((mass * np.abs(y)) @ np.abs(along)):
        return y if moment > 0 else -y
    value = y[int(np.argmax(along))]
    return y if value >= 0 else -y


def descriptor_functions(
    eigenvalues: np.ndarray,
    eigenvectors: np.ndarray,
    mass: np.ndarray,
    vertices: np.ndarray,
    dim: int,
    symmetric: bool,
    tolerance: float = DEFAULT_TOLERANCE,
    complete: bool = False,
) -> tuple[np.ndarray, list[tuple[int, ...]]] | None:
    """Descriptor functions from the smallest non-constant eigenpairs, normalised to [0, 1].

    Args:
        eigenvalues: (K,) ascending; eigenvectors: (N, K) M-orthonormal; mass: (N,) lumped mass;
        vertices: (N, 3) (only for the sign rule's fall-back).
        dim, symmetric, tolerance: as in :func:`embed`.
        complete: the K eigenpairs are all there are, so the last group is closed too.

    Returns:
        ``(descriptors (N, dim) float32, groups)`` or None when the eigenpairs do not yet close
        ``dim`` informative groups (compute more). A merged group whose function is constant
        (relative variation below :data:`CONSTANT_GROUP_RTOL`) is skipped.
    """
    if symmetric:
        groups = group_eigenvalues(eigenvalues, tolerance)
        if not complete:
            groups = groups[:-1]  # its end is not confirmed by a following, different eigenvalue
    else:
        groups = [(i,) for i in range(len(eigenvalues))]
    functions, used = [], []
    for group in groups:
        if len(group) == 1:
            f = _fix_sign(eigenvectors[:, group[0]], mass, vertices)
        else:
            f = np.sum(eigenvectors[:, list(group)] ** 2, axis=1)
            mean = float(np.sum(mass * f) / np.sum(mass))
            if float(f.max() - f.min()) <= CONSTANT_GROUP_RTOL * abs(mean):
                continue
        functions.append(f)
        used.append(group)
        if len(used) == dim:
            values = np.stack(functions, axis=1)
            low, high = values.min(axis=0), values.max(axis=0)
            return ((values - low) / np.maximum(high - low, 1e-300)).astype(np.float32), used
    return None


def _compass_search(
    tree: cKDTree, start: np.ndarray, step: float, min_step: float, center: np.ndarray | None = None, reach: float = 0.0
) -> tuple[np.ndarray, float]:
    """Maximise the distance to the nearest point of ``tree`` over the unit cube by compass search
    (move along +-axes while that helps, else halve the step); with ``center``, stay within
    ``reach`` (max-norm) of it."""
    dim = len(start)
    directions = np.concatenate([np.eye(dim), -np.eye(dim)])
    x, fx = start.copy(), float(tree.query(start)[0])
    while step > min_step:
        trial = np.clip(x + step * directions, 0.0, 1.0)
        if center is not None:
            trial = np.clip(trial, center - reach, center + reach)
        d, _ = tree.query(trial)
        i = int(np.argmax(d))
        if d[i] > fx + 1e-12:
            x, fx = trial[i], float(d[i])
        else:
            step /= 2
    return x, fx


def background_descriptor(descriptors: np.ndarray, grid_points: int = 1000) -> np.ndarray:
    """The point of the unit cube [0, 1]^D that maximises the distance to the nearest descriptor.

    Two stages, because nearest-neighbour queries far from the data visit most of a k-d tree:

    1. On a subset with one descriptor per cell of side 1/64 (every descriptor lies within
       ``delta = sqrt(D)/64`` of the subset): evaluate all corners of the cube (the optimum is often
       one; 4096 random corners for D > 12) and a regular grid of about ``grid_points`` points
       (random points for D > 8, seeded, so the result is deterministic), then refine the best 4 by
       compass search (steps down to 1/256).
    2. Exactly, for the best 2 of those: every descriptor that can be the nearest one to a point
       within ``s = sqrt(D)/64`` of it lies in a ball (radius = subset distance + 2 s), so a k-d
       tree of that ball gives exact distances; compass search within that reach down to steps
       of 1e-4.

    Args:
        descriptors: (N, D) values in [0, 1].
    Returns:
        (D,) float32.
    """
    points = np.asarray(descriptors, dtype=np.float64)
    dim = points.shape[1]
    cell = 1.0 / 64.0
    code = np.clip(np.floor(points / cell), 0, 64).astype(np.int64)
    if dim <= 9:  # 7 bits per axis fit in one int64 key; np.unique on rows is much slower
        code = code @ (np.int64(1) << (7 * np.arange(dim, dtype=np.int64)))
        _, first = np.unique(code, return_index=True)
    else:
        _, first = np.unique(code, axis=0, return_index=True)
    # Symmetric parts repeat the same descriptor many times: median-split (balanced) k-d trees
    # degrade badly with duplicates, sliding-midpoint ones do not.
    coarse_tree = cKDTree(points[np.sort(first)], balanced_tree=False)

    if dim <= 12:
        corners = ((np.arange(2**dim)[:, None] >> np.arange(dim)) & 1).astype(np.float64)
    else:
        corners = np.random.default_rng(0).integers(0, 2, size=(4096, dim)).astype(np.float64)
    per_axis = max(2, int(round(grid_points ** (1.0 / dim))))
    if dim <= 8:
        axes = [np.linspace(0.0, 1.0, per_axis)] * dim
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, dim)
    else:
        grid = np.random.default_rng(0).random((grid_points, dim))
    candidates = np.concatenate([corners, grid])
    distance, _ = coarse_tree.query(candidates)
    starts = candidates[np.argsort(-distance, kind="stable")[:4]]
    coarse = [_compass_search(coarse_tree, s, 0.5 / (per_axis - 1), cell / 4) for s in starts]
    coarse.sort(key=lambda item: -item[1])

    reach = cell
    best_point, best_distance = None, -1.0
    for x0, r0 in coarse[:2]:
        offset = points - x0
        radius = r0 + 2 * reach * math.sqrt(dim)
        near = points[np.einsum("ij,ij->i", offset, offset) <= radius * radius]
        x, fx = _compass_search(cKDTree(near, balanced_tree=False), x0, cell, 1e-4, center=x0, reach=reach)
        if fx > best_distance:
            best_point, best_distance = x, fx
    return best_point.astype(np.float32)


def _components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components over face edges (labels (N,)); unreferenced vertices are their own."""
    return _connected_pieces(n_vertices, np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]]))


def _connected_pieces(n_vertices: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """(number of pieces, labels (N,)) of the graph with undirected ``edges`` (E, 2)."""
    graph = sp.csr_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)


def embed(
    mesh: trimesh.Trimesh | ObjectModel,
    dim: int = 3,
    symmetric: bool = True,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
    components: Literal["error", "largest"] = "error",
    method: Literal["auto", "direct", "multilevel"] = "auto",
) -> DescriptorField:
    """Optimal ``dim``-dimensional descriptors of a mesh's vertices (module docstring).

    Args:
        mesh: a ``trimesh.Trimesh`` or :class:`~don_gym.objects.ObjectModel` (any unit; the result
            does not depend on scale). Vertices are used as given (not merged): load files with
            :func:`don_gym.objects.load_object`, which cleans them.
        dim: number of descriptor dimensions (>= 1).
        symmetric: merge groups of equal eigenvalues (GISIF) so that symmetric points get equal
            descriptors; False gives plain Laplacian Eigenmaps.
        tolerance: relative tolerance for equal eigenvalues (``|l[i+1] - l[i]| <= tolerance*l[i]``).
        components: the Laplacian has one zero eigenvalue per connected piece, so a mesh in several
            pieces has no well-defined embedding. ``"error"`` raises :class:`MeshError` naming the
            number of pieces; ``"largest"`` embeds the piece with the largest area, and every other
            vertex takes the descriptor of the nearest vertex of that piece (3-D distance).
            Unreferenced vertices (in no face) are always treated like the latter.
        method: eigensolver, see :func:`laplacian_eigenpairs`.

    Returns:
        A :class:`DescriptorField`.

    Raises:
        MeshError: empty mesh, NaN/infinite vertices, zero area, several pieces (with
            ``components="error"``), or too few vertices to give ``dim`` descriptor functions.
    """
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
        raise DonGymError(f"dim={dim!r}: expected an integer >= 1")
    if not (np.isfinite(tolerance) and 0 <= tolerance < 1):
        raise DonGymError(f"tolerance={tolerance!r}: expected a relative tolerance in [0, 1)")
    if components not in ("error", "largest"):
        raise DonGymError(f"components={components!r}: expected 'error' or 'largest'")
    if method not in ("auto", "direct", "multilevel"):
        raise DonGymError(f"method={method!r}: expected 'auto', 'direct' or 'multilevel'")
    vertices, faces, digest = _as_mesh(mesh)
    n_all = len(vertices)

    # Choose the piece to embed.
    _, label = _components(n_all, faces)
    referenced = np.zeros(n_all, dtype=bool)
    referenced[faces.ravel()] = True
    piece_labels = np.flatnonzero(np.bincount(label[faces[:, 0]]))
    if len(piece_labels) > 1:
        tri = vertices[faces]
        face_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        area_per_label = np.bincount(label[faces[:, 0]], face_area, minlength=label.max() + 1)
        largest = int(np.argmax(area_per_label))
        if components == "error":
            share = area_per_label[largest] / max(area_per_label.sum(), 1e-300)
            raise MeshError(
                f"mesh has {len(piece_labels)} connected components (the largest has {share:.0%} of the area); "
                "the Laplacian then has one zero eigenvalue per component and no single embedding. "
                "Use the largest component only (embed(..., components='largest'), CLI --components largest)"
                + (
                    " or merge duplicate vertices first (load_object does)"
                    if len(piece_labels) > len(faces) / 4
                    else ""
                )
            )
        keep = label == largest
    else:
        keep = referenced
    keep_index = np.flatnonzero(keep)
    if len(keep_index) == n_all:
        sub_faces = faces
    else:
        remap = np.full(n_all, -1, dtype=np.int64)
        remap[keep_index] = np.arange(len(keep_index))
        sub_faces = remap[faces]
        sub_faces = sub_faces[sub_faces.min(axis=1) >= 0]
    sub_vertices, area = normalize_to_unit_area(vertices[keep_index], sub_faces)
    n = len(sub_vertices)
    if n < dim + 2:
        raise MeshError(
            f"mesh has {n} vertices; {dim} descriptor dimensions need at least {dim + 2} "
            "(one more eigenpair than dimensions, after the constant one)"
        )

    cache: dict = {}
    # Symmetric: start with two spare eigenpairs (enough for a part with one pair among its first
    # groups) and double while the groups do not close.
    count = min(n - 1, dim if not symmetric else dim + 2)
    while True:
        w, Y, mass, solver = _eigenpairs(sub_vertices, sub_faces, count, method, cache)
        result = descriptor_functions(w, Y, mass, sub_vertices, dim, symmetric, tolerance, complete=count >= n - 1)
        if result is not None:
            break
        if count >= n - 1 or count >= max(_MAX_EIGENPAIRS, 8 * dim):
            raise MeshError(
                f"the first {count} eigenpairs of this mesh ({n} vertices) give fewer than {dim} informative "
                f"descriptor functions{' after merging symmetric groups' if symmetric else ''}. "
                + (
                    "A highly symmetric shape (e.g. a sphere, whose merged groups are constant) has no "
                    "symmetric descriptors: use symmetric=False (CLI --no-symmetry) or a smaller dim"
                    if symmetric
                    else "Use a finer mesh or a smaller dim"
                )
            )
        count = min(n - 1, 2 * count)
    descriptors, used = result

    full = np.empty((n_all, dim), dtype=np.float32)
    full[keep_index] = descriptors
    if len(keep_index) < n_all:
        _, nearest = cKDTree(vertices[keep_index]).query(vertices[~keep])
        full[~keep] = descriptors[nearest]
    last = max(max(g) for g in used)
    return DescriptorField(
        vertex_descriptors=full,
        eigenvalues=np.asarray(w[: last + 1], dtype=np.float64) / area,
        groups=tuple(used),
        background=background_descriptor(descriptors),
        symmetric=bool(symmetric),
        mesh_hash=digest,
        tolerance=float(tolerance),
        solver=solver,
        embedded_vertices=n,
    )
