"""Candidate networks against the shipped ones on the development seeds, rendered both ways (issue 56, item 5).

A network meant to hold on steel that looks like steel must hold on both splits: the development scenes (the
development seeds of :data:`don_gym.evaluation.splits.SPLIT_SEEDS`, 8 scenes x 12 frames each, 640x480, D435) with
TinyRenderer's RGB and the same scenes path-traced. For each object this evaluates, by the tracking protocol with
predicted points from D435 depth (bench_grasp.py's), the oracle, the shipped networks and the candidates that
``benchmarks/train_shipped.py --renderer R --no-ship --work W`` left in ``W/run_<object>_<method>_<R>/``, and
gives per network and split the median 3D error modulo symmetry, the p99 of the 3D error and the share of matches
more than 100 mm off, each with its 95% interval over scenes, with the issue's targets for the supervised networks
(:data:`TRACKING_TARGETS_MM`, :data:`TARGET_FAR_PCT`: the same on both splits). Records RESULTS.md section
``fine-tune-dev`` (``--section``); the test split is not touched (the choices are made here).

    python benchmarks/bench_fine_tune.py --candidates runs/shipped_pbr --renderer mixed
    python benchmarks/bench_fine_tune.py --candidates runs/shipped_pbr --objects toolcap --methods supervised-edge
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import record_section  # noqa: E402
from bench_grasp import (  # noqa: E402
    FIGURE_DEPTH,
    SUPERVISED,
    TARGET_FAR_PCT,
    TRACKING_TARGETS_MM,
    object_networks,
    tracking_figures,
)
from train_shipped import METHODS, OBJECTS  # noqa: E402

from don_gym.data.build import DATASET_RENDERERS  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.splits import FRAMES_PER_SCENE, SCENES_PER_SEED, SPLIT_SEEDS  # noqa: E402
from don_gym.evaluation.tracking import (  # noqa: E402
    TrackingConfig,
    evaluate_tracking_depths,
    reference_edge_distances_px,
)
from don_gym.evaluation.tracking_metrics import tail_by_edge_distance  # noqa: E402
from don_gym.learning.checkpoints import read_checkpoint_metadata  # noqa: E402
from don_gym.sim.pbr import INSTALL_HINT, mitsuba_available  # noqa: E402
from don_gym.stats import format_estimate  # noqa: E402

SPLIT = "dev"
IMAGE_SIZE = (640, 480)
RENDERERS = ("tiny", "pbr")
COLUMNS = ("network", "3D error mod sym p50 (mm)", "3D error p99 (mm)", "matches > 100 mm (%)", "targets")


def candidate_paths(work: Path, object_name: str, methods: list[str], renderer: str) -> dict[str, Path]:
    """``{label: model path}`` of the finished candidates in ``work`` (a method without one is left out)."""
    found = {}
    for method in methods:
        path = work / f"run_{object_name}_{method}_{renderer}" / "model.safetensors"
        if path.is_file():
            found[f"{object_name}/{method} ({renderer} fine-tune)"] = path
    return found


def figure_row(label: str, method_summary: dict[str, Any], object_name: str) -> list[str]:
    """One table row: the figures of one network with their intervals, and for a supervised one the targets."""
    ((kind, f),) = tracking_figures({"methods": {label: method_summary}}).items()
    p50_target, p99_target = TRACKING_TARGETS_MM[object_name]
    if kind in SUPERVISED:
        met = f["p50_sym_mm"] <= p50_target and f["p99_mm"] <= p99_target and f["far_pct"] <= TARGET_FAR_PCT
        verdict = "met" if met else "missed"
    else:
        verdict = "-"
    return [
        label,
        format_estimate(f["p50_sym_mm"], f["p50_sym_ci"], 1),
        format_estimate(f["p99_mm"], f["p99_ci"], 1),
        format_estimate(f["far_pct"], f["far_pct_ci"], 2),
        verdict,
    ]


def evaluate_object(args: argparse.Namespace, object_name: str) -> str:
    """The section's part for one object: one table per renderer of the development split."""
    candidates = candidate_paths(Path(args.candidates), object_name, args.methods, args.renderer)
    if not candidates:
        raise DonGymError(
            f"{args.candidates}: no finished candidate of {object_name} ({args.methods}); run "
            f"benchmarks/train_shipped.py --renderer {args.renderer} --no-ship --work {args.candidates} first"
        )
    shipped = [n for n in object_networks(object_name) if n.rsplit("/", 1)[-1] in args.methods]
    also = [p for p in args.also if read_checkpoint_metadata(p).object_name == object_name]
    models = ["oracle", *shipped, *(str(p) for p in candidates.values()), *also]
    labels = {str(p): label for label, p in candidates.items()}
    p50_target, p99_target = TRACKING_TARGETS_MM[object_name]
    text = [
        f"### {object_name}\n\nTargets of a supervised network on both splits: median 3D error mod symmetry <= "
        f"{p50_target:g} mm, p99 of the 3D error <= {p99_target:g} mm, matches > 100 mm <= {TARGET_FAR_PCT:g}%."
    ]
    for renderer in RENDERERS:
        start = time.perf_counter()
        datasets = build_evaluation_datasets(
            object_name, SPLIT_SEEDS[SPLIT], Path(args.work), SPLIT, SCENES_PER_SEED, FRAMES_PER_SCENE, IMAGE_SIZE,
            args.workers, renderer=renderer,
        )  # fmt: skip
        result = evaluate_tracking_depths(
            datasets, models, TrackingConfig(points_per_scene=args.points), depths=(FIGURE_DEPTH,)
        )[FIGURE_DEPTH]
        summary = result.summary()
        rows = [figure_row(labels.get(name, name), m, object_name) for name, m in summary["methods"].items()]
        header = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        table = "\n".join(header + ["| " + " | ".join(row) + " |" for row in rows])
        look = "TinyRenderer" if renderer == "tiny" else "path-traced (pbr)"
        text.append(
            f"{object_name}, development split {look} ({', '.join(p.name for p in datasets)}), "
            f"{time.perf_counter() - start:.0f} s:\n\n{table}\n\n{edge_table(result, labels, p99_target)}"
        )
    return "\n\n".join(text)


