"""Part identity: networks recognise their part by geometry and carry their descriptor field, compared
numerically, so another machine's bits, a renamed or re-exported mesh and old checkpoints behave as documented."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from safetensors.torch import load_file, save_file

import don_gym.perception.descriptor_sources as descriptor_sources
from don_gym.descriptors import FIELD_MATCH_ATOL, DescriptorField
from don_gym.errors import CheckpointError
from don_gym.learning.checkpoints import (
    FIELD_TENSORS,
    PART_TENSORS,
    CheckpointMetadata,
    PartIdentity,
    check_metadata,
    load_checkpoint,
    read_checkpoint_metadata,
    read_part_identity,
    restamp_checkpoint,
    save_checkpoint,
)
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import SHAPE_MATCH_RTOL, ObjectModel, load_object, part_name
from don_gym.perception.descriptor_sources import descriptor_field_for, load_descriptor_source
from don_gym.zoo import (
    checkpoint_path,
    read_don_metadata,
    shipped_multi_part_names,
    shipped_names,
    shipped_names_for,
)

torch.set_num_threads(1)

SHIPPED_TOOLCAP = [n for n in shipped_names() if n.startswith("toolcap/")]
SHIPPED_BIN = shipped_multi_part_names()
#: Shipped networks that carry the toolcap's field (supervised-edge also reads its references from it).
SHIPPED_FIELD_NETS = [n for n in ("toolcap/supervised-edge", "toolcap/supervised-mask") if n in SHIPPED_TOOLCAP]


@pytest.fixture(scope="module")
def toolcap() -> ObjectModel:
    return load_object("toolcap")


@pytest.fixture(scope="module")
def toolcap_field(toolcap: ObjectModel) -> DescriptorField:
    return descriptor_field_for(toolcap)


def _perturbed(field: DescriptorField, amount: float) -> DescriptorField:
    """``field`` with every vertex descriptor moved by +-``amount`` (other bits, same values to ``amount``)."""
    signs = np.where(np.arange(field.vertex_descriptors.size) % 2 == 0, 1.0, -1.0).reshape(
        field.vertex_descriptors.shape
    )
    moved = np.clip(field.vertex_descriptors + amount * signs, 0.0, 1.0).astype(np.float32)
    return dataclasses.replace(field, vertex_descriptors=moved)


def _permuted_copy(part: ObjectModel, path: Path, seed: int = 0) -> ObjectModel:
    """``part``'s mesh with its vertices in another order, written to ``path`` and loaded back."""
    order = np.random.default_rng(seed).permutation(len(part.mesh.vertices))
    inverse = np.argsort(order)
    trimesh.Trimesh(part.mesh.vertices[order], inverse[part.mesh.faces], process=False).export(path)
    return load_object(path)


def _tiny_checkpoint(
    path: Path, part: ObjectModel, field: DescriptorField | None, identity: bool = True, **metadata
) -> Path:
    torch.manual_seed(0)
    fields = {
        "method": "supervised-edge",
        "object_name": part.name,
        "object_mesh_hash": part.mesh_hash,
        "image_size": (64, 48),
        "descriptor_field_hash": field.field_hash if field is not None else "",
    } | metadata
    save_checkpoint(
        path, DenseObjectNet(descriptor_dim=3), fields, identity=PartIdentity.of(part, field) if identity else None
    )
    return path


# ------------------------------------------------------------------------------------------ fields


def test_identity_round_trips_through_the_checkpoint(toolcap, toolcap_field, tmp_path: Path) -> None:
    path = _tiny_checkpoint(tmp_path / "n.safetensors", toolcap, toolcap_field)
    metadata = read_checkpoint_metadata(path)
    assert metadata.format_version == 2 and metadata.object_signature == toolcap.shape_signature.to_dict()
    identity = read_part_identity(path)
    np.testing.assert_array_equal(identity.vertices_m, toolcap.mesh.vertices)
    np.testing.assert_array_equal(identity.faces, toolcap.mesh.faces)
    for name in ("vertex_descriptors", "eigenvalues", "background"):
        np.testing.assert_array_equal(getattr(identity.field, name), getattr(toolcap_field, name))
    assert identity.field.groups == toolcap_field.groups and identity.field.solver == toolcap_field.solver
    assert identity.field.field_hash == toolcap_field.field_hash  # the same exact data
    model, _ = load_checkpoint(path, expect_part=toolcap)  # the identity tensors are not weights
    assert not any(name.startswith(("part.", "field.")) for name in model.state_dict())


def test_fields_match_within_the_stated_tolerance(toolcap, toolcap_field) -> None:
    assert FIELD_MATCH_ATOL == 1e-3
    close, far = _perturbed(toolcap_field, 1e-6), _perturbed(toolcap_field, 1e-2)
    assert close.field_hash != toolcap_field.field_hash  # other bits ...
    assert close.max_difference(toolcap_field) <= FIELD_MATCH_ATOL  # ... the same field
    assert far.max_difference(toolcap_field) > FIELD_MATCH_ATOL
    accepted = PartIdentity.of(toolcap, close).field_on(toolcap, toolcap_field, "checkpoint 'near'")
    np.testing.assert_array_equal(accepted.vertex_descriptors, close.vertex_descriptors)  # the network's own field
    with pytest.raises(CheckpointError, match=r"checkpoint 'far': .*differs from part 'toolcap'.*retrain on this part"):
        PartIdentity.of(toolcap, far).field_on(toolcap, toolcap_field, "checkpoint 'far'")


