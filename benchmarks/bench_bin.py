"""Piles of 3 toolcaps + 2 shafts in a bin, D435 wrist camera: clearing them, and tracking in them.

Clearing (``--only clearing``). Per method (the oracle with the true poses of the instances it sees, the descriptor
agent on the pile's optimal descriptors, the toolcap's shipped networks, and the networks of several parts:
``--multi-part``, by default the shipped ones), the same seeded piles are picked one instance per attempt, target
toolcap, a part lifted standing regrasped at the station (:func:`don_gym.evaluation.bin_benchmark.run_bin_benchmark`):
placed per target instance (the headline), picks and lift success per attempt, piles fully placed, give-ups,
wrong-part lifts, flips, regrasps and their success, each with its 95% Wilson interval, the pushes (parts rolled
away from a wall), and placements per hour of simulated time (motion and the method's measured perception
charged), with each method's ratios to the oracle on the
same piles (:mod:`don_gym.evaluation.bin_metrics`). The piles are the bin test piles (from
:data:`don_gym.evaluation.splits.BIN_TEST_SEED`, used for no decision); ``--split dev`` runs the development piles
(from :data:`~don_gym.evaluation.splits.BIN_DEVELOPMENT_SEED`) into section ``bin-dev``. Records RESULTS.md section
``bin`` with the targets checked (``TARGET_*`` of the benchmark module): the oracle places >= 95% of the target
instances and >= 80% per attempt at >= 300 placements per hour; a supervised network of several parts reaches >= 0.9x
the oracle's placed-per-target rate and pace on the same piles, wrong-part lifts <= 2% of lifts, gives up on <= 10% of
piles. The chart goes to ``benchmarks/figures/bin_rates.png``.

Tracking (``--only tracking``). Datasets of piles (:func:`don_gym.evaluation.datasets.build_evaluation_datasets`), one
per dataset seed of the split (:data:`don_gym.evaluation.splits.SPLIT_SEEDS`, as benchmarks/bench_grasp.py's
tracking: the
test seeds, or the development seeds with ``--split dev``), ``--scenes`` piles x ``--frames`` frames each, at the
networks' training size with the variety of the multi-part networks' training data (:data:`VARIETY`); per part the
tracking protocol with D435 depth (:func:`don_gym.evaluation.tracking.evaluate_tracking_per_part`) for the oracle,
the part's
shipped networks and the ``--multi-part`` networks. Records RESULTS.md section ``bin-tracking`` (``bin-tracking-dev``
for ``--split dev``) with the 3D error modulo symmetry to the nearest instance of the part (any instance: a part's
instances are alike), its far share, and the issue's target checked: a network of several parts' median within
1.5x the best single-part supervised network's of the same part.

Regrasp (``--only regrasp``, not run by default). The regrasp station on standing parts: the target part alone in the
bin, stood on each end in turn and turned about its axis by each of :data:`REGRASP_TURNS`, is grasped standing from
its true pose and set down at the station; per method (the oracle, the descriptor agent on optimal descriptors) the
agent then grasps it again from the station's observation and the env places it. Records section ``bin-regrasp``
(``bin-regrasp-dev``): parts lying at the station after the set-down, placed after the regrasp, placed reversed,
each with its Wilson interval.

Clearing and tracking run by default; datasets and raw outputs go to ``--work``.

    python benchmarks/bench_bin.py                  # test split, the shipped networks: "bin", "bin-tracking"
    python benchmarks/bench_bin.py --only tracking  # "bin-tracking" only
    python benchmarks/bench_bin.py --only clearing --multi-part runs/bin/model.safetensors   # "bin", another network
    python benchmarks/bench_bin.py --quick        # 2 development piles, the oracles, 160x120, temp dir, records nothing
    python benchmarks/bench_bin.py --split dev    # development piles and seeds: "bin-dev", "bin-tracking-dev"
    python benchmarks/bench_bin.py --only regrasp --split dev   # the regrasp station: "bin-regrasp-dev"
"""

from __future__ import annotations

import argparse
import itertools
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _results import FIGURES, freeze_commit_description, record_section, split_line  # noqa: E402

