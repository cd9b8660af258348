"""Simulation speed of the pick-and-place env against panda-gym, and with the wrist RGB-D camera.

(a) ``control="ee"`` without images against panda-gym's ``PandaPickAndPlace-v3`` (target: >= 1.0x);
(b) with the wrist camera, TinyRenderer and EGL (target: >= 40 steps/s at 160x120 on 2 cores);
(c) wall time of one scripted grasp-and-place episode.

    python benchmarks/bench_env.py            # full run, records the "env" section of RESULTS.md
    python benchmarks/bench_env.py --quick    # short smoke run, records nothing

The baseline is a benchmark-only dependency: ``pip install panda-gym`` first (a full run without it
stops before measuring anything; ``--quick`` runs without it).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import OtherProcessLoad, record_section  # noqa: E402

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.sim.bullet import silence_c_stdout  # noqa: E402


def measure(env: gym.Env, steps: int, seed: int) -> dict[str, float]:
    """Run ``steps`` random steps (resetting at episode ends); wall and CPU rates, others' load."""
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    with OtherProcessLoad() as load:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        for action in actions:
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    # Unknown (no /proc/stat) shows as nan rather than as a machine that was ours.
    others = float("nan") if load.cores is None else load.cores
    return {"wall": steps / wall, "cpu": steps / cpu, "others": others}


def summarise(rounds: list[dict[str, float]]) -> dict[str, float]:
    return {key: float(np.median([r[key] for r in rounds])) for key in rounds[0]}


def make_panda_gym() -> tuple[gym.Env | None, str]:
    try:
        with silence_c_stdout():
            import panda_gym  # noqa: F401

            env = gym.make("PandaPickAndPlace-v3")
            env.reset(seed=0)
        return env, f"panda-gym {panda_gym.__version__}"
    except Exception as exc:  # not installed, or broken under this gymnasium
        return None, f"panda-gym unavailable ({type(exc).__name__}: {exc})"


