"""DON training with either method on one dataset directory.

``train(config)`` runs Adam on a :class:`~don_gym.model.DenseObjectNet` with

- ``supervised`` / ``supervised-edge`` / ``supervised-mask``: the paper's l2 loss
  (object and background terms normalised by their pixel counts) to rendered optimal
  descriptor targets (:class:`~don_gym.torch_data.SupervisedFrames`);
- ``self-supervised``: the pixelwise contrastive loss with hard-negative scaling on
  correspondences sampled from fused sensor depth
  (:class:`~don_gym.torch_data.CorrespondencePairs`),

with background randomisation and photometric jitter for both. Defaults follow the
original DON (Adam, lr 1e-4, weight decay 1e-4, lr x0.9 every 250 steps), except the
learning rate of the CPU-sized default network, which trains from scratch.

Everything a step uses is drawn from generators seeded with ``(seed, step)``, so a
fixed seed gives the same loss curve, and a resumed run continues it exactly.

A run directory holds ``config.json``, ``losses.csv`` (one row per step),
``loss_curve.png``, ``checkpoints/step_XXXXXX.safetensors`` every
``checkpoint_every`` steps, ``train_state.pt`` (optimiser state for ``--resume``) and
the final ``model.safetensors``.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from don_gym.augment import AugmentConfig, augment
from don_gym.checkpoints import CheckpointMetadata, save_checkpoint
from don_gym.errors import DonGymError
from don_gym.io import atomic_path, write_text_atomic
from don_gym.losses import batch_contrastive_loss, supervised_l2_loss
from don_gym.methods import SUPERVISED_TARGET_VARIANT, is_supervised, validate_method
from don_gym.model import DEFAULT_ARCH, DenseObjectNet
from don_gym.torch_data import CorrespondencePairs, SupervisedFrames

RUN_CONFIG = "config.json"
LOSS_CSV = "losses.csv"
LOSS_PNG = "loss_curve.png"
TRAIN_STATE = "train_state.pt"
FINAL_MODEL = "model.safetensors"
#: Settings that may differ when resuming a run.
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "device", "threads")


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``lr`` None picks 1e-4 (paper) for ImageNet-layout ResNets and
    1e-3 for the from-scratch ``resnet-lite``. ``crop_size`` (width, height) trains on
    object-centred random crops (None: whole frames); the network still runs on whole frames.
    ``threads`` sets torch's CPU threads (None: torch's default); on a machine whose cores
    are shared with other work, 1 thread avoids OpenMP stalls that can slow a step 10x."""

    method: str
    data: str
    out: str
    steps: int = 2000
    arch: str = DEFAULT_ARCH
    batch_size: int = 4
    lr: float | None = None
    weight_decay: float = 1e-4
    lr_decay: float = 0.9
    lr_decay_every: int = 250
    seed: int = 0
    checkpoint_every: int = 500
    pretrained_path: str | None = None
    depth_source: str = "fused"
    object_margin: float = 0.5
    background_margin: float = 2.5
    device: str = "auto"
    crop_size: tuple[int, int] | None = (160, 120)
    threads: int | None = None
    augment: dict[str, float] = field(default_factory=lambda: asdict(AugmentConfig()))

    def learning_rate(self) -> float:
        if self.lr is not None:
            return self.lr
        return 1e-3 if self.arch == "resnet-lite" else 1e-4


@dataclass(frozen=True)
class TrainResult:
    """What a finished run reports; ``seconds`` and ``images_per_second`` cover every session of a
    resumed run, and are None for a run resumed from a state saved before they were recorded."""

    model_path: Path
    final_loss: float
    steps: int
    seconds: float | None
    images_per_second: float | None


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _step_generator(seed: int, step: int) -> torch.Generator:
    generator = torch.Generator()
    generator.manual_seed(int(np.random.SeedSequence([seed, step, 1]).generate_state(1)[0]))
    return generator


def _read_loss_rows(path: Path, up_to_step: int) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open() as f:
        return [row for row in csv.DictReader(f) if int(row["step"]) <= up_to_step]


def _write_loss_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


