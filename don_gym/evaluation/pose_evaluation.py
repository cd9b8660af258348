"""6D pose evaluation of descriptor sources on recorded scenes, scored as the BOP Challenge scores it.

Per frame of every scene, each method's descriptor image gives one pose estimate of the dataset's part
(:func:`don_gym.perception.pose.estimate_pose`, with the frame's sensor or ideal depth, or RGB-only PnP); it is scored
against the frame's TRUE pose of the part (:meth:`don_gym.data.dataset.SceneRecord.T_camera_object`; with several
annotated instances, the one it matches best) by MSSD, MSPD and ADD-S (:mod:`don_gym.evaluation.pose_metrics`, with the
part's rotational symmetry). As BOP does, only instances with at least 10 % of their silhouette visible are
targets, and a frame without an estimate counts as wrong at every threshold. AR here is the mean of AR_MSSD
and AR_MSPD: BOP's third error, VSD, is not computed.

Methods are loaded as everywhere else (:func:`don_gym.perception.descriptor_sources.load_descriptor_source`). The
networks' targets (:func:`don_gym.perception.pose.pose_targets_for`) and every method's calibration come from
reference views with known poses: the :data:`REFERENCE_VIEWS` frames of the first scene showing most of the
part. They are left out of the scoring for every method.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym.data.dataset import DONDataset, instance_mask
from don_gym.data.render import DescriptorRenderer
from don_gym.errors import DonGymError
from don_gym.evaluation.frames import frame_observation, open_datasets, pooled_object, source_info
from don_gym.evaluation.pose_metrics import adds, mspd, mssd, object_symmetries, pose_recalls
from don_gym.learning.model import torch_device
from don_gym.perception.descriptor_sources import DescriptorSource, NetworkDescriptors, load_descriptor_source
from don_gym.perception.pose import PoseConfig, estimate_pose, pose_targets_for

__all__ = [
    "MIN_VISIBLE_FRACTION",
    "OBJECT_ID",
    "POSE_DEPTHS",
    "REFERENCE_VIEWS",
    "SCENE_ID_STRIDE",
    "PoseEstimates",
    "PoseResult",
    "evaluate_pose",
    "method_file_name",
    "pose_table",
    "write_pose_outputs",
]

#: Depth for the pose estimate, by name: the dataset's sensor depth, the simulator's ideal depth, or none
#: (RGB-only PnP).
POSE_DEPTHS: dict[str, str | None] = {"sensor": "depth", "ideal": "depth_ideal", "none": None}
#: BOP's target rule: an instance is a target when at least this share of its silhouette is visible.
MIN_VISIBLE_FRACTION = 0.1
#: BOP object id of the dataset's part (as ``don-gym export --format bop`` numbers it).
OBJECT_ID = 1
#: Scene ids of pooled datasets: the scene index plus this times the dataset's position (the first keeps
#: its indices, as ``don-gym export`` writes them).
SCENE_ID_STRIDE = 1000


@dataclass
class PoseEstimates:
    """One method's estimates at one depth, one entry per target (scene, frame): arrays of equal length M.

    ``scene_id`` (BOP scene id), ``dataset``, ``scene`` (position in the dataset), ``frame``, ``found``
    (bool), ``T_camera_object`` (M, 4, 4; NaN where none), ``score``, ``time_s`` (descriptor image and
    estimate), ``inliers``, ``mssd_m``, ``mspd_px``, ``adds_m`` (inf where none), ``image_width``.
    """

    scene_id: np.ndarray
    dataset: np.ndarray
    scene: np.ndarray
    frame: np.ndarray
    found: np.ndarray
    T_camera_object: np.ndarray
    score: np.ndarray
    time_s: np.ndarray
    inliers: np.ndarray
    mssd_m: np.ndarray
    mspd_px: np.ndarray
    adds_m: np.ndarray
    image_width: np.ndarray

    def bop_rows(self) -> list[dict[str, Any]]:
        """BOP results rows (:func:`don_gym.data.bop.write_pose_results`) of the estimates made: R, t in mm."""
        rows = []
        for k in np.flatnonzero(self.found):
            T = self.T_camera_object[k]
            rows.append(
                {
                    "scene_id": int(self.scene_id[k]),
                    "im_id": int(self.frame[k]),
                    "obj_id": OBJECT_ID,
                    "score": float(self.score[k]),
                    "R": T[:3, :3],
                    "t": T[:3, 3] * 1000.0,
                    "time": float(self.time_s[k]),
                }
            )
        return rows


@dataclass
class PoseResult:
    """Pose estimates of every method at one depth, with what is needed to score them."""

    datasets: list[str]
    depth: str
    object_name: str
    diameter_m: float
    symmetric: bool
    estimates: dict[str, PoseEstimates]
    sources: dict[str, dict[str, Any]]
    reference: dict[str, Any]
    config: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Per method the BOP recalls and ARs (:func:`don_gym.evaluation.pose_metrics.pose_recalls`), the share with an
        estimate, the mean and median time per image; JSON-ready."""
        methods = {}
        for name, e in self.estimates.items():
            recalls = pose_recalls(e.mssd_m, e.mspd_px, e.adds_m, self.diameter_m, e.image_width)
            methods[name] = {
                "source": self.sources[name],
                **recalls,
                "found_share": float(np.mean(e.found)) if len(e.found) else float("nan"),
                "time_per_image_s": float(np.mean(e.time_s)) if len(e.time_s) else float("nan"),
                "median_time_per_image_s": float(np.median(e.time_s)) if len(e.time_s) else float("nan"),
            }
        return {
            "datasets": self.datasets,
            "object": self.object_name,
            "depth": self.depth,
            "diameter_mm": self.diameter_m * 1000.0,
            "symmetric": self.symmetric,
            "reference": self.reference,
            "config": self.config,
            "note": "AR = mean of AR_MSSD and AR_MSPD (BOP's AR also averages AR_VSD, not computed here); "
            "ADD-S share: estimates with ADD-S below 10% of the diameter",
            "methods": methods,
        }


