"""Training-time image augmentation that never moves a pixel, so targets and correspondences stay valid.

:func:`augment` applies :func:`randomize_background` (the original DON's, docs/background.md, section
"Self-supervised DON training") and :func:`photometric_jitter` to batched float RGB ``(B, 3, H, W)`` in
[0, 1]; the same ``torch.Generator`` state gives the same output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from don_gym.errors import DonGymError

__all__ = [
    "BACKGROUND_KINDS",
    "NOISE_CELL_SIZES_PX",
    "PATTERN_PERIOD_PX",
    "AugmentConfig",
    "augment",
    "photometric_jitter",
    "random_backgrounds",
    "randomize_background",
]

#: Background kinds of :func:`randomize_background`, chosen uniformly.
BACKGROUND_KINDS = ("colour", "gradient", "noise")
#: Cell sizes in pixels of the noise background: 1 = per-pixel speckle, larger = smoother blobs.
NOISE_CELL_SIZES_PX = (1, 2, 4, 8, 16)
#: Range of the period in pixels of the pattern backgrounds (stripes, checks), drawn log-uniformly.
PATTERN_PERIOD_PX = (6.0, 96.0)

# RGB <-> YIQ (NTSC): Y is luma, I/Q span the chroma plane, so rotating (I, Q) shifts hue.
_RGB_TO_YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
_LUMA = _RGB_TO_YIQ[0]


@dataclass(frozen=True)
class AugmentConfig:
    """Strengths of :func:`augment`; a zero switches that part off.

    Attributes:
        background_probability: probability per image of randomising the background.
        brightness: gain drawn from ``[1 - brightness, 1 + brightness]``.
        contrast: contrast factor from ``[1 - contrast, 1 + contrast]`` about the image mean.
        saturation: saturation factor from ``[1 - saturation, 1 + saturation]``.
        hue: hue rotation from ``[-hue, hue]`` in turns (0.5 = half the colour wheel).
        noise_std: Gaussian pixel noise with a standard deviation drawn from ``[0, noise_std]``.
        pattern_probability: probability that a randomised background is a sharp two-colour pattern,
            stripes or checks (:func:`random_backgrounds`), instead of a colour, gradient or noise; 0
            draws no pattern and no random numbers for one.
    """

    background_probability: float = 0.5
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.03
    noise_std: float = 0.02
    pattern_probability: float = 0.0

    def __post_init__(self) -> None:
        for name in ("background_probability", "pattern_probability"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise DonGymError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("brightness", "contrast", "saturation"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise DonGymError(f"{name} jitter must be in [0, 1), got {getattr(self, name)}")
        if not 0.0 <= self.hue <= 0.5:
            raise DonGymError(f"hue jitter must be in [0, 0.5] turns, got {self.hue}")
        if self.noise_std < 0:
            raise DonGymError(f"noise_std must be >= 0, got {self.noise_std}")


def _check_rgb(rgb: torch.Tensor) -> None:
    if rgb.ndim != 4 or rgb.shape[1] != 3 or not rgb.is_floating_point():
        raise DonGymError(f"augmentation expects float RGB (B, 3, H, W) in [0, 1], got {rgb.dtype} {tuple(rgb.shape)}")


def _uniform(
    shape: tuple[int, ...], low: float, high: float, generator: torch.Generator | None, like: torch.Tensor
) -> torch.Tensor:
    device = generator.device if generator is not None else like.device
    values = torch.rand(shape, generator=generator, device=device, dtype=torch.float32)
    return (low + (high - low) * values).to(device=like.device, dtype=like.dtype)


def _random_index(batch: int, count: int, generator: torch.Generator | None, like: torch.Tensor) -> torch.Tensor:
    """``(batch,)`` uniform integers in ``[0, count)``."""
    return (_uniform((batch,), 0.0, 1.0, generator, like).float() * count).long().clamp(max=count - 1)


def random_backgrounds(
    batch: int,
    height: int,
    width: int,
    generator: torch.Generator | None,
    like: torch.Tensor,
    pattern_probability: float = 0.0,
) -> torch.Tensor:
    """``(batch, 3, H, W)`` random backgrounds in [0, 1], each a colour, a random linear colour gradient
    or noise (uniform colours on a grid of a random cell size, from per-pixel speckle to smooth blobs);
    with ``pattern_probability`` > 0, that share of them is instead a sharp two-colour pattern: stripes
    or checks at a random angle, phase and period (:data:`PATTERN_PERIOD_PX`, pixels)."""
    kind = _random_index(batch, len(BACKGROUND_KINDS), generator, like)
    colour_a = _uniform((batch, 3, 1, 1), 0.0, 1.0, generator, like)
    colour_b = _uniform((batch, 3, 1, 1), 0.0, 1.0, generator, like)
    # Gradient: the position along a random direction, rescaled to [0, 1] over the image.
    angle = _uniform((batch, 1, 1, 1), 0.0, 2.0 * math.pi, generator, like)
    ys = torch.linspace(-1.0, 1.0, height, device=like.device, dtype=like.dtype).view(1, 1, height, 1)
    xs = torch.linspace(-1.0, 1.0, width, device=like.device, dtype=like.dtype).view(1, 1, 1, width)
    along = torch.cos(angle) * xs + torch.sin(angle) * ys
    low = along.amin(dim=(2, 3), keepdim=True)
    high = along.amax(dim=(2, 3), keepdim=True)
    t = (along - low) / (high - low).clamp(min=1e-6)
    gradient = colour_a + (colour_b - colour_a) * t
    # Noise: uniform colours on a grid of a random cell size per image, bilinearly upsampled.
    cells = _random_index(batch, len(NOISE_CELL_SIZES_PX), generator, like)
    noise_images = []
    for index in cells.tolist():
        cell = NOISE_CELL_SIZES_PX[index]
        coarse = _uniform((1, 3, math.ceil(height / cell), math.ceil(width / cell)), 0.0, 1.0, generator, like)
        if cell > 1:
            coarse = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
        noise_images.append(coarse)
    noise = torch.cat(noise_images)
    colour = colour_a.expand(batch, 3, height, width)
    selector = kind.view(batch, 1, 1, 1)
    background = torch.where(selector == 0, colour, torch.where(selector == 1, gradient, noise))
    if pattern_probability <= 0.0:
        return background
    # Sharp, high-contrast periodic patterns: where the networks' matches far off the part landed on
    # unseen scenes (striped table tops), which the smooth kinds above never show. The shipped recipe
    # leaves them out: on the development scenes they moved the far matches elsewhere rather than
    # removing them (docs/background.md, "Training data").
    chosen = _uniform((batch, 1, 1, 1), 0.0, 1.0, generator, like) < pattern_probability
    checks = _uniform((batch, 1, 1, 1), 0.0, 1.0, generator, like) < 0.5
    low, high = (math.log(p) for p in PATTERN_PERIOD_PX)
    period = torch.exp(_uniform((batch, 1, 1, 1), low, high, generator, like))
    angle = _uniform((batch, 1, 1, 1), 0.0, math.pi, generator, like)
    phase = _uniform((batch, 2, 1, 1), 0.0, 1.0, generator, like)
    pixel_ys = torch.arange(height, device=like.device, dtype=like.dtype).view(1, 1, height, 1)
    pixel_xs = torch.arange(width, device=like.device, dtype=like.dtype).view(1, 1, 1, width)
    across = (torch.cos(angle) * pixel_xs + torch.sin(angle) * pixel_ys) / period + phase[:, :1]
    along = (-torch.sin(angle) * pixel_xs + torch.cos(angle) * pixel_ys) / period + phase[:, 1:]
    first = torch.floor(across).remainder(2.0) < 1.0
    second = torch.floor(along).remainder(2.0) < 1.0
    use_a = torch.where(checks, first ^ second, first)
    pattern = torch.where(use_a, colour_a, colour_b)
    return torch.where(chosen, pattern, background)


def randomize_background(
    rgb: torch.Tensor,
    object_mask: torch.Tensor,
    generator: torch.Generator | None = None,
    probability: float = 0.5,
    pattern_probability: float = 0.0,
) -> torch.Tensor:
    """Replace the background (pixels outside ``object_mask``) of each image with probability ``probability``,
    by :func:`random_backgrounds` (``pattern_probability`` as there).

    ``rgb`` float ``(B, 3, H, W)`` in [0, 1], ``object_mask`` bool ``(B, H, W)``. Returns a
    new tensor; object pixels and unchosen images are bit-identical to the input.
    """
    _check_rgb(rgb)
    batch, _, height, width = rgb.shape
    if tuple(object_mask.shape) != (batch, height, width) or object_mask.dtype != torch.bool:
        raise DonGymError(
            f"object_mask must be bool (B, H, W) = {(batch, height, width)}, got {object_mask.dtype} "
            f"{tuple(object_mask.shape)}"
        )
    if not 0.0 <= probability <= 1.0:
        raise DonGymError(f"background randomisation probability must be in [0, 1], got {probability}")
    if not 0.0 <= pattern_probability <= 1.0:
        raise DonGymError(f"pattern_probability must be in [0, 1], got {pattern_probability}")
    chosen = _uniform((batch,), 0.0, 1.0, generator, rgb) < probability
    background = random_backgrounds(batch, height, width, generator, rgb, pattern_probability)
    replace = (~object_mask & chosen.view(batch, 1, 1)).unsqueeze(1)
    return torch.where(replace, background, rgb)


def photometric_jitter(
    rgb: torch.Tensor, generator: torch.Generator | None = None, config: AugmentConfig = AugmentConfig()
) -> torch.Tensor:
    """Per-image brightness, contrast, saturation, hue and pixel-noise jitter; output clamped to [0, 1].

    Hue is a rotation of the chroma plane in YIQ space; the pixel noise is Gaussian.
    """
    _check_rgb(rgb)
    batch = rgb.shape[0]
    out = rgb * _uniform((batch, 1, 1, 1), 1.0 - config.brightness, 1.0 + config.brightness, generator, rgb)
    luma_weights = _LUMA.to(device=rgb.device, dtype=rgb.dtype).view(1, 3, 1, 1)
    mean_luma = (out * luma_weights).sum(dim=1, keepdim=True).mean(dim=(2, 3), keepdim=True)
    contrast = _uniform((batch, 1, 1, 1), 1.0 - config.contrast, 1.0 + config.contrast, generator, rgb)
    out = mean_luma + (out - mean_luma) * contrast
    # Saturation and hue together: scale and rotate the (I, Q) chroma plane, keep luma Y.
    saturation = _uniform((batch,), 1.0 - config.saturation, 1.0 + config.saturation, generator, rgb)
    theta = _uniform((batch,), -config.hue, config.hue, generator, rgb) * (2.0 * math.pi)
    to_yiq = _RGB_TO_YIQ.to(device=rgb.device, dtype=rgb.dtype)
    chroma = torch.zeros(batch, 3, 3, device=rgb.device, dtype=rgb.dtype)
    chroma[:, 0, 0] = 1.0
    chroma[:, 1, 1] = saturation * torch.cos(theta)
    chroma[:, 1, 2] = -saturation * torch.sin(theta)
    chroma[:, 2, 1] = saturation * torch.sin(theta)
    chroma[:, 2, 2] = saturation * torch.cos(theta)
    colour_transform = torch.linalg.inv(to_yiq) @ chroma @ to_yiq  # (B, 3, 3) in RGB
    out = torch.einsum("bij,bjhw->bihw", colour_transform, out)
    if config.noise_std > 0:
        sigma = _uniform((batch, 1, 1, 1), 0.0, config.noise_std, generator, rgb)
        device = generator.device if generator is not None else rgb.device
        gaussian = torch.randn(tuple(rgb.shape), generator=generator, device=device, dtype=torch.float32)
        out = out + sigma * gaussian.to(device=rgb.device, dtype=rgb.dtype)
    return out.clamp(0.0, 1.0)


def augment(
    rgb: torch.Tensor,
    object_mask: torch.Tensor,
    generator: torch.Generator | None = None,
    config: AugmentConfig = AugmentConfig(),
) -> torch.Tensor:
    """Background randomisation then photometric jitter: ``(B, 3, H, W)`` in, same shape out.

    The background goes first, so the new background is jittered like the rest of the image.
    Random numbers are drawn on the generator's device and moved to the images' device, so a CPU
    generator also serves CUDA images (bit-identical results across devices are not promised).
    """
    out = randomize_background(rgb, object_mask, generator, config.background_probability, config.pattern_probability)
    return photometric_jitter(out, generator, config)
