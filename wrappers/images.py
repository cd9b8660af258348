"""Descriptor images in the form stable-baselines3 treats as images: uint8, (H, W, D), 0..255.

:class:`DescriptorImage` quantises the ``descriptors`` of :class:`~don_gym.wrappers.DescriptorObservation`
(clipped to [0, 1], the optimal descriptors' range) so that SB3's ``MultiInputPolicy`` feeds them to its CNN.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError

#: Descriptor value of one uint8 step: a quantised descriptor ``q`` stands for ``q * DESCRIPTOR_SCALE``.
DESCRIPTOR_SCALE = 1.0 / 255.0
#: SB3's NatureCNN needs images at least this many pixels wide and high.
MIN_CNN_SIZE_PX = 36


class DescriptorImage(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """``descriptors`` as uint8 (H, W, D): ``round(clip(d, 0, 1) / DESCRIPTOR_SCALE)``.

    Args:
        env: an env whose observations hold float ``descriptors`` (H, W, D).
        size: (width, height) to resize the descriptor image to (area averaging before quantising),
            at least 36x36 for SB3's NatureCNN; None keeps the env's size (then it must be that large).
        keep: observation keys to keep besides ``descriptors`` (None: all). Keeping only small
            vectors (``ee_pose``, ``gripper_width``) gives an observation SB3's checker accepts as is.

    The scale is :attr:`descriptor_scale` (= :data:`DESCRIPTOR_SCALE`): descriptors outside [0, 1]
    (a trained network's overshoot) saturate at 0 or 255.
    """

    def __init__(self, env: gym.Env, size: tuple[int, int] | None = None, keep: Sequence[str] | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, size=size, keep=keep)
        gym.ObservationWrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "descriptors" not in space.spaces:
            raise DonGymError(
                "DescriptorImage needs observations with 'descriptors': wrap the env in DescriptorObservation first"
            )
        height, width, dim = space["descriptors"].shape
        if size is not None:
            try:
                width, height = (int(v) for v in size)
            except (TypeError, ValueError) as exc:
                raise DonGymError(f"size={size!r}: expected (width, height) in pixels") from exc
        if min(width, height) < MIN_CNN_SIZE_PX:
            raise DonGymError(
                f"descriptor image {width}x{height}: SB3's CNN needs at least {MIN_CNN_SIZE_PX}x{MIN_CNN_SIZE_PX} "
                "pixels; give size= or a larger env image_size"
            )
        missing = [k for k in (keep or ()) if k not in space.spaces]
        if missing:
            raise DonGymError(f"keep={list(keep)}: the observation has no keys {missing}")
        self.size = (width, height)
        self.keep = None if keep is None else tuple(keep)
        self.descriptor_scale = DESCRIPTOR_SCALE
        entries = {k: v for k, v in space.spaces.items() if self.keep is None or k in self.keep}
        entries["descriptors"] = spaces.Box(0, 255, shape=(height, width, dim), dtype=np.uint8)
        self.observation_space = spaces.Dict(entries)

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        descriptors = np.asarray(observation["descriptors"], dtype=np.float32)
        width, height = self.size
        if descriptors.shape[:2] != (height, width):
            channels = [
                cv2.resize(descriptors[..., c], (width, height), interpolation=cv2.INTER_AREA)
                for c in range(descriptors.shape[2])
            ]
            descriptors = np.stack(channels, axis=2)
        out = {k: v for k, v in observation.items() if self.keep is None or k in self.keep}
        out["descriptors"] = np.rint(np.clip(descriptors, 0.0, 1.0) / DESCRIPTOR_SCALE).astype(np.uint8)
        return out
