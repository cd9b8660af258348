"""Reading and writing the files of the BOP format (Benchmark for 6D Object Pose estimation).

Plain functions, arrays in and out, in BOP's own units: millimetres for model points, translations
and depth (times a per-image ``depth_scale``), pixels for ``cam_K``, seconds for run times. What don_gym
does with them lives in :mod:`don_gym.data.import_bop` (import into a dataset) and :mod:`don_gym.data.export`;
this module only knows the files. Every reader raises :class:`~don_gym.errors.DatasetError` (or
:class:`~don_gym.errors.MeshError` for a model) naming the file and what was expected; every writer
writes to a temporary name and renames, so no half-written file is left under the final name.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.errors import DatasetError
from don_gym.io import write_text_atomic

__all__ = [
    "GT_INFO_KEYS",
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_PIXELS",
    "POSE_RESULTS_HEADER",
    "bbox_of",
    "find_image",
    "gt_info",
    "image_size",
    "mask_path",
    "model_diameter",
    "models_info_entry",
    "models_info_json",
    "read_bop_json",
    "read_color_image",
    "read_depth_mm",
    "read_mask",
    "read_models_info",
    "read_ply_model",
    "read_pose_results",
    "read_scene_camera",
    "read_scene_gt",
    "read_scene_gt_info",
    "write_bop_json",
    "write_color_image",
    "write_depth_mm",
    "write_mask",
    "write_models_info",
    "write_ply_model",
    "write_pose_results",
    "write_scene_camera",
    "write_scene_gt",
    "write_scene_gt_info",
]

#: Header line of a BOP results file (the BOP Challenge's 6D localization format, "bop19").
POSE_RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"


# --- pose results (CSV) ---------------------------------------------------------------------


def _number_text(value: float) -> str:
    return repr(float(value))


def write_pose_results(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> None:
    """Write pose estimates as a BOP results file at ``path`` (atomically).

    Each row holds ``scene_id``, ``im_id``, ``obj_id`` (ints), ``score`` (float), ``R`` (3x3 rotation of the
    model in the camera frame, written row-major), ``t`` (3 numbers, the model origin in the camera frame in
    millimetres) and ``time`` (seconds spent on the image; -1 when unknown, BOP's convention).
    """
    lines = [POSE_RESULTS_HEADER]
    for number, row in enumerate(rows):
        try:
            R = np.asarray(row["R"], dtype=np.float64).reshape(9)
            t = np.asarray(row["t"], dtype=np.float64).reshape(3)
            ids = [int(row[k]) for k in ("scene_id", "im_id", "obj_id")]
            score, seconds = float(row["score"]), float(row.get("time", -1.0))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"pose result row {number}: {exc}; expected scene_id, im_id, obj_id, score, R, t") from exc
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and math.isfinite(score)):
            raise ValueError(f"pose result row {number}: R, t and score must be finite")
        lines.append(
            ",".join(
                [*(str(i) for i in ids), _number_text(score), " ".join(_number_text(v) for v in R),
                 " ".join(_number_text(v) for v in t), _number_text(seconds)]
            )
        )  # fmt: skip
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_pose_results(path: str | Path) -> list[dict[str, Any]]:
    """The rows of BOP results file ``path``: dicts with int ``scene_id``, ``im_id``, ``obj_id``, float
    ``score``, ``R`` (3, 3), ``t`` (3,) in millimetres and ``time`` in seconds. The header line is optional,
    as for BOP's own reader; DatasetError naming the file and line for anything else."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: missing or unreadable results file ({exc.strerror or exc})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or (number == 1 and POSE_RESULTS_HEADER in line):
            continue
        fields = line.split(",")
        try:
            if len(fields) != 7:
                raise ValueError(f"{len(fields)} comma-separated fields")
            R = np.array([float(v) for v in fields[4].split()], dtype=np.float64)
            t = np.array([float(v) for v in fields[5].split()], dtype=np.float64)
            if R.size != 9 or t.size != 3:
                raise ValueError(f"R has {R.size} numbers, t {t.size}")
            rows.append(
                {
                    "scene_id": int(fields[0]),
                    "im_id": int(fields[1]),
                    "obj_id": int(fields[2]),
                    "score": float(fields[3]),
                    "R": R.reshape(3, 3),
                    "t": t,
                    "time": float(fields[6]),
                }
            )
        except ValueError as exc:
            raise DatasetError(
                f"{path}: line {number}: {exc}; expected '{POSE_RESULTS_HEADER}', R 9 and t 3 space-separated numbers"
            ) from None
    return rows


# --- JSON files -----------------------------------------------------------------------------


def read_bop_json(path: str | Path) -> Any:
    """The parsed JSON file ``path``; DatasetError if it is missing or not JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path}: not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable JSON ({exc})") from None


def write_bop_json(path: str | Path, content: Any) -> None:
    """Write ``content`` (ints, floats, lists, dicts; numpy values converted) as JSON atomically."""

    def plain(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, (np.floating, np.integer, np.bool_)):
            return value.item()
        if isinstance(value, Mapping):
            return {str(k): plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    write_text_atomic(path, json.dumps(plain(content), indent=1, sort_keys=True) + "\n")


def _int_keyed(content: Any, path: Path, what: str) -> dict[int, Any]:
    if not isinstance(content, dict):
        raise DatasetError(f"{path}: expected a JSON object keyed by {what} id, found {type(content).__name__}")
    try:
        return {int(k): v for k, v in content.items()}
    except ValueError:
        raise DatasetError(f"{path}: keys must be integer {what} ids") from None


def _matrix(value: Any, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(shape)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: {where}: expected {math.prod(shape)} numbers") from None
    if not np.all(np.isfinite(array)):
        raise DatasetError(f"{path}: {where}: not finite")
    return array


def read_scene_camera(path: str | Path) -> dict[int, dict[str, Any]]:
    """``scene_camera.json``: per image id ``cam_K`` (3, 3) pixels, ``depth_scale`` (depth PNG value times
    it is mm; None if absent), and when present ``cam_R_w2c`` (3, 3), ``cam_t_w2c`` (3,) in mm."""
    path = Path(path)
    cameras = {}
    for im_id, entry in _int_keyed(read_bop_json(path), path, "image").items():
        if not isinstance(entry, dict) or "cam_K" not in entry:
            raise DatasetError(f"{path}: image {im_id}: no cam_K")
        camera: dict[str, Any] = {"cam_K": _matrix(entry["cam_K"], (3, 3), path, f"image {im_id} cam_K")}
        scale = entry.get("depth_scale")
        if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0):
            raise DatasetError(f"{path}: image {im_id}: depth_scale {scale!r} is not a positive number")
        camera["depth_scale"] = None if scale is None else float(scale)
        if "cam_R_w2c" in entry and "cam_t_w2c" in entry:
            camera["cam_R_w2c"] = _matrix(entry["cam_R_w2c"], (3, 3), path, f"image {im_id} cam_R_w2c")
            camera["cam_t_w2c"] = _matrix(entry["cam_t_w2c"], (3,), path, f"image {im_id} cam_t_w2c")
        cameras[im_id] = camera
    return cameras


def write_scene_camera(path: str | Path, cameras: Mapping[int, Mapping[str, Any]]) -> None:
    """Inverse of :func:`read_scene_camera` (entries without ``depth_scale`` or world pose leave them out)."""
    content = {}
    for im_id, camera in cameras.items():
        entry: dict[str, Any] = {"cam_K": np.asarray(camera["cam_K"], dtype=np.float64).reshape(9)}
        if camera.get("depth_scale") is not None:
            entry["depth_scale"] = float(camera["depth_scale"])
        for key, size in (("cam_R_w2c", 9), ("cam_t_w2c", 3)):
            if camera.get(key) is not None:
                entry[key] = np.asarray(camera[key], dtype=np.float64).reshape(size)
        content[str(int(im_id))] = entry
    write_bop_json(path, content)


def read_scene_gt(path: str | Path) -> dict[int, list[dict[str, Any]]]:
    """``scene_gt.json``: per image id the annotated objects in order (their position is BOP's ``gt_id``):
    dicts with int ``obj_id``, ``cam_R_m2c`` (3, 3) and ``cam_t_m2c`` (3,) in mm (model in camera frame)."""
    path = Path(path)
    scene = {}
    for im_id, entries in _int_keyed(read_bop_json(path), path, "image").items():
        if not isinstance(entries, list):
            raise DatasetError(f"{path}: image {im_id}: expected a list of annotated objects")
        annotations = []
        for gt_id, entry in enumerate(entries):
            where = f"image {im_id} object {gt_id}"
            if not isinstance(entry, dict) or not {"obj_id", "cam_R_m2c", "cam_t_m2c"} <= set(entry):
                raise DatasetError(f"{path}: {where}: expected obj_id, cam_R_m2c and cam_t_m2c")
            R = _matrix(entry["cam_R_m2c"], (3, 3), path, f"{where} cam_R_m2c")
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
                raise DatasetError(f"{path}: {where}: cam_R_m2c is not a rotation matrix")
            obj_id = entry["obj_id"]
            if isinstance(obj_id, bool) or not isinstance(obj_id, int):
                raise DatasetError(f"{path}: {where}: obj_id {obj_id!r} is not an integer")
            annotations.append(
                {"obj_id": obj_id, "cam_R_m2c": R, "cam_t_m2c": _matrix(entry["cam_t_m2c"], (3,), path, where)}
            )
        scene[im_id] = annotations
    return scene


def write_scene_gt(path: str | Path, scene: Mapping[int, Iterable[Mapping[str, Any]]]) -> None:
    """Inverse of :func:`read_scene_gt`."""
    write_bop_json(
        path,
        {
            str(int(im_id)): [
                {
                    "obj_id": int(a["obj_id"]),
                    "cam_R_m2c": np.asarray(a["cam_R_m2c"], dtype=np.float64).reshape(9),
                    "cam_t_m2c": np.asarray(a["cam_t_m2c"], dtype=np.float64).reshape(3),
                }
                for a in entries
            ]
            for im_id, entries in scene.items()
        },
    )


#: Keys of one object's entry in ``scene_gt_info.json``.
GT_INFO_KEYS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


def read_scene_gt_info(path: str | Path) -> dict[int, list[dict[str, Any]]]:
    """``scene_gt_info.json``: per image id, per annotated object (same order as ``scene_gt.json``) the
    boxes ``bbox_obj``/``bbox_visib`` ([x, y, width, height] pixels, [-1]*4 if not visible), pixel counts
    and ``visib_fract``."""
    path = Path(path)
    info = _int_keyed(read_bop_json(path), path, "image")
    for im_id, entries in info.items():
        if not isinstance(entries, list) or not all(
            isinstance(e, dict) and set(GT_INFO_KEYS) <= set(e) for e in entries
        ):
            raise DatasetError(f"{path}: image {im_id}: expected a list of objects with {', '.join(GT_INFO_KEYS)}")
    return info


def write_scene_gt_info(path: str | Path, info: Mapping[int, Iterable[Mapping[str, Any]]]) -> None:
    """Inverse of :func:`read_scene_gt_info`."""
    write_bop_json(
        path,
        {
            str(int(im_id)): [
                {
                    "bbox_obj": [int(v) for v in e["bbox_obj"]],
                    "bbox_visib": [int(v) for v in e["bbox_visib"]],
                    "px_count_all": int(e["px_count_all"]),
                    "px_count_valid": int(e["px_count_valid"]),
                    "px_count_visib": int(e["px_count_visib"]),
                    "visib_fract": float(e["visib_fract"]),
                }
                for e in entries
            ]
            for im_id, entries in info.items()
        },
    )


def gt_info(
    mask_all: np.ndarray, mask_visib: np.ndarray, depth_valid: np.ndarray, mask_all_count: int | None = None
) -> dict[str, Any]:
    """One object's ``scene_gt_info`` entry from its masks in the image: ``mask_all`` (the silhouette without
    occlusion), ``mask_visib`` (the visible part), ``depth_valid`` (pixels with a depth reading).
    ``mask_all_count``: the silhouette's pixel count beyond the image border too, when known."""
    mask_all, mask_visib = np.asarray(mask_all, dtype=bool), np.asarray(mask_visib, dtype=bool)
    count_all = int(mask_all.sum()) if mask_all_count is None else int(mask_all_count)
    count_visib = int(mask_visib.sum())
    return {
        "bbox_obj": bbox_of(mask_all) if count_visib else [-1, -1, -1, -1],
        "bbox_visib": bbox_of(mask_visib) if count_visib else [-1, -1, -1, -1],
        "px_count_all": count_all,
        "px_count_valid": int((mask_all & np.asarray(depth_valid, dtype=bool)).sum()),
        "px_count_visib": count_visib,
        "visib_fract": count_visib / count_all if count_all else 0.0,
    }


def bbox_of(mask: np.ndarray) -> list[int]:
    """[x, y, width, height] of the pixels of ``mask`` as BOP computes boxes (width = max x - min x);
    [-1, -1, -1, -1] for an empty mask."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def read_models_info(path: str | Path) -> dict[int, dict[str, Any]]:
    """``models_info.json``: per object id ``diameter`` (mm), and when present ``symmetries_discrete``
    (list of (4, 4) transforms in the model frame, translation in mm) and ``symmetries_continuous`` (list of
    dicts with ``axis`` (3,) and ``offset`` (3,) mm); other keys (bounding box) as in the file."""
    path = Path(path)
    models = {}
    for obj_id, entry in _int_keyed(read_bop_json(path), path, "object").items():
        if not isinstance(entry, dict):
            raise DatasetError(f"{path}: object {obj_id}: expected a JSON object")
        diameter = entry.get("diameter")
        if isinstance(diameter, bool) or not isinstance(diameter, (int, float)) or not diameter > 0:
            raise DatasetError(f"{path}: object {obj_id}: diameter {diameter!r} is not a positive number (mm)")
        info = dict(entry)
        info["diameter"] = float(diameter)
        info["symmetries_discrete"] = [
            _matrix(s, (4, 4), path, f"object {obj_id} symmetries_discrete")
            for s in entry.get("symmetries_discrete", [])
        ]
        continuous = []
        for s in entry.get("symmetries_continuous", []):
            if not isinstance(s, dict) or "axis" not in s:
                raise DatasetError(f"{path}: object {obj_id}: a continuous symmetry needs 'axis' and 'offset'")
            axis = _matrix(s["axis"], (3,), path, f"object {obj_id} symmetries_continuous axis")
            if not np.linalg.norm(axis) > 0:
                raise DatasetError(f"{path}: object {obj_id}: a continuous symmetry's axis is zero")
            offset = _matrix(s.get("offset", [0, 0, 0]), (3,), path, f"object {obj_id} symmetries_continuous offset")
            continuous.append({"axis": axis, "offset": offset})
        info["symmetries_continuous"] = continuous
        models[obj_id] = info
    return models


def write_models_info(path: str | Path, models: Mapping[int, Mapping[str, Any]]) -> None:
    """Inverse of :func:`read_models_info`; empty symmetry lists are left out, as in BOP's files."""
    write_bop_json(path, models_info_json(models))


def models_info_json(models: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """The content of ``models_info.json`` (keys: object ids as strings) for entries as :func:`read_models_info`
    returns them, written by :func:`write_models_info` (or merged with a file's entries, then written)."""
    content = {}
    for obj_id, info in models.items():
        entry = {k: v for k, v in info.items() if k not in ("symmetries_discrete", "symmetries_continuous")}
        if len(info.get("symmetries_discrete", [])):
            entry["symmetries_discrete"] = [
                np.asarray(s, dtype=np.float64).reshape(16) for s in info["symmetries_discrete"]
            ]
        if len(info.get("symmetries_continuous", [])):
            entry["symmetries_continuous"] = [
                {"axis": np.asarray(s["axis"], dtype=np.float64).reshape(3),
                 "offset": np.asarray(s["offset"], dtype=np.float64).reshape(3)}
                for s in info["symmetries_continuous"]
            ]  # fmt: skip
        content[str(int(obj_id))] = entry
    return content


def models_info_entry(vertices_mm: np.ndarray, **symmetries: Any) -> dict[str, Any]:
    """A ``models_info.json`` entry for a model with ``vertices_mm``: ``diameter`` (largest distance between
    two vertices, mm) and the axis-aligned box (``min_x``, ``size_x``, ...), plus the ``symmetries`` given."""
    vertices_mm = np.asarray(vertices_mm, dtype=np.float64)
    low, high = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    entry: dict[str, Any] = {"diameter": model_diameter(vertices_mm)}
    for axis, name in enumerate("xyz"):
        entry[f"min_{name}"], entry[f"size_{name}"] = float(low[axis]), float(high[axis] - low[axis])
    entry.update(symmetries)
    return entry


def model_diameter(vertices: np.ndarray) -> float:
    """Largest distance between two of ``vertices`` (exact over the convex hull's vertices)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    try:
        from scipy.spatial import ConvexHull

        vertices = vertices[ConvexHull(vertices).vertices]
    except Exception:  # flat or tiny point sets: all points
        pass
    best = 0.0
    for start in range(0, len(vertices), 1024):
        chunk = vertices[start : start + 1024]
        best = max(best, float(np.sqrt(((chunk[:, None] - vertices[None]) ** 2).sum(-1).max())))
    return best


# --- models (PLY, millimetres) --------------------------------------------------------------


def read_ply_model(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) float64 in the file's units (mm in BOP) and triangles (M, 3) int64 of PLY ``path``
    (ASCII or binary). MeshError for a missing or unreadable file and for one without faces (a point cloud
    cannot be rendered into masks and targets)."""
    import trimesh

    from don_gym.errors import MeshError
    from don_gym.objects import check_faces

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: model not found (expected a PLY mesh in millimetres)")
    try:
        loaded = trimesh.load(str(path), file_type="ply", process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for bad files
        raise MeshError(f"{path}: unreadable PLY ({type(exc).__name__}: {exc})") from None
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if faces.ndim != 2 or len(faces) == 0:
        raise MeshError(f"{path}: a PLY without faces (a point cloud); expected a triangle mesh")
    if len(vertices) < 3 or not np.all(np.isfinite(vertices)):
        raise MeshError(f"{path}: expected at least 3 finite vertices")
    check_faces(faces, len(vertices), str(path))
    return vertices, faces


def write_ply_model(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as binary little-endian PLY with float ``x y z`` and ``uchar int
    vertex_indices``: the property types BOP's own PLY reader knows."""
    from don_gym.io import write_bytes_atomic

    vertices = np.ascontiguousarray(vertices, dtype="<f4")
    faces = np.asarray(faces, dtype=np.int64)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment written by don_gym, units: millimetres\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_records = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_records["n"], face_records["v"] = 3, faces
    write_bytes_atomic(path, header.encode("ascii") + vertices.tobytes() + face_records.tobytes())


# --- images ---------------------------------------------------------------------------------

#: Extensions of colour/gray images in BOP datasets, in the order they are looked for.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def find_image(folder: Path, im_id: int) -> Path | None:
    """The file of image ``im_id`` (``NNNNNN`` and one of :data:`IMAGE_EXTENSIONS`) in ``folder``, or None."""
    for suffix in IMAGE_EXTENSIONS:
        path = folder / f"{im_id:06d}{suffix}"
        if path.is_file():
            return path
    return None


#: Pixels an image of a BOP dataset may declare; a header declaring more is refused before decoding. BOP's
#: cameras give a few megapixels; a header can declare gigapixels in a file of kilobytes.
MAX_IMAGE_PIXELS = 50_000_000


def image_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) in pixels that image file ``path`` declares in its header, read without decoding a pixel
    (PNG: the IHDR chunk; JPEG, TIFF: Pillow's header parser); None when no header is recognised."""
    from don_gym.data.dataset import png_size

    path = Path(path)
    try:
        with open(path, "rb") as file:
            head = file.read(24)
    except OSError as exc:
        raise DatasetError(f"{path}: missing or unreadable image ({exc.strerror or exc})") from None
    size = png_size(head)
    if size is not None:
        return size
    try:
        from PIL import Image

        limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None  # only the header is read here
        try:
            with Image.open(path) as image:  # lazy: reads the header only
                return tuple(image.size)
        finally:
            Image.MAX_IMAGE_PIXELS = limit
    except Exception:  # Pillow raises many types for files it does not know
        return None


def _read_image_file(path: Path, flags: int, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """The decoded image at ``path``; its header checked first: at most :data:`MAX_IMAGE_PIXELS`, and of
    ``expected_size`` (width, height) when given."""
    from don_gym.data.dataset import decode_png

    declared = image_size(path)
    if declared is not None:
        width, height = declared
        if expected_size is not None and tuple(declared) != tuple(expected_size):
            raise DatasetError(
                f"{path}: {width}x{height} pixels (its header), expected {expected_size[0]}x{expected_size[1]} as the "
                "images before it; a dataset holds one image size"
            )
        if width * height > MAX_IMAGE_PIXELS:
            raise DatasetError(
                f"{path}: its header declares {width}x{height} pixels, more than the {MAX_IMAGE_PIXELS:,} an image "
                "may have here; expected a camera image"
            )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: missing or unreadable image ({exc.strerror or exc})") from None
    image = decode_png(data, flags)  # any format OpenCV decodes; its log silenced
    if image is None:
        raise DatasetError(f"{path}: unreadable image (empty, truncated or not an image OpenCV reads)")
    if expected_size is not None and image.shape[:2] != (expected_size[1], expected_size[0]):
        raise DatasetError(
            f"{path}: {image.shape[1]}x{image.shape[0]} pixels, expected {expected_size[0]}x{expected_size[1]} as the "
            "images before it; a dataset holds one image size"
        )
    return image


def read_color_image(path: str | Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """RGB uint8 (H, W, 3) of a colour or gray PNG/JPEG/TIFF (gray repeated in the three channels;
    16-bit images scaled to 8 bits). ``expected_size`` (width, height): refused unless of that size (checked on
    the header, before decoding, as the size limit :data:`MAX_IMAGE_PIXELS`)."""
    import cv2

    image = _read_image_file(Path(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR, expected_size)
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    if image.dtype != np.uint8:
        raise DatasetError(f"{path}: a {image.dtype} image; expected 8- or 16-bit colour or gray")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    if image.shape[2] == 4:
        image = image[..., :3]
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def write_color_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write RGB uint8 (H, W, 3) as PNG (or JPEG by ``path``'s suffix), atomically."""
    import cv2

    from don_gym.io import write_bytes_atomic

    bgr = cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    suffix = Path(path).suffix.lower()
    ok, buffer = cv2.imencode(suffix if suffix in (".jpg", ".jpeg") else ".png", bgr)
    if not ok:
        raise OSError(f"could not encode {path}")
    write_bytes_atomic(path, buffer.tobytes())


def read_depth_mm(path: str | Path, depth_scale: float, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) float64 depth in millimetres of a BOP depth image (uint16 PNG/TIFF; value times
    ``depth_scale`` is mm), 0 = no reading; ``expected_size`` as for :func:`read_color_image`."""
    import cv2

    image = _read_image_file(Path(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE, expected_size)
    if image.ndim != 2 or image.dtype not in (np.uint16, np.uint8, np.float32):
        raise DatasetError(f"{path}: a {image.dtype} image of shape {image.shape}; expected a one-channel 16-bit depth")
    return image.astype(np.float64) * float(depth_scale)


def write_depth_mm(path: str | Path, depth_mm: np.ndarray, depth_scale: float = 1.0) -> None:
    """Write depth in millimetres as a uint16 PNG of ``depth_mm / depth_scale`` (0 = no reading)."""
    from don_gym.io import write_png

    depth = np.asarray(depth_mm, dtype=np.float64) / float(depth_scale)
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    write_png(path, np.clip(np.rint(depth), 0, 65535).astype(np.uint16))


def read_mask(path: str | Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """A BOP mask (``mask/`` or ``mask_visib/``, 0 or 255 per pixel) as bool (H, W); ``expected_size`` as for
    :func:`read_color_image`."""
    import cv2

    return _read_image_file(Path(path), cv2.IMREAD_GRAYSCALE, expected_size) > 127


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    """Write a bool mask as a uint8 PNG of 0 and 255, as BOP's masks are."""
    from don_gym.io import write_png

    write_png(path, np.asarray(mask, dtype=bool).astype(np.uint8) * 255)


def mask_path(scene_path: Path, kind: str, im_id: int, gt_id: int) -> Path:
    """Path of the ``kind`` (``mask`` or ``mask_visib``) image of annotation ``gt_id`` in image ``im_id``."""
    return scene_path / kind / f"{im_id:06d}_{gt_id:06d}.png"
