"""Benchmark: time and accuracy of don_gym.descriptors.embed against the direct eigensolver.

Baseline ("direct"): robust_laplacian on the mesh as given and ``eigsh(L, k, M=M, sigma=-1e-8)``, the
standard solve (docs/background.md, section "Optimal descriptors"); compared: ``embed(method="direct")``
and ``embed()``, timed best of ``--repeats`` interleaved runs, and the largest difference of their
descriptors (modulo the basis of repeated eigenvalues for plain eigenmaps). Meshes: the bunny
Loop-subdivided and the toolcap with split triangles, then families the solver was not tuned on:
ellipsoids, spheres, scan-like and CAD-like meshes (``--quick``: the smaller ones). Writes the
"descriptors" section of benchmarks/RESULTS.md (unless --no-record).
"""

from __future__ import annotations

import os

# One BLAS thread unless the caller says otherwise (before numpy loads OpenBLAS): on a shared
# 2-core machine whose cores are busy with other work, multi-threaded OpenBLAS waits for its
# descheduled worker thread on every call (measured here: a 27x27 eigh 22 ms instead of 0.07 ms),
# which would time the scheduler rather than the eigensolvers.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import importlib  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import robust_laplacian  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402
import trimesh  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import record_section  # noqa: E402

from don_gym import descriptors as D  # noqa: E402
from don_gym.descriptors import eigensolver  # noqa: E402
from don_gym.objects import toolcap_mesh  # noqa: E402


def split_triangles(mesh: trimesh.Trimesh, n: int) -> trimesh.Trimesh:
    """Split every edge into ``n`` equal parts and every triangle into ``n^2`` (geometry unchanged)."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    lattice = [(i, j) for i in range(n + 1) for j in range(n + 1 - i)]
    index = {ij: k for k, ij in enumerate(lattice)}
    bary = np.array([(n - i - j, i, j) for i, j in lattice], dtype=np.float64) / n
    local = []
    for i in range(n):
        for j in range(n - i):
            local.append((index[i, j], index[i + 1, j], index[i, j + 1]))
            if i + j < n - 1:
                local.append((index[i + 1, j], index[i + 1, j + 1], index[i, j + 1]))
    local = np.asarray(local)
    points = np.einsum("pk,fkd->fpd", bary, vertices[faces]).reshape(-1, 3)
    new_faces = (local[None] + (np.arange(len(faces)) * len(lattice))[:, None, None]).reshape(-1, 3)
    out = trimesh.Trimesh(points, new_faces, process=False)
    out.merge_vertices(digits_vertex=10)  # shared edge points coincide up to rounding
    return out


def bunny() -> trimesh.Trimesh:
    import pybullet_data

    path = os.path.join(pybullet_data.getDataPath(), "bunny.obj")
    mesh = trimesh.load(path, force="mesh", process=False)
    mesh.merge_vertices()
    return mesh


def loop_subdivided(mesh: trimesh.Trimesh, levels: int) -> trimesh.Trimesh:
    vertices, faces = trimesh.remesh.subdivide_loop(mesh.vertices, mesh.faces, iterations=levels)
    return trimesh.Trimesh(vertices, faces, process=False)


# Mesh families the multilevel solver was not tuned on, built offline (trimesh.creation, the bunny).


def ellipsoid(subdivisions: int, axes: tuple[float, float, float] = (1.0, 0.75, 0.55)) -> trimesh.Trimesh:
    """Smooth ellipsoid: an icosphere scaled along x, y, z (distinct first eigenvalues, each
    eigenvector odd or even under the three mirror planes)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return trimesh.Trimesh(np.asarray(sphere.vertices) * np.asarray(axes), sphere.faces, process=False)


