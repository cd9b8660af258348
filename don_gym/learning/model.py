"""Dense Object Net: a fully convolutional ResNet that maps an RGB image to a descriptor image.

As in the original DON (docs/background.md, section "Self-supervised DON training"): a dilated ResNet
encoder with output stride 8, a 1x1 convolution to ``D`` channels and bilinear upsampling back to the
input size; archs with a decoder (``"resnet-lite-fine"``) first refine the stride-8 features with the
encoder's stride-4 and stride-2 features. :class:`DenseObjectNet` is the network, :data:`ARCHS` its sizes.
"""

from __future__ import annotations

import pickle
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from don_gym.errors import CheckpointError, DonGymError

__all__ = [
    "ARCHS",
    "DEFAULT_ARCH",
    "ENCODER_STRIDE",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "ArchSpec",
    "BasicBlock",
    "DecoderStage",
    "DenseObjectNet",
    "DilatedResNet",
    "PretrainedReport",
    "count_parameters",
    "torch_device",
    "validate_arch",
    "validate_device_name",
]

IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)

#: Spatial downsampling between the input and the encoder's last stage.
ENCODER_STRIDE = 8


@dataclass(frozen=True)
class ArchSpec:
    """Shape of a dilated ResNet encoder.

    ``stem`` is ``"imagenet"`` (7x7 stride-2 conv + 3x3 stride-2 max-pool, torchvision
    names ``conv1``/``bn1``) or ``"fast"`` (two 3x3 stride-2 convs of ``stem_widths``).
    ``decoder_widths`` (at most 2) are the channels of the decoder stages at stride 4 and 2: each
    upsamples the previous features x2, joins the encoder's features of that stride and applies a 3x3
    convolution; ``()`` puts the descriptor head on the stride-8 features.
    """

    blocks: tuple[int, int, int, int]
    widths: tuple[int, int, int, int]
    stem: str
    stem_widths: tuple[int, ...]
    torchvision_layout: bool
    description: str = field(default="", compare=False)
    decoder_widths: tuple[int, ...] = ()

    @property
    def output_stride(self) -> int:
        """Spatial downsampling between the input and the descriptor head (8, 4 or 2)."""
        return ENCODER_STRIDE >> len(self.decoder_widths)


#: Encoder sizes. ``"resnet34"`` is the paper's network (BasicBlock [3, 4, 6, 3], widths 64-512, 7x7 stem
#: and max-pool), ``"resnet18"`` the same layout with [2, 2, 2, 2] blocks; both use torchvision's ResNet
#: parameter names, so ImageNet weights in that layout load with ``pretrained_path=``. ``"resnet-lite"``
#: (:data:`DEFAULT_ARCH`) has [2, 2, 2, 2] blocks of widths (24, 48, 64, 96) and a stem of two stride-2 3x3
#: convolutions (16, 24 channels): at output stride 8 the dilated stages run on 1/64 of the input's pixels
#: and their cost grows with width squared, so narrow stages keep CPU inference cheap (benchmarks/RESULTS.md,
#: "train-speed") while the dilation keeps the receptive field at 431 px, more than a whole 320x240 frame.
#: Its 0.55 M parameters make a 2.2 MB float32 checkpoint; it has no ImageNet weights and trains from scratch.
#: ``"resnet-lite-fine"`` adds a decoder to output stride 2 (32 and 16 channels): at stride 8 a pixel a few
#: pixels inside the part's silhouette gets a blend of the part's and the background's descriptors, which a
#: supervised-mask network's background channel turns into matches off the part (docs/reproduction.md, (b)).
ARCHS: dict[str, ArchSpec] = {
    "resnet-lite": ArchSpec(
        (2, 2, 2, 2), (24, 48, 64, 96), "fast", (16, 24), False, "CPU-sized ResNet, trains from scratch"
    ),
    "resnet-lite-fine": ArchSpec(
        (2, 2, 2, 2),
        (24, 48, 64, 96),
        "fast",
        (16, 24),
        False,
        "resnet-lite with a decoder to output stride 2 (sharper silhouettes)",
        decoder_widths=(32, 16),
    ),
    "resnet18": ArchSpec((2, 2, 2, 2), (64, 128, 256, 512), "imagenet", (64,), True, "ResNet-18, dilated"),
    "resnet34": ArchSpec((3, 4, 6, 3), (64, 128, 256, 512), "imagenet", (64,), True, "ResNet-34, dilated (paper)"),
}
DEFAULT_ARCH = "resnet-lite"


