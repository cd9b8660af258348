"""6D pose from descriptors, scored as the BOP Challenge scores it, for the toolcap and the shaft (issue #34).

On the held-out test split of each object (the scenes of :data:`don_gym.evaluation.splits.TEST_SEEDS`, built as the
tracking benchmark builds them: :data:`~don_gym.evaluation.splits.SCENES_PER_SEED` scenes x
:data:`~don_gym.evaluation.splits.FRAMES_PER_SCENE` frames per seed at the shipped networks' training size, D435
sensor), :func:`don_gym.evaluation.pose_evaluation.evaluate_pose` for the oracle and every shipped network of the
object,
with the recorded D435 depth (3D-3D RANSAC and ICP) and without depth (RGB-only PnP). Records RESULTS.md section
``pose`` (``pose-dev`` for ``--split dev``) with the issue's targets checked: oracle AR >= 0.95 and both
supervised networks AR >= 0.7 with depth; RGB-only PnP and the self-supervised network as measured. Figures
(recall against threshold per method) go to ``benchmarks/figures/`` for the test split; datasets, pose.json
and the BOP results files of every method to ``--work``.

    python benchmarks/bench_pose.py            # test split, records RESULTS.md section "pose"
    python benchmarks/bench_pose.py --quick    # 1 development scene x 6 frames per object, temp dir, records nothing
    python benchmarks/bench_pose.py --split dev   # development seeds, section "pose-dev"
    python benchmarks/bench_pose.py --only grasp  # only the grasp comparison, section "pose-grasp"
    python benchmarks/bench_pose.py --renderer pbr --only pose   # the physically rendered test split, "pose-pbr"

``--renderer pbr`` (issue 56): the same scenes with path-traced RGB (datasets ``<split>_pbr_<object>_<seed>``, the
ones ``bench_grasp.py --renderer pbr`` builds when both get the same ``--work``), into sections of their own right
after TinyRenderer's (``pose-pbr``, ``pose-dev-pbr``, ``pose-grasp-pbr``), figures and outputs with ``_pbr``.

The grasp comparison (section ``pose-grasp``, :func:`don_gym.evaluation.grasp_benchmark.run_grasp_benchmark`, as
``don-gym benchmark grasp --methods M pose:M ...``): every method's descriptors used twice on the 8 fixed poses,
by the two-descriptor ``AxisGraspAgent`` and by ``PoseGraspAgent`` (grasp from the estimated 6D pose), D435.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import (  # noqa: E402
    FIGURES,
    MEASURED_RENDERERS,
    OtherProcessLoad,
    freeze_commit_description,
    kept_object_subsections,
    record_section,
    renderer_section,
    renderer_suffix,
    rendering_text,
    split_line,
)

from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.grasp_benchmark import (
    POSE_AGENT_PREFIX,
    GraspBenchmarkConfig,
    default_methods,
    run_grasp_benchmark,
    training_image_size,
)
from don_gym.evaluation.grasp_report import outcome_table, write_grasp_outputs
from don_gym.evaluation.pose_evaluation import evaluate_pose, pose_table, write_pose_outputs  # noqa: E402
from don_gym.evaluation.splits import FRAMES_PER_SCENE, SCENES_PER_SEED, SPENT_SEEDS, SPLIT_SEEDS  # noqa: E402
from don_gym.objects import load_object  # noqa: E402
from don_gym.sim.pbr import INSTALL_HINT, mitsuba_available  # noqa: E402
from don_gym.zoo import read_don_metadata, shipped_names_for  # noqa: E402

OBJECTS = ("toolcap", "shaft")
#: Depths of the estimate: the D435's recorded depth, and none (RGB-only PnP).
DEPTHS = ("sensor", "none")
DEPTH_TEXT = {"sensor": "D435 depth (3D-3D RANSAC + ICP)", "none": "no depth (RGB-only PnP)"}
#: The issue's targets, with depth: the oracle's AR, and each supervised network's.
TARGET_ORACLE_AR, TARGET_SUPERVISED_AR = 0.95, 0.7
SUPERVISED = ("supervised-edge", "supervised-mask")


def object_networks(object_name: str) -> list[str]:
    """The shipped networks of the object, in the paper's order."""
    shipped = set(shipped_names_for(load_object(object_name)))
    return [m for m in default_methods(object_name) if m in shipped]


def check_targets(summary: dict[str, Any]) -> list[str]:
    """The issue's targets missed by a summary with depth (empty: all met)."""
    missed = []
    for name, m in summary["methods"].items():
        kind = m["source"].get("method", name)
        if kind == "oracle" and not m["ar"] >= TARGET_ORACLE_AR:
            missed.append(f"{name} AR {m['ar']:.3f} < {TARGET_ORACLE_AR}")
        if kind in SUPERVISED and not m["ar"] >= TARGET_SUPERVISED_AR:
            missed.append(f"{name} AR {m['ar']:.3f} < {TARGET_SUPERVISED_AR}")
    return missed