def icosphere(subdivisions: int) -> trimesh.Trimesh:
    """Unit sphere (eigenvalues l(l+1), repeated 2l+1 = 3, 5, 7, ... times)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return trimesh.Trimesh(sphere.vertices, sphere.faces, process=False)


def uv_sphere(count: int) -> trimesh.Trimesh:
    """Unit sphere of ``count`` latitude x longitude lines: fans of thin triangles at the poles."""
    sphere = trimesh.creation.uv_sphere(count=[count, count])
    sphere.merge_vertices()
    return trimesh.Trimesh(sphere.vertices, sphere.faces, process=False)


def scanned_sphere(points: int, noise: float = 0.2, seed: int = 0) -> trimesh.Trimesh:
    """Scan-like sphere: ``points`` uniformly random points (irregular sampling: no minimum spacing)
    triangulated by their convex hull, then moved radially by Gaussian noise of ``noise`` times the
    mean spacing."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(points, 3))
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    faces = ConvexHull(vertices).simplices
    normal = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    inward = np.einsum("ij,ij->i", normal, vertices[faces].mean(axis=1)) < 0
    faces[inward] = faces[inward][:, ::-1]
    spacing = math.sqrt(4 * math.pi / points)
    vertices *= (1.0 + noise * spacing * rng.standard_normal(points))[:, None]
    return trimesh.Trimesh(vertices, faces, process=False)


def scanned_bunny(levels: int, jitter: float = 0.3, noise: float = 0.15, seed: int = 0) -> trimesh.Trimesh:
    """Scan-like bunny: Loop-subdivided, every vertex moved along the surface by up to ``jitter`` and
    along its normal by Gaussian noise of ``noise`` times the mean edge length (irregular sampling,
    rough surface, some nearly flat triangles)."""
    mesh = loop_subdivided(bunny(), levels)
    rng = np.random.default_rng(seed)
    normals = np.asarray(mesh.vertex_normals)
    edge = float(mesh.edges_unique_length.mean())
    tangent = rng.standard_normal((len(mesh.vertices), 3))
    tangent -= np.einsum("ij,ij->i", tangent, normals)[:, None] * normals
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    shift = jitter * edge * rng.random((len(tangent), 1)) * tangent
    shift += noise * edge * rng.standard_normal((len(tangent), 1)) * normals
    return trimesh.Trimesh(np.asarray(mesh.vertices) + shift, mesh.faces, process=False)


def _revolved(profile: list[tuple[float, float]], sections: int) -> trimesh.Trimesh:
    mesh = trimesh.creation.revolve(np.asarray(profile), sections=sections)
    mesh.merge_vertices()
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def cad_cylinder(sections: int, rows: int = 6, rings: int = 4, radius: float = 1.0, height: float = 3.0):
    """CAD-like closed cylinder: many sections around, ``rows`` rows along the side (long slivers,
    aspect ratio ~ height sections / (2 pi radius rows)) and ``rings`` rings on the caps (fans of
    thin triangles at their centres)."""
    profile = [(0.0, -height / 2)]
    profile += [(radius * k / rings, -height / 2) for k in range(1, rings + 1)]
    profile += [(radius, -height / 2 + height * k / rows) for k in range(1, rows + 1)]
    profile += [(radius * (rings - k) / rings, height / 2) for k in range(1, rings + 1)]
    return _revolved(profile, sections)


def cad_shaft(rows: int, sections: int = 24, radius: float = 0.02, length: float = 1.0) -> trimesh.Trimesh:
    """CAD-like long thin shaft (length 50 diameters) meshed finely along its length, with flat
    caps as fans; few vertices around."""
    profile = [(0.0, -length / 2), (radius, -length / 2)]
    profile += [(radius, -length / 2 + length * k / rows) for k in range(1, rows + 1)]
    profile += [(0.0, length / 2)]
    return _revolved(profile, sections)


def fan_box(per_unit: float, extents: tuple[float, float, float] = (1.0, 0.6, 0.4)) -> trimesh.Trimesh:
    """CAD-like box: each face's boundary sampled ``per_unit`` points per unit length and the face
    triangulated as one fan from its centre (needles; every vertex but the centres on an edge)."""
    half = np.asarray(extents) / 2
    index: dict[tuple[float, ...], int] = {}
    points: list[np.ndarray] = []

    def vertex(p: np.ndarray) -> int:
        key = tuple(np.round(p, 9))
        if key not in index:
            index[key] = len(points)
            points.append(p)
        return index[key]

    faces = []
    for axis in range(3):
        u, w = [a for a in range(3) if a != axis]
        counts = {u: max(2, round(per_unit * 2 * half[u])), w: max(2, round(per_unit * 2 * half[w]))}
        for side in (-1.0, 1.0):
            corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
            loop = []
            for (a0, b0), (a1, b1) in zip(corners, corners[1:] + corners[:1], strict=True):
                n = counts[u] if a0 != a1 else counts[w]
                for k in range(n):
                    p = np.zeros(3)
                    p[axis] = side * half[axis]
                    p[u] = (a0 + (a1 - a0) * k / n) * half[u]
                    p[w] = (b0 + (b1 - b0) * k / n) * half[w]
                    loop.append(vertex(p))
            centre = np.zeros(3)
            centre[axis] = side * half[axis]
            c = vertex(centre)
            faces += [(c, loop[i], loop[(i + 1) % len(loop)]) for i in range(len(loop))]
    mesh = trimesh.Trimesh(np.asarray(points), np.asarray(faces), process=False)
    trimesh.repair.fix_winding(mesh)
    return mesh


