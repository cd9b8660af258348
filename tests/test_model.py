"""DenseObjectNet shapes, single-frame inference, the ImageNet-weights loader, and augmentation."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch

from don_gym.errors import CheckpointError, DonGymError
from don_gym.learning.augment import (
    AugmentConfig,
    augment,
    photometric_jitter,
    random_backgrounds,
    randomize_background,
)
from don_gym.learning.model import ARCHS, DEFAULT_ARCH, DenseObjectNet


@pytest.mark.parametrize("arch", sorted(ARCHS))
def test_output_matches_input_size_and_the_archs_stride_inside(arch: str) -> None:
    model = DenseObjectNet(arch, descriptor_dim=5).eval()
    stride = ARCHS[arch].output_stride
    assert model.output_stride == stride == (2 if ARCHS[arch].decoder_widths else 8)
    with torch.no_grad():
        for height, width in ((38, 50), (48, 64), (33, 17)):
            rgb = torch.rand(2, 3, height, width)
            out = model(rgb)
            assert out.shape == (2, 5, height, width)
            assert out.is_contiguous() and torch.isfinite(out).all()
            low = model.forward_low_res(rgb)
            assert low.shape == (2, 5, math.ceil(height / stride), math.ceil(width / stride))


def test_default_arch_is_small_and_resnet34_is_the_papers() -> None:
    lite = DenseObjectNet()
    assert lite.arch == DEFAULT_ARCH == "resnet-lite"
    assert sum(p.numel() for p in lite.parameters()) < 1_000_000  # about 2 MB of float32
    spec = ARCHS["resnet34"]
    assert spec.blocks == (3, 4, 6, 3) and spec.widths == (64, 128, 256, 512)
    # Dilation replaces the strides of stages 3 and 4.
    r34 = DenseObjectNet("resnet34").encoder
    assert r34.layer3[0].conv1.stride == (1, 1) and r34.layer3[1].conv1.dilation == (2, 2)
    assert r34.layer4[0].conv1.stride == (1, 1) and r34.layer4[1].conv2.dilation == (4, 4)
    with pytest.raises(DonGymError, match="resnet50"):
        DenseObjectNet("resnet50")
    with pytest.raises(DonGymError, match="descriptor_dim"):
        DenseObjectNet(descriptor_dim=0)


def test_normalisation_happens_inside_the_model() -> None:
    torch.manual_seed(0)
    model = DenseObjectNet(descriptor_dim=3).eval()
    rgb = torch.rand(1, 3, 16, 24)
    with torch.no_grad():
        normalised = (rgb - torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)) / torch.tensor(
            [0.229, 0.224, 0.225]
        ).view(1, 3, 1, 1)
        expected = model.head(model.encoder(normalised))
        assert torch.allclose(model.forward_low_res(rgb), expected, atol=1e-5)
    # The statistics are metadata, not weights.
    assert "mean" not in model.state_dict() and "std" not in model.state_dict()


def test_descriptor_image_matches_forward_and_restores_mode() -> None:
    torch.manual_seed(0)
    model = DenseObjectNet(descriptor_dim=4)
    model.train()
    rgb = np.random.default_rng(0).integers(0, 256, size=(38, 50, 3), dtype=np.uint8)
    descriptors = model.descriptor_image(rgb)
    assert descriptors.shape == (38, 50, 4) and descriptors.dtype == np.float32
    assert model.training  # restored
    model.eval()
    with torch.no_grad():
        expected = model(torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255.0)[0].permute(1, 2, 0)
    np.testing.assert_allclose(descriptors, expected.numpy(), atol=1e-5)
    with pytest.raises(DonGymError, match="uint8"):
        model.descriptor_image(rgb.astype(np.float32))
    with pytest.raises(DonGymError, match=r"\(H, W, 3\)"):
        model.descriptor_image(rgb[..., :2])
    with pytest.raises(DonGymError, match="float"):
        model(torch.zeros(1, 3, 8, 8, dtype=torch.uint8))


def _torchvision_style_state_dict(model: DenseObjectNet) -> dict[str, torch.Tensor]:
    """An ImageNet-style file: torchvision key names, a classifier, no num_batches_tracked (old files)."""
    state = {k: v.clone().contiguous() for k, v in model.encoder.state_dict().items()}
    state = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    state["fc.weight"] = torch.randn(1000, 512)
    state["fc.bias"] = torch.randn(1000)
    return state


def test_pretrained_loader_round_trip_with_torchvision_names(tmp_path) -> None:
    torch.manual_seed(0)
    source = DenseObjectNet("resnet34")
    with torch.no_grad():  # distinctive BN statistics, so that a skipped buffer would show
        for name, buffer in source.encoder.named_buffers():
            if name.endswith("running_mean"):
                buffer.normal_()
    state = _torchvision_style_state_dict(source)
    for key in ("conv1.weight", "bn1.running_var", "layer1.0.conv1.weight", "layer2.0.downsample.0.weight",
                "layer2.0.downsample.1.running_mean", "layer3.5.bn2.bias", "layer4.2.conv2.weight"):  # fmt: skip
        assert key in state, key
    path = tmp_path / "resnet34-imagenet.pth"
    torch.save(state, path)
    loaded = DenseObjectNet("resnet34", descriptor_dim=3, pretrained_path=path)
    for key, value in source.encoder.state_dict().items():
        assert torch.equal(loaded.encoder.state_dict()[key], value), key
    report = DenseObjectNet("resnet34").load_pretrained_encoder(path)
    assert report.ignored == ("fc.bias", "fc.weight") and not report.missing and not report.unexpected
    assert len(report.loaded) == len(state) - 2


def test_pretrained_loader_errors(tmp_path) -> None:
    torch.manual_seed(0)
    state = _torchvision_style_state_dict(DenseObjectNet("resnet18"))
    resnet18_file = tmp_path / "resnet18.pth"
    torch.save(state, resnet18_file)
    # ResNet-18 weights never silently half-initialise a ResNet-34.
    with pytest.raises(CheckpointError, match=r"missing from the file \['layer1.2"):
        DenseObjectNet("resnet34", pretrained_path=resnet18_file)
    # Non-strict: loads what matches and reports the rest.
    model = DenseObjectNet("resnet34")
    with pytest.warns(UserWarning, match="missing"):
        report = model.load_pretrained_encoder(resnet18_file, strict=False)
    assert "layer3.5.conv1.weight" in report.missing
    assert torch.equal(model.encoder.layer1[0].conv1.weight, state["layer1.0.conv1.weight"])
    wrong_shape = dict(state, **{"layer2.0.conv1.weight": torch.zeros(128, 64, 5, 5)})
    torch.save(wrong_shape, tmp_path / "shape.pth")
    with pytest.raises(CheckpointError, match=r"layer2.0.conv1.weight: file \(128, 64, 5, 5\)"):
        DenseObjectNet("resnet18", pretrained_path=tmp_path / "shape.pth")
    with pytest.raises(CheckpointError, match="no such file"):
        DenseObjectNet("resnet18", pretrained_path=tmp_path / "absent.pth")
    (tmp_path / "garbage.pth").write_bytes(os.urandom(2000))
    with pytest.raises(CheckpointError, match="cannot be read"):
        DenseObjectNet("resnet18", pretrained_path=tmp_path / "garbage.pth")
    with pytest.raises(CheckpointError, match="no ImageNet layout"):
        DenseObjectNet("resnet-lite", pretrained_path=resnet18_file)


# --- augmentation (training inputs of the model) ------------------------------------------


def _images(batch: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(batch, 3, 24, 32, generator=g)
    mask = torch.zeros(batch, 24, 32, dtype=torch.bool)
    mask[:, 6:18, 8:20] = True
    return rgb, mask


def test_background_randomisation_keeps_object_pixels() -> None:
    rgb, mask = _images()
    out = randomize_background(rgb, mask, torch.Generator().manual_seed(3), probability=1.0)
    object_pixels = mask.unsqueeze(1).expand_as(rgb)
    assert torch.equal(out[object_pixels], rgb[object_pixels])  # bit-identical
    changed = (out != rgb).any(dim=1)  # (B, H, W)
    assert changed[~mask].float().mean() > 0.95  # essentially every background pixel is new
    assert out.min() >= 0.0 and out.max() <= 1.0
    assert torch.equal(randomize_background(rgb, mask, torch.Generator().manual_seed(3), probability=0.0), rgb)


def test_background_randomisation_probability_and_kinds() -> None:
    rgb, mask = _images(batch=400)
    out = randomize_background(rgb, mask, torch.Generator().manual_seed(0), probability=0.5)
    chosen = (out != rgb).flatten(1).any(dim=1)
    assert 150 < int(chosen.sum()) < 250  # binomial(400, 0.5): mean 200, sd 10
    background = out[chosen].permute(0, 2, 3, 1)[:, ~mask[0]]  # (n, pixels, 3)
    spread = background.std(dim=1).amax(dim=1)
    constant = spread < 1e-6
    assert constant.any() and (~constant).any()  # plain colours and gradients/noise both occur


def test_pattern_backgrounds_are_two_colour_stripes_or_checks_and_off_by_default() -> None:
    like = torch.zeros(1)
    plain = random_backgrounds(64, 48, 64, torch.Generator().manual_seed(5), like)
    # Probability 0 draws nothing more: the backgrounds are those of the call without the option.
    assert torch.equal(random_backgrounds(64, 48, 64, torch.Generator().manual_seed(5), like, 0.0), plain)
    # 192 px or more in every direction: at least two of the longest periods (PATTERN_PERIOD_PX).
    patterns = random_backgrounds(32, 192, 256, torch.Generator().manual_seed(5), like, pattern_probability=1.0)
    assert patterns.shape == (32, 3, 192, 256)
    for image in patterns:
        colours = image.flatten(1).T.unique(dim=0)
        assert len(colours) == 2  # sharp: exactly two colours, no blend between them
        share = (image.flatten(1).T == colours[0]).all(dim=1).float().mean()
        assert 0.2 < share < 0.8  # both colours cover a good part of the image at any period, angle and phase
    half = random_backgrounds(400, 24, 32, torch.Generator().manual_seed(6), like, pattern_probability=0.5)
    two_colours = torch.tensor([len(image.flatten(1).T.unique(dim=0)) == 2 for image in half])
    assert 150 < int(two_colours.sum()) < 250  # binomial(400, 0.5); colours, gradients and noise never have two
    with pytest.raises(DonGymError, match="pattern_probability"):
        AugmentConfig(pattern_probability=1.5)


def test_augmentation_is_deterministic_given_a_seed() -> None:
    rgb, mask = _images()
    first = augment(rgb, mask, torch.Generator().manual_seed(7))
    again = augment(rgb, mask, torch.Generator().manual_seed(7))
    other = augment(rgb, mask, torch.Generator().manual_seed(8))
    assert torch.equal(first, again)
    assert not torch.equal(first, other)
    assert first.shape == rgb.shape and first.min() >= 0.0 and first.max() <= 1.0


def test_photometric_jitter_is_pixelwise_and_off_when_zero() -> None:
    rgb, _ = _images()
    off = AugmentConfig(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0, noise_std=0.0)
    assert torch.allclose(photometric_jitter(rgb, torch.Generator().manual_seed(0), off), rgb, atol=1e-5)
    # Brightness alone is a per-image gain: every pixel of an image scales by the same factor.
    gain_only = AugmentConfig(brightness=0.3, contrast=0.0, saturation=0.0, hue=0.0, noise_std=0.0)
    dim = rgb * 0.5  # no clipping at 1
    out = photometric_jitter(dim, torch.Generator().manual_seed(1), gain_only)
    gain = out.sum(dim=(1, 2, 3), keepdim=True) / dim.sum(dim=(1, 2, 3), keepdim=True)
    assert torch.allclose(out, dim * gain, atol=1e-5)
    assert ((gain > 0.69) & (gain < 1.31)).all() and gain.flatten().unique().numel() == gain.numel()
    # Saturation and hue keep a grey pixel grey (they only act on the chroma plane).
    grey = torch.full((2, 3, 4, 4), 0.4)
    colour_only = AugmentConfig(brightness=0.0, contrast=0.0, saturation=0.5, hue=0.2, noise_std=0.0)
    assert torch.allclose(photometric_jitter(grey, torch.Generator().manual_seed(2), colour_only), grey, atol=1e-5)
    with pytest.raises(DonGymError, match="hue"):
        AugmentConfig(hue=0.7)
