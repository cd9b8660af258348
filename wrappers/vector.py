"""Descriptor and keypoint observations for a gymnasium vector env, with one DON pass per batch.

:class:`VectorKeypointObservation` wraps a ``gymnasium.vector`` env of plain don_gym envs (with
images) and adds what :class:`~don_gym.wrappers.KeypointObservation` adds to each sub-env's
observation, but runs a network on the stacked images of all sub-envs at once
(:meth:`~don_gym.perception.descriptor_sources.NetworkDescriptors.descriptor_images`), on ``device``;
the keypoints of each image then come from :func:`don_gym.perception.keypoints.locate_keypoints` as in the
per-env wrapper, so both give the same observations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, SyncVectorEnv, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from don_gym.errors import DonGymError
from don_gym.learning.model import DenseObjectNet
from don_gym.perception.descriptor_sources import DescriptorSource, NetworkDescriptors
from don_gym.wrappers.descriptors import DESCRIPTOR_BOUND
from don_gym.wrappers.keypoints import KeypointObservation


def unbatch_info(infos: Mapping[str, Any], index: int) -> dict[str, Any]:
    """The info dict of sub-env ``index`` from a vector env's batched infos (``key`` / ``_key`` mask pairs)."""
    out: dict[str, Any] = {}
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get(f"_{key}")
        if mask is not None and not bool(mask[index]):
            continue
        out[key] = unbatch_info(value, index) if isinstance(value, Mapping) else value[index]
    return out


def _resolve_device(device: str | None) -> str:
    if device is not None:
        return str(device)
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


class VectorKeypointObservation(VectorWrapper):
    """Keypoint (or descriptor) observations for every sub-env of a vector env, one DON pass per step.

    Args:
        envs: a ``gymnasium.vector`` env (sync or async) of don_gym envs with images, all of one object.
        model, reference_descriptors, keep_images, keypoint_kwargs: as for
            :class:`~don_gym.wrappers.KeypointObservation` (the reference descriptors are found the
            same way, on sub-env 0 or, for an async vector env, on a fresh env from its first env_fn).
        keypoints: False adds only ``descriptors`` (as :class:`~don_gym.wrappers.DescriptorObservation`).
        device: where the network runs (None: ``"cuda"`` if torch sees a GPU, else ``"cpu"``); moves
            the network object there. The oracle renders on the CPU, one image at a time.

    Both autoreset modes NEXT_STEP and SAME_STEP work; in SAME_STEP the terminal observations in
    ``infos["final_obs"]`` are transformed too, in the same batch as the step's observations.
    """

    def __init__(
        self,
        envs: VectorEnv,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        reference_descriptors: np.ndarray | None = None,
        *,
        keypoints: bool = True,
        keep_images: bool = True,
        device: str | None = None,
        **keypoint_kwargs: Any,
    ) -> None:
        super().__init__(envs)
        self.keypoints_enabled = bool(keypoints)
        self.autoreset_mode = envs.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        template_env, temporary = self._template_env(envs)
        try:
            # The per-env wrapper decides the source, references and spaces: the two paths cannot drift.
            template = KeypointObservation(
                template_env,
                model,
                reference_descriptors,
                keep_images=keep_images or not self.keypoints_enabled,
                **keypoint_kwargs,
            )
        finally:
            if temporary:
                template_env.close()
        if template.window_px is not None:
            raise DonGymError(
                f"VectorKeypointObservation: sub-envs with window_px={template.window_px} are unsupported (each "
                "needs its own window placement); wrap each env in KeypointObservation (vectorize='dummy' or 'subproc')"
            )
        self.template = template
        self.source = template.source
        self.keep_images = bool(keep_images)
        if isinstance(self.source, NetworkDescriptors):
            self.device = _resolve_device(device)
            self.source.network.to(self.device)
        else:
            self.device = "cpu"
        if self.keypoints_enabled:
            single = template.observation_space
        else:
            single = gym.spaces.Dict(
                {k: v for k, v in template.observation_space.spaces.items() if not k.startswith("keypoint_")}
            )
        self.single_observation_space = single
        self.observation_space = batch_space(single, self.num_envs)
        self._out = create_empty_array(single, self.num_envs)

    @staticmethod
    def _template_env(envs: VectorEnv) -> tuple[gym.Env, bool]:
        base = envs.unwrapped
        if isinstance(base, SyncVectorEnv):
            return base.envs[0], False
        env_fns = getattr(base, "env_fns", None)
        if not env_fns:
            raise DonGymError(
                f"VectorKeypointObservation needs a SyncVectorEnv or AsyncVectorEnv, got {type(base).__name__}"
            )
        return env_fns[0](), True

    @property
    def method(self) -> str:
        return self.source.method

    # ------------------------------------------------------------------ frames
    def observe_frames(self, frames: Sequence[tuple[Mapping[str, np.ndarray], Mapping[str, Any]]]) -> list[dict]:
        """Transform single-env (observation, info) pairs, all images in one network pass."""
        if not frames:
            return []
        if isinstance(self.source, NetworkDescriptors):
            images = self.source.descriptor_images(np.stack([np.asarray(obs["rgb"]) for obs, _ in frames]))
        else:
            images = [self.source.descriptor_image(obs, info) for obs, info in frames]
        return [self._observation(obs, image) for (obs, _), image in zip(frames, images, strict=True)]

    def _observation(self, obs: Mapping[str, np.ndarray], image: np.ndarray) -> dict[str, np.ndarray]:
        out = dict(obs)
        descriptors = np.clip(image, -DESCRIPTOR_BOUND, DESCRIPTOR_BOUND).astype(np.float32, copy=False)
        out["descriptors"] = descriptors
        if not self.keypoints_enabled:
            return out
        return self.template.add_keypoints(out)

    def _batched(self, observations: Any, infos: Mapping[str, Any], extra: Sequence[tuple[Any, Any]] = ()):
        frames = [
            (obs, unbatch_info(infos, i)) for i, obs in enumerate(iterate(self.env.observation_space, observations))
        ]
        outputs = self.observe_frames([*frames, *extra])
        batch = concatenate(self.single_observation_space, outputs[: self.num_envs], self._out)
        return _copy_tree(batch), outputs[self.num_envs :]

    # ---------------------------------------------------------------- gym API
    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        observations, infos = self.env.reset(seed=seed, options=options)
        batch, _ = self._batched(observations, infos)
        return batch, infos

    def step(self, actions: Any):
        observations, rewards, terminations, truncations, infos = self.env.step(actions)
        finals: list[int] = []
        if self.autoreset_mode == AutoresetMode.SAME_STEP and "final_obs" in infos:
            finals = [i for i in range(self.num_envs) if bool(infos["_final_obs"][i])]
        extra = [(infos["final_obs"][i], unbatch_info(infos["final_info"], i)) for i in finals]
        batch, final_outputs = self._batched(observations, infos, extra)
        if finals:
            infos = dict(infos)
            final_obs = np.array(infos["final_obs"], dtype=object, copy=True)
            for i, out in zip(finals, final_outputs, strict=True):
                final_obs[i] = out
            infos["final_obs"] = final_obs
        return batch, rewards, terminations, truncations, infos


def _copy_tree(batch: Any) -> Any:
    if isinstance(batch, dict):
        return {k: _copy_tree(v) for k, v in batch.items()}
    return np.array(batch, copy=True)
