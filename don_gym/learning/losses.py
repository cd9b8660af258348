"""Training losses of Dense Object Nets: the supervised l2 loss and the pixelwise contrastive loss.

:func:`supervised_l2_loss` is Kupcsik et al. 2021, eq. (l2loss); :func:`pixelwise_contrastive_loss` is the
loss of Florence et al. 2018 (docs/background.md, section "Self-supervised DON training").
Pixel indices are ``(u, v)`` = (column, row), as everywhere in don_gym.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from don_gym.errors import DonGymError
from don_gym.learning.methods import METHODS, SUPERVISED_METHODS, is_supervised, validate_method

__all__ = [
    "HARD_BACKGROUND_BAND_PX",
    "METHODS",
    "SUPERVISED_METHODS",
    "is_supervised",
    "validate_method",
    "supervised_l2_loss",
    "supervised_l2_loss_terms",
    "pixelwise_contrastive_loss",
    "contrastive_loss_from_correspondences",
    "batch_contrastive_loss",
]

#: Margins of the paper's self-supervised baseline (the original code defaults to 0.5 / 0.5).
DEFAULT_OBJECT_MARGIN = 0.5
DEFAULT_BACKGROUND_MARGIN = 2.5


#: Background pixels within this many pixels of the object (the network's output stride) are left out of the hard
#: background pixels: a match there is still near the part, and pushing the blend at the silhouette towards the
#: background only moves the part's own edge descriptors towards it.
HARD_BACKGROUND_BAND_PX = 8


def _hardest_mean(squared_error: torch.Tensor, on_region: torch.Tensor, fraction: float) -> torch.Tensor:
    """Per image ``(B,)``: the mean of the largest ``ceil(fraction x H x W)`` squared errors inside the region."""
    error = (squared_error * on_region).flatten(1)
    count = on_region.sum(dim=(1, 2))
    hardest = math.ceil(fraction * error.shape[1])
    # Pixels outside the region count 0; where the region has fewer pixels than ``hardest`` the top-k includes
    # zeros, so divide by the region's pixels among them.
    taken = torch.minimum(count, torch.full_like(count, float(hardest)))
    return error.topk(hardest, dim=1).values.sum(dim=1) / taken.clamp(min=1)


def supervised_l2_loss_terms(
    pred: torch.Tensor,
    target: torch.Tensor,
    object_mask: torch.Tensor,
    hard_object_fraction: float = 0.0,
    hard_background_fraction: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image object and background terms of the supervised l2 loss, ``(B,)`` each.

    ``pred`` and ``target`` are ``(B, D, H, W)``, ``object_mask`` is bool ``(B, H, W)``.
    The object term is the squared error summed over descriptor channels and object pixels,
    divided by the number of object pixels; likewise for the background. An image without
    object pixels (or without background pixels) gets 0 for that term.

    ``hard_object_fraction`` and ``hard_background_fraction``, each in [0, 1): with f > 0 the term also adds the
    mean squared error of the image's worst ``ceil(f x H x W)`` pixels of its region (for the background: those
    more than :data:`HARD_BACKGROUND_BAND_PX` from the object). A plain mean hardly sees a
    few pixels gone wrong: part pixels whose descriptors collapse to the background's (where steel mirrors the
    table) or background pixels that drift towards the part's, yet each of them can take a match anywhere in
    the frame.
    """
    if pred.ndim != 4 or pred.shape != target.shape:
        raise DonGymError(
            f"supervised_l2_loss: pred and target must both be (B, D, H, W), got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )
    expected_mask = (pred.shape[0], *pred.shape[2:])
    if tuple(object_mask.shape) != expected_mask:
        raise DonGymError(
            f"supervised_l2_loss: object_mask must be (B, H, W) = {expected_mask}, got {tuple(object_mask.shape)}"
        )
    if object_mask.dtype != torch.bool:
        raise DonGymError(f"supervised_l2_loss: object_mask must be bool, got {object_mask.dtype}")
    fractions = {"hard_object_fraction": hard_object_fraction, "hard_background_fraction": hard_background_fraction}
    for name, fraction in fractions.items():
        if not 0.0 <= fraction < 1.0:
            raise DonGymError(f"supervised_l2_loss: {name} must be in [0, 1), got {fraction}")
    # float32 even under autocast: the sums run over ~10^5 pixels.
    squared_error = (pred.float() - target.float()).pow(2).sum(dim=1)
    on_object = object_mask.to(squared_error.dtype)
    on_background = 1.0 - on_object
    object_count = on_object.sum(dim=(1, 2))
    background_count = on_object[0].numel() - object_count
    object_term = (squared_error * on_object).sum(dim=(1, 2)) / object_count.clamp(min=1)
    background_term = (squared_error * on_background).sum(dim=(1, 2)) / background_count.clamp(min=1)
    if hard_object_fraction > 0.0:
        object_term = object_term + _hardest_mean(squared_error, on_object, hard_object_fraction)
    if hard_background_fraction > 0.0:
        band = HARD_BACKGROUND_BAND_PX
        near_object = torch.nn.functional.max_pool2d(on_object[:, None], 2 * band + 1, stride=1, padding=band)[:, 0]
        far_background = on_background * (1.0 - near_object)
        background_term = background_term + _hardest_mean(squared_error, far_background, hard_background_fraction)
    return object_term, background_term


def supervised_l2_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    object_mask: torch.Tensor,
    hard_object_fraction: float = 0.0,
    hard_background_fraction: float = 0.0,
) -> torch.Tensor:
    """The paper's l2 loss (eq. l2loss), averaged over the batch: a scalar tensor.

    Per image, the object term plus the background term, each normalised by its pixel count so
    that a small object is not drowned by its background. See :func:`supervised_l2_loss_terms`
    for shapes; use it to log the two terms.
    """
    object_term, background_term = supervised_l2_loss_terms(
        pred, target, object_mask, hard_object_fraction, hard_background_fraction
    )
    return (object_term + background_term).mean()


