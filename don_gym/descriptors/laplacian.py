"""Discrete Laplace-Beltrami operators of a triangle mesh: robust_laplacian's intrinsic-Delaunay
Laplacian, the cotangent Laplacian, normalisation to unit area, and connected pieces."""

from __future__ import annotations

import math

import numpy as np
import robust_laplacian
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from don_gym.errors import MeshError

#: Mollification of robust_laplacian, relative to the mean edge length (docs/background.md,
#: "Optimal descriptors").
MOLLIFY_FACTOR = 1e-5
_COTAN_MAX_ANGLE = math.radians(170.0)  # cotan_laplacian refuses meshes with a larger angle
# ... and meshes with an edge longer than this fraction of sqrt(area) that is not locally Delaunay
# (weight below -_DELAUNAY_TOL): intrinsic edge flips there, and the flips they set off across
# nearly cocircular neighbours (a fan over collinear points), retriangulate a region of the size of
# the first eigenfunctions, so the two Laplacians' eigenvectors differ (descriptors by 0.07 on a box
# whose faces are fans of needles, where every angle is below 160 degrees).
_COTAN_MAX_FLIPPED_EDGE = 0.1
_DELAUNAY_TOL = 1e-9  # cotangent weights of cocircular pairs (rectangles' diagonals) round to about +-1e-13


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
    (radians), a face of zero area, an edge in more than two faces, or a long edge that is not
    locally Delaunay (see :data:`_COTAN_MAX_FLIPPED_EDGE`).

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
    flipped = upper.data > _DELAUNAY_TOL
    if flipped.any():
        row = np.repeat(np.arange(n), np.diff(upper.indptr))[flipped]
        length = np.linalg.norm(vertices[row] - vertices[upper.indices[flipped]], axis=1)
        if length.max() > _COTAN_MAX_FLIPPED_EDGE * math.sqrt(0.5 * float(twice_area.sum())):
            return None
    off = upper + upper.T
    L = sp.csr_matrix(off - sp.diags(np.asarray(off.sum(axis=1)).ravel()))
    mass = np.bincount(faces.ravel(), np.repeat(twice_area / 6.0, 3), minlength=n)
    return L, mass


def _components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components over face edges (labels (N,)); unreferenced vertices are their own."""
    return _connected_pieces(n_vertices, np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]]))


def _connected_pieces(n_vertices: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """(number of pieces, labels (N,)) of the graph with undirected ``edges`` (E, 2)."""
    graph = sp.csr_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)
