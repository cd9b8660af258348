"""Dataset-building speed: whole builds, and target rendering next to RGB rendering.

Frames/s of whole builds with 1 worker (the baseline) and 2 (target: >= 15 frames/s at 320x240 on
2 cores); descriptor-target rendering time per frame against PyBullet's RGB-D render (target: <= 10 %);
the 3D error of self-supervised matches per depth source. Records the "dataset" section of
benchmarks/RESULTS.md (not with --no-record). ``--quick`` runs a smaller build.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import record_section  # noqa: E402

from don_gym.data.build import DatasetConfig, build_dataset  # noqa: E402
from don_gym.data.render import DescriptorRenderer, make_target  # noqa: E402
from don_gym.descriptors import embed  # noqa: E402
from don_gym.geometry import invert_transform  # noqa: E402
from don_gym.objects import load_object  # noqa: E402
from don_gym.sim.camera import render_camera  # noqa: E402
from don_gym.sim.recorder import SceneRecorder  # noqa: E402


def time_builds(config: DatasetConfig, worker_counts: list[int]) -> dict[int, float]:
    """Frames/s of a whole build (record, sensor model, targets, TSDF fusion, PNG writes) per worker count."""
    rates = {}
    for workers in worker_counts:
        with tempfile.TemporaryDirectory(prefix="don_gym_bench_") as tmp:
            report = build_dataset(config, Path(tmp) / "data", workers=workers, progress=False)
        rates[workers] = report.frames_per_second
        print(
            f"build with {workers} worker(s): {report.frames_written} frames in {report.seconds:.1f} s "
            f"= {report.frames_per_second:.1f} frames/s"
        )
    return rates


def time_targets(object_name: str, size: tuple[int, int], frames: int, seed: int) -> tuple[float, float, float]:
    """Median ms per frame: RGB-D render, target render, target render + edge blending."""
    model = load_object(object_name)
    field = embed(model)
    renderer = DescriptorRenderer(model.mesh, field.vertex_descriptors, field.background)
    with SceneRecorder(model, size, sensor="ideal") as recorder:
        scene = recorder.record(seed=seed, num_frames=frames)
        rgb_ms, target_ms, edge_ms = [], [], []
        for frame in scene.frames:
            start = time.perf_counter()
            render_camera(recorder.sim.client, scene.intrinsics, frame.T_world_camera, renderer=recorder.renderer)
            rgb_ms.append(1e3 * (time.perf_counter() - start))
            T_camera_object = invert_transform(frame.T_world_camera_reported) @ scene.T_world_object
            start = time.perf_counter()
            rendered = renderer.render(scene.intrinsics, T_camera_object, visible_mask=frame.object_mask)
            target_ms.append(1e3 * (time.perf_counter() - start))
            make_target("edge", rendered.descriptor_image, rendered.object_mask, field.background)
            edge_ms.append(1e3 * (time.perf_counter() - start))
    return float(np.median(rgb_ms)), float(np.median(target_ms)), float(np.median(edge_ms))


def correspondence_errors(config: DatasetConfig, pairs: int, seed: int) -> dict[str, np.ndarray]:
    """3D error (m) of sampled matches, per depth source, against the true object surface point.

    Matches are sampled as the self-supervised trainer does (reported poses, default margins);
    each match's two pixels are lifted with *ideal* depth and true poses into the object frame,
    so the error is what the training signal gets wrong.
    """
    from don_gym.data.correspondences import sample_correspondences
    from don_gym.data.dataset import DEPTH_SOURCES
    from don_gym.geometry import backproject_depth, transform_points

    errors: dict[str, list[np.ndarray]] = {name: [] for name in DEPTH_SOURCES}
    with tempfile.TemporaryDirectory(prefix="don_gym_bench_") as tmp:
        build_dataset(config, Path(tmp) / "data", progress=False)
        from don_gym.data.dataset import DONDataset

        data = DONDataset(Path(tmp) / "data")
        rng = np.random.default_rng(seed)
        for _ in range(pairs):
            s = int(rng.integers(len(data.scenes)))
            scene = data.scenes[s]
            a, b = (int(v) for v in rng.choice(scene.num_frames, size=2, replace=False))
            ideal = [data.image(s, f, "depth_ideal") for f in (a, b)]
            T_object_world = invert_transform(scene.T_world_object)
            for name, (depth_kind, mask_kind) in DEPTH_SOURCES.items():
                corr = sample_correspondences(
                    data.image(s, a, depth_kind), data.image(s, b, depth_kind),
                    data.image(s, a, mask_kind), data.image(s, b, mask_kind), scene.intrinsics,
                    scene.T_world_camera_reported[a], scene.T_world_camera_reported[b], rng,
                )  # fmt: skip
                if len(corr.matches_a) == 0:
                    continue
                points = []
                for depth, frame, uv in ((ideal[0], a, corr.matches_a), (ideal[1], b, corr.matches_b)):
                    camera = backproject_depth(scene.intrinsics, depth, uv)
                    points.append(transform_points(T_object_world @ scene.T_world_camera[frame], camera))
                valid = (points[0][:, 2] != 0) & (points[1][:, 2] != 0)
                errors[name].append(np.linalg.norm(points[0] - points[1], axis=1)[valid])
    return {name: np.concatenate(v) if v else np.zeros(0) for name, v in errors.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=6, help="scenes per build")
    parser.add_argument("--frames", type=int, default=24, help="frames per scene")
    parser.add_argument("--size", default="320x240", help="image size WIDTHxHEIGHT")
    parser.add_argument("--sensor", default="d435")
    parser.add_argument("--quick", action="store_true", help="2 scenes of 12 frames")
    parser.add_argument("--no-record", action="store_true", help="print only, do not update RESULTS.md")
    args = parser.parse_args()
    if args.quick:
        args.scenes, args.frames = 2, 12
    size = tuple(int(v) for v in args.size.split("x"))
    config = DatasetConfig(scenes=args.scenes, frames_per_scene=args.frames, image_size=size, sensor=args.sensor)
    rates = time_builds(config, [1, 2])
    rgb_ms, target_ms, edge_ms = time_targets("toolcap", size, frames=24, seed=3)
    corr_errors = correspondence_errors(
        DatasetConfig(scenes=2, frames_per_scene=12, image_size=size, sensor=args.sensor, seed=1), pairs=30, seed=0
    )
    corr_rows = "\n".join(
        f"| {name} | {len(e)} | "
        + " | ".join(f"{1e3 * np.percentile(e, q):.2f}" if len(e) else "-" for q in (50, 90, 99))
        + f" | {100 * np.mean(e > 0.005) if len(e) else 0:.1f}% |"
        for name, e in corr_errors.items()
    )
    ratio = target_ms / rgb_ms
    body = f"""Toolcap, {args.scenes} scenes x {args.frames} frames at {size[0]}x{size[1]},