from don_gym.errors import DonGymError  # noqa: E402
from don_gym.evaluation.bin_benchmark import (
    ORACLE_DESCRIPTORS_METHOD,
    ORACLE_METHOD,
    BinBenchmarkConfig,
    bin_table,
    check_targets,
    run_bin_benchmark,
    write_bin_outputs,
)
from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.grasp_benchmark import default_methods, training_image_size  # noqa: E402
from don_gym.evaluation.report import tail_table, tracking_table, write_tracking_outputs
from don_gym.evaluation.splits import BIN_DEVELOPMENT_SEED, BIN_TEST_SEED, SPENT_SEEDS, SPLIT_SEEDS
from don_gym.evaluation.tracking import TrackingConfig, evaluate_tracking_per_part
from don_gym.objects import load_object  # noqa: E402
from don_gym.stats import BOOTSTRAP_RESAMPLES, format_estimate  # noqa: E402
from don_gym.zoo import read_don_metadata, shipped_multi_part_names, shipped_names_for  # noqa: E402

PARTS = (("toolcap", 3), ("shaft", 2))
TARGET = "toolcap"
SENSOR = "d435"
#: Piles per method of the full run (the issue's 100 test piles): about 300 target instances, so a placed-per-target
#: rate of 95% has a Wilson interval of about +-2.5 points.
PILES = 100
QUICK_PILES = 2
SPLIT_SEED = {"test": BIN_TEST_SEED, "dev": BIN_DEVELOPMENT_SEED}

#: Tracking piles per dataset seed and frames per pile: 24 piles of the test split (48 of the development split), so
#: >= 48 reference instances of the shaft (2 per pile) and 72 of the toolcap; 6 frames like the multi-part
#: training data.
TRACKING_SCENES = 8
TRACKING_FRAMES = 6
#: The variety of the multi-part networks' training data (runs/bin/data_bin/dataset.json: backgrounds, lighting).
VARIETY = {"backgrounds": "wide", "lighting": "random"}
#: The quick run's tracking: one pile of 3 frames (the split's first seed) at 64x48, the oracle only.
QUICK_TRACKING = {"scenes": 1, "frames": 3, "image_size": (64, 48), "points": 4}
#: The summary metric of the issue's tracking target: 3D error modulo symmetry to the nearest instance of the part.
TARGET_METRIC = "error_3d_symmetric_any_instance_mm"
#: The issue's target: a network of several parts' median at most this many times the best single-part
#: supervised network's median on the same part.
TARGET_RATIO = 1.5
SUPERVISED = ("supervised-edge", "supervised-mask")
#: The regrasp measurement: turns (rad) of the standing part about its axis, on each end; the quick run's first two.
REGRASP_TURNS = tuple(float(t) for t in np.linspace(0.0, 2 * np.pi, 8, endpoint=False))
REGRASP_METHODS = (ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD)
REGRASP_IMAGE_SIZE = (320, 240)


def methods(multi_part: list[str], quick: bool, only: list[str] | None = None) -> list[str]:
    """The oracle, the descriptor agent on optimal descriptors, the target's shipped networks, the multi-part ones
    (``only``: those of them named, in that order)."""
    if only:
        return list(only)
    if quick:
        return [ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD, *multi_part]
    shipped = set(shipped_names_for(load_object(TARGET)))
    own = [m for m in default_methods(TARGET) if m in shipped]
    return [ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD, *own, *multi_part]


def clearing(args: argparse.Namespace, split: str) -> None:
    """The clearing benchmark: section ``bin`` (``bin-dev``)."""
    piles = args.piles if args.piles is not None else (QUICK_PILES if args.quick else PILES)
    chosen = methods(list(args.multi_part), args.quick, args.methods)
    config = BinBenchmarkConfig(
        parts=PARTS,
        target=TARGET,
        methods=tuple(chosen),
        piles=piles,
        seed=SPLIT_SEED[split],
        sensor=SENSOR,
        # The oracles alone in a quick run: a small camera; otherwise the networks' training size.
        image_size=(160, 120) if args.quick and not args.multi_part and not args.methods else None,
    )
    work = Path(tempfile.mkdtemp(prefix="don_gym_bench_bin_")) if args.quick else Path(args.work) / split
    try:
        result = run_bin_benchmark(config, workers=args.workers, progress=not args.quick, device=args.device)
        paths = write_bin_outputs(result, work)
        table = bin_table(result)
        targets = check_targets(result)
        if not args.multi_part:
            targets.append("no network of several parts given (--multi-part): its targets are not checked")
        body = (
            f"Piles of 3 toolcaps + 2 shafts, target toolcap, sensor {SENSOR}, {split} piles "
            f"(seeds {config.seed}-{config.seed + piles - 1}); {len(result.episodes)} episodes in "
            + (f"{result.seconds:.0f} s" if result.seconds < 120 else f"{result.seconds / 60:.0f} min")
            + f" on {result.workers} worker(s).\n\n"
            + table
            + "\n\nThe issue's targets:\n\n"
            + "\n".join(f"- {line}" for line in targets)
            + "\n"
        )
        print(body)
        if args.quick:
            print("quick run: nothing recorded")
            return
        if split == "test":
            FIGURES.mkdir(parents=True, exist_ok=True)
            figure = FIGURES / "bin_rates.png"
            shutil.copyfile(paths["chart"], figure)
            body += f"\nFigure: `benchmarks/figures/{figure.name}` (each rate per method, with its interval).\n"
            record_section("bin", "Clearing piles from a bin (test piles)", body)
        else:
            record_section("bin-dev", "Clearing piles from a bin (development piles)", body, after="bin")
    finally:
        if args.quick:
            shutil.rmtree(work, ignore_errors=True)