def edge_table(result: Any, labels: dict[str, str], tail_mm: float) -> str:
    """Where each network's tail comes from: its matches by the reference pixel's distance inside the silhouette
    (:func:`~don_gym.evaluation.tracking_metrics.tail_by_edge_distance`), the oracle left out."""
    bands = None
    rows = []
    for name in result.matches:
        if name == "oracle":
            continue
        bands = tail_by_edge_distance(reference_edge_distances_px(result, name), result.matches[name].error_3d_m,
                                      tail_mm / 1000.0)  # fmt: skip
        cells = [
            "-" if b["tail_share"] is None else
            f"{100 * b['tail_share']:.1f}% / {100 * b['far_share']:.1f}% ({100 * b['share']:.0f}%)"
            for b in bands
        ]  # fmt: skip
        rows.append(f"| {labels.get(name, name)} | " + " | ".join(cells) + " |")
    if bands is None:
        return ""
    names = [
        f"{b['low_px']:g}-{b['high_px']:g} px" if np.isfinite(b["high_px"]) else f"> {b['low_px']:g} px" for b in bands
    ]
    return (
        f"Where the tail comes from: matches by their reference pixel's distance inside the part's silhouette; per "
        f"band, the share of its matches more than {tail_mm:g} mm (the p99 target) / more than 100 mm off, and (in "
        "brackets) the band's share of all matches. The supervised-edge targets blend the part's descriptors into "
        "the background's over the outermost 3 px.\n\n| network | "
        + " | ".join(names)
        + " |\n|"
        + "---|" * (len(names) + 1)
        + "\n"
        + "\n".join(rows)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--candidates", required=True, help="work directory of train_shipped.py --no-ship")
    parser.add_argument(
        "--renderer", choices=[r for r in DATASET_RENDERERS if r != "tiny"], default="mixed",
        help="the renderer the candidates were fine-tuned on (their run directories' suffix)",
    )  # fmt: skip
    parser.add_argument("--work", default="runs/bench_grasp", help="directory of the evaluation datasets")
    parser.add_argument("--objects", nargs="+", choices=OBJECTS, default=list(OBJECTS))
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    parser.add_argument("--points", type=int, default=16, help="reference pixels per scene")
    parser.add_argument("--workers", type=int, default=2, help="processes that build missing datasets")
    parser.add_argument(
        "--also", nargs="+", default=[], metavar="CHECKPOINT",
        help="further networks to evaluate beside them (e.g. a candidate's earlier checkpoint), each on its part",
    )  # fmt: skip
    parser.add_argument("--section", default="fine-tune-dev", help="RESULTS.md section to record")
    parser.add_argument("--no-record", action="store_true", help="print the section; record nothing")
    args = parser.parse_args()
    if not mitsuba_available():
        raise DonGymError(INSTALL_HINT)
    parts = [evaluate_object(args, name) for name in args.objects]
    body = (
        f"Candidates fine-tuned on `{args.renderer}` data (`{args.candidates}`) beside the shipped networks and the "
        f"oracle, on the development split (seeds {', '.join(map(str, SPLIT_SEEDS[SPLIT]))}, {SCENES_PER_SEED} "
        f"scenes x {FRAMES_PER_SCENE} frames each, {IMAGE_SIZE[0]}x{IMAGE_SIZE[1]}, D435) rendered both ways; "
        f"tracking protocol of bench_grasp.py, {args.points} reference pixels per scene, predicted points from "
        "D435 depth; 95% intervals over scenes.\n\n" + "\n\n".join(parts)
    )
    print(body)
    if not args.no_record:
        record_section(args.section, "Fine-tuned candidates on the development split, both renderers", body)


if __name__ == "__main__":
    try:
        main()
    except DonGymError as exc:
        sys.exit(f"bench_fine_tune.py: {exc}")
