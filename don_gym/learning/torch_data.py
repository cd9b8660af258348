"""PyTorch datasets over a don_gym dataset directory, one per training method.

:class:`SupervisedFrames` serves frames with descriptor targets for the supervised l2 loss,
:class:`CorrespondencePairs` image pairs with sampled correspondences for the contrastive loss.
:class:`StepBatches` serves a training run's augmented batches by step number, so that
:func:`step_loader` can build them in worker processes.
"""

from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.context
import os
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from don_gym.data.bin_dataset import (
    BinTargets,
    filter_correspondences_by_instance,
    instance_parts,
    is_multi_part,
    load_part_space,
)
from don_gym.data.correspondences import Correspondences, camera_poses_differ, sample_correspondences
from don_gym.data.dataset import DEPTH_SOURCES, DONDataset, has_fused_depth
from don_gym.data.render import TARGET_VARIANTS, default_edge_width_px, make_target, mask_background
from don_gym.errors import DatasetError, DonGymError
from don_gym.learning.augment import AugmentConfig, augment

__all__ = [
    "CorrespondencePairs",
    "StepBatches",
    "SupervisedFrames",
    "collate_pairs",
    "crop_correspondences",
    "crop_window",
    "item_generator",
    "rgb_to_tensor",
    "step_loader",
]


def crop_window(
    object_mask: np.ndarray, crop_size: tuple[int, int], rng: np.random.Generator, background_probability: float
) -> tuple[int, int]:
    """Top-left ``(u0, v0)`` of a ``crop_size`` = (width, height) window inside the image.

    The object's mask centroid falls in the middle half of the window, unless the image has
    no object pixels or, with ``background_probability``, the window is placed anywhere.
    A fully convolutional network trains on such crops and runs on whole frames.
    """
    height, width = object_mask.shape
    crop_w, crop_h = min(crop_size[0], width), min(crop_size[1], height)
    rows, cols = np.nonzero(object_mask)
    if len(rows) == 0 or rng.random() < background_probability:
        return int(rng.integers(width - crop_w + 1)), int(rng.integers(height - crop_h + 1))
    centre_u = cols.mean() - crop_w * rng.uniform(0.25, 0.75)
    centre_v = rows.mean() - crop_h * rng.uniform(0.25, 0.75)
    return int(np.clip(round(centre_u), 0, width - crop_w)), int(np.clip(round(centre_v), 0, height - crop_h))


def _crop_pixels(uv_a: np.ndarray, uv_b: np.ndarray, box_a, box_b) -> tuple[np.ndarray, np.ndarray]:
    """Keep pixel pairs inside both crop boxes ``(u0, v0, w, h)``, in crop coordinates."""

    def inside(uv, box):
        u0, v0, w, h = box
        return (uv[:, 0] >= u0) & (uv[:, 0] < u0 + w) & (uv[:, 1] >= v0) & (uv[:, 1] < v0 + h)

    keep = inside(uv_a, box_a) & inside(uv_b, box_b)
    return uv_a[keep] - np.array(box_a[:2]), uv_b[keep] - np.array(box_b[:2])


def crop_correspondences(corr: Correspondences, box_a, box_b) -> Correspondences:
    """Correspondences restricted to two crop boxes ``(u0, v0, width, height)``, re-indexed."""
    pairs = {}
    for name in ("matches", "nonmatches_object", "nonmatches_background"):
        pairs[f"{name}_a"], pairs[f"{name}_b"] = _crop_pixels(
            getattr(corr, f"{name}_a"), getattr(corr, f"{name}_b"), box_a, box_b
        )
    return Correspondences(**pairs)


