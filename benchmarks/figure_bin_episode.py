"""A pile being cleared: the frames of one bin episode (a development pile), each with the grasp (or push) the agent
is about to make drawn on the wrist camera's image (the finger pads and the line they close along, the believed
+axis), its kind and its outcome below. Writes ``benchmarks/figures/bin_episode.png`` for docs/bin.md; measures nothing.

    python benchmarks/figure_bin_episode.py                 # the oracle on development pile 9 (topples)
    python benchmarks/figure_bin_episode.py --pile 3 --method oracle-descriptors --out /tmp/episode.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import FIGURES  # noqa: E402

from don_gym import plotting  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.evaluation.bin_benchmark import BinBenchmarkConfig, make_agent, pile_seed  # noqa: E402
from don_gym.evaluation.splits import BIN_DEVELOPMENT_SEED  # noqa: E402
from don_gym.geometry import CameraIntrinsics, project_points, transform_points  # noqa: E402
from don_gym.sim.bin_env import BinPickEnv  # noqa: E402
from don_gym.sim.bin_task import grasp_opening_m  # noqa: E402
from don_gym.sim.script import STEP_KINDS  # noqa: E402

#: Length (m) of the drawn +axis arrow.
ARROW_M = 0.04


def grasp_overlay(action: np.ndarray, obs: dict, opening_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(fingers_uv, axis_uv), each (2, 2) pixels: the two pads of the grasp ``action`` opened to ``opening_m`` and
    an arrow along its believed +axis, projected with the observation's (reported) camera pose."""
    kind = STEP_KINDS[int(round(float(action[4])))]
    yaw = float(action[3])
    closing = yaw + (np.pi / 2 if kind == "along" else 0.0)  # the fingers close across this yaw
    across = np.array([-np.sin(closing), np.cos(closing), 0.0])
    point = np.asarray(action[:3], dtype=np.float64)
    world = np.stack(
        [
            point - across * opening_m / 2,
            point + across * opening_m / 2,
            point,
            point + ARROW_M * np.array([np.cos(yaw), np.sin(yaw), 0.0]),
        ]
    )
    T_camera_world = np.linalg.inv(np.asarray(obs["camera_pose"], dtype=np.float64))
    intrinsics = CameraIntrinsics.from_array(obs["camera_intrinsics"])
    uv, _ = project_points(intrinsics, transform_points(T_camera_world, world))
    return uv[:2], uv[2:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pile", type=int, default=9, help="development pile (seed BIN_DEVELOPMENT_SEED + pile)")
    parser.add_argument("--method", default="oracle", help="the bin benchmark's method (default: oracle)")
    parser.add_argument("--out", default=str(FIGURES / "bin_episode.png"), help="the figure's path")
    args = parser.parse_args()
    config = BinBenchmarkConfig(methods=(args.method,), image_size=(320, 240))
    env = BinPickEnv(**config.env_kwargs())
    try:
        agent = make_agent(env, args.method)
        seed = pile_seed(BIN_DEVELOPMENT_SEED, args.pile)
        obs, info = env.reset(seed=seed)
        agent.reset()
        frames, step = [], 1
        while True:
            try:
                action = agent.act(obs, info)
            except DonGymError as exc:
                frames.append({"rgb": obs["rgb"], "title": f"agent gave up: {exc}"})
                break
            # The frame shows the image the grasp was chosen on, the grasp drawn, and what came of it.
            kind = STEP_KINDS[int(round(float(action[4])))]
            # A push at a standing part is a topple; elsewhere it rolls a part away from a wall.
            label = "push (topple)" if kind == "push" and agent.last_ranking[0].kind == "standing" else kind
            opening = grasp_opening_m(env.model, kind, action[:2], float(action[3]))
            fingers, axis = grasp_overlay(action, obs, opening)
            frame = {"rgb": obs["rgb"], "fingers_uv": fingers, "axis_uv": axis}
            # Env steps, not attempts: a push is no attempt, and a set-down and its regrasp are one.
            phase = "regrasp at the station" if info["phase"] == "regrasp" else f"step {step}"
            obs, _, terminated, truncated, info = env.step(action)
            agent.observe_outcome(info["outcome"])
            frames.append(frame | {"title": f"{phase}: {label} -> {info['outcome']}"})
            step += 1
            if terminated or truncated:
                frames.append({"rgb": obs["rgb"], "title": f"end: {info['end_reason']}"})
                break
    finally:
        env.close()
    plotting.plot_episode_frames(frames, args.out, title=f"{args.method} clearing development pile {args.pile}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
