"""Optimal descriptors of a mesh (:func:`embed`): Laplacian Eigenmaps with symmetric eigenfunctions
merged (GISIF), signs fixed by shape, and the background descriptor."""

from __future__ import annotations

import math
import time
from typing import Literal

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from don_gym.descriptors.eigensolver import mesh_eigenpairs
from don_gym.descriptors.field import DescriptorField, mesh_arrays
from don_gym.descriptors.laplacian import face_areas, mesh_components, normalize_to_unit_area
from don_gym.errors import DonGymError, MeshError, SeveralPiecesError
from don_gym.objects import ObjectModel

#: Default relative tolerance under which consecutive eigenvalues count as equal (one symmetry group).
DEFAULT_TOLERANCE = 1e-2
#: A merged group whose function varies by less than this fraction of its mean is taken as
#: constant and skipped: on a sphere the sum of squares of all spherical harmonics of one degree is
#: constant, and on a triangulated sphere what is left (1-9 % on icospheres) is the pattern of the
#: triangulation, which normalisation to [0, 1] would blow up into meaningless descriptors.
CONSTANT_GROUP_RTOL = 0.1
#: embed gives up (MeshError) when this many eigenpairs (or 8 * dim) still do not close dim groups.
_MAX_EIGENPAIRS = 64


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


# A fixed generic direction for the sign fall-back (no symmetry plane of common parts contains it).
_GENERIC_DIRECTION = np.array([1.0, math.sqrt(2.0), math.sqrt(3.0)]) / math.sqrt(6.0)
# A sign rule's integral counts as zero below these fractions of its bound: above what the multilevel
# solver's error (eigenvectors accurate to ~1e-3) leaves in them for functions where they are exactly
# zero (measured: skewness up to 2e-3, the moment up to 3e-5), so that the sign of an eigenvector that
# is odd under a mirror symmetry never follows the solver's error.
_SKEW_RTOL = 1e-2
_MOMENT_RTOL = 1e-3


