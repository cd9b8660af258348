"""Figures of descriptor fields on meshes (matplotlib, Agg backend, no display needed).

:func:`plot_descriptor_field` draws the mesh coloured by each descriptor dimension with the hot
colour map and by the RGB composite of the first three dimensions, from two opposite views,
like the bunny and torus figures of Kupcsik et al. (AAAI 2021).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from don_gym.errors import DonGymError
from don_gym.io import atomic_path
from don_gym.objects import ObjectModel

#: Figure formats matplotlib writes from the file extension.
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
#: Default views (elevation, azimuth) in degrees: one from above one end, one from below the other.
DEFAULT_VIEWS = ((25.0, -60.0), (-25.0, 120.0))


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
    """Write a figure of ``mesh`` coloured by its descriptors; returns the path.

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

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
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

    fig = plt.figure(figsize=(3.0 * len(panels), 3.0 * len(views) + (0.4 if title else 0.0)), dpi=dpi)
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return path