sensor `{args.sensor}`, TinyRenderer,
with TSDF fusion. Baseline: the same build with 1 worker.

| build | frames/s | vs 1 worker |
|---|---|---|
| 1 worker | {rates[1]:.1f} | 1.00x |
| 2 workers | {rates[2]:.1f} | {rates[2] / rates[1]:.2f}x |

Target: >= 15 frames/s with 2 workers: {"met" if rates[2] >= 15 else "**not met**"}.

Per frame (median over 24 frames of one scene, {size[0]}x{size[1]}):

| step | ms per frame | vs RGB-D render |
|---|---|---|
| PyBullet RGB-D render (TinyRenderer), baseline | {rgb_ms:.1f} | 1.00 |
| descriptor target (Embree ray casting, visible pixels) | {target_ms:.2f} | {ratio:.3f} |
| descriptor target + edge blending | {edge_ms:.2f} | {edge_ms / rgb_ms:.3f} |

Target: target rendering <= 10% of the RGB render: {"met" if ratio <= 0.10 else "**not met**"}.

Self-supervised correspondences (2 scenes x 12 frames, 30 random pairs, sensor `{args.sensor}`, default
sampler margins, reported camera poses): 3D distance between the two pixels of a match on the true object
surface, by the depth the sampler used (`fused` = TSDF of sensor depth, the original pipeline).

| depth source | matches | p50 (mm) | p90 (mm) | p99 (mm) | > 5 mm |
|---|---|---|---|---|---|
{corr_rows}"""
    print(body)
    if not args.no_record:
        record_section("dataset", "Dataset building (bench_dataset.py)", body)


if __name__ == "__main__":
    main()