def _pixels(name: str, uv: Any, height: int, width: int, device: torch.device) -> torch.Tensor:
    """Validate an ``(n, 2)`` integer array of (u, v) pixels inside an ``H x W`` image."""
    if isinstance(uv, np.ndarray) and not np.issubdtype(uv.dtype, np.integer):
        raise DonGymError(f"{name} must hold integer (u, v) pixels, got dtype {uv.dtype}")
    tensor = torch.as_tensor(uv, device=device)
    if tensor.is_floating_point() or tensor.is_complex() or tensor.dtype == torch.bool:
        raise DonGymError(f"{name} must hold integer (u, v) pixels, got dtype {tensor.dtype}")
    if tensor.ndim != 2 or tensor.shape[1] != 2:
        raise DonGymError(f"{name} must have shape (n, 2) of (u, v) pixels, got {tuple(tensor.shape)}")
    tensor = tensor.long()
    if tensor.shape[0] > 0:
        u, v = tensor[:, 0], tensor[:, 1]
        if bool((u < 0).any() | (u >= width).any() | (v < 0).any() | (v >= height).any()):
            raise DonGymError(
                f"{name} has pixels outside the {width}x{height} (W x H) image: u in [{int(u.min())}, {int(u.max())}], "
                f"v in [{int(v.min())}, {int(v.max())}]"
            )
    return tensor


def _pair_descriptors(
    name: str, descriptors_a: torch.Tensor, descriptors_b: torch.Tensor, uv_a: Any, uv_b: Any
) -> tuple[torch.Tensor, torch.Tensor]:
    """Descriptors ``(n, D)`` at paired pixels of images a and b."""
    _, height, width = descriptors_a.shape
    a = _pixels(f"{name}_a", uv_a, height, width, descriptors_a.device)
    b = _pixels(f"{name}_b", uv_b, height, width, descriptors_b.device)
    if a.shape[0] != b.shape[0]:
        raise DonGymError(f"{name}_a and {name}_b must pair up, got {a.shape[0]} and {b.shape[0]} pixels")
    return descriptors_a[:, a[:, 1], a[:, 0]].T, descriptors_b[:, b[:, 1], b[:, 0]].T


