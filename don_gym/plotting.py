"""Every figure of don_gym: descriptor fields on meshes, tracking errors, grasp outcomes, loss and learning curves.

Pure functions, arrays in and a file out, built on ``matplotlib.figure.Figure`` with the Agg canvas
(no pyplot state, no display, safe in worker processes), written atomically; the format follows the
file extension. matplotlib is imported inside the functions so that importing this module stays light.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh

from don_gym.errors import DonGymError
from don_gym.io import atomic_path
from don_gym.objects import ObjectModel

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Figure formats matplotlib writes from the file extension.
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
#: Default views (elevation, azimuth) in degrees: one from above one end, one from below the other.
DEFAULT_VIEWS = ((25.0, -60.0), (-25.0, 120.0))
#: Labels and colours of the grasp outcomes (paper: fail / grasp only / grasp & place).
OUTCOME_LABELS: dict[str, str] = {"fail": "fail", "grasp_only": "grasp only", "grasp_and_place": "grasp & place"}
OUTCOME_COLORS: dict[str, str] = {"fail": "#d62728", "grasp_only": "#ffbf00", "grasp_and_place": "#2ca02c"}
#: Bins per decade of the log-scale error histogram.
BINS_PER_DECADE = 6


def _new_figure(width_in: float, height_in: float, *, dpi: float | None = None, layout: str | None = None) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=dpi, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | Path, dpi: float | str = "figure") -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=dpi)
    return path


# --- descriptor fields -------------------------------------------------------------------------------


def _view_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector from the scene towards a matplotlib 3-D camera at (elevation, azimuth)."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def plot_descriptor_field(
    mesh: trimesh.Trimesh | ObjectModel,
    vertex_descriptors: np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    dimension_labels: Sequence[str] | None = None,
    views: Sequence[tuple[float, float]] = DEFAULT_VIEWS,
    dpi: int = 110,
) -> Path:
    """Write a figure of ``mesh`` coloured by its descriptors, like the bunny and torus figures of
    Kupcsik et al. (AAAI 2021); returns the path.

    Columns: each descriptor dimension (hot colour map, 0 black to 1 white) and the RGB composite of
    dimensions 1-3 (missing ones are 0). Rows: ``views`` as (elevation, azimuth) in degrees, with
    z up. Each face takes the mean of its vertices' descriptors, shaded by a Lambertian light
    near the camera; faces turned away from the camera are culled on closed meshes (they are
    hidden anyway, and fewer polygons keep matplotlib's depth sorting fast and correct).

    Args:
        mesh: the mesh the descriptors belong to (N vertices).
        vertex_descriptors: (N, D) values in [0, 1].
        path: output file; the format follows the extension (``PLOT_SUFFIXES``).
        title: figure title.
        dimension_labels: D column titles (default "descriptor 1", ...).
        views: camera (elevation, azimuth) pairs in degrees, one row each.
        dpi: resolution.
    """
    import matplotlib
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    path = Path(path)
    if path.suffix.lower() not in PLOT_SUFFIXES:
        raise DonGymError(f"plot file {str(path)!r}: expected one of the extensions {', '.join(PLOT_SUFFIXES)}")
    tm = mesh.mesh if isinstance(mesh, ObjectModel) else mesh
    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces)
    values = np.asarray(vertex_descriptors, dtype=np.float64)
    if values.ndim != 2 or len(values) != len(vertices):
        raise DonGymError(f"vertex_descriptors {values.shape}: expected ({len(vertices)}, D) for this mesh")
    dim = values.shape[1]
    labels = list(dimension_labels) if dimension_labels is not None else [f"descriptor {i + 1}" for i in range(dim)]

    face_values = np.clip(values[faces].mean(axis=1), 0.0, 1.0)  # (F, D)
    rgb = np.zeros((len(faces), 3))
    rgb[:, : min(dim, 3)] = face_values[:, :3]
    hot = matplotlib.colormaps["hot"]
    panels = [(labels[d], hot(face_values[:, d])[:, :3]) for d in range(dim)]
    panels.append(("RGB = descriptors " + "-".join(str(i + 1) for i in range(min(dim, 3))), rgb))

    triangles = vertices[faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    closed = bool(tm.is_watertight)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    center, half = (low + high) / 2, (high - low).max() / 2

    fig = _new_figure(3.0 * len(panels), 3.0 * len(views) + (0.4 if title else 0.0), dpi=dpi)
    for row, (elevation, azimuth) in enumerate(views):
        toward_camera = _view_direction(elevation, azimuth)
        # Light from the camera, a little above and to the left, so that shading shows the shape.
        light = toward_camera + 0.5 * _view_direction(elevation + 60.0, azimuth - 45.0)
        light /= np.linalg.norm(light)
        facing = normals @ toward_camera
        visible = facing > -1e-9 if closed else np.ones(len(faces), dtype=bool)
        lambert = np.abs(normals @ light) if not closed else np.clip(normals @ light, 0.0, 1.0)
        shade = (0.35 + 0.65 * lambert)[visible, None]
        for col, (label, colors) in enumerate(panels):
            ax = fig.add_subplot(len(views), len(panels), row * len(panels) + col + 1, projection="3d")
            shaded = colors[visible] * shade
            # Edges in the face colour hide the hairline seams antialiasing leaves between faces.
            collection = Poly3DCollection(triangles[visible], facecolors=shaded, edgecolors=shaded, linewidths=0.3)
            ax.add_collection3d(collection)
            for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center, strict=True):
                setter(c - half, c + half)
            ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.25)  # equal scale on all axes (limits are a cube)
            ax.view_init(elev=elevation, azim=azimuth)
            ax.set_axis_off()
            if row == 0:
                ax.set_title(label, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92 if title else 0.95, wspace=0.0, hspace=0.0)
    return _save(fig, path, dpi=dpi)


# --- tracking errors (don_gym.evaluation) ------------------------------------------------------------


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
    fig = _new_figure(4.6 * len(panels) + 2.2, 3.8, dpi=110, layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (xlabel, by_method, floor) in zip(axes, panels, strict=True):
        samples = [by_method[k] for k in by_method]
        _stacked_histogram(ax, by_method, floor, log_bins(samples, floor), list(by_method))
        ax.set_xlabel(xlabel)
    if axes[-1].get_legend_handles_labels()[0]:  # no method with a finite value draws nothing to label
        axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _stacked_histogram(
    ax: Axes, by_method: Mapping[str, np.ndarray], floor: float, bins: np.ndarray, colour_order: Sequence[str]
) -> None:
    """Per method the normalised histogram over ``bins``, stacked, log x axis; a method's colour is
    its place in ``colour_order``, so that it keeps its colour across panels."""
    present = [(label, _finite_positive(values, floor)) for label, values in by_method.items()]
    present = [(label, s) for label, s in present if len(s)]
    if present:
        ax.hist(
            [s for _, s in present],
            bins=bins,
            weights=[np.full(len(s), 1.0 / len(s)) for _, s in present],
            stacked=True,
            color=[f"C{list(colour_order).index(label) % 10}" for label, _ in present],
            label=[f"{label} (n={len(s)})" for label, s in present],
            edgecolor="white",
            linewidth=0.5,
        )
    ax.set_xscale("log")
    ax.set_ylabel("fraction of matches (stacked per method)")
    ax.grid(True, which="major", axis="x", alpha=0.3)


def plot_tracking_error_histograms(
    errors_by_object: Mapping[str, Mapping[str, np.ndarray]],
    path: str | Path,
    *,
    xlabel: str = "3D tracking error (mm)",
    floor: float = 0.1,
    title: str | None = None,
) -> Path:
    """The paper's tracking figure for several objects in one picture: one panel per object (side by side,
    same log-spaced bins and axes), in each the normalised error histogram of every method, stacked.

    ``errors_by_object``: {object: {method: errors}}; a method keeps its colour in every panel, NaNs are
    skipped and values below ``floor`` fall into the first bin.
    """
    objects = list(errors_by_object)
    if not objects:
        raise DonGymError("no objects to plot; expected {object: {method: errors}}")
    methods = list(dict.fromkeys(m for by_method in errors_by_object.values() for m in by_method))
    bins = log_bins([v for by_method in errors_by_object.values() for v in by_method.values()], floor)
    fig = _new_figure(4.4 * len(objects) + 0.6, 4.0, dpi=110, layout="constrained")
    axes = fig.subplots(1, len(objects), squeeze=False, sharex=True, sharey=True)[0]
    for ax, name in zip(axes, objects, strict=True):
        _stacked_histogram(ax, errors_by_object[name], floor, bins, methods)
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.legend(fontsize=7, loc="upper right")
        ax.label_outer()
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def _cdf(ax: Axes, values: np.ndarray, floor: float, label: str) -> None:
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
    fig = _new_figure(4.2 * len(panels) + 2.2, 3.6, dpi=110, layout="constrained")
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


def plot_match_gallery(
    entries_by_method: Mapping[str, Sequence[Mapping[str, Any]]],
    path: str | Path,
    *,
    title: str | None = None,
    panel_width_in: float = 2.4,
    dpi: int = 80,
) -> Path:
    """Matches to look at (a method's worst, say): per method a pair of columns, per match a row with the
    reference frame, the reference pixel marked (o), beside the frame of the match, the best match
    marked (x) and, when given, the point's true position (o).

    ``entries_by_method``: {method: entries}, each a mapping with ``reference_rgb`` and ``match_rgb``
    ((H, W, 3) uint8), ``reference_uv`` and ``match_uv`` ((2,) pixel ``(u, v)``), optionally ``true_uv``
    (2,), ``reference_title`` and ``match_title``. Methods with fewer entries leave their rows empty.
    """
    methods = list(entries_by_method)
    if not methods:
        raise DonGymError("no methods to show; expected {method: [match entries]}")
    rows = max(1, max(len(entries) for entries in entries_by_method.values()))
    shapes = [np.asarray(e["match_rgb"]).shape for entries in entries_by_method.values() for e in entries]
    aspect = shapes[0][0] / shapes[0][1] if shapes else 0.75
    fig = _new_figure(
        2 * panel_width_in * len(methods), rows * panel_width_in * aspect + 0.9, dpi=dpi, layout="constrained"
    )
    axes = fig.subplots(rows, 2 * len(methods), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    marker = {"markersize": 11, "markeredgewidth": 2.0, "linestyle": "none"}
    for column, method in enumerate(methods):
        axes[0, 2 * column].set_title(method, fontsize=9, loc="left", fontweight="bold")
        for row, entry in enumerate(entries_by_method[method]):
            reference_ax, match_ax = axes[row, 2 * column], axes[row, 2 * column + 1]
            reference_ax.imshow(entry["reference_rgb"], interpolation="bilinear")
            u, v = np.asarray(entry["reference_uv"], dtype=np.float64)
            reference_ax.plot([u], [v], "o", markerfacecolor="none", markeredgecolor="lime", **marker)
            match_ax.imshow(entry["match_rgb"], interpolation="bilinear")
            if entry.get("true_uv") is not None:
                u, v = np.asarray(entry["true_uv"], dtype=np.float64)
                match_ax.plot([u], [v], "o", markerfacecolor="none", markeredgecolor="lime", **marker)
            u, v = np.asarray(entry["match_uv"], dtype=np.float64)
            match_ax.plot([u], [v], "x", color="red", **marker)
            for ax, key in ((reference_ax, "reference_title"), (match_ax, "match_title")):
                if entry.get(key):
                    # Titles below the images, so that the method's name above the first row stays readable.
                    ax.set_xlabel(str(entry[key]), fontsize=7)
                    ax.set_axis_on()
                    ax.set_xticks([])
                    ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_image_grid(
    images: Mapping[str, Mapping[str, np.ndarray]],
    path: str | Path,
    *,
    title: str | None = None,
    panel_width_in: float = 2.6,
    dpi: int = 100,
) -> Path:
    """A grid of images: one row per key of ``images`` (its name on the left), one column per key of each
    row's mapping (the column names of the first row on top). Each image is (H, W, 3) uint8, or float in
    [0, 1]; all of one shape."""
    rows = list(images)
    if not rows or not images[rows[0]]:
        raise DonGymError("no images to show; expected {row: {column: image}}")
    columns = list(images[rows[0]])
    height, width = np.asarray(next(iter(images[rows[0]].values()))).shape[:2]
    fig = _new_figure(
        panel_width_in * len(columns) + 0.4,
        panel_width_in * height / width * len(rows) + (0.5 if title else 0.3),
        dpi=dpi,
        layout="constrained",
    )
    axes = fig.subplots(len(rows), len(columns), squeeze=False)
    for r, row in enumerate(rows):
        for c, column in enumerate(columns):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            if column in images[row]:
                ax.imshow(images[row][column], interpolation="nearest")
            if r == 0:
                ax.set_title(column, fontsize=9)
            if c == 0:
                ax.set_ylabel(row, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


# --- grasp outcomes (don_gym.evaluation.grasp_benchmark) --------------------------------------------------------


def plot_outcome_bars(
    counts_by_method: Mapping[str, Mapping[str, int]],
    path: str | Path,
    outcomes: Sequence[str],
    *,
    title: str | None = None,
) -> Path:
    """One stacked bar per method with the number of episodes ending in each of ``outcomes`` (worst first, as
    :data:`don_gym.sim.task.OUTCOMES`; stacked best at the bottom), like the paper's robot-experiment figure."""
    from matplotlib.ticker import MaxNLocator

    labels = list(counts_by_method)
    fig = _new_figure(max(4.0, 1.3 * len(labels) + 1.5), 3.8, dpi=110, layout="constrained")
    ax = fig.add_subplot()
    x = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for outcome in reversed(outcomes):
        heights = np.array([counts_by_method[k].get(outcome, 0) for k in labels], dtype=np.float64)
        ax.bar(x, heights, 0.6, bottom=bottom, color=OUTCOME_COLORS[outcome], label=OUTCOME_LABELS[outcome])
        for xi, b, h in zip(x, bottom, heights, strict=True):
            if h > 0:
                ax.text(xi, b + h / 2, f"{int(h)}", ha="center", va="center", fontsize=8)
        bottom += heights
    ax.set_xticks(x, [k.replace("/", "/\n") for k in labels], fontsize=8)
    ax.set_ylabel("episodes")
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
    from matplotlib.patches import Patch

    sensors = list(counts_by_sensor)
    methods = list(counts_by_sensor[sensors[0]]) if sensors else []
    fig = _new_figure(max(5.5, 1.6 * len(sensors) * max(1, len(methods)) / 2 + 2.5), 3.8, dpi=110, layout="constrained")
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
    handles.append(Patch(facecolor="white", edgecolor="gray", hatch="///"))
    labels.append("grasp only (on top of grasp & place)")
    ax.legend(handles, labels, fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_rate_bars(
    rates_by_method: Mapping[str, Mapping[str, tuple[float, float, float]]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Rates side by side: per rate (x, a group) one bar per method (colour) with its interval as an error bar.

    ``rates_by_method[method][rate name] = (rate, low, high)``, fractions in [0, 1] (NaN: no trials, no bar).
    """
    methods = list(rates_by_method)
    names = list(rates_by_method[methods[0]]) if methods else []
    fig = _new_figure(max(5.5, 1.2 * len(names) * max(1, len(methods)) / 2 + 2.5), 3.8, dpi=110, layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / max(1, len(methods))
    for index, method in enumerate(methods):
        x = np.arange(len(names)) - 0.4 + width * (index + 0.5)
        values = np.array([rates_by_method[method][n] for n in names], dtype=np.float64).reshape(-1, 3)
        rate = values[:, 0]
        shown = np.isfinite(rate)
        errors = np.abs(np.stack([rate - values[:, 1], values[:, 2] - rate]))
        ax.bar(x[shown], rate[shown], width * 0.9, color=f"C{index % 10}", label=method)
        ax.errorbar(x[shown], rate[shown], yerr=errors[:, shown], fmt="none", ecolor="black", capsize=2, linewidth=0.8)
    ax.set_xticks(np.arange(len(names)), [n.replace(" (", "\n(") for n in names], fontsize=8)
    ax.set_ylabel("rate (95% Wilson interval)")
    ax.set_ylim(0.0, 1.05)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def plot_episode_frames(
    frames: Sequence[Mapping[str, Any]],
    path: str | Path,
    *,
    title: str | None = None,
    columns: int = 3,
    panel_width_in: float = 3.2,
) -> Path:
    """Frames of one episode side by side, each with the grasp about to be made drawn on it: the two finger pads
    (squares, joined by the line they close along) and the believed +axis (an arrow from the grasp point).

    ``frames``: mappings with ``rgb`` ((H, W, 3) uint8), optionally ``fingers_uv`` ((2, 2) pixels of the two
    pads), ``axis_uv`` ((2, 2) pixels: grasp point, a point along the believed +axis) and ``title``.
    """
    if not frames:
        raise DonGymError("no frames to show; expected at least one {'rgb': image}")
    rows = -(-len(frames) // columns)
    shape = np.asarray(frames[0]["rgb"]).shape
    aspect = shape[0] / shape[1]
    fig = _new_figure(
        columns * panel_width_in, rows * (panel_width_in * aspect + 0.3) + 0.4, dpi=100, layout="constrained"
    )
    axes = fig.subplots(rows, columns, squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for ax, frame in zip(axes.ravel(), frames, strict=False):
        ax.imshow(frame["rgb"], interpolation="bilinear")
        if frame.get("fingers_uv") is not None:
            fingers = np.asarray(frame["fingers_uv"], dtype=np.float64)
            ax.plot(fingers[:, 0], fingers[:, 1], "-", color="yellow", linewidth=1.2)
            ax.plot(fingers[:, 0], fingers[:, 1], "s", markersize=6, markerfacecolor="none", markeredgecolor="yellow")
        if frame.get("axis_uv") is not None:
            (u0, v0), (u1, v1) = np.asarray(frame["axis_uv"], dtype=np.float64)
            ax.annotate("", xy=(u1, v1), xytext=(u0, v0), arrowprops={"arrowstyle": "->", "color": "red", "lw": 1.5})
        if frame.get("title"):
            ax.set_title(str(frame["title"]), fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    return _save(fig, path)


# --- training (don_gym.learning.train, don_gym.agents.rl) -----------------------------------------------------


def plot_loss_curve(rows: Sequence[Mapping[str, Any]], path: str | Path, title: str) -> Path:
    """Loss per step (light) and its moving average (dark), log scale; ``rows`` are the loss CSV's
    rows with at least ``step`` and ``loss`` (numbers or their strings)."""
    steps = np.array([int(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    fig = _new_figure(6, 3.5, dpi=120)
    ax = fig.add_subplot()
    ax.plot(steps, loss, color="tab:blue", alpha=0.3, lw=0.8, label="loss per step")
    window = max(1, len(loss) // 50)
    if len(loss) >= window:
        smooth = np.convolve(loss, np.ones(window) / window, mode="valid")
        ax.plot(steps[window - 1 :], smooth, color="tab:blue", lw=1.8, label=f"moving average ({window} steps)")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_learning_curve(
    curves: Sequence[tuple[str, tuple[np.ndarray, np.ndarray, np.ndarray]]],
    path: str | Path,
    window: int,
    title: str,
    reference_lines: Sequence[tuple[str, float, float]] = (),
) -> Path:
    """Success rate and mean return of RL training episodes against env steps, side by side.

    ``curves``: (label, (env steps, success rate, mean return)) with the rates rolled over the last
    ``window`` episodes (``LearningCurve.rolling(window)`` of :mod:`don_gym.agents.rl`);
    ``reference_lines``: (label, success rate, mean return) of baselines drawn as dashed lines.
    """
    entries = len(curves) + len(reference_lines)
    # Long labels (the baselines' names) fit two to a row; one legend under both plots hides no line.
    columns = 2 if max((len(label) for label, *_ in [*curves, *reference_lines]), default=0) > 35 else 3
    rows = -(-entries // columns)
    fig = _new_figure(10, 3.6 + 0.22 * rows)
    ax_success, ax_return = fig.subplots(1, 2)
    for label, (steps, success, returns) in curves:
        ax_success.plot(steps, success, label=label)
        ax_return.plot(steps, returns, label=label)
    # Reference lines take the colours the curves leave free, then repeat them with another dash pattern,
    # so that no baseline shares a curve's colour.
    free = max(1, 10 - len(curves))
    for k, (label, success_rate, mean_return) in enumerate(reference_lines):
        style = {"linestyle": ("--", ":", "-.")[(k // free) % 3], "color": f"C{len(curves) + k % free}"}
        ax_success.axhline(success_rate, label=label, **style)
        ax_return.axhline(mean_return, label=label, **style)
    ax_success.set(xlabel="env steps", ylabel=f"success rate (last {window} episodes)", ylim=(-0.02, 1.02))
    ax_return.set(xlabel="env steps", ylabel=f"episode return (mean of last {window})")
    handles, labels = ax_success.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=columns, fontsize=8, frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0.0, min(0.6, 0.22 * rows / (3.6 + 0.22 * rows) + 0.02), 1.0, 1.0))
    return _save(fig, path, dpi=110)


def plot_pose_recalls(
    curves: Mapping[str, Mapping[str, Any]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Recall against threshold of 6D pose estimates, BOP's two panels: MSSD (fraction of the diameter) and
    MSPD (px at 640 px width).

    ``curves``: {method: {"mssd_thresholds", "mssd_recall", "mspd_thresholds_px", "mspd_recall", "ar"}} as
    :func:`don_gym.evaluation.pose_metrics.pose_recalls` gives them; the legend names each method with its AR.
    """
    if not curves:
        raise DonGymError("plot_pose_recalls: no method to draw")
    fig = _new_figure(10.0, 3.8, dpi=110, layout="constrained")
    axes = fig.subplots(1, 2)
    panels = (
        ("mssd_thresholds", "mssd_recall", "MSSD threshold (fraction of the diameter)"),
        ("mspd_thresholds_px", "mspd_recall", "MSPD threshold (px at 640 px width)"),
    )
    for ax, (x_key, y_key, xlabel) in zip(axes, panels, strict=True):
        for method, curve in curves.items():
            ar = curve.get("ar")
            label = method if ar is None or not np.isfinite(ar) else f"{method} (AR {ar:.2f})"
            ax.plot(curve[x_key], curve[y_key], marker="o", markersize=3, label=label)
        ax.set_ylim(0.0, 1.02)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("recall")
        ax.grid(True, alpha=0.25)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_success_against_demonstrations(
    rates: Mapping[str, Sequence[tuple[int, float, float, float]]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Success rate against the number of demonstrations, one line per input: ``rates[input]`` lists
    ``(demonstrations, rate, low, high)`` with the rate's interval, all in [0, 1]; the x axis is logarithmic."""
    fig = _new_figure(6.0, 3.8, dpi=110, layout="constrained")
    ax = fig.add_subplot()
    for index, (name, points) in enumerate(rates.items()):
        n, rate, low, high = (np.array(v, dtype=np.float64) for v in zip(*sorted(points), strict=True))
        ax.plot(n, rate, "o-", color=f"C{index % 10}", label=name)
        ax.fill_between(n, low, high, color=f"C{index % 10}", alpha=0.15)
    ax.set_xscale("log")
    ticks = sorted({int(n) for points in rates.values() for n, *_ in points})
    ax.set_xticks(ticks, [str(n) for n in ticks])
    ax.minorticks_off()
    ax.set_xlabel("demonstrations")
    ax.set_ylabel("success rate (95% Wilson interval)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)
