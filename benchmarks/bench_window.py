"""Windowed observations (``window_px``) against the whole frame, with DON keypoints at 640x480.

(a) Throughput: env steps/s of ``control="ee"`` with :class:`~don_gym.wrappers.KeypointObservation` of a shipped
    network at 640x480 (D435 sensor model), the whole frame against a ``--window``-pixel window around the part,
    rounds alternating so both see the same machine load; wall and CPU rates. Target: >= 5x.
(b) Agreement: on the tracking protocol's scenes (``--split test``: the test seeds' scenes of
    ``don_gym.evaluation.splits``), the keypoints tracked through each scene's frames as the wrapper tracks them
    (the first frame whole, then each frame's window placed from the last confident keypoints) against the whole
    frame's keypoints on the same frames; the window is cut from the recorded frame, whose pixels a window render
    equals (``tests/test_window.py``). Target: median difference <= 1.5 px.

    python benchmarks/bench_window.py            # full run, records the "window" section of RESULTS.md
    python benchmarks/bench_window.py --quick    # short smoke run (dev scenes), records nothing
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import OtherProcessLoad, record_section, split_line  # noqa: E402

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.frames import open_datasets  # noqa: E402
from don_gym.evaluation.splits import FRAMES_PER_SCENE, SCENES_PER_SEED, SPENT_SEEDS, SPLIT_SEEDS  # noqa: E402
from don_gym.geometry import (  # noqa: E402
    CameraIntrinsics,
    image_window,
    invert_transform,
    project_points,
    transform_points,
    window_origin_px,
)
from don_gym.wrappers import KeypointObservation  # noqa: E402
from don_gym.wrappers.keypoints import WINDOW_MIN_CONFIDENCE  # noqa: E402

FRAME_SIZE = (640, 480)
SPEED_TARGET = 5.0
AGREEMENT_TARGET_PX = 1.5


def keypoint_env(model: str, window_px: int | None, sensor: str = "d435") -> KeypointObservation:
    env = gym.make("DONToolcapPick-v0", control="ee", image_size=FRAME_SIZE, sensor=sensor, window_px=window_px)
    return KeypointObservation(env, model=model, keep_images=False)


def measure(env: gym.Env, steps: int, seed: int) -> dict[str, float]:
    """``steps`` seeded uniform random steps after a reset (resetting at episode ends, untimed); wall and CPU
    seconds per step, the reset's wall seconds, and the others' load."""
    t0 = time.perf_counter()
    env.reset(seed=seed)
    reset_s = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    wall = cpu = 0.0
    with OtherProcessLoad() as load:
        for _ in range(steps):
            action = rng.uniform(-1.0, 1.0, 5).astype(np.float32)
            w0, c0 = time.perf_counter(), time.process_time()
            _, _, terminated, truncated, _ = env.step(action)
            wall += time.perf_counter() - w0
            cpu += time.process_time() - c0
            if terminated or truncated:
                env.reset()
    return {"wall_s": wall / steps, "cpu_s": cpu / steps, "reset_s": reset_s, "load": load.cores}


def run_throughput(model: str, window_px: int, rounds: int, steps: int) -> dict[str, dict[str, float]]:
    envs = {"whole frame": keypoint_env(model, None), f"window {window_px}": keypoint_env(model, window_px)}
    results: dict[str, list[dict[str, float]]] = {name: [] for name in envs}
    for r in range(rounds):
        for name, env in envs.items():
            results[name].append(measure(env, steps, seed=r))
    for env in envs.values():
        env.close()
    return {
        name: {key: float(np.median([m[key] for m in ms if m[key] is not None] or [np.nan])) for key in ms[0]}
        for name, ms in results.items()
    }


def _centre_uv(frame: CameraIntrinsics, T_world_camera: np.ndarray, centre_world: np.ndarray) -> np.ndarray:
    return project_points(frame, transform_points(invert_transform(T_world_camera), centre_world))[0][0]


def scene_differences(wrapper: KeypointObservation, data, scene: int, window_px: int) -> tuple[np.ndarray, int]:
    """(frames - 1, K) pixel distances between the windowed and the whole frame's keypoints of a scene's frames
    after the first, and how many of those frames the window lost every keypoint in."""
    record = data.scenes[scene]
    frame = record.intrinsics
    centre_world, distances, lost = None, [], 0
    for f in range(record.num_frames):
        rgb, depth = data.image(scene, f, "rgb"), data.image(scene, f, "depth")
        T_world_camera = np.asarray(record.T_world_camera[f], dtype=np.float64)
        obs = {"rgb": rgb, "depth": depth, "camera_intrinsics": frame.as_array(), "camera_pose": T_world_camera}
        obs["descriptors"] = wrapper.source.descriptor_image(obs)
        whole = wrapper.settings.locate(obs, wrapper.source, wrapper.reference_descriptors)
        if centre_world is None:  # the wrapper's reset: the whole frame
            found = whole
        else:
            window = image_window(frame, _centre_uv(frame, T_world_camera, centre_world), window_px)
            u0, v0 = window_origin_px(frame, window)
            rows, columns = slice(v0, v0 + window.height), slice(u0, u0 + window.width)
            cut = {"rgb": np.ascontiguousarray(rgb[rows, columns]), "depth": np.ascontiguousarray(depth[rows, columns])}
            cut |= {"camera_intrinsics": window.as_array(), "camera_pose": T_world_camera}
            cut["descriptors"] = wrapper.source.descriptor_image(cut)
            found = wrapper.settings.locate(cut, wrapper.source, wrapper.reference_descriptors)
            distances.append(np.linalg.norm(found.pixels + [u0, v0] - whole.pixels, axis=1))
            lost += int(not np.any(found.confidence >= WINDOW_MIN_CONFIDENCE))
        seen = found.confidence >= WINDOW_MIN_CONFIDENCE
        if seen.any():
            centre_world = found.points_world[seen].mean(axis=0)
    return np.array(distances), lost


def run_agreement(
    model: str, window_px: int, split: str, scenes: int, frames: int, work: Path
) -> dict[str, float | int]:
    wrapper = keypoint_env(model, None)
    datasets = build_evaluation_datasets("toolcap", SPLIT_SEEDS[split], work, split, scenes, frames, FRAME_SIZE)
    distances, lost, frames_compared = [], 0, 0
    for data in open_datasets(datasets):
        for scene in range(len(data.scenes)):
            d, scene_lost = scene_differences(wrapper, data, scene, window_px)
            distances.append(d.reshape(-1))
            lost += scene_lost
            frames_compared += len(d)
    wrapper.close()
    all_d = np.concatenate(distances)
    return {
        "median_px": float(np.median(all_d)),
        "p90_px": float(np.percentile(all_d, 90)),
        "max_px": float(np.max(all_d)),
        "within_target": float(np.mean(all_d <= AGREEMENT_TARGET_PX)),
        "keypoints": int(len(all_d)),
        "frames": frames_compared,
        "lost_frames": lost,
    }


def report(model: str, window_px: int, speed: dict, agreement: dict, split: str) -> tuple[str, bool]:
    whole, windowed = speed["whole frame"], speed[f"window {window_px}"]
    wall_ratio, cpu_ratio = whole["wall_s"] / windowed["wall_s"], whole["cpu_s"] / windowed["cpu_s"]
    met_speed, met_agreement = wall_ratio >= SPEED_TARGET, agreement["median_px"] <= AGREEMENT_TARGET_PX
    lines = [
        f'DON keypoints of `{model}` at {FRAME_SIZE[0]}x{FRAME_SIZE[1]}, `control="ee"`, D435 sensor model, '
        f"torch threads {torch.get_num_threads()}.",
        "",
        "| observation | steps/s (wall) | steps/s (CPU) | ms/step (wall) | reset ms (wall) | others' load (cores) |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in speed.items():
        lines.append(
            f"| {name} | {1 / m['wall_s']:.2f} | {1 / m['cpu_s']:.2f} | {1000 * m['wall_s']:.0f} | "
            f"{1000 * m['reset_s']:.0f} | {m['load']:.2f} |"
        )
    lines += [
        "",
        f"Speed-up of the window: {wall_ratio:.1f}x wall, {cpu_ratio:.1f}x CPU (target >= {SPEED_TARGET:.0f}x wall: "
        f"{'met' if met_speed else 'NOT met'}). A windowed reset renders and runs the DON on the whole frame once.",
        "",
        f"Keypoints tracked through the windows against the whole frame's, {split} scenes "
        f"({agreement['frames']} frames after each scene's first, {agreement['keypoints']} keypoints): median "
        f"{agreement['median_px']:.2f} px, 90th percentile {agreement['p90_px']:.2f} px, max {agreement['max_px']:.1f} "
        f"px, {100 * agreement['within_target']:.0f}% within {AGREEMENT_TARGET_PX} px; frames where the window lost "
        f"every keypoint: {agreement['lost_frames']} (target median <= {AGREEMENT_TARGET_PX} px: "
        f"{'met' if met_agreement else 'NOT met'}).",
        "",
        split_line(split, SPLIT_SEEDS[split], SPENT_SEEDS),
    ]
    return "\n".join(lines), met_speed and met_agreement


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="few steps and scenes, print only")
    parser.add_argument("--model", default="toolcap/supervised-edge", help="shipped network or checkpoint")
    parser.add_argument("--window", type=int, default=192, help="window side in pixels")
    parser.add_argument("--rounds", type=int, default=None, help="alternating rounds (default 3, quick 1)")
    parser.add_argument("--steps", type=int, default=None, help="steps per round (default 40, quick 5)")
    parser.add_argument("--split", choices=sorted(SPLIT_SEEDS), default=None, help="scenes (default test, quick dev)")
    parser.add_argument("--work", type=Path, default=None, help="where the scenes are built (default: a temp dir)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: a shared machine)")
    args = parser.parse_args(argv)
    torch.set_num_threads(max(1, args.threads))
    rounds, steps = args.rounds or (1 if args.quick else 3), args.steps or (5 if args.quick else 40)
    split = args.split or ("dev" if args.quick else "test")
    scenes, frames = (1, 4) if args.quick else (SCENES_PER_SEED, FRAMES_PER_SCENE)

    speed = run_throughput(args.model, args.window, rounds, steps)
    with tempfile.TemporaryDirectory() as temp:
        work = args.work or Path(temp)
        agreement = run_agreement(args.model, args.window, split, scenes, frames, work)
    body, met = report(args.model, args.window, speed, agreement, split)
    print(body)
    if not args.quick:
        record_section("window", "Windowed observations: DON keypoints at 640x480 (bench_window)", body)
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
