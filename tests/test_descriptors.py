"""Tests of don_gym.descriptors: eigenpairs, symmetry merging (GISIF), invariances, I/O, errors."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import scipy.sparse as sp
import trimesh

from don_gym import descriptors as D
from don_gym.descriptors import DescriptorField, embed, interpolate_field
from don_gym.descriptors.eigensolver import mesh_eigenpairs
from don_gym.descriptors.embed import _fix_sign
from don_gym.errors import DonGymError, MeshError
from don_gym.objects import load_object

# ---------------------------------------------------------------- fixtures and helpers


@pytest.fixture(scope="module")
def toolcap():
    return load_object("toolcap")


@pytest.fixture(scope="module")
def bunny() -> trimesh.Trimesh:
    mesh = trimesh.load(os.path.join(pybullet_data.getDataPath(), "bunny.obj"), force="mesh", process=False)
    mesh.merge_vertices()
    return mesh


@pytest.fixture(scope="module")
def torus() -> trimesh.Trimesh:
    return trimesh.creation.torus(major_radius=1.0, minor_radius=0.4, major_sections=40, minor_sections=20)


@pytest.fixture(scope="module")
def cylinder() -> trimesh.Trimesh:
    """Closed cylinder, radius 1, height 3, 36 sections, profile sampled every ~0.15."""
    radius, height = 1.0, 3.0
    corners = np.array([[0.0, -height / 2], [radius, -height / 2], [radius, height / 2], [0.0, height / 2]])
    profile = [corners[0]]
    for start, end in zip(corners[:-1], corners[1:], strict=True):
        count = int(np.ceil(np.linalg.norm(end - start) / 0.15))
        profile += [start + (end - start) * k / count for k in range(1, count + 1)]
    mesh = trimesh.creation.revolve(np.asarray(profile), sections=36)
    mesh.merge_vertices()
    assert mesh.is_watertight
    return mesh


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def change_under_rotation(mesh: trimesh.Trimesh, descriptors: np.ndarray, angle: float, samples: int = 300) -> float:
    """Largest |d(R x) - d(x)| over sampled vertices x: R x is located on the mesh (closest point,
    barycentric coordinates) and the field interpolated there."""
    rng = np.random.default_rng(0)
    idx = rng.choice(len(mesh.vertices), size=min(samples, len(mesh.vertices)), replace=False)
    points = np.asarray(mesh.vertices)[idx] @ rotation_z(angle).T
    closest, _, triangle = trimesh.proximity.closest_point(mesh, points)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[triangle], closest)
    moved = interpolate_field(descriptors, mesh.faces, triangle, bary)
    return float(np.abs(moved - descriptors[idx]).max())


def permuted(mesh: trimesh.Trimesh, seed: int = 1) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The same mesh with vertices in random order; returns it and ``order`` (new i = old order[i])."""
    order = np.random.default_rng(seed).permutation(len(mesh.vertices))
    inverse = np.argsort(order)
    return trimesh.Trimesh(np.asarray(mesh.vertices)[order], inverse[np.asarray(mesh.faces)], process=False), order


# ---------------------------------------------------------------- eigenpairs and groups


def test_group_eigenvalues_uses_relative_tolerance():
    values = np.array([1.0, 1.005, 2.0, 2.001, 2.003, 3.0])
    assert D.group_eigenvalues(values, 1e-2) == [(0, 1), (2, 3, 4), (5,)]
    assert D.group_eigenvalues(values * 1e-6, 1e-2) == [(0, 1), (2, 3, 4), (5,)]  # scale-free
    assert D.group_eigenvalues(values, 1e-4) == [(0,), (1,), (2,), (3,), (4,), (5,)]


def test_unit_sphere_eigenvalues_come_in_groups_of_3_5_7_at_l_l_plus_1():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    values, vectors, _ = D.laplacian_eigenpairs(sphere.vertices, sphere.faces, 15)
    groups = D.group_eigenvalues(values)
    assert [len(g) for g in groups] == [3, 5, 7]
    for degree, group in zip((1, 2, 3), groups, strict=True):
        assert np.allclose(values[list(group)], degree * (degree + 1), rtol=0.02 if degree < 3 else 0.03)
    # M-orthonormal eigenvectors for the mesh's own mass matrix.
    _, mass = D.mesh_laplacian(np.asarray(sphere.vertices), np.asarray(sphere.faces))
    gram = vectors.T @ (mass[:, None] * vectors)
    assert np.allclose(gram, np.eye(15), atol=1e-6)


