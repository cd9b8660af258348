"""Discrete Laplace-Beltrami operators of a triangle mesh: the intrinsic-Delaunay Laplacian of
robust_laplacian (computed here by edge flips on closed manifold meshes), the cotangent Laplacian,
normalisation to unit area, and connected pieces."""

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
# robust_laplacian flips an edge when its weight (half the sum of its two cotangents) is below -1e-6;
# the same threshold keeps nearly cocircular pairs (a CAD mesh stored in float32) unflipped, as there:
# flipping them leaves L unchanged but moves lumped mass between the quad's corners.
_FLIP_TOL = 1e-6


def _corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions of each face's corners 0, 1, 2, each (3, F) coordinate-major: the layout in which the
    per-face arithmetic below runs on contiguous rows."""
    columns = np.ascontiguousarray(vertices.T)
    return tuple(columns[:, np.ascontiguousarray(faces[:, k])] for k in range(3))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products of (3, F) vectors stored coordinate-major (np.cross on the last axis of an (F, 3)
    copy is several times slower)."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _norm(a: np.ndarray) -> np.ndarray:
    """Lengths (F,) of (3, F) vectors."""
    return np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas (F,) of the faces, in the square of the unit of ``vertices`` (N, 3)."""
    return _areas(*_corners(vertices, faces))