#: Reference views: this many frames of the first scene, those showing most of the part.
REFERENCE_VIEWS = 2


def _reference_frames(data: DONDataset, count: int = REFERENCE_VIEWS) -> list[int]:
    """Frames of the first scene showing most of the part's reference instance (the one :func:`_primary_pose`
    takes; in a pile, an instance of the primary part, not the pile), at most ``count`` and at least one fewer
    than the scene has (one is left to score)."""
    record = data.scenes[0]
    sizes = []
    for f in range(record.num_frames):
        poses = _part_poses(data, record, f)
        sizes.append(int(np.count_nonzero(instance_mask(data, 0, f) == min(poses))) if poses else 0)
    keep = max(1, min(count, record.num_frames - 1))
    return sorted(int(f) for f in np.argsort(sizes)[::-1][:keep])


def _part_poses(data: DONDataset, record, frame: int) -> dict[int, np.ndarray]:
    """TRUE poses (camera frame) of the instances of the dataset's primary part (the one evaluated) in a
    frame, by instance id: every annotated instance in a dataset of one part."""
    poses = record.T_camera_object(frame)
    if len(data.parts) <= 1:
        return poses
    name = data.parts[0]["name"]
    ids = {int(i["instance_id"]) for i in record.instances if i["part"] == name}
    return {k: T for k, T in poses.items() if k in ids}


def _primary_pose(data: DONDataset, record, frame: int) -> np.ndarray:
    poses = _part_poses(data, record, frame)
    if not poses:
        raise DonGymError(f"{record.path}: frame {frame} shows no instance of the part {data.parts[0]['name']!r}")
    return poses[min(poses)]