def test_sphere_groups_are_constant_and_skipped():
    # Sums of squares over a whole degree of spherical harmonics are constant: no information.
    # (What remains on a triangulated sphere are higher groups split by the icosahedral mesh.)
    sphere = trimesh.creation.icosphere(subdivisions=3)
    field = embed(sphere, 2, symmetric=True)
    assert min(min(g) for g in field.groups) >= 15  # the 3-, 5- and 7-groups (l = 1, 2, 3) are skipped
    plain = embed(sphere, 3, symmetric=False)
    assert plain.groups == ((0,), (1,), (2,))


# ---------------------------------------------------------------- symmetry


@pytest.mark.parametrize(
    ("name", "sections"),
    [("torus", 40), ("cylinder", 36), ("toolcap", 64)],
)
def test_symmetric_descriptors_are_invariant_under_rotation_about_the_axis(name, sections, request):
    fixture = request.getfixturevalue(name)
    mesh = fixture.mesh if name == "toolcap" else fixture
    # About 90 degrees plus half a section: maps no vertex onto a vertex.
    angle = (round(sections / 4) + 0.5) * 2 * np.pi / sections
    symmetric = embed(mesh, 3, symmetric=True)
    plain = embed(mesh, 3, symmetric=False)
    assert any(len(g) > 1 for g in symmetric.groups)  # a repeated eigenvalue was merged
    assert change_under_rotation(mesh, symmetric.vertex_descriptors, angle) < 0.03
    # Plain eigenvectors of a repeated eigenvalue are some basis of cos/sin-like functions.
    assert change_under_rotation(mesh, plain.vertex_descriptors, angle) > 0.3


def test_toolcap_groups_and_distinct_ends(toolcap):
    field = embed(toolcap)
    assert field.groups == ((0,), (1,), (2, 3))
    assert np.isclose(field.eigenvalues[2], field.eigenvalues[3], rtol=1e-6)
    z = toolcap.mesh.vertices @ toolcap.plus_axis
    open_end = field.vertex_descriptors[z < z.min() + 1e-4]
    flange_end = field.vertex_descriptors[z > z.max() - 1e-4]
    assert len(open_end) >= 64 and len(flange_end) >= 64
    gaps = np.linalg.norm(open_end[:, None, :] - flange_end[None, :, :], axis=2)
    assert gaps.min() > 0.5  # every open-end point is far from every flange-face point
    # Vertices on one ring (same height and radius) share one descriptor (64-fold symmetric mesh).
    radius = np.linalg.norm(toolcap.mesh.vertices[:, :2], axis=1)
    _, ring = np.unique(np.round(np.stack([z, radius], axis=1), 7), axis=0, return_inverse=True)
    ring = ring.ravel()
    for d in range(3):
        values = field.vertex_descriptors[:, d]
        spread = np.zeros(ring.max() + 1)
        np.maximum.at(spread, ring, values)
        low = np.full(ring.max() + 1, np.inf)
        np.minimum.at(low, ring, values)
        assert (spread - low).max() < 1e-4


# ---------------------------------------------------------------- invariances and reproducibility


def test_vertex_permutation_does_not_change_descriptors(toolcap, bunny):
    for mesh, symmetric in ((toolcap.mesh, True), (bunny, False)):
        reference = embed(mesh, 3, symmetric)
        shuffled_mesh, order = permuted(mesh)
        shuffled = embed(shuffled_mesh, 3, symmetric)
        assert np.abs(shuffled.vertex_descriptors - reference.vertex_descriptors[order]).max() < 1e-4
        assert np.allclose(shuffled.background, reference.background, atol=1e-3)