# --- regrasp --------------------------------------------------------------------------------------


def regrasp_case(env, agent, seed: int, plus_up: bool, turn_rad: float) -> dict:
    """One standing part set down at the station and regrasped by ``agent``: ``lying`` (outcome ``set_down``),
    ``placed`` (the regrasp's outcome ``grasp_and_place``), ``reversed`` (the regrasp lifted it and it lies off
    the cradle's direction by more than 90 degrees), ``gave_up`` (the agent found no part at the station)."""
    from don_gym.sim.bin_task import BIN_CENTER_XY_M
    from don_gym.sim.script import GRASP_KINDS

    env.reset(seed=seed)
    agent.reset()
    instance = env.task.instances[0]
    env.task.stand(instance, BIN_CENTER_XY_M, plus_up=plus_up, turn_rad=turn_rad)
    grasp = env.task.grasp_point_world(instance)
    standing = np.array([*grasp, turn_rad, GRASP_KINDS.index("standing")], dtype=np.float32)
    obs, _, _, _, info = env.step(standing)
    out = {"lying": info["outcome"] == "set_down", "placed": False, "reversed": False, "gave_up": False}
    if info["phase"] != "regrasp":
        return out
    try:
        action = agent.act(obs, info)
    except DonGymError:
        return out | {"gave_up": True}
    _, _, _, _, info = env.step(action)
    out["placed"] = info["regrasp_outcome"] == "grasp_and_place"
    out["reversed"] = info["regrasp_outcome"] == "grasp_only" and info["placement_axis_error_rad"] > np.pi / 2
    return out


def regrasp(args: argparse.Namespace, split: str) -> None:
    """The regrasp station on standing parts: section ``bin-regrasp`` (``bin-regrasp-dev``)."""
    from don_gym.evaluation.bin_benchmark import make_agent
    from don_gym.sim.bin_env import BinPickEnv
    from don_gym.stats import format_rate

    turns = REGRASP_TURNS[:2] if args.quick else REGRASP_TURNS
    size = (160, 120) if args.quick else REGRASP_IMAGE_SIZE
    env = BinPickEnv(parts={TARGET: 1}, target=TARGET, image_size=size, sensor=SENSOR)
    cases = list(itertools.product((True, False), turns))
    start = time.perf_counter()
    rows = []
    try:
        for method in REGRASP_METHODS:
            agent = make_agent(env, method, args.device)
            results = [
                regrasp_case(env, agent, SPLIT_SEED[split] + k, plus_up, turn)
                for k, (plus_up, turn) in enumerate(cases)
            ]
            n = len(results)
            cells = [format_rate(sum(r[key] for r in results), n) for key in ("lying", "placed", "reversed", "gave_up")]
            rows.append(f"| {method} | " + " | ".join(cells) + " |")
    finally:
        env.close()
    body = (
        f"A {TARGET} alone in the bin, stood on each end in turn and turned about its axis by {len(turns)} angles "
        f"({len(cases)} cases, {split} pile seeds {SPLIT_SEED[split]}-{SPLIT_SEED[split] + len(cases) - 1} for the "
        f"rest of the scene), sensor `{SENSOR}`, {size[0]}x{size[1]} wrist camera: grasped standing from its true "
        "pose (kind `standing`), set down over the station's 25 mm ledge, observed from the station's pose, "
        "grasped again by the method and placed; "
        f"{time.perf_counter() - start:.0f} s. Rates with their 95% Wilson interval.\n\n"
        "| method | lying at the station after the set-down | placed after the regrasp | placed reversed | "
        "no part found at the station |\n|---|---|---|---|---|\n" + "\n".join(rows) + "\n"
    )
    print(body)
    if args.quick:
        print("quick run: nothing recorded")
    elif split == "test":
        record_section("bin-regrasp", "Regrasping standing parts at the station (test seeds)", body, after="bin")
    else:
        title = "Regrasping standing parts at the station (development seeds)"
        record_section("bin-regrasp-dev", title, body, after="bin-dev")


# --- tracking -------------------------------------------------------------------------------------


