"""Multi-process data-parallel training on ``torch.distributed``, as launched by ``torchrun``.

:func:`launch_environment` reads the process's rank from torchrun's environment variables;
:func:`start_process_group` joins the group (NCCL for GPUs, gloo for CPUs). Batch statistics
of BatchNorm layers are computed over every process's share of the batch
(:func:`synchronize_batchnorm`), so N processes with batch B/N each train the same network
as one process with batch B.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from don_gym.errors import DonGymError

__all__ = [
    "BACKENDS",
    "COLLECTIVE_TIMEOUT",
    "SINGLE_PROCESS",
    "LaunchEnvironment",
    "SyncedBatchNorm2d",
    "all_reduce_sum",
    "broadcast_from_main",
    "launch_environment",
    "reported_elsewhere",
    "resolve_backend",
    "same_on_every_process",
    "start_process_group",
    "synchronize_batchnorm",
]

#: Values of ``TrainConfig.backend``; "auto" is NCCL on CUDA and gloo on the CPU.
BACKENDS = ("auto", "gloo", "nccl")
#: How long a collective waits for a process that stopped answering before the run ends.
COLLECTIVE_TIMEOUT = datetime.timedelta(minutes=10)


@dataclass(frozen=True)
class LaunchEnvironment:
    """This process's place in a torchrun launch (``WORLD_SIZE`` processes in all)."""

    rank: int
    world_size: int
    local_rank: int

    @property
    def is_main(self) -> bool:
        return self.rank == 0


SINGLE_PROCESS = LaunchEnvironment(rank=0, world_size=1, local_rank=0)


def launch_environment(environ: dict[str, str] | None = None) -> LaunchEnvironment:
    """The rank, world size and local rank torchrun set, or :data:`SINGLE_PROCESS` outside torchrun."""
    environ = dict(os.environ if environ is None else environ)
    names = ("RANK", "WORLD_SIZE", "LOCAL_RANK")
    if "WORLD_SIZE" not in environ:
        return SINGLE_PROCESS
    values = {}
    for name in names:
        text = environ.get(name, "0" if name == "LOCAL_RANK" else None)
        try:
            values[name] = int(text)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise DonGymError(
                f"environment variable {name}={text!r}: expected an integer, as torchrun sets it "
                "(launch with torchrun --nproc_per_node=N -m don_gym.cli train ...)"
            ) from None
    world_size, rank = values["WORLD_SIZE"], values["RANK"]
    if world_size < 1 or not 0 <= rank < world_size or values["LOCAL_RANK"] < 0:
        raise DonGymError(f"torchrun environment RANK={rank}, WORLD_SIZE={world_size}: expected 0 <= RANK < WORLD_SIZE")
    return LaunchEnvironment(rank, world_size, values["LOCAL_RANK"])


def resolve_backend(name: str, device: torch.device) -> str:
    """The torch.distributed backend for ``name`` (:data:`BACKENDS`) on ``device``; a one-line error if unusable."""
    if name not in BACKENDS:
        raise DonGymError(f"backend {name!r} is unknown; expected one of {list(BACKENDS)}")
    backend = ("nccl" if device.type == "cuda" else "gloo") if name == "auto" else name
    if not dist.is_available():
        raise DonGymError("multi-process training needs torch.distributed, which this torch build lacks")
    if backend == "nccl" and device.type != "cuda":
        raise DonGymError(f"backend 'nccl' runs on GPUs only, but the device is {device}; use --backend gloo on CPUs")
    available = dist.is_nccl_available() if backend == "nccl" else dist.is_gloo_available()
    if not available:
        raise DonGymError(f"backend {backend!r} is not available in this torch build ({torch.__version__})")
    return backend


def start_process_group(launch: LaunchEnvironment, backend: str, device: torch.device) -> bool:
    """Join torchrun's process group unless already joined; True if this call joined it (and should leave it)."""
    if dist.is_initialized():
        if dist.get_world_size() != launch.world_size:
            raise DonGymError(
                f"a process group of {dist.get_world_size()} processes already exists, but WORLD_SIZE is "
                f"{launch.world_size}"
            )
        return False
    missing = [name for name in ("MASTER_ADDR", "MASTER_PORT") if name not in os.environ]
    if missing:
        raise DonGymError(f"WORLD_SIZE is set but {' and '.join(missing)} not; launch with torchrun, which sets both")
    if "TORCHELASTIC_RUN_ID" in os.environ:
        from don_gym.processes import end_with_parent

        # torchrun starts every process in a session of its own: killed with kill -9, it would leave them
        # training (rank 0 holding the run directory's lock) until a collective timed out.
        end_with_parent(os.getppid(), parent_death_signal=False)
    options: dict[str, Any] = {"timeout": COLLECTIVE_TIMEOUT}
    if device.type == "cuda":
        options["device_id"] = device
    dist.init_process_group(backend, rank=launch.rank, world_size=launch.world_size, **options)
    return True