def validate_device_name(name: str) -> str:
    """``name`` if it names a device :func:`torch_device` knows, else a :class:`DonGymError`; looks at no hardware."""
    if not isinstance(name, str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", name):
        raise DonGymError(f"device {name!r} is unknown; expected auto, cpu, cuda or cuda:N")
    return name


def torch_device(name: str) -> torch.device:
    """The torch device a user names: ``"auto"`` (CUDA if torch sees a GPU, else the CPU), ``"cpu"``,
    ``"cuda"`` or ``"cuda:N"``; a :class:`DonGymError` for another name or a GPU that is not there."""
    validate_device_name(name)
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        built = "a torch built without CUDA" if torch.version.cuda is None else "no CUDA GPU visible"
        raise DonGymError(f"device {name!r}: this machine has {built} (torch {torch.__version__}); use --device cpu")
    index = int(name.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise DonGymError(f"device {name!r}: only {torch.cuda.device_count()} GPU(s) are visible")
    return torch.device("cuda", index)


def validate_arch(arch: str) -> ArchSpec:
    if arch not in ARCHS:
        raise DonGymError(f"network arch {arch!r} is unknown; expected one of {sorted(ARCHS)}")
    return ARCHS[arch]


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with a residual connection (ResNet BasicBlock), with dilation."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, dilation_first: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(
            in_channels, out_channels, 3, stride, dilation_first, dilation=dilation_first, bias=False
        )
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, dilation, dilation=dilation, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != out_channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False), nn.BatchNorm2d(out_channels)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = F.relu(self.bn1(self.conv1(x)), inplace=True)
        out = self.bn2(self.conv2(out))
        return F.relu(out + identity, inplace=True)