def test_scale_and_translation_do_not_change_descriptors(bunny):
    reference = embed(bunny, 4, symmetric=False)
    moved = bunny.copy()
    moved.apply_scale(1000.0)
    moved.apply_translation([5.0, -3.0, 2.0])
    field = embed(moved, 4, symmetric=False)
    assert np.abs(field.vertex_descriptors - reference.vertex_descriptors).max() < 1e-4
    assert np.allclose(field.eigenvalues, reference.eigenvalues * 1e-6, rtol=1e-6)


def test_field_hash_is_stable_and_tracks_content(toolcap):
    a, b = embed(toolcap), embed(toolcap)
    assert a.field_hash == b.field_hash and len(a.field_hash) == 16
    assert embed(toolcap, symmetric=False).field_hash != a.field_hash
    assert a.mesh_hash == toolcap.mesh_hash == D.mesh_content_hash(toolcap.mesh.vertices, toolcap.mesh.faces)


def test_multilevel_solver_matches_direct_and_is_order_independent(toolcap):
    # 17k vertices: each triangle split in four; flat, so the 64-fold symmetry stays exact.
    vertices, faces = trimesh.remesh.subdivide(toolcap.mesh.vertices, toolcap.mesh.faces)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    direct = embed(mesh, 3, method="direct")
    multilevel = embed(mesh, 3, method="multilevel")
    assert direct.solver == "direct" and multilevel.solver == "multilevel"
    assert multilevel.groups == direct.groups
    assert np.allclose(multilevel.eigenvalues, direct.eigenvalues, rtol=2e-3)
    assert np.abs(multilevel.vertex_descriptors - direct.vertex_descriptors).max() < 0.02
    shuffled_mesh, order = permuted(mesh)
    shuffled = embed(shuffled_mesh, 3, method="multilevel")
    assert np.abs(shuffled.vertex_descriptors - direct.vertex_descriptors[order]).max() < 0.02


def test_cotan_laplacian_is_robust_laplacian_on_a_delaunay_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=3)  # near-equilateral: intrinsically Delaunay
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    L, mass = D.cotan_laplacian(vertices, faces)
    L_robust, mass_robust = D.mesh_laplacian(vertices, faces)
    assert abs(L - L_robust).max() < 1e-4 * abs(L_robust).max()  # mollification only
    assert np.allclose(mass, mass_robust, rtol=1e-4)
    assert np.allclose(L @ np.ones(len(vertices)), 0.0, atol=1e-9)