def rgb_to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """uint8 (H, W, 3) -> float32 (3, H, W) in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div_(255.0)


class SupervisedFrames(Dataset):
    """Every frame of a dataset as ``{"rgb", "target", "object_mask"}``.

    ``rgb`` float32 (3, H, W) in [0, 1]; ``target`` float32 (D, H, W); ``object_mask``
    bool (H, W) from the rendered target (object pixels hidden in the image are
    background, as the segmentation says).

    ``variant`` is the paper's target variant, computed from the stored geometric target and
    mask: ``"geometric"`` (method ``supervised``), ``"edge"`` (``supervised-edge``) or ``"mask"``
    (``supervised-mask``). With ``crop_size`` (width, height), each item is a window cut by
    :func:`crop_window` (object-centred with probability ``1 - background_crop_probability``).
    ``part_layout`` is the layout of a bin dataset's descriptor space to train in (:class:`BinTargets`):
    ``"identity"`` one more dimension for part identity, ``"dataset"`` the dataset's own, ``"auto"`` identity
    wherever it applies; a dataset of one part accepts only ``"auto"``.
    """

    def __init__(
        self,
        root: str,
        variant: str = "edge",
        edge_width_px: float | None = None,
        crop_size: tuple[int, int] | None = None,
        background_crop_probability: float = 0.1,
        seed: int = 0,
        part_layout: str = "auto",
    ) -> None:
        if variant not in TARGET_VARIANTS:
            raise DatasetError(f"target variant {variant!r} is unknown; expected one of {TARGET_VARIANTS}")
        self.data = DONDataset(root)
        if part_layout != "auto" and not is_multi_part(self.data):
            raise DatasetError(
                f"part layout {part_layout!r} (--part-layout) is for bin datasets of several parts; {self.data.root} "
                "is a dataset of one part, which trains in its own space (--part-layout auto)"
            )
        self.variant = variant
        width = self.data.scenes[0].intrinsics.width
        self.edge_width_px = default_edge_width_px(width) if edge_width_px is None else float(edge_width_px)
        #: A bin dataset's targets (several parts in one space, :class:`~don_gym.data.bin_dataset.BinTargets`),
        #: else None.
        self.bin_targets = None
        #: The multi-part descriptor space the network learns (bin datasets), else None.
        self.part_space = None
        if is_multi_part(self.data):
            self.bin_targets = BinTargets(self.data, variant, self.edge_width_px, part_layout)
            self.part_space = self.bin_targets.space
            self.background = self.bin_targets.background
        else:
            field = self.data.descriptor_field()
            #: (D,) descriptor of the targets off the object (the variant's, :func:`make_target`).
            self.background = (
                mask_background(field.vertex_descriptors)
                if variant == "mask"
                else np.asarray(field.background, dtype=np.float32)
            )
        self.index = self.data.frames
        self.crop_size = crop_size
        self.background_crop_probability = background_crop_probability
        self.seed = seed
        self.epoch = 0  # set by the trainer so that crops differ between visits of a frame

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.frame(i, np.random.default_rng([self.seed, self.epoch, int(i)]))

    def frame(self, i: int, crop_rng: np.random.Generator) -> dict[str, torch.Tensor]:
        """Item ``i`` with its crop window drawn from ``crop_rng``."""
        scene, frame = self.index[i]
        rgb = self.data.image(scene, frame, "rgb")
        if self.bin_targets is not None:
            target, mask = self.bin_targets.frame(scene, frame)
        else:
            mask = self.data.image(scene, frame, "target_mask")
            target = make_target(
                self.variant, self.data.image(scene, frame, "descriptor"), mask, self.background, self.edge_width_px
            )
        if self.crop_size is not None:
            u0, v0 = crop_window(mask, self.crop_size, crop_rng, self.background_crop_probability)
            window = (slice(v0, v0 + self.crop_size[1]), slice(u0, u0 + self.crop_size[0]))
            rgb, mask, target = rgb[window], mask[window], target[window]
        return {
            "rgb": rgb_to_tensor(rgb),
            "target": torch.from_numpy(np.ascontiguousarray(target.transpose(2, 0, 1), dtype=np.float32)),
            "object_mask": torch.from_numpy(np.ascontiguousarray(mask)),
        }


class CorrespondencePairs(Dataset):
    """Random image pairs within a scene with sampled correspondences.

    Item ``i`` is deterministic given ``seed`` (pair and samples drawn from a generator
    seeded with ``(seed, i)``), so a fixed seed gives the same training data. Pairs are
    redrawn until the camera poses differ by more than 0.2 m or 20 degrees (docs/background.md,
    section "Self-supervised DON training"; at most ``max_pair_tries`` times). Returns
    ``{"rgb_a", "rgb_b", "object_mask_a", "object_mask_b", "correspondences"}``; use
    ``collate_pairs`` (batch of lists).

    ``depth_source`` names the depth and masks correspondences are sampled from
    (:data:`don_gym.data.dataset.DEPTH_SOURCES`): ``"fused"`` (the original pipeline's), ``"sensor"``
    or ``"ideal"`` for ablations. ``crop_size`` crops both images as in :class:`SupervisedFrames`.
    """

    def __init__(
        self,
        root: str,
        depth_source: str = "fused",
        length: int = 100_000,
        seed: int = 0,
        num_match_attempts: int = 10_000,
        max_pair_tries: int = 20,
        crop_size: tuple[int, int] | None = None,
        background_crop_probability: float = 0.1,
    ) -> None:
        if depth_source not in DEPTH_SOURCES:
            raise DatasetError(f"depth source {depth_source!r} is unknown; expected one of {sorted(DEPTH_SOURCES)}")
        self.data = DONDataset(root)
        self.depth_kind, self.mask_kind = DEPTH_SOURCES[depth_source]
        if self.depth_kind == "depth_fused" and not has_fused_depth(self.data):
            raise DatasetError(
                f"{self.data.root}: was built with --no-fusion, so it has no fused depth for the self-supervised "
                "method's default depth source; rebuild it without --no-fusion, or train from the sensor depth "
                "with --depth-source sensor"
            )
        #: A bin dataset's descriptor space (its parts' identity, for the checkpoint), else None.
        self.part_space = load_part_space(self.data) if is_multi_part(self.data) else None
        self.length = int(length)
        self.seed = int(seed)
        self.num_match_attempts = num_match_attempts
        self.max_pair_tries = max_pair_tries
        self.crop_size = crop_size
        self.background_crop_probability = background_crop_probability

    def __len__(self) -> int:
        return self.length

    def _pick_pair(self, rng: np.random.Generator) -> tuple[int, int, int]:
        scene = int(rng.integers(len(self.data.scenes)))
        poses = self.data.scenes[scene].T_world_camera_reported
        for _ in range(self.max_pair_tries):
            a, b = (int(v) for v in rng.choice(len(poses), size=2, replace=False))
            if camera_poses_differ(poses[a], poses[b]):
                break
        return scene, a, b

    def __getitem__(self, i: int) -> dict:
        rng = np.random.default_rng([self.seed, int(i)])
        scene, a, b = self._pick_pair(rng)
        record = self.data.scenes[scene]
        depth_a = self.data.image(scene, a, self.depth_kind)
        depth_b = self.data.image(scene, b, self.depth_kind)
        mask_a = self.data.image(scene, a, self.mask_kind)
        mask_b = self.data.image(scene, b, self.mask_kind)
        correspondences: Correspondences = sample_correspondences(
            depth_a,
            depth_b,
            mask_a,
            mask_b,
            record.intrinsics,
            record.T_world_camera_reported[a],
            record.T_world_camera_reported[b],
            rng,
            num_match_attempts=self.num_match_attempts,
        )
        if self.part_space is not None:  # a pile: matches within an instance, non-matches across parts
            correspondences = filter_correspondences_by_instance(
                correspondences,
                self.data.image(scene, a, "instance"),
                self.data.image(scene, b, "instance"),
                instance_parts(record),
            )
        rgb_a, rgb_b = self.data.image(scene, a, "rgb"), self.data.image(scene, b, "rgb")
        if self.crop_size is not None:
            width, height = self.crop_size
            box_a = (*crop_window(mask_a, self.crop_size, rng, self.background_crop_probability), width, height)
            box_b = (*crop_window(mask_b, self.crop_size, rng, self.background_crop_probability), width, height)
            correspondences = crop_correspondences(correspondences, box_a, box_b)
            rgb_a, mask_a = (x[box_a[1] : box_a[1] + height, box_a[0] : box_a[0] + width] for x in (rgb_a, mask_a))
            rgb_b, mask_b = (x[box_b[1] : box_b[1] + height, box_b[0] : box_b[0] + width] for x in (rgb_b, mask_b))
        return {
            "rgb_a": rgb_to_tensor(rgb_a),
            "rgb_b": rgb_to_tensor(rgb_b),
            "object_mask_a": torch.from_numpy(np.ascontiguousarray(mask_a)),
            "object_mask_b": torch.from_numpy(np.ascontiguousarray(mask_b)),
            "correspondences": correspondences,
        }


def collate_pairs(items: list[dict]) -> dict:
    """Stack images; keep per-pair correspondences (different counts) as a list."""
    out = {
        key: torch.stack([item[key] for item in items]) for key in ("rgb_a", "rgb_b", "object_mask_a", "object_mask_b")
    }
    out["correspondences"] = [item["correspondences"] for item in items]
    return out


def item_generator(seed: int, step: int, number: int) -> torch.Generator:
    """The augmentation generator of image ``number`` of training step ``step``."""
    generator = torch.Generator()
    generator.manual_seed(int(np.random.SeedSequence([seed, step, number, 1]).generate_state(1)[0]))
    return generator


class StepBatches(Dataset):
    """A training run's batches: item ``s`` is this process's share of the batch of step ``s``, augmented.

    Image ``k`` (0 <= k < ``batch_size``) of step ``s`` is chosen, cropped and augmented with
    generators seeded from ``(seed, s, k)`` alone, so a step's batch is the same whichever
    worker process builds it and however many processes train: process ``rank`` of
    ``world_size`` gets images ``rank * b`` to ``(rank + 1) * b - 1``, ``b = batch_size //
    world_size``. Supervised sources (:class:`SupervisedFrames`) pick the step's frames with a
    generator seeded from ``(seed, s)``; :class:`CorrespondencePairs` serves pair ``s *
    batch_size + k``.

    Items are ``{"rgb", "target", "object_mask"}`` (supervised) or ``{"rgb_a", "rgb_b",
    "correspondences"}`` (pairs), batched along the first dimension. A user error while
    loading comes back as ``{"error": exception}`` for the trainer to raise, so it reads the
    same with or without worker processes.
    """

    def __init__(
        self,
        source: SupervisedFrames | CorrespondencePairs,
        steps: int,
        batch_size: int,
        seed: int,
        augment_config: AugmentConfig,
        rank: int = 0,
        world_size: int = 1,
    ) -> None:
        if batch_size < 1 or world_size < 1 or batch_size % world_size or not 0 <= rank < world_size:
            raise DonGymError(
                f"batch size {batch_size} must be a positive multiple of the number of processes {world_size}"
            )
        self.source = source
        self.steps = int(steps)
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.augment_config = augment_config
        share = batch_size // world_size
        self.numbers = range(rank * share, (rank + 1) * share)

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, step: int) -> dict[str, Any]:
        try:
            if isinstance(self.source, SupervisedFrames):
                return self._frames(int(step))
            return self._pairs(int(step))
        except DonGymError as exc:
            return {"error": exc}

    def _augment(self, rgb: torch.Tensor, mask: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return augment(rgb[None], mask[None], generator, self.augment_config)[0]

    def _frames(self, step: int) -> dict[str, Any]:
        frames = np.random.default_rng([self.seed, step]).integers(len(self.source), size=self.batch_size)
        rgb, target, mask = [], [], []
        for k in self.numbers:
            item = self.source.frame(int(frames[k]), np.random.default_rng([self.seed, step, k]))
            rgb.append(self._augment(item["rgb"], item["object_mask"], item_generator(self.seed, step, k)))
            target.append(item["target"])
            mask.append(item["object_mask"])
        return {"rgb": torch.stack(rgb), "target": torch.stack(target), "object_mask": torch.stack(mask)}

    def _pairs(self, step: int) -> dict[str, Any]:
        rgb_a, rgb_b, correspondences = [], [], []
        for k in self.numbers:
            item = self.source[step * self.batch_size + k]
            generator = item_generator(self.seed, step, k)
            rgb_a.append(self._augment(item["rgb_a"], item["object_mask_a"], generator))
            rgb_b.append(self._augment(item["rgb_b"], item["object_mask_b"], generator))
            correspondences.append(item["correspondences"])
        return {"rgb_a": torch.stack(rgb_a), "rgb_b": torch.stack(rgb_b), "correspondences": correspondences}


def _init_loader_worker(owner_pid: int, worker_id: int) -> None:
    import cv2

    from don_gym.processes import end_with_parent

    # The worker's parent is the fork server: watch the trainer itself, so that a trainer killed with
    # kill -9 takes its workers along (each holds a batch or two of images).
    end_with_parent(owner_pid)
    # Each worker builds whole batches on its own; threads inside a worker would only compete
    # with the other workers and the training process for the same cores.

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def _worker_context() -> multiprocessing.context.BaseContext:
    """Workers start from a fork server that imported this module and nothing else. Forked from the
    training process itself, a worker inherits thread pools in use (OpenCV's decodes images in
    parallel) without their threads, and can hang on their locks."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


def _as_is(batch: dict[str, Any]) -> dict[str, Any]:
    return batch


def step_loader(batches: StepBatches, first_step: int, workers: int, pin_memory: bool = False) -> DataLoader:
    """Batches of steps ``first_step, first_step + 1, ...`` in order, built by ``workers`` processes
    (0: in the calling thread). ``pin_memory`` pins them for asynchronous copies to a GPU."""
    return DataLoader(
        batches,
        batch_size=None,
        sampler=range(first_step, len(batches)),
        num_workers=workers,
        collate_fn=_as_is,
        pin_memory=pin_memory,
        worker_init_fn=functools.partial(_init_loader_worker, os.getpid()) if workers else None,
        multiprocessing_context=_worker_context() if workers else None,
        prefetch_factor=2 if workers else None,
    )