class DilatedResNet(nn.Module):
    """ResNet encoder with output stride 8: stages 3 and 4 use dilation 2 and 4 instead of stride.

    Parameter names follow torchvision's ResNet (``conv1``, ``bn1``, ``layer1.0.conv1``,
    ``layer2.0.downsample.0``, ...) for the ``"imagenet"`` stem; the ``"fast"`` stem uses
    ``stem_conv1``/``stem_bn1``/``stem_conv2``/``stem_bn2`` so that it can never be
    mistaken for torchvision's 7x7 stem.
    """

    def __init__(self, spec: ArchSpec) -> None:
        super().__init__()
        self.spec = spec
        if spec.stem == "imagenet":
            self.conv1 = nn.Conv2d(3, spec.stem_widths[0], 7, 2, 3, bias=False)
            self.bn1 = nn.BatchNorm2d(spec.stem_widths[0])
            self.maxpool = nn.MaxPool2d(3, 2, 1)
        elif spec.stem == "fast":
            self.stem_conv1 = nn.Conv2d(3, spec.stem_widths[0], 3, 2, 1, bias=False)
            self.stem_bn1 = nn.BatchNorm2d(spec.stem_widths[0])
            self.stem_conv2 = nn.Conv2d(spec.stem_widths[0], spec.stem_widths[1], 3, 2, 1, bias=False)
            self.stem_bn2 = nn.BatchNorm2d(spec.stem_widths[1])
        else:
            raise ValueError(f"unknown stem {spec.stem!r}")
        in_channels = spec.stem_widths[-1]
        # Stage strides/dilations for output stride 8: (stride, dilation) per stage. As in
        # DeepLab, the first conv of a newly dilated stage keeps the previous dilation.
        plan = ((1, 1), (2, 1), (1, 2), (1, 4))
        previous_dilation = 1
        for index, (count, width, (stride, dilation)) in enumerate(
            zip(spec.blocks, spec.widths, plan, strict=True), start=1
        ):
            blocks = []
            for b in range(count):
                blocks.append(
                    BasicBlock(
                        in_channels, width, stride if b == 0 else 1, previous_dilation if b == 0 else dilation, dilation
                    )
                )
                in_channels = width
            setattr(self, f"layer{index}", nn.Sequential(*blocks))
            previous_dilation = dilation
        self.out_channels = in_channels
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)

    def skip_channels(self) -> tuple[int, int]:
        """Channels of :meth:`features`' stride-4 and stride-2 maps."""
        return self.spec.widths[0], self.spec.stem_widths[0]

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The normalised input's features at stride 8 (the last stage), 4 (stage 1) and 2 (the stem's first
        convolution)."""
        if self.spec.stem == "imagenet":
            stride_2 = F.relu(self.bn1(self.conv1(x)), inplace=True)
            x = self.maxpool(stride_2)
        else:
            stride_2 = F.relu(self.stem_bn1(self.stem_conv1(x)), inplace=True)
            x = F.relu(self.stem_bn2(self.stem_conv2(stride_2)), inplace=True)
        stride_4 = self.layer1(x)
        return self.layer4(self.layer3(self.layer2(stride_4))), stride_4, stride_2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)[0]


class DecoderStage(nn.Module):
    """Upsample x2 (to the skip's size), join the encoder's skip features, 3x3 convolution + BN + ReLU."""

    def __init__(self, in_channels: int, skip_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels + skip_channels, out_channels, 3, 1, 1, bias=False)
        self.bn = nn.BatchNorm2d(out_channels)
        nn.init.kaiming_normal_(self.conv.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        joined = torch.cat([up, skip], dim=1).contiguous(memory_format=torch.channels_last)
        return F.relu(self.bn(self.conv(joined)), inplace=True)


@dataclass(frozen=True)
class PretrainedReport:
    """What :meth:`DenseObjectNet.load_pretrained_encoder` did, by torchvision key name."""

    loaded: tuple[str, ...]
    missing: tuple[str, ...]  # encoder keys the file lacks (kept at their initialisation)
    unexpected: tuple[str, ...]  # file keys the encoder does not have (not loaded)
    ignored: tuple[str, ...]  # classifier keys (fc.*), never used by a DON


def _read_state_dict_file(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise CheckpointError(f"pretrained weights {path}: no such file")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            # weights_only: a .pth is a pickle; never execute code from a weights file.
            state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        global_name = re.search(r"Unsupported global: GLOBAL (\S+)", str(exc))
        if global_name:
            raise CheckpointError(
                f"pretrained weights {path}: holds a pickled {global_name[1]}, not only tensors; expected a state "
                "dict, e.g. torch.save(model.state_dict(), path)"
            ) from None
        raise CheckpointError(
            f"pretrained weights {path}: cannot be read as a state dict (not a torch or safetensors file, or damaged)"
        ) from None
    except Exception as exc:  # any other parse failure also means a damaged file
        detail = (str(exc).strip().splitlines() or [""])[0]
        raise CheckpointError(
            f"pretrained weights {path}: cannot be read as a state dict ({type(exc).__name__}: {detail})"
        ) from exc
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise CheckpointError(
            f"pretrained weights {path}: expected a state dict (names to tensors), got a {type(state).__name__}"
        )
    not_tensor = next((k for k, v in state.items() if not isinstance(v, torch.Tensor)), None)
    if not_tensor is not None:
        raise CheckpointError(
            f"pretrained weights {path}: expected a state dict of tensors, but {not_tensor!r} is a "
            f"{type(state[not_tensor]).__name__}"
        )
    # Weights saved from nn.DataParallel carry a "module." prefix.
    return {k.removeprefix("module."): v for k, v in state.items()}


class DenseObjectNet(nn.Module):
    """Dense Object Net: ``(B, 3, H, W)`` RGB in [0, 1] -> ``(B, D, H, W)`` descriptors.

    The ImageNet mean/std normalisation happens inside the model. Tensors are kept channels-last
    internally, which suits oneDNN on CPU.

    Args:
        arch: a key of :data:`ARCHS`.
        descriptor_dim: ``D``, the number of descriptor channels.
        pretrained_path: optional local file of ImageNet weights in torchvision's ResNet
            state-dict layout (``.pth`` or ``.safetensors``); only for archs with
            ``torchvision_layout``. Loaded strictly (see :meth:`load_pretrained_encoder`).
            Nothing is ever downloaded.
        normalization_mean, normalization_std: per-channel RGB statistics subtracted and
            divided inside :meth:`forward` (ImageNet by default, matching pretrained weights).
    """

    def __init__(
        self,
        arch: str = DEFAULT_ARCH,
        descriptor_dim: int = 3,
        pretrained_path: str | Path | None = None,
        normalization_mean: tuple[float, float, float] = IMAGENET_MEAN,
        normalization_std: tuple[float, float, float] = IMAGENET_STD,
    ) -> None:
        super().__init__()
        spec = validate_arch(arch)
        if int(descriptor_dim) != descriptor_dim or descriptor_dim < 1:
            raise DonGymError(f"descriptor_dim must be a positive integer, got {descriptor_dim!r}")
        if len(normalization_mean) != 3 or len(normalization_std) != 3 or min(normalization_std) <= 0:
            raise DonGymError(
                f"normalization mean/std must be 3 values each with std > 0, got {normalization_mean}, "
                f"{normalization_std}"
            )
        self.arch = arch
        self.descriptor_dim = int(descriptor_dim)
        self.normalization_mean = tuple(float(m) for m in normalization_mean)
        self.normalization_std = tuple(float(s) for s in normalization_std)
        # Not persistent: checkpoints record them as metadata, and the state dict stays
        # exactly the learned weights.
        self.register_buffer("mean", torch.tensor(self.normalization_mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(self.normalization_std).view(1, 3, 1, 1), persistent=False)
        self.encoder = DilatedResNet(spec)
        self.output_stride = spec.output_stride
        self.decoder = nn.ModuleList()
        channels = self.encoder.out_channels
        for width, skip in zip(spec.decoder_widths, self.encoder.skip_channels(), strict=False):
            self.decoder.append(DecoderStage(channels, skip, width))
            channels = width
        self.head = nn.Conv2d(channels, self.descriptor_dim, 1)
        if pretrained_path is not None:
            self.load_pretrained_encoder(pretrained_path)
        self.to(memory_format=torch.channels_last)

    def forward_low_res(self, rgb: torch.Tensor) -> torch.Tensor:
        """Descriptors at the arch's output stride ``s`` (:attr:`output_stride`): ``(B, D, ceil(H/s), ceil(W/s))``,
        before upsampling."""
        if rgb.ndim != 4 or rgb.shape[1] != 3:
            raise DonGymError(f"DenseObjectNet input must be (B, 3, H, W) RGB in [0, 1], got shape {tuple(rgb.shape)}")
        if not rgb.is_floating_point():
            raise DonGymError(f"DenseObjectNet input must be a float tensor in [0, 1], got dtype {rgb.dtype}")
        x = ((rgb - self.mean) / self.std).contiguous(memory_format=torch.channels_last)
        features, *skips = self.encoder.features(x)
        for stage, skip in zip(self.decoder, skips, strict=False):
            features = stage(features, skip)
        return self.head(features)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` float RGB in [0, 1] -> ``(B, D, H, W)`` descriptors (contiguous NCHW)."""
        low = self.forward_low_res(rgb)
        return F.interpolate(low, size=rgb.shape[-2:], mode="bilinear", align_corners=False).contiguous()

    def descriptor_image(self, rgb_uint8_hwc: np.ndarray) -> np.ndarray:
        """One frame: uint8 ``(H, W, 3)`` RGB -> float32 ``(H, W, D)`` descriptors.

        Runs in eval mode without autograd on the model's device; the previous train/eval
        mode is restored afterwards.
        """
        rgb = np.asarray(rgb_uint8_hwc)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise DonGymError(
                f"descriptor_image expects a uint8 (H, W, 3) RGB image, got {rgb.dtype} of shape {rgb.shape}"
            )
        device = self.head.weight.device
        was_training = self.training
        self.eval()
        try:
            with torch.inference_mode():
                x = torch.from_numpy(np.ascontiguousarray(rgb)).to(device).permute(2, 0, 1)[None]
                descriptors = self(x.float().div_(255.0))[0].permute(1, 2, 0)
                return np.ascontiguousarray(descriptors.float().cpu().numpy())
        finally:
            self.train(was_training)

    def load_pretrained_encoder(self, path: str | Path, strict: bool = True) -> PretrainedReport:
        """Load ImageNet encoder weights saved in torchvision's ResNet layout from a local file.

        Shapes must match exactly. With ``strict`` (the default), any encoder key missing
        from the file or any non-classifier file key the encoder lacks is an error, so a
        ResNet-18 file never half-initialises a ResNet-34. With ``strict=False`` the
        matching keys are loaded and the rest reported with a warning. ``fc.*`` is ignored
        and ``num_batches_tracked`` is optional (old torchvision files lack it).
        """
        path = Path(path)
        spec = ARCHS[self.arch]
        if not spec.torchvision_layout:
            raise CheckpointError(
                f"pretrained weights {path}: arch {self.arch!r} has no ImageNet layout; "
                f"use one of {sorted(k for k, v in ARCHS.items() if v.torchvision_layout)}"
            )
        state = _read_state_dict_file(path)
        own = self.encoder.state_dict()
        ignored = sorted(k for k in state if k.startswith("fc."))
        candidate = {k: v for k, v in state.items() if not k.startswith("fc.")}
        optional = "num_batches_tracked"
        missing = sorted(k for k in own if k not in candidate and not k.endswith(optional))
        unexpected = sorted(k for k in candidate if k not in own)
        mismatched = [
            f"{k}: file {tuple(v.shape)}, {self.arch} {tuple(own[k].shape)}"
            for k, v in candidate.items()
            if k in own and tuple(v.shape) != tuple(own[k].shape)
        ]
        if mismatched:
            raise CheckpointError(
                f"pretrained weights {path}: {len(mismatched)} tensor shapes differ from arch {self.arch!r}: "
                + "; ".join(mismatched[:5])
                + (" ..." if len(mismatched) > 5 else "")
            )
        if strict and (missing or unexpected):
            raise CheckpointError(
                f"pretrained weights {path} do not match arch {self.arch!r}: "
                f"{len(missing)} encoder keys missing from the file {missing[:5]}"
                f"{' ...' if len(missing) > 5 else ''}, {len(unexpected)} unexpected keys {unexpected[:5]}"
                f"{' ...' if len(unexpected) > 5 else ''}"
            )
        loaded = sorted(k for k in candidate if k in own)
        if not loaded:
            raise CheckpointError(f"pretrained weights {path}: no key matches arch {self.arch!r}")
        with torch.no_grad():
            for key in loaded:
                own[key].copy_(candidate[key].to(own[key].dtype))
        if missing or unexpected:
            warnings.warn(
                f"pretrained weights {path}: loaded {len(loaded)} tensors; {len(missing)} encoder keys missing "
                f"{missing[:5]}, {len(unexpected)} unexpected {unexpected[:5]}",
                stacklevel=2,
            )
        return PretrainedReport(tuple(loaded), tuple(missing), tuple(unexpected), tuple(ignored))

    def extra_repr(self) -> str:
        return f"arch={self.arch!r}, descriptor_dim={self.descriptor_dim}"


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