def all_reduce_sum(tensor: torch.Tensor) -> torch.Tensor:
    """Sum of ``tensor`` over all processes (in place, returned); ``tensor`` itself outside a group."""
    if dist.is_initialized() and dist.get_world_size() > 1:
        dist.all_reduce(tensor)
    return tensor


def broadcast_from_main(value: Any) -> Any:
    """Rank 0's ``value`` on every process (any picklable object); ``value`` itself outside a group."""
    if not (dist.is_initialized() and dist.get_world_size() > 1):
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


class _AllReduceSum(torch.autograd.Function):
    """Sum over processes whose gradient is the sum of the gradients over processes."""

    @staticmethod
    def forward(ctx: Any, tensor: torch.Tensor) -> torch.Tensor:
        total = tensor.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(total)
        return total

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        total = grad.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(total)
        return total


class SyncedBatchNorm2d(nn.BatchNorm2d):
    """BatchNorm2d whose training-mode statistics span every process of the group.

    torch's own ``nn.SyncBatchNorm`` runs on GPUs only; this one works with any backend (gloo
    on CPUs) through an all-reduce that autograd differentiates. Two all-reduces per layer (sum
    and count, then squared deviations) compute the variance about the global mean, as a
    single process does. Parameter and buffer names are those of ``nn.BatchNorm2d``.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        channels = x.shape[1]
        dims = (0, 2, 3)
        count = torch.tensor([x.numel() // channels], dtype=x.dtype, device=x.device)
        totals = _AllReduceSum.apply(torch.cat([x.sum(dims), count]))
        total_count = totals[channels]
        mean = totals[:channels] / total_count
        centred = x - mean.view(1, -1, 1, 1)
        var = _AllReduceSum.apply(centred.pow(2).sum(dims)) / total_count
        out = centred * torch.rsqrt(var + self.eps).view(1, -1, 1, 1)
        if self.affine:
            out = out * self.weight.view(1, -1, 1, 1) + self.bias.view(1, -1, 1, 1)
        if self.track_running_stats and self.running_mean is not None and self.running_var is not None:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)  # type: ignore[union-attr]
                factor = 1.0 / float(self.num_batches_tracked) if self.momentum is None else self.momentum
                unbiased = var * (total_count / (total_count - 1).clamp(min=1))
                self.running_mean.mul_(1 - factor).add_(mean.detach(), alpha=factor)
                self.running_var.mul_(1 - factor).add_(unbiased.detach(), alpha=factor)
        return out


def synchronize_batchnorm(module: nn.Module, device: torch.device) -> nn.Module:
    """Swap every ``nn.BatchNorm2d`` of ``module`` for one with statistics over all processes, in place.

    On CUDA this is torch's ``nn.SyncBatchNorm`` (fused NCCL kernels), elsewhere
    :class:`SyncedBatchNorm2d`. Parameters and buffers are moved, not copied, so an optimiser
    created afterwards and the state-dict keys are unaffected.
    """
    if device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(module)
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm2d:
            synced = SyncedBatchNorm2d(
                child.num_features, child.eps, child.momentum, child.affine, child.track_running_stats
            ).to(device)
            synced.load_state_dict(child.state_dict())
            if child.affine:
                synced.weight, synced.bias = child.weight, child.bias
            setattr(module, name, synced)
        else:
            synchronize_batchnorm(child, device)
    return module


def same_on_every_process(exc: BaseException) -> BaseException:
    """Mark ``exc`` as raised alike by every process of a launch (a bad option, a broadcast
    verdict of rank 0), so that the command line prints it once, from rank 0."""
    exc.same_on_every_process = True  # type: ignore[attr-defined]
    return exc


def reported_elsewhere(exc: BaseException, launch: LaunchEnvironment) -> bool:
    """True if rank 0 prints ``exc`` for this process (see :func:`same_on_every_process`)."""
    return not launch.is_main and getattr(exc, "same_on_every_process", False)