def test_a_checkpoint_whose_field_differs_is_refused_with_one_line(toolcap, toolcap_field, tmp_path: Path) -> None:
    near = _tiny_checkpoint(tmp_path / "near.safetensors", toolcap, _perturbed(toolcap_field, 1e-6))
    source = load_descriptor_source(near, toolcap)
    assert source.reference_from_field
    np.testing.assert_allclose(source.field.vertex_descriptors, toolcap_field.vertex_descriptors, atol=2e-6)
    far = _tiny_checkpoint(tmp_path / "far.safetensors", toolcap, _perturbed(toolcap_field, 1e-2))
    with pytest.raises(CheckpointError) as refused:
        load_descriptor_source(far, toolcap)
    message = str(refused.value)
    assert "\n" not in message and "far.safetensors" in message and "part 'toolcap'" in message
    assert "retrain on this part" in message and "reference_descriptors" in message


def test_another_machines_bits_never_make_the_shipped_networks_fall_back(toolcap, monkeypatch) -> None:
    # Another machine computes the toolcap's field with other last bits: another field_hash, same values.
    real_embed = descriptor_sources.embed
    monkeypatch.setattr(descriptor_sources, "_FIELDS", {})
    monkeypatch.setattr(descriptor_sources, "embed", lambda *a, **k: _perturbed(real_embed(*a, **k), 1e-7))
    for name in SHIPPED_FIELD_NETS:
        metadata = read_don_metadata(name)
        assert descriptor_field_for(toolcap).field_hash != metadata.descriptor_field_hash
        trained = read_part_identity(checkpoint_path(name)).field
        assert trained is not None and trained.field_hash == metadata.descriptor_field_hash
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            source = load_descriptor_source(name, toolcap)
            assert source.reference_from_field == (metadata.method == "supervised-edge")
        if source.reference_from_field:  # the network's own field, not the recomputed one
            np.testing.assert_array_equal(source.field.vertex_descriptors, trained.vertex_descriptors)


# -------------------------------------------------------------------------------------- the part


def test_shape_signature_ignores_vertex_order_and_name_but_not_geometry(toolcap, tmp_path: Path) -> None:
    assert SHAPE_MATCH_RTOL == 1e-4
    permuted = _permuted_copy(toolcap, tmp_path / "cap_export.ply")
    assert permuted.name == "cap_export" and permuted.mesh_hash != toolcap.mesh_hash
    assert permuted.shape_signature.differences(toolcap.shape_signature) == []
    longer = load_object("toolcap", scale=1.001)
    assert any("area_m2" in d for d in longer.shape_signature.differences(toolcap.shape_signature))
    assert part_name(tmp_path / "my_part.stl") == "my_part" and part_name("toolcap") == "toolcap"


@pytest.mark.skipif(not SHIPPED_TOOLCAP, reason="no shipped toolcap networks")
def test_shipped_toolcap_networks_refuse_a_box_named_toolcap(tmp_path: Path) -> None:
    trimesh.creation.box((0.03, 0.03, 0.04)).export(tmp_path / "toolcap.stl")
    box = load_object(tmp_path / "toolcap.stl")
    assert box.name == "toolcap"
    assert shipped_names_for(box) == []
    for name in SHIPPED_TOOLCAP:
        with pytest.raises(CheckpointError, match=r"trained on part 'toolcap', but part 'toolcap' .*another shape"):
            load_descriptor_source(name, box)
        with pytest.raises(CheckpointError, match="another shape"):
            read_don_metadata(name, expect_part=box)


@pytest.mark.skipif(not SHIPPED_TOOLCAP, reason="no shipped toolcap networks")
def test_shipped_toolcap_networks_accept_the_toolcap_with_its_vertices_permuted(toolcap, tmp_path: Path) -> None:
    permuted = _permuted_copy(toolcap, tmp_path / "my_cap.stl", seed=1)
    # The toolcap's own networks, and the networks of several parts whose space holds it.
    assert shipped_names_for(permuted) == shipped_names_for(toolcap) == sorted(SHIPPED_TOOLCAP + SHIPPED_BIN)
    for name in SHIPPED_FIELD_NETS:
        source = load_descriptor_source(name, permuted)
        if not source.reference_from_field:
            continue  # supervised-mask: references from a reference frame
        # The network's field, put on the permuted vertices: the permuted part's own field, to float noise.
        assert source.field.max_difference(descriptor_field_for(permuted)) < 1e-5
        reference = load_descriptor_source(name, toolcap)
        index = [int(np.argmin(np.linalg.norm(toolcap.mesh.vertices - v, axis=1))) for v in permuted.mesh.vertices[:50]]
        np.testing.assert_array_equal(source.field.vertex_descriptors[:50], reference.field.vertex_descriptors[index])


