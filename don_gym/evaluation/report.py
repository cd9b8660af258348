"""The tracking protocol's report: Markdown tables of a :meth:`~don_gym.evaluation.tracking.TrackingResult.summary`
(percentiles with intervals, tails, where far matches land, per scene), the worst-match gallery and the files
``don-gym evaluate`` writes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.data.dataset import DONDataset
from don_gym.errors import DonGymError
from don_gym.evaluation.tracking import TrackingResult
from don_gym.evaluation.tracking_metrics import (
    FAR_MATCH_M,
    LONG_TAIL_RATIO,
    MATCH_CATEGORIES,
    PILE_CATEGORY,
    worst_matches,
)
from don_gym.stats import DEFAULT_CONFIDENCE, format_estimate

__all__ = [
    "GALLERY_COUNT",
    "far_match_table",
    "gallery_entries",
    "per_scene_table",
    "tail_table",
    "tracking_report",
    "tracking_table",
    "write_tracking_outputs",
    "write_worst_matches_figure",
]

#: Worst matches per method in the gallery figure.
GALLERY_COUNT = 6


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _estimate(method: Mapping[str, Any], metric: str, key: str, digits: int = 1, scale: float = 1.0) -> str:
    """A percentile of a method's summary with its interval, e.g. ``39.5 [31.0, 52.3]``."""
    value = method[metric][key]
    interval = method.get("intervals", {}).get(metric, {}).get(key)
    return format_estimate(
        None if value is None else scale * value,
        None if interval is None else [scale * v for v in interval],
        digits,
    )


def _p50_p90(method: Mapping[str, Any], metric: str, digits: int = 1, scale: float = 1.0) -> str:
    """Median and 90th percentile of a metric with their intervals, ``p50 / p90``."""
    return f"{_estimate(method, metric, 'p50', digits, scale)} / {_estimate(method, metric, 'p90', digits, scale)}"


def _far_share_pct(far: Mapping[str, Any]) -> str:
    """The share of far matches (a summary's ``tail`` or ``tail_any_instance``) in percent with its interval."""
    share, interval = far["far_share"], far["far_share_interval"]
    return format_estimate(
        None if share is None else 100.0 * share, None if interval is None else [100.0 * v for v in interval], 2
    )


def _any_instance(summary: Mapping[str, Any]) -> bool:
    """Whether the methods of a summary carry the any-instance errors of a pile (:func:`tracking_errors`)."""
    return any("tail_any_instance" in m for m in summary["methods"].values())


def _confidence(summary: Mapping[str, Any]) -> str:
    boot = summary.get("bootstrap", {})
    return (
        f"[{100 * boot.get('confidence', DEFAULT_CONFIDENCE):.0f}% interval from {boot.get('resamples', '?')} "
        f"resamples of the {summary.get('scenes', '?')} scenes]"
    )


def tracking_table(summary: Mapping[str, Any]) -> str:
    """Markdown table of a :meth:`TrackingResult.summary`: one row per method, every percentile with its
    interval from resampling scenes; on piles also the any-instance errors' p50 / p90."""
    any_instance = _any_instance(summary)
    header = (
        "| method | matches (with depth) | 3D error p50 (mm) | 3D error p90 (mm) | 3D error p99 (mm) "
        "| 3D error mod symmetry p50 (mm) | 3D error mod symmetry p90 (mm) | pixel error p50 / p90 (px) "
        "| fraction closer p50 / p90 (%) |"
    )
    if any_instance:
        header += " 3D error, any instance p50 / p90 (mm) | 3D error mod symmetry, any instance p50 / p90 (mm) |"
    lines = [header, "|---|---|---|---|---|---|---|---|---|" + ("---|---|" if any_instance else "")]
    for name, m in summary["methods"].items():
        counts = m["counts"]
        row = (
            f"| {name} | {counts['visible_matches']} ({counts['matches_with_depth']}) "
            f"| {_estimate(m, 'error_3d_mm', 'p50')} | {_estimate(m, 'error_3d_mm', 'p90')} "
            f"| {_estimate(m, 'error_3d_mm', 'p99')} | {_estimate(m, 'error_3d_symmetric_mm', 'p50')} "
            f"| {_estimate(m, 'error_3d_symmetric_mm', 'p90')} | {_p50_p90(m, 'pixel_error_px')} "
            f"| {_p50_p90(m, 'fraction_closer', 3, 100.0)} |"
        )
        if any_instance:
            row += f" {_p50_p90(m, 'error_3d_any_instance_mm')} | {_p50_p90(m, 'error_3d_symmetric_any_instance_mm')} |"
        lines.append(row)
    return "\n".join(lines)


