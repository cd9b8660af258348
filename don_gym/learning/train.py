"""DON training with either method on one dataset directory.

``train(config)`` runs Adam on a :class:`~don_gym.learning.model.DenseObjectNet` with the supervised l2 loss or the
contrastive loss (:mod:`don_gym.learning.methods`), with the original DON's optimiser defaults (docs/background.md,
section "Self-supervised DON training"). Every step is seeded with ``(seed, step)``, so a resumed run continues
the same loss curve. A run directory holds ``config.json``, ``losses.csv`` (one row per step), ``loss_curve.png``,
``checkpoints/step_XXXXXX.safetensors`` every ``checkpoint_every`` steps, ``train_state.pt`` (optimiser state for
``--resume``) and the final ``model.safetensors``. One run writes a run directory at a time: the writing process
holds the directory's lock (:class:`~don_gym.io.DirectoryLock` on ``.lock``) from before its first write to its end.

Batches come from :class:`~don_gym.learning.torch_data.StepBatches`, built in ``workers`` processes. Under
``torchrun`` each process trains on its share of every step's batch with DistributedDataParallel
(:mod:`don_gym.learning.distributed`) and rank 0 alone writes the run directory. On a GPU, steps run under
mixed precision (bf16, or fp16 with a gradient scaler) in channels-last layout.
"""

from __future__ import annotations

import csv
import fcntl
import hashlib
import json
import math
import re
import shutil
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from don_gym.data.dataset import DEPTH_SOURCES, DONDataset
from don_gym.descriptors.multi_part import IDENTITY_LAYOUT, TRAINING_LAYOUT_CHOICES
from don_gym.errors import DonGymError
from don_gym.io import DirectoryLock, atomic_path, check_output_dir, write_text_atomic
from don_gym.learning.augment import AugmentConfig
from don_gym.learning.checkpoints import CheckpointMetadata, PartIdentity, load_checkpoint, save_checkpoint
from don_gym.learning.distributed import (
    BACKENDS,
    SINGLE_PROCESS,
    LaunchEnvironment,
    all_reduce_sum,
    broadcast_from_main,
    launch_environment,
    resolve_backend,
    same_on_every_process,
    start_process_group,
    synchronize_batchnorm,
)
from don_gym.learning.losses import batch_contrastive_loss, supervised_l2_loss
from don_gym.learning.methods import SUPERVISED_TARGET_VARIANT, is_supervised, validate_method
from don_gym.learning.model import (
    ARCHS,
    DEFAULT_ARCH,
    DenseObjectNet,
    torch_device,
    validate_arch,
    validate_device_name,
)
from don_gym.learning.torch_data import CorrespondencePairs, StepBatches, SupervisedFrames, step_loader
from don_gym.objects import part_name
from don_gym.plotting import plot_loss_curve

__all__ = [
    "DATASET_IDENTITY_KEY",
    "FINAL_MODEL",
    "LOSS_CSV",
    "LOSS_PNG",
    "PATH_SETTINGS",
    "PRECISIONS",
    "RESUMABLE_CHANGES",
    "RUN_CONFIG",
    "TRAIN_STATE",
    "TrainConfig",
    "TrainResult",
    "autocast_dtype",
    "checkpoint_metadata",
    "dataset_identity",
    "dataset_part_identity",
    "resolve_device",
    "train",
    "validate_config",
]

RUN_CONFIG = "config.json"
LOSS_CSV = "losses.csv"
LOSS_PNG = "loss_curve.png"
TRAIN_STATE = "train_state.pt"
FINAL_MODEL = "model.safetensors"
#: Settings that may differ when resuming a run: they change how long, how often or how fast
#: it trains, not what a step computes (beyond float rounding).
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "device", "threads", "workers", "precision", "backend")
#: Paths are compared by what they point at, never by spelling: the run directory is the run
#: being resumed wherever it lies, the dataset is compared by content (:func:`dataset_identity`)
#: and pretrained weights matter only before the first step.
PATH_SETTINGS = ("out", "data", "pretrained_path", "init_path")
#: Values of ``TrainConfig.precision``.
PRECISIONS = ("auto", "fp32", "bf16", "fp16")
#: Key of config.json that records :func:`dataset_identity`.
DATASET_IDENTITY_KEY = "dataset_identity"


