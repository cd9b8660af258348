"""The DescriptorObservation wrapper: adds a descriptor source's ``descriptors`` to every observation.

The sources themselves (the oracle, trained DONs) live in :mod:`don_gym.perception.descriptor_sources`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.learning.model import DenseObjectNet
from don_gym.perception.descriptor_sources import DescriptorSource, env_object_model, load_descriptor_source

#: Descriptors in observations are clipped to +-this (the observation space's documented bound).
#: Optimal descriptors lie in [0, 1]; trained networks stay within a few units of that.
DESCRIPTOR_BOUND = 1000.0


class DescriptorObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Adds ``descriptors`` (H, W, D) float32 to every observation, computed from ``rgb``.

    Args:
        env: a don_gym env with images (``rgb``, ``depth``).
        model: ``"oracle"``, a shipped network name, a checkpoint path, a DenseObjectNet or a
            :class:`~don_gym.perception.descriptor_sources.DescriptorSource` (see
            :func:`~don_gym.perception.descriptor_sources.load_descriptor_source`).
        descriptor_dim: required descriptor size (None: the model's; 3 for the oracle).
        occlusion_check: see :class:`~don_gym.perception.descriptor_sources.OracleDescriptors`.

    The observation space gains ``descriptors``: a Box of shape (H, W, D) bounded by
    ``+-DESCRIPTOR_BOUND`` (values are clipped to it); all other keys are kept. ``reset`` and
    ``step`` are overridden (not ``observation``) because the oracle needs the step's ``info``. The
    constructor arguments are recorded (not copied) so that ``env.spec`` can re-create the wrapper.
    """

    def __init__(
        self,
        env: gym.Env,
        model: str | Path | DenseObjectNet | DescriptorSource = "oracle",
        descriptor_dim: int | None = None,
        occlusion_check: bool = True,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self, _disable_deepcopy=True, model=model, descriptor_dim=descriptor_dim, occlusion_check=occlusion_check
        )
        gym.Wrapper.__init__(self, env)
        self.object_model = env_object_model(env)
        self.source = load_descriptor_source(model, self.object_model, descriptor_dim, occlusion_check)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "rgb" not in space.spaces:
            raise DonGymError("DescriptorObservation needs an env that observes 'rgb' images (image_size not None)")
        height, width = space["rgb"].shape[:2]
        entries = dict(space.spaces)
        entries["descriptors"] = spaces.Box(
            -DESCRIPTOR_BOUND, DESCRIPTOR_BOUND, shape=(height, width, self.source.descriptor_dim), dtype=np.float32
        )
        self.observation_space = spaces.Dict(entries)

    @property
    def method(self) -> str:
        """``"oracle"`` or the checkpoint's training method."""
        return self.source.method

    def _add_descriptors(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        image = self.source.descriptor_image(obs, info)
        obs = dict(obs)
        obs["descriptors"] = np.clip(image, -DESCRIPTOR_BOUND, DESCRIPTOR_BOUND).astype(np.float32, copy=False)
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._add_descriptors(obs, info), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._add_descriptors(obs, info), reward, terminated, truncated, info
