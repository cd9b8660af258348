"""Smallest eigenpairs of ``L y = lambda M y`` of a connected mesh: a direct solver (shift-invert
Lanczos) and a multilevel one (vertex-clustered coarse meshes, prolongation, LOBPCG refinement)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from don_gym.descriptors.laplacian import (
    connected_pieces,
    cotan_laplacian,
    mesh_components,
    mesh_laplacian,
    normalize_to_unit_area,
)
from don_gym.errors import MeshError

#: ``method="auto"`` solves meshes with fewer vertices than this directly (multilevel above).
DIRECT_MAX_VERTICES = 10_000
# Multilevel solver settings (see _coarsen, _Level and _lobpcg).
_COARSEST_VERTICES = 8000  # solve directly at or below this size
_CLUSTER_SIZE = 24.0  # target fine vertices per coarse vertex (voxel area in units of vertex area)
_MIN_COARSE_VERTICES = 2000  # smaller clusters where 24 would give fewer coarse vertices
_VOXEL_TRIES = 6  # voxel refinements where unevenly spread vertices give too few clusters
_VOXEL_ACCEPT = 0.8  # ... until at least this fraction of the target count
_REFINE_TOL = 2e-3  # stop refining when each needed eigenvector's estimated error is below (M-norm)
_REFINE_TOL_COARSE = 1e-2  # the same on intermediate levels, which only give starting vectors
_REFINE_MAXITER = 12
# ARPACK's accuracy on the coarsest level: its eigenvectors only start the refinement, and differ from
# the fine level's by the coarse discretisation (~1e-2), so machine precision there buys nothing.
_COARSEST_TOL = 1e-6
# l1-Jacobi smoothing, x += omega r / sum_j |a_ij|: where every weight of L is non-negative (zero row
# sums) this is about Jacobi with 2/3; where obtuse angles give negative weights, as on fans and rows of
# slivers, plain Jacobi can amplify some modes and the two-grid cycle diverge, while diag(sum_j |a_ij|)
# bounds A from above, so l1-Jacobi damps every mode.
_L1_JACOBI_OMEGA = 4.0 / 3.0
# The refinement needs eigenvectors to ~1e-3: single precision halves the memory traffic of its
# dense products and of the preconditioner; L x (see _lobpcg) and the Rayleigh-Ritz matrices are
# computed in double precision.
_REFINE_DTYPE = np.float32
_GRAM_RTOL = 1e-6  # Rayleigh-Ritz drops directions whose Gram eigenvalue is below this (relative)
_PRECONDITIONER_SHIFT = 1.0  # sigma of L + sigma*M on unit-area meshes (lambda_1 ~ 0.3-25)
_MAX_RATE = 0.9  # cap of the estimated LOBPCG convergence rate (error estimate <= 9 x last step)
_GUARD = 4


def _direct_eigenpairs(
    L: sp.spmatrix,
    mass: np.ndarray,
    count: int,
    shift: float = 1e-6,
    factor: object | None = None,
    tol: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest ``count`` non-constant eigenpairs of ``L y = lambda M y`` (``mass`` the diagonal of M)
    for a connected mesh normalised to unit area (eigenvalues O(1-100)).

    Shift-invert Lanczos about ``-shift``; ``factor`` is a factorisation of ``L + shift * M`` (its
    ``solve``) when the caller has one, else it is computed; ``tol`` is ARPACK's relative accuracy
    of the eigenvalues (0: machine precision).
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
            sp.csc_matrix(L), k=count + 1, M=sp.csc_matrix(Bm), sigma=-shift, which="LM", OPinv=solve, v0=start, tol=tol
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


def _cluster(vertices: np.ndarray, edges: np.ndarray, voxel: float) -> tuple[int, np.ndarray]:
    """Labels (N,) of voxel clusters split into connected pieces; ``edges`` (E, 2) vertex pairs."""
    cell = np.floor((vertices - vertices.min(axis=0)) / voxel).astype(np.int64)
    key = (cell[:, 0] << 42) + (cell[:, 1] << 21) + cell[:, 2]
    _, voxel_id = np.unique(key, return_inverse=True)
    voxel_id = voxel_id.ravel()
    inside = voxel_id[edges[:, 0]] == voxel_id[edges[:, 1]]
    return connected_pieces(len(vertices), edges[inside])


def _coarsen(vertices: np.ndarray, faces: np.ndarray, cluster_size: float):
    """One coarse level: (coarse vertices, coarse faces, prolongation P (n_fine, n_coarse) CSR).

    Vertices are grouped by a voxel grid (about ``cluster_size`` per cluster) and split into
    connected pieces inside each voxel, so two sheets of a thin wall never merge. Each cluster's
    vertex nearest its centroid becomes a coarse vertex; each fine face with its corners in three
    clusters becomes a coarse face. ``P`` is linear: a fine vertex takes the barycentric coordinates
    of its projection onto the coarse face (around its cluster's coarse vertex) it lies most inside
    of, so smooth eigenfunctions are approximated to second order.
    """
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    # Mean vertex area is 1/n on a unit-area mesh; a voxel that cuts a patch of ~cluster_size vertices
    # where vertices are spread evenly. Where they are not (a long thin part, rows of slivers, fans:
    # vertices dense along curves), far fewer clusters come out; the voxel then shrinks until the count
    # is reached (secant steps on log count over log voxel, as the count goes with voxel^-1 to ^-2).
    target = n / cluster_size
    voxel = math.sqrt(cluster_size / n)
    n_coarse, label = _cluster(vertices, edges, voxel)
    previous = None
    for _ in range(_VOXEL_TRIES):
        if n_coarse >= _VOXEL_ACCEPT * target:
            break
        slope = -2.0
        if previous is not None and previous[1] != n_coarse:
            slope = min(-0.5, max(-3.0, math.log(n_coarse / previous[1]) / math.log(voxel / previous[0])))
        previous = (voxel, n_coarse)
        voxel *= (target / n_coarse) ** (1.0 / slope)
        n_coarse, label = _cluster(vertices, edges, voxel)
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
    # Fine vertices sorted by the number of candidate faces, so that pass j works on a prefix. Points
    # and face terms are coordinate-major: gathering single values is several times faster than
    # gathering rows of three.
    vertex_degree = degree[label]
    by_degree = np.argsort(-vertex_degree, kind="stable")
    sorted_degree = vertex_degree[by_degree]
    first_face = start[label[by_degree]]
    points = np.ascontiguousarray(vertices[by_degree].T)
    g1_rows, g2_rows = np.ascontiguousarray(g1.T), np.ascontiguousarray(g2.T)

    def coordinates(p: np.ndarray, face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Barycentric coordinates 2 and 3 of the points p (3, m), each on its face.
        v = p[0] * g1_rows[0][face] + p[1] * g1_rows[1][face] + p[2] * g1_rows[2][face] - o1[face]
        w = p[0] * g2_rows[0][face] + p[1] * g2_rows[1][face] + p[2] * g2_rows[2][face] - o2[face]
        return v, w

    best_inside = np.full(n, -np.inf)
    best_face = np.full(n, -1, dtype=np.int64)
    for j in range(int(degree.max()) if len(degree) else 0):
        m = int(np.searchsorted(-sorted_degree, -j, side="left"))  # vertices with more than j faces
        face = inc_face[first_face[:m] + j]
        v, w = coordinates(points[:, :m], face)
        inside = np.minimum(np.minimum(v, w), 1.0 - v - w)
        better = inside > best_inside[:m]
        np.copyto(best_inside[:m], inside, where=better)
        np.copyto(best_face[:m], face, where=better)
    best_v, best_w = np.zeros(n), np.zeros(n)
    found = best_face >= 0
    best_v[found], best_w[found] = coordinates(points[:, found], best_face[found])
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
    :data:`_COARSEST_VERTICES` vertices the next coarser mesh (:func:`_coarsen`, fewer vertices per
    cluster where :data:`_CLUSTER_SIZE` would leave under :data:`_MIN_COARSE_VERTICES`) with its
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
        if mesh_components(len(coarse_vertices), coarse_faces)[0] > 1:
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
        row_l1 = np.asarray(abs(shifted).sum(axis=1)).ravel()
        self._smoother = (_L1_JACOBI_OMEGA / row_l1).astype(_REFINE_DTYPE)[:, None]
        self._P_single, self._PT_single = self.P.astype(_REFINE_DTYPE), self.PT.astype(_REFINE_DTYPE)
        coarse = self.coarse
        self._coarse_lu = _factorize_spd(coarse.L + sp.diags(_PRECONDITIONER_SHIFT * coarse.mass))

    def _precondition(self, R: np.ndarray) -> np.ndarray:
        # Symmetric two-grid cycle for (L + sigma M)^-1: smoothing, coarse correction, smoothing.
        A, d = self._shifted, self._smoother
        X = d * R
        coarse_residual = np.asarray(self._PT_single @ (R - A @ X), dtype=np.float64)
        X += self._P_single @ self._coarse_lu.solve(coarse_residual).astype(_REFINE_DTYPE)
        X += d * (R - A @ X)
        return X

    def eigenpairs(
        self, count: int, block: int | None = None, tol: float = _REFINE_TOL
    ) -> tuple[np.ndarray, np.ndarray]:
        """Smallest ``block`` non-constant eigenpairs, of which the first ``count`` are converged
        to ``tol``: solved on the coarse level (recursively; directly on the coarsest), prolonged,
        and refined here by single-precision LOBPCG preconditioned by a two-grid cycle."""
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
            w, Y = _direct_eigenpairs(
                coarse.L, coarse.mass, block, _PRECONDITIONER_SHIFT, self._coarse_lu, _COARSEST_TOL
            )
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
    L: sp.csr_matrix,
    mass: np.ndarray,
    X0: np.ndarray,
    precond: Callable[[np.ndarray], np.ndarray],
    n_check: int,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Block LOBPCG (Knyazev 2001) for the smallest eigenpairs of ``A x = lambda M x`` (``mass`` the
    diagonal of M, A = ``L``) orthogonal to constants, from the start block
    ``X0`` (n, m); ``precond`` approximates ``(A + sigma M)^-1``. Converged when the estimated
    remaining error of each of the first ``n_check`` Ritz vectors is below ``tol`` (M-norm); raises
    _NotConverged after :data:`_REFINE_MAXITER` iterations.

    Returns ``(Ritz values (m,), Ritz vectors (n, m) M-orthonormal, iterations)``."""
    n, m = X0.shape
    # Solved for z = M^(1/2) x, an ordinary symmetric eigenproblem (M is diagonal): no M-products
    # to carry along, and the M-norm of x is the 2-norm of z.
    dtype = _REFINE_DTYPE
    root64 = np.sqrt(mass)[:, None]
    root = root64.astype(dtype)

    def apply_A(Z: np.ndarray) -> np.ndarray:
        # In double precision: in single, L x summed from L's entries cancels terms of size L_ii x_i
        # down to lambda m_i x_i, with rounding errors of eps L_ii / (lambda m_i) relative (1 % in the
        # first eigenvalue of a long thin shaft; on rows of slivers the residual drowned in them).
        return ((L @ (Z / root64)) / root64).astype(dtype)

    constant = root / dtype(math.sqrt(float(mass.sum())))

    def deflate(Z: np.ndarray) -> np.ndarray:
        return Z - constant @ (constant.T @ Z)

    # The blocks X, W (preconditioned residuals) and P (last step) sit side by side in one array,
    # and their A-products in another, so that the Rayleigh-Ritz matrices and the updates are
    # single matrix products.
    S, AS = np.empty((n, 3 * m), dtype), np.empty((n, 3 * m), dtype)
    S[:, :m] = deflate(root * X0.astype(dtype))
    AS[:, :m] = apply_A(S[:, :m])
    lam, C = _rayleigh_ritz(S[:, :m], AS[:, :m], m)
    for block in (S, AS):
        block[:, :m] = block[:, :m] @ C.astype(dtype)
    width = 2 * m  # no P block before the first step
    previous_step = None
    remaining = np.inf
    for iteration in range(1, _REFINE_MAXITER + 1):
        residual = AS[:, :m] - S[:, :m] * lam.astype(dtype)
        W = deflate(root * precond(root * residual))
        S[:, m : 2 * m], AS[:, m : 2 * m] = W, apply_A(W)
        lam, C = _rayleigh_ritz(S[:, :width], AS[:, :width], m)
        # A-products are updated with the same coefficients as the vectors (dense products)
        # instead of being recomputed with the sparse matrix.
        C = C.astype(dtype)
        for block in (S, AS):
            new_x = block[:, :width] @ C
            block[:, 2 * m :] = block[:, m:width] @ C[m:]
            block[:, :m] = new_x
        width = 3 * m
        # Size of this step outside the previous subspace (X is orthonormal), per needed vector.
        # Convergence is linear, so the remaining error is the geometric tail step * r / (1 - r)
        # with the rate r estimated from the last two steps; after the first step, whose rate is not
        # known yet, with the largest rate the estimate allows (where the prolonged start was already
        # accurate, as on finely meshed CAD parts, its first step is that small).
        step_needed = S[:, 2 * m : 2 * m + n_check]
        step = np.sqrt(np.einsum("ij,ij->j", step_needed, step_needed, dtype=np.float64))
        rate = _MAX_RATE if previous_step is None else np.minimum(step / np.maximum(previous_step, 1e-300), _MAX_RATE)
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
            ``"multilevel"`` (coarse solve, prolongation, LOBPCG refinement; the direct solver when
            that fails) or ``"auto"`` (direct below
            :data:`DIRECT_MAX_VERTICES` vertices).

    Returns:
        ``(eigenvalues (count,) ascending in 1/unit^2, eigenvectors (N, count) M-orthonormal for
        the lumped mass matrix of the Laplacian the solver used, solver name)``.
    """
    faces = np.asarray(faces, dtype=np.int64)
    normalized, area = normalize_to_unit_area(np.asarray(vertices, dtype=np.float64), faces)
    w, Y, _, solver = mesh_eigenpairs(normalized, faces, count, method, {})
    return w / area, Y / math.sqrt(area), solver


def mesh_eigenpairs(
    vertices: np.ndarray, faces: np.ndarray, count: int, method: str, cache: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(eigenvalues, eigenvectors, lumped mass, solver) of a connected unit-area mesh; ``cache``
    keeps Laplacians and the multilevel hierarchy between calls with growing ``count``.

    The multilevel solver's finest-level operator is :func:`cotan_laplacian` when the mesh meets its
    gate (maximum angle, no long edge that intrinsic flips would change; a consistent discretisation
    of the same operator, built without intrinsic edge flips), else robust_laplacian's Laplacian of
    the whole mesh, as for the direct solver.
    """
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