def run_object(args: argparse.Namespace, work: Path, object_name: str, publish: bool) -> str:
    """Build the split's datasets of one object, evaluate every method at both depths, write the outputs;
    the object's markdown."""
    networks = object_networks(object_name)
    image_size = training_image_size({n: read_don_metadata(n).image_size for n in networks})
    start = time.perf_counter()
    datasets = build_evaluation_datasets(
        object_name,
        args.seeds,
        work,
        args.split,
        args.scenes,
        args.frames,
        image_size,
        args.workers,
        renderer=args.renderer,
    )
    build_s = time.perf_counter() - start
    start = time.perf_counter()
    # The times per image are wall-clock: a reader needs to know whether other work shared the cores.
    with OtherProcessLoad() as load:
        results = evaluate_pose(datasets, ["oracle", *networks], depths=DEPTHS, progress=not args.quick)
    evaluation_s = time.perf_counter() - start
    parts = []
    tag = renderer_suffix(args.renderer, "_")  # in the names of files, so that no renderer overwrites another's
    for depth, result in results.items():
        summary = result.summary()
        paths = write_pose_outputs(result, work / f"pose_{object_name}{tag}_{depth}")
        lines = [f"### {object_name}, {DEPTH_TEXT[depth]}", "", pose_table(summary)]
        if depth == "sensor":
            missed = check_targets(summary)
            lines += [
                "",
                f"Targets (oracle AR >= {TARGET_ORACLE_AR}, supervised networks AR >= {TARGET_SUPERVISED_AR}): "
                + ("all met." if not missed else "missed: " + "; ".join(missed) + "."),
            ]
        if publish:
            FIGURES.mkdir(exist_ok=True)
            target = FIGURES / f"pose_{object_name}{tag}_{depth}_recall.png"
            shutil.copyfile(paths["recall"], target)
            lines += ["", f"Figure: `benchmarks/figures/{target.name}`."]
        else:
            lines += ["", f"Figure: `{paths['recall']}`."]
        parts.append("\n".join(lines))
    parts[-1] += (
        f"\n\n{object_name}: {sum(len(r.estimates) for r in results.values())} method x depth runs; datasets built "
        f"in {build_s:.0f} s, both depths evaluated in one pass in {evaluation_s:.0f} s (times per image are "
        f"wall-clock; CPU cores kept busy by other processes meanwhile: {load.describe()}, 0 = the machine was "
        f"ours); BOP results files and pose.json in `{work}`."
    )
    return "\n\n".join(parts)