def tail_table(summary: Mapping[str, Any]) -> str:
    """Markdown table of each method's tail: p99 / median of the 3D error and the share of far matches, with
    their intervals, and the verdict (:func:`long_tail_verdict`); on piles also the far matches by the
    any-instance 3D error."""
    far_mm = summary.get("far_match_mm", FAR_MATCH_M * 1000.0)
    ratio = summary.get("long_tail_ratio", LONG_TAIL_RATIO)
    any_instance = _any_instance(summary)
    header = (
        f"| method | 3D error p99 / p50 | matches > {far_mm:.0f} mm | share > {far_mm:.0f} mm (%) "
        f"| verdict (no long tail: p99 / p50 interval below {ratio:g}) |"
    )
    if any_instance:
        header += f" matches > {far_mm:.0f} mm, any instance | share > {far_mm:.0f} mm, any instance (%) |"
    lines = [header, "|---|---|---:|---|---|" + ("---:|---|" if any_instance else "")]
    for name, m in summary["methods"].items():
        tail, with_depth = m["tail"], m["counts"]["matches_with_depth"]
        row = (
            f"| {name} | {format_estimate(tail['p99_over_p50'], tail['p99_over_p50_interval'])} "
            f"| {tail['far_matches']} of {with_depth} | {_far_share_pct(tail)} | {tail['verdict']} |"
        )
        if any_instance:
            far_any = m["tail_any_instance"]
            row += f" {far_any['far_matches']} of {with_depth} | {_far_share_pct(far_any)} |"
        lines.append(row)
    return "\n".join(lines)


def far_match_table(summary: Mapping[str, Any]) -> str:
    """Markdown table of where each method's far matches land (:func:`attribute_matches`): count and share
    of its far matches per category; with sensor depth also how many are far only because of the depth
    (within the far threshold with ideal depth at the same pixel). On piles a second row per method, ``<method>,
    any instance``, counts the matches far by the any-instance 3D error (none that found the point on a twin)."""
    far_mm = summary.get("far_match_mm", FAR_MATCH_M * 1000.0)
    sensor = summary["config"]["depth"] != "ideal"
    pile = any("instance_id" in scene for scene in summary.get("scene_list", []))
    categories = [c for c in MATCH_CATEGORIES if pile or c != PILE_CATEGORY]
    header = f"| method | matches > {far_mm:.0f} mm | " + " | ".join(categories) + " |"
    if sensor:
        header += f" of these, within {far_mm:.0f} mm with ideal depth |"
    lines = [header, "|---|---:|" + "---:|" * len(categories) + ("---:|" if sensor else "")]
    for name, m in summary["methods"].items():
        by = m["far_by_category"]
        rows = [(name, m["tail"]["far_matches"], "matches")]
        if "tail_any_instance" in m:
            rows.append((f"{name}, any instance", m["tail_any_instance"]["far_matches"], "matches_any_instance"))
        for label, far, key in rows:
            cells = [f"{by[c][key]} ({100.0 * by[c][key] / far:.0f}%)" if far else "0" for c in categories]
            row = f"| {label} | {far} | " + " | ".join(cells) + " |"
            if sensor:  # only the reference instance's error was computed with ideal depth
                row += f" {sum(v['far_only_from_depth'] for v in by.values()) if key == 'matches' else '-'} |"
            lines.append(row)
    return "\n".join(lines)