def part_networks(part: str) -> list[str]:
    """The part's shipped networks, in the paper's order (supervised-edge, supervised-mask, self-supervised)."""
    shipped = set(shipped_names_for(load_object(part)))
    return [m for m in default_methods(part) if m in shipped]


def tracking_target(summary: dict, singles: list[str], multi_part: list[str]) -> list[str]:
    """The issue's target on one part (``summary``: its :meth:`TrackingResult.summary`), one line per network of
    several parts: its median :data:`TARGET_METRIC` over the lowest one of the single-part supervised networks
    among ``singles``, and the verdict that ratio gives."""
    methods = summary["methods"]
    if not multi_part:
        return ["no network of several parts given (--multi-part): the target is not checked"]
    supervised = [n for n in singles if n in methods and methods[n]["source"].get("method") in SUPERVISED]
    with_median = [n for n in supervised if methods[n][TARGET_METRIC]["p50"]]
    if not with_median:
        return ["no single-part supervised network with a median to compare with: the target is not checked"]
    best = min(with_median, key=lambda n: methods[n][TARGET_METRIC]["p50"])

    def median(name: str) -> str:
        interval = methods[name].get("intervals", {}).get(TARGET_METRIC, {}).get("p50")
        return f"{format_estimate(methods[name][TARGET_METRIC]['p50'], interval)} mm"

    lines = []
    for name in multi_part:
        value = methods[name][TARGET_METRIC]["p50"]
        if value is None:
            lines.append(f"{name}: no match with depth, no median: the target is not checked")
            continue
        ratio = value / methods[best][TARGET_METRIC]["p50"]
        verdict = "met" if ratio <= TARGET_RATIO else "missed"
        lines.append(
            f"{name}: median {median(name)} / {best}'s {median(best)} (the better single-part supervised network "
            f"of the part) = {ratio:.2f}, target <= {TARGET_RATIO:g}: **{verdict}**"
        )
    return lines


def tracking(args: argparse.Namespace, split: str) -> None:
    """The tracking benchmark on piles: section ``bin-tracking`` (``bin-tracking-dev``)."""
    seeds = SPLIT_SEEDS[split]
    multi_part = [] if args.quick else list(args.multi_part)
    if args.quick:
        scenes, frames, points = QUICK_TRACKING["scenes"], QUICK_TRACKING["frames"], QUICK_TRACKING["points"]
        image_size = QUICK_TRACKING["image_size"]
        seeds = seeds[:1]
        singles: dict[str, list[str]] = {}
    else:
        scenes, frames, points = args.scenes, args.frames, args.points
        singles = {part: part_networks(part) for part, _ in PARTS}
        trained = {n: tuple(read_don_metadata(n).image_size) for n in [*sum(singles.values(), []), *multi_part]}
        image_size = training_image_size(trained)
    chosen = ["oracle", *sum(singles.values(), []), *multi_part]
    root = Path(tempfile.mkdtemp(prefix="don_gym_bench_bin_")) if args.quick else Path(args.work)
    work = root / f"tracking_{split}"
    try:
        start = time.perf_counter()
        datasets = build_evaluation_datasets(
            None,
            seeds,
            work,
            split,
            scenes,
            frames,
            image_size,
            args.workers,
            parts=dict(PARTS),
            progress=not args.quick,
            **VARIETY,
        )
        build_s = time.perf_counter() - start
        start = time.perf_counter()
        config = TrackingConfig(points_per_scene=points, depth="sensor")
        results = evaluate_tracking_per_part(datasets, chosen, config, progress=not args.quick, device=args.device)
        parts = []
        for part, result in results.items():
            summary = result.summary()
            write_tracking_outputs(result, work / part)
            far_mm = summary["far_match_mm"]
            parts.append(
                f"### {part}\n\n{summary['scenes']} reference instances of the {part}.\n\n"
                + tracking_table(summary)
                + f"\n\nTails (a match more than {far_mm:.0f} mm off is far; *any instance*: by the 3D error to the "
                "nearest instance of the part):\n\n"
                + tail_table(summary)
                + "\n\nThe issue's target (median 3D error mod symmetry, any instance, D435 depth):\n\n"
                + "\n".join(f"- {line}" for line in tracking_target(summary, singles.get(part, []), multi_part))
            )
        evaluation_s = time.perf_counter() - start
        width, height = image_size
        size_note = "the quick run's tiny size" if args.quick else "the networks' training size"
        body = (
            split_line(split, seeds, SPENT_SEEDS, trained_on_seed_0=False)
            + f", {scenes} piles x {frames} frames each, "
            f"{len(seeds) * scenes} piles of {' + '.join(f'{n} {p}s' for p, n in PARTS)}, pooled, {width}x{height} "
            f"({size_note}), sensor `{SENSOR}`, backgrounds `{VARIETY['backgrounds']}` and lighting "
            f"`{VARIETY['lighting']}` (those of the multi-part networks' training data). Protocol "
            "(`don_gym.evaluation.tracking.evaluate_tracking_per_part`): per part, every instance of it in a pile gets "
            f"{points} reference pixels in the frame showing most of it, followed through the frames where the ideal "
            "depth shows them (occlusion by other instances counts); the best match is the argmin L2 over the image "
            "(for a network, but for its outer 16 pixels, where its output saw zero padding) and the predicted point "
            f"back-projects the frame's {SENSOR} depth with the true camera pose. "
            "Methods: the oracle (optimal descriptors rendered for every instance of the part), the part's shipped "
            "single-part networks, and the networks of several parts (`--multi-part`, by default the shipped ones). "
            "*Any instance*: "
            "the error to the same point on the nearest instance of the part, since a part's descriptors are alike "
            "on its identical instances; *mod symmetry*: the distance between the rings the predicted and true "
            "points sweep about the part's axis. Intervals: 95%, bootstrap over reference instances (the scenes "
            f"of the tables; {BOOTSTRAP_RESAMPLES} resamples).\n\n"
            + "\n\n".join(parts)
            + f"\n\nDatasets built in {build_s:.0f} s, both parts evaluated in {evaluation_s:.0f} s"
            + ("." if args.quick else f"; raw outputs in `{work}`.")
        )
    finally:
        if args.quick:
            shutil.rmtree(root, ignore_errors=True)
    print(body)
    if args.quick:
        print("quick run: nothing recorded")
    elif split == "test":
        record_section("bin-tracking", "Tracking in piles of a bin (test split)", body, after="bin")
    else:
        title = "Tracking in piles of a bin (development split)"
        record_section("bin-tracking-dev", title, body, after="bin-tracking")