@dataclass(frozen=True)
class TrainConfig:
    """One training run. ``lr`` None picks 1e-4 (paper) for ImageNet-layout ResNets and
    1e-3 for the from-scratch ``resnet-lite`` archs. ``crop_size`` (width, height) trains on
    object-centred random crops (None: whole frames); the network still runs on whole frames, so
    ``background_crop_probability`` of the crops are placed anywhere in the frame instead, showing
    it backgrounds far from the part and the frame's borders.
    ``threads`` sets torch's CPU threads (None: torch's default); on a machine whose cores
    are shared with other work, 1 thread avoids OpenMP stalls that slow a step several-fold (benchmarks/RESULTS.md,
    section ``train-threads``).

    ``batch_size`` is the batch of one step over all processes of a torchrun launch (each of
    N processes computes ``batch_size / N``). ``workers`` processes build the batches (0: the
    training thread does). ``device`` is ``"auto"`` (CUDA if present), ``"cpu"``, ``"cuda"`` or
    ``"cuda:N"``; ``precision`` ``"auto"`` is bf16 autocast on GPUs that support it, else fp16
    with a gradient scaler, and fp32 on the CPU. ``backend`` (``"auto"``: NCCL on GPUs, gloo on
    CPUs) is the torch.distributed backend under torchrun. ``part_layout`` (supervised methods on bin datasets of
    several parts only) is the descriptor space's layout the network learns: ``"identity"`` every part's whole field
    plus one output channel for part identity (:func:`~don_gym.descriptors.multi_part.build_part_space`; not with
    ``supervised-mask``), ``"dataset"`` the dataset's own (each part's field shrunk into a region of its own),
    ``"auto"`` identity wherever it applies (:func:`~don_gym.descriptors.multi_part.training_layout`).
    ``init_path`` fine-tunes: the run starts from the weights of a don_gym checkpoint of the same method, arch,
    part and descriptor space (e.g. a shipped network, to adapt it to new data) instead of random ones.
    ``hard_object_fraction`` and ``hard_background_fraction`` (supervised methods) add to the loss's object and
    background terms the mean error of each crop's worst fraction of pixels of that region
    (:func:`~don_gym.learning.losses.supervised_l2_loss_terms`).
    ``ema_decay`` > 0 keeps an exponential moving average of the weights (and of batch-norm's running statistics),
    updated after every step with decay ``min(ema_decay, (1 + t) / (10 + t))`` at step t, so that the first
    steps do not hold on to the starting weights; checkpoints and the final model then hold the average, the
    resumable state both. 0 (the default) saves the weights as trained."""

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
    background_crop_probability: float = 0.1
    threads: int | None = None
    augment: dict[str, float] = field(default_factory=lambda: asdict(AugmentConfig()))
    workers: int = 0
    precision: str = "auto"
    backend: str = "auto"
    part_layout: str = "auto"
    init_path: str | None = None
    hard_object_fraction: float = 0.0
    hard_background_fraction: float = 0.0
    ema_decay: float = 0.0

    def learning_rate(self) -> float:
        if self.lr is not None:
            return self.lr
        return 1e-4 if ARCHS[self.arch].torchvision_layout else 1e-3


@dataclass(frozen=True)
class TrainResult:
    """What a finished run reports; ``seconds`` and ``images_per_second`` cover every session of a
    resumed run, and are None for a run resumed from a state saved before they were recorded.
    ``data_wait_fraction`` is the share of this session's step time spent waiting for a batch, after
    the first batch (whose wait is the loader's start-up); None for a session of fewer than 2 steps."""

    model_path: Path
    final_loss: float
    steps: int
    seconds: float | None
    images_per_second: float | None
    data_wait_fraction: float | None = None


def _integer(config: TrainConfig, name: str, minimum: int) -> None:
    value = getattr(config, name)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise DonGymError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _real(config: TrainConfig, name: str, low: float, high: float, low_open: bool = False) -> None:
    value = getattr(config, name)
    ok = isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value > high or value < low or (low_open and value == low):
        interval = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise DonGymError(f"{name} must be a finite number in {interval}, got {value!r}")


def validate_config(config: TrainConfig) -> None:
    """Every check on ``config`` that needs neither files nor devices; raises :class:`DonGymError`."""
    validate_method(config.method)
    validate_arch(config.arch)
    for name in ("data", "out"):
        if not isinstance(getattr(config, name), str) or not getattr(config, name):
            raise DonGymError(f"{name} must be a path, got {getattr(config, name)!r}")
    for name, minimum in (("steps", 1), ("batch_size", 1), ("lr_decay_every", 1), ("checkpoint_every", 1),
                          ("seed", 0), ("workers", 0)):  # fmt: skip
        _integer(config, name, minimum)
    if config.threads is not None:
        _integer(config, "threads", 1)
    if config.lr is not None:
        _real(config, "lr", 0.0, 1.0, low_open=True)  # Adam steps beyond 1 only diverge
    _real(config, "weight_decay", 0.0, 1.0)
    _real(config, "lr_decay", 0.0, 1.0, low_open=True)
    _real(config, "background_crop_probability", 0.0, 1.0)
    _real(config, "hard_object_fraction", 0.0, 0.5)
    _real(config, "hard_background_fraction", 0.0, 0.5)
    _real(config, "ema_decay", 0.0, 0.99999)
    _real(config, "object_margin", 0.0, 1e6)
    _real(config, "background_margin", 0.0, 1e6)
    if config.depth_source not in DEPTH_SOURCES:
        raise DonGymError(f"depth_source {config.depth_source!r} is unknown; expected one of {sorted(DEPTH_SOURCES)}")
    if config.crop_size is not None and (
        len(config.crop_size) != 2 or any(isinstance(v, bool) or int(v) != v or v < 1 for v in config.crop_size)
    ):
        raise DonGymError(f"crop_size must be (width, height) in pixels > 0 or None, got {config.crop_size!r}")
    try:
        AugmentConfig(**config.augment)
    except TypeError as exc:
        raise DonGymError(f"augment: {exc}; the settings are {[f.name for f in fields(AugmentConfig)]}") from None
    validate_device_name(config.device)
    if config.precision not in PRECISIONS:
        raise DonGymError(f"precision {config.precision!r} is unknown; expected one of {list(PRECISIONS)}")
    if config.backend not in BACKENDS:
        raise DonGymError(f"backend {config.backend!r} is unknown; expected one of {list(BACKENDS)}")
    if config.part_layout not in TRAINING_LAYOUT_CHOICES:
        raise DonGymError(
            f"part_layout {config.part_layout!r} is unknown; expected one of {list(TRAINING_LAYOUT_CHOICES)}"
        )
    if config.part_layout != "auto" and not is_supervised(config.method):
        raise DonGymError(
            f"part_layout {config.part_layout!r} is for the supervised methods; {config.method} learns a descriptor "
            "space of its own (use part_layout 'auto')"
        )
    for name in ("hard_object_fraction", "hard_background_fraction"):
        if getattr(config, name) > 0 and not is_supervised(config.method):
            raise DonGymError(
                f"{name} {getattr(config, name)} is a term of the supervised loss; {config.method} has no per-pixel "
                "targets (use 0)"
            )
    if config.part_layout == IDENTITY_LAYOUT and config.method == "supervised-mask":
        raise DonGymError(
            "part_layout 'identity' does not support supervised-mask, whose mask channel would replace a "
            "descriptor dimension; use supervised or supervised-edge, or part_layout 'auto'"
        )
    if config.init_path is not None and (not isinstance(config.init_path, str) or not config.init_path):
        raise DonGymError(f"init_path must be a checkpoint path or None, got {config.init_path!r}")
    if config.init_path is not None and config.pretrained_path is not None:
        raise DonGymError(
            f"init_path {config.init_path} and pretrained_path {config.pretrained_path}: a run starts from one of "
            "them (a checkpoint to fine-tune, or ImageNet weights for the encoder), not both"
        )
    if config.pretrained_path is not None and not ARCHS[config.arch].torchvision_layout:
        raise DonGymError(
            f"pretrained weights {config.pretrained_path}: arch {config.arch!r} has no ImageNet layout; "
            f"use one of {sorted(k for k, v in ARCHS.items() if v.torchvision_layout)}"
        )


