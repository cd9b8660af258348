"""``don-gym evaluate``: the paper's tracking-error evaluation of DONs on a held-out dataset."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from don_gym.objects import ObjectModel

DESCRIPTION = """\
Tracking-error evaluation (Kupcsik et al., AAAI 2021, Sec. "Quantitative Evaluation of Prediction
Accuracy"), with the original DON metrics (Florence et al. 2018). Per scene: reference pixels on the
object in one frame, their descriptors and their true 3D points (ideal depth, true camera pose);
in every other frame where a point is visible, the best match (argmin L2 over the image; for a
network, but for its outer 16 pixels, where its output saw the convolutions' padding), and per match
the 3D error, the 3D error modulo the part's rotational symmetry, the pixel error to the true
projection and the fraction of pixels closer than the true match.

DATA must be scenes the networks were NOT trained on and no decision has used. Several datasets
(e.g. one per seed) are pooled: every percentile comes with a 95% interval from resampling their
scenes (the unit a long tail comes in), and per method the report gives the share of matches more
than 100 mm off, where those far matches land (part: wrong end or elsewhere, table, background,
robot/fixture) and each scene's share. Which seeds are for what (test, development, spent,
training) is set in don_gym.evaluation and listed in docs/reproduction.md; each dataset's is
printed. Predicted 3D points use the frame's true camera pose, so the errors measure the
descriptors (and, with --depth sensor, the sensor depth), not hand-eye calibration.
"""

EPILOG = """\
examples (3101 3102 3103: the development seeds):
  for seed in 3101 3102 3103; do
    don-gym build-dataset --object toolcap --scenes 8 --frames 12 --size 640x480 --seed $seed \\
        --no-fusion --out data/dev_toolcap_$seed
  done
  don-gym evaluate --data data/dev_toolcap_3101 data/dev_toolcap_3102 data/dev_toolcap_3103 --out eval/toolcap
  don-gym evaluate --data data/dev_toolcap_3101 --models oracle toolcap/supervised-edge run/model.safetensors \\
      --points 20 --depth sensor --out eval/toolcap_sensor

with --pose, 6D pose estimation from the descriptors as well, after tracking (docs: don_gym.perception.pose,
don_gym.evaluation.pose_evaluation):
  don-gym evaluate --data data/dev_toolcap_3101 --pose --pose-depth sensor --out eval/toolcap_pose
writes OUT/pose.json (per method BOP's MSSD and MSPD recalls over their thresholds, AR_MSSD, AR_MSPD, their
mean AR (no VSD), the share with ADD-S below 10% of the diameter, time per image), OUT/pose.md,
OUT/pose_<method>.csv (BOP results files, '/' in method names as '-') and OUT/pose_recall.png.

always writes OUT/tracking.json (percentiles 50/90/99 of each metric with their intervals, tails, far matches
by category and per scene, counts per method), OUT/tracking.md (the tables printed),
OUT/tracking_histogram.png (stacked, normalised, log-scale histogram of the 3D error, as in the
paper), OUT/tracking_cdf.png (CDFs of every metric, log x) and OUT/tracking_worst_matches.png (the
worst matches of every network: reference pixel beside the best match).
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate",
        help="tracking-error evaluation of DONs on a held-out dataset (paper's protocol)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--data",
        required=True,
        nargs="+",
        metavar="DIR",
        help="held-out dataset(s) of one part (don-gym build-dataset); the scenes of several are pooled",
    )
    parser.add_argument(
        "--models",
        nargs="+",
        default=None,
        metavar="MODEL",
        help="'oracle' (optimal descriptors rendered from the true poses), shipped network names "
        "(e.g. toolcap/supervised-edge) or checkpoint paths (default: oracle and every shipped network "
        "for the dataset's object)",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--points", type=int, default=16, help="reference pixels per scene (default: 16)")
    parser.add_argument(
        "--depth",
        choices=("ideal", "sensor"),
        default="ideal",
        help="depth for the predicted 3D points: simulator depth (default) or the dataset's sensor depth",
    )
    parser.add_argument(
        "--visibility-tolerance-mm",
        type=float,
        default=4.0,
        help="a point counts as occluded when the ideal depth at its projection differs by more (default: 4)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the reference-pixel draw (default: 0)")
    parser.add_argument(
        "--match-within",
        choices=("image", "instance"),
        default="image",
        help="search each best match in the image (default, the paper's; for a network but for --border-margin) or, "
        "as a diagnostic, only on the part's pixels in that frame (in a pile: the reference's own instance)",
    )
    parser.add_argument(
        "--border-margin",
        type=int,
        default=None,
        metavar="PX",
        help="pixels along each edge of the frame where best matches are not searched (default: each method's "
        "own, 16 for a network, whose output there saw the convolutions' zero padding, 0 for the oracle; "
        "0: the whole image, the paper's search)",
    )
    parser.add_argument("--max-scenes", type=int, default=None, help="evaluate only the first N scenes")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for the networks (default: 1)")
    parser.add_argument("--device", default="cpu", help="device of the networks: cpu (default), cuda, cuda:N or auto")
    parser.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="frames per network pass (default: 8 on a GPU, 1 on the CPU); results differ only by float rounding",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--pose",
        action="store_true",
        help="evaluate 6D pose estimation from the descriptors as well as tracking (BOP's MSSD/MSPD recalls, AR, "
        "ADD-S): writes OUT/pose.json, OUT/pose.md, OUT/pose_<method>.csv (BOP results files) and OUT/pose_recall.png",
    )
    parser.add_argument(
        "--pose-depth",
        choices=("sensor", "ideal", "none"),
        default=None,
        help="with --pose: depth for the estimate: the dataset's sensor depth (default; 3D-3D RANSAC and ICP), the "
        "simulator's ideal depth, or none (RGB-only PnP)",
    )
    parser.set_defaults(run=run)


