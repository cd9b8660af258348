"""Tracking accuracy and grasp-and-place outcomes of the shipped DONs against the oracle, for the toolcap and the shaft.

Tracking (RESULTS.md section "tracking") on the test split of each object (the scenes of three seeds no
decision has used, :data:`don_gym.evaluation.splits.TEST_SEEDS`; ``--split dev`` runs the development seeds into
section "tracking-dev", with each method's border margin beside the paper's whole-image search, and writes no
README or docs block), every percentile with its 95% interval over
scenes, the supervised networks checked against their targets (:data:`TRACKING_TARGETS_MM`), with the paper's
tracking figure for all objects in one picture; grasp-and-place (sections "grasp",
the toolcap, the headline, and "grasp-shaft") on each object's 8 fixed poses over a depth-sensor sweep, with
the issue's targets checked, and on seeded random poses. From the same results it writes the generated
blocks of README.md (sections "Tracking error" and "Grasp benchmark") and docs/reproduction.md (the paper's
claims, each with a computed verdict). Figures go to ``benchmarks/figures/``; datasets and raw outputs to
``--work``.

    python benchmarks/bench_grasp.py            # full run, records RESULTS.md, README.md, docs/reproduction.md
    python benchmarks/bench_grasp.py --quick    # smoke run into a temp dir, prints the blocks, records nothing
    python benchmarks/bench_grasp.py --only tracking --split dev   # tracking on the development seeds
    python benchmarks/bench_grasp.py --renderer pbr   # the same, on the physically rendered test split

``--renderer pbr`` (issue 56) measures the same methods on the same scenes with path-traced RGB (depth, masks and
targets unchanged): datasets ``test_pbr_<object>_<seed>`` in ``--work``, RESULTS.md sections of their own right
after TinyRenderer's (``tracking-pbr``, ``grasp-pbr``, ``grasp-shaft-pbr``), figures and raw outputs with ``_pbr``
in their names, and the PBR verdict blocks of docs/reproduction.md (``bench_grasp:claim-a-pbr`` ...); it writes
no README block. Its grasp part runs the 8 fixed poses x ``--repeats`` with the D435 only: the depth-sensor
sweep, the random poses and the varied backgrounds stay TinyRenderer's (see :func:`grasp`).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import (  # noqa: E402
    FIGURES,
    MEASURED_RENDERERS,
    REPO_ROOT,
    command_line,
    commit_description,
    freeze_commit_description,
    machine_description,
    record_section,
    renderer_section,
    renderer_suffix,
    renderer_title,
    rendering_text,
    replace_block,
    require_blocks,
    split_line,
    utc_now,
)

from don_gym import plotting  # noqa: E402
from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.grasp_benchmark import (
    GraspBenchmarkConfig,
    GraspBenchmarkResult,
    default_methods,
    run_grasp_benchmark,
    training_image_size,
)
from don_gym.evaluation.grasp_report import check_targets, miss_table, outcome_table, sweep_table, write_grasp_outputs
from don_gym.evaluation.report import (
    far_match_table,
    per_scene_table,
    tail_table,
    tracking_table,
    write_tracking_outputs,
)
from don_gym.evaluation.splits import FRAMES_PER_SCENE, SCENES_PER_SEED, SPENT_SEEDS, SPLIT_SEEDS
from don_gym.evaluation.tracking import TRACKING_DEPTHS, TrackingConfig, evaluate_tracking_depths
from don_gym.evaluation.tracking_metrics import LONG_TAIL_RATIO
from don_gym.objects import load_object  # noqa: E402
from don_gym.sim.pbr import INSTALL_HINT, mitsuba_available  # noqa: E402
from don_gym.stats import format_estimate, format_rate  # noqa: E402
from don_gym.zoo import read_don_metadata, shipped_names_for  # noqa: E402

README_PATH = REPO_ROOT / "README.md"
REPRODUCTION_PATH = REPO_ROOT / "docs" / "reproduction.md"
OBJECTS = ("toolcap", "shaft")
#: The object of the paper's robot experiment: its grasp section and README table come first.
HEADLINE_OBJECT = "toolcap"
#: Depth of the predicted points in the combined tracking figure, the README tables and the claims: the
#: paper's camera is a D435.
FIGURE_DEPTH = "sensor"
GRASP_SENSORS = ("ideal", "d435@0.5", "d435")
#: The env background of the second grasp run, the fixed poses over varied backgrounds: the backdrops and
#: cradle colours of the datasets the networks are tested on (the recorder's classic families).
GRASP_BACKGROUNDS = "random"
SUPERVISED = ("supervised-edge", "supervised-mask")
SELF_SUPERVISED = "self-supervised"
#: "Slightly less accurate": a supervised network's median error at most this many times the self-supervised one's.
SLIGHTLY_LESS_ACCURATE = 2.0
#: The paper's robot result for the supervised networks, per 8 poses: all grasped, at least 7 grasped and placed.
TARGET_GRASPED_PER_8, TARGET_PLACED_PER_8 = 8, 7
#: What a supervised network that generalises reaches on the test scenes with D435 depth, per object: the median
#: 3D error modulo symmetry and the p99 of the 3D error (mm); and for every object the share of matches more
#: than 100 mm off (%). Checked on the estimates; their intervals are shown beside them.
TRACKING_TARGETS_MM = {"toolcap": (3.0, 45.0), "shaft": (5.0, 60.0)}
TARGET_FAR_PCT = 0.5


def block(name: str, renderer: str = "tiny") -> str:
    """Name of a generated block owned by this script (``<!-- begin bench_grasp:NAME -->``; ``NAME-pbr`` for the
    physically rendered runs' blocks)."""
    return f"bench_grasp:{name}{renderer_suffix(renderer)}"


def blocks_of(part: str, objects: list[str], renderer: str = "tiny") -> list[str]:
    """The blocks the part (``tracking`` or ``grasp``) writes for ``objects``: README's per object (TinyRenderer
    only); the claims of docs/reproduction.md (a) to (c) from the tracking of every object, (d) and (e) from the
    toolcap's grasp, (f) from the shaft's, each renderer into its own."""
    names = [block(f"{part}-{o}") for o in objects] if renderer == "tiny" else []
    if part == "tracking":
        return names + ([block(f"claim-{c}", renderer) for c in "abc"] if set(OBJECTS) <= set(objects) else [])
    names += [block(f"claim-{c}", renderer) for c in "de"] if HEADLINE_OBJECT in objects else []
    return names + ([block("claim-f", renderer)] if "shaft" in objects else [])


def object_networks(object_name: str) -> list[str]:
    """The shipped networks of the object, in the paper's order (supervised-edge, supervised-mask, self-supervised)."""
    shipped = set(shipped_names_for(load_object(object_name)))
    return [m for m in default_methods(object_name) if m in shipped]


def preflight(args: argparse.Namespace) -> None:
    """Refuse before any work what would fail or mislead after it: missing networks, networks of one object
    trained at different image sizes (a DON is not scale invariant and every method of an object runs at one
    wrist-camera size), missing block markers in README.md and docs/reproduction.md, a physically based run
    without Mitsuba installed."""
    problems = [] if args.renderer != "pbr" or mitsuba_available() else [INSTALL_HINT]
    for object_name in args.objects:
        networks = object_networks(object_name)
        missing = [m for m in default_methods(object_name)[1:] if m not in networks]
        if missing and not args.quick:
            problems.append(f"shipped networks missing: {missing}; run benchmarks/train_shipped.py first")
        sizes = {n: tuple(read_don_metadata(n).image_size) for n in networks}
        if len(set(sizes.values())) > 1:
            listed = ", ".join(f"{n} {w}x{h}" for n, (w, h) in sizes.items())
            problems.append(
                f"{object_name}: the shipped networks were trained at different image sizes ({listed}); every "
                f"method of an object is benchmarked at one wrist-camera size, so ship all of them from one "
                f"`benchmarks/train_shipped.py --objects {object_name}` run first"
            )
    # --quick checks the markers too: it is the rehearsal of a full run.
    parts = ("tracking", "grasp") if args.only is None else (args.only,)
    names = [n for part in parts for n in blocks_of(part, args.objects, args.renderer)]
    try:
        require_blocks(README_PATH, [n for n in names if ":claim-" not in n])
        require_blocks(REPRODUCTION_PATH, [n for n in names if ":claim-" in n])
    except (ValueError, OSError) as exc:
        problems.append(str(exc))
    if problems:
        sys.exit("bench_grasp.py: " + "\n".join(problems))


def provenance(results_link: str, section: str) -> str:
    """The line under every generated block: what made its figures, where, when, on which code."""
    return (
        f"*Measured by `{command_line()}`, {utc_now()}, {machine_description()}, commit {commit_description()}; "
        f"full tables in [benchmarks/RESULTS.md]({results_link}), section `{section}`.*"
    )


# --- tracking -------------------------------------------------------------------------------------


def tracking(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, dict[str, Any]]]:
    """The "tracking" section (``tracking-dev`` for ``--split dev``) and ``{object: summary}``
    (:meth:`TrackingResult.summary` with :data:`FIGURE_DEPTH`): per object, one dataset per seed of the split
    (:data:`don_gym.evaluation.splits.SPLIT_SEEDS`: the test seeds no decision has used, or the development seeds),
    ``--scenes`` x ``--frames`` each at the image size the object's shipped networks were trained at, with
    the D435 sensor, their scenes pooled; then :func:`don_gym.evaluation.tracking.evaluate_tracking_depths` for the
    oracle (optimal descriptors rendered from the true poses: the baseline every network is compared with)
    and every shipped network of the object, predicted points from ideal depth and from the recorded D435
    depth. Every percentile comes with its 95% interval from resampling scenes; per object and depth the
    tails, where the far matches land, and for :data:`FIGURE_DEPTH` the per-scene shares and the gallery
    of the supervised networks' worst matches (``tracking_<object>_worst_matches.png``). The 3D errors with
    D435 depth of all objects make the paper's figure, ``tracking_error_histograms.png``. With ``--renderer pbr``
    the same scenes with path-traced RGB (``<split>_pbr_<object>_<seed>``), every file name with ``_pbr``.
    """
    seeds = SPLIT_SEEDS[args.split]
    tag = renderer_suffix(args.renderer, "_")  # in the names of files, so that no renderer overwrites another's
    publish = not args.quick and args.split == "test"  # benchmarks/figures shows the test split only
    parts = []
    sizes = []
    errors_by_object = {}
    summaries = {}
    for object_name in args.objects:
        networks = object_networks(object_name)
        image_size = training_image_size({n: read_don_metadata(n).image_size for n in networks})
        sizes.append(f"{object_name} {image_size[0]}x{image_size[1]}")
        start = time.perf_counter()
        datasets = build_evaluation_datasets(
            object_name,
            seeds,
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
        results = evaluate_tracking_depths(
            datasets, ["oracle", *networks], TrackingConfig(points_per_scene=args.points), depths=TRACKING_DEPTHS
        )
        evaluation_s = time.perf_counter() - start
        for depth, result in results.items():
            summary = result.summary()
            supervised = [n for n in result.matches if _kind(result.sources[n], n) in SUPERVISED]
            output = work / f"tracking_{object_name}{tag}_{depth}"
            paths = write_tracking_outputs(result, output, gallery_methods=supervised)
            figures = []
            keys = ("histogram", "cdf", "worst_matches") if depth == FIGURE_DEPTH else ("histogram", "cdf")
            for key in keys:
                if publish and key in paths:
                    name = f"tracking_{object_name}{tag}_{key}.png" if key == "worst_matches" else None
                    target = FIGURES / (name or f"tracking_{object_name}{tag}_{depth}_{key}.png")
                    FIGURES.mkdir(exist_ok=True)
                    shutil.copyfile(paths[key], target)
                    figures.append(f"`benchmarks/figures/{target.name}`")
            if depth == FIGURE_DEPTH:
                summaries[object_name] = summary
                # Methods without the object's prefix, so that each keeps its name and colour in every panel.
                errors_by_object[object_name] = {
                    name.removeprefix(f"{object_name}/"): matches.error_3d_m * 1000.0
                    for name, matches in result.matches.items()
                }
            tables = [
                tracking_table(summary),
                f"Tails (a match more than {summary['far_match_mm']:.0f} mm off is far):",
                tail_table(summary),
                "Where the far matches land:",
                far_match_table(summary),
            ]
            if depth == FIGURE_DEPTH:
                tables += [f"Per scene, share of matches more than {summary['far_match_mm']:.0f} mm off:"]
                tables += [per_scene_table(summary)]
                targets = tracking_targets(object_name, tracking_figures(summary))
                if targets:
                    tables += ["Targets of the supervised networks:\n\n" + "\n".join(f"- {t}" for t in targets)]
            parts.append(
                f"### {object_name}, predicted points from {depth} depth\n\n"
                + "\n\n".join(tables)
                + (f"\n\nFigures: {', '.join(figures)}." if figures else "")
            )
        parts[-1] += (
            f"\n\n{object_name}: datasets built in {build_s:.0f} s, both depths evaluated in one pass in "
            f"{evaluation_s:.0f} s (bootstrap and figures included)."
        )
        if args.split == "dev":
            # Decisions about the matcher need its baseline in the same run: the paper's whole-image search.
            whole = evaluate_tracking_depths(
                datasets,
                ["oracle", *networks],
                TrackingConfig(points_per_scene=args.points, border_margin_px=0),
                depths=(FIGURE_DEPTH,),
            )[FIGURE_DEPTH]
            parts[-1] += (
                f"\n\n{object_name}, {FIGURE_DEPTH} depth: each method's border margin against the paper's search "
                "over the whole image (margin 0), the same scenes and reference points:\n\n"
                + margin_comparison_table(summaries[object_name], whole.summary())
            )
    header = (
        split_line(args.split, seeds, SPENT_SEEDS) + ", "
        f"{args.scenes} scenes x {args.frames} frames each, {len(seeds) * args.scenes} scenes per object, pooled, "
        f"at the networks' training size ({', '.join(sizes)}), sensor `d435`{rendering_text(args.renderer)}. "
        "Protocol (`don_gym.evaluation`): "
        f"{args.points} reference pixels per scene on the object in the frame showing most of it, their "
        "descriptors and true 3D points (ideal depth, true camera pose); in every other frame where a point "
        "is visible (ideal depth within 4 mm of its projection), the best match is the argmin L2 over the "
        "image, for a network but for its outer 16 pixels (`border_margin_px`: there its output saw the "
        "convolutions' zero padding; the paper searched the whole image, as for the oracle here), and the "
        "predicted point back-projects the frame's depth at that pixel with the true "
        "camera pose. Matches whose pixel has no depth (D435 holes) have no 3D error and are counted apart. "
        "*3D error mod symmetry*: distance between the rings the predicted and true points sweep about the "
        "part's axis; symmetric optimal descriptors are constant on those rings, so the plain 3D error of even "
        "the oracle is bounded below by the ring ambiguity. *Fraction closer*: share of all image pixels whose "
        "descriptor is closer to the reference than the true pixel's (DON's false-positive fraction). "
        "Baseline: the oracle.\n\n"
        "Intervals: 95%, percentile bootstrap over *scenes* (2000 resamples of the pooled scenes, seeded): the "
        "matches of one scene share its background, lighting and part pose, so resampling single matches would "
        f"understate how much a figure moves with the draw. A 3D error has *no long tail* only when the whole "
        f"interval of its p99 / median lies below {LONG_TAIL_RATIO:g}, a *long tail* when it lies at or above, "
        "and the sample does not settle it otherwise. Far matches (> 100 mm) by where the matched pixel lies: on "
        "the part's mask on the other half along its axis (*part, wrong end*) or elsewhere on it; otherwise its "
        "point from ideal depth and the true camera pose on the table top (within 5 mm of its plane), above it "
        "(*robot/fixture*: arm, gripper, cradle) or below and beyond it or without depth (*background*). With "
        "sensor depth the last column counts far matches that ideal depth at the same pixel would put within "
        "100 mm: the depth's doing, not the descriptors'."
    )
    figure = (FIGURES if publish else work) / f"tracking_error_histograms{tag}.png"
    figure.parent.mkdir(parents=True, exist_ok=True)
    plotting.plot_tracking_error_histograms(
        errors_by_object,
        figure,
        title="3D tracking error per method, predicted points from D435 depth (normalised per method, stacked)"
        + renderer_title(args.renderer),
    )
    print(f"wrote {figure}")
    if publish:
        header += (
            f"\n\nThe paper's tracking figure, {', '.join(errors_by_object)} side by side: "
            f"`benchmarks/figures/{figure.name}` (3D error with D435 depth; per method the histogram of its "
            "matches with depth, normalised to 1 and stacked, log-spaced bins)."
        )
    else:
        header += f"\n\nFigures and raw outputs stay in `{work}`."
    return header + "\n\n" + "\n\n".join(parts), summaries


def _kind(info: dict[str, Any], name: str) -> str:
    """The method kind (``oracle``, ``supervised-edge``, ...) of a method's recorded source info."""
    return str(info.get("method", name.rsplit("/", 1)[-1]))


def _interval(value: list[float] | None) -> tuple[float, float]:
    return (math.nan, math.nan) if value is None else (float(value[0]), float(value[1]))


def tracking_figures(summary: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``{kind: figures}`` of one object's tracking summary, each figure with its 95% interval over scenes
    (``*_ci``, NaN where undefined): the median of the 3D error modulo symmetry (the plain median for a part
    without an axis), the median and p99 of the 3D error and their ratio with its verdict, the share of far
    matches, the fraction closer."""
    out = {}
    for name, m in summary["methods"].items():
        plain, symmetric, closer = m["error_3d_mm"], m["error_3d_symmetric_mm"], m["fraction_closer"]
        intervals, tail = m["intervals"], m["tail"]
        # NaN where a method has no match with depth: every comparison with it fails, so no claim holds on it.
        p50, p99 = (math.nan if plain[k] is None else plain[k] for k in ("p50", "p99"))
        has_axis = symmetric["p50"] is not None
        out[_kind(m["source"], name)] = {
            "name": name,
            "p50_sym_mm": symmetric["p50"] if has_axis else p50,
            "p50_sym_ci": _interval(intervals["error_3d_symmetric_mm" if has_axis else "error_3d_mm"]["p50"]),
            "p50_mm": p50,
            "p50_ci": _interval(intervals["error_3d_mm"]["p50"]),
            "p99_mm": p99,
            "p99_ci": _interval(intervals["error_3d_mm"]["p99"]),
            "tail_ratio": math.nan if tail["p99_over_p50"] is None else tail["p99_over_p50"],
            "tail_ratio_ci": _interval(tail["p99_over_p50_interval"]),
            "tail": tail["verdict"],
            "far_pct": math.nan if tail["far_share"] is None else 100.0 * tail["far_share"],
            "far_pct_ci": tuple(100.0 * v for v in _interval(tail["far_share_interval"])),
            "far_matches": tail["far_matches"],
            "matches": m["counts"]["matches_with_depth"],
            "closer_pct": {k: None if v is None else 100.0 * v for k, v in closer.items()},
            "closer_pct_ci": {
                k: tuple(100.0 * x for x in _interval(v)) for k, v in intervals["fraction_closer"].items()
            },
        }
    return out


def _mm(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.1f}"


def _with_ci(value: float | None, interval: tuple[float, float], digits: int = 1) -> str:
    """``39.5 [31.0, 52.3]`` (:func:`don_gym.stats.format_estimate`)."""
    return format_estimate(value, interval, digits)


def margin_comparison_table(own: dict[str, Any], whole_image: dict[str, Any]) -> str:
    """Markdown table, one row per method: far share, p99 and median modulo symmetry with each method's own
    border margin beside the same figures of the whole-image search (two summaries of the same scenes)."""
    rows = [
        "| method | border margin (px) | share > 100 mm (%), whole image | with margin | 3D error p99 (mm), whole "
        "image | with margin | mod symmetry p50 (mm), whole image | with margin |",
        "|---|---:|---|---|---|---|---|---|",
    ]
    baseline = tracking_figures(whole_image)
    for kind, f in tracking_figures(own).items():
        b = baseline[kind]
        margin = own["methods"][f["name"]]["source"].get("border_margin_px", 0)
        rows.append(
            f"| {f['name']} | {margin} | {_with_ci(b['far_pct'], b['far_pct_ci'], 2)} | "
            f"{_with_ci(f['far_pct'], f['far_pct_ci'], 2)} | {_with_ci(b['p99_mm'], b['p99_ci'])} | "
            f"{_with_ci(f['p99_mm'], f['p99_ci'])} | {_with_ci(b['p50_sym_mm'], b['p50_sym_ci'])} | "
            f"{_with_ci(f['p50_sym_mm'], f['p50_sym_ci'])} |"
        )
    return "\n".join(rows)


def _dataset_text(summary: dict[str, Any], renderer: str = "tiny") -> str:
    width, height = summary["image_size"]
    seeds = summary["dataset_seeds"]
    return (
        f"{summary['scenes']} {summary['split']} scenes (seeds {', '.join(map(str, seeds))}, "
        f"{summary['scenes'] // max(1, len(seeds))} scenes x {summary['frames_per_scene']} frames each; never "
        f"trained on{', no decision has used them' if summary['split'] == 'test' else ''}), {width}x{height}"
        f"{rendering_text(renderer)}, predicted points from the D435's depth; 95% intervals from resampling the scenes"
    )


def tracking_block(object_name: str, summary: dict[str, Any], source: str) -> str:
    """README: per method the median 3D error modulo symmetry, the 99th percentile of the plain 3D error, their
    ratio's verdict and the share of far matches, each with its interval over scenes."""
    figures = tracking_figures(summary)
    lines = [
        f"**{object_name}**, {_dataset_text(summary)}:",
        "",
        "| method | 3D error mod symmetry, median (mm) | 3D error, 99th percentile (mm) | p99 / median "
        "| matches > 100 mm (%) | long tail | matches with depth |",
        "|---|---:|---:|---:|---:|---|---:|",
    ]
    lines += [
        f"| {f['name']} | {_with_ci(f['p50_sym_mm'], f['p50_sym_ci'])} | {_with_ci(f['p99_mm'], f['p99_ci'])} "
        f"| {_with_ci(f['tail_ratio'], f['tail_ratio_ci'])} | {_with_ci(f['far_pct'], f['far_pct_ci'], 2)} "
        f"| {f['tail']} | {f['matches']} |"
        for f in figures.values()
    ]
    lines += [
        "",
        f'*Long tail*: "no long tail" only when the whole interval of p99 / median lies below {LONG_TAIL_RATIO:g}, '
        '"long tail" when it lies at or above; "not settled" when this sample cannot tell.',
    ]
    targets = tracking_targets(object_name, figures)
    if targets:
        lines += ["", "Targets of the supervised networks:", "", *(f"- {line}" for line in targets)]
    return "\n".join(lines) + "\n\n" + source


def tracking_targets(object_name: str, figures: dict[str, dict[str, Any]]) -> list[str]:
    """One line per supervised network of :func:`tracking_figures`: its median 3D error modulo symmetry, p99 of
    the 3D error and share of far matches against :data:`TRACKING_TARGETS_MM` and :data:`TARGET_FAR_PCT`,
    ``met`` or the figures that miss; none for an object without targets."""
    if object_name not in TRACKING_TARGETS_MM:
        return []
    p50_target, p99_target = TRACKING_TARGETS_MM[object_name]
    lines = []
    for kind in SUPERVISED:
        if kind not in figures:
            continue
        f = figures[kind]
        checks = [
            ("3D error mod symmetry p50", f["p50_sym_mm"], f["p50_sym_ci"], p50_target, "mm", 1),
            ("3D error p99", f["p99_mm"], f["p99_ci"], p99_target, "mm", 1),
            ("matches > 100 mm", f["far_pct"], f["far_pct_ci"], TARGET_FAR_PCT, "%", 2),
        ]
        parts, missed = [], False
        for label, value, interval, target, unit, digits in checks:
            ok = math.isfinite(value) and value <= target
            missed |= not ok
            parts.append(f"{label} {_with_ci(value, interval, digits)} {unit} (target <= {target:g} {unit})")
        lines.append(f"{f['name']}: " + "; ".join(parts) + (": MISSED" if missed else ": met"))
    return lines


def _grasp_claim(
    criterion: str, results: GraspBenchmarkResult, kinds: list[str], failed: list[str], source_line: str
) -> str:
    """A generated grasp-claim block: the criterion, the outcome rows, the computed verdict, the data, the source."""
    rows = _grasp_rows(results, kinds)
    return "\n".join(
        [criterion, "", *rows, "", f"Verdict: {_verdict(failed)}.", "", _grasp_data(results), "", source_line]
    )


def _verdict(failed: list[str]) -> str:
    return "**holds**" if not failed else "**differs**: " + "; ".join(failed)


def _overall(per_object: dict[str, tuple[list[str], list[str]]]) -> str:
    """The verdict over objects, each with (failed, unsettled) lists."""
    outcome = {o: _tracking_outcome(*lists) for o, lists in per_object.items()}
    by_outcome: dict[str, list[str]] = {}
    for o, word in outcome.items():
        by_outcome.setdefault(word, []).append(o)
    if len(by_outcome) == 1:
        word, objects = next(iter(by_outcome.items()))
        return f"Verdict: **{word}** ({', '.join(objects)})."
    return "Verdict: " + ", ".join(f"**{word}** for {', '.join(objects)}" for word, objects in by_outcome.items()) + "."


def _tracking_outcome(failed: list[str], unsettled: list[str]) -> str:
    return "differs" if failed else ("not settled" if unsettled else "holds")


def _tracking_verdict(failed: list[str], unsettled: list[str]) -> str:
    """One object's verdict: **differs** when the intervals contradict a criterion, **not settled** when
    they straddle one (this sample cannot tell), **holds** when they meet every criterion."""
    if failed:
        return "**differs**: " + "; ".join(failed + unsettled)
    if unsettled:
        return "**not settled** (the intervals straddle the criterion): " + "; ".join(unsettled)
    return "**holds**"


def _compare(a: tuple[float, float], b: tuple[float, float]) -> str:
    """``"below"`` when interval ``a`` lies wholly below ``b``, ``"above"`` when wholly above, ``"overlap"``
    otherwise (NaN ends: ``"overlap"``, nothing is settled on them)."""
    if a[1] < b[0]:
        return "below"
    if a[0] > b[1]:
        return "above"
    return "overlap"


def _tracking_claim_table(by_object: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    lines = [
        "| object | method | 3D error mod symmetry, median (mm) | 3D error, median (mm) | 3D error, p99 (mm) "
        "| p99 / median | matches > 100 mm (%) | long tail |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for object_name, figures in by_object.items():
        for kind, f in figures.items():
            lines.append(
                f"| {object_name} | {kind} | {_with_ci(f['p50_sym_mm'], f['p50_sym_ci'])} "
                f"| {_with_ci(f['p50_mm'], f['p50_ci'])} | {_with_ci(f['p99_mm'], f['p99_ci'])} "
                f"| {_with_ci(f['tail_ratio'], f['tail_ratio_ci'])} | {_with_ci(f['far_pct'], f['far_pct_ci'], 2)} "
                f"| {f['tail']} |"
            )
    return lines


def tracking_claim_blocks(summaries: dict[str, dict[str, Any]], source: str, renderer: str = "tiny") -> dict[str, str]:
    """docs/reproduction.md, claims (a) to (c), from the tracking summaries of every object on the RGB of
    ``renderer`` (blocks ``claim-a`` ..., ``claim-a-pbr`` ...); every comparison is made on the 95% intervals over
    scenes, so a verdict can also be "not settled"."""
    by_object = {o: tracking_figures(s) for o, s in summaries.items()}
    datasets = "; ".join(f"{o}: {_dataset_text(s, renderer)}" for o, s in summaries.items())
    table = _tracking_claim_table(by_object)
    blocks = {}

    verdicts_a, verdicts_b, verdicts_c = {}, {}, {}
    for object_name, f in by_object.items():
        ssl = f.get(SELF_SUPERVISED)
        supervised = {k: f[k] for k in SUPERVISED if k in f}
        if ssl is None or not supervised:
            missing = ["no self-supervised network evaluated" if ssl is None else "no supervised network evaluated"]
            verdicts_a[object_name] = verdicts_b[object_name] = verdicts_c[object_name] = (missing, [])
            continue
        failed, unsettled = [], []
        for kind, s in supervised.items():
            text = (
                f"self-supervised median {_with_ci(ssl['p50_sym_mm'], ssl['p50_sym_ci'])} mm vs {kind}'s "
                f"{_with_ci(s['p50_sym_mm'], s['p50_sym_ci'])} mm"
            )
            order = _compare(ssl["p50_sym_ci"], s["p50_sym_ci"])
            if order == "above":
                failed.append(f"{text}: above")
            elif order == "overlap":
                unsettled.append(f"{text}: the intervals overlap")
        if ssl["tail"] == "no long tail":
            failed.append(
                f"self-supervised has no long tail (p99 / median {_with_ci(ssl['tail_ratio'], ssl['tail_ratio_ci'])})"
            )
        elif ssl["tail"] != "long tail":
            unsettled.append(
                f"self-supervised p99 / median {_with_ci(ssl['tail_ratio'], ssl['tail_ratio_ci'])} straddles "
                f"{LONG_TAIL_RATIO:g}"
            )
        verdicts_a[object_name] = (failed, unsettled)
        failed, unsettled = [], []
        for kind, s in supervised.items():
            ratio = _with_ci(s["tail_ratio"], s["tail_ratio_ci"])
            if s["tail"] == "long tail":
                failed.append(f"{kind} has a long tail (p99 / median {ratio})")
            elif s["tail"] != "no long tail":
                unsettled.append(f"{kind}'s p99 / median {ratio} does not lie wholly below {LONG_TAIL_RATIO:g}")
            medians = (
                f"{_with_ci(s['p50_sym_mm'], s['p50_sym_ci'])} vs self-supervised's "
                f"{_with_ci(ssl['p50_sym_mm'], ssl['p50_sym_ci'])} mm"
            )
            order = _compare(s["p50_sym_ci"], ssl["p50_sym_ci"])
            if order == "below":
                failed.append(f"{kind} is more accurate at the median than self-supervised ({medians})")
            elif order == "overlap":
                unsettled.append(f"{kind}'s median and self-supervised's overlap ({medians})")
            else:
                within = _compare(s["p50_sym_ci"], tuple(SLIGHTLY_LESS_ACCURATE * v for v in ssl["p50_sym_ci"]))
                if within == "above":
                    failed.append(
                        f"{kind}'s median is more than {SLIGHTLY_LESS_ACCURATE:g}x self-supervised's ({medians})"
                    )
                elif within == "overlap":
                    unsettled.append(
                        f"{kind}'s median may be more than {SLIGHTLY_LESS_ACCURATE:g}x self-supervised's ({medians})"
                    )
        verdicts_b[object_name] = (failed, unsettled)
        failed, unsettled = [], []
        for kind, s in supervised.items():
            ssl_mean = _with_ci(ssl["closer_pct"]["mean"], ssl["closer_pct_ci"]["mean"], 3)
            text = (
                f"self-supervised's mean fraction closer {ssl_mean} vs {kind}'s "
                f"{_with_ci(s['closer_pct']['mean'], s['closer_pct_ci']['mean'], 3)}"
            )
            order = _compare(ssl["closer_pct_ci"]["mean"], s["closer_pct_ci"]["mean"])
            if order == "below":
                failed.append(f"{text}: below")
            elif order == "overlap":
                unsettled.append(f"{text}: the intervals overlap")
        verdicts_c[object_name] = (failed, unsettled)

    def claim(criterion: str, verdicts: dict[str, tuple[list[str], list[str]]], rows: list[str]) -> str:
        per_object = "\n".join(f"- {o}: {_tracking_verdict(*v)}" for o, v in verdicts.items())
        return "\n".join(
            [criterion, "", *rows, "", per_object, "", _overall(verdicts), "", f"Data: {datasets}.", "", source]
        )

    blocks[block("claim-a", renderer)] = claim(
        f"Criterion: per object, the self-supervised network's median 3D error modulo symmetry is below both "
        f"supervised networks' (more accurate at the median: its interval wholly below theirs), and its 3D "
        f"error has a long tail (the interval of its 99th percentile over its median at or above "
        f"{LONG_TAIL_RATIO:g}). Overlapping intervals leave a comparison not settled.",
        verdicts_a,
        table,
    )
    blocks[block("claim-b", renderer)] = claim(
        f"Criterion: per object, each supervised network's 3D error has no long tail (the interval of its 99th "
        f"percentile over its median wholly below {LONG_TAIL_RATIO:g}), and its median 3D error modulo symmetry is "
        f"above the self-supervised network's (less accurate: interval wholly above) by at most "
        f"{SLIGHTLY_LESS_ACCURATE:g}x (slightly). Overlapping intervals leave a comparison not settled.",
        verdicts_b,
        table,
    )
    closer_rows = [
        "| object | method | fraction closer, median (%) | 90th percentile (%) | mean (%) |",
        "|---|---|---:|---:|---:|",
    ]
    for object_name, figures in by_object.items():
        for kind, f in figures.items():
            pct, ci = f["closer_pct"], f["closer_pct_ci"]
            closer_rows.append(
                f"| {object_name} | {kind} | {_with_ci(pct['p50'], ci['p50'], 3)} "
                f"| {_with_ci(pct['p90'], ci['p90'], 3)} | {_with_ci(pct['mean'], ci['mean'], 3)} |"
            )
    blocks[block("claim-c", renderer)] = claim(
        "Criterion: per object, the self-supervised network's mean fraction closer (share of the image's pixels "
        "whose descriptor is nearer the reference than the true match's) is above both supervised networks' "
        "(interval wholly above). Overlapping intervals leave a comparison not settled.",
        verdicts_c,
        closer_rows,
    )
    return blocks


# --- grasp ----------------------------------------------------------------------------------------


def _copy_grasp_figures(args: argparse.Namespace, paths: dict[str, Path], prefix: str) -> list[str]:
    """Copy a grasp run's charts to ``benchmarks/figures/PREFIX_KEY.png`` (not with ``--quick``); their names."""
    if args.quick:
        return []
    FIGURES.mkdir(exist_ok=True)
    figures = []
    for key, path in paths.items():
        if path.suffix == ".png":
            target = FIGURES / f"{prefix}_{key}.png"
            shutil.copyfile(path, target)
            figures.append(f"`benchmarks/figures/{target.name}`")
    return figures


def grasp(
    args: argparse.Namespace, work: Path, object_name: str
) -> tuple[str, GraspBenchmarkResult, GraspBenchmarkResult | None]:
    """The object's grasp section: :func:`don_gym.evaluation.grasp_benchmark.run_grasp_benchmark` (``don-gym
    benchmark grasp
    --object OBJECT``): oracle and the object's shipped networks on the 8 fixed poses, ``--repeats`` seeds,
    sensors ideal, d435@0.5 and d435 (the headline table is the D435's), ``--random-poses`` random poses, and
    the issue's targets checked (oracle 8/8 grasp & place; supervised networks 8/8 grasped and at least 7/8
    grasp & place, per 8 poses). Then the same methods on the 8 fixed poses over varied backgrounds
    (``--backgrounds random``: ``--background-repeats`` backdrops per pose, D435), with the same targets.
    For the toolcap, the README's ``don-gym benchmark grasp --quick`` then runs as a separate process and is
    timed; its episodes must equal the full run's matching ones. Returns the section, the plain run's result
    and the varied backgrounds' result.

    With ``--renderer pbr``: the 8 fixed poses x ``--repeats`` at the D435 only, the same seeds as TinyRenderer's
    run, and nothing else (varied backgrounds None): the sweep over depth sensors measures the depth, which the
    renderer does not change, and the random poses, the varied backgrounds and the README's quick run would
    multiply a run whose every wrist image is path-traced.
    """
    tiny = args.renderer == "tiny"
    tag = renderer_suffix(args.renderer, "_")
    methods = ("oracle", *object_networks(object_name))
    config = GraspBenchmarkConfig(
        object=object_name,
        methods=methods,
        repeats=args.repeats,
        sensors=GRASP_SENSORS if tiny else GRASP_SENSORS[-1:],
        image_size=None,  # the networks' training size (preflight made sure they agree)
        poses=(0, 1) if args.quick else tuple(range(8)),
        random_poses=args.random_poses if tiny else 0,
        renderer=args.renderer,
    )
    result = run_grasp_benchmark(config, workers=args.workers)
    prefix = ("grasp" if object_name == HEADLINE_OBJECT else f"grasp_{object_name}") + tag
    figures = _copy_grasp_figures(args, write_grasp_outputs(result, work / f"grasp_{object_name}{tag}"), prefix)
    backgrounds = None
    if tiny:
        # The fixed poses over varied backgrounds, at the headline sensor; repeat r has the plain run's seed of
        # repeat r (the same part pose, noise and calibration error), so the background is the only difference.
        backgrounds_config = replace(
            result.config,
            sensors=(GRASP_SENSORS[-1],),
            repeats=1 if args.quick else args.background_repeats,
            random_poses=0,
            backgrounds=GRASP_BACKGROUNDS,
        )
        backgrounds = run_grasp_benchmark(backgrounds_config, workers=args.workers)
        backgrounds_paths = write_grasp_outputs(backgrounds, work / f"grasp_{object_name}_backgrounds")
        figures += _copy_grasp_figures(args, backgrounds_paths, f"{prefix}_backgrounds")
    targets = check_targets(result)
    per_episode = sorted(e["seconds"] for e in result.episodes)
    width, height = result.config.image_size
    body = (
        f'{object_name.capitalize()}, `control="grasp"`, {width}x{height} wrist camera '
        f"(the shipped networks' training size){rendering_text(args.renderer)}, "
        f"`AxisGraspAgent` per method, {len(config.poses)} fixed poses x {config.repeats} repeats (seeds vary "
        "sensor noise and hand-eye calibration error; every method and sensor sees the same seeds), "
        f"{args.workers} worker processes. Baseline: the oracle (optimal descriptors from the true pose). "
        "Flipped +axis = yaw error over 90 degrees (the paper's upside-down placements); grasp errors are "
        "against the true grasp point and +axis yaw.\n\n"
        "#### Outcomes, D435 sensor (the paper's robot-experiment figure)\n\n"
        + outcome_table(result)
        + "\n\nTargets (per 8 poses, scaled by the repeats):\n\n"
        + "\n".join(f"- {line}" for line in targets)
        + "\n\n#### Why episodes were not placed\n\n"
        + miss_table(result)
    )
    if not tiny:
        body += (
            "\n\nThe depth-sensor sweep, the random poses and the varied backgrounds are TinyRenderer's only "
            f"(section `{grasp_section(object_name)}`). {len(result.episodes)} episodes in "
            f"{result.seconds / 60:.1f} min; per episode median {per_episode[len(per_episode) // 2]:.1f} s (in a "
            "worker, env and model set-up included in the first)."
            + (f" Figures: {', '.join(figures)}." if figures else "")
        )
        return body, result, None
    body += (
        "\n\n#### Depth-sensor sweep (ideal -> D435)\n\n"
        + sweep_table(result)
        + (
            f"\n\n#### {config.random_poses} random poses, D435 sensor\n\n"
            "Beyond the paper's 8 poses: `env.reset(seed)` draws the part's position over the workspace and its "
            "yaw uniformly; the seeds derive from the benchmark seed, so every method and sensor sees the same "
            "poses.\n\n" + outcome_table(result, poses="random") + "\n\n" + sweep_table(result, poses="random")
            if config.random_poses
            else ""
        )
        + "\n\n"
        + backgrounds_section(backgrounds)
        + f"\n\n{len(result.episodes)} + {len(backgrounds.episodes)} episodes (plain, varied backgrounds) in "
        f"{result.seconds / 60:.1f} + {backgrounds.seconds / 60:.1f} min; per episode median "
        f"{per_episode[len(per_episode) // 2]:.1f} s (in a worker, env and model set-up included in the first)."
        + (f" Figures: {', '.join(figures)}." if figures else "")
    )
    if object_name == HEADLINE_OBJECT:
        body += "\n\n" + readme_quick_run(args, work, result)
    return body, result, backgrounds


def backgrounds_section(result: GraspBenchmarkResult) -> str:
    """RESULTS.md: the fixed poses over varied backgrounds, their outcomes, targets and misses."""
    return (
        f"#### {len(result.config.poses)} fixed poses over varied backgrounds, D435 sensor\n\n"
        f'`background="{result.config.backgrounds}"`: every episode another procedural backdrop on the table top '
        "and the floor (the families of the datasets the networks are tested on) and another cradle colour, drawn "
        "from the episode's seed. Repeat r of a pose has the seed of the plain run's repeat r, so the part pose, "
        "sensor noise and calibration error are that episode's and the background is the only difference.\n\n"
        + outcome_table(result)
        + "\n\nTargets over varied backgrounds (per 8 poses, scaled by the repeats):\n\n"
        + "\n".join(f"- {line}" for line in check_targets(result))
        + "\n\n"
        + miss_table(result)
    )


def readme_quick_run(args: argparse.Namespace, work: Path, result: GraspBenchmarkResult) -> str:
    """The README's quick run, timed as a user runs it (a fresh process, imports included), checked
    against the full run's matching episodes."""
    quick_out = work / "grasp_quick"
    command = [sys.executable, "-m", "don_gym.cli", "benchmark", "grasp", "--quick", "--no-progress"]
    command += ["--workers", str(args.workers), "--out", str(quick_out)]
    if args.quick:
        command += ["--poses", "0", "1"]
    start = time.perf_counter()
    subprocess.run(command, check=True)
    quick_s = time.perf_counter() - start
    quick = json.loads((quick_out / "grasp_episodes.json").read_text())["episodes"]
    same = [{k: v for k, v in e.items() if k != "seconds"} for e in quick] == [
        {k: v for k, v in e.items() if k != "seconds"}
        for e in result.episodes
        if e["sensor"] == "d435"
        and e["repeat"] == 0
        and e["random_pose"] is None
        and e["method"] in {q["method"] for q in quick}
    ]
    return (
        f"`don-gym benchmark grasp --quick` (the README's run: {len(quick)} episodes, 1 repeat, sensor d435, "
        f"{args.workers} workers): {quick_s:.0f} s wall-clock including start-up; its episodes "
        + ("equal" if same else "DIFFER FROM")
        + " the full run's repeat-0 D435 episodes."
    )


def _by_kind(result: GraspBenchmarkResult, poses: str = "fixed") -> dict[str, dict[str, Any]]:
    """``{kind: summary of the method}`` at the headline sensor, each with its ``name``."""
    summary = result.summary()["results" if poses == "fixed" else "random_pose_results"][result.headline_sensor]
    return {_kind(result.method_info.get(m, {}), m): {"name": m, **s} for m, s in summary.items()}


def _targets(result: GraspBenchmarkResult) -> tuple[int, float, float]:
    """Episodes per method at the fixed poses, and the paper's supervised result scaled to them."""
    episodes = result.episodes_per_cell("fixed")
    return episodes, TARGET_GRASPED_PER_8 * episodes / 8.0, TARGET_PLACED_PER_8 * episodes / 8.0


def _met_and_missed(result: GraspBenchmarkResult) -> tuple[list[str], list[str]]:
    """The networks (no oracle) that meet the supervised target at the fixed poses, and those that miss it."""
    _, need_grasped, need_placed = _targets(result)
    networks = [s for kind, s in _by_kind(result).items() if kind != "oracle"]
    met = [
        s["name"] for s in networks if s["grasped"] >= need_grasped and s["counts"]["grasp_and_place"] >= need_placed
    ]
    return met, [s["name"] for s in networks if s["name"] not in met]


def grasp_block(result: GraspBenchmarkResult, source: str, backgrounds: GraspBenchmarkResult | None = None) -> str:
    """README: the object's outcome table at the D435, the targets, a sentence per kind of network, the
    targets over varied backgrounds (``backgrounds``), and for the headline object the depth-sensor sweep."""
    by_kind = _by_kind(result)
    episodes, need_grasped, need_placed = _targets(result)
    met, missed = _met_and_missed(result)
    criterion = (
        "all 8 poses grasped and at least 7 of 8 grasped and placed, scaled to "
        f"{episodes} episodes (at least {need_grasped:g} grasped and {need_placed:g} grasped and placed)"
    )
    if result.config.object == HEADLINE_OBJECT:
        claim = f"The paper's result for its supervised networks on the {HEADLINE_OBJECT}, {criterion}"
    else:
        # The paper found the shaft not challenging for any network: every one is held to the toolcap's result.
        claim = (
            f"The paper found the {result.config.object} not challenging for any network; every network is held "
            f"to its result for the supervised networks on the {HEADLINE_OBJECT}, {criterion}"
        )
    lines = [
        outcome_table(result),
        "",
        f"{claim}: "
        + (f"met by {', '.join(met)}" if met else "met by no network")
        + (f"; missed by {', '.join(missed)}." if missed else "."),
    ]
    ssl = by_kind.get(SELF_SUPERVISED)
    if ssl is not None:
        lines[-1] += (
            f" {ssl['name']}: grasped {format_rate(ssl['grasped'], episodes)}, grasped and placed "
            f"{format_rate(ssl['counts']['grasp_and_place'], episodes)}, +axis flipped (placed upside down) in "
            f"{ssl['flipped']} of {episodes}."
        )
    if backgrounds is not None:
        bg_episodes, bg_grasped, bg_placed = _targets(backgrounds)
        bg_met, bg_missed = _met_and_missed(backgrounds)
        lines[-1] += (
            f' Over varied backgrounds (`background="{backgrounds.config.backgrounds}"`, '
            f"{backgrounds.config.repeats} backdrops per fixed pose, {bg_episodes} episodes per method, sensor "
            f"`{backgrounds.headline_sensor}`; at least {bg_grasped:g} grasped and {bg_placed:g} grasped and placed): "
            + (f"met by {', '.join(bg_met)}" if bg_met else "met by no network")
            + (f"; missed by {', '.join(bg_missed)}." if bg_missed else ".")
        )
    if result.config.object == HEADLINE_OBJECT and len(result.config.sensors) > 1:
        lines += ["", "Depth-sensor sweep from ideal depth to the D435:", "", sweep_table(result)]
    return "\n".join(lines) + "\n\n" + source


def _grasp_rows(result: GraspBenchmarkResult, kinds: list[str]) -> list[str]:
    episodes = result.episodes_per_cell("fixed")
    by_kind = _by_kind(result)
    lines = [
        "| method | grasped | grasped and placed | +axis flipped | median yaw error (deg) |",
        "|---|---|---|---|---:|",
    ]
    for kind in kinds:
        if kind in by_kind:
            s = by_kind[kind]
            lines.append(
                f"| {s['name']} | {format_rate(s['grasped'], episodes)} "
                f"| {format_rate(s['counts']['grasp_and_place'], episodes)} | {format_rate(s['flipped'], episodes)} "
                f"| {_mm(s['median_yaw_error_deg'])} |"
            )
    return lines


def _grasp_data(result: GraspBenchmarkResult) -> str:
    width, height = result.config.image_size
    return (
        f"Data: {result.config.object}, sensor `{result.headline_sensor}`, {width}x{height} wrist camera"
        f"{rendering_text(result.config.renderer)}, "
        f"{len(result.config.poses)} fixed poses x {result.config.repeats} repeats = "
        f"{result.episodes_per_cell('fixed')} episodes per method (95% Wilson intervals)."
    )


def _meets_supervised_target(result: GraspBenchmarkResult, kind: str) -> list[str]:
    episodes, need_grasped, need_placed = _targets(result)
    s = _by_kind(result).get(kind)
    if s is None:
        return [f"{result.config.object}: no {kind} network benchmarked"]
    failed = []
    if s["grasped"] < need_grasped:
        failed.append(f"{s['name']} grasped {s['grasped']} of {episodes} (needs {need_grasped:g})")
    if s["counts"]["grasp_and_place"] < need_placed:
        failed.append(
            f"{s['name']} grasped and placed {s['counts']['grasp_and_place']} of {episodes} (needs {need_placed:g})"
        )
    return failed


def grasp_claim_blocks(results: dict[str, GraspBenchmarkResult], source: Callable[[str], str]) -> dict[str, str]:
    """docs/reproduction.md, claims (d) and (e) from the toolcap's result, (f) from the shaft's, into the blocks of
    the results' renderer (``claim-d``, ``claim-d-pbr``, ...); ``source`` gives the provenance line of an object's
    grasp section."""
    blocks = {}
    kinds = ["oracle", *SUPERVISED, SELF_SUPERVISED]
    toolcap = results.get(HEADLINE_OBJECT)
    if toolcap is not None:
        episodes, need_grasped, need_placed = _targets(toolcap)
        failed = [f for kind in SUPERVISED for f in _meets_supervised_target(toolcap, kind)]
        blocks[block("claim-d", toolcap.config.renderer)] = _grasp_claim(
            f"Criterion: each supervised network grasps the toolcap in all {episodes} episodes at the fixed "
            f"poses (the paper's 8 of 8, scaled: at least {need_grasped:g}) and grasps and places it in at "
            f"least {need_placed:g} (7 of 8, scaled). The oracle is shown as the reference.",
            toolcap,
            kinds,
            failed,
            source(HEADLINE_OBJECT),
        )
        by_kind = _by_kind(toolcap)
        ssl = by_kind.get(SELF_SUPERVISED)
        failed = []
        if ssl is None:
            failed.append("no self-supervised network benchmarked")
        else:
            for kind in SUPERVISED:
                s = by_kind.get(kind)
                if s is None:
                    continue
                if not ssl["flipped"] > s["flipped"]:
                    failed.append(f"self-supervised flipped {ssl['flipped']}, {kind} {s['flipped']}")
                if not ssl["counts"]["grasp_and_place"] < s["counts"]["grasp_and_place"]:
                    failed.append(
                        f"self-supervised grasped and placed {ssl['counts']['grasp_and_place']}, "
                        f"{kind} {s['counts']['grasp_and_place']}"
                    )
        blocks[block("claim-e", toolcap.config.renderer)] = _grasp_claim(
            "Criterion: on the toolcap, the self-supervised network flips the part's +axis (grasps it "
            "the wrong way round, so that it is placed upside down) in more episodes than each supervised "
            "network, and grasps and places it in fewer.",
            toolcap,
            kinds,
            failed,
            source(HEADLINE_OBJECT),
        )
    shaft = results.get("shaft")
    if shaft is not None:
        episodes, need_grasped, need_placed = _targets(shaft)
        networks = [k for k in (*SUPERVISED, SELF_SUPERVISED) if k in _by_kind(shaft)] or [*SUPERVISED]
        failed = [f for kind in networks for f in _meets_supervised_target(shaft, kind)]
        blocks[block("claim-f", shaft.config.renderer)] = _grasp_claim(
            f"Criterion: every network, the self-supervised one included, meets on the shaft what the paper "
            f"reports for the supervised networks on the toolcap: all {episodes} episodes at the fixed poses "
            f"grasped (at least {need_grasped:g}), at least {need_placed:g} grasped and placed.",
            shaft,
            kinds,
            failed,
            source("shaft"),
        )
    return blocks


# --- main -----------------------------------------------------------------------------------------


def grasp_section(object_name: str, renderer: str = "tiny") -> str:
    """The object's RESULTS.md section (the headline object keeps the name it always had; ``-pbr`` added for the
    physically based renderer)."""
    return ("grasp" if object_name == HEADLINE_OBJECT else f"grasp-{object_name}") + renderer_suffix(renderer)


def tracking_section(split: str, renderer: str = "tiny") -> tuple[str, str, str | None]:
    """The tracking section of a run: its name (``tracking``, ``tracking-dev``, ``tracking-pbr``,
    ``tracking-dev-pbr``), its title and the section it goes right after (None: where it is, or at the end)."""
    if split == "test":
        return renderer_section(
            "tracking", "Tracking error of the shipped DONs (paper's protocol), test split", renderer
        )
    title = "Tracking error of the shipped DONs (paper's protocol), development split"
    return renderer_section("tracking-dev", title, renderer, after="tracking")


def grasp_title(object_name: str, renderer: str = "tiny") -> tuple[str, str | None]:
    """The title of an object's grasp section and the section it goes right after: TinyRenderer's shaft after
    the toolcap's, a physically based run's after TinyRenderer's of the same object."""
    if renderer == "tiny":
        after = None if object_name == HEADLINE_OBJECT else grasp_section(HEADLINE_OBJECT)
        return (
            f"Grasp and place: {object_name}, 8 fixed poses, depth-sensor sweep, random poses, varied backgrounds",
            after,
        )
    title = f"Grasp and place: {object_name}, 8 fixed poses, D435 sensor{renderer_title(renderer)}"
    return title, grasp_section(object_name)


def write_blocks(path: Path, blocks: dict[str, str], quick: bool) -> None:
    """Print each block; outside ``--quick`` write it into ``path`` (:func:`_results.replace_block`)."""
    for name, text in blocks.items():
        print(f"\n--- {path.relative_to(REPO_ROOT)}, block {name}{' (not written: --quick)' if quick else ''} ---")
        print(text)
        if not quick:
            replace_block(path, name, text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="runs/bench_grasp", help="directory for datasets and raw outputs")
    parser.add_argument(
        "--split",
        choices=tuple(SPLIT_SEEDS),
        default=None,
        help="tracking scenes: the test seeds (default; the figures the README and docs quote) or the development "
        "seeds (for decisions: recorded in RESULTS.md's section tracking-dev only; the default of --quick, so that a "
        "smoke run shows no test scene)",
    )
    parser.add_argument("--scenes", type=int, default=SCENES_PER_SEED, help="tracking scenes per seed of the split")
    parser.add_argument("--frames", type=int, default=FRAMES_PER_SCENE, help="frames per tracking scene")
    parser.add_argument("--points", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--random-poses", type=int, default=24, help="seeded random poses beyond the 8 fixed ones")
    parser.add_argument(
        "--background-repeats", type=int, default=3, help="backdrops per fixed pose in the varied-backgrounds run"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS), choices=OBJECTS, help="objects of both parts")
    parser.add_argument("--only", choices=("tracking", "grasp"), default=None)
    parser.add_argument(
        "--renderer",
        choices=MEASURED_RENDERERS,
        default="tiny",
        help="RGB of every scene and episode: tiny (TinyRenderer, default; what the networks were trained on) or "
        "pbr (path-traced, the pbr extra: the same scenes with datasets <split>_pbr_<object>_<seed>, sections "
        "tracking-pbr, grasp-pbr, grasp-shaft-pbr, blocks bench_grasp:claim-X-pbr of docs/reproduction.md, no "
        "README block; grasp at the 8 fixed poses with the D435 only)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny smoke run in a temp dir; records nothing")
    args = parser.parse_args()
    freeze_commit_description()  # before this run writes README.md and docs/reproduction.md
    args.objects = [o for o in OBJECTS if o in args.objects]  # the headline object first, each once
    torch.set_num_threads(1)
    preflight(args)
    work = Path(tempfile.mkdtemp(prefix="don_gym_bench_grasp_")) if args.quick else Path(args.work)
    if args.quick:
        args.scenes, args.frames, args.points, args.repeats, args.random_poses = 1, 4, 6, 1, 1
    if args.split is None:
        args.split = "dev" if args.quick else "test"
    record: Callable[..., Any] = (lambda *a, **k: None) if args.quick else record_section
    if args.only in (None, "tracking"):
        body, summaries = tracking(args, work)
        print(body)
        section, title, after = tracking_section(args.split, args.renderer)
        record(section, title, body, after=after)
        source = provenance("benchmarks/RESULTS.md", "tracking")
        # The README and docs/reproduction.md quote the test split only; --quick prints their blocks, writes none.
        quote = args.split == "test" or args.quick
        if quote and args.renderer == "tiny":
            write_blocks(
                README_PATH,
                {block(f"tracking-{o}"): tracking_block(o, s, source) for o, s in summaries.items()},
                args.quick,
            )
        if quote and set(OBJECTS) <= set(summaries):
            write_blocks(
                REPRODUCTION_PATH,
                tracking_claim_blocks(
                    summaries,
                    provenance("../benchmarks/RESULTS.md", tracking_section("test", args.renderer)[0]),
                    args.renderer,
                ),
                args.quick,
            )
    if args.only in (None, "grasp"):
        results, backgrounds = {}, {}
        for object_name in args.objects:
            body, results[object_name], backgrounds[object_name] = grasp(args, work, object_name)
            print(body)
            section = grasp_section(object_name, args.renderer)
            title, after = grasp_title(object_name, args.renderer)
            record(section, title, body, after=after)
            if args.renderer == "tiny":
                source = provenance("benchmarks/RESULTS.md", section)
                readme_block = grasp_block(results[object_name], source, backgrounds[object_name])
                write_blocks(README_PATH, {block(f"grasp-{object_name}"): readme_block}, args.quick)
        claims = grasp_claim_blocks(
            results, lambda o: provenance("../benchmarks/RESULTS.md", grasp_section(o, args.renderer))
        )
        write_blocks(REPRODUCTION_PATH, claims, args.quick)


if __name__ == "__main__":
    main()
