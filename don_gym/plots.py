"""Charts of evaluation and benchmark results (matplotlib, Agg, no display needed).

Tracking errors (:mod:`don_gym.evaluation`): the paper's normalised stacked histogram on a
log-scale error axis, and empirical CDFs of the original DON metrics. Grasp benchmark
(:mod:`don_gym.grasp_benchmark`): outcome bars like the paper's robot-experiment figure and the
depth-sensor sweep. Mesh figures live in :mod:`don_gym.plotting`.

Figures are built on ``matplotlib.figure.Figure`` (no pyplot state, safe in worker processes)
and written atomically; the format follows the file extension.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from don_gym.io import atomic_path

#: Outcome order and colours of the grasp charts (paper: fail / grasp only / grasp & place).
OUTCOMES: tuple[str, ...] = ("fail", "grasp_only", "grasp_and_place")
OUTCOME_LABELS: dict[str, str] = {"fail": "fail", "grasp_only": "grasp only", "grasp_and_place": "grasp & place"}
OUTCOME_COLORS: dict[str, str] = {"fail": "#d62728", "grasp_only": "#ffbf00", "grasp_and_place": "#2ca02c"}
#: Bins per decade of the log-scale error histogram.
BINS_PER_DECADE = 6


def _new_figure(width_in: float, height_in: float):
    # A bare Figure renders with Agg whatever pyplot's backend is, and keeps no global state.
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), dpi=110, layout="constrained")


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png")
    return path


def _finite_positive(values: np.ndarray, floor: float) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    return np.maximum(values[np.isfinite(values)], floor)


def log_bins(samples: Sequence[np.ndarray], floor: float, per_decade: int = BINS_PER_DECADE) -> np.ndarray:
    """Log-spaced bin edges covering all finite samples (values below ``floor`` count as ``floor``),
    from a whole decade to a whole decade."""
    finite = [_finite_positive(s, floor) for s in samples]
    finite = [s for s in finite if len(s)]
    if not finite:
        return np.logspace(np.log10(floor), np.log10(floor) + 1, per_decade + 1)
    low = np.floor(np.log10(min(s.min() for s in finite)))
    high = max(np.ceil(np.log10(max(s.max() for s in finite))), low + 1)
    return np.logspace(low, high, int(round((high - low) * per_decade)) + 1)


def plot_error_histograms(
    panels: Sequence[tuple[str, Mapping[str, np.ndarray], float]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """The paper's tracking-error figure: per method the normalised histogram (fractions of its
    matches, summing to 1) over log-spaced bins, stacked, with a log x axis; one panel per metric.

    ``panels``: (x label, {method: values}, floor) triples; NaNs are skipped and values below
    ``floor`` fall into the first bin.
    """
    fig = _new_figure(4.6 * len(panels) + 2.2, 3.8)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, by_method, floor) in zip(axes, panels, strict=True):
        labels = list(by_method)
        samples = [_finite_positive(by_method[k], floor) for k in labels]
        present = [(i, label, s) for i, (label, s) in enumerate(zip(labels, samples, strict=True)) if len(s)]
        if present:
            ax.hist(
                [s for _, _, s in present],
                bins=log_bins(samples, floor),
                weights=[np.full(len(s), 1.0 / len(s)) for _, _, s in present],
                stacked=True,
                color=[f"C{i % 10}" for i, _, _ in present],
                label=[f"{label} (n={len(s)})" for _, label, s in present],
                edgecolor="white",
                linewidth=0.5,
            )
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of matches (stacked per method)")
        ax.grid(True, which="major", axis="x", alpha=0.3)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _cdf(ax, values: np.ndarray, floor: float, label: str) -> None:
    values = np.sort(_finite_positive(values, floor))
    if len(values):
        ax.step(values, np.arange(1, len(values) + 1) / len(values), where="post", label=label)


def plot_cdfs(
    panels: Sequence[tuple[str, Mapping[str, np.ndarray], float]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Empirical CDFs, one panel per metric with all methods in each, log x axes.

    ``panels``: (x label, {method: values}, floor) triples; values below ``floor`` are drawn at it
    (a log axis has no zero) and NaNs are skipped.
    """
    fig = _new_figure(4.2 * len(panels) + 2.2, 3.6)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, by_method, floor) in zip(axes, panels, strict=True):
        for label, values in by_method.items():
            _cdf(ax, values, floor, label)
        ax.set_xscale("log")
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of matches")
        ax.grid(True, which="both", alpha=0.25)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_outcome_bars(
    counts_by_method: Mapping[str, Mapping[str, int]], path: str | Path, *, title: str | None = None
) -> Path:
    """One stacked bar per method with the number of episodes ending in each outcome
    (bottom to top: grasp & place, grasp only, fail), like the paper's robot-experiment figure."""
    labels = list(counts_by_method)
    fig = _new_figure(max(4.0, 1.3 * len(labels) + 1.5), 3.8)
    ax = fig.add_subplot()
    x = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for outcome in reversed(OUTCOMES):
        heights = np.array([counts_by_method[k].get(outcome, 0) for k in labels], dtype=np.float64)
        ax.bar(x, heights, 0.6, bottom=bottom, color=OUTCOME_COLORS[outcome], label=OUTCOME_LABELS[outcome])
        for xi, b, h in zip(x, bottom, heights, strict=True):
            if h > 0:
                ax.text(xi, b + h / 2, f"{int(h)}", ha="center", va="center", fontsize=8)
        bottom += heights
    ax.set_xticks(x, [k.replace("/", "/\n") for k in labels], fontsize=8)
    ax.set_ylabel("episodes")
    from matplotlib.ticker import MaxNLocator

    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_sweep(
    counts_by_sensor: Mapping[str, Mapping[str, Mapping[str, int]]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Outcomes against the depth sensor: per sensor (x, in the given order) one group of stacked
    bars, one bar per method (colour) with grasp & place solid, grasp only hatched on top and fail
    left empty, as fractions of that method's episodes.

    ``counts_by_sensor[sensor][method][outcome]`` are episode counts.
    """
    sensors = list(counts_by_sensor)
    methods = list(counts_by_sensor[sensors[0]]) if sensors else []
    fig = _new_figure(max(5.5, 1.6 * len(sensors) * max(1, len(methods)) / 2 + 2.5), 3.8)
    ax = fig.add_subplot()
    width = 0.8 / max(1, len(methods))
    for index, method in enumerate(methods):
        color = f"C{index % 10}"
        x = np.arange(len(sensors)) - 0.4 + width * (index + 0.5)
        totals = np.array([max(1, sum(counts_by_sensor[s][method].values())) for s in sensors], dtype=np.float64)
        place = np.array([counts_by_sensor[s][method].get("grasp_and_place", 0) for s in sensors]) / totals
        only = np.array([counts_by_sensor[s][method].get("grasp_only", 0) for s in sensors]) / totals
        ax.bar(x, place, width * 0.9, color=color, label=f"{method}")
        ax.bar(x, only, width * 0.9, bottom=place, color="white", edgecolor=color, hatch="///", linewidth=0.8)
    ax.set_xticks(np.arange(len(sensors)), sensors)
    ax.set_xlabel("depth sensor (ideal -> D435)")
    ax.set_ylabel("fraction of episodes")
    ax.set_ylim(0.0, 1.05)
    ax.grid(True, axis="y", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    from matplotlib.patches import Patch

    handles.append(Patch(facecolor="white", edgecolor="gray", hatch="///"))
    labels.append("grasp only (on top of grasp & place)")
    ax.legend(handles, labels, fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)
