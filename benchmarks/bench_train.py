"""Training throughput and single-frame inference latency of the DON networks.

For each network size (default: the CPU-sized ``resnet-lite`` and the paper's ``resnet34``, the baseline),
timed in alternation so that machine load hits all alike: training images per second, inference ms per frame
on the CPU (target for the default network: at most 30 ms per 320x240 frame), parameter count and checkpoint
sizes. Results go to the "train-speed" section of benchmarks/RESULTS.md (not with --quick).

Further parts (``--parts``), each against its baseline in the same run, on a dataset it builds once
(640x480 toolcap frames, cached in the temp directory) and the real training code:

- ``loader`` ("train-loader"): training images/s of ``resnet-lite`` on 128x128 crops with batches built
  in the training loop (``--workers 0``, the baseline) and in worker processes, in alternating blocks;
- ``ddp`` ("train-ddp"): ``don-gym train`` in one process against ``torchrun`` with 2 gloo processes;
- ``threads`` ("train-threads"): training steps and inference of ``resnet-lite`` with 1 and 2 torch threads, on the
  machine as it is and while processes this run starts keep all cores but one busy (the README's advice to train
  with ``--threads 1`` on a shared machine rests on it);
- ``gpu`` ("train-gpu", needs CUDA; ``benchmarks/device_check_train.sh``): images/s of ``resnet-lite`` and
  ``resnet34`` on whole 640x480 frames, fp32 against mixed precision, and the share of step time spent
  waiting for data.

    python benchmarks/bench_train.py            # full run (speed, loader, ddp, threads), records RESULTS.md
    python benchmarks/bench_train.py --quick    # smoke run, few repeats, records nothing
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import OtherProcessLoad, record_section  # noqa: E402

from don_gym.data.build import DatasetConfig, build_dataset  # noqa: E402
from don_gym.learning.augment import AugmentConfig  # noqa: E402
from don_gym.learning.checkpoints import CheckpointMetadata, save_checkpoint  # noqa: E402
from don_gym.learning.losses import supervised_l2_loss  # noqa: E402
from don_gym.learning.model import ARCHS, DEFAULT_ARCH, DenseObjectNet, count_parameters  # noqa: E402
from don_gym.learning.torch_data import StepBatches, SupervisedFrames, step_loader  # noqa: E402
from don_gym.learning.train import TRAIN_STATE, TrainConfig, train  # noqa: E402

BASELINE_ARCH = "resnet34"
TARGET_MS = 30.0
PARTS = ("speed", "loader", "ddp", "threads", "gpu")
#: Frames and crops of the loader, ddp and gpu parts: the shipped networks' training set-up.
FRAME_SIZE = (640, 480)
CROP_SIZE = (128, 128)
LOADER_TARGET = 1.4
GPU_WAIT_TARGET = 0.10


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
    parser.add_argument(
        "--parts",
        default="speed,loader,ddp,threads",
        help=f"comma-separated parts among {', '.join(PARTS)} (default %(default)s)",
    )
    parser.add_argument("--loader-workers", default="1,2", help="worker counts timed against 0 (default 1,2)")
    parser.add_argument("--loader-steps", type=int, default=10, help="timed steps per block of the loader part")
    parser.add_argument("--loader-blocks", type=int, default=4, help="blocks per setting of the loader part")
    parser.add_argument("--ddp-steps", type=int, default=24, help="timed steps of each run of the ddp part")
    parser.add_argument("--threads-blocks", type=int, default=2, help="alternating blocks of the threads part")
    parser.add_argument("--gpu-steps", type=int, default=60, help="timed steps of each run of the gpu part")
    parser.add_argument("--gpu-batch-size", type=int, default=8, help="batch of the gpu part (default 8)")
    parser.add_argument(
        "--gpu-workers", type=int, default=min(8, os.cpu_count() or 1), help="data workers of the gpu part"
    )
    parser.add_argument("--quick", action="store_true", help="few steps and repeats; does not record RESULTS.md")
    parser.add_argument("--no-record", action="store_true", help="print only, do not update RESULTS.md")
    args = parser.parse_args(argv)
    args.parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not set(args.parts) <= set(PARTS):
        parser.error(f"unknown parts {sorted(set(args.parts) - set(PARTS))}; choose from {PARTS}")
    args.loader_workers = [int(w) for w in str(args.loader_workers).split(",") if w.strip()]
    args.archs = [a.strip() for a in args.archs.split(",") if a.strip()]
    args.inference_threads = [int(t) for t in str(args.inference_threads).split(",") if t.strip()]
    unknown = [a for a in args.archs if a not in ARCHS]
    if unknown:
        parser.error(f"unknown arch {unknown}; choose from {sorted(ARCHS)}")
    if args.quick:
        args.train_steps, args.train_warmup, args.repeats, args.warmup = 1, 1, 3, 1
        args.width, args.height, args.inference_threads = 160, 120, args.inference_threads[:1]
        args.loader_steps, args.loader_blocks, args.loader_workers = 2, 1, args.loader_workers[-1:]
        args.ddp_steps, args.gpu_steps, args.threads_blocks = 2, 4, 1
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    return args


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_training(args: argparse.Namespace) -> dict[str, list[float]]:
    """Seconds per training step for each arch, the archs stepped in alternation.

    A step is forward + supervised l2 loss + backward + Adam step on random images, targets and object
    masks of the given size and batch, on ``--device``.
    """
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
        # The original DON's optimiser settings (docs/background.md, section "Self-supervised DON training").
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
    """Milliseconds per ``descriptor_image`` call on the CPU with ``threads`` threads, the archs in alternation.

    uint8 HWC in, float32 HWD out; warm-up first, the caller reports the median, 90th percentile and minimum.
    """
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
    """Parameter count and the MB of a float32 and a float16 checkpoint written by ``save_checkpoint``."""
    model = DenseObjectNet(arch, descriptor_dim)
    metadata = CheckpointMetadata("supervised", "benchmark", "", (width, height))
    sizes = []
    with tempfile.TemporaryDirectory() as tmp:
        for dtype in ("float32", "float16"):
            path = Path(tmp) / f"{arch}-{dtype}.safetensors"
            save_checkpoint(path, model, metadata, weights_dtype=dtype)
            sizes.append(path.stat().st_size / 1e6)
    return count_parameters(model), sizes[0], sizes[1]


def run_speed(args: argparse.Namespace) -> None:
    """The "train-speed" part: synthetic training steps and single-frame inference per network."""
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


def _record(args: argparse.Namespace, name: str, title: str, body: str) -> None:
    print(body, flush=True)
    if args.quick or args.no_record:
        print(f"(section '{name}' not recorded: --quick or --no-record)")
    else:
        record_section(name, title, body)
        print(f"recorded section '{name}' in benchmarks/RESULTS.md")


def benchmark_dataset(scenes: int, frames_per_scene: int, workers: int = 1) -> Path:
    """Toolcap frames at :data:`FRAME_SIZE` for the supervised methods (no depth fusion), built once
    into the temp directory; a later run reuses the finished scenes."""
    width, height = FRAME_SIZE
    root = Path(tempfile.gettempdir()) / "don_gym_bench_train" / f"toolcap_{width}x{height}_{scenes}x{frames_per_scene}"
    config = DatasetConfig(
        object="toolcap", scenes=scenes, frames_per_scene=frames_per_scene, image_size=FRAME_SIZE, fuse_depth=False
    )
    build_dataset(config, root, workers=workers, progress=False)
    return root


def _describe_load(load: OtherProcessLoad) -> str:
    return f"CPU cores kept busy by other processes while timing (0 = the machine was ours): {load.describe()}."


def run_loader(args: argparse.Namespace) -> None:
    """The "train-loader" part: batches built in the training loop against worker processes.

    Each setting trains ``resnet-lite`` in blocks of steps, the settings in alternation; a block
    starts a fresh loader and leaves out its first steps, which only drain the loader's prefetch.
    """
    data = benchmark_dataset(1 if args.quick else 2, 4 if args.quick else 8)
    torch.set_num_threads(1)  # as `don-gym train --threads 1` on a shared 2-core machine
    batch_size = 8
    frames = SupervisedFrames(str(data), variant="edge", crop_size=CROP_SIZE)
    batches = StepBatches(frames, 10**9, batch_size, seed=0, augment_config=AugmentConfig())
    torch.manual_seed(0)
    model = DenseObjectNet(DEFAULT_ARCH, 3).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-4)
    settings = [0, *args.loader_workers]
    seconds = dict.fromkeys(settings, 0.0)
    waiting = dict.fromkeys(settings, 0.0)
    step = 0
    wait_for_quiet_machine(args.wait_quiet)
    with OtherProcessLoad() as load:
        for _ in range(args.loader_blocks):
            for workers in settings:
                iterator = iter(step_loader(batches, step, workers))
                warm_up = 1 + 2 * workers
                for index in range(warm_up + args.loader_steps):
                    start = time.perf_counter()
                    batch = next(iterator)
                    arrived = time.perf_counter()
                    loss = supervised_l2_loss(model(batch["rgb"]), batch["target"], batch["object_mask"])
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    optimizer.step()
                    if index >= warm_up:
                        seconds[workers] += time.perf_counter() - start
                        waiting[workers] += arrived - start
                del iterator  # ends the block's worker processes
                step += warm_up + args.loader_steps
    timed = args.loader_steps * args.loader_blocks
    rate = {w: batch_size * timed / seconds[w] for w in settings}
    names = {w: f"{w} worker process{'es' if w > 1 else ''}" for w in settings}
    names[0] = "in the training loop (`--workers 0`, baseline)"
    rows = [
        f"| {names[w]} | {rate[w]:.1f} | {rate[w] / rate[0]:.2f}x | {100 * waiting[w] / seconds[w]:.0f}% |"
        for w in settings
    ]
    best = max(settings[1:], key=lambda w: rate[w])
    verdict = "met" if rate[best] / rate[0] >= LOADER_TARGET else "not met"
    width, height = FRAME_SIZE
    body = "\n".join(
        [
            f"`{DEFAULT_ARCH}`, supervised-edge targets, batch {batch_size} of {CROP_SIZE[0]}x{CROP_SIZE[1]} crops of "
            f"{width}x{height} frames (PNG decoding, edge-blended targets, crops and augmentation per image), "
            "forward + l2 loss + backward + Adam step, 1 torch thread in the training process. "
            f"{args.loader_blocks} blocks of {args.loader_steps} timed steps per setting, settings in alternation, "
            "each block after its loader's warm-up. Baseline: batches built in the training loop.",
            "",
            "| batches built | training images/s | vs baseline | share of step time waiting for data |",
            "|---|---|---|---|",
            *rows,
            "",
            f"Target: >= {LOADER_TARGET}x with worker processes ({best}: {rate[best] / rate[0]:.2f}x): {verdict}. "
            + _describe_load(load),
        ]
    )
    _record(args, "train-loader", "Training data loading: worker processes vs the training loop", body)


def _cli_rate(launcher: list[str], data: Path, out: Path, steps: int, threads: int, workers: int) -> float:
    """Training images/s of one `don-gym train` run, from the time and images its train_state.pt records."""
    command = [
        *launcher, "train", "--method", "supervised-edge", "--data", str(data), "--out", str(out),
        "--steps", str(steps), "--batch-size", "8", "--crop", f"{CROP_SIZE[0]}x{CROP_SIZE[1]}",
        "--threads", str(threads), "--workers", str(workers), "--checkpoint-every", str(steps),
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=3600)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")
    state = torch.load(out / TRAIN_STATE, weights_only=True)
    return float(state["images_seen"]) / float(state["seconds"])


def run_ddp(args: argparse.Namespace) -> None:
    """The "train-ddp" part: one process against torchrun with two gloo processes, same global batch."""
    data = benchmark_dataset(1 if args.quick else 2, 4 if args.quick else 8)
    single = [sys.executable, "-m", "don_gym.cli"]
    torchrun = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "don_gym.cli",
    ]
    settings = [
        ("1 process, 2 threads (baseline)", single, 2, 0),
        ("1 process, 1 thread, 1 data worker", single, 1, 1),
        ("torchrun, 2 gloo processes x 1 thread", torchrun, 1, 0),
    ]
    if args.quick:
        settings = [settings[0], settings[2]]
    rates = {}
    wait_for_quiet_machine(args.wait_quiet)
    with OtherProcessLoad() as load, tempfile.TemporaryDirectory() as tmp:
        for index, (name, launcher, threads, workers) in enumerate(settings):
            rates[name] = _cli_rate(launcher, data, Path(tmp) / f"run{index}", args.ddp_steps, threads, workers)
    baseline = rates[settings[0][0]]
    rows = [f"| {name} | {rate:.1f} | {rate / baseline:.2f}x |" for name, rate in rates.items()]
    body = "\n".join(
        [
            f"`don-gym train --method supervised-edge --batch-size 8 --crop {CROP_SIZE[0]}x{CROP_SIZE[1]}` "
            f"({DEFAULT_ARCH}) for {args.ddp_steps} steps on {FRAME_SIZE[0]}x{FRAME_SIZE[1]} frames; images/s from "
            "the time the run records (its whole loop, first step included). Under torchrun each process trains "
            "4 of the 8 images of a step, BatchNorm statistics synchronised over both. Baseline: one process "
            "using both cores.",
            "",
            "| launch | training images/s | vs baseline |",
            "|---|---|---|",
            *rows,
            "",
            "This machine has 2 cores, so two processes share the cores one process would use; the comparison "
            "shows the cost of the data-parallel machinery (gradient all-reduce, synchronised BatchNorm), not a "
            "multi-GPU speed-up. " + _describe_load(load),
        ]
    )
    _record(args, "train-ddp", "Data-parallel training on the CPU: torchrun with 2 gloo processes vs 1", body)


class BusyCores:
    """``count`` processes that each keep one core busy (a Python loop) while the block runs: another
    user's work on a shared machine, made reproducible."""

    def __init__(self, count: int) -> None:
        self.count = count
        self.processes: list[subprocess.Popen] = []

    def __enter__(self) -> BusyCores:
        # Each ends with this script, also when it is killed with kill -9: none spins on after it.
        loop = "import sys\nfrom don_gym.processes import end_with_parent\nend_with_parent(int(sys.argv[1]))\n"
        loop += "while True: pass"
        command = [sys.executable, "-c", loop, str(os.getpid())]
        self.processes = [subprocess.Popen(command) for _ in range(self.count)]
        time.sleep(0.5)  # running before the timing starts
        return self

    def __exit__(self, *exc: object) -> None:
        for process in self.processes:
            process.kill()
            process.wait()