def resolve_device(name: str, launch: LaunchEnvironment = SINGLE_PROCESS) -> torch.device:
    """The torch device for ``TrainConfig.device`` (:func:`~don_gym.learning.model.torch_device`); under torchrun each
    process takes GPU ``LOCAL_RANK``."""
    device = torch_device(name)
    if launch.world_size == 1 or device.type == "cpu":
        return device
    if name not in ("auto", "cuda"):
        raise DonGymError(f"device {name!r}: under torchrun use --device cuda; process k takes GPU LOCAL_RANK=k")
    if launch.local_rank >= torch.cuda.device_count():
        raise DonGymError(
            f"rank {launch.rank}: LOCAL_RANK {launch.local_rank} but only {torch.cuda.device_count()} GPU(s) are "
            "visible; start at most one process per GPU"
        )
    return torch.device("cuda", launch.local_rank)


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of ``precision`` on ``device``; None for fp32."""
    if precision == "auto":
        if device.type != "cuda":
            return None
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    if precision == "fp32":
        return None
    if device.type != "cuda":
        raise DonGymError(f"precision {precision!r} needs a GPU (--device cuda); the CPU trains in fp32")
    if precision == "bf16" and not torch.cuda.is_bf16_supported():
        raise DonGymError(f"precision 'bf16': {torch.cuda.get_device_name(device)} does not support it; use fp16")
    return torch.bfloat16 if precision == "bf16" else torch.float16


def dataset_identity(data: DONDataset) -> str:
    """A digest of what a dataset directory holds (its dataset.json and complete scenes), not where it lies."""
    digest = hashlib.sha256(json.dumps(data.info, sort_keys=True).encode())
    digest.update(json.dumps([[scene.index, scene.num_frames] for scene in data.scenes]).encode())
    return digest.hexdigest()[:16]


def _config_json(config: TrainConfig) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(config)))


def _read_saved_config(path: Path) -> dict[str, Any]:
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise DonGymError(f"{path}: missing; the run directory has a {TRAIN_STATE} but no {RUN_CONFIG}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DonGymError(f"{path}: cannot be read as JSON ({exc}); the run cannot be resumed") from None
    if not isinstance(saved, dict):
        raise DonGymError(f"{path}: expected a JSON object of training settings, got {type(saved).__name__}")
    return saved


def _changed_settings(saved: dict[str, Any], config: TrainConfig, identity: str) -> list[str]:
    wanted = _config_json(config)
    defaults = _config_json(TrainConfig(method=config.method, data=config.data, out=config.out))

    def completed(name: str, value: Any) -> Any:
        # A nested setting left out (an augmentation strength added after a run was saved) is its default.
        if isinstance(value, dict) and isinstance(defaults[name], dict):
            return {**defaults[name], **value}
        return value

    changed = sorted(
        name
        for name in wanted
        if name not in RESUMABLE_CHANGES + PATH_SETTINGS
        and completed(name, saved.get(name, defaults[name])) != completed(name, wanted[name])
    )
    if DATASET_IDENTITY_KEY in saved:
        same_data = saved[DATASET_IDENTITY_KEY] == identity
    else:  # written before identities were recorded: the best left is the resolved path
        same_data = Path(str(saved.get("data"))).resolve() == Path(config.data).resolve()
    return changed if same_data else sorted([*changed, "data"])


def _short_reason(exc: Exception) -> str:
    """The gist of a ``torch.load`` failure: its specific line, without PyTorch's paragraph on ``weights_only``."""
    text = str(exc).split("WeightsUnpickler error:", 1)[-1]
    line = next((s.strip() for s in text.splitlines() if s.strip()), type(exc).__name__)
    reason = line.split(". ")[0].rstrip(".")
    return reason if len(reason) <= 120 else reason[:117] + "..."


