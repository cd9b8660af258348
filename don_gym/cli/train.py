"""``don-gym train``: train a Dense Object Net with one of the four methods."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    from don_gym.cli import decay_rate
    from don_gym.descriptors.multi_part import TRAINING_LAYOUT_CHOICES
    from don_gym.learning.methods import METHOD_DESCRIPTIONS, METHODS

    methods = "; ".join(f"{m}: {METHOD_DESCRIPTIONS[m]}" for m in METHODS)
    parser = subparsers.add_parser(
        "train",
        help="train a DON (supervised on optimal targets, or self-supervised contrastive)",
        description=(
            f"Train a Dense Object Net on a dataset from 'don-gym build-dataset'. Methods: {methods}. "
            "Writes RUN/losses.csv, RUN/loss_curve.png, periodic checkpoints and RUN/model.safetensors. "
            "A fixed --seed gives the same loss curve; --resume continues an interrupted run exactly. "
            "For several processes (GPUs, or CPU cores), launch with "
            "'torchrun --standalone --nproc_per_node=N -m don_gym.cli train ...': --batch-size is then the "
            "batch of one step over all processes, and rank 0 writes the run directory."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--method", required=True, choices=METHODS, help="training method")
    parser.add_argument("--data", required=True, help="dataset directory")
    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument("--steps", type=int, default=2000, help="optimisation steps")
    parser.add_argument(
        "--arch",
        default="resnet-lite",
        help="network: resnet-lite (CPU default), resnet-lite-fine (decoder to stride 2: sharper silhouettes), "
        "resnet18, resnet34",
    )
    parser.add_argument(
        "--batch-size",
        type=int,
        default=4,
        help="images (supervised) or image pairs per step, over all processes under torchrun",
    )
    parser.add_argument(
        "--lr", type=float, default=None, help="Adam learning rate (default: 1e-3 resnet-lite*, 1e-4 else)"
    )
    parser.add_argument(
        "--lr-decay-every",
        type=int,
        default=250,
        help="steps between learning-rate decays by x0.9; scale it with --steps to keep the schedule's shape",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed for weights, data order and augmentation")
    parser.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    parser.add_argument("--pretrained", default=None, help="local ImageNet weights (torchvision ResNet layout)")
    parser.add_argument(
        "--init",
        default=None,
        metavar="CHECKPOINT",
        help="fine-tune: start from this don_gym checkpoint (same method, arch, part and descriptor space; a shipped "
        "network's path, e.g. from 'don-gym zoo') instead of random weights",
    )
    parser.add_argument(
        "--depth-source",
        default="fused",
        choices=["fused", "sensor", "ideal"],
        help="depth for self-supervised correspondences (fused = the original pipeline)",
    )
    parser.add_argument(
        "--crop",
        default="160x120",
        help="train on object-centred random crops WIDTHxHEIGHT ('none': whole frames); inference uses whole frames",
    )
    parser.add_argument(
        "--hard-object",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="supervised methods: also penalise each crop's worst FRACTION of part pixels (e.g. 0.1), those whose "
        "descriptors fall towards the background's where the part looks like its surroundings (0: the plain l2 loss)",
    )
    parser.add_argument(
        "--hard-background",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="supervised methods: also penalise each crop's worst FRACTION of background pixels (e.g. 0.01), "
        "those whose descriptors drift towards the part's and take matches off it (0: the plain l2 loss)",
    )
    parser.add_argument(
        "--ema-decay",
        type=decay_rate,
        default=0.0,
        metavar="DECAY",
        help="save an exponential moving average of the weights, updated every step with this decay (e.g. 0.999, "
        "an average over about the last 1000 steps), instead of the last step's weights (0: off)",
    )
    parser.add_argument(
        "--background-crops",
        type=float,
        default=0.1,
        help="share of training crops placed anywhere in the frame rather than on the part (backgrounds far from "
        "it and the frame's borders, which whole-frame inference sees)",
    )
    parser.add_argument(
        "--pattern-backgrounds",
        type=float,
        default=0.0,
        help="share of the augmentation's random backgrounds drawn as sharp two-colour stripes or checks "
        "(AugmentConfig.pattern_probability); 0 draws none",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads for torch (1 is fastest when other work shares the cores)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="processes that load and augment batches (0: the training process does); results do not depend on it",
    )
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    parser.add_argument(
        "--precision",
        default="auto",
        choices=["auto", "fp32", "bf16", "fp16"],
        help="GPU arithmetic: auto = bf16 autocast where supported, else fp16 with a gradient scaler; CPU: fp32",
    )
    parser.add_argument(
        "--backend",
        default="auto",
        help="torch.distributed backend under torchrun: auto (nccl on GPUs, gloo on CPUs), nccl or gloo",
    )
    parser.add_argument(
        "--part-layout",
        default="auto",
        choices=list(TRAINING_LAYOUT_CHOICES),
        help="bin datasets of several parts, supervised and supervised-edge only: the descriptor space the network "
        "learns. identity = every part's whole field plus one output channel for part identity (D + 1 channels), "
        "so a part's descriptors stay as far apart as in a single-part network; dataset = the dataset's own "
        "(every part's field shrunk into a region of its own, same D: about 0.43 of the distances for two parts); "
        "auto = identity wherever it applies (not supervised-mask, whose targets keep the dataset's layout) "
        "(docs/background.md, 'Several parts in one descriptor space')",
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")
    parser.set_defaults(run=run)


def _crop(text: str) -> tuple[int, int] | None:
    from don_gym.cli import parse_size

    return None if text.lower() == "none" else parse_size(text, "--crop")


def run(args: argparse.Namespace) -> int:
    from dataclasses import asdict

    from don_gym.errors import DonGymError
    from don_gym.io import check_output_dir
    from don_gym.learning.augment import AugmentConfig
    from don_gym.learning.distributed import launch_environment, reported_elsewhere, same_on_every_process
    from don_gym.learning.train import TrainConfig, train

    config = TrainConfig(
        method=args.method,
        data=args.data,
        out=args.out,
        steps=args.steps,
        arch=args.arch,
        batch_size=args.batch_size,
        lr=args.lr,
        lr_decay_every=args.lr_decay_every,
        seed=args.seed,
        checkpoint_every=args.checkpoint_every,
        pretrained_path=args.pretrained,
        init_path=args.init,
        depth_source=args.depth_source,
        device=args.device,
        crop_size=_crop(args.crop),
        background_crop_probability=args.background_crops,
        hard_object_fraction=args.hard_object,
        hard_background_fraction=args.hard_background,
        ema_decay=args.ema_decay,
        augment=asdict(AugmentConfig(pattern_probability=args.pattern_backgrounds)),
        threads=args.threads,
        workers=args.workers,
        precision=args.precision,
        backend=args.backend,
        part_layout=args.part_layout,
    )
    launch = launch_environment()
    try:
        try:
            check_output_dir(args.out, "--out")  # before the dataset and the network are loaded
        except DonGymError as exc:
            raise same_on_every_process(exc) from None  # the processes of a launch share --out
        result = train(config, resume=args.resume)
    except DonGymError as exc:
        if reported_elsewhere(exc, launch):  # under torchrun, rank 0 prints what every process found
            return 2
        raise
    if not launch.is_main:
        return 0
    timing = (
        "training time unknown (resumed from an older state)"
        if result.seconds is None or result.images_per_second is None
        else f"in {result.seconds:.0f} s ({result.images_per_second:.1f} images/s)"
    )
    waiting = "" if result.data_wait_fraction is None else f", {100 * result.data_wait_fraction:.0f}% waiting for data"
    print(f"{result.model_path}: {result.steps} steps {timing}{waiting}, final loss {result.final_loss:.4g}")
    return 0