def multi_part_networks(given: list[str] | None, quick: bool) -> list[str]:
    """The networks of several parts to benchmark: those ``given`` (``--multi-part``, none: an empty list), else the
    shipped ones (:func:`~don_gym.zoo.shipped_multi_part_names`), except in a ``quick`` run."""
    if given is not None:
        return list(given)
    return [] if quick else shipped_multi_part_names()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--multi-part",
        nargs="*",
        default=None,
        metavar="CHECKPOINT",
        help="networks of several parts (trained on bin datasets) benchmarked beside the single-part ones (default: "
        "the shipped ones, don_gym.zoo.shipped_multi_part_names(), except with --quick; give none to leave them out)",
    )
    parser.add_argument(
        "--split",
        choices=("test", "dev"),
        default=None,
        help="the test piles and seeds (default) or the development ones (sections bin-dev, bin-tracking-dev; the "
        "default of --quick)",
    )
    parser.add_argument(
        "--only",
        choices=("clearing", "tracking", "regrasp"),
        default=None,
        help="run one benchmark (default: clearing and tracking)",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        metavar="METHOD",
        help="clearing: only these methods (oracle, oracle-descriptors, shipped names, checkpoints; default: the "
        "oracles, the toolcap's shipped networks and --multi-part)",
    )
    parser.add_argument("--piles", type=int, default=None, help=f"clearing: piles per method (default: {PILES})")
    parser.add_argument(
        "--scenes",
        type=int,
        default=TRACKING_SCENES,
        help=f"tracking: piles per dataset seed (default: {TRACKING_SCENES})",
    )
    parser.add_argument(
        "--frames", type=int, default=TRACKING_FRAMES, help=f"tracking: frames per pile (default: {TRACKING_FRAMES})"
    )
    parser.add_argument("--points", type=int, default=16, help="tracking: reference pixels per instance (default: 16)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="clearing: 2 development piles, the two oracles; tracking: one tiny development pile, the oracle; "
        "records nothing",
    )
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    parser.add_argument("--device", default="cpu", help="device of the networks (default: cpu)")
    parser.add_argument(
        "--work", default="bench_work/bin", help="folder for datasets and raw outputs (default: bench_work/bin)"
    )
    args = parser.parse_args()
    args.multi_part = multi_part_networks(args.multi_part, args.quick)
    split = args.split or ("dev" if args.quick else "test")
    freeze_commit_description()
    if args.only in (None, "clearing"):
        clearing(args, split)
    if args.only in (None, "tracking"):
        tracking(args, split)
    if args.only == "regrasp":
        regrasp(args, split)


if __name__ == "__main__":
    main()