def _read_train_state(path: Path) -> dict[str, Any]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except OSError as exc:
        raise DonGymError(f"run dir {path.parent}: {path.name}: cannot be read ({exc.strerror or exc})") from None
    except Exception as exc:  # any unpickling failure means a damaged file
        # Deleting the state makes --resume start the run over: checkpoints hold weights but no optimiser.
        raise DonGymError(
            f"run dir {path.parent}: {path.name}: cannot be read, the file is damaged ({_short_reason(exc)}); "
            "delete it to train this run again from step 0, or train into a new --out"
        ) from None
    keys = ("model", "optimizer", "scheduler", "step")
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise DonGymError(f"{path}: not a training state (expected the keys {list(keys)})")
    return state


def _read_loss_rows(path: Path, up_to_step: int) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    try:
        with path.open() as f:
            return [row for row in csv.DictReader(f) if int(row["step"]) <= up_to_step]
    except (KeyError, TypeError, ValueError, UnicodeDecodeError, csv.Error) as exc:
        raise DonGymError(f"{path}: not a loss table with a 'step' column ({exc!r})") from None


def _write_loss_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


@contextmanager
def _writing(path: Path) -> Iterator[None]:
    """Turn a failed write (read-only or full file system, a file where a directory should be) into one line."""
    try:
        yield
    except OSError as exc:
        raise DonGymError(f"cannot write {path}: {exc.strerror or exc}") from None


def checkpoint_metadata(
    config: TrainConfig,
    dataset_info: dict[str, Any],
    image_size: tuple[int, int],
    step: int,
    background_descriptor: np.ndarray | None = None,
    part_space: dict[str, Any] | None = None,
) -> CheckpointMetadata:
    """What a checkpoint of this run records; ``background_descriptor`` is its targets' background (supervised
    methods: ``SupervisedFrames.background``), ``part_space`` the descriptor space of a network of several
    parts (:meth:`~don_gym.descriptors.multi_part.PartSpace.to_dict`)."""
    supervised = is_supervised(config.method)
    return CheckpointMetadata(
        part_space=dict(part_space or {}),
        method=config.method,
        object_name=dataset_info.get("object_name") or part_name(dataset_info["object"]),
        object_mesh_hash=dataset_info["mesh_hash"],
        image_size=tuple(image_size),
        descriptor_field_hash=dataset_info["descriptor_field_hash"] if supervised else "",
        background_descriptor=tuple(float(v) for v in background_descriptor) if supervised else (),
        renderer=dataset_info["renderer"],
        sensor_preset=dataset_info["sensor"],
        training_steps=step,
        extra={
            "seed": config.seed,
            "lr": config.learning_rate(),
            "batch_size": config.batch_size,
            "crop_size": list(config.crop_size) if config.crop_size else None,
            "background_crop_probability": config.background_crop_probability,
            "hard_object_fraction": config.hard_object_fraction,
            "hard_background_fraction": config.hard_background_fraction,
            "ema_decay": config.ema_decay,
            "dataset_scenes": int(dataset_info["scenes"]),
            "dataset_frames_per_scene": int(dataset_info["frames_per_scene"]),
            "dataset_seed": int(dataset_info["seed"]),
            "depth_source": "" if supervised else config.depth_source,
            "init": Path(config.init_path).name if config.init_path else None,
        },
    )


def dataset_part_identity(data: DONDataset, supervised: bool) -> PartIdentity | None:
    """The part (and for supervised methods the descriptor field) that a network trained on ``data`` carries
    in its checkpoint; None, with a warning, when the dataset's object cannot be loaded here."""
    try:
        part = data.object_model()
    except DonGymError as exc:
        warnings.warn(f"{exc}; the checkpoint will carry no part identity (matched to parts by name)", stacklevel=2)
        return None
    return PartIdentity.of(part, data.descriptor_field() if supervised else None)


@dataclass
class _RunStart:
    """Rank 0's verdict on the run directory, broadcast to every process."""

    error: str | None = None
    state: dict[str, Any] | None = None
    rows: list[dict[str, str]] = field(default_factory=list)


def _check_run_dir_place(out: Path) -> None:
    """Read-only: a file in the run directory's place, or a place where nothing can be written, is refused."""
    if out.exists() and not out.is_dir():
        raise DonGymError(f"--out {out}: is a file; expected a run directory (new or to --resume)")
    check_output_dir(out, "--out")


def _hold_run_dir(out: Path) -> tuple[DirectoryLock, Path | None]:
    """Create the run directory ``out`` (and missing parents) and take its lock, held for the whole run (and
    released by the kernel if the process dies): one writer per run directory. Returns the lock and the
    topmost directory created here (None: ``out`` existed), which a run refused before its first write
    removes. Another process writing ``out`` is refused in one line."""
    created = next((path for path in reversed([out, *out.parents]) if not path.exists()), None)
    out.mkdir(parents=True, exist_ok=True)
    lock = DirectoryLock(out)
    if not lock.lock(0, fcntl.LOCK_EX, blocking=False):
        lock.close()
        raise DonGymError(
            f"{out}: another training run is writing this run directory; wait for it to end (then --resume "
            "continues it), or choose another --out"
        )
    return lock, created


