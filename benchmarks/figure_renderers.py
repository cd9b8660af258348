"""The figure of one scene in each renderer beside each method's descriptor image of it, and the README's
opening picture of what the wrist camera sees with ``renderer="pbr"``.

    python benchmarks/figure_renderers.py      # writes docs/renderers.png and docs/wrist_camera_pbr.png

One toolcap scene (development seed 3101, pose 3, random backdrop, 640x480: the size the shipped networks
were trained at), rendered by TinyRenderer, EGL (where this machine has it) and PBR; per renderer the RGB
crop around the part, the optimal descriptors (the oracle: identical in every renderer, since they come
from the geometry) and each shipped network's descriptor image, the first three descriptor dimensions as
colours (the self-supervised network's stretched to its own range).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.evaluation.splits import DEVELOPMENT_SEEDS  # noqa: E402
from don_gym.geometry import project_points  # noqa: E402
from don_gym.perception.descriptor_sources import load_descriptor_source  # noqa: E402
from don_gym.plotting import plot_image_grid  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
METHODS = ("oracle", "toolcap/supervised-edge", "toolcap/supervised-mask", "toolcap/self-supervised")
CROP_PX = (240, 180)


def _as_colours(descriptor_image: np.ndarray, stretch: bool) -> np.ndarray:
    """The first three descriptor dimensions as colours in [0, 1]: as they are (the optimal descriptors and the
    supervised networks' live in [0, 1]), or with ``stretch`` each over its 1st-99th percentile (the
    self-supervised network's have no fixed range)."""
    image = np.asarray(descriptor_image, dtype=np.float64)[..., :3]
    if not stretch:
        return np.clip(image, 0.0, 1.0)
    low, high = np.percentile(image.reshape(-1, image.shape[-1]), [1, 99], axis=0)
    return np.clip((image - low) / np.maximum(high - low, 1e-9), 0.0, 1.0)


def _crop(image: np.ndarray, centre_uv: np.ndarray) -> np.ndarray:
    width, height = CROP_PX
    u0 = int(np.clip(centre_uv[0] - width / 2, 0, image.shape[1] - width))
    v0 = int(np.clip(centre_uv[1] - height / 2, 0, image.shape[0] - height))
    return image[v0 : v0 + height, u0 : u0 + width]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(REPO / "docs"), help="folder for renderers.png and wrist_camera_pbr.png")
    args = parser.parse_args()
    rows: dict[str, dict[str, np.ndarray]] = {}
    for renderer in ("tiny", "egl", "pbr"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an EGL that falls back is skipped below
            env = gym.make("DONToolcapPick-v0", image_size=(640, 480), renderer=renderer, background="random")
        if env.unwrapped.renderer != renderer:
            env.close()
            continue
        obs, info = env.reset(seed=DEVELOPMENT_SEEDS[0], options={"pose_id": 3})
        T_world_object, T_world_camera = info["T_world_object"], info["T_world_camera"]
        centre_camera = (np.linalg.inv(T_world_camera) @ T_world_object[:, 3])[None, :3]
        uv, _ = project_points(env.unwrapped.intrinsics, centre_camera)
        label = {"tiny": "TinyRenderer", "egl": "EGL", "pbr": "PBR (Mitsuba)"}[renderer]
        rows[label] = {"RGB": _crop(obs["rgb"], uv[0])}
        model = env.unwrapped.model
        for method in METHODS:
            source = load_descriptor_source(method, model)
            descriptors = source.descriptor_image(obs, info)
            colours = _as_colours(descriptors, stretch=method.endswith("self-supervised"))
            rows[label][method.split("/")[-1]] = _crop(colours, uv[0])
        if renderer == "pbr":
            from don_gym.io import write_png

            write_png(Path(args.out) / "wrist_camera_pbr.png", np.ascontiguousarray(obs["rgb"][..., ::-1]))
        env.close()
    path = plot_image_grid(
        rows,
        Path(args.out) / "renderers.png",
        title="One toolcap scene per renderer: the wrist camera's crop and each method's descriptor image",
    )
    print(f"wrote {path} and {Path(args.out) / 'wrist_camera_pbr.png'}")


if __name__ == "__main__":
    main()
