"""Dataset plumbing shared by the tracking and pose evaluations: opening the datasets to pool, the part they
show, a frame as an env observation, what a method's results rest on, and a scene's background in one line.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.data.dataset import DONDataset
from don_gym.errors import DonGymError
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import DescriptorSource

__all__ = [
    "background_description",
    "dataset_object",
    "frame_observation",
    "open_datasets",
    "pooled_object",
    "source_info",
]


def open_datasets(datasets: DONDataset | str | Path | Sequence[DONDataset | str | Path]) -> list[DONDataset]:
    """The datasets to pool, opened, each once, all of one part."""
    items = [datasets] if isinstance(datasets, (DONDataset, str, Path)) else list(datasets)
    if not items:
        raise DonGymError("no dataset to evaluate; give one or more dataset directories")
    opened = [d if isinstance(d, DONDataset) else DONDataset(d) for d in items]
    roots = [d.root.resolve() for d in opened]
    if len(set(roots)) != len(roots):
        raise DonGymError(f"datasets {[str(d.root) for d in opened]}: each dataset may be given once")
    return opened


def dataset_object(dataset: DONDataset) -> ObjectModel:
    """The object of a dataset, loaded as it was built and checked to be its part (:meth:`DONDataset.object_model`)."""
    return dataset.object_model()


def pooled_object(datasets: Sequence[DONDataset]) -> ObjectModel:
    """The one part that pooled datasets show (:func:`dataset_object` of the first); datasets of different parts
    are a :class:`DonGymError` naming both and how their shapes differ."""
    model = dataset_object(datasets[0])
    for other in datasets[1:]:
        differences = model.shape_signature.differences(dataset_object(other).shape_signature)
        if differences:
            raise DonGymError(
                f"datasets {datasets[0].root} and {other.root} show different parts ({'; '.join(differences)}); "
                "pool only datasets of one part"
            )
    return model


def frame_observation(dataset: DONDataset, scene: int, frame: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A dataset frame as an env observation and info, for
    :class:`don_gym.perception.descriptor_sources.DescriptorSource`:
    ``rgb``, ``depth`` (the *ideal* depth, so the oracle's occlusion test is exact) and
    ``camera_intrinsics``; info holds the true ``T_world_object`` and ``T_world_camera``."""
    record = dataset.scenes[scene]
    obs = {
        "rgb": dataset.image(scene, frame, "rgb"),
        "depth": dataset.image(scene, frame, "depth_ideal"),
        "camera_intrinsics": record.intrinsics.as_array().astype(np.float32),
    }
    info = {"T_world_object": record.T_world_object, "T_world_camera": record.T_world_camera[frame]}
    if dataset.scene_kind == "bin":  # a pile: every instance, for the oracle of each part
        info["instances"] = [i for i in record.instances if "T_world_object" in i]
    return obs, info


def source_info(source: DescriptorSource, border_margin_px: int | None = None) -> dict[str, Any]:
    """What a method's results rest on, for a report; with ``border_margin_px``, the border margin (px) its
    matches used."""
    info: dict[str, Any] = {"method": source.method, "descriptor_dim": source.descriptor_dim}
    if border_margin_px is not None:
        info["border_margin_px"] = int(border_margin_px)
    metadata = getattr(source, "metadata", None)
    if metadata is not None:
        info |= {
            "arch": metadata.arch,
            "training_image_size": list(metadata.image_size),
            "training_steps": metadata.training_steps,
            "renderer": metadata.renderer,
        }
    return info


def background_description(background: Mapping[str, Any] | None) -> str:
    """One line for a scene's ``background`` entry of ``scene.json``: per surface its texture family (when
    recorded) and mean colour, e.g. ``table checks (201, 40, 38), floor noise (90, 160, 150), cradle (...)``;
    a recorded ``description`` as it is; ``"-"`` when absent."""
    if not background:
        return "-"
    if isinstance(background.get("description"), str) and background["description"]:
        return str(background["description"])

    def colour(value: Any) -> str:
        values = np.asarray(value, dtype=np.float64).ravel()[:3]
        scale = 255.0 if values.size and values.max() <= 1.0 else 1.0  # rgba in [0, 1] as 0-255
        return "(" + ", ".join(f"{v * scale:.0f}" for v in values) + ")"

    parts, used = [], set()
    for surface in ("table", "floor"):
        family, mean = background.get(f"{surface}_texture_family"), background.get(f"{surface}_texture_mean_rgb")
        if family is None and mean is None:
            continue
        used |= {f"{surface}_texture_family", f"{surface}_texture_mean_rgb"}
        parts.append(
            " ".join([surface, *([str(family)] if family else []), *([colour(mean)] if mean is not None else [])])
        )
    if background.get("cradle_rgba") is not None:
        used.add("cradle_rgba")
        parts.append(f"cradle {colour(background['cradle_rgba'])}")
    parts += [f"{key} {value}" for key, value in background.items() if key not in used]
    return ", ".join(parts)