def evaluate_pose(
    dataset: DONDataset | str | Path | Sequence[DONDataset | str | Path],
    methods: Sequence[str] | Mapping[str, str | DescriptorSource],
    depths: Sequence[str] = ("sensor",),
    config: PoseConfig | None = None,
    max_scenes: int | None = None,
    progress: bool = True,
    device: str = "cpu",
) -> dict[str, PoseResult]:
    """Estimate and score the part's pose in every frame, for each method and each depth of
    :data:`POSE_DEPTHS` (``"sensor"``, ``"ideal"``, ``"none"``): ``{depth: PoseResult}``. Each method's
    descriptor image of a frame is computed once for all depths; its time is added to each estimate's."""
    config = PoseConfig() if config is None else config
    depths = tuple(dict.fromkeys(depths))
    if not depths or any(d not in POSE_DEPTHS for d in depths):
        raise DonGymError(f"depths={list(depths)!r}: expected one or more of {list(POSE_DEPTHS)}")
    if max_scenes is not None and (isinstance(max_scenes, bool) or not isinstance(max_scenes, int) or max_scenes < 1):
        raise DonGymError(f"max_scenes={max_scenes!r}: expected an integer >= 1 or None")
    run_on = torch_device(device)
    datasets = open_datasets(dataset)
    if not methods:
        raise DonGymError("no methods to evaluate; give 'oracle' and/or network names or checkpoint paths")
    labelled = dict(methods) if isinstance(methods, Mapping) else {str(m): m for m in methods}
    model = pooled_object(datasets)
    sources = {name: load_descriptor_source(ref, model) for name, ref in labelled.items()}
    for source in sources.values():
        if isinstance(source, NetworkDescriptors):
            source.network.to(run_on)
    ref_frames = _reference_frames(datasets[0])
    targets = {name: _pose_targets(source, datasets[0], ref_frames) for name, source in sources.items()}
    scoring = _Scoring(model)
    plan = [
        (d, s, f)
        for d, data in enumerate(datasets)
        for s in range(len(data.scenes))[:max_scenes]
        for f in range(data.scenes[s].num_frames)
        if not (d == 0 and s == 0 and f in ref_frames)
    ]
    rows: dict[tuple[str, str], list[dict[str, Any]]] = {(n, d): [] for n in sources for d in depths}
    with tqdm(total=len(plan) * len(sources), unit="frame", desc="pose", disable=not progress) as bar:
        for d, s, f in plan:
            data = datasets[d]
            truths = scoring.visible_truths(data, s, f)
            if not truths:
                bar.update(len(sources))
                continue
            depth_images = {
                name: data.image(s, f, kind) if kind else None for name, kind in POSE_DEPTHS.items() if name in depths
            }
            for name, source in sources.items():
                start = time.perf_counter()
                image = source.descriptor_image(*frame_observation(data, s, f))
                image_s = time.perf_counter() - start
                for depth in depths:
                    K = data.scenes[s].intrinsics
                    estimate = estimate_pose(image, targets[name], K, depth_images[depth], config=config)
                    row = scoring.row(estimate, truths, K, data.scenes[s].index + SCENE_ID_STRIDE * d, d, s, f)
                    row["time_s"] += image_s
                    rows[(name, depth)].append(row)
                bar.update(1)
    return {
        depth: PoseResult(
            datasets=[str(data.root) for data in datasets],
            depth=depth,
            object_name=model.name,
            diameter_m=targets[next(iter(targets))].diameter_m,
            symmetric=model.symmetry_axis is not None,
            estimates={name: _pose_estimates(rows[(name, depth)]) for name in sources},
            sources={name: source_info(source) for name, source in sources.items()},
            reference={"dataset": str(datasets[0].root), "scene": 0, "frames": ref_frames},
            config=asdict(config) | {"max_scenes": max_scenes},
        )
        for depth in depths
    }


def _pose_targets(source: DescriptorSource, reference: DONDataset, frames: Sequence[int]) -> Any:
    """A method's pose targets (:func:`~don_gym.perception.pose.pose_targets_for`) from its descriptor images
    of the reference ``frames`` of the first scene of ``reference``, at their true poses."""
    record = reference.scenes[0]
    views = [
        (
            source.descriptor_image(*frame_observation(reference, 0, f)),
            record.intrinsics,
            _primary_pose(reference, record, f),
        )
        for f in frames
    ]
    return pose_targets_for(source, views)