def test_a_part_in_another_frame_is_refused_for_field_references(toolcap, toolcap_field, tmp_path: Path) -> None:
    moved = toolcap.mesh.copy()
    moved.apply_translation([0.01, 0.0, 0.0])
    moved.export(tmp_path / "moved.ply")
    part = load_object(tmp_path / "moved.ply")
    assert part.shape_signature.differences(toolcap.shape_signature) == []
    path = _tiny_checkpoint(tmp_path / "net.safetensors", toolcap, toolcap_field)
    with pytest.raises(CheckpointError, match=r"not its vertices in the same object frame.*retrain on this part"):
        load_descriptor_source(path, part)


# -------------------------------------------------------------------------- old checkpoints, restamp


def _as_format_1(path: Path) -> Path:
    """Rewrite a checkpoint saved without identity as a format-1 file (what don_gym wrote before)."""
    tensors = load_file(str(path))
    metadata = read_checkpoint_metadata(path).to_dict()
    for key in ("object_signature", "descriptor_field", "identity_sha256"):
        metadata.pop(key)
    metadata["format_version"] = 1
    save_file(tensors, str(path), metadata={"don_gym": json.dumps(metadata, sort_keys=True)})
    return path


def test_format_1_checkpoint_loads_warns_and_restamps_without_touching_its_weights(
    toolcap, toolcap_field, tmp_path: Path, monkeypatch
) -> None:
    path = _as_format_1(_tiny_checkpoint(tmp_path / "old.safetensors", toolcap, toolcap_field, identity=False))
    old = read_checkpoint_metadata(path)
    assert old.format_version == 1 and read_part_identity(path) is None
    model, _ = load_checkpoint(path, expect_part=toolcap)
    source = load_descriptor_source(path, toolcap)
    with pytest.warns(UserWarning, match=r"carries no descriptor field.*reference frame.*restamp"):
        assert not source.reference_from_field
    # Restamp with the dataset's field as candidate: no embed needed.
    monkeypatch.setattr("don_gym.learning.checkpoints.embed", lambda *a, **k: pytest.fail("embed called"))
    metadata, done = restamp_checkpoint(path, toolcap, [toolcap_field])
    assert "identity and its descriptor field" in done and metadata.format_version == 2
    assert metadata.weights_sha256 == old.weights_sha256 and metadata.descriptor_field_hash == old.descriptor_field_hash
    after = load_file(str(path))
    assert set(after) - set(model.state_dict()) == set(PART_TENSORS + FIELD_TENSORS)
    for name, tensor in model.state_dict().items():
        assert after[name].dtype == tensor.dtype and torch.equal(after[name], tensor.cpu())
    stamped_bytes = path.read_bytes()
    _, again = restamp_checkpoint(path, toolcap, [toolcap_field])
    assert again.startswith("unchanged") and path.read_bytes() == stamped_bytes  # idempotent
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_descriptor_source(path, toolcap).reference_from_field


def test_restamp_refuses_another_part_and_stamps_only_the_part_without_its_field(
    toolcap, toolcap_field, tmp_path: Path
) -> None:
    path = _tiny_checkpoint(tmp_path / "n.safetensors", toolcap, None, identity=False, descriptor_field_hash="0" * 16)
    with pytest.raises(CheckpointError, match="trained on part 'toolcap'.*part 'shaft'"):
        restamp_checkpoint(path, load_object("shaft"))
    metadata, done = restamp_checkpoint(path, toolcap, [toolcap_field])
    assert "part identity only" in done and metadata.object_signature and not metadata.descriptor_field
    assert restamp_checkpoint(path, toolcap, [toolcap_field])[1].startswith("unchanged")
    with pytest.warns(UserWarning, match="carries no descriptor field"):
        assert not load_descriptor_source(path, toolcap).reference_from_field


def test_format_1_names_follow_the_naming_rule(toolcap, tmp_path: Path) -> None:
    metadata = CheckpointMetadata(
        method="self-supervised", object_name="parts/toolcap.stl", object_mesh_hash="0" * 16, image_size=(64, 48)
    )
    check_metadata(metadata, "old", expect_part=toolcap)  # a file stem names the part
    with pytest.raises(CheckpointError, match="object_name is 'parts/toolcap.stl', expected 'shaft'"):
        check_metadata(metadata, "old", expect_part=load_object("shaft"))


def test_a_damaged_identity_is_refused(toolcap, toolcap_field, tmp_path: Path) -> None:
    path = _tiny_checkpoint(tmp_path / "n.safetensors", toolcap, toolcap_field)
    tensors = load_file(str(path))
    tensors["field.vertex_descriptors"][0, 0] += 0.5
    raw = read_checkpoint_metadata(path).to_dict()
    save_file(tensors, str(path), metadata={"don_gym": json.dumps(raw, sort_keys=True)})
    with pytest.raises(CheckpointError, match="identity_sha256 .*corrupt"):
        load_descriptor_source(path, toolcap)
