"""Supervised l2 and pixelwise contrastive losses: hand-computed values, edge cases, and that they train."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from don_gym.errors import DonGymError
from don_gym.learning.losses import (
    HARD_BACKGROUND_BAND_PX,
    batch_contrastive_loss,
    contrastive_loss_from_correspondences,
    pixelwise_contrastive_loss,
    supervised_l2_loss,
    supervised_l2_loss_terms,
)
from don_gym.learning.methods import METHODS, SUPERVISED_TARGET_VARIANT, is_supervised, validate_method
from don_gym.learning.model import DenseObjectNet


def test_methods_are_canonical() -> None:
    assert METHODS == ("supervised", "supervised-edge", "supervised-mask", "self-supervised")
    assert all(validate_method(m) == m for m in METHODS)
    assert set(SUPERVISED_TARGET_VARIANT) == {m for m in METHODS if is_supervised(m)}
    assert not is_supervised("self-supervised")
    with pytest.raises(DonGymError, match="supervised_edge"):
        validate_method("supervised_edge")


# --- supervised l2 loss -----------------------------------------------------------------


def test_supervised_l2_hand_computed() -> None:
    pred = torch.zeros(3, 2, 2, 3)
    target = torch.zeros(3, 2, 2, 3)
    mask = torch.zeros(3, 2, 3, dtype=torch.bool)
    # Image 0: object pixels (row 0, col 0) and (1, 1); squared errors summed over D=2:
    # object 1 + 4 = 5 over 2 pixels -> 2.5; background (1, 0): 1, (1, 2): 9 -> 10 over 4 -> 2.5.
    target[0, 0] = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    target[0, 1] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 3.0]])
    mask[0, 0, 0] = mask[0, 1, 1] = True
    # Image 1: no object pixel, error 1 per channel everywhere -> background term 2, object term 0.
    target[1] = 1.0
    # Image 2: all object, error 1 per channel -> object term 2, background term 0.
    target[2] = 1.0
    mask[2] = True
    object_term, background_term = supervised_l2_loss_terms(pred, target, mask)
    assert object_term.tolist() == pytest.approx([2.5, 0.0, 2.0])
    assert background_term.tolist() == pytest.approx([2.5, 2.0, 0.0])
    assert supervised_l2_loss(pred, target, mask).item() == pytest.approx((5.0 + 2.0 + 2.0) / 3)


def test_supervised_l2_normalises_by_pixel_counts() -> None:
    # 7 object pixels and 93 background pixels: both terms weigh the same whatever the counts.
    pred = torch.zeros(1, 3, 10, 10, requires_grad=True)
    target = torch.zeros(1, 3, 10, 10)
    mask = torch.zeros(1, 10, 10, dtype=torch.bool)
    mask.view(-1)[[3, 17, 31, 45, 59, 73, 88]] = True
    target[0, 0][mask[0]] = 1.0  # error 1 on every object pixel
    target[0, 2][~mask[0]] = 0.5  # error 0.25 on every background pixel
    loss = supervised_l2_loss(pred, target, mask)
    assert loss.item() == pytest.approx(1.0 + 0.25)
    loss.backward()
    # d/dpred of (pred - t)^2 / count = 2 (pred - t) / count.
    assert pred.grad[0, 0][mask[0]] == pytest.approx(torch.full((7,), -2.0 / 7))
    assert pred.grad[0, 2][~mask[0]] == pytest.approx(torch.full((93,), -1.0 / 93))


def test_supervised_l2_hard_background_adds_the_worst_pixels() -> None:
    # 24x24 image, 4 object pixels, 572 background: one background pixel far from the object with squared error 9.
    pred = torch.zeros(1, 1, 24, 24, requires_grad=True)
    target = torch.zeros(1, 1, 24, 24)
    mask = torch.zeros(1, 24, 24, dtype=torch.bool)
    mask[0, :2, :2] = True
    target[0, 0, 20, 20] = 3.0
    plain = supervised_l2_loss_terms(pred, target, mask)[1].item()
    assert plain == pytest.approx(9.0 / 572)
    # f = 0.02 of 576 pixels: the worst 12 (9 and zeros) -> 0.75 added; the plain mean barely sees the outlier.
    hard = supervised_l2_loss_terms(pred, target, mask, hard_background_fraction=0.02)[1]
    assert hard.item() == pytest.approx(9.0 / 572 + 0.75)
    hard.sum().backward()
    assert pred.grad[0, 0, 20, 20].item() == pytest.approx(-6.0 / 572 - 6.0 / 12)
    assert pred.grad[0, 0, 15, 15].item() == 0.0
    # Object pixels never count as background, however bad.
    target[0, 0, 0, 0] = 100.0
    assert supervised_l2_loss_terms(pred, target, mask, 0.0, 0.02)[1].item() == pytest.approx(hard.item())
    # A background pixel within the band around the object is no hard background pixel.
    target[0, 0, 20, 20] = 0.0
    target[0, 0, 2 + HARD_BACKGROUND_BAND_PX - 1, 0] = 3.0
    near = supervised_l2_loss_terms(pred, target, mask, 0.0, 0.02)[1].item()
    assert near == pytest.approx(9.0 / 572)
    with pytest.raises(DonGymError, match="hard_background_fraction"):
        supervised_l2_loss(pred, target, mask, hard_background_fraction=1.0)


def test_supervised_l2_hard_object_pixels_weigh_more() -> None:
    # 20 object pixels, one of them (a mirror-like face the network calls background) with squared error 4.
    pred = torch.zeros(1, 1, 10, 10)
    target = torch.zeros(1, 1, 10, 10)
    mask = torch.zeros(1, 10, 10, dtype=torch.bool)
    mask[0, :2] = True
    target[0, 0, 1, 5] = 2.0
    target[0, 0, 9, 9] = 5.0  # background: never in the object term
    object_term, background_term = supervised_l2_loss_terms(pred, target, mask, hard_object_fraction=0.01)
    assert object_term.item() == pytest.approx(4.0 / 20 + 4.0)
    assert background_term.item() == pytest.approx(25.0 / 80)


def test_supervised_l2_rejects_bad_shapes() -> None:
    with pytest.raises(DonGymError, match="object_mask"):
        supervised_l2_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), torch.zeros(1, 4, 5, dtype=torch.bool))
    with pytest.raises(DonGymError, match="bool"):
        supervised_l2_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), torch.zeros(1, 4, 4))
    with pytest.raises(DonGymError, match="pred and target"):
        supervised_l2_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 2, 4, 4), torch.zeros(1, 4, 4, dtype=torch.bool))


# --- pixelwise contrastive loss ---------------------------------------------------------


def _hand_built_pair() -> dict[str, torch.Tensor]:
    """D=2, a 1x6 image pair; descriptors_a is zero except pixel u=1, which is (1, 1)."""
    a = torch.zeros(2, 1, 6)
    a[:, 0, 1] = torch.tensor([1.0, 1.0])
    b = torch.zeros(2, 1, 6)
    b[:, 0, 0] = torch.tensor([0.3, 0.4])  # match with a(0): distance 0.5
    b[:, 0, 1] = torch.tensor([1.0, 1.0])  # match with a(1): distance 0
    b[:, 0, 2] = torch.tensor([0.1, 0.0])  # distance 0.1 to a zero descriptor
    b[:, 0, 3] = torch.tensor([0.0, 0.3])  # distance 0.3
    b[:, 0, 4] = torch.tensor([0.6, 0.8])  # distance 1.0
    b[:, 0, 5] = torch.tensor([1.2, 1.6])  # distance 2.0

    def uv(*us: int) -> torch.Tensor:
        return torch.tensor([[u, 0] for u in us], dtype=torch.long)

    return {
        "descriptors_a": a.requires_grad_(),
        "descriptors_b": b.requires_grad_(),
        "matches_a": uv(0, 1),
        "matches_b": uv(0, 1),
        # Object non-matches at distances 0.1, 0.3 (inside margin 0.5) and 1.0 (beyond it).
        "nonmatches_object_a": uv(2, 3, 4),
        "nonmatches_object_b": uv(2, 3, 4),
        # Background non-matches at distances 2.0 and 1.0: inside margin 2.5, beyond 0.5.
        "nonmatches_background_a": uv(5, 0),
        "nonmatches_background_b": uv(5, 4),
    }


def test_contrastive_hand_computed_with_hard_negative_scaling() -> None:
    pair = _hand_built_pair()
    loss, stats = pixelwise_contrastive_loss(**pair, object_margin=0.5, background_margin=2.5)
    # match: (0.5^2 + 0) / 2 = 0.125.
    # object hinge: (0.5-0.1)^2 = 0.16, (0.5-0.3)^2 = 0.04, 0 -> 2 hard negatives.
    # background hinge: (2.5-2)^2 = 0.25, (2.5-1)^2 = 2.25 -> 2 hard negatives.
    # non-match = (0.16 + 0.04 + 0.25 + 2.25) / 4 = 0.675.
    assert stats["match_loss"] == pytest.approx(0.125)
    assert stats["num_hard_negatives_object"] == 2
    assert stats["num_hard_negatives_background"] == 2
    assert stats["nonmatch_object_loss"] == pytest.approx(0.20 / 4)
    assert stats["nonmatch_background_loss"] == pytest.approx(2.50 / 4)
    assert loss.item() == pytest.approx(0.125 + 0.675)
    assert stats["loss"] == pytest.approx(loss.item())
    loss.backward()
    # d/db of the match term |b - a|^2 / N at the first match: 2 (0.3, 0.4) / 2. The
    # non-match at u=4 is beyond the margin and must get no gradient from the object term;
    # its only gradient is from the background pair (0 -> 4): -2 (2.5 - 1) (b - a)/|b - a| / 4.
    grad_b = pair["descriptors_b"].grad
    assert grad_b[:, 0, 0].tolist() == pytest.approx([0.3, 0.4])
    assert grad_b[:, 0, 4].tolist() == pytest.approx((-2 * 1.5 * torch.tensor([0.6, 0.8]) / 4).tolist())


def test_contrastive_without_scaling_and_with_other_margins() -> None:
    loss, stats = pixelwise_contrastive_loss(**_hand_built_pair(), hard_negative_scaling=False)
    # Same sums, divided by the 5 non-match pairs instead of the 4 hard negatives.
    assert loss.item() == pytest.approx(0.125 + 2.70 / 5)
    # Background margin 0.5 (the original code's default): both background pairs are beyond
    # it, so only the two object hard negatives count: (0.16 + 0.04) / 2.
    loss, stats = pixelwise_contrastive_loss(**_hand_built_pair(), object_margin=0.5, background_margin=0.5)
    assert stats["num_hard_negatives_background"] == 0
    assert stats["nonmatch_background_loss"] == 0.0
    assert loss.item() == pytest.approx(0.125 + 0.1)


def test_contrastive_no_hard_negatives_and_empty_sets() -> None:
    pair = _hand_built_pair()
    loss, stats = pixelwise_contrastive_loss(**pair, object_margin=0.05, background_margin=0.05)
    assert stats["num_hard_negatives_object"] == stats["num_hard_negatives_background"] == 0
    assert loss.item() == pytest.approx(0.125)  # divisor max(0, 1): no division by zero
    empty = torch.zeros(0, 2, dtype=torch.long)
    loss, stats = pixelwise_contrastive_loss(
        pair["descriptors_a"], pair["descriptors_b"], empty, empty, empty, empty, empty, empty
    )
    assert loss.item() == 0.0 and stats["num_matches"] == 0
    loss.backward()  # stays connected to the graph, so a trainer never special-cases empty pairs
    assert torch.count_nonzero(pair["descriptors_a"].grad) == 0


def test_contrastive_from_correspondences_object_and_batch() -> None:
    pair = _hand_built_pair()
    # Duck-typed correspondences with numpy int64 (u, v) arrays, as don_gym.data.correspondences has.
    corr = SimpleNamespace(**{k: v.numpy().astype(np.int64) for k, v in pair.items() if "matches" in k})
    loss, _ = contrastive_loss_from_correspondences(pair["descriptors_a"], pair["descriptors_b"], corr)
    assert loss.item() == pytest.approx(0.8)
    a = torch.stack([pair["descriptors_a"].detach(), torch.zeros(2, 1, 6)])
    b = torch.stack([pair["descriptors_b"].detach(), torch.zeros(2, 1, 6)])
    # Second pair: every descriptor zero -> match 0, all 5 non-matches are hard negatives with
    # terms 0.25, 0.25, 0.25, 6.25, 6.25 -> (0.75 + 12.5) / 5 = 2.65.
    loss, stats = batch_contrastive_loss(a, b, [corr, corr])
    assert loss.item() == pytest.approx((0.8 + 2.65) / 2)
    assert stats["num_hard_negatives_object"] == 2 + 3
    with pytest.raises(DonGymError, match="lacks"):
        contrastive_loss_from_correspondences(a[0], b[0], SimpleNamespace(matches_a=corr.matches_a))


def test_contrastive_rejects_bad_pixels() -> None:
    pair = _hand_built_pair()
    with pytest.raises(DonGymError, match="outside the 6x1"):
        pixelwise_contrastive_loss(**{**pair, "matches_b": torch.tensor([[0, 0], [6, 0]])})
    with pytest.raises(DonGymError, match="integer"):
        pixelwise_contrastive_loss(**{**pair, "matches_a": torch.tensor([[0.0, 0.0], [1.0, 0.0]])})
    with pytest.raises(DonGymError, match="pair up"):
        pixelwise_contrastive_loss(**{**pair, "nonmatches_object_b": torch.tensor([[0, 0]])})
    with pytest.raises(DonGymError, match=r"\(n, 2\)"):
        pixelwise_contrastive_loss(**{**pair, "matches_a": torch.tensor([0, 1])})


# --- both losses train a real network ----------------------------------------------------


def test_supervised_loss_fits_a_fixed_target_in_30_steps() -> None:
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 32, 32, generator=g)
    # A smooth random target (an output-stride-8 network can represent it).
    target = F.interpolate(torch.rand(2, 3, 4, 4, generator=g), size=(32, 32), mode="bilinear")
    mask = torch.zeros(2, 32, 32, dtype=torch.bool)
    mask[:, 8:24, 10:26] = True
    model = DenseObjectNet(descriptor_dim=3)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss = supervised_l2_loss(model(rgb), target, mask)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.02 * losses[0], losses


def test_contrastive_loss_learns_correspondences_of_a_shifted_texture() -> None:
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    texture = F.interpolate(torch.rand(1, 3, 12, 12, generator=g), size=(48, 48), mode="bilinear")
    dx, dy, size = 4, 3, 40
    image_a = texture[:, :, :size, :size]
    image_b = texture[:, :, dy : dy + size, dx : dx + size]  # a(u, v) shows what b(u - dx, v - dy) shows
    grid = torch.stack(torch.meshgrid(torch.arange(dx, size), torch.arange(dy, size), indexing="xy"), -1)
    in_both = grid.reshape(-1, 2)[torch.randperm(grid.shape[0] * grid.shape[1], generator=g)]
    shift = torch.tensor([dx, dy])
    train_a, held_out_a = in_both[:200], in_both[200:400]

    def non_matches(uv_a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        uv_b = torch.randint(0, size, uv_a.shape, generator=g)
        far = (uv_a - shift - uv_b).abs().amax(dim=1) > 6
        return uv_a[far], uv_b[far]

    nonmatch_a, nonmatch_b = non_matches(train_a)
    empty = torch.zeros(0, 2, dtype=torch.long)
    model = DenseObjectNet(descriptor_dim=3)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        d = model(torch.cat([image_a, image_b]))
        loss, _ = pixelwise_contrastive_loss(
            d[0], d[1], train_a, train_a - shift, nonmatch_a, nonmatch_b, empty, empty, object_margin=1.0
        )
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0], losses
    # On pixels never trained on, true matches are now much closer than non-matches.
    model.eval()
    with torch.no_grad():
        d = model(torch.cat([image_a, image_b]))
    held_nonmatch_a, held_nonmatch_b = non_matches(held_out_a)

    def mean_distance(uv_a: torch.Tensor, uv_b: torch.Tensor) -> float:
        da = d[0][:, uv_a[:, 1], uv_a[:, 0]]
        db = d[1][:, uv_b[:, 1], uv_b[:, 0]]
        return float(torch.linalg.vector_norm(da - db, dim=0).mean())

    assert mean_distance(held_out_a, held_out_a - shift) < 0.25 * mean_distance(held_nonmatch_a, held_nonmatch_b)