class _Scoring:
    """What an estimate of the part's pose is scored against: the part's points, symmetries and silhouette."""

    def __init__(self, model: Any) -> None:
        self.points = np.asarray(model.mesh.vertices, dtype=np.float64)
        self.symmetries = object_symmetries(model)
        self.silhouette = DescriptorRenderer(
            model.mesh, np.zeros((len(self.points), 1), np.float32), np.zeros(1, np.float32)
        )

    def visible_truths(self, data: DONDataset, scene: int, frame: int) -> list[np.ndarray]:
        """The true ``T_camera_object`` of each instance of the part showing at least
        :data:`MIN_VISIBLE_FRACTION` of its silhouette in the frame (BOP's rule)."""
        record = data.scenes[scene]
        instances = instance_mask(data, scene, frame)
        truths = []
        for instance_id, T in sorted(_part_poses(data, record, frame).items()):
            full = self.silhouette.render(record.intrinsics, T).object_mask
            if full.any() and np.count_nonzero((instances == instance_id) & full) >= MIN_VISIBLE_FRACTION * full.sum():
                truths.append(T)
        return truths

    def row(
        self, estimate: Any, truths: list[np.ndarray], K: Any, scene_id: int, d: int, s: int, f: int
    ) -> dict[str, Any]:
        """One estimate's row of :class:`PoseEstimates`, scored against the nearest true instance by MSSD."""
        row = {
            "scene_id": scene_id,
            "dataset": d,
            "scene": s,
            "frame": f,
            "found": estimate.found,
            "T_camera_object": np.full((4, 4), np.nan),
            "score": estimate.score,
            "time_s": estimate.time_s,
            "inliers": estimate.inliers,
            "mssd_m": np.inf,
            "mspd_px": np.inf,
            "adds_m": np.inf,
            "image_width": K.width,
        }
        if estimate.found:
            T_est = estimate.T_camera_object
            errors = [mssd(T_est, T, self.points, self.symmetries) for T in truths]
            best = truths[int(np.argmin(errors))]
            row |= {
                "T_camera_object": T_est,
                "mssd_m": float(min(errors)),
                "mspd_px": mspd(T_est, best, K.K, self.points, self.symmetries),
                "adds_m": adds(T_est, best, self.points),
            }
        return row


def _pose_estimates(rows: list[dict[str, Any]]) -> PoseEstimates:
    arrays = {key: np.asarray([r[key] for r in rows]) for key in PoseEstimates.__dataclass_fields__}
    if not rows:
        arrays["T_camera_object"] = np.zeros((0, 4, 4))
    return PoseEstimates(**arrays)


def method_file_name(method: str) -> str:
    """A method's name in file names: ``/`` (and the path separator) become ``-``."""
    return method.replace("/", "-").replace("\\", "-")


def pose_table(summary: Mapping[str, Any]) -> str:
    """Markdown table of a :meth:`PoseResult.summary`: AR, AR_MSSD, AR_MSPD, ADD-S share, estimates made, time."""
    lines = [
        "| method | AR | AR_MSSD | AR_MSPD | ADD-S < 0.1 d | estimated | time per image |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in summary["methods"].items():
        lines.append(
            f"| {name} | {m['ar']:.3f} | {m['ar_mssd']:.3f} | {m['ar_mspd']:.3f} | {m['adds_share']:.3f} | "
            f"{m['found_share'] * m['count']:.0f}/{m['count']} | {m['time_per_image_s'] * 1000:.0f} ms |"
        )
    return "\n".join(lines)


def write_pose_outputs(result: PoseResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``pose.json`` (:meth:`PoseResult.summary`), ``pose.md`` (:func:`pose_table`), each method's
    estimates as a BOP results file ``pose_<method>.csv`` (:func:`method_file_name`) and ``pose_recall.png``
    (recall against threshold per method) into ``out_dir``; returns the paths by key."""
    from don_gym import plotting
    from don_gym.data.bop import write_pose_results
    from don_gym.io import check_output_dir, write_text_atomic

    out = check_output_dir(out_dir, "out_dir")
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    paths: dict[str, Path] = {"json": out / "pose.json", "table": out / "pose.md"}
    write_text_atomic(paths["json"], json.dumps(summary, indent=1) + "\n")
    write_text_atomic(paths["table"], pose_table(summary) + "\n")
    for name, estimates in result.estimates.items():
        path = out / f"pose_{method_file_name(name)}.csv"
        write_pose_results(path, estimates.bop_rows())
        paths[f"csv:{name}"] = path
    names = ", ".join(Path(d).name for d in result.datasets)
    paths["recall"] = plotting.plot_pose_recalls(
        summary["methods"],
        out / "pose_recall.png",
        title=f"6D pose recall, {result.object_name} ({names}, depth: {result.depth})",
    )
    return paths