def run_threads(args: argparse.Namespace) -> None:
    """The "train-threads" part: ``resnet-lite`` training steps and inference with 1 and 2 torch threads, on
    the machine as it is and with all cores but one kept busy by other processes, the four settings in
    alternating blocks (the speed part's synthetic steps and frames)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    conditions = {"as it is": 0, f"{max(cores - 1, 1)} of {cores} cores busy": max(cores - 1, 1)}
    thread_counts = (1, 2)
    settings = [(condition, threads) for condition in conditions for threads in thread_counts]
    one_arch = argparse.Namespace(**{**vars(args), "archs": [DEFAULT_ARCH]})
    step_seconds: dict[tuple[str, int], list[float]] = {setting: [] for setting in settings}
    frame_ms: dict[tuple[str, int], list[float]] = {setting: [] for setting in settings}
    loads: dict[str, list[float]] = {condition: [] for condition in conditions}
    default_threads = torch.get_num_threads()
    for _ in range(args.threads_blocks):
        for condition, spinners in conditions.items():
            with BusyCores(spinners), OtherProcessLoad() as load:
                for threads in thread_counts:
                    frame_ms[condition, threads] += time_inference(one_arch, threads)[DEFAULT_ARCH]
                    torch.set_num_threads(threads)
                    step_seconds[condition, threads] += time_training(one_arch)[DEFAULT_ARCH]
            if load.cores is not None:
                loads[condition].append(load.cores)
    torch.set_num_threads(default_threads)

    def images_per_s(setting: tuple[str, int]) -> float:
        return args.batch_size / float(np.median(step_seconds[setting]))

    rows = []
    for condition, threads in settings:
        ms = frame_ms[condition, threads]
        train_slowdown = images_per_s((condition, 1)) / images_per_s((condition, threads))
        infer_slowdown = float(np.median(ms)) / float(np.median(frame_ms[condition, 1]))
        rows.append(
            f"| {condition} | {threads} | {images_per_s((condition, threads)):.1f} | {train_slowdown:.2f}x "
            f"| {np.median(ms):.1f} ({np.percentile(ms, 90):.1f}) | {infer_slowdown:.2f}x |"
        )
    load_text = "; ".join(
        f"{name}: {np.mean(values):.2f}" if values else f"{name}: unknown" for name, values in loads.items()
    )
    body = "\n".join(
        [
            f"`{DEFAULT_ARCH}` on the CPU: training steps as in the speed part (forward + supervised l2 loss + "
            f"backward + Adam step, batch {args.batch_size}, {args.width}x{args.height}, median over "
            f"{args.train_steps} steps after {args.train_warmup} warm-up per block) and `descriptor_image` on "
            f"one {args.width}x{args.height} frame (median and 90th percentile over {args.repeats} frames after "
            f"{args.warmup} warm-up per block), with `torch.set_num_threads(1)` and `(2)`; on the machine as it "
            "is and while processes this run starts each keep a core busy (a Python loop), "
            f"{args.threads_blocks} alternating blocks of the four settings. Slowdown: time against 1 thread "
            "under the same condition.",
            "",
            "| machine | torch threads | train images/s | train slowdown vs 1 thread | inference ms, median (p90) "
            "| inference slowdown vs 1 thread |",
            "|---|---|---|---|---|---|",
            *rows,
            "",
            f"CPU cores kept busy by other processes while timing (the busy processes included): {load_text}.",
        ]
    )
    _record(args, "train-threads", "Torch threads on a busy machine: 1 vs 2", body)


def run_gpu(args: argparse.Namespace) -> None:
    """The "train-gpu" part: images/s on one GPU, fp32 against mixed precision, and the data-wait share."""
    if not torch.cuda.is_available():
        raise SystemExit("the gpu part needs a CUDA GPU; this machine has none")
    data = benchmark_dataset(2, 8, workers=min(8, os.cpu_count() or 1))
    archs = [DEFAULT_ARCH, BASELINE_ARCH]
    precisions = ["fp32", "auto"]
    warm_up = 5
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for arch in archs:
            for precision in precisions:
                config = TrainConfig(
                    method="supervised-edge", data=str(data), out=str(Path(tmp) / f"{arch}-{precision}"), arch=arch,
                    steps=warm_up, batch_size=args.gpu_batch_size, crop_size=None, device="cuda",
                    precision=precision, workers=args.gpu_workers, checkpoint_every=10**6,
                )  # fmt: skip
                # The first session warms up (cuDNN autotuning, allocator); the resumed one is timed.
                first = train(config, progress=False)
                second = train(replace(config, steps=warm_up + args.gpu_steps), resume=True, progress=False)
                assert first.seconds is not None and second.seconds is not None
                rate = args.gpu_batch_size * args.gpu_steps / (second.seconds - first.seconds)
                wait = second.data_wait_fraction or 0.0
                dtype = "fp32" if precision == "fp32" else ("bf16" if torch.cuda.is_bf16_supported() else "fp16")
                rows.append((arch, dtype, rate, wait))
    fp32 = {arch: rate for arch, dtype, rate, _ in rows if dtype == "fp32"}
    table = [
        f"| `{arch}` | {dtype} | {rate:.1f} | {rate / fp32[arch]:.2f}x | {100 * wait:.1f}% "
        f"| {'yes' if wait < GPU_WAIT_TARGET else 'NO'} |"
        for arch, dtype, rate, wait in rows
    ]
    body = "\n".join(
        [
            f"`train()` with supervised-edge targets on whole {FRAME_SIZE[0]}x{FRAME_SIZE[1]} frames, batch "
            f"{args.gpu_batch_size}, {args.gpu_workers} data workers, 1 process on {torch.cuda.get_device_name(0)}; "
            f"{args.gpu_steps} timed steps after {warm_up} warm-up steps. Baseline: fp32 on the same GPU.",
            "",
            f"| network | precision | training images/s | vs fp32 | step time waiting for data "
            f"| < {100 * GPU_WAIT_TARGET:.0f}% |",
            "|---|---|---|---|---|---|",
            *table,
        ]
    )
    _record(args, "train-gpu", "DON training on a GPU: fp32 vs mixed precision", body)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    runners = {"speed": run_speed, "loader": run_loader, "ddp": run_ddp, "threads": run_threads, "gpu": run_gpu}
    for part in args.parts:
        print(f"--- {part}", flush=True)
        runners[part](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