def direct_baseline(mesh: trimesh.Trimesh, dim: int, symmetric: bool, count: int):
    """The direct baseline + embed's descriptor construction; returns (descriptors, groups).

    robust_laplacian.mesh_laplacian on the mesh as given, then ``scipy.sparse.linalg.eigsh(L, k, M=M,
    sigma=-1e-8)`` (shift-invert Lanczos, SuperLU) on the full mesh, with k = ``count`` eigenpairs after
    the constant one, followed by the same descriptor construction and background search as embed.
    """
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    L, M = robust_laplacian.mesh_laplacian(vertices, faces, mollify_factor=1e-5)
    w, Y = spla.eigsh(L, count + 1, M=M, sigma=-1e-8)
    order = np.argsort(w)
    w, Y = w[order][1:], Y[:, order][:, 1:]
    normalized, _ = D.normalize_to_unit_area(vertices, faces)  # for the sign rule's fall-back only
    result = D.descriptor_functions(w, Y, M.diagonal(), normalized, dim, symmetric, D.DEFAULT_TOLERANCE)
    if result is None:
        return None, None
    descriptors, groups = result
    D.background_descriptor(descriptors)
    return descriptors, groups


def reference_eigenpairs(mesh: trimesh.Trimesh, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(eigenvalues, eigenvectors, lumped mass) of the baseline's problem, ``count`` after the constant one."""
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    L, M = robust_laplacian.mesh_laplacian(vertices, faces, mollify_factor=1e-5)
    w, Y = spla.eigsh(L, count + 1, M=M, sigma=-1e-8)
    order = np.argsort(w)
    return w[order][1:], Y[:, order][:, 1:], M.diagonal()


def difference_modulo_basis(
    descriptors: np.ndarray, baseline: np.ndarray, mesh: trimesh.Trimesh, extra: int = 8
) -> tuple[float, bool]:
    """Largest |embed - direct| of plain Laplacian Eigenmaps, where a repeated eigenvalue's
    eigenvectors are any orthonormal basis of its eigenspace (a sphere's first 3, 5, 7, ...; nearly
    so on a scanned sphere): a dimension whose eigenvalue is in a group (D.group_eigenvalues) is
    compared with its best fit (mass-weighted least squares) by a constant plus the direct
    solver's eigenvectors of the whole group, which is the same normalised function whatever the
    basis. Returns ``(difference, whether any dimension was in a group)``."""
    dim = descriptors.shape[1]
    w, Y, mass = reference_eigenpairs(mesh, dim + extra)
    weight = np.sqrt(mass)[:, None]
    difference, grouped = 0.0, False
    for group in D.group_eigenvalues(w):
        for d in (i for i in group if i < dim):
            if len(group) == 1:
                difference = max(difference, float(np.abs(descriptors[:, d] - baseline[:, d]).max()))
                continue
            grouped = True
            basis = np.column_stack([np.ones(len(mass)), Y[:, list(group)]])
            coefficients, *_ = np.linalg.lstsq(weight * basis, weight[:, 0] * descriptors[:, d], rcond=None)
            difference = max(difference, float(np.abs(basis @ coefficients - descriptors[:, d]).max()))
    return difference, grouped


@contextlib.contextmanager
def robust_fine_level() -> Iterator[None]:
    """embed as for a mesh that fails the cotangent Laplacian's gate (fine level: the intrinsic-Delaunay
    Laplacian of ``mesh_laplacian``)."""
    # Patched where the multilevel solver looks it up.
    gate = eigensolver.cotan_laplacian
    eigensolver.cotan_laplacian = lambda *args, **kwargs: None
    try:
        yield
    finally:
        eigensolver.cotan_laplacian = gate


#: embed's stages for :func:`embed_stages`: (stage, module, functions timed as that stage). A call made
#: inside another timed call counts towards the outer one (robust_laplacian's pass inside the fine
#: level's `_robust`).
STAGES: list[tuple[str, str, tuple[str, ...]]] = [
    ("checks & hash", "don_gym.descriptors.embed", ("mesh_arrays",)),
    ("pieces & unit area", "don_gym.descriptors.embed", ("mesh_components", "face_areas", "normalize_to_unit_area")),
    ("fine Laplacian", "don_gym.descriptors.eigensolver", ("cotan_laplacian", "_robust")),
    (
        "coarse levels",
        "don_gym.descriptors.eigensolver",
        ("_coarsen", "_drop_unreferenced", "mesh_components", "mesh_laplacian"),
    ),
    ("eigensolve", "don_gym.descriptors.eigensolver", ("_direct_eigenpairs", "_lobpcg", "_Level._prepare")),
    ("descriptors & background", "don_gym.descriptors.embed", ("descriptor_functions", "background_descriptor")),
]


#: The targets (>= 5x, <= 0.02) apply to meshes with at least this many vertices.
TARGET_MIN_VERTICES = 35_000


def stage_targets() -> list[tuple[str, object, str]]:
    """(stage, owner, attribute) of every function of :data:`STAGES`: the module or class where embed's
    modules look it up, and its name there."""
    targets = []
    for stage, module_name, names in STAGES:
        module = importlib.import_module(module_name)
        for name in names:
            owner, _, attribute = name.rpartition(".")
            targets.append((stage, getattr(module, owner) if owner else module, attribute))
    return targets


@contextlib.contextmanager
def stage_timer(spent: dict[str, float]) -> Iterator[None]:
    """Adds the wall-clock seconds of each of :data:`STAGES` spent inside the block to ``spent``, by
    wrapping the functions where embed's modules look them up."""
    depth = [0]
    patched: list[tuple[object, str, object]] = []

    def timed(stage: str, fn: Callable) -> Callable:
        def wrapper(*args, **kwargs):
            if depth[0]:
                return fn(*args, **kwargs)
            depth[0] += 1
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[stage] = spent.get(stage, 0.0) + time.perf_counter() - start
                depth[0] -= 1

        return wrapper

    try:
        for stage, target, attribute in stage_targets():
            original = getattr(target, attribute)
            patched.append((target, attribute, original))
            setattr(target, attribute, timed(stage, original))
        yield
    finally:
        for target, attribute, original in reversed(patched):
            setattr(target, attribute, original)


def embed_stages(mesh: trimesh.Trimesh, dim: int, symmetric: bool) -> dict[str, float]:
    """Seconds of one ``embed(mesh, dim, symmetric)`` per stage of :data:`STAGES`, its ``total`` and
    ``other`` (what no stage covers: argument checks, the descriptor field's assembly)."""
    spent: dict[str, float] = {}
    with stage_timer(spent):
        start = time.perf_counter()
        D.embed(mesh, dim, symmetric)
        spent["total"] = time.perf_counter() - start
    spent["other"] = spent["total"] - sum(spent.get(stage, 0.0) for stage, _, _ in STAGES)
    return spent


def compare_laplacians(name: str, vertices: np.ndarray, faces: np.ndarray, repeats: int) -> dict[str, object]:
    """robust_laplacian's Laplacian against don_gym's ``mesh_laplacian`` on the unit-area mesh: best
    times of ``repeats`` interleaved runs, which path computed don_gym's, and the largest difference
    of L (relative to its largest entry) and of M (relative to its largest entry)."""
    normalized, _ = D.normalize_to_unit_area(vertices, faces)
    robust_s = own_s = np.inf
    for _ in range(repeats):
        t, (L_robust, M_robust) = best_time(
            partial(robust_laplacian.mesh_laplacian, normalized, faces, mollify_factor=D.MOLLIFY_FACTOR), 1
        )
        robust_s = min(robust_s, t)
        t, (L_own, mass_own) = best_time(partial(D.mesh_laplacian, normalized, faces), 1)
        own_s = min(own_s, t)
    mass_robust = M_robust.diagonal()
    return {
        "mesh": name,
        "vertices": len(vertices),
        "path": "flips" if D.intrinsic_delaunay_laplacian(normalized, faces) is not None else "robust",
        "robust_s": robust_s,
        "own_s": own_s,
        "L_difference": float(abs(L_own - L_robust).max() / abs(L_robust).max()),
        "M_difference": float(np.abs(mass_own - mass_robust).max() / mass_robust.max()),
    }


def best_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="only meshes of up to ~50k vertices, one repeat")
    parser.add_argument("--repeats", type=int, default=2, help="timed runs per method and mesh (best is kept)")
    parser.add_argument("--dim", type=int, default=3, help="descriptor dimensions (default 3)")
    parser.add_argument("--no-record", action="store_true", help="print only; do not update benchmarks/RESULTS.md")
    args = parser.parse_args(argv)
    repeats = 1 if args.quick else max(1, args.repeats)

    # Bunny Loop-subdivided 2-4 times (7k, 29k, 115k vertices); toolcap with each triangle split into n^2
    # (17k, 38k, 152k vertices; flat splitting keeps its exact 64-fold rotational symmetry); then families
    # the solver was not tuned on (see their builders). Symmetric (GISIF) descriptors do not depend on the
    # basis of repeated eigenvalues; plain Laplacian Eigenmaps are compared modulo that basis
    # (difference_modulo_basis). Spheres have no symmetric descriptors (every merged group is constant;
    # embed refuses them), so only plain ones there.
    cases: list[tuple[str, Callable[[], trimesh.Trimesh], list[bool], bool]] = [
        ("bunny, Loop x2", lambda: loop_subdivided(bunny(), 2), [True, False], True),
        ("toolcap, split 2", lambda: split_triangles(toolcap_mesh(), 2), [True], True),
        ("bunny, Loop x3", lambda: loop_subdivided(bunny(), 3), [True, False], True),
        ("toolcap, split 3", lambda: split_triangles(toolcap_mesh(), 3), [True], True),
        ("bunny, Loop x4", lambda: loop_subdivided(bunny(), 4), [True, False], False),
        ("toolcap, split 6", lambda: split_triangles(toolcap_mesh(), 6), [True], False),
        ("ellipsoid, icosphere 6", lambda: ellipsoid(6), [True, False], True),
        ("ellipsoid, icosphere 7", lambda: ellipsoid(7), [True], False),
        ("sphere, icosphere 6", lambda: icosphere(6), [False], True),
        ("sphere, UV 150", lambda: uv_sphere(150), [False], False),
        ("scanned sphere, 50k points", lambda: scanned_sphere(50_000), [False], False),
        ("scanned bunny, Loop x4", lambda: scanned_bunny(4), [True, False], False),
        ("CAD cylinder, 4096 sections", lambda: cad_cylinder(4096), [True], False),
        ("CAD shaft, 2000 rows", lambda: cad_shaft(2000), [True], True),
        ("CAD box, fans", lambda: fan_box(5000), [True], False),
    ]
    if args.quick:
        cases = [case for case in cases if case[3]]

    rows, laplacian_rows = [], []
    for name, make, modes, _ in tqdm(cases, desc="meshes", unit="mesh"):
        mesh = make()
        vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        laplacian_rows.append(compare_laplacians(name, vertices, faces, repeats))
        for symmetric in modes:
            embed_time = direct_time = own_direct_time = robust_time = background_time = np.inf
            field = baseline = groups = robust_field = None
            stages: dict[str, float] = {"total": np.inf}
            for _ in range(repeats):  # interleaved, so that load from other work hits all alike
                t, field = best_time(partial(D.embed, mesh, args.dim, symmetric, method="auto"), 1)
                embed_time = min(embed_time, t)
                # The fewest eigenpairs that reproduce embed's groups: one past the last used
                # (confirming its group's end) for symmetric descriptors.
                count = len(field.eigenvalues) + (1 if symmetric else 0)
                t, (baseline, groups) = best_time(partial(direct_baseline, mesh, args.dim, symmetric, count), 1)
                direct_time = min(direct_time, t)
                t, _ = best_time(partial(D.embed, mesh, args.dim, symmetric, method="direct"), 1)
                own_direct_time = min(own_direct_time, t)
                if field.solver == "multilevel":
                    with robust_fine_level():
                        t, robust_field = best_time(partial(D.embed, mesh, args.dim, symmetric, method="auto"), 1)
                    robust_time = min(robust_time, t)
                t, _ = best_time(partial(D.background_descriptor, field.vertex_descriptors), 1)
                background_time = min(background_time, t)
                if len(mesh.vertices) >= TARGET_MIN_VERTICES:
                    run = embed_stages(mesh, args.dim, symmetric)
                    stages = run if run["total"] < stages["total"] else stages
            grouped = False
            if baseline is None:
                difference = robust_difference = float("nan")
                same_groups = False
            elif symmetric:
                difference = float(np.abs(field.vertex_descriptors - baseline).max())
                same_groups = [tuple(g) for g in groups] == [tuple(g) for g in field.groups]
                robust_difference = (
                    float(np.abs(robust_field.vertex_descriptors - baseline).max()) if robust_field else float("nan")
                )
            else:
                difference, grouped = difference_modulo_basis(field.vertex_descriptors, baseline, mesh)
                same_groups = [tuple(g) for g in groups] == [tuple(g) for g in field.groups]
                robust_difference = (
                    difference_modulo_basis(robust_field.vertex_descriptors, baseline, mesh)[0]
                    if robust_field
                    else float("nan")
                )
            normalized, _ = D.normalize_to_unit_area(vertices, faces)
            # A mesh that fails the gate gets mesh_laplacian's path, found once per mesh by compare_laplacians.
            fine_level = "cotan" if D.cotan_laplacian(normalized, faces) is not None else laplacian_rows[-1]["path"]
            rows.append(
                {
                    "mesh": name,
                    "vertices": len(mesh.vertices),
                    "symmetric": symmetric,
                    "solver": field.solver,
                    "eigenpairs": count,
                    "direct_s": direct_time,
                    "own_direct_s": own_direct_time,
                    "embed_s": embed_time,
                    "background_s": background_time,
                    "robust_s": robust_time,
                    "robust_difference": robust_difference,
                    "fine_level": fine_level if field.solver == "multilevel" else "-",
                    "difference": difference,
                    "modulo_basis": grouped,
                    "same_groups": same_groups,
                    "groups": field.groups,
                    "stages": stages,
                }
            )

    lines = [
        f"Descriptor dimension {args.dim}, tolerance {D.DEFAULT_TOLERANCE}; times are wall-clock seconds, "
        f"best of {repeats} interleaved run(s), each including the Laplacian, eigenpairs, descriptors and "
        f"background; BLAS threads: {os.environ.get('OPENBLAS_NUM_THREADS')} (OPENBLAS_NUM_THREADS). "
        "*direct* = robust-laplacian + `eigsh(L, k, M=M, sigma=-1e-8)` on the mesh as given "
        '(the standard solve, docs/background.md, section "Optimal descriptors"); *embed direct* = '
        "`embed(method='direct')`; *embed* = `embed()` (multilevel "
        f"solver from {D.DIRECT_MAX_VERTICES} vertices; *fine level* = the Laplacian its refinement used: "
        "`cotan` when the mesh passes the gate of `cotan_laplacian` (maximum angle, no long non-Delaunay edge), "
        "else the intrinsic-Delaunay Laplacian of `mesh_laplacian`: `flips` where don_gym's own edge flips "
        "compute it (closed, oriented manifold meshes), `robust` where robust_laplacian does; *embed solver* "
        "`direct` on a "
        "multilevel-sized mesh = the multilevel solver failed and embed fell back to the direct one). "
        "*background s* = the background search alone, part of both *direct s* and *embed s*. Max diff = "
        "largest |embed - direct| of the normalised descriptors over all vertices and dimensions; marked "
        "*mod basis* where a plain (non-symmetric) dimension belongs to a repeated eigenvalue, whose "
        "eigenvectors are any basis of its eigenspace: that dimension is compared with its best fit by a "
        "constant plus the direct solver's eigenvectors of the whole group. *embed, robust fine* "
        "= embed with the intrinsic-Delaunay Laplacian (`mesh_laplacian`) of the whole mesh on the fine level, "
        "as a mesh that fails the gate gets.",
        "",
        "| mesh | vertices | symmetric | k | groups | embed solver | fine level | direct s | embed direct s "
        "| embed s | background s | speed-up vs direct | max diff | embed, robust fine s | its speed-up "
        "| its max diff | same groups |",
        "|---|---:|---|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        groups = " ".join("(" + ",".join(str(i + 1) for i in g) + ")" for g in r["groups"])
        lines.append(
            f"| {r['mesh']} | {r['vertices']} | {'yes' if r['symmetric'] else 'no'} | {r['eigenpairs']} | {groups} "
            f"| {r['solver']} | {r['fine_level']} | {r['direct_s']:.2f} | {r['own_direct_s']:.2f} | {r['embed_s']:.2f} "
            f"| {r['background_s']:.2f} | {r['direct_s'] / r['embed_s']:.1f}x | {r['difference']:.4f}"
            + (" mod basis " if r["modulo_basis"] else " ")
            + (
                f"| {r['robust_s']:.2f} | {r['direct_s'] / r['robust_s']:.1f}x | {r['robust_difference']:.4f} "
                if np.isfinite(r["robust_s"])
                else "| - | - | - "
            )
            + f"| {'yes' if r['same_groups'] else 'NO'} |"
        )
    large = [r for r in rows if r["vertices"] >= TARGET_MIN_VERTICES]
    if large:
        worst = min(r["direct_s"] / r["embed_s"] for r in large)
        worst_diff = max(r["difference"] for r in large)
        missed = [
            f"{r['mesh']}{'' if r['symmetric'] else ' (plain)'} {r['direct_s'] / r['embed_s']:.1f}x, "
            f"{r['difference']:.4f}, fine level {r['fine_level']}, solver {r['solver']}"
            for r in large
            if r["direct_s"] / r["embed_s"] < 5.0 or not r["difference"] <= 0.02
        ]
        with_robust = [r["direct_s"] / r["robust_s"] for r in large if np.isfinite(r["robust_s"])]
        lines += [
            "",
            f"Meshes with >= 35k vertices: smallest speed-up {worst:.1f}x (target >= 5x), largest descriptor "
            f"difference {worst_diff:.4f} (target <= 0.02). "
            + (f"Below a target: {'; '.join(missed)}. " if missed else "Every one meets both targets. ")
            + (
                f"With the intrinsic-Delaunay Laplacian on the fine level (meshes that fail the gate): smallest "
                f"speed-up {min(with_robust):.1f}x."
                if with_robust
                else ""
            ),
        ]
    if large:  # every one has its stages
        names = [stage for stage, _, _ in STAGES] + ["other"]
        lines += [
            "",
            "**Where embed's time goes** (meshes with >= 35k vertices; the stages of the fastest of the same "
            "number of instrumented embed runs, seconds): *budget* = *direct s* / 5, the time embed has for "
            "the 5x target; *checks & hash* = validating the mesh and its content hash; *pieces & unit area* = "
            "connected pieces, centring and scaling; *fine Laplacian* = `cotan_laplacian` or, where the mesh "
            "fails its gate, the intrinsic-Delaunay Laplacian; *coarse levels* = clustering, prolongation and "
            "the coarse meshes' Laplacians; *eigensolve* = coarsest direct solve, two-grid set-up and LOBPCG "
            "refinement; *descriptors & background* = groups, sign rule, normalisation and the background "
            "search, the same step as the direct baseline's last one; *other* = the rest.",
            "",
            "| mesh | symmetric | direct s | budget s | embed s | " + " | ".join(f"{n} s" for n in names) + " |",
            "|---|---|---:|---:|---:|" + "---:|" * len(names),
        ]
        for r in large:
            st = r["stages"]
            lines.append(
                f"| {r['mesh']} | {'yes' if r['symmetric'] else 'no'} | {r['direct_s']:.3f} | {r['direct_s'] / 5:.3f} "
                f"| {st['total']:.3f} | " + " | ".join(f"{st.get(n, 0.0):.3f}" for n in names) + " |"
            )
    lines += [
        "",
        "**The Laplacian alone** (unit-area mesh, best of the same runs): robust_laplacian's against "
        "`mesh_laplacian`, which computes the same operator with don_gym's own intrinsic edge flips on closed, "
        "oriented manifold meshes (*path* `flips`) and calls robust_laplacian on others (`robust`); differences "
        "relative to the largest entry of L and of M.",
        "",
        "| mesh | vertices | path | robust_laplacian s | mesh_laplacian s | speed-up | L diff | M diff |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in laplacian_rows:
        lines.append(
            f"| {r['mesh']} | {r['vertices']} | {r['path']} | {r['robust_s']:.3f} | {r['own_s']:.3f} "
            f"| {r['robust_s'] / r['own_s']:.1f}x | {r['L_difference']:.1e} | {r['M_difference']:.1e} |"
        )
    body = "\n".join(lines)
    print(body)
    if not args.no_record:
        record_section("descriptors", "Optimal descriptors: embed vs direct eigensolver", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
