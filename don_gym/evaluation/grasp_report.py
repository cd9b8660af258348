"""The grasp benchmark's report: outcome, miss and sweep tables of a
:class:`~don_gym.evaluation.grasp_benchmark.GraspBenchmarkResult`, its files and figures, and the paper's targets.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from don_gym.errors import DonGymError
from don_gym.evaluation.grasp_benchmark import (
    ACCURATE_GRASP_M,
    ACCURATE_GRASP_YAW_RAD,
    POSE_SETS,
    GraspBenchmarkConfig,
    GraspBenchmarkResult,
)
from don_gym.sim.task import OUTCOMES

__all__ = ["check_targets", "miss_table", "outcome_table", "sweep_table", "write_grasp_outputs"]


def _median_text(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _summary_of(result: GraspBenchmarkResult, poses: str) -> dict[str, Any]:
    if poses not in POSE_SETS:
        raise DonGymError(f"poses={poses!r}: expected one of {list(POSE_SETS)}")
    summary = result.summary()
    if poses == "random" and "random_pose_results" not in summary:
        raise DonGymError("this result has no random poses (GraspBenchmarkConfig.random_poses=0)")
    return summary["results" if poses == "fixed" else "random_pose_results"]


def _backgrounds_text(config: GraspBenchmarkConfig) -> str:
    """How the episodes' backgrounds were chosen (nothing for the plain table)."""
    if config.backgrounds == "plain":
        return ""
    return f", background `{config.backgrounds}` (a new backdrop and cradle colour per episode, from its seed)"


def _poses_text(result: GraspBenchmarkResult, poses: str) -> str:
    if poses == "fixed":
        text = f"{len(result.config.poses)} fixed poses x {result.config.repeats} repeats"
    else:
        text = f"{result.config.random_poses} random poses seeded from the benchmark seed, 1 episode each"
    return text + _backgrounds_text(result.config)