def default_models(part: ObjectModel) -> list[str]:
    """``oracle`` and the shipped networks trained on ``part`` (matched by its geometry)."""
    from don_gym.zoo import shipped_names_for

    return ["oracle", *shipped_names_for(part)]


def run(args: argparse.Namespace) -> int:
    import torch

    from don_gym.data.dataset import DONDataset
    from don_gym.errors import DonGymError
    from don_gym.evaluation.frames import dataset_object
    from don_gym.evaluation.tracking import TrackingConfig
    from don_gym.io import check_output_dir
    from don_gym.learning.model import torch_device

    if args.threads < 1:
        raise DonGymError(f"--threads {args.threads}: expected at least 1")
    if args.pose_depth is not None and not args.pose:
        raise DonGymError(f"--pose-depth {args.pose_depth}: only with --pose (tracking takes --depth)")
    if args.batch_size is not None and args.batch_size < 1:
        raise DonGymError(f"--batch-size {args.batch_size}: expected at least 1")
    torch_device(args.device)  # a bad or absent device is refused before the work
    check_output_dir(args.out, "--out")
    torch.set_num_threads(args.threads)
    config = TrackingConfig(
        points_per_scene=args.points,
        depth=args.depth,
        visibility_tolerance_m=args.visibility_tolerance_mm / 1000.0,
        seed=args.seed,
        max_scenes=args.max_scenes,
        match_within=args.match_within,
        border_margin_px=args.border_margin,
    )
    config.validate()
    datasets = [DONDataset(path) for path in args.data]
    if datasets[0].scene_kind == "bin":
        run_bins(args, datasets, config)
    else:
        run_tracking(args, datasets, config)
    if args.pose:
        models = args.models if args.models is not None else default_models(dataset_object(datasets[0]))
        return run_pose(args, datasets, models)
    return 0


def run_tracking(args: argparse.Namespace, datasets: list, config) -> int:
    """Datasets of one part: the tracking protocol, printed and written to ``--out``."""
    from don_gym.evaluation.frames import dataset_object
    from don_gym.evaluation.report import tracking_report, write_tracking_outputs
    from don_gym.evaluation.splits import seed_split
    from don_gym.evaluation.tracking import evaluate_tracking

    models = args.models if args.models is not None else default_models(dataset_object(datasets[0]))
    result = evaluate_tracking(
        datasets, models, config, progress=not args.no_progress, device=args.device, batch_size=args.batch_size
    )
    for data in datasets:
        seed = data.info.get("seed")
        split = seed_split(seed) if isinstance(seed, int) else "unlisted"
        print(f"{data.root}: seed {seed} ({split})")
    print(tracking_report(result.summary()))  # before writing: a disk that fills up meanwhile loses no result
    paths = write_tracking_outputs(result, args.out)
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def run_bins(args: argparse.Namespace, datasets: list, config) -> int:
    """Datasets of bins: the tracking protocol per part
    (:func:`don_gym.evaluation.tracking.evaluate_tracking_per_part`),
    each part's report printed and written to ``--out/<part>/``."""
    from pathlib import Path

    from don_gym.data.bin_dataset import load_part_models
    from don_gym.evaluation.report import tracking_report, write_tracking_outputs
    from don_gym.evaluation.tracking import evaluate_tracking_per_part

    models = args.models
    if models is None:
        models = list(dict.fromkeys(m for part in load_part_models(datasets[0]).values() for m in default_models(part)))
    results = evaluate_tracking_per_part(
        datasets, models, config, progress=not args.no_progress, device=args.device, batch_size=args.batch_size
    )
    for part, result in results.items():
        print(f"## part {part}")
        print(tracking_report(result.summary()))
    for part, result in results.items():
        paths = write_tracking_outputs(result, Path(args.out) / part)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def run_pose(args: argparse.Namespace, datasets: list, models: list[str]) -> int:
    """``--pose``: the pose evaluation of :mod:`don_gym.evaluation.pose_evaluation`, printed and written to
    ``--out``."""
    from don_gym.evaluation.pose_evaluation import evaluate_pose, pose_table, write_pose_outputs

    depth = args.pose_depth or "sensor"
    result = evaluate_pose(
        datasets, models, depths=(depth,), max_scenes=args.max_scenes, progress=not args.no_progress, device=args.device
    )[depth]
    summary = result.summary()
    print(f"6D pose, {summary['object']}, depth: {summary['depth']} ({summary['note']})")
    print(pose_table(summary))  # before writing: a disk that fills up meanwhile loses no result
    paths = write_pose_outputs(result, args.out)
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