def per_scene_table(summary: Mapping[str, Any]) -> str:
    """Markdown table, one row per scene (dataset seed, scene index, background): per method its far
    matches out of its matches with depth and their share."""
    far_mm = summary.get("far_match_mm", FAR_MATCH_M * 1000.0)
    methods = list(summary["methods"])
    lines = [
        "| dataset seed | scene | background | " + " | ".join(f"{m}: > {far_mm:.0f} mm" for m in methods) + " |",
        "|---:|---:|---|" + "---:|" * len(methods),
    ]
    for k, scene in enumerate(summary["scene_list"]):
        cells = []
        for name in methods:
            row = summary["methods"][name]["per_scene"][k]
            with_depth, far = row["matches_with_depth"], row["far_matches"]
            cells.append(f"{far}/{with_depth} ({100.0 * far / with_depth:.1f}%)" if with_depth else "-")
        # A pile's scene appears once per instance of the part (its reference pixels), named "scene#instance".
        name = f"{scene['scene_index']}#{scene['instance_id']}" if "instance_id" in scene else scene["scene_index"]
        lines.append(f"| {scene['dataset_seed']} | {name} | {scene['background']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def tracking_report(summary: Mapping[str, Any]) -> str:
    """All tables of a summary in Markdown: percentiles, tails, far matches by category, per scene."""
    far_mm = summary.get("far_match_mm", FAR_MATCH_M * 1000.0)
    seeds = ", ".join(str(s) for s in summary.get("dataset_seeds", []))
    return "\n\n".join(
        [
            f"{summary['scenes']} scenes of {summary['object']} (dataset seeds {seeds}, split "
            f"`{summary.get('split', '?')}`), predicted points from {summary['config']['depth']} depth. "
            f"Every figure with its {_confidence(summary)}."
            + (
                " Any instance: the error to the same point on the nearest instance of the part in the scene "
                "(descriptors of a part cannot tell its instances apart; docs/background.md, Tracking in clutter)."
                if _any_instance(summary)
                else ""
            ),
            tracking_table(summary),
            f"Tails (3D error; a match more than {far_mm:.0f} mm off is far):",
            tail_table(summary),
            "Where the far matches land (matched pixel: on the part's mask, on the wrong half along its axis or "
            "elsewhere; otherwise its point from ideal depth and the true camera pose on the table top, above it "
            "(robot, fixture) or background):",
            far_match_table(summary),
            "Per scene:",
            per_scene_table(summary),
        ]
    )


def gallery_entries(result: TrackingResult, method: str, count: int = GALLERY_COUNT) -> list[dict[str, Any]]:
    """The ``count`` worst matches of ``method`` (:func:`worst_matches`) for
    :func:`don_gym.plotting.plot_match_gallery`: both frames' RGB, the reference pixel, the match and the
    true position, and titles with the scene, the 3D error and where the match landed."""
    matches = result.matches[method]
    opened: dict[int, DONDataset] = {}
    entries = []
    for i in worst_matches(matches, count):
        d, scene = int(matches.dataset[i]), int(matches.scene[i])
        data = opened.setdefault(d, DONDataset(result.datasets[d]))
        info = next(s for s in result.scenes if s["dataset"] == d and s["scene"] == scene)
        reference_frame, frame = int(matches.reference_frame[i]), int(matches.frame[i])
        entries.append(
            {
                "reference_rgb": data.image(scene, reference_frame, "rgb"),
                "reference_uv": matches.reference_uv[i],
                "match_rgb": data.image(scene, frame, "rgb"),
                "match_uv": matches.matched_uv[i],
                "true_uv": matches.true_uv[i],
                "reference_title": f"seed {info['dataset_seed']} scene {info['scene_index']}, frame {reference_frame}",
                "match_title": f"frame {frame}: {1000.0 * matches.error_3d_m[i]:.0f} mm, "
                f"{MATCH_CATEGORIES[int(matches.category[i])]}",
            }
        )
    return entries


def write_worst_matches_figure(
    result: TrackingResult,
    methods: Sequence[str],
    path: str | Path,
    count: int = GALLERY_COUNT,
    title: str | None = None,
) -> Path:
    """The gallery of the ``count`` worst matches of each of ``methods`` (:func:`gallery_entries`), one
    column pair per method."""
    from don_gym import plotting

    unknown = [m for m in methods if m not in result.matches]
    if unknown:
        raise DonGymError(f"methods {unknown}: not in the result; expected some of {list(result.matches)}")
    return plotting.plot_match_gallery(
        {m: gallery_entries(result, m, count) for m in methods},
        path,
        title=title
        or f"Worst matches, {result.dataset_infos[0].get('object')} ({result.config.depth} depth): reference "
        "point (o, left) and best match (x, right; o: where the point is)",
    )


def write_tracking_outputs(
    result: TrackingResult, out_dir: str | Path, gallery_methods: Sequence[str] | None = None
) -> dict[str, Path]:
    """Write ``tracking.json`` (summary), ``tracking.md`` (:func:`tracking_report`), ``tracking_histogram.png``
    (the paper's stacked, normalised log-scale histogram of the 3D error, and of the 3D error modulo
    symmetry for a part with a symmetry axis), ``tracking_cdf.png`` (CDFs of 3D error, 3D error modulo
    symmetry, on piles the same to any instance, pixel error and fraction closer) and
    ``tracking_worst_matches.png`` (the worst matches of ``gallery_methods``; None: every method but the oracle;
    none, no gallery) into ``out_dir``."""
    import json

    from don_gym import plotting
    from don_gym.io import check_output_dir, write_text_atomic

    out = check_output_dir(out_dir, "out_dir")
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    paths = {"json": out / "tracking.json", "table": out / "tracking.md"}
    write_text_atomic(paths["json"], json.dumps(summary, indent=1) + "\n")
    write_text_atomic(paths["table"], tracking_report(summary) + "\n")
    matches = result.matches
    name = ", ".join(Path(d).name for d in result.datasets)
    errors_mm = {k: m.error_3d_m * 1000.0 for k, m in matches.items()}
    symmetric_mm = {k: m.symmetric_error_m * 1000.0 for k, m in matches.items()}
    has_axis = any(np.isfinite(m.symmetric_error_m).any() for m in matches.values())
    histograms = [("3D tracking error (mm)", errors_mm, 0.1)]
    if has_axis:
        histograms.append(("3D tracking error modulo symmetry (mm)", symmetric_mm, 0.1))
    depth = summary["config"]["depth"]
    paths["histogram"] = plotting.plot_error_histograms(
        histograms, out / "tracking_histogram.png", title=f"Tracking error, {summary['object']} ({name}, {depth} depth)"
    )
    panels = [
        ("3D error (mm)", errors_mm, 0.1),
        ("3D error modulo symmetry (mm)", symmetric_mm, 0.1),
        ("pixel error (px)", {k: m.pixel_error_px for k, m in matches.items()}, 0.1),
        (
            "fraction of pixels closer than the true match\n(0 drawn at 1e-5)",
            {k: m.fraction_closer for k, m in matches.items()},
            1e-5,
        ),
    ]
    if not has_axis:
        panels.pop(1)
    elif all(m.symmetric_error_any_instance_m is not None for m in matches.values()):
        panels.insert(
            2,
            (
                "3D error modulo symmetry, any instance (mm)",
                {k: m.symmetric_error_any_instance_m * 1000.0 for k, m in matches.items()},
                0.1,
            ),
        )
    paths["cdf"] = plotting.plot_cdfs(
        panels, out / "tracking_cdf.png", title=f"Tracking, {summary['object']} ({name}, {depth} depth)"
    )
    if gallery_methods is None:
        gallery_methods = [k for k in matches if result.sources[k].get("method") != "oracle"]
    if gallery_methods:
        paths["worst_matches"] = write_worst_matches_figure(result, gallery_methods, out / "tracking_worst_matches.png")
    return paths
