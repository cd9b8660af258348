"""Checkpoint round trip and a clear CheckpointError for every kind of wrong or broken file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from file_snapshots import snapshot
from safetensors.torch import save_file

from don_gym import __version__
from don_gym.errors import CheckpointError, DonGymError
from don_gym.learning.checkpoints import (
    FORMAT_VERSION,
    CheckpointMetadata,
    load_checkpoint,
    read_checkpoint_metadata,
    save_checkpoint,
)
from don_gym.learning.model import DenseObjectNet

METADATA = CheckpointMetadata(
    method="supervised-mask",
    object_name="toolcap",
    object_mesh_hash="0123abcd0123abcd",
    image_size=(64, 48),
    descriptor_field_hash="feedbeef",
    renderer="tiny",
    training_steps=30,
    extra={"lr": 1e-4, "seed": 0},
)


def _trained_model() -> DenseObjectNet:
    """A model whose BN statistics moved away from their initial values, as after training."""
    torch.manual_seed(0)
    model = DenseObjectNet(descriptor_dim=3)
    model.train()
    with torch.no_grad():
        model(torch.rand(2, 3, 48, 64))
    return model.eval()


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> tuple[Path, DenseObjectNet]:
    model = _trained_model()
    path = tmp_path_factory.mktemp("ckpt") / "toolcap.safetensors"
    save_checkpoint(path, model, METADATA)
    return path, model


def test_an_arch_with_a_decoder_round_trips_and_its_name_must_fit_the_weights(tmp_path: Path) -> None:
    torch.manual_seed(0)
    fine = DenseObjectNet("resnet-lite-fine", descriptor_dim=3).eval()
    path = tmp_path / "fine.safetensors"
    save_checkpoint(path, fine, METADATA)
    loaded, metadata = load_checkpoint(path)
    assert metadata.arch == "resnet-lite-fine" and loaded.output_stride == 2
    rgb = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(loaded(rgb), fine(rgb))
    # Weights of the plain arch under the decoder arch's name: refused, naming the arch.
    plain = _trained_model()
    save_checkpoint(tmp_path / "plain.safetensors", plain, METADATA)
    stored = read_checkpoint_metadata(tmp_path / "plain.safetensors").to_dict()
    tensors = {k: v.contiguous() for k, v in plain.state_dict().items()}
    renamed = tmp_path / "renamed.safetensors"
    save_file(tensors, str(renamed), metadata={"don_gym": json.dumps({**stored, "arch": "resnet-lite-fine"})})
    with pytest.raises(CheckpointError, match="do not fit arch 'resnet-lite-fine'"):
        load_checkpoint(renamed)


def test_round_trip_gives_identical_outputs_and_metadata(saved) -> None:
    path, model = saved
    loaded, metadata = load_checkpoint(
        path, expect_object="toolcap", expect_descriptor_dim=3, expect_method="supervised-mask",
        expect_field_hash="feedbeef",
    )  # fmt: skip
    assert not loaded.training
    rgb = torch.rand(2, 3, 48, 64)
    with torch.no_grad():
        assert torch.equal(loaded(rgb), model(rgb))
    assert metadata.arch == "resnet-lite" and metadata.descriptor_dim == 3
    assert metadata.image_size == (64, 48) and metadata.normalization_mean == (0.485, 0.456, 0.406)
    assert metadata.don_gym_version == __version__ and metadata.format_version == FORMAT_VERSION
    assert metadata.extra == {"lr": 1e-4, "seed": 0} and metadata.training_steps == 30
    assert read_checkpoint_metadata(path) == metadata
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # atomic write left no temp file


def test_float16_weights_halve_the_file(tmp_path, saved) -> None:
    path32, model = saved
    path16 = tmp_path / "half.safetensors"
    save_checkpoint(path16, model, METADATA, weights_dtype="float16")
    assert path16.stat().st_size < 0.55 * path32.stat().st_size
    loaded, metadata = load_checkpoint(path16)
    assert metadata.weights_dtype == "float16" and loaded.head.weight.dtype == torch.float32
    rgb = torch.rand(1, 3, 48, 64)
    with torch.no_grad():
        assert torch.allclose(loaded(rgb), model(rgb), atol=2e-2)


def test_metadata_as_a_mapping(tmp_path, saved) -> None:
    _, model = saved
    fields = {**METADATA.to_dict(), "background_descriptor": [1.0, 0.0, 1.0], "image_size": [64, 48]}
    written = save_checkpoint(tmp_path / "m.safetensors", model, fields)
    assert written.background_descriptor == (1.0, 0.0, 1.0) and written.image_size == (64, 48)
    assert load_checkpoint(tmp_path / "m.safetensors")[1] == written
    with pytest.raises(CheckpointError, match=r"unknown metadata fields \['objekt'\]"):
        save_checkpoint(tmp_path / "n.safetensors", model, {**fields, "objekt": "toolcap"})
    with pytest.raises(CheckpointError, match=r"lacks the fields \['object_name'\]"):
        save_checkpoint(tmp_path / "n.safetensors", model, {k: v for k, v in fields.items() if k != "object_name"})
    assert not (tmp_path / "n.safetensors").exists()


def test_save_refuses_metadata_that_contradicts_the_model(tmp_path) -> None:
    model = DenseObjectNet(descriptor_dim=3)
    with pytest.raises(DonGymError, match="descriptor_dim=4"):
        save_checkpoint(
            tmp_path / "x.safetensors", model, CheckpointMetadata(**{**METADATA.to_dict(), "descriptor_dim": 4})
        )
    with pytest.raises(DonGymError, match="method"):
        save_checkpoint(tmp_path / "x.safetensors", model, CheckpointMetadata(**{**METADATA.to_dict(), "method": "l2"}))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("expectation", "message"),
    [
        ({"expect_descriptor_dim": 8}, "descriptor_dim is 3, expected 8"),
        ({"expect_object": "shaft"}, "object_name is 'toolcap', expected 'shaft'"),
        ({"expect_method": "self-supervised"}, "method is 'supervised-mask', expected 'self-supervised'"),
        ({"expect_field_hash": "00000000"}, "descriptor_field_hash is 'feedbeef', expected '00000000'"),
    ],
)
def test_wrong_checkpoint_is_named(saved, expectation: dict, message: str) -> None:
    path, _ = saved
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path, **expectation)
    assert str(path) in str(info.value) and message in str(info.value)


def test_broken_files(tmp_path, saved) -> None:
    path, _ = saved
    data = path.read_bytes()
    cases = {
        "missing.safetensors": None,
        "truncated.safetensors": data[: len(data) // 2],
        "random.safetensors": os.urandom(4096),
        "empty.safetensors": b"",
    }
    flipped = bytearray(data)
    flipped[-1000] ^= 0xFF  # a weight byte: same size, valid header, wrong numbers
    cases["flipped.safetensors"] = bytes(flipped)
    expected = {
        "missing.safetensors": "no such file",
        "truncated.safetensors": "corrupt or truncated",
        "random.safetensors": "corrupt or truncated",
        "empty.safetensors": "corrupt or truncated",
        "flipped.safetensors": "weights_sha256",
    }
    for name, content in cases.items():
        target = tmp_path / name
        if content is not None:
            target.write_bytes(content)
        before = snapshot(tmp_path)
        with pytest.raises(CheckpointError, match=expected[name]) as info:
            load_checkpoint(target)
        assert str(target) in str(info.value)
        assert snapshot(tmp_path) == before  # a refused file is left as it was, for the user to look at
    with pytest.raises(CheckpointError, match="not a file"):
        load_checkpoint(tmp_path)


def test_foreign_or_future_safetensors(tmp_path, saved) -> None:
    foreign = tmp_path / "foreign.safetensors"
    save_file({"weight": torch.zeros(3)}, str(foreign), metadata={"format": "pt"})
    with pytest.raises(CheckpointError, match="not a don_gym checkpoint"):
        load_checkpoint(foreign)
    path, model = saved
    tensors = {k: v.contiguous() for k, v in model.state_dict().items()}
    stored = read_checkpoint_metadata(path).to_dict()
    future = tmp_path / "future.safetensors"
    save_file(tensors, str(future), metadata={"don_gym": json.dumps({**stored, "format_version": FORMAT_VERSION + 1})})
    with pytest.raises(CheckpointError, match=f"format_version is {FORMAT_VERSION + 1}, expected <= {FORMAT_VERSION}"):
        load_checkpoint(future)
    lying = tmp_path / "lying.safetensors"  # metadata says D=4, weights are D=3
    save_file(tensors, str(lying), metadata={"don_gym": json.dumps({**stored, "descriptor_dim": 4})})
    with pytest.raises(CheckpointError, match="do not fit arch 'resnet-lite' with descriptor_dim 4"):
        load_checkpoint(lying)
    no_json = tmp_path / "nojson.safetensors"
    save_file(tensors, str(no_json), metadata={"don_gym": "{not json"})
    with pytest.raises(CheckpointError, match="not valid JSON"):
        read_checkpoint_metadata(no_json)


def test_zoo_reads_metadata_of_a_file_a_run_directory_or_a_shipped_name_without_weights(saved, tmp_path) -> None:
    from don_gym.zoo import load_don, read_don_metadata, shipped_names

    path, _ = saved
    run = tmp_path / "run"
    run.mkdir()
    (run / "model.safetensors").write_bytes(path.read_bytes())
    assert read_don_metadata(path) == read_don_metadata(run) == load_don(run)[1] == read_checkpoint_metadata(path)
    with pytest.raises(CheckpointError, match="object_name is 'toolcap', expected 'shaft'"):
        read_don_metadata(path, expect_object="shaft")
    with pytest.raises(CheckpointError, match="no shipped network named 'toolcap/nonsense'; available"):
        read_don_metadata("toolcap/nonsense")
    with pytest.raises(CheckpointError, match="no such file"):
        read_don_metadata(tmp_path / "missing.safetensors")
    with pytest.raises(CheckpointError, match="directory without model.safetensors"):
        load_don(tmp_path)
    for name in shipped_names():
        metadata = read_don_metadata(name)
        if metadata.part_space:  # a network of several parts ("bin/<method>") names the first of its parts
            assert name.startswith("bin/") and metadata.object_name in ("toolcap", "shaft")
        else:
            assert metadata.object_name == name.split("/")[0]
