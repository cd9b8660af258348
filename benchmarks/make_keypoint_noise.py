"""Measure the shipped DONs' keypoint errors and write their default noise models (a model of each DON
for :class:`don_gym.wrappers.SimulatedKeypoints`) next to the networks, as
``don_gym/shipped/<object>/<method>.keypoint-noise.npz``.

    python benchmarks/make_keypoint_noise.py                          # every shipped network
    python benchmarks/make_keypoint_noise.py toolcap/supervised-edge  # one
    python benchmarks/make_keypoint_noise.py --quick --out /tmp/noise # smoke run, not into the package

Each network is measured at the image size it was trained at, sensor d435, on held-out seeds
(:func:`don_gym.wrappers.simulated_keypoints.measure_keypoint_noise`); rerun after retraining a network.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from don_gym.errors import DonGymError
from don_gym.wrappers.simulated_keypoints import NOISE_SUFFIX, measure_keypoint_noise, shipped_noise_path
from don_gym.zoo import read_don_metadata, shipped_names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="shipped network names (default: all)")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--steps-per-episode", type=int, default=8)
    parser.add_argument("--seed", type=int, default=20_000, help="episode i is reset with seed + i")
    parser.add_argument("--sensor", default="d435")
    parser.add_argument("--out", type=Path, default=None, help="directory for the files (default: the package)")
    parser.add_argument("--quick", action="store_true", help="3 episodes of 2 steps")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.quick:
        args.episodes, args.steps_per_episode = 3, 2
    names = args.names or shipped_names()
    for name in names:
        if name not in shipped_names():
            parser.error(f"{name!r} is not a shipped network; available: {', '.join(shipped_names())}")
    for name in names:
        metadata = read_don_metadata(name)
        try:
            noise = measure_keypoint_noise(
                name,
                object=metadata.object_name,
                image_size=tuple(metadata.image_size),
                sensor=args.sensor,
                episodes=args.episodes,
                steps_per_episode=args.steps_per_episode,
                seed=args.seed,
            )
        except DonGymError as exc:
            print(f"{name}: {exc}", file=sys.stderr)
            return 2
        path = shipped_noise_path(name) if args.out is None else args.out / f"{name}{NOISE_SUFFIX}"
        noise.save(path)
        print(f"{name} -> {path}\n{json.dumps(noise.summary(), indent=1)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