def _noisy_sphere(bench_descriptors, points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The benchmark's scan-like sphere (closed, outward-wound, radial noise): many non-Delaunay edges."""
    mesh = bench_descriptors.scanned_sphere(points, seed=seed)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _robust_pair(vertices: np.ndarray, faces: np.ndarray):
    import robust_laplacian

    L, M = robust_laplacian.mesh_laplacian(vertices, faces, mollify_factor=D.MOLLIFY_FACTOR)
    return L, M.diagonal()


def test_intrinsic_flips_give_robust_laplacians_operator_on_a_closed_manifold_mesh(bench_descriptors):
    vertices, faces = _noisy_sphere(bench_descriptors, 600, seed=1)
    L_robust, mass_robust = _robust_pair(vertices, faces)
    # Long edges that are not locally Delaunay: the cotangent Laplacian refuses the mesh, flips are needed.
    assert D.cotan_laplacian(vertices, faces) is None
    L, mass = D.intrinsic_delaunay_laplacian(vertices, faces)
    off_diagonal = L - sp.diags(L.diagonal())
    assert off_diagonal.max() <= 1e-12  # Delaunay: no negative edge weight left
    assert abs(L - L_robust).max() < 1e-9 * abs(L_robust).max()
    assert np.allclose(mass, mass_robust, rtol=1e-9)
    assert (L - L.T).count_nonzero() == 0 and np.allclose(L @ np.ones(len(vertices)), 0.0, atol=1e-9)
    L_auto, mass_auto = D.mesh_laplacian(vertices, faces)  # the same pair, by the same path
    assert abs(L_auto - L).max() == 0 and np.array_equal(mass_auto, mass)


def test_intrinsic_flips_through_a_long_cascade_give_robust_laplacians_operator(bench_descriptors):
    # Faces fanned over collinear points: each needle becomes non-Delaunay only once its neighbour has
    # flipped, so the flips run through hundreds of rounds of a few edges each.
    mesh = bench_descriptors.fan_box(1250)
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
    L_robust, mass_robust = _robust_pair(vertices, faces)
    L, mass = D.intrinsic_delaunay_laplacian(vertices, faces)
    assert (L - sp.diags(L.diagonal())).max() <= 1e-6  # no weight below robust_laplacian's flip threshold
    assert abs(L - L_robust).max() < 1e-9 * abs(L_robust).max()
    # Rectangles of the ladders across each face are cocircular: which of their diagonals is kept moves
    # lumped mass between their corners, but not the total.
    assert np.abs(mass - mass_robust).max() < 1e-3 * mass_robust.max()
    assert mass.sum() == pytest.approx(mass_robust.sum(), rel=1e-9)


def _open_cap(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    faces = faces[vertices[faces].mean(axis=1)[:, 2] < 0.3]
    used, faces = np.unique(faces, return_inverse=True)
    return vertices[used], faces.reshape(-1, 3)


def _miswound(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    faces = faces.copy()
    faces[:5] = faces[:5, ::-1]
    return vertices, faces


def _two_spheres_at_a_vertex(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    shared = int(np.argmax(vertices[:, 0]))
    other = vertices.copy()
    other[:, 0] = 2 * vertices[shared, 0] - other[:, 0]  # mirrored through the plane x = x_shared
    other_faces = faces[:, ::-1] + len(vertices)
    other_faces[other_faces == shared + len(vertices)] = shared
    keep = np.setdiff1d(np.arange(2 * len(vertices)), [shared + len(vertices)])
    renumber = np.full(2 * len(vertices), -1)
    renumber[keep] = np.arange(len(keep))
    return np.vstack([vertices, other])[keep], renumber[np.vstack([faces, other_faces])]


@pytest.mark.parametrize("make", [_open_cap, _miswound, _two_spheres_at_a_vertex])
def test_meshes_where_the_tufted_cover_differs_go_to_robust_laplacian(bench_descriptors, make):
    vertices, faces = make(*_noisy_sphere(bench_descriptors, 400, seed=2))
    assert (np.bincount(faces.ravel(), minlength=len(vertices)) > 0).all()
    assert D.intrinsic_delaunay_laplacian(vertices, faces) is None
    L_robust, mass_robust = _robust_pair(vertices, faces)
    L, mass = D.mesh_laplacian(vertices, faces)
    assert abs(L - L_robust).max() == 0 and np.array_equal(mass, mass_robust)


@pytest.mark.parametrize(
    "vertices, faces, problem",
    [
        ([[0, 0, 0], [1, 0, 0], [0.5, 0.02, 0]], [[0, 1, 2]], "angle of 175 degrees"),
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], "zero area"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], [[0, 1, 2], [1, 0, 3], [0, 1, 4]], "fin"),
    ],
)
def test_cotan_laplacian_refuses_meshes_it_is_not_reliable_on(vertices, faces, problem):
    assert D.cotan_laplacian(np.asarray(vertices, float), np.asarray(faces)) is None, problem
    equilateral = D.cotan_laplacian(np.eye(3), np.array([[0, 1, 2]]))
    assert equilateral is not None and np.allclose(equilateral[0].diagonal(), 1 / np.sqrt(3))


def test_multilevel_solver_on_a_poorly_shaped_mesh_refines_with_robust_laplacian(toolcap):
    vertices, faces = trimesh.remesh.subdivide(toolcap.mesh.vertices, toolcap.mesh.faces)
    # A needle: one vertex pulled almost onto the opposite edge of one of its faces.
    a, b, c = faces[100]
    vertices[a] = 0.99 * (vertices[b] + vertices[c]) / 2 + 0.01 * vertices[a]
    normalized, _ = D.normalize_to_unit_area(vertices, faces)
    assert D.cotan_laplacian(normalized, faces) is None
    cache: dict = {}
    _, _, mass, solver = mesh_eigenpairs(normalized, faces, 5, "multilevel", cache)
    assert solver == "multilevel" and "robust" in cache and mass is cache["robust"][1]
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    direct, multilevel = embed(mesh, 3, method="direct"), embed(mesh, 3, method="multilevel")
    assert multilevel.solver == "multilevel" and multilevel.groups == direct.groups
    assert np.abs(multilevel.vertex_descriptors - direct.vertex_descriptors).max() < 0.02


def test_sign_of_an_odd_eigenvector_does_not_follow_solver_sized_errors():
    # An ellipsoid's first eigenvector is odd under x -> -x: its skewness is zero, and errors of the
    # multilevel solver's size (~1e-3) must not decide its sign.
    sphere = trimesh.creation.icosphere(subdivisions=4)
    vertices, faces = np.asarray(sphere.vertices) * [1.0, 0.75, 0.55], np.asarray(sphere.faces)
    _, vectors, _ = D.laplacian_eigenpairs(vertices, faces, 1)
    _, mass = D.mesh_laplacian(vertices, faces)
    y = vectors[:, 0]
    reference = _fix_sign(y, mass, vertices)
    even = y**2 / float(mass @ y**2) - 1.0  # even under the mirror, so it adds skewness
    for error in (-2e-3, 2e-3):
        noisy = y + error * even * float(np.sqrt(mass @ y**2))
        assert float(_fix_sign(noisy, mass, vertices) @ (mass * reference)) > 0, error


@pytest.fixture(scope="module")
def bench_descriptors():
    """benchmarks/bench_descriptors.py: its mesh families and its comparison modulo eigenspace bases."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_descriptors.py"
    spec = importlib.util.spec_from_file_location("bench_descriptors", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("build", "symmetric", "cotan"),
    [
        # Odd eigenvectors (three mirror planes): their signs must not follow the solver's error.
        pytest.param(lambda b: b.ellipsoid(5), True, True, id="ellipsoid"),
        # Eigenvalues repeated 3, 5, 7 times (exactly, or nearly on a scanned sphere): plain
        # eigenvectors are compared modulo the basis of each eigenspace.
        pytest.param(lambda b: b.icosphere(5), False, True, id="icosphere"),
        pytest.param(lambda b: b.uv_sphere(72), False, True, id="uv sphere"),
        pytest.param(lambda b: b.scanned_sphere(10_000), False, True, id="scanned sphere"),
        # Nearly flat triangles: the fine level is robust_laplacian's.
        pytest.param(lambda b: b.scanned_bunny(3), True, False, id="scanned bunny"),
        # Rows of long slivers (aspect ratio ~60): L x in double precision, l1-Jacobi; a prolonged start
        # accurate enough to stop after one LOBPCG step.
        pytest.param(lambda b: b.cad_cylinder(1024, rows=8), True, True, id="CAD cylinder"),
        # Long and thin, finely meshed along its length.
        pytest.param(lambda b: b.cad_shaft(420), True, True, id="CAD shaft"),
        # Fans of needles over collinear points: flips cascade, so the fine level is robust_laplacian's.
        pytest.param(lambda b: b.fan_box(1250), True, False, id="CAD box with fans"),
    ],
)
def test_multilevel_solver_matches_direct_on_unseen_mesh_families(bench_descriptors, build, symmetric, cotan):
    mesh = build(bench_descriptors)
    assert 8_000 < len(mesh.vertices) < 30_000  # multilevel-sized, yet small
    normalized, _ = D.normalize_to_unit_area(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    assert (D.cotan_laplacian(normalized, np.asarray(mesh.faces)) is not None) == cotan
    direct = embed(mesh, 3, symmetric, method="direct")
    multilevel = embed(mesh, 3, symmetric, method="multilevel")
    assert direct.solver == "direct" and multilevel.solver == "multilevel"  # no fall-back
    assert multilevel.groups == direct.groups
    if symmetric:
        difference = float(np.abs(multilevel.vertex_descriptors - direct.vertex_descriptors).max())
    else:
        difference, repeated = bench_descriptors.difference_modulo_basis(
            multilevel.vertex_descriptors, direct.vertex_descriptors, mesh
        )
        assert repeated  # the first eigenvalue is (nearly) threefold
    assert difference < 0.02


def test_benchmark_stage_timer_accounts_for_embed_and_restores_its_functions(bench_descriptors):
    """bench_descriptors' table "Where embed's time goes": every stage of the multilevel path is timed,
    the stages and the rest add up to embed's time, and embed's modules get their own functions back."""
    mesh = bench_descriptors.cad_shaft(420)
    assert len(mesh.vertices) >= D.DIRECT_MAX_VERTICES  # multilevel under method="auto"
    targets = bench_descriptors.stage_targets()
    before = [getattr(owner, attribute) for _, owner, attribute in targets]
    spent = bench_descriptors.embed_stages(mesh, 3, True)
    assert all(getattr(owner, attribute) is f for (_, owner, attribute), f in zip(targets, before, strict=True))
    stages = [stage for stage, _, _ in bench_descriptors.STAGES]
    assert all(spent.get(stage, 0.0) > 0 for stage in stages), spent
    assert sum(spent[stage] for stage in stages) + spent["other"] == pytest.approx(spent["total"])
    assert 0 <= spent["other"] < 0.5 * spent["total"]


# ---------------------------------------------------------------- interpolation


def test_interpolation_at_vertices_reproduces_vertex_values(toolcap):
    field = embed(toolcap)
    faces = toolcap.mesh.faces
    rng = np.random.default_rng(3)
    triangles = rng.integers(0, len(faces), size=200)
    corners = rng.integers(0, 3, size=200)
    bary = np.eye(3)[corners]
    values = field.at(toolcap, triangles, bary)
    assert np.array_equal(values, field.vertex_descriptors[faces[triangles, corners]])
    centre = interpolate_field(field.vertex_descriptors, faces, triangles, np.full((200, 3), 1 / 3))
    assert np.allclose(centre, field.vertex_descriptors[faces[triangles]].mean(axis=1), atol=1e-6)
    other = load_object("shaft")
    with pytest.raises(DonGymError, match="re-run embed"):
        field.at(other, triangles[:1], bary[:1])
    with pytest.raises(DonGymError, match="triangle_ids"):
        interpolate_field(field.vertex_descriptors, faces, np.array([len(faces)]), bary[:1])


# ---------------------------------------------------------------- background


def test_background_maximises_the_distance_to_the_descriptors():
    rng = np.random.default_rng(0)
    # Descriptors filling most of the cube except a region around (0.8, 0.2, 0.3).
    points = rng.random((4000, 3))
    points = points[np.linalg.norm(points - [0.8, 0.2, 0.3], axis=1) > 0.25]
    background = D.background_descriptor(points)
    assert background.dtype == np.float32 and np.all((background >= 0) & (background <= 1))
    found = np.linalg.norm(points - background, axis=1).min()
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 31)] * 3, indexing="ij"), -1).reshape(-1, 3)
    best_on_grid = max(np.linalg.norm(points - g, axis=1).min() for g in grid[::7])
    assert found >= best_on_grid - 1e-6
    assert found > 0.2  # the hole is found, not a corner


def test_background_search_on_a_shell_keeps_every_point_that_can_be_nearest(monkeypatch):
    embed_module = importlib.import_module("don_gym.descriptors.embed")
    rng = np.random.default_rng(1)
    # Descriptors of a sphere-like part: a noisy shell about the cube's centre, where the search
    # keeps a thinning band of points as its step shrinks.
    direction = rng.standard_normal((20_000, 3))
    points = 0.5 + (0.45 + 0.002 * rng.standard_normal((20_000, 1))) * direction / np.linalg.norm(
        direction, axis=1, keepdims=True
    )
    full, around = embed_module._NearestByScan(points), embed_module._NearestAround(points)
    x = np.array([0.51, 0.49, 0.5])
    fx = float(full.query(x)[0])
    directions = np.concatenate([np.eye(3), -np.eye(3)])
    for step in [1 / 64, 1 / 64, 1 / 256, 1 / 1024, 1 / 1024, 1e-4]:
        trial = np.clip(x + step * directions, 0.0, 1.0)
        distance = around.distances(trial, x, fx, step)
        assert np.array_equal(distance, full.query(trial)[0])  # bit for bit
        x, fx = trial[int(np.argmax(distance))], float(distance.max())
    assert len(around._kept) < len(points) // 4
    background = D.background_descriptor(points)
    monkeypatch.setattr(embed_module, "_NearestAround", embed_module._Nearest)  # every point, every query
    assert np.array_equal(background, D.background_descriptor(points))


def test_embed_background_is_far_from_all_descriptors(toolcap):
    field = embed(toolcap)
    nearest = np.linalg.norm(field.vertex_descriptors - field.background, axis=1).min()
    corners = ((np.arange(8)[:, None] >> np.arange(3)) & 1).astype(np.float32)
    best_corner = max(np.linalg.norm(field.vertex_descriptors - c, axis=1).min() for c in corners)
    assert nearest >= best_corner - 1e-6 and nearest > 0.3


# ---------------------------------------------------------------- save / load


def test_save_load_round_trip(tmp_path, toolcap):
    field = embed(toolcap)
    path = field.save(tmp_path / "toolcap.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["toolcap.npz"]  # no temporary left behind
    loaded = DescriptorField.load(path)
    assert loaded.field_hash == field.field_hash
    assert np.array_equal(loaded.vertex_descriptors, field.vertex_descriptors)
    assert np.array_equal(loaded.eigenvalues, field.eigenvalues)
    assert loaded.groups == field.groups and loaded.symmetric and loaded.mesh_hash == toolcap.mesh_hash
    assert not loaded.vertex_descriptors.flags.writeable


def test_load_rejects_missing_corrupt_foreign_and_tampered_files(tmp_path, toolcap):
    with pytest.raises(DonGymError, match="does not exist"):
        DescriptorField.load(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip file" * 10)
    with pytest.raises(DonGymError, match="not a readable"):
        DescriptorField.load(garbage)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, weights=np.zeros(3))
    with pytest.raises(DonGymError, match="expected"):
        DescriptorField.load(foreign)
    field = embed(toolcap)
    path = field.save(tmp_path / "field.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["vertex_descriptors"] = arrays["vertex_descriptors"].copy()
    arrays["vertex_descriptors"][0, 0] = 1.0 - arrays["vertex_descriptors"][0, 0]
    tampered = tmp_path / "tampered.npz"
    np.savez(tampered, **arrays)
    with pytest.raises(DonGymError, match="corrupt"):
        DescriptorField.load(tampered)
    meta = json.loads(str(arrays["meta"]))
    meta["groups"] = [[0], [1]]
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tampered, **arrays)
    with pytest.raises(DonGymError, match="corrupt"):
        DescriptorField.load(tampered)


# ---------------------------------------------------------------- bad input


def test_bad_meshes_raise_mesh_error(toolcap, tmp_path):
    with pytest.raises(MeshError, match="empty"):
        embed(trimesh.Trimesh())
    broken = toolcap.mesh.copy()
    broken.vertices[5] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        embed(broken)
    with pytest.raises(MeshError, match="at least 5"):
        embed(_tetrahedron(), 3)
    with pytest.raises(MeshError, match="Trimesh"):
        embed("toolcap")  # type: ignore[arg-type]
    with pytest.raises(DonGymError, match="dim"):
        embed(toolcap, 0)
    unreadable = tmp_path / "part.stl"
    unreadable.write_bytes(b"\x00\x01garbage")
    with pytest.raises(MeshError, match="part.stl"):
        embed(load_object(unreadable))


def _tetrahedron() -> trimesh.Trimesh:
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return trimesh.Trimesh(vertices, faces, process=False)


def test_multi_component_mesh_errors_or_embeds_the_largest_piece(bunny):
    small = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    small.apply_translation([5.0, 0.0, 0.0])
    both = trimesh.util.concatenate([bunny, small])
    with pytest.raises(MeshError, match="2 connected components.*components='largest'"):
        embed(both)
    field = embed(both, 3, symmetric=False, components="largest")
    alone = embed(bunny, 3, symmetric=False)
    n = len(bunny.vertices)
    assert field.embedded_vertices == n and field.n_vertices == len(both.vertices)
    assert np.abs(field.vertex_descriptors[:n] - alone.vertex_descriptors).max() < 1e-5
    # The far sphere's vertices take the descriptor of the nearest bunny vertex.
    nearest = np.argmin(np.linalg.norm(bunny.vertices - small.vertices[0], axis=1))
    assert np.allclose(field.vertex_descriptors[n], alone.vertex_descriptors[nearest])