def pixelwise_contrastive_loss(
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    matches_a: Any,
    matches_b: Any,
    nonmatches_object_a: Any,
    nonmatches_object_b: Any,
    nonmatches_background_a: Any,
    nonmatches_background_b: Any,
    object_margin: float = DEFAULT_OBJECT_MARGIN,
    background_margin: float = DEFAULT_BACKGROUND_MARGIN,
    hard_negative_scaling: bool = True,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Pixelwise contrastive loss of one image pair (Florence et al. 2018), with unnormalised
    descriptors and hard-negative scaling as in the original code.

    Args:
        descriptors_a, descriptors_b: ``(D, H, W)`` unnormalised descriptor images.
        matches_a, matches_b: ``(N, 2)`` integer (u, v) pixels; row i of a matches row i of b.
        nonmatches_object_a/b: ``(M, 2)`` non-corresponding pairs on the object.
        nonmatches_background_a/b: ``(K, 2)`` non-corresponding pairs whose b pixel is background.
        object_margin, background_margin: margins ``M`` of the two non-match kinds.
        hard_negative_scaling: divide the summed non-match terms by the number of hard
            negatives (pairs with a nonzero term) of both kinds, at least 1; otherwise by
            the number of non-match pairs.

    Returns:
        ``(loss, stats)``: loss = match loss + non-match loss, where match loss is the mean
        squared L2 distance over matches and each non-match pair contributes
        ``max(0, margin - ||d_a - d_b||)^2``. ``stats`` holds floats ``loss``,
        ``match_loss``, ``nonmatch_loss``, ``nonmatch_object_loss`` and
        ``nonmatch_background_loss`` (the two parts of ``nonmatch_loss``, same divisor) and
        ints ``num_matches``, ``num_hard_negatives_object``, ``num_hard_negatives_background``.
        Empty index sets contribute 0.
    """
    if descriptors_a.ndim != 3 or descriptors_a.shape != descriptors_b.shape:
        raise DonGymError(
            f"contrastive loss: descriptors_a and descriptors_b must both be (D, H, W), got "
            f"{tuple(descriptors_a.shape)} and {tuple(descriptors_b.shape)}"
        )
    if object_margin < 0 or background_margin < 0:
        raise DonGymError(f"margins must be >= 0, got object {object_margin}, background {background_margin}")
    # A zero that stays connected to the graph, so backward() works on a pair without pixels.
    zero = descriptors_a.flatten()[:0].sum() + descriptors_b.flatten()[:0].sum()

    da, db = _pair_descriptors("matches", descriptors_a, descriptors_b, matches_a, matches_b)
    match_loss = (da - db).pow(2).sum(dim=1).mean() if da.shape[0] else zero

    def hinge_terms(name: str, uv_a: Any, uv_b: Any, margin: float) -> torch.Tensor:
        na, nb = _pair_descriptors(name, descriptors_a, descriptors_b, uv_a, uv_b)
        # vector_norm has a zero subgradient at 0, where a hand-written sqrt would give NaN.
        distance = torch.linalg.vector_norm(na - nb, dim=1)
        return (margin - distance).clamp(min=0).pow(2)

    object_terms = hinge_terms("nonmatches_object", nonmatches_object_a, nonmatches_object_b, object_margin)
    background_terms = hinge_terms(
        "nonmatches_background", nonmatches_background_a, nonmatches_background_b, background_margin
    )
    hard_object = int((object_terms > 0).sum())
    hard_background = int((background_terms > 0).sum())
    if hard_negative_scaling:
        divisor = max(hard_object + hard_background, 1)
    else:
        divisor = max(object_terms.shape[0] + background_terms.shape[0], 1)
    nonmatch_object = object_terms.sum() / divisor if object_terms.shape[0] else zero
    nonmatch_background = background_terms.sum() / divisor if background_terms.shape[0] else zero
    nonmatch_loss = nonmatch_object + nonmatch_background
    loss = match_loss + nonmatch_loss
    stats = {
        "loss": float(loss.detach()),
        "match_loss": float(match_loss.detach()),
        "nonmatch_loss": float(nonmatch_loss.detach()),
        "nonmatch_object_loss": float(nonmatch_object.detach()),
        "nonmatch_background_loss": float(nonmatch_background.detach()),
        "num_matches": int(da.shape[0]),
        "num_hard_negatives_object": hard_object,
        "num_hard_negatives_background": hard_background,
    }
    return loss, stats


def contrastive_loss_from_correspondences(
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    correspondences: Any,
    object_margin: float = DEFAULT_OBJECT_MARGIN,
    background_margin: float = DEFAULT_BACKGROUND_MARGIN,
    hard_negative_scaling: bool = True,
) -> tuple[torch.Tensor, dict[str, float]]:
    """:func:`pixelwise_contrastive_loss` with the pixels read from a correspondences object.

    ``correspondences`` is anything with the attributes of
    ``don_gym.data.correspondences.Correspondences``: ``matches_a``, ``matches_b``,
    ``nonmatches_object_a``, ``nonmatches_object_b``, ``nonmatches_background_a``,
    ``nonmatches_background_b`` (each ``(n, 2)`` integer (u, v), numpy or torch).
    """
    names = (
        "matches_a",
        "matches_b",
        "nonmatches_object_a",
        "nonmatches_object_b",
        "nonmatches_background_a",
        "nonmatches_background_b",
    )
    missing = [n for n in names if not hasattr(correspondences, n)]
    if missing:
        raise DonGymError(
            f"contrastive loss: {type(correspondences).__name__} is not a correspondences object, it lacks {missing}"
        )
    return pixelwise_contrastive_loss(
        descriptors_a,
        descriptors_b,
        *(getattr(correspondences, n) for n in names),
        object_margin=object_margin,
        background_margin=background_margin,
        hard_negative_scaling=hard_negative_scaling,
    )


def batch_contrastive_loss(
    descriptors_a: torch.Tensor,
    descriptors_b: torch.Tensor,
    correspondences: Sequence[Any],
    object_margin: float = DEFAULT_OBJECT_MARGIN,
    background_margin: float = DEFAULT_BACKGROUND_MARGIN,
    hard_negative_scaling: bool = True,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Mean contrastive loss over a batch of pairs: ``(B, D, H, W)`` twice and B correspondences.

    Loss values in the stats are batch means; counts are batch sums.
    """
    if descriptors_a.ndim != 4 or descriptors_a.shape != descriptors_b.shape:
        raise DonGymError(
            f"batch contrastive loss: descriptors must both be (B, D, H, W), got {tuple(descriptors_a.shape)} and "
            f"{tuple(descriptors_b.shape)}"
        )
    if len(correspondences) != descriptors_a.shape[0]:
        raise DonGymError(
            f"batch contrastive loss: {descriptors_a.shape[0]} image pairs but {len(correspondences)} correspondences"
        )
    losses = []
    totals: dict[str, float] = {}
    for i, corr in enumerate(correspondences):
        loss, stats = contrastive_loss_from_correspondences(
            descriptors_a[i], descriptors_b[i], corr, object_margin, background_margin, hard_negative_scaling
        )
        losses.append(loss)
        for key, value in stats.items():
            totals[key] = totals.get(key, 0) + value
    batch = len(losses)
    summary = {k: (v if k.startswith("num_") else v / batch) for k, v in totals.items()}
    return torch.stack(losses).mean(), summary
