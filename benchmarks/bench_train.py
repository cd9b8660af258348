"""Training throughput and single-frame inference latency of the DON networks.

For each network size (default: the CPU-sized ``resnet-lite`` and the paper's
``resnet34``, the baseline) this measures

- training images per second: forward + supervised l2 loss + backward + Adam step on
  random images, targets and object masks of the given size and batch, on ``--device``;
- inference milliseconds per frame through ``DenseObjectNet.descriptor_image`` (uint8
  HWC in, float32 HWD out), on the CPU with ``torch.set_num_threads(2)``: warm-up, then
  the median (and 90th percentile, minimum) over repeats. The target for the default network is at
  most 30 ms per 320x240 frame;
- parameter count and the size of a float32 and a float16 checkpoint file written by
  ``don_gym.checkpoints.save_checkpoint``.

The networks are timed in alternation (one step or frame each, in turn) so that a change
in machine load during the run affects all of them alike and the ratios stay fair.
Results go to the "train-speed" section of benchmarks/RESULTS.md (not with --quick).

    python benchmarks/bench_train.py            # full run, records RESULTS.md
    python benchmarks/bench_train.py --quick    # smoke run, few repeats, records nothing
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record_section  # noqa: E402

from don_gym.checkpoints import CheckpointMetadata, save_checkpoint  # noqa: E402
from don_gym.losses import supervised_l2_loss  # noqa: E402
from don_gym.model import ARCHS, DEFAULT_ARCH, DenseObjectNet, count_parameters  # noqa: E402

BASELINE_ARCH = "resnet34"
TARGET_MS = 30.0


def _machine_busy_seconds() -> float | None:
    """CPU seconds all processes have spent busy since boot (Linux /proc/stat), or None elsewhere."""
    try:
        with open("/proc/stat") as f:
            ticks = [int(v) for v in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = ticks[3] + ticks[4]  # idle + iowait
    return (sum(ticks) - idle) / os.sysconf("SC_CLK_TCK")


class OtherProcessLoad:
    """Average number of CPU cores that *other* processes kept busy while the block ran.

    Timings on a shared machine are only meaningful when this is near 0; it is reported
    next to the figures so a reader can tell.
    """

    def __enter__(self) -> OtherProcessLoad:
        self.wall = time.perf_counter()
        self.busy = _machine_busy_seconds()
        self.own = sum(os.times()[:2])
        self.cores: float | None = None
        return self

    def __exit__(self, *exc: object) -> None:
        busy = _machine_busy_seconds()
        if busy is not None and self.busy is not None:
            own = sum(os.times()[:2]) - self.own
            self.cores = max(0.0, (busy - self.busy - own) / (time.perf_counter() - self.wall))

    def describe(self) -> str:
        return "unknown" if self.cores is None else f"{self.cores:.2f}"


def wait_for_quiet_machine(max_wait_s: float, threshold_cores: float = 0.2) -> None:
    """Poll 2 s windows until other processes use under ``threshold_cores`` cores, at most ``max_wait_s``."""
    deadline = time.monotonic() + max_wait_s
    while time.monotonic() < deadline:
        with OtherProcessLoad() as load:
            time.sleep(2.0)
        if load.cores is None or load.cores < threshold_cores:
            return
        print(f"waiting for a quiet machine: other processes use {load.describe()} cores", flush=True)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--archs", default=f"{DEFAULT_ARCH},{BASELINE_ARCH}", help="comma-separated networks to time")
    parser.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    parser.add_argument("--height", type=int, default=240, help="image height in pixels (default 240)")
    parser.add_argument("--batch-size", type=int, default=4, help="training batch size (default 4)")
    parser.add_argument("--descriptor-dim", type=int, default=3, help="D (default 3)")
    parser.add_argument("--device", default="auto", help="training device: auto (cuda if available), cpu, cuda")
    parser.add_argument("--train-steps", type=int, default=6, help="timed training steps per network")
    parser.add_argument("--train-warmup", type=int, default=1, help="untimed training steps per network")
    parser.add_argument("--repeats", type=int, default=40, help="timed inference frames per network")
    parser.add_argument("--warmup", type=int, default=5, help="untimed inference frames per network")
    parser.add_argument(
        "--inference-threads",
        default="2,1",
        help="comma-separated CPU thread counts for inference; the target applies to the first (default 2,1)",
    )
    parser.add_argument(
        "--wait-quiet",
        type=float,
        default=0.0,
        help="before each timing phase, wait up to this many seconds for other processes to leave the CPU idle",
    )
    parser.add_argument("--quick", action="store_true", help="few steps and repeats; does not record RESULTS.md")
    parser.add_argument("--no-record", action="store_true", help="print only, do not update RESULTS.md")
    args = parser.parse_args(argv)
    args.archs = [a.strip() for a in args.archs.split(",") if a.strip()]
    args.inference_threads = [int(t) for t in str(args.inference_threads).split(",") if t.strip()]
    unknown = [a for a in args.archs if a not in ARCHS]
    if unknown:
        parser.error(f"unknown arch {unknown}; choose from {sorted(ARCHS)}")
    if args.quick:
        args.train_steps, args.train_warmup, args.repeats, args.warmup = 2, 1, 5, 2
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    return args


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_training(args: argparse.Namespace) -> dict[str, list[float]]:
    """Seconds per training step for each arch, the archs stepped in alternation."""
    device = torch.device(args.device)
    generator = torch.Generator().manual_seed(0)
    shape = (args.batch_size, 3, args.height, args.width)
    rgb = torch.rand(shape, generator=generator).to(device)
    target = torch.rand((args.batch_size, args.descriptor_dim, args.height, args.width), generator=generator)
    target = target.to(device)
    mask = torch.zeros((args.batch_size, args.height, args.width), dtype=torch.bool)
    mask[:, args.height // 4 : 3 * args.height // 4, args.width // 3 : 2 * args.width // 3] = True
    mask = mask.to(device)
    setups = {}
    for arch in args.archs:
        model = DenseObjectNet(arch, args.descriptor_dim).to(device).train()
        # The original DON's optimiser settings (NOTES.md section 2).
        setups[arch] = (model, torch.optim.Adam(model.parameters(), lr=1e-4, weight_decay=1e-4))
    step_seconds: dict[str, list[float]] = {arch: [] for arch in args.archs}
    for step in range(args.train_warmup + args.train_steps):
        for arch, (model, optimizer) in setups.items():
            _sync(device)
            start = time.perf_counter()
            loss = supervised_l2_loss(model(rgb), target, mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            _sync(device)
            if step >= args.train_warmup:
                step_seconds[arch].append(time.perf_counter() - start)
    return step_seconds


def time_inference(args: argparse.Namespace, threads: int) -> dict[str, list[float]]:
    """Milliseconds per ``descriptor_image`` call on the CPU with ``threads`` threads, the archs in alternation."""
    torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, size=(args.height, args.width, 3), dtype=np.uint8)
    models = {arch: DenseObjectNet(arch, args.descriptor_dim).eval() for arch in args.archs}
    frame_ms: dict[str, list[float]] = {arch: [] for arch in args.archs}
    for index in range(args.warmup + args.repeats):
        for arch, model in models.items():
            start = time.perf_counter()
            model.descriptor_image(frame)
            if index >= args.warmup:
                frame_ms[arch].append(1000.0 * (time.perf_counter() - start))
    return frame_ms


def checkpoint_sizes_mb(arch: str, descriptor_dim: int, width: int, height: int) -> tuple[int, float, float]:
    model = DenseObjectNet(arch, descriptor_dim)
    metadata = CheckpointMetadata("supervised", "benchmark", "", (width, height))
    sizes = []
    with tempfile.TemporaryDirectory() as tmp:
        for dtype in ("float32", "float16"):
            path = Path(tmp) / f"{arch}-{dtype}.safetensors"
            save_checkpoint(path, model, metadata, weights_dtype=dtype)
            sizes.append(path.stat().st_size / 1e6)
    return count_parameters(model), sizes[0], sizes[1]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    default_threads = torch.get_num_threads()
    load_before = os.getloadavg()
    print(
        f"training on {args.device} ({default_threads} CPU threads), batch {args.batch_size}, "
        f"{args.width}x{args.height}; inference on CPU with {args.inference_threads} threads",
        flush=True,
    )
    # Inference first: it is short, and it carries the latency target.
    frame_ms = {}
    inference_load = {}
    for threads in args.inference_threads:
        wait_for_quiet_machine(args.wait_quiet)
        with OtherProcessLoad() as inference_load[threads]:
            frame_ms[threads] = time_inference(args, threads)
    torch.set_num_threads(default_threads)
    wait_for_quiet_machine(args.wait_quiet)
    with OtherProcessLoad() as training_load:
        step_seconds = time_training(args)
    load_after = os.getloadavg()

    baseline = BASELINE_ARCH if BASELINE_ARCH in args.archs else None
    train_ips = {a: args.batch_size / float(np.median(s)) for a, s in step_seconds.items()}
    main_threads = args.inference_threads[0]
    infer_ms = {a: float(np.median(v)) for a, v in frame_ms[main_threads].items()}
    rows = []
    for arch in args.archs:
        params, mb32, mb16 = checkpoint_sizes_mb(arch, args.descriptor_dim, args.width, args.height)
        train_ratio = f"{train_ips[arch] / train_ips[baseline]:.1f}x" if baseline else "-"
        infer_ratio = f"{infer_ms[baseline] / infer_ms[arch]:.1f}x" if baseline else "-"
        p90 = float(np.percentile(frame_ms[main_threads][arch], 90))
        fastest = float(np.min(frame_ms[main_threads][arch]))
        other_threads = "".join(f" | {float(np.median(frame_ms[t][arch])):.1f}" for t in args.inference_threads[1:])
        verdict = ("yes" if infer_ms[arch] <= TARGET_MS else "NO") if arch == DEFAULT_ARCH else "-"
        rows.append(
            f"| `{arch}`{' (default)' if arch == DEFAULT_ARCH else ''}{' (baseline)' if arch == baseline else ''} "
            f"| {params / 1e6:.2f} M | {mb32:.1f} / {mb16:.1f} | {train_ips[arch]:.1f} | {train_ratio} "
            f"| {infer_ms[arch]:.1f} ({p90:.1f}, {fastest:.1f}) | {infer_ratio} | {verdict}{other_threads} |"
        )
    device_name = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "CPU"
    extra_headers = "".join(f" | inference ms, {t} thread{'s' if t > 1 else ''}" for t in args.inference_threads[1:])
    body = "\n".join(
        [
            f"Training: forward + supervised l2 loss + backward + Adam step, batch {args.batch_size}, "
            f"{args.width}x{args.height}, D={args.descriptor_dim}, on {args.device} ({device_name}, "
            f"{default_threads} CPU threads); median over {args.train_steps} steps after {args.train_warmup} "
            f"warm-up. Inference: `descriptor_image` on one uint8 {args.width}x{args.height} frame on the CPU with "
            f"`torch.set_num_threads({main_threads})` (and the other thread counts listed), median (90th "
            f"percentile, minimum) over {args.repeats} frames after {args.warmup} warm-up. Networks timed in "
            f"alternation. Baseline: `{BASELINE_ARCH}`, the paper's network. Checkpoint sizes are safetensors "
            "files from `save_checkpoint`.",
            "",
            "| network | parameters | checkpoint MB float32 / float16 | train images/s | train speed vs baseline "
            f"| inference ms, {main_threads} threads, median (p90, min) | inference speed-up vs baseline "
            f"| <= {TARGET_MS:.0f} ms{extra_headers} |",
            "|---|---|---|---|---|---|---|---|" + "---|" * (len(args.inference_threads) - 1),
            *rows,
            "",
            "CPU cores kept busy by other processes while timing (0 = the machine was ours): inference "
            + ", ".join(
                f"{t} thread{'s' if t > 1 else ''}: {inference_load[t].describe()}" for t in args.inference_threads
            )
            + f"; training: {training_load.describe()}. Load average (1 min) before / after: {load_before[0]:.2f} / "
            f"{load_after[0]:.2f}. When another process takes a core, 2-thread inference stalls at OpenMP barriers "
            "(see p90); 1 thread is far less sensitive to that.",
        ]
    )
    print(body)
    if args.quick or args.no_record:
        print("(not recorded: --quick or --no-record)")
    else:
        record_section("train-speed", "DON training and inference speed", body)
        print("recorded section 'train-speed' in benchmarks/RESULTS.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