def grasp_comparison(args: argparse.Namespace, work: Path, object_name: str) -> str:
    """The object's part of section ``pose-grasp``: the oracle and every shipped network, each by the axis agent
    and by the pose agent, on the fixed poses (2 with ``--quick``), ``--grasp-repeats`` seeds each, D435."""
    methods = ["oracle", *object_networks(object_name)]
    config = GraspBenchmarkConfig(
        object=object_name,
        methods=tuple(m for method in methods for m in (method, f"{POSE_AGENT_PREFIX}{method}")),
        repeats=args.grasp_repeats,
        sensors=("d435",),
        poses=(0, 1) if args.quick else tuple(range(8)),
        renderer=args.renderer,
    )
    result = run_grasp_benchmark(config, workers=args.workers, progress=not args.quick)
    paths = write_grasp_outputs(result, work / f"pose_grasp_{object_name}{renderer_suffix(args.renderer, '_')}")
    return (
        f"### {object_name}\n\n{outcome_table(result)}\n\n"
        f"{len(result.episodes)} episodes in {result.seconds:.0f} s on {result.workers} workers; "
        f"episodes in `{paths['json']}`."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="runs/bench_pose", help="directory for datasets and raw outputs")
    parser.add_argument(
        "--split",
        choices=tuple(SPLIT_SEEDS),
        default=None,
        help="the test seeds (default) or the development seeds (section pose-dev; the default of --quick)",
    )
    parser.add_argument("--scenes", type=int, default=SCENES_PER_SEED, help="scenes per seed of the split")
    parser.add_argument("--frames", type=int, default=FRAMES_PER_SCENE, help="frames per scene")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--objects",
        nargs="+",
        default=list(OBJECTS),
        choices=OBJECTS,
        help="objects to measure; the sections keep the other objects' figures, marked with the run that made them",
    )
    parser.add_argument(
        "--only",
        choices=("pose", "grasp"),
        default=None,
        help="only the pose evaluation (section pose) or only the grasp comparison (section pose-grasp)",
    )
    parser.add_argument(
        "--grasp-repeats", type=int, default=1, help="seeds per fixed pose and method in the grasp comparison"
    )
    parser.add_argument(
        "--renderer",
        choices=MEASURED_RENDERERS,
        default="tiny",
        help="RGB of every scene and episode: tiny (TinyRenderer, default) or pbr (path-traced, the pbr extra: "
        "datasets <split>_pbr_<object>_<seed>, sections pose-pbr, pose-dev-pbr and pose-grasp-pbr)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny smoke run in a temp dir; records nothing")
    args = parser.parse_args()
    freeze_commit_description()
    torch.set_num_threads(1)
    args.objects = [o for o in OBJECTS if o in args.objects]
    if args.renderer == "pbr" and not mitsuba_available():
        sys.exit(f"bench_pose.py: {INSTALL_HINT}")
    missing = [m for o in args.objects for m in default_methods(o)[1:] if m not in object_networks(o)]
    if missing and not args.quick:
        sys.exit(f"bench_pose.py: shipped networks missing: {missing}; run benchmarks/train_shipped.py first")
    if args.quick:
        args.scenes, args.frames = 1, 6
    if args.split is None:
        args.split = "dev" if args.quick else "test"
    seeds = SPLIT_SEEDS[args.split][:1] if args.quick else SPLIT_SEEDS[args.split]
    args.seeds = seeds
    work = Path(tempfile.mkdtemp(prefix="don_gym_bench_pose_")) if args.quick else Path(args.work)
    publish = not args.quick and args.split == "test"
    header = (
        split_line(args.split, seeds, SPENT_SEEDS) + ", "
        f"{args.scenes} scenes x {args.frames} frames each, pooled, at the networks' training size, sensor `d435`"
        f"{rendering_text(args.renderer)}. "
        "Protocol (`don_gym.evaluation.pose_evaluation`): one pose estimate of the part per frame and method "
        "(`don_gym.perception.pose`: part pixels matched to the part's surface rings in descriptor space, ratio "
        "test; with depth, RANSAC fit of the axis to the matched depth points and point-to-point ICP; without depth, "
        "OpenCV's RANSAC PnP), scored against the frame's true pose by BOP's MSSD (thresholds 0.05-0.5 of the "
        "diameter) and MSPD (5-50 px at 640 px width) with the part's continuous symmetry discretised as BOP "
        "does; AR = mean of AR_MSSD and AR_MSPD (BOP's VSD is not computed); ADD-S share below 10% of the "
        "diameter; a frame without an estimate is wrong at every threshold. The two frames of the first scene "
        "that show most of the part are the reference views (the networks' targets and every method's "
        "calibration) and are not scored. Time per image: descriptor image (one CPU thread) plus estimate."
    )
    if args.only != "grasp":
        run_pose(args, work, header, publish)
    if args.only != "pose":
        publish_grasp = not args.quick and args.split == "test"
        section, title, after = renderer_section(
            "pose-grasp", "Grasping from a 6D pose beside the two-descriptor agent", args.renderer, after="pose"
        )
        measured = {o: grasp_comparison(args, work, o) for o in args.objects}
        grasp_body = (
            "Each method's descriptors used twice: by the two-descriptor `AxisGraspAgent` (the paper's agent) and "
            "by `PoseGraspAgent` (`pose:` methods: a grasp along the axis of the 6D pose estimated with "
            "`don_gym.perception.pose` from the same descriptor image and the D435 depth).\n\n"
            + "\n\n".join(with_kept_objects(section, measured, keep=publish_grasp))
        )
        print(grasp_body)
        if publish_grasp:
            record_section(section, title, grasp_body, after=after)


def with_kept_objects(section: str, measured: dict[str, str], keep: bool) -> list[str]:
    """Each object's markdown in OBJECTS order: this run's where it measured the object, else (with ``keep``)
    the one RESULTS.md's ``section`` holds, marked with the run that measured it; so ``--objects toolcap``
    after retraining the toolcap's networks leaves the shaft's figures in the section."""
    kept = kept_object_subsections(section, OBJECTS, list(measured)) if keep else {}
    return [measured.get(o) or kept[o] for o in OBJECTS if o in measured or o in kept]


def pose_section(split: str, renderer: str = "tiny") -> tuple[str, str, str | None]:
    """The pose section of a run: its name (``pose``, ``pose-dev``, ``pose-pbr``, ``pose-dev-pbr``), its title
    and the section it goes right after (None: where it is, or at the end)."""
    if split == "test":
        return renderer_section("pose", "6D pose from descriptors (BOP metrics), test split", renderer)
    title = "6D pose from descriptors (BOP metrics), development split"
    return renderer_section("pose-dev", title, renderer, after="pose")


def run_pose(args: argparse.Namespace, work: Path, header: str, publish: bool) -> None:
    """Section ``pose`` (``pose-dev``, ``pose-pbr``, ...): every object's pose evaluation, printed and recorded."""
    section, title, after = pose_section(args.split, args.renderer)
    measured = {o: run_object(args, work, o, publish) for o in args.objects}
    body = header + "\n\n" + "\n\n".join(with_kept_objects(section, measured, keep=not args.quick))
    print(body)
    if not args.quick:
        record_section(section, title, body, after=after)


if __name__ == "__main__":
    main()
