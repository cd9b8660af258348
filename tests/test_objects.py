"""Tests of don_gym.objects: built-in parts within spec, physical properties, file loading, errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from don_gym.errors import MeshError
from don_gym.objects import STEEL_DENSITY_KG_M3, builtin_names, load_object


def radial_diameter(mesh) -> np.ndarray:
    """(N,) twice the distance of each vertex from the z axis."""
    return 2 * np.linalg.norm(np.asarray(mesh.vertices)[:, :2], axis=1)


def test_builtin_names():
    assert builtin_names() == ["shaft", "toolcap"]


def test_toolcap_dimensions_and_mass():
    toolcap = load_object("toolcap")
    mesh = toolcap.mesh
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    z = mesh.vertices[:, 2]
    assert np.ptp(z) == pytest.approx(0.040, abs=5e-4)  # ~40 mm long
    diameter = radial_diameter(mesh)
    assert 0.028 - 1e-6 <= diameter.max() <= 0.034 + 1e-6  # flange 34 mm
    body = diameter[(z > z.min() + 0.005) & (z < z.max() - 0.010)]
    assert body.max() == pytest.approx(0.028, abs=2e-4)  # 28 mm body
    # Solid of revolution: 28 mm x 34 mm body, 34 mm x 6 mm flange, minus an 18 mm x 24 mm bore.
    volume = np.pi * (0.014**2 * 0.034 + 0.017**2 * 0.006 - 0.009**2 * 0.024)
    assert toolcap.volume_m3 == pytest.approx(volume, rel=0.02)  # chamfers and 64 facets
    assert toolcap.mass_kg == pytest.approx(toolcap.volume_m3 * STEEL_DENSITY_KG_M3)
    assert toolcap.material.density_kg_m3 == STEEL_DENSITY_KG_M3 == 7850.0
    assert np.allclose(toolcap.center_of_mass, 0.0, atol=1e-9)
    assert np.allclose(toolcap.symmetry_axis, [0, 0, 1]) and np.allclose(toolcap.plus_axis, [0, 0, 1])
    inertia = toolcap.inertia_kg_m2
    assert np.allclose(inertia, inertia.T) and inertia[0, 0] == pytest.approx(inertia[1, 1], rel=1e-3)


def test_shaft_dimensions_and_mass():
    shaft = load_object("shaft")
    mesh = shaft.mesh
    assert mesh.is_watertight and mesh.volume > 0
    z = mesh.vertices[:, 2]
    assert np.ptp(z) == pytest.approx(0.120, abs=5e-4)
    diameter = radial_diameter(mesh)
    assert diameter.max() == pytest.approx(0.016, abs=1e-6)
    # Each step's diameter, sampled in the middle of the step (from the 10 mm end at z.min()).
    starts = z.min() + np.array([0.011, 0.041, 0.080, 0.110])
    for middle, expected in zip(starts, (0.010, 0.016, 0.013, 0.012), strict=True):
        ring = diameter[np.abs(z - middle) < 0.002]
        assert ring.max() == pytest.approx(expected, abs=2e-4)
    volume = np.pi * (0.005**2 * 0.022 + 0.008**2 * 0.038 + 0.0065**2 * 0.040 + 0.006**2 * 0.020)
    assert shaft.volume_m3 == pytest.approx(volume, rel=0.02)
    assert shaft.mass_kg == pytest.approx(shaft.volume_m3 * STEEL_DENSITY_KG_M3)


def test_builtin_hash_is_deterministic():
    assert load_object("toolcap").mesh_hash == load_object("toolcap").mesh_hash
    assert load_object("toolcap").mesh_hash != load_object("shaft").mesh_hash


@pytest.mark.parametrize("suffix", ["stl", "obj", "ply", "off", "glb"])
def test_millimetre_file_round_trip(tmp_path, suffix):
    original = load_object("toolcap")
    in_mm = original.mesh.copy()
    in_mm.apply_scale(1000.0)
    path = tmp_path / f"cap.{suffix}"
    in_mm.export(path)
    with pytest.warns(UserWarning, match="millimetres"):
        loaded = load_object(path)  # 40 units > 1 m: taken as millimetres
    assert loaded.name == "cap" and loaded.source == str(path.resolve())
    assert len(loaded.mesh.faces) == len(original.mesh.faces)
    assert np.allclose(loaded.extents_m, original.extents_m, rtol=1e-6)
    assert loaded.mesh.is_watertight
    assert loaded.volume_m3 == pytest.approx(original.volume_m3, rel=1e-6)
    assert loaded.symmetry_axis is None  # files do not declare one
    assert abs(loaded.plus_axis @ [0, 0, 1]) == pytest.approx(1.0, abs=1e-6)  # long axis
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an explicit scale gives no warning
        explicit = load_object(path, scale=0.001)
    assert np.allclose(explicit.extents_m, original.extents_m, rtol=1e-6)


def test_loading_errors(tmp_path):
    garbage = tmp_path / "part.stl"
    garbage.write_bytes(b"\x00\x01 not an stl" * 4)
    with pytest.raises(MeshError, match="part.stl"):
        load_object(garbage)
    unknown_format = tmp_path / "part.xyz123"
    unknown_format.write_text("hello")
    with pytest.raises(MeshError, match="could not be read"):
        load_object(unknown_format)
    empty = tmp_path / "empty.obj"
    empty.write_text("# no geometry\n")
    with pytest.raises(MeshError, match="empty"):
        load_object(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    with pytest.raises(MeshError, match="NaN"):
        load_object(nan)
    with pytest.raises(MeshError, match="neither a built-in"):
        load_object("toolcapp")
    with pytest.raises(MeshError, match="does not exist"):
        load_object(tmp_path / "missing.stl")
    with pytest.raises(MeshError, match="scale"):
        load_object("toolcap", scale=-1.0)
    with pytest.raises(MeshError, match="material"):
        load_object("toolcap", material="unobtainium")