def _inspect_run_dir(out: Path, config: TrainConfig, identity: str, resume: bool) -> _RunStart:
    """Read-only, under the run directory's lock: the state to resume from (None: start afresh), or a user error."""
    state_path = out / TRAIN_STATE
    if not state_path.exists():
        # No progress saved (e.g. a run that failed before its first checkpoint): nothing to keep.
        return _RunStart()
    if not resume:
        raise DonGymError(f"{out}: already holds a training run; pass --resume to continue it or choose a new --out")
    changed = _changed_settings(_read_saved_config(out / RUN_CONFIG), config, identity)
    if changed:
        raise DonGymError(
            f"{out}: --resume with a different configuration than the saved {RUN_CONFIG} ({', '.join(changed)})"
        )
    state = _read_train_state(state_path)
    return _RunStart(state=state, rows=_read_loss_rows(out / LOSS_CSV, int(state["step"])))


def _open_source(config: TrainConfig) -> SupervisedFrames | CorrespondencePairs:
    if is_supervised(config.method):
        variant = SUPERVISED_TARGET_VARIANT[config.method]
        return SupervisedFrames(
            config.data,
            variant=variant,
            crop_size=config.crop_size,
            seed=config.seed,
            background_crop_probability=config.background_crop_probability,
            part_layout=config.part_layout,
        )
    return CorrespondencePairs(
        config.data,
        depth_source=config.depth_source,
        seed=config.seed,
        crop_size=config.crop_size,
        background_crop_probability=config.background_crop_probability,
    )


