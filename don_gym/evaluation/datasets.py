"""The recipe of the evaluation datasets: the scenes of a split's seeds, built the one way every benchmark
builds the data it evaluates on (D435 depth, no fused depth)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from don_gym.data.bin_dataset import build_bin_dataset
from don_gym.data.build import DatasetConfig, build_dataset

__all__ = ["build_evaluation_datasets"]


def build_evaluation_datasets(
    object_name: str | None,
    seeds: Sequence[int],
    out_root: Path,
    split: str,
    scenes: int,
    frames_per_scene: int,
    image_size: tuple[int, int],
    workers: int = 1,
    parts: Mapping[str, int] | None = None,
    backgrounds: str = "classic",
    lighting: str = "fixed",
    progress: bool = True,
    renderer: str = "tiny",
) -> list[Path]:
    """The evaluation datasets of one part, one per seed of a split (``out_root/<split>_<part>_<seed>``): D435
    depth and no fused depth (evaluation reads the sensor and ideal depth only); built, or resumed where a
    run stopped. The benchmarks' one way to make the data they evaluate on. With ``parts`` (``{part: count}``;
    ``object_name`` None), piles of a bin instead (``out_root/<split>_pile_<seed>``, docs/bin.md);
    ``backgrounds`` and ``lighting`` as in :class:`DatasetConfig`, to match the variety a network trained on.
    ``renderer`` other than "tiny": the same scenes (same seeds, poses, depth) with that renderer's RGB, in
    ``out_root/<split>_<renderer>_...`` (the physically rendered test split: ``renderer="pbr"``)."""
    datasets = []
    prefix = split if renderer == "tiny" else f"{split}_{renderer}"
    for seed in seeds:
        config = DatasetConfig(
            **({} if object_name is None else {"object": object_name}),
            scenes=scenes,
            frames_per_scene=frames_per_scene,
            image_size=image_size,
            sensor="d435",
            seed=seed,
            fuse_depth=False,
            backgrounds=backgrounds,
            lighting=lighting,
            renderer=renderer,
        )
        if parts is None:
            datasets.append(Path(out_root) / f"{prefix}_{object_name}_{seed}")
            build_dataset(config, datasets[-1], workers=workers, progress=progress)
        else:
            datasets.append(Path(out_root) / f"{prefix}_pile_{seed}")
            build_bin_dataset(config, parts, datasets[-1], workers=workers, progress=progress)
    return datasets