def plot_loss_curve(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """Loss per step (light) and its moving average (dark), log scale, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([int(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=120)
    ax.plot(steps, loss, color="tab:blue", alpha=0.3, lw=0.8, label="loss per step")
    window = max(1, len(loss) // 50)
    if len(loss) >= window:
        smooth = np.convolve(loss, np.ones(window) / window, mode="valid")
        ax.plot(steps[window - 1 :], smooth, color="tab:blue", lw=1.8, label=f"moving average ({window} steps)")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def checkpoint_metadata(
    config: TrainConfig, dataset_info: dict[str, Any], image_size: tuple[int, int], step: int
) -> CheckpointMetadata:
    supervised = is_supervised(config.method)
    return CheckpointMetadata(
        method=config.method,
        object_name=dataset_info["object"],
        object_mesh_hash=dataset_info["mesh_hash"],
        image_size=tuple(image_size),
        descriptor_field_hash=dataset_info["descriptor_field_hash"] if supervised else "",
        background_descriptor=tuple(float(v) for v in dataset_info["background_descriptor"]) if supervised else (),
        renderer=dataset_info["renderer"],
        sensor_preset=dataset_info["sensor"],
        training_steps=step,
        extra={
            "seed": config.seed,
            "lr": config.learning_rate(),
            "batch_size": config.batch_size,
            "dataset_scenes": int(dataset_info["scenes"]),
            "dataset_frames_per_scene": int(dataset_info["frames_per_scene"]),
            "dataset_seed": int(dataset_info["seed"]),
            "depth_source": "" if supervised else config.depth_source,
        },
    )


def train(config: TrainConfig, resume: bool = False, progress: bool = True) -> TrainResult:
    """Train a DON as configured; see the module docstring for what a run writes."""
    validate_method(config.method)
    if config.steps < 1:
        raise DonGymError(f"steps must be >= 1, got {config.steps}")
    out = Path(config.out)
    device = _device(config.device)
    if config.threads is not None:
        torch.set_num_threads(int(config.threads))
    torch.manual_seed(config.seed)

    if is_supervised(config.method):
        dataset: Any = SupervisedFrames(
            config.data, variant=SUPERVISED_TARGET_VARIANT[config.method], crop_size=config.crop_size, seed=config.seed
        )
    else:
        dataset = CorrespondencePairs(
            config.data, depth_source=config.depth_source, seed=config.seed, crop_size=config.crop_size
        )
    info = dataset.data.info
    intrinsics = dataset.data.scenes[0].intrinsics
    image_size = (intrinsics.width, intrinsics.height)

    model = DenseObjectNet(config.arch, int(info["descriptor_dim"]), pretrained_path=config.pretrained_path).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.learning_rate(), weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=config.lr_decay_every, gamma=config.lr_decay)
    augment_config = AugmentConfig(**config.augment)

    start_step = 0
    # Training time and images of earlier sessions of a resumed run; None when unknown.
    earlier_seconds: float | None = 0.0
    earlier_images: int | None = 0
    rows: list[dict[str, Any]] = []
    state_path = out / TRAIN_STATE
    if resume and state_path.is_file():
        saved_config = json.loads((out / RUN_CONFIG).read_text())
        wanted = json.loads(json.dumps(asdict(config)))
        # A resumed run may train for longer or checkpoint at another interval; anything else
        # would silently change what the first steps meant.
        changed = sorted(k for k in wanted if k not in RESUMABLE_CHANGES and saved_config.get(k) != wanted[k])
        if changed:
            raise DonGymError(
                f"{out}: --resume with a different configuration than the saved {RUN_CONFIG} ({', '.join(changed)})"
            )
        state = torch.load(state_path, map_location=device, weights_only=True)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start_step = int(state["step"])
        earlier_seconds = float(state["seconds"]) if "seconds" in state else None
        earlier_images = int(state["images_seen"]) if "images_seen" in state else None
        rows = _read_loss_rows(out / LOSS_CSV, start_step)
    elif out.exists() and (out / RUN_CONFIG).exists() and not resume:
        raise DonGymError(f"{out}: already holds a training run; pass --resume to continue it or choose a new --out")
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / RUN_CONFIG, json.dumps(asdict(config), indent=1) + "\n")

    def save_state(step: int) -> None:
        with atomic_path(state_path) as tmp:
            torch.save(
                {
                    "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "scheduler": scheduler.state_dict(),
                    "step": step,
                    **(
                        {}
                        if earlier_seconds is None or earlier_images is None
                        else {
                            "seconds": earlier_seconds + time.perf_counter() - start_time,
                            "images_seen": earlier_images + images_seen,
                        }
                    ),
                },
                tmp,
            )
        _write_loss_csv(out / LOSS_CSV, rows)

    model.train()
    images_seen = 0
    start_time = time.perf_counter()
    bar = tqdm(
        range(start_step, config.steps),
        initial=start_step,
        total=config.steps,
        desc=config.method,
        unit="step",
        disable=not progress,
    )
    for step in bar:
        generator = _step_generator(config.seed, step)
        index_rng = np.random.default_rng([config.seed, step])
        if is_supervised(config.method):
            dataset.epoch = step
            items = [dataset[int(i)] for i in index_rng.integers(len(dataset), size=config.batch_size)]
            rgb = torch.stack([it["rgb"] for it in items]).to(device)
            target = torch.stack([it["target"] for it in items]).to(device)
            mask = torch.stack([it["object_mask"] for it in items]).to(device)
            pred = model(augment(rgb, mask, generator, augment_config))
            loss = supervised_l2_loss(pred, target, mask)
            stats: dict[str, float] = {}
        else:
            items = [dataset[step * config.batch_size + k] for k in range(config.batch_size)]
            rgb_a = torch.stack([it["rgb_a"] for it in items]).to(device)
            rgb_b = torch.stack([it["rgb_b"] for it in items]).to(device)
            mask_a = torch.stack([it["object_mask_a"] for it in items]).to(device)
            mask_b = torch.stack([it["object_mask_b"] for it in items]).to(device)
            both = model(
                torch.cat(
                    [
                        augment(rgb_a, mask_a, generator, augment_config),
                        augment(rgb_b, mask_b, generator, augment_config),
                    ]
                )
            )
            desc_a, desc_b = both[: len(items)], both[len(items) :]
            loss, stats = batch_contrastive_loss(
                desc_a, desc_b, [it["correspondences"] for it in items], config.object_margin, config.background_margin
            )
        if not torch.isfinite(loss):
            raise RuntimeError(f"loss became {loss.item()} at step {step}; lower --lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        images_seen += config.batch_size * (1 if is_supervised(config.method) else 2)
        rate = images_seen / (time.perf_counter() - start_time)
        rows.append(
            {
                "step": step + 1,
                "loss": f"{loss.item():.6g}",
                "lr": f"{scheduler.get_last_lr()[0]:.3g}",
                **{k: f"{v:.6g}" for k, v in stats.items()},
            }
        )
        bar.set_postfix(loss=f"{loss.item():.4f}", img_s=f"{rate:.1f}")
        done = step + 1
        if done % config.checkpoint_every == 0 or done == config.steps:
            save_checkpoint(
                out / "checkpoints" / f"step_{done:06d}.safetensors",
                model,
                checkpoint_metadata(config, info, image_size, done),
            )
            save_state(done)
            plot_loss_curve(rows, out / LOSS_PNG, f"{config.method} on {info['object']} ({config.arch})")
    bar.close()
    seconds = time.perf_counter() - start_time
    save_checkpoint(out / FINAL_MODEL, model, checkpoint_metadata(config, info, image_size, config.steps))
    save_state(config.steps)
    plot_loss_curve(rows, out / LOSS_PNG, f"{config.method} on {info['object']} ({config.arch})")
    final_loss = float(np.mean([float(r["loss"]) for r in rows[-max(1, len(rows) // 20) :]]))
    if earlier_seconds is None or earlier_images is None:
        return TrainResult(out / FINAL_MODEL, final_loss, config.steps, None, None)
    total_seconds = earlier_seconds + seconds
    total_images = earlier_images + images_seen
    return TrainResult(
        out / FINAL_MODEL, final_loss, config.steps, total_seconds, total_images / max(total_seconds, 1e-9)
    )