def _fix_sign(y: np.ndarray, mass: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Sign of an eigenvector fixed by the shape only (independent of vertex order).

    1. the integral of y^3 over the surface (skewness) is made positive;
    2. if that vanishes (y is odd under a reflection of the part), the integral of y times the
       coordinate along a fixed generic direction is made positive;
    3. otherwise the value at the vertex furthest along that direction is made positive.
    """
    weighted_square = mass * y * y
    skew = float(weighted_square @ y)
    if abs(skew) > _SKEW_RTOL * float(weighted_square @ np.abs(y)):
        return y if skew > 0 else -y
    along = vertices @ _GENERIC_DIRECTION
    moment = float((mass * y) @ along)
    if abs(moment) > _MOMENT_RTOL * float((mass * np.abs(y)) @ np.abs(along)):
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
    nearest: _Nearest | _NearestAround,
    start: np.ndarray,
    step: float,
    min_step: float,
    center: np.ndarray | None = None,
    reach: float = 0.0,
) -> tuple[np.ndarray, float]:
    """Maximise the distance to the nearest point (``nearest.distances``) over the unit cube by compass
    search (move along +-axes while that helps, else halve the step); with ``center``, stay within
    ``reach`` (max-norm) of it."""
    dim = len(start)
    directions = np.concatenate([np.eye(dim), -np.eye(dim)])
    x = start.copy()
    fx = float(nearest.distances(start[None], x, math.inf, 0.0)[0])
    while step > min_step:
        trial = np.clip(x + step * directions, 0.0, 1.0)
        if center is not None:
            trial = np.clip(trial, center - reach, center + reach)
        d = nearest.distances(trial, x, fx, step)
        i = int(np.argmax(d))
        if d[i] > fx + 1e-12:
            x, fx = trial[i], float(d[i])
        else:
            step /= 2
    return x, fx


class _NearestByScan:
    """``query(x)`` like cKDTree's (distance to the nearest of ``points``, first of the pair it
    returns) by scanning all points. Where the points lie on a closed surface around the queried
    point (descriptors of spheres and ellipsoids: the background is their centre), a k-d tree visits
    every node at a fraction of a vectorised scan's speed. Squares are summed in cKDTree's order
    (groups of four, then the rest; checked bit for bit), so the distances are the same."""

    _CHUNK = 1 << 20  # points per pass

    def __init__(self, points: np.ndarray):
        self.columns = np.ascontiguousarray(points.T)  # (D, N): one coordinate at a time

    def query(self, x: np.ndarray) -> tuple[np.ndarray | float, None]:
        queries = np.atleast_2d(x)
        dim, n = self.columns.shape
        full = 4 * (dim // 4)
        best = np.full(len(queries), np.inf)
        for start in range(0, n, self._CHUNK):
            columns = self.columns[:, start : start + self._CHUNK]

            def square(i: int, columns: np.ndarray = columns) -> np.ndarray:
                difference = columns[i][None, :] - queries[:, i, None]
                return np.multiply(difference, difference, out=difference)

            if full:
                acc = [square(j) for j in range(4)]
                for i in range(4, full, 4):
                    for j in range(4):
                        acc[j] += square(i + j)
                total = ((acc[0] + acc[1]) + acc[2]) + acc[3]
            else:
                total = np.zeros((len(queries), columns.shape[1]))
            for i in range(full, dim):
                total += square(i)
            np.minimum(best, total.min(axis=1), out=best)
        distance = np.sqrt(best)
        return (distance if np.ndim(x) > 1 else float(distance[0])), None


class _Nearest:
    """Nearest-neighbour distances of ``points`` by :class:`_NearestByScan` or a k-d tree (built on
    first use), whichever has been faster so far (each is tried once first): they give the same
    distances, so the result does not depend on the choice, only the time (a tree wins on spread-out
    points, a scan around shells)."""

    def __init__(self, points: np.ndarray, tree: cKDTree | None = None):
        self._points = points
        self._methods: list = [_NearestByScan(points), tree]
        self._seconds = [0.0, 0.0]
        self._calls = [0, 0]

    def distances(self, trial: np.ndarray, x: np.ndarray, fx: float, step: float) -> np.ndarray:
        """(K,) distances of the ``trial`` points (K, D) to their nearest points (``x``, ``fx``, ``step``:
        the search's state, which :class:`_NearestAround` uses)."""
        return np.asarray(self.query(trial)[0])

    def query(self, x: np.ndarray) -> tuple[np.ndarray | float, None]:
        if 0 in self._calls:
            k = self._calls.index(0)
        else:
            k = int(np.argmin([t / c for t, c in zip(self._seconds, self._calls, strict=True)]))
        start = time.perf_counter()
        if self._methods[k] is None:
            self._methods[k] = cKDTree(self._points, balanced_tree=False)
        distance = self._methods[k].query(x)[0]
        self._seconds[k] += time.perf_counter() - start
        self._calls[k] += 1
        return distance, None


class _NearestAround:
    """Exact nearest-point distances for a compass search, scanning (:class:`_NearestByScan`) only the
    points that can be nearest to one of its trials.

    A trial t lies within ``step`` of the current point x, so its nearest point p satisfies
    |p - t| = d(t) <= d(x) + step and |p - x| <= d(x) + 2 step. The points kept are those within
    ``d(a) + 2 (s_a + m)`` of an anchor a (the point, step s_a and margin m = 2 s_a when they were
    kept), which holds every such p while |x - a| + step <= s_a + m; otherwise, and whenever the step
    has halved, they are kept anew around x. Where the points surround the searched point (a shell of
    descriptors about its centre), a step of 1e-3 keeps a thin band of them instead of all. Distances
    are those of the full scan, bit for bit: each point's distance is computed the same way whatever
    else is scanned.
    """

    def __init__(self, points: np.ndarray):
        self._all = points
        self._kept = points
        self._scan = _NearestByScan(points)
        self._anchor: np.ndarray | None = None
        self._anchor_step = self._radius = math.inf

    def _keep(self, x: np.ndarray, fx: float, step: float) -> None:
        radius = fx + 6.0 * step
        # The new ball lies inside the kept one when |x - a| + radius <= the kept radius: filter those.
        source = (
            self._kept
            if self._anchor is not None and float(np.linalg.norm(x - self._anchor)) + radius <= self._radius
            else self._all
        )
        offset = source - x
        # Rounding of the squared distances (~1e-16 relative) must never drop a point on the ball's edge.
        bound = radius * (1.0 + 1e-9) + 1e-12
        self._kept = source[np.einsum("ij,ij->i", offset, offset) <= bound * bound]
        self._scan = _NearestByScan(self._kept)
        self._anchor, self._anchor_step, self._radius = x.copy(), step, bound

    def distances(self, trial: np.ndarray, x: np.ndarray, fx: float, step: float) -> np.ndarray:
        """(K,) distances of the ``trial`` points (K, D), each within ``step`` of ``x`` (distance ``fx``
        to its nearest point), to their nearest points; ``fx`` infinite (the search's first query, of
        its start point) scans the points kept so far."""
        if math.isfinite(fx):
            valid = (
                self._anchor is not None and float(np.linalg.norm(x - self._anchor)) + step <= 3.0 * self._anchor_step
            )
            if not valid or step < self._anchor_step:
                self._keep(x, fx, step)
        return np.asarray(self._scan.query(trial)[0])


def background_descriptor(descriptors: np.ndarray, grid_points: int = 1000) -> np.ndarray:
    """The point of the unit cube [0, 1]^D that maximises the distance to the nearest descriptor.

    Two stages, because nearest-neighbour queries far from the data visit most of a k-d tree:

    1. On a subset with one descriptor per cell of side 1/64 (every descriptor lies within
       ``delta = sqrt(D)/64`` of the subset): evaluate all corners of the cube (the optimum is often
       one; 4096 random corners for D > 12) and a regular grid of about ``grid_points`` points
       (random points for D > 8, seeded, so the result is deterministic), then refine the best 4 by
       compass search (steps down to 1/256).
    2. Exactly, for the best 2 of those (once where both searches ended at the same point): every
       descriptor that can be the nearest one to a point within ``s = sqrt(D)/64`` of it lies in a
       ball (radius = subset distance + 2 s), so distances to that ball are exact; compass search
       within that reach down to steps of 1e-4, scanning the ever fewer points that can be nearest
       to its next trials (:class:`_NearestAround`).

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
    coarse_points = points[np.sort(first)]
    coarse_tree = cKDTree(coarse_points, balanced_tree=False)

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
    coarse_nearest = _Nearest(coarse_points, coarse_tree)
    coarse = [_compass_search(coarse_nearest, s, 0.5 / (per_axis - 1), cell / 4) for s in starts]
    coarse.sort(key=lambda item: -item[1])

    reach = cell
    best_point, best_distance = None, -1.0
    searched: list[np.ndarray] = []
    for x0, r0 in coarse[:2]:
        if any(np.array_equal(x0, s) for s in searched):
            continue  # the coarse searches met: the same start gives the same result
        searched.append(x0)
        offset = points - x0
        radius = r0 + 2 * reach * math.sqrt(dim)
        near = points[np.einsum("ij,ij->i", offset, offset) <= radius * radius]
        x, fx = _compass_search(_NearestAround(near), x0, cell, 1e-4, center=x0, reach=reach)
        if fx > best_distance:
            best_point, best_distance = x, fx
    return best_point.astype(np.float32)


def embed(
    mesh: trimesh.Trimesh | ObjectModel,
    dim: int = 3,
    symmetric: bool = True,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
    components: Literal["error", "largest"] = "error",
    method: Literal["auto", "direct", "multilevel"] = "auto",
) -> DescriptorField:
    """Optimal ``dim``-dimensional descriptors of a mesh's vertices (docs/background.md, "Optimal
    descriptors"; Kupcsik et al. 2021).

    The eigenvectors of the smallest non-zero eigenvalues of ``L y = lambda M y`` are the smoothest
    functions on the surface. With ``symmetric``, consecutive eigenvalues equal within the relative
    ``tolerance`` form a group replaced by the sum of squares of its eigenvectors (independent of the
    eigenspace's basis, invariant under the symmetry); more eigenpairs are computed until ``dim``
    groups are closed (the last one's end confirmed by a following, different eigenvalue). The mesh
    is centred and scaled to unit area first, so descriptors do not depend on its size or position.

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
        method: eigensolver, see :func:`~don_gym.descriptors.eigensolver.laplacian_eigenpairs`.

    Returns:
        A :class:`DescriptorField`.

    Raises:
        MeshError: empty mesh, NaN/infinite vertices, zero area, several pieces (with
            ``components="error"``), or too few vertices to give ``dim`` descriptor functions.
    """
    # Every argument is checked before the mesh: a wrong type is a DonGymError naming it, not a TypeError.
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
        raise DonGymError(f"dim={dim!r}: expected an integer >= 1")
    if not isinstance(symmetric, (bool, np.bool_)):
        raise DonGymError(f"symmetric={symmetric!r}: expected True or False")
    number = isinstance(tolerance, (int, float, np.integer, np.floating)) and not isinstance(tolerance, bool)
    if not (number and math.isfinite(tolerance) and 0 <= tolerance < 1):
        raise DonGymError(f"tolerance={tolerance!r}: expected a relative tolerance in [0, 1)")
    if not isinstance(components, str) or components not in ("error", "largest"):
        raise DonGymError(f"components={components!r}: expected 'error' or 'largest'")
    if not isinstance(method, str) or method not in ("auto", "direct", "multilevel"):
        raise DonGymError(f"method={method!r}: expected 'auto', 'direct' or 'multilevel'")
    vertices, faces, digest = mesh_arrays(mesh)
    n_all = len(vertices)

    # Choose the piece to embed.
    _, label = mesh_components(n_all, faces)
    referenced = np.zeros(n_all, dtype=bool)
    referenced[faces.ravel()] = True
    piece_labels = np.flatnonzero(np.bincount(label[faces[:, 0]]))
    if len(piece_labels) > 1:
        area_per_label = np.bincount(label[faces[:, 0]], face_areas(vertices, faces), minlength=label.max() + 1)
        largest = int(np.argmax(area_per_label))
        if components == "error":
            share = area_per_label[largest] / max(area_per_label.sum(), 1e-300)
            raise SeveralPiecesError(
                f"mesh has {len(piece_labels)} connected components (the largest has {share:.0%} of the area); "
                "the Laplacian then has one zero eigenvalue per component and no single embedding",
                "Pass components='largest' to embed the largest component only"
                + (
                    " or merge duplicate vertices first (load_object does)"
                    if len(piece_labels) > len(faces) / 4
                    else ""
                ),
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
        w, Y, mass, solver = mesh_eigenpairs(sub_vertices, sub_faces, count, method, cache)
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