def egl_description(opengl_renderers: set[str]) -> str:
    """What EGL rendered with on this machine, as the EGL plugin reported it (``Bullet.opengl_renderer``)."""
    if not opengl_renderers:
        return "EGL was unavailable here, so its rows fell back to TinyRenderer."
    names = ", ".join(f"`{name}`" for name in sorted(opengl_renderers))
    software_rasterisers = ("llvmpipe", "softpipe", "swiftshader")
    software = any(word in name.lower() for name in opengl_renderers for word in software_rasterisers)
    return f"EGL rendered with {names}" + (" (software OpenGL on the CPU)." if software else ".")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="few steps, print only (RESULTS.md untouched)")
    parser.add_argument(
        "--rounds", type=int, default=None, help="alternating rounds per comparison (default 5, quick 1)"
    )
    parser.add_argument("--steps", type=int, default=None, help="steps per round without images (default 1000)")
    parser.add_argument("--camera-steps", type=int, default=None, help="steps per round with images (default 150)")
    args = parser.parse_args(argv)
    rounds = args.rounds or (1 if args.quick else 5)
    steps = args.steps or (200 if args.quick else 1000)
    camera_steps = args.camera_steps or (30 if args.quick else 150)
    load_before = os.getloadavg()[0]

    # (a) no images vs panda-gym (the baseline; `pip install panda-gym`, benchmark only), alternating rounds
    # so both see the same machine load. Both: seeded uniform random actions, reset whenever an episode ends
    # (ours truncates after 100 steps, panda-gym after 50), 25 Hz control. Ours simulates 10 steps of 4 ms with
    # up to 150 solver iterations, a V-HACD/slab steel part and null-space IK; panda-gym 20 steps of 2 ms with
    # PyBullet's defaults.
    baseline, baseline_name = make_panda_gym()
    if baseline is None and not args.quick:
        # A record without its baseline would read "target NOT met" for want of a comparison.
        print(f"bench_env: {baseline_name}; `pip install panda-gym` (the baseline), or run --quick", file=sys.stderr)
        return 2
    ours = gym.make("DONToolcapPick-v0", control="ee", image_size=None, sensor="ideal")
    ours_rounds, base_rounds = [], []
    for r in range(rounds):
        ours_rounds.append(measure(ours, steps, seed=r))
        if baseline is not None:
            with silence_c_stdout():
                base_rounds.append(measure(baseline, steps, seed=r))
    ours.close()
    if baseline is not None:
        baseline.close()
    ours_a = summarise(ours_rounds)
    base_a = summarise(base_rounds) if base_rounds else None

    # (b) wrist camera 160x120: TinyRenderer and EGL, ideal depth and the D435 model.
    camera_rows = []
    opengl_renderers = set()
    configs = [((160, 120), r, s) for r in ("tiny", "egl") for s in ("ideal", "d435")]
    # 640x480 with the default sensor only: where the renderers' costs differ most.
    configs += [((640, 480), r, "d435") for r in ("tiny", "egl")]
    for size, renderer, sensor in configs:
        with warnings.catch_warnings(record=True) as caught, silence_c_stdout():
            warnings.simplefilter("always")
            env = gym.make("DONToolcapPick-v0", control="ee", image_size=size, sensor=sensor, renderer=renderer)
        used = env.unwrapped.renderer
        if used == "egl":
            opengl_renderers.add(env.unwrapped.sim.opengl_renderer or "an OpenGL renderer that did not name itself")
        n = camera_steps if size == (160, 120) else max(10, camera_steps // 3)
        result = summarise([measure(env, n, seed=r) for r in range(max(1, rounds // 2))])
        with silence_c_stdout():
            env.close()
        note = "" if used == renderer else f" (fell back to {used}: {caught[-1].message if caught else ''})"
        camera_rows.append((f"{size[0]}x{size[1]}", renderer + note, sensor, result))

    # (c) one scripted grasp-and-place episode.
    grasp = gym.make("DONToolcapPick-v0", control="grasp", image_size=(160, 120)).unwrapped
    episode_s, sim_s = [], []
    for k in range(2 if args.quick else 8):
        grasp.reset(options={"pose_id": k})
        start = time.perf_counter()
        _, _, _, _, info = grasp.step(grasp.oracle_action())
        episode_s.append(time.perf_counter() - start)
        sim_s.append(info["sim_time_s"])
    grasp.close()
    load_after = os.getloadavg()[0]

    lines = [
        "Steps/s are wall-clock, median over rounds (ours and the baseline alternate); *CPU* = steps per "
        "CPU-second of this process; *others* = cores other processes kept busy meanwhile (0 = the machine "
        f"was ours). Load average (1 min) before / after: {load_before:.2f} / {load_after:.2f}.",
        "",
        f'(a) `control="ee"`, no images, {steps} random steps x {rounds} rounds; baseline {baseline_name} '
        "`PandaPickAndPlace-v3` (benchmark-only dependency, not in pyproject).",
        "",
        "| env | steps/s | steps/CPU-s | others (cores) | vs baseline |",
        "|---|---:|---:|---:|---:|",
        f"| DONToolcapPick-v0 ee, no images | {ours_a['wall']:.0f} | {ours_a['cpu']:.0f} | {ours_a['others']:.2f} | "
        + (f"{ours_a['wall'] / base_a['wall']:.2f}x |" if base_a else "n/a |"),
    ]
    if base_a:
        lines.append(
            f"| PandaPickAndPlace-v3 (baseline) | {base_a['wall']:.0f} | {base_a['cpu']:.0f} | "
            f"{base_a['others']:.2f} | 1.00x |"
        )
    lines += [
        "",
        f"Target >= 1.0x: {'met' if base_a and ours_a['wall'] >= base_a['wall'] else 'NOT met'}"
        + (
            f" ({ours_a['wall'] / base_a['wall']:.2f}x wall, {ours_a['cpu'] / base_a['cpu']:.2f}x CPU)."
            if base_a
            else "."
        ),
        "",
        f'(b) `control="ee"` with the wrist RGB-D camera, {camera_steps} random steps (640x480: a third) x '
        f"{max(1, rounds // 2)} rounds. TinyRenderer is the default everywhere; {egl_description(opengl_renderers)}",
        "",
        "| image | renderer | depth sensor | steps/s | steps/CPU-s | others (cores) | >= 40 steps/s |",
        "|---|---|---|---:|---:|---:|---|",
    ]
    for size, renderer, sensor, result in camera_rows:
        target = ("yes" if result["wall"] >= 40 else "no") if size == "160x120" else "(no target)"
        lines.append(
            f"| {size} | {renderer} | {sensor} | {result['wall']:.1f} | {result['cpu']:.1f} | "
            f"{result['others']:.2f} | {target} |"
        )
    lines += [
        "",
        f'(c) `control="grasp"`, oracle action, 160x120 D435 observations: one scripted grasp-and-place '
        f"episode takes {np.median(episode_s):.2f} s wall (median of {len(episode_s)}, max {max(episode_s):.2f} s) "
        f"for {np.median(sim_s):.1f} s of simulated time.",
    ]
    body = "\n".join(lines)
    print(body)
    if not args.quick:
        record_section("env", "Simulation speed (PyBullet pick-and-place env)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