def _areas(c0: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Areas (F,) of the triangles with corners ``c0``, ``c1``, ``c2`` (each (3, F), see :func:`_corners`)."""
    return 0.5 * _norm(_cross(c1 - c0, c2 - c0))


def normalize_to_unit_area(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre the vertices on their area-weighted centroid and scale the surface to unit area.

    Returns ``(vertices_normalized, area)`` where ``area`` is the original surface area; eigenvalues
    of the normalised mesh divided by ``area`` are those of the original one.
    """
    corners = _corners(vertices, faces)
    face_area = _areas(*corners)
    area = float(face_area.sum())
    if not area > 0 or not np.isfinite(area):
        raise MeshError(f"mesh has surface area {area:g}; expected a positive area (all faces are degenerate)")
    centroid = (sum(corners) @ face_area) / (3.0 * area)
    return (vertices - centroid) / math.sqrt(area), area


def mesh_laplacian(vertices: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Intrinsic-Delaunay Laplacian ``L`` (positive semi-definite, CSR) and lumped mass diagonal ``M``
    (N,) of ``robust_laplacian.mesh_laplacian`` (mollify factor :data:`MOLLIFY_FACTOR`).

    On a closed, consistently oriented manifold mesh the same pair comes from
    :func:`intrinsic_delaunay_laplacian` (equal to rounding, several times faster on meshes with many
    non-Delaunay edges); robust_laplacian's tufted cover handles every other mesh.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    flipped = intrinsic_delaunay_laplacian(vertices, faces)
    if flipped is not None:
        L, mass = flipped
    else:
        L, M = robust_laplacian.mesh_laplacian(vertices, faces, mollify_factor=MOLLIFY_FACTOR)
        L, mass = sp.csr_matrix(L), np.asarray(M.diagonal(), dtype=np.float64)
    if not np.all(mass > 0):
        # Unreferenced vertices get zero mass: the eigenproblem would be singular.
        raise MeshError(f"{int((mass <= 0).sum())} vertices have zero area (unreferenced or isolated)")
    return L, mass


def _cotangent(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cotangent of the angle opposite side ``c``, area) of triangles with side lengths a, b, c."""
    s = 0.5 * (a + b + c)
    area = np.sqrt(np.maximum(s * (s - a) * (s - b) * (s - c), 0.0))
    return (a * a + b * b - c * c) / (4.0 * area), area


def intrinsic_delaunay_laplacian(
    vertices: np.ndarray, faces: np.ndarray, max_rounds: int = 100_000
) -> tuple[sp.csr_matrix, np.ndarray] | None:
    """Cotangent Laplacian ``L`` (N, N) CSR and lumped mass ``M`` (N,) of the intrinsic Delaunay
    triangulation of a closed, consistently oriented manifold mesh (the operator of Sharp & Crane's
    robust_laplacian on such a mesh, with its mollification :data:`MOLLIFY_FACTOR`); None for any
    other mesh (a boundary edge, an edge in more than two faces, inconsistent winding, a vertex whose
    faces form more than one fan), or when the flips do not finish in ``max_rounds`` rounds.

    The triangulation keeps the mesh's vertices and intrinsic metric (edge lengths) and flips every
    edge whose two opposite angles sum to more than pi; each round flips a set of such edges no two
    of which share a face, all at once, so the work is a few array passes per round rather than a
    loop over edges. Edge lengths are in the units of ``vertices``; M is a third of the intrinsic
    area of each face at its corners.
    """
    n, n_faces = len(vertices), len(faces)
    corner_vertex = np.array(faces, dtype=np.int64)  # (F, 3), updated by the flips
    if n_faces == 0 or np.any(corner_vertex[:, [0, 1, 2]] == corner_vertex[:, [1, 2, 0]]):
        return None  # no faces, or a face with a repeated vertex
    # Edge k of a face is opposite its corner k and joins corners k+1 -> k+2 (the face's winding).
    tail = corner_vertex[:, [1, 2, 0]].T.ravel()
    head = corner_vertex[:, [2, 0, 1]].T.ravel()
    key = np.minimum(tail, head) * n + np.maximum(tail, head)
    order = np.argsort(key, kind="stable")
    starts = np.ones(len(key), dtype=bool)
    starts[1:] = key[order][1:] != key[order][:-1]
    edge_of = np.empty(len(key), dtype=np.int64)
    edge_of[order] = np.cumsum(starts) - 1
    n_edges = int(edge_of[order[-1]]) + 1
    faces_per_edge = np.bincount(edge_of, minlength=n_edges)
    forward = np.bincount(edge_of, (tail < head).astype(np.int64), minlength=n_edges)
    if np.any(faces_per_edge != 2) or np.any(forward != 1):  # boundary, non-manifold or mis-wound
        return None
    face_edge = edge_of.reshape(3, n_faces).T.copy()  # (F, 3) edge opposite each corner
    # Both sides of each edge: (face, corner opposite the edge).
    side_face = np.tile(np.arange(n_faces), 3)[order].reshape(n_edges, 2)
    side_corner = np.repeat(np.arange(3), n_faces)[order].reshape(n_edges, 2)
    if _fans(corner_vertex, face_edge, side_face, side_corner) != np.count_nonzero(np.bincount(tail, minlength=n)):
        return None  # a vertex where two or more fans of faces meet: the tufted cover differs there

    first = order[starts]
    columns = np.ascontiguousarray(vertices.T)
    length = _norm(columns[:, tail[first]] - columns[:, head[first]])
    # Mollification as robust_laplacian's: lengthen every edge by the least amount that gives every
    # face a triangle-inequality margin of MOLLIFY_FACTOR times the mean edge length.
    sides = length[face_edge]
    margin = sides.sum(axis=1, keepdims=True) - 2.0 * sides
    length = length + max(0.0, float((MOLLIFY_FACTOR * length.mean() - margin).max()))

    # Flat views (the arrays are C-contiguous): slot 3 f + k is face f's corner k and the edge opposite
    # it, slot 2 e + s side s of edge e. The flip rounds below index these: many rounds are only a few
    # edges, where the cost of a two-array fancy index, not the arithmetic, would dominate.
    corner_at, edge_at = corner_vertex.reshape(-1), face_edge.reshape(-1)
    side_face_at, side_corner_at = side_face.reshape(-1), side_corner.reshape(-1)
    following, preceding = np.array([1, 2, 0]), np.array([2, 0, 1])  # corner k -> k + 1, k + 2 (mod 3)

    def cot_opposite(face: np.ndarray, corner: np.ndarray) -> np.ndarray:
        slot = 3 * face
        return _cotangent(
            length[edge_at[slot + following[corner]]],
            length[edge_at[slot + preceding[corner]]],
            length[edge_at[slot + corner]],
        )[0]

    def edge_weights() -> np.ndarray:
        """(E,) half the sum of each edge's two opposite cotangents, from every face's cotangents at once."""
        sides = length[face_edge]
        cot = np.stack([_cotangent(sides[:, (k + 1) % 3], sides[:, (k + 2) % 3], sides[:, k])[0] for k in range(3)], 1)
        return 0.5 * (cot[side_face[:, 0], side_corner[:, 0]] + cot[side_face[:, 1], side_corner[:, 1]])

    # Priorities only break ties between neighbouring candidates: the Delaunay triangulation is unique but
    # for cocircular pairs, which the threshold leaves unflipped, so the order of flips does not matter.
    rng = np.random.default_rng(0)
    active = np.arange(n_edges)
    # Per face, the highest priority among its candidates; reset after each round where it was set, so
    # that a round costs in proportion to its candidates (flips cascade through thousands of rounds of a
    # few edges each over fans of needles), not to the mesh.
    highest = np.full(n_faces, -1.0)
    # Every edge's weight: those of a flipped quad's edges, the only ones a flip changes, are recomputed
    # in the next round (the same arithmetic as edge_weights, since halving is exact).
    weights = weight = edge_weights()
    for round_ in range(max_rounds):
        if round_ > 0:
            cot = cot_opposite(side_face[active].ravel(), side_corner[active].ravel())  # both sides, interleaved
            weight = 0.5 * cot[0::2] + 0.5 * cot[1::2]
            weights[active] = weight
        candidates = active[weight < -_FLIP_TOL]
        if len(candidates) == 0:
            break
        # Flip the candidates whose random priority is the highest among the candidates of both faces.
        priority = rng.random(len(candidates))
        face_0, face_1 = side_face_at[2 * candidates], side_face_at[2 * candidates + 1]
        np.maximum.at(highest, face_0, priority)
        np.maximum.at(highest, face_1, priority)
        wins = (highest[face_0] == priority) & (highest[face_1] == priority)
        highest[face_0] = highest[face_1] = -1.0
        edge = candidates[wins]
        # Face f = (k, i, j) from its corner opposite the edge, face g = (l, j, i): the edge i-j
        # becomes k-l, f = (k, i, l) and g = (l, j, k), each corner keeping its slot.
        side_0 = 2 * edge
        f, g = side_face_at[side_0], side_face_at[side_0 + 1]
        cf, cg = side_corner_at[side_0], side_corner_at[side_0 + 1]
        cf1, cg1 = following[cf], following[cg]
        f_cf, f_cf1, f_cf2 = 3 * f + cf, 3 * f + cf1, 3 * f + preceding[cf]
        g_cg, g_cg1, g_cg2 = 3 * g + cg, 3 * g + cg1, 3 * g + preceding[cg]
        vertex_k, vertex_l = corner_at[f_cf], corner_at[g_cg]
        edge_jk, edge_ki = edge_at[f_cf1], edge_at[f_cf2]
        edge_il, edge_lj = edge_at[g_cg1], edge_at[g_cg2]
        # The new length: lay the two faces out in the plane, i at the origin, j on the x axis.
        ij, ik, jk, il, lj = length[edge], length[edge_ki], length[edge_jk], length[edge_il], length[edge_lj]
        x_k = (ij * ij + ik * ik - jk * jk) / (2.0 * ij)
        x_l = (ij * ij + il * il - lj * lj) / (2.0 * ij)
        y_k = np.sqrt(np.maximum(ik * ik - x_k * x_k, 0.0))
        y_l = np.sqrt(np.maximum(il * il - x_l * x_l, 0.0))
        length[edge] = np.hypot(x_k - x_l, y_k + y_l)
        corner_at[f_cf2], corner_at[g_cg2] = vertex_l, vertex_k
        edge_at[f_cf], edge_at[f_cf1] = edge_il, edge
        edge_at[g_cg], edge_at[g_cg1] = edge_jk, edge
        side_corner_at[side_0], side_corner_at[side_0 + 1] = cf1, cg1
        # The side of edge il that was g's corner cg1 is now f's corner cf; that of jk, g's corner cg.
        slot = 2 * edge_il + ((side_face_at[2 * edge_il] != g) | (side_corner_at[2 * edge_il] != cg1))
        side_face_at[slot], side_corner_at[slot] = f, cf
        slot = 2 * edge_jk + ((side_face_at[2 * edge_jk] != f) | (side_corner_at[2 * edge_jk] != cf1))
        side_face_at[slot], side_corner_at[slot] = g, cg
        # Only the flipped quads' edges, and the candidates that lost, can be non-Delaunay now.
        active = _sorted_unique(np.concatenate([candidates[~wins], edge, edge_jk, edge_ki, edge_il, edge_lj]))
    else:
        return None

    # Each edge once: its end points are the vertices at the other two corners of either face.
    face, corner = side_face[:, 0], side_corner[:, 0]
    i, j = corner_at[3 * face + following[corner]], corner_at[3 * face + preceding[corner]]
    # An edge flipped into a loop at one vertex adds equally to a diagonal entry and its row sum.
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    off = sp.csr_matrix((np.concatenate([-weights, -weights]), (rows, cols)), (n, n))
    L = sp.csr_matrix(off - sp.diags(np.asarray(off.sum(axis=1)).ravel()))
    sides = length[face_edge]
    area = _cotangent(sides[:, 0], sides[:, 1], sides[:, 2])[1]
    mass = np.bincount(corner_vertex.ravel(), np.repeat(area / 3.0, 3), minlength=n)
    return L, mass


def _sorted_unique(values: np.ndarray) -> np.ndarray:
    """``np.unique`` of a 1-D integer array (non-empty), without its fixed cost of tens of microseconds,
    which thousands of flip rounds of a few edges each would pay."""
    values = np.sort(values)
    keep = np.empty(len(values), dtype=bool)
    keep[0] = True
    np.not_equal(values[1:], values[:-1], out=keep[1:])
    return values[keep]


def _fans(corner_vertex: np.ndarray, face_edge: np.ndarray, side_face: np.ndarray, side_corner: np.ndarray) -> int:
    """Number of fans of faces about the vertices of a closed, oriented edge-manifold mesh: corners
    at a vertex joined across the edges between them, counted as connected pieces."""
    n_faces = len(corner_vertex)
    face = np.arange(n_faces)
    following = np.empty((n_faces, 3), dtype=np.int64)  # corner -> next corner about the same vertex
    for k in range(3):
        # Corner k's edge to corner k+1 is the edge opposite corner k+2; across it, in the other
        # face g (corner q opposite), the same vertex is corner q+2 (the windings are opposite).
        edge = face_edge[:, (k + 2) % 3]
        other = np.where(side_face[edge, 0] == face, 1, 0)
        following[:, k] = side_face[edge, other] * 3 + (side_corner[edge, other] + 2) % 3
    # A permutation of the corners: its cycles are the fans, the strong components of its graph.
    size = 3 * n_faces
    graph = sp.csr_matrix((np.ones(size, dtype=np.int8), following.ravel(), np.arange(size + 1)), shape=(size, size))
    return connected_components(graph, directed=True, connection="strong")[0]


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
    corners = _corners(vertices, faces)
    # Edge k is opposite corner k; its squared length and the face's doubled area give the
    # cotangent at corner k: (|a|^2 + |b|^2 - |e_k|^2) / (4 area) for its two other edges a, b.
    edge = [corners[(k + 2) % 3] - corners[(k + 1) % 3] for k in range(3)]
    length2 = [e[0] * e[0] + e[1] * e[1] + e[2] * e[2] for e in edge]
    twice_area = _norm(_cross(edge[2], edge[1]))
    if not np.all(twice_area > 0):
        return None
    lowest_cot = 1.0 / math.tan(max_angle) if max_angle < math.pi else -np.inf
    weights = []
    for k in range(3):
        cot = (length2[(k + 1) % 3] + length2[(k + 2) % 3] - length2[k]) / (2.0 * twice_area)
        if not np.all(cot >= lowest_cot):  # also catches non-finite values
            return None
        weights.append(0.5 * cot)  # half the cotangent of the angle at corner k weighs the opposite edge
    # Edge k joins corners k+1 and k+2; each is entered once per face with its pair of vertices in order.
    i, j = faces[:, [1, 2, 0]].T.ravel(), faces[:, [2, 0, 1]].T.ravel()
    low, high = np.minimum(i, j), np.maximum(i, j)
    # One sparse assembly sums both an edge's weights (real part) and the faces it is in (imaginary part).
    summed = sp.csr_matrix((1j - np.concatenate(weights), (low, high)), shape=(n, n))
    if summed.nnz and summed.data.imag.max() > 2:  # sums of ones: exact
        return None
    upper = sp.csr_matrix((summed.data.real, summed.indices, summed.indptr), shape=(n, n))
    flipped = upper.data > _DELAUNAY_TOL
    if flipped.any():
        row = np.repeat(np.arange(n), np.diff(upper.indptr))[flipped]
        length = np.linalg.norm(vertices[row] - vertices[upper.indices[flipped]], axis=1)
        if length.max() > _COTAN_MAX_FLIPPED_EDGE * math.sqrt(0.5 * float(twice_area.sum())):
            return None
    off = upper + upper.T
    L = sp.csr_matrix(off - sp.diags(np.asarray(off.sum(axis=1)).ravel()))
    third = twice_area / 6.0
    mass = sum(np.bincount(faces[:, k], third, minlength=n) for k in range(3))
    return L, mass


def mesh_components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components over face edges (labels (N,)); unreferenced vertices are their own."""
    return connected_pieces(n_vertices, np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]]))


def connected_pieces(n_vertices: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """(number of pieces, labels (N,)) of the graph with undirected ``edges`` (E, 2)."""
    graph = sp.csr_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(graph, directed=False)
