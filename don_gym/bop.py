"""Reading and writing the files of the BOP format (Benchmark for 6D Object Pose estimation).

Plain functions, arrays in and out, in BOP's own units: millimetres for model points, translations
and depth (times a per-image ``depth_scale``), pixels for ``cam_K``, seconds for run times. What don_gym
does with them (import into a dataset, export from one) lives in :mod:`don_gym.import_bop` and :mod:`don_gym.export`; this module
only knows the files. Every reader raises :class:`~don_gym.errors.DatasetError` (or
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
                f"{path}: line {number}: {exc}; expected '{POSE_RESULTS_HEADER}' with R 9 and t 3 space-separated numbers"
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