def outcome_table(result: GraspBenchmarkResult, sensor: str | None = None, poses: str = "fixed") -> str:
    """Markdown: per method the outcome counts for one sensor (default: the headline sensor) at the
    fixed or the random poses, each rate with its 95% Wilson interval."""
    from don_gym.stats import format_rate

    sensor = result.headline_sensor if sensor is None else sensor
    summary = _summary_of(result, poses)[sensor]
    total = result.episodes_per_cell(poses)
    width, height = result.config.image_size
    lines = [
        f"Sensor `{sensor}`, {width}x{height} wrist camera, {_poses_text(result, poses)} = {total} episodes "
        "per method; rates with their 95% Wilson interval.",
        "",
        "| method | grasp & place | grasp only | fail | grasped | flipped +axis "
        "| median grasp position error (mm) | median yaw error (deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method, s in summary.items():
        c = s["counts"]
        rates = [format_rate(n, total) for n in (c["grasp_and_place"], c["grasp_only"], c["fail"], s["grasped"])]
        lines.append(
            f"| {method} | " + " | ".join(rates) + f" | {s['flipped']} | {_median_text(s['median_position_error_mm'])} "
            f"| {_median_text(s['median_yaw_error_deg'])} |"
        )
    return "\n".join(lines)


def miss_table(result: GraspBenchmarkResult) -> str:
    """Markdown: per method, over every sensor and pose, the episodes that did not end placed, by where
    they went wrong: no grasp (outcome ``"fail"``, as in :func:`outcome_table`), a grasp off the true
    grasp point or +axis by more than :data:`ACCURATE_GRASP_M` / :data:`ACCURATE_GRASP_YAW_RAD` (the
    descriptors or the agent; flips included), or an accurate grasp whose placement failed (the part
    tilted or slid in the hand or the cradle: the simulated placement, whatever the descriptors)."""
    lines = [
        f"Episodes not placed, by cause, over every sensor and pose ({len(result.episodes)} episodes"
        + ("" if result.config.backgrounds == "plain" else f", background `{result.config.backgrounds}`")
        + "); "
        f"an accurate grasp is within {ACCURATE_GRASP_M * 1000:g} mm of the true grasp point and "
        f"{math.degrees(ACCURATE_GRASP_YAW_RAD):g} deg of the true +axis.",
        "",
        "| method | episodes | not placed | no grasp | grasp off | accurate grasp, placement failed |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method in result.config.methods:
        episodes = [e for e in result.episodes if e["method"] == method]
        missed = sum(e["outcome"] != "grasp_and_place" for e in episodes)
        failed = sum(e["outcome"] == "fail" for e in episodes)
        accurate = sum(
            e["outcome"] == "grasp_only"
            and e["position_error_m"] is not None
            and e["position_error_m"] <= ACCURATE_GRASP_M
            and e["yaw_error_rad"] <= ACCURATE_GRASP_YAW_RAD
            for e in episodes
        )
        lines.append(
            f"| {method} | {len(episodes)} | {missed} | {failed} | {missed - failed - accurate} | {accurate} |"
        )
    return "\n".join(lines)


def sweep_table(result: GraspBenchmarkResult, poses: str = "fixed") -> str:
    """Markdown: per method and sensor, ``grasp & place / grasped`` out of the episodes per cell at the
    fixed or the random poses, each with its 95% Wilson interval."""
    from don_gym.stats import format_interval

    summary = _summary_of(result, poses)
    sensors = list(result.config.sensors)
    total = result.episodes_per_cell(poses)
    lines = [
        f"Cells: grasp & place / grasped, out of {total} episodes ({_poses_text(result, poses)}), "
        "each with its 95% Wilson interval.",
        "",
        "| method | " + " | ".join(f"`{s}`" for s in sensors) + " |",
        "|---|" + "---|" * len(sensors),
    ]
    for method in result.config.methods:
        cells = []
        for sensor in sensors:
            place, grasped = summary[sensor][method]["counts"]["grasp_and_place"], summary[sensor][method]["grasped"]
            cells.append(f"{place} ({format_interval(place, total)}) / {grasped} ({format_interval(grasped, total)})")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_grasp_outputs(result: GraspBenchmarkResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``grasp_episodes.json`` (summary and every episode), ``grasp.md`` (tables),
    ``grasp_outcomes.png`` (headline sensor, one bar per method), with several sensors
    ``grasp_sweep.png``, and with random poses ``grasp_outcomes_random.png``."""
    import json

    from don_gym import plotting
    from don_gym.io import check_output_dir, write_text_atomic

    out = check_output_dir(out_dir, "out_dir")
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "grasp_episodes.json", "table": out / "grasp.md"}
    write_text_atomic(
        paths["json"], json.dumps({"summary": result.summary(), "episodes": result.episodes}, indent=1) + "\n"
    )
    tables = "### Outcomes\n\n" + outcome_table(result)
    if len(result.config.sensors) > 1:
        tables += "\n\n### Depth-sensor sweep\n\n" + sweep_table(result)
    if result.config.random_poses:
        tables += "\n\n### Outcomes at random poses\n\n" + outcome_table(result, poses="random")
        if len(result.config.sensors) > 1:
            tables += "\n\n### Depth-sensor sweep at random poses\n\n" + sweep_table(result, poses="random")
    write_text_atomic(paths["table"], tables + "\n")
    sensor = result.headline_sensor
    paths["outcomes"] = plotting.plot_outcome_bars(
        result.counts(sensor),
        out / "grasp_outcomes.png",
        OUTCOMES,
        title=f"{result.config.object}: {len(result.config.poses)} poses x {result.config.repeats} repeats, "
        f"sensor {sensor}"
        + ("" if result.config.backgrounds == "plain" else f", {result.config.backgrounds} backgrounds"),
    )
    if len(result.config.sensors) > 1:
        paths["sweep"] = plotting.plot_sweep(
            {s: result.counts(s) for s in result.config.sensors},
            out / "grasp_sweep.png",
            title=f"{result.config.object}: depth-sensor sweep, {len(result.config.poses)} poses x "
            f"{result.config.repeats} repeats",
        )
    if result.config.random_poses:
        paths["outcomes_random"] = plotting.plot_outcome_bars(
            result.counts(sensor, "random"),
            out / "grasp_outcomes_random.png",
            OUTCOMES,
            title=f"{result.config.object}: {result.config.random_poses} random poses, sensor {sensor}",
        )
    return paths


def check_targets(result: GraspBenchmarkResult) -> list[str]:
    """Lines comparing the headline counts with the issue's targets (per 8 poses, scaled by repeats):
    oracle 8/8 grasp & place; supervised networks 8/8 grasped and >= 7/8 grasp & place."""
    summary = result.summary()["results"][result.headline_sensor]
    per_pose_set = result.config.repeats * len(result.config.poses) / 8.0
    lines = []
    for method, s in summary.items():
        kind = result.method_info.get(method, {}).get("method", method)
        if kind == "oracle":
            want_place, want_grasp = 8, 8
        elif kind in ("supervised", "supervised-edge", "supervised-mask"):
            want_place, want_grasp = 7, 8
        else:
            continue
        need_place, need_grasp = want_place * per_pose_set, want_grasp * per_pose_set
        place, grasped = s["counts"]["grasp_and_place"], s["grasped"]
        ok = place >= need_place and grasped >= need_grasp
        lines.append(
            f"{method}: grasp & place {place} (target >= {need_place:g}), grasped {grasped} "
            f"(target >= {need_grasp:g}): {'met' if ok else 'MISSED'}"
        )
    return lines