@contextmanager
def _terminate_as_exit() -> Iterator[None]:
    """torchrun stops the other processes with SIGTERM when one fails; exiting through Python
    (not at once) lets an interrupted atomic write remove its temporary file."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def train(config: TrainConfig, resume: bool = False, progress: bool = True) -> TrainResult:
    """Train a DON as configured; see the module docstring for what a run writes.

    Everything the configuration alone can get wrong is refused before any file is written.
    Under torchrun (``WORLD_SIZE`` set) every process calls this and trains its share of each batch.
    """
    launch = launch_environment()
    try:
        validate_config(config)
        device = resolve_device(config.device, launch)
        amp_dtype = autocast_dtype(config.precision, device)
        backend = resolve_backend(config.backend, device) if launch.world_size > 1 else ""
        if config.batch_size % launch.world_size:
            raise DonGymError(
                f"batch_size {config.batch_size} must be a multiple of the number of processes ({launch.world_size})"
            )
    except DonGymError as exc:
        raise same_on_every_process(exc) from None
    if config.threads is not None:
        torch.set_num_threads(int(config.threads))
    try:
        source = _open_source(config)
    except DonGymError as exc:
        raise same_on_every_process(exc) from None  # the processes of a launch read the same dataset
    if device.type == "cuda":
        torch.cuda.set_device(device)
        torch.backends.cudnn.benchmark = True  # fixed crop sizes: pick the fastest kernels once
    joined = start_process_group(launch, backend, device) if launch.world_size > 1 else False
    held: list[DirectoryLock] = []  # rank 0's lock on the run directory, from before its first write to the end
    try:
        with _terminate_as_exit():
            return _train(config, resume, progress, launch, device, amp_dtype, source, held)
    finally:
        for lock in held:
            lock.close()
        if joined:
            torch.distributed.destroy_process_group()


class _TrainingRun:
    """One session of a training run: the network, its optimiser and the losses so far, how a session starts
    (the run directory, a resumed state) and how it is saved. :func:`_train`'s loop drives it."""

    def __init__(
        self,
        config: TrainConfig,
        launch: LaunchEnvironment,
        device: torch.device,
        amp_dtype: torch.dtype | None,
        source: SupervisedFrames | CorrespondencePairs,
    ) -> None:
        self.config, self.launch, self.device, self.amp_dtype = config, launch, device, amp_dtype
        self.out = Path(config.out)
        self.info = source.data.info
        intrinsics = source.data.scenes[0].intrinsics
        self.image_size = (intrinsics.width, intrinsics.height)
        self.identity = dataset_identity(source.data)
        self.supervised = is_supervised(config.method)
        self.part_identity = dataset_part_identity(source.data, self.supervised) if launch.is_main else None
        self.target_background = source.background if isinstance(source, SupervisedFrames) else None
        part_space = getattr(source, "part_space", None)
        self.part_space_record = part_space.to_dict() if part_space is not None else None
        # A network of several parts outputs its space's D (one more than the fields' with the identity layout).
        descriptor_dim = (
            part_space.dim if part_space is not None and self.supervised else int(self.info["descriptor_dim"])
        )

        torch.manual_seed(config.seed)
        self.model = DenseObjectNet(config.arch, descriptor_dim).to(device)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=config.learning_rate(), weight_decay=config.weight_decay
        )
        self.scheduler = torch.optim.lr_scheduler.StepLR(
            self.optimizer, step_size=config.lr_decay_every, gamma=config.lr_decay
        )
        self.scaler = torch.amp.GradScaler(device.type) if amp_dtype == torch.float16 else None
        # The average starts from the network's first weights (random, pretrained or fine-tuned from; set again in
        # ``open_run_dir``) or from the resumed state's average (``restore``). Only rank 0 writes checkpoints, so
        # only rank 0 keeps it.
        self.ema_model = _frozen_copy(self.model) if config.ema_decay > 0 and launch.is_main else None
        self.start_step = 0
        # Training time and images of earlier sessions of a resumed run; None when unknown.
        self.earlier_seconds: float | None = 0.0
        self.earlier_images: int | None = 0
        self.rows: list[dict[str, Any]] = []
        self.images_seen = 0
        self.start_time = time.perf_counter()
        self.title = f"{config.method} on {self.info['object']} ({config.arch})"

    def open_run_dir(self, resume: bool, held: list[DirectoryLock]) -> _RunStart:
        """Rank 0: the run directory's lock (kept in ``held`` until the run ends), everything that reads the
        run directory or pretrained weights, then the first write."""
        out, config = self.out, self.config
        lock, created = None, None
        try:
            _check_run_dir_place(out)
            with _writing(out):
                lock, created = _hold_run_dir(out)
            run = _inspect_run_dir(out, config, self.identity, resume)
            if run.state is None and config.pretrained_path is not None:
                # Other processes receive these weights with DistributedDataParallel's first broadcast.
                self.model.load_pretrained_encoder(config.pretrained_path)
            if run.state is None and config.init_path is not None:
                self.load_init_weights(Path(config.init_path))
            if run.state is None and self.ema_model is not None:
                self.ema_model.load_state_dict(self.model.state_dict())
            with _writing(out / RUN_CONFIG):
                saved = {**asdict(config), DATASET_IDENTITY_KEY: self.identity}
                write_text_atomic(out / RUN_CONFIG, json.dumps(saved, indent=1) + "\n")
        except DonGymError as exc:
            if lock is not None:
                if created is not None:  # refused before its first write: leave no directory behind
                    shutil.rmtree(created, ignore_errors=True)
                lock.close()
            return _RunStart(error=str(exc))
        held.append(lock)
        return run

    def load_init_weights(self, path: Path) -> None:
        """The weights of checkpoint ``path`` into the network, once it is shown to be a network of this run's
        method, arch, part and descriptor space; :class:`DonGymError` naming what differs otherwise."""
        config, info = self.config, self.info
        network, metadata = load_checkpoint(
            path, expect_method=config.method, expect_descriptor_dim=self.model.descriptor_dim
        )
        problems = []
        if metadata.arch != config.arch:
            problems.append(f"arch is {metadata.arch!r}, this run's {config.arch!r}")
        if metadata.object_mesh_hash != info["mesh_hash"]:
            problems.append(f"it describes {metadata.object_name!r}, the dataset {info.get('object_name')!r}")
        if dict(metadata.part_space) != dict(self.part_space_record or {}):
            problems.append("its parts' descriptor space is not the dataset's")
        if self.target_background is not None and not np.allclose(
            metadata.background_descriptor, self.target_background, atol=1e-4
        ):
            problems.append("its background descriptor is not the dataset's (another descriptor field)")
        if problems:
            raise DonGymError(f"init checkpoint {path}: cannot be fine-tuned here: " + "; ".join(problems))
        self.model.load_state_dict(network.state_dict())

    def restore(self, run: _RunStart) -> None:
        """The resumed state of ``run`` (if any) into the network and optimiser, and its losses so far."""
        if run.state is not None:
            state = run.state
            try:
                self.model.load_state_dict(state["model"])
                self.optimizer.load_state_dict(state["optimizer"])
                self.scheduler.load_state_dict(state["scheduler"])
                if self.scaler is not None and "scaler" in state:
                    self.scaler.load_state_dict(state["scaler"])
                if self.ema_model is not None:
                    self.ema_model.load_state_dict(state["ema"])
            except (KeyError, RuntimeError, ValueError) as exc:
                detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                raise same_on_every_process(
                    DonGymError(f"{self.out / TRAIN_STATE}: does not fit this run's network or optimiser ({detail})")
                ) from None
            self.start_step = int(state["step"])
            self.earlier_seconds = float(state["seconds"]) if "seconds" in state else None
            self.earlier_images = int(state["images_seen"]) if "images_seen" in state else None
        self.rows = list(run.rows)

    def network(self) -> torch.nn.Module:
        """The network the steps train: the model, wrapped for several processes."""
        if self.launch.world_size == 1:
            return self.model
        synchronize_batchnorm(self.model, self.device)
        return torch.nn.parallel.DistributedDataParallel(
            self.model, device_ids=[self.device.index] if self.device.type == "cuda" else None
        )

    def session_seconds(self) -> float:
        # Resuming a finished run trains nothing: it reports, and keeps, the run's own time.
        return time.perf_counter() - self.start_time if self.config.steps > self.start_step else 0.0

    def save_state(self, step: int, seconds: float | None = None) -> None:
        """The resumable state; ``seconds`` this session's training time (default: until now)."""
        state_path = self.out / TRAIN_STATE
        timing = (
            {}
            if self.earlier_seconds is None or self.earlier_images is None
            else {
                "seconds": self.earlier_seconds + (self.session_seconds() if seconds is None else seconds),
                "images_seen": self.earlier_images + self.images_seen,
            }
        )
        with _writing(state_path):
            with atomic_path(state_path) as tmp:
                torch.save(
                    {
                        "model": self.model.state_dict(),
                        "optimizer": self.optimizer.state_dict(),
                        "scheduler": self.scheduler.state_dict(),
                        "step": step,
                        **({} if self.scaler is None else {"scaler": self.scaler.state_dict()}),
                        **({} if self.ema_model is None else {"ema": self.ema_model.state_dict()}),
                        **timing,
                    },
                    tmp,
                )
        with _writing(self.out / LOSS_CSV):
            _write_loss_csv(self.out / LOSS_CSV, self.rows)

    def saved_network(self) -> torch.nn.Module:
        """What checkpoints hold: the weights' moving average when ``ema_decay`` > 0, else the weights."""
        return self.model if self.ema_model is None else self.ema_model

    def update_average(self, step: int) -> None:
        """Fold the weights after step ``step`` (0-based) into their moving average."""
        if self.ema_model is None:
            return
        decay = min(self.config.ema_decay, (1 + step) / (10 + step))
        with torch.no_grad():
            averaged = self.ema_model.state_dict()
            for name, value in self.model.state_dict().items():
                if value.is_floating_point():
                    averaged[name].lerp_(value, 1.0 - decay)
                else:  # batch-norm's step counters
                    averaged[name].copy_(value)

    def save(self, step: int, path: Path, seconds: float | None = None) -> None:
        """Rank 0: the weights at ``path``, then the state and losses (a crash in between keeps the older state)."""
        if not self.launch.is_main:
            return
        metadata = checkpoint_metadata(
            self.config, self.info, self.image_size, step, self.target_background, self.part_space_record
        )
        with _writing(path):
            save_checkpoint(path, self.saved_network(), metadata, identity=self.part_identity)
        self.save_state(step, seconds)
        with _writing(self.out / LOSS_PNG):
            plot_loss_curve(self.rows, self.out / LOSS_PNG, self.title)

    def train_step(
        self,
        net: torch.nn.Module,
        step_loss: Callable[..., tuple[torch.Tensor, dict[str, float]]],
        batch: Any,
        step: int,
    ) -> dict[str, float]:
        """One optimiser step on ``batch``; the batch's loss and statistics, averaged over processes."""
        config, launch, device, scaler = self.config, self.launch, self.device, self.scaler
        try:
            with torch.autocast(device.type, dtype=self.amp_dtype) if self.amp_dtype is not None else nullcontext():
                loss, stats = step_loss(net, batch, device)
            self.optimizer.zero_grad(set_to_none=True)
            (loss if scaler is None else scaler.scale(loss)).backward()
            # The loss of the whole batch (mean over processes) decides, on every process alike.
            logged = _batch_means(loss, stats, launch.world_size)
            if not math.isfinite(logged["loss"]):
                raise same_on_every_process(
                    DonGymError(
                        f"loss became {logged['loss']} at step {step + 1} (lr {config.learning_rate():g}); lower --lr "
                        "(the run directory keeps its last checkpoint)"
                    )
                )
            if scaler is None:
                self.optimizer.step()
            else:
                scaler.step(self.optimizer)
                scaler.update()
            self.scheduler.step()
            self.update_average(step)
        except RuntimeError as exc:
            if launch.world_size == 1:
                raise
            # gloo prefixes its messages with a source location and appends advice; keep the finding.
            detail = re.sub(r"^\[[^\]]*\]\s*", "", (str(exc).strip().splitlines() or [type(exc).__name__])[0])
            detail = detail.split(". ")[0]
            raise DonGymError(
                f"rank {launch.rank}: step {step + 1} failed ({detail}); another process has probably stopped. "
                f"The last checkpoint in {self.out} is intact: rerun with --resume"
            ) from None
        return logged

    def log(self, step: int, logged: dict[str, float], images: int, bar: tqdm) -> None:
        """A finished step's row of the loss table and the progress bar's figures."""
        self.images_seen += images
        rate = self.images_seen / (time.perf_counter() - self.start_time)
        self.rows.append(
            {
                "step": step + 1,
                "loss": f"{logged['loss']:.6g}",
                "lr": f"{self.scheduler.get_last_lr()[0]:.3g}",
                **{k: f"{v:.6g}" for k, v in logged.items() if k != "loss"},
            }
        )
        bar.set_postfix(loss=f"{logged['loss']:.4f}", img_s=f"{rate:.1f}")

    def result(self, seconds: float, steady_from: float, data_wait: float) -> TrainResult:
        """What the session reports: the final loss (mean of the last 5% of steps), the run's time and pace (over
        every session, when known) and the share of its steady time spent waiting for data."""
        config, rows = self.config, self.rows
        final_loss = float(np.mean([float(r["loss"]) for r in rows[-max(1, len(rows) // 20) :]]))
        steady_seconds = self.start_time + seconds - steady_from if config.steps > self.start_step + 1 else 0.0
        wait_fraction = data_wait / steady_seconds if steady_seconds > 0 else None
        final = self.out / FINAL_MODEL
        if self.earlier_seconds is None or self.earlier_images is None:
            return TrainResult(final, final_loss, config.steps, None, None, wait_fraction)
        total_seconds = self.earlier_seconds + seconds
        total_images = self.earlier_images + self.images_seen
        return TrainResult(
            final, final_loss, config.steps, total_seconds, total_images / max(total_seconds, 1e-9), wait_fraction
        )


def _train(
    config: TrainConfig,
    resume: bool,
    progress: bool,
    launch: LaunchEnvironment,
    device: torch.device,
    amp_dtype: torch.dtype | None,
    source: SupervisedFrames | CorrespondencePairs,
    held: list[DirectoryLock],
) -> TrainResult:
    session = _TrainingRun(config, launch, device, amp_dtype, source)
    run = broadcast_from_main(session.open_run_dir(resume, held) if launch.is_main else None)
    if run.error is not None:
        raise same_on_every_process(DonGymError(run.error))
    session.restore(run)
    del run
    net = session.network()
    batches = StepBatches(
        source, config.steps, config.batch_size, config.seed, AugmentConfig(**config.augment), launch.rank,
        launch.world_size,
    )  # fmt: skip
    loader = step_loader(batches, session.start_step, config.workers, pin_memory=device.type == "cuda")
    images_per_step = config.batch_size * (1 if session.supervised else 2)
    step_loss = _supervised_step_loss(config) if session.supervised else _contrastive_step_loss(config)
    net.train()
    data_wait = 0.0
    session.start_time = steady_from = time.perf_counter()
    bar = tqdm(
        range(session.start_step, config.steps),
        initial=session.start_step,
        total=config.steps,
        desc=config.method,
        unit="step",
        disable=not (progress and launch.is_main),
    )
    batch_iterator = iter(loader)
    for step in bar:
        waited_from = time.perf_counter()
        batch = next(batch_iterator)
        arrived = time.perf_counter()
        if step == session.start_step:
            steady_from = arrived  # the first batch's wait is the workers' start-up, not their pace
        else:
            data_wait += arrived - waited_from
        if "error" in batch:
            raise batch["error"]
        logged = session.train_step(net, step_loss, batch, step)
        session.log(step, logged, images_per_step, bar)
        done = step + 1
        if done % config.checkpoint_every == 0 or done == config.steps:
            session.save(done, session.out / "checkpoints" / f"step_{done:06d}.safetensors")
    bar.close()
    del batch_iterator  # stops the loader's worker processes
    seconds = session.session_seconds()
    session.save(config.steps, session.out / FINAL_MODEL, seconds)  # the state records the time this run reports
    return session.result(seconds, steady_from, data_wait)


def _frozen_copy(model: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``model`` in eval mode that no optimiser sees, to hold its weights' moving average."""
    copy = DenseObjectNet(model.arch, model.descriptor_dim).to(next(model.parameters()).device)
    copy.load_state_dict(model.state_dict())
    copy.eval()
    for parameter in copy.parameters():
        parameter.requires_grad_(False)
    return copy


def _to_device(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    # Batches come pinned when the device is a GPU, so the copy overlaps with queued work.
    return tensor.to(device, non_blocking=True)


def _channels_last(rgb: torch.Tensor, device: torch.device) -> torch.Tensor:
    # The network computes in channels-last; on a GPU the input is converted once, on arrival.
    rgb = _to_device(rgb, device)
    return rgb.contiguous(memory_format=torch.channels_last) if device.type == "cuda" else rgb


def _supervised_step_loss(config: TrainConfig) -> Callable[..., tuple[torch.Tensor, dict[str, float]]]:
    def step_loss(
        net: torch.nn.Module, batch: dict[str, Any], device: torch.device
    ) -> tuple[torch.Tensor, dict[str, float]]:
        pred = net(_channels_last(batch["rgb"], device))
        # The loss sums ~10^5 pixels: float32 even under autocast.
        loss = supervised_l2_loss(
            pred.float(),
            _to_device(batch["target"], device),
            _to_device(batch["object_mask"], device),
            config.hard_object_fraction,
            config.hard_background_fraction,
        )
        return loss, {}

    return step_loss


def _contrastive_step_loss(config: TrainConfig) -> Callable[..., tuple[torch.Tensor, dict[str, float]]]:
    def step_loss(
        net: torch.nn.Module, batch: dict[str, Any], device: torch.device
    ) -> tuple[torch.Tensor, dict[str, float]]:
        both = net(_channels_last(torch.cat([batch["rgb_a"], batch["rgb_b"]]), device)).float()
        pairs = len(batch["correspondences"])
        return batch_contrastive_loss(
            both[:pairs], both[pairs:], batch["correspondences"], config.object_margin, config.background_margin
        )

    return step_loss


def _batch_means(loss: torch.Tensor, stats: dict[str, float], world_size: int) -> dict[str, float]:
    """Loss and statistics of the whole step's batch: means over processes, except counts (``num_*``), summed."""
    stats = {k: v for k, v in stats.items() if k != "loss"}  # the same quantity as ``loss``
    if world_size == 1:
        return {"loss": loss.item(), **stats}
    names = ["loss", *stats]
    values = torch.tensor([loss.item(), *(float(stats[k]) for k in stats)], dtype=torch.float64, device=loss.device)
    values = all_reduce_sum(values)
    divisors = [1.0 if name.startswith("num_") else world_size for name in names]
    return {name: value / divisor for name, value, divisor in zip(names, values.tolist(), divisors, strict=True)}
