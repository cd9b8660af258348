"""The BOP Challenge's pose-error metrics, on arrays: MSSD, MSPD, ADD-S, their recalls and AR.

Definitions as in the BOP Challenge (Hodan et al., "BOP Challenge 2020 on 6D Object Localization"):

- MSSD (maximum symmetry-aware surface distance): over the model's symmetry transformations S, the
  smallest largest distance between a model point placed by the estimate and by the ground truth
  composed with S; in metres here (BOP: mm), thresholded as a fraction of the object's diameter.
- MSPD (maximum symmetry-aware projection distance): the same in the image, in pixels, thresholded at
  5..50 px for a 640 px wide image (scaled by width / 640 for other widths).
- AR_MSSD, AR_MSPD: mean recall over their thresholds; AR here is their average. The BOP Challenge's
  AR also averages AR_VSD (visible surface discrepancy), which needs depth renderings of the model and
  is not computed here: our AR is AR_MSSD and AR_MSPD only, and reports say so.
- ADD-S (ADI, Hinterstoisser et al. 2012): mean distance from each ground-truth model point to the
  nearest estimated one; a pose is correct below 10 % of the diameter.

A continuous symmetry is discretised as BOP does: ``ceil(pi / max_sym_disc_step)`` rotations evenly
spaced over a full turn (BOP's evaluation uses ``max_sym_disc_step = 0.01``: 315 rotations), each
composed with every discrete symmetry (the identity included).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from don_gym.data.bop import model_diameter  # noqa: F401  (the one home of BOP's diameter; re-exported)
from don_gym.errors import DonGymError

__all__ = [
    "ADDS_THRESHOLD",
    "MAX_SYM_DISC_STEP",
    "MSPD_REFERENCE_WIDTH_PX",
    "MSPD_THRESHOLDS_PX",
    "MSSD_THRESHOLDS",
    "adds",
    "bop_symmetries",
    "mspd",
    "mssd",
    "object_symmetries",
    "pose_recalls",
    "recall_curve",
    "symmetry_transformations",
]

#: MSSD thresholds of the BOP Challenge, as fractions of the object's diameter: 0.05, 0.10, ..., 0.50.
MSSD_THRESHOLDS: np.ndarray = np.round(np.arange(0.05, 0.51, 0.05), 2)
#: MSPD thresholds of the BOP Challenge in pixels for a 640 px wide image: 5, 10, ..., 50.
MSPD_THRESHOLDS_PX: np.ndarray = np.arange(5.0, 51.0, 5.0)
#: Image width the MSPD thresholds are given for.
MSPD_REFERENCE_WIDTH_PX = 640
#: ADD-S below this fraction of the diameter counts as correct.
ADDS_THRESHOLD = 0.1
#: BOP's discretisation of a continuous symmetry: the furthest point from the axis travels at most this
#: fraction of the diameter between consecutive rotations (``max_sym_disc_step`` in its evaluation).
MAX_SYM_DISC_STEP = 0.01


def _as_transform(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DonGymError(f"{name}: expected a finite (4, 4) transform, got shape {T.shape}")
    return T


def _as_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise DonGymError(f"model points: expected (N, 3) with N >= 1, got shape {points.shape}")
    return points


def symmetry_transformations(
    discrete: Iterable[np.ndarray] = (),
    continuous: Iterable[tuple[np.ndarray, np.ndarray]] = (),
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> np.ndarray:
    """(S, 4, 4) object-frame symmetry transformations, the identity first.

    Args:
        discrete: (4, 4) transforms (metres) mapping the model onto itself, besides the identity.
        continuous: ``(axis (3,), offset (3,) metres)`` pairs, an axis of rotational symmetry through
            ``offset``; each is discretised into ``ceil(pi / max_sym_disc_step)`` rotations over a turn.
        max_sym_disc_step: see :data:`MAX_SYM_DISC_STEP`.
    """
    discrete_set = [np.eye(4)] + [_as_transform(T, "discrete symmetry") for T in discrete]
    continuous_set: list[np.ndarray] = []
    steps = int(np.ceil(np.pi / float(max_sym_disc_step)))
    for axis, offset in continuous:
        axis = np.asarray(axis, dtype=np.float64)
        offset = np.asarray(offset, dtype=np.float64).reshape(3)
        if axis.shape != (3,) or np.linalg.norm(axis) == 0:
            raise DonGymError(f"continuous symmetry axis {axis!r}: expected a non-zero (3,) vector")
        axis = axis / np.linalg.norm(axis)
        for i in range(steps):
            T = np.eye(4)
            T[:3, :3] = Rotation.from_rotvec(axis * (2.0 * np.pi * i / steps)).as_matrix()
            T[:3, 3] = offset - T[:3, :3] @ offset
            continuous_set.append(T)
    if not continuous_set:
        return np.stack(discrete_set)
    return np.stack([C @ D for D in discrete_set for C in continuous_set])


def bop_symmetries(model_info: Mapping[str, Any], max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> np.ndarray:
    """:func:`symmetry_transformations` of a BOP ``models_info.json`` entry (``symmetries_discrete``: flat
    row-major 4x4 lists, ``symmetries_continuous``: ``{"axis", "offset"}``, both in millimetres), in metres."""
    discrete = []
    for values in model_info.get("symmetries_discrete", []):
        T = np.asarray(values, dtype=np.float64).reshape(4, 4).copy()
        T[:3, 3] /= 1000.0
        discrete.append(T)
    continuous = [
        (np.asarray(s["axis"], dtype=np.float64), np.asarray(s["offset"], dtype=np.float64) / 1000.0)
        for s in model_info.get("symmetries_continuous", [])
    ]
    return symmetry_transformations(discrete, continuous, max_sym_disc_step)


def object_symmetries(model: Any, max_sym_disc_step: float = MAX_SYM_DISC_STEP) -> np.ndarray:
    """Symmetry transformations of a :class:`don_gym.objects.ObjectModel`: its rotational symmetry about
    ``symmetry_axis`` through the centre of mass (the built-ins' axis), or the identity alone."""
    if model.symmetry_axis is None:
        return np.eye(4)[None]
    return symmetry_transformations((), [(model.symmetry_axis, model.center_of_mass)], max_sym_disc_step)


def _symmetric_gt_points(T_gt: np.ndarray, points: np.ndarray, symmetries: np.ndarray) -> np.ndarray:
    """(S, N, 3) model points placed by the ground truth composed with each symmetry."""
    T = np.matmul(T_gt, np.asarray(symmetries, dtype=np.float64))  # (S, 4, 4)
    return np.matmul(T[:, :3, :3], points.T).transpose(0, 2, 1) + T[:, None, :3, 3]


def mssd(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, symmetries: np.ndarray) -> float:
    """MSSD in the points' unit (metres): ``min_S max_x |T_est x - T_gt S x|`` over model points x (N, 3)
    and symmetries S (S, 4, 4) (:func:`symmetry_transformations`; include the identity)."""
    T_est, T_gt, points = _as_transform(T_est, "T_est"), _as_transform(T_gt, "T_gt"), _as_points(points)
    estimated = points @ T_est[:3, :3].T + T_est[:3, 3]
    truth = _symmetric_gt_points(T_gt, points, symmetries)
    return float(np.linalg.norm(truth - estimated[None], axis=2).max(axis=1).min())


def _project(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    z = points_camera[..., 2:3]
    return (points_camera[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])


def mspd(T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, points: np.ndarray, symmetries: np.ndarray) -> float:
    """MSPD in pixels: ``min_S max_x |pi(T_est x) - pi(T_gt S x)|`` with the (3, 3) camera matrix ``K``
    (not yet scaled by image width; :func:`pose_recalls` does that)."""
    T_est, T_gt, points = _as_transform(T_est, "T_est"), _as_transform(T_gt, "T_gt"), _as_points(points)
    K = np.asarray(K, dtype=np.float64)
    estimated = _project(points @ T_est[:3, :3].T + T_est[:3, 3], K)
    truth = _project(_symmetric_gt_points(T_gt, points, symmetries), K)
    return float(np.linalg.norm(truth - estimated[None], axis=2).max(axis=1).min())


def adds(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S in the points' unit: mean over ground-truth-placed model points of the distance to the
    nearest estimated-placed one (symmetric by construction, no symmetry list needed)."""
    T_est, T_gt, points = _as_transform(T_est, "T_est"), _as_transform(T_gt, "T_gt"), _as_points(points)
    estimated = points @ T_est[:3, :3].T + T_est[:3, 3]
    truth = points @ T_gt[:3, :3].T + T_gt[:3, 3]
    distances, _ = cKDTree(estimated).query(truth, k=1)
    return float(np.mean(distances))


def recall_curve(errors: Sequence[float] | np.ndarray, thresholds: Sequence[float] | np.ndarray) -> np.ndarray:
    """(T,) share of errors strictly below each threshold; a missing estimate counts as an infinite error
    (NaN is taken as one). Empty ``errors``: NaN."""
    errors = np.asarray(errors, dtype=np.float64).ravel()
    thresholds = np.asarray(thresholds, dtype=np.float64).ravel()
    if len(errors) == 0:
        return np.full(len(thresholds), np.nan)
    errors = np.where(np.isnan(errors), np.inf, errors)
    return (errors[None, :] < thresholds[:, None]).mean(axis=1)


def pose_recalls(
    mssd_m: Sequence[float] | np.ndarray,
    mspd_px: Sequence[float] | np.ndarray,
    adds_m: Sequence[float] | np.ndarray,
    diameter_m: float,
    image_width_px: int | Sequence[int] | np.ndarray,
) -> dict[str, Any]:
    """Recalls and average recalls of a set of estimates, one entry per ground-truth instance (NaN or inf
    where no estimate was made).

    Args:
        mssd_m, mspd_px, adds_m: (M,) errors of :func:`mssd`, :func:`mspd`, :func:`adds`.
        diameter_m: the object's diameter (:func:`model_diameter`).
        image_width_px: width of the images (one for all or (M,)): MSPD is scaled by 640 / width, as BOP does.

    Returns:
        ``mssd_thresholds`` (fractions of the diameter), ``mssd_recall`` (T,), ``mspd_thresholds_px``,
        ``mspd_recall`` (T,), ``ar_mssd``, ``ar_mspd``, ``ar`` (their mean; no VSD), ``adds_share`` (share with
        ADD-S below :data:`ADDS_THRESHOLD` of the diameter) and ``count``.
    """
    if not (np.isfinite(diameter_m) and diameter_m > 0):
        raise DonGymError(f"diameter_m={diameter_m!r}: expected a positive number of metres")
    mssd_m = np.asarray(mssd_m, dtype=np.float64)
    mspd_scaled = np.asarray(mspd_px, dtype=np.float64) * (
        MSPD_REFERENCE_WIDTH_PX / np.asarray(image_width_px, dtype=np.float64)
    )
    mssd_recall = recall_curve(mssd_m / diameter_m, MSSD_THRESHOLDS)
    mspd_recall = recall_curve(mspd_scaled, MSPD_THRESHOLDS_PX)
    adds_share = recall_curve(np.asarray(adds_m, dtype=np.float64) / diameter_m, [ADDS_THRESHOLD])[0]
    ar_mssd, ar_mspd = float(np.mean(mssd_recall)), float(np.mean(mspd_recall))
    return {
        "mssd_thresholds": MSSD_THRESHOLDS.tolist(),
        "mssd_recall": mssd_recall.tolist(),
        "mspd_thresholds_px": MSPD_THRESHOLDS_PX.tolist(),
        "mspd_recall": mspd_recall.tolist(),
        "ar_mssd": ar_mssd,
        "ar_mspd": ar_mspd,
        "ar": float((ar_mssd + ar_mspd) / 2.0),
        "adds_share": float(adds_share),
        "count": int(len(mssd_m)),
    }
