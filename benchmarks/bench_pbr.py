"""Physically based rendering (``renderer="pbr"``) against TinyRenderer: speed, noise, and the PBR test split.

(a) ``noise``: one wrist-camera frame (640x480) path-traced at 4 to 64 samples per pixel, with and without
    the denoiser, against a 512-sample reference of the same frame: RMSE in 8-bit grey levels over the whole
    frame and over the part, and the time per frame. The chosen setting (:class:`don_gym.sim.pbr.PbrSettings`)
    is marked.
(b) ``speed``: frames per second of the env's observation at 640x480 and at the envs' default 160x120, PBR
    at the chosen setting against TinyRenderer in the same run (the ratio is the figure).
(c) ``build``: the PBR test split built as the benchmarks build it (the test seeds' 24 scenes x 12 frames per
    part, 640x480, D435 depth: ``don_gym.evaluation.datasets.build_evaluation_datasets(..., renderer="pbr")``),
    timed; target: at most 15 minutes per part on 2 cores. The datasets land in ``--work`` and are the ones
    ``bench_grasp.py --renderer pbr`` evaluates on.

    python benchmarks/bench_pbr.py                      # all three: RESULTS.md sections pbr-noise, pbr-speed, pbr-build
    python benchmarks/bench_pbr.py --parts noise speed  # without the build (each part records its own section)
    python benchmarks/bench_pbr.py --quick              # smoke run at 160x120, records nothing

Time (b) and (c) on a machine nothing else loads (each table says how many cores other processes kept busy):
the build's time is only meaningful for a fresh ``--work``.

Development seed 3101 gives the frames of (a) and (b); (c) builds the test seeds' scenes (building looks at
no result, so it spends no seed).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import OtherProcessLoad, record_section  # noqa: E402

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.evaluation.datasets import build_evaluation_datasets  # noqa: E402
from don_gym.evaluation.splits import DEVELOPMENT_SEEDS, FRAMES_PER_SCENE, SCENES_PER_SEED, TEST_SEEDS  # noqa: E402
from don_gym.sim.camera import body_mask, render_camera  # noqa: E402
from don_gym.sim.pbr import DENOISERS, PbrSettings, denoise, expose  # noqa: E402

SAMPLES = (4, 8, 16, 32, 64)
REFERENCE_SAMPLES = 512
BUILD_TARGET_S = 15 * 60


def _env(renderer: str, size: tuple[int, int]) -> gym.Env:
    env = gym.make("DONToolcapPick-v0", image_size=size, renderer=renderer, background="random")
    env.reset(seed=DEVELOPMENT_SEEDS[0], options={"pose_id": 3})
    return env


def _noiseless(radiance: np.ndarray, reference_gain_from: np.ndarray) -> np.ndarray:
    """8-bit sRGB of ``radiance`` exposed as the reference is (same gain), without sensor noise."""
    settings = PbrSettings(full_well_electrons=1e12, read_noise=0.0)
    luminance = lambda image: np.exp(np.mean(np.log(np.maximum(image @ [0.2126, 0.7152, 0.0722], 1e-4))))  # noqa: E731
    gain = luminance(radiance) / luminance(reference_gain_from)
    return expose(radiance, settings, np.random.default_rng(0), gain=gain).astype(np.float64)


def noise(size: tuple[int, int], samples: tuple[int, ...], reference_samples: int) -> str:
    env = _env("pbr", size)
    unwrapped = env.unwrapped
    client, intrinsics = unwrapped.sim.client, unwrapped.intrinsics
    T_world_camera = unwrapped.robot.camera_pose()
    with unwrapped.robot.hidden():
        _, _, segmentation = render_camera(client, intrinsics, T_world_camera, renderer="tiny")
        part = body_mask(segmentation, unwrapped.task.part.body_id)
        render = client.pbr.render_layers
        reference = render(client, intrinsics, T_world_camera, samples_per_pixel=reference_samples, seed=99)
        reference = reference["radiance"]
        reference_image = _noiseless(reference, reference)
        chosen = PbrSettings()
        rows = []
        for spp in samples:
            start = time.perf_counter()
            layers = render(client, intrinsics, T_world_camera, samples_per_pixel=spp, seed=1)
            render_s = time.perf_counter() - start
            for denoiser in DENOISERS:
                start = time.perf_counter()
                image = _noiseless(denoise(layers, denoiser), reference)
                seconds = render_s + time.perf_counter() - start
                error = image - reference_image
                mark = " (chosen)" if (spp, denoiser) == (chosen.samples_per_pixel, chosen.denoiser) else ""
                rows.append(
                    f"| {spp}{mark} | {denoiser} | {seconds:.2f} | "
                    f"{np.sqrt(np.mean(error**2)):.1f} | {np.sqrt(np.mean(error[part] ** 2)):.1f} |"
                )
    env.close()
    return (
        f"**(a) Noise against a {reference_samples}-sample reference** (one {size[0]}x{size[1]} wrist frame, "
        f"development seed {DEVELOPMENT_SEEDS[0]}, pose 3, random backdrop; RMSE in 8-bit grey levels after the "
        f"camera's exposure, without its sensor noise; {int(part.sum())} part pixels)\n\n"
        "| samples per pixel | denoiser | s per frame | RMSE frame | RMSE part |\n|---|---|---|---|---|\n"
        + "\n".join(rows)
    )


def _observation_rate(renderer: str, size: tuple[int, int], frames: int) -> tuple[float, float]:
    env = _env(renderer, size)
    observe = env.unwrapped._observation
    observe()  # Mitsuba compiles its kernels at the first frame
    with OtherProcessLoad() as load:
        start = time.perf_counter()
        for _ in range(frames):
            observe()
        rate = frames / (time.perf_counter() - start)
    env.close()
    return rate, float("nan") if load.cores is None else load.cores


def speed(sizes: list[tuple[int, int]], frames: int) -> str:
    rows = []
    for size in sizes:
        tiny, tiny_load = _observation_rate("tiny", size, frames * 10)
        pbr, pbr_load = _observation_rate("pbr", size, frames)
        rows.append(
            f"| {size[0]}x{size[1]} | {tiny:.1f} | {pbr:.2f} | {tiny / pbr:.0f}x | {max(tiny_load, pbr_load):.1f} |"
        )
    settings = PbrSettings()
    return (
        f"**(b) Observation rate** (frames per second of the env's wrist observation: render, depth-sensor model; "
        f"PBR at {settings.samples_per_pixel} samples per pixel, denoiser {settings.denoiser}, "
        f"{settings.max_depth} bounces)\n\n"
        "| size | TinyRenderer frames/s | PBR frames/s | PBR slower by | other processes' cores |\n"
        "|---|---|---|---|---|\n" + "\n".join(rows)
    )


def _scenes_on_disk(datasets: list[Path]) -> int:
    return sum(len(list((d / "scenes").glob("scene_*"))) for d in datasets if (d / "scenes").is_dir())


def build(work: Path, objects: list[str], scenes: int, frames: int, size: tuple[int, int], workers: int) -> str:
    rows = []
    total = scenes * frames * len(TEST_SEEDS)
    for object_name in objects:
        names = [work / f"test_pbr_{object_name}_{seed}" for seed in TEST_SEEDS]
        before = _scenes_on_disk(names)
        start = time.perf_counter()
        with OtherProcessLoad() as load:
            datasets = build_evaluation_datasets(
                object_name, TEST_SEEDS, work, "test", scenes, frames, size, workers=workers, renderer="pbr"
            )
        seconds = time.perf_counter() - start
        built = (_scenes_on_disk(datasets) - before) * frames
        others = f"{load.cores:.1f}" if load.cores is not None else "nan"
        if built == 0:
            rows.append(f"| {object_name} | 0 of {total} (complete before this run) | | | | | {others} |")
            continue
        projected_s = total * seconds / built
        verdict = ("met" if projected_s <= BUILD_TARGET_S else "MISSED") + ("" if built == total else " (projected)")
        rows.append(
            f"| {object_name} | {built} of {total} | {seconds / 60:.1f} | {built / seconds:.2f} | "
            f"{projected_s / 60:.1f} | {verdict} | {others} |"
        )
    return (
        f"**(c) The PBR test split** (test seeds {list(TEST_SEEDS)}, {scenes} scenes x {frames} frames each, "
        f"{size[0]}x{size[1]}, D435 depth, {workers} worker processes, into `{work}`; target <= "
        f"{BUILD_TARGET_S // 60} min for a part's {total} frames. Scenes already on disk are kept, so the time is "
        "that of the frames this run built, and the whole set's time is projected from their rate where it built "
        "fewer)\n\n"
        "| part | frames built | minutes | frames/s | minutes for all (projected) | target | other processes' cores |\n"
        "|---|---|---|---|---|---|---|\n" + "\n".join(rows)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", choices=("noise", "speed", "build"), default=["noise", "speed", "build"])
    parser.add_argument("--work", default="runs/bench_grasp", help="where the PBR test split is built (bench_grasp's)")
    parser.add_argument("--objects", nargs="+", default=["toolcap", "shaft"])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="160x120, few samples and frames; records nothing")
    args = parser.parse_args()
    record = (lambda *a, **k: None) if args.quick else record_section
    gpu_note = "\n\nNo GPU was lent to this run: Mitsuba's CUDA variant is untried here."
    if args.quick:
        size, sizes, samples, reference, frames = (160, 120), [(160, 120)], (4, 16), 64, 2
    else:
        size, sizes, samples, reference, frames = (640, 480), [(640, 480), (160, 120)], SAMPLES, REFERENCE_SAMPLES, 8
    if "noise" in args.parts:
        body = noise(size, samples, reference)
        print(body + "\n")
        record("pbr-noise", "Physically based rendering: noise against samples and denoising", body, after="env")
    if "speed" in args.parts:
        body = speed(sizes, frames) + gpu_note
        print(body + "\n")
        record(
            "pbr-speed", "Physically based rendering: frames per second against TinyRenderer", body, after="pbr-noise"
        )
    if "build" in args.parts:
        if args.quick:
            import tempfile

            work, scenes, frames_per_scene = Path(tempfile.mkdtemp(prefix="don_gym_bench_pbr_")), 1, 2
        else:
            work, scenes, frames_per_scene = Path(args.work), SCENES_PER_SEED, FRAMES_PER_SCENE
        body = build(work, args.objects, scenes, frames_per_scene, size, args.workers)
        print(body + "\n")
        record("pbr-build", "Physically based rendering: building the PBR test split", body, after="pbr-speed")


if __name__ == "__main__":
    main()
