"""A HER replay buffer that draws a fixed share of every batch from the expert's demonstrations.

With demonstrations in SAC+HER's replay buffer (:func:`~don_gym.agents.rl_demos.add_expert_episodes`) a batch
sampled uniformly holds fewer and fewer of them as the policy's own episodes pile up. RLPD (Ball et al. 2023, "Efficient
online reinforcement learning with offline data") keeps the share fixed instead, half of each batch from the
offline data ("symmetric sampling"). :class:`DemonstrationHerReplayBuffer` does that for HER: ``demo_fraction``
of each batch comes from the buffer's first ``demo_rows`` rows (where the demonstrations were written), the rest
from the policy's own episodes; HER relabels both as usual.

Needs stable-baselines3 (imported here at the top: import this module only where SB3 is installed).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.type_aliases import DictReplayBufferSamples

__all__ = ["DemonstrationHerReplayBuffer"]


class DemonstrationHerReplayBuffer(HerReplayBuffer):
    """:class:`~stable_baselines3.HerReplayBuffer` whose batches hold ``demo_fraction`` (in [0, 1]) of
    transitions from its first :attr:`demo_rows` rows, the expert's episodes, once both those and the policy's own
    are there; uniform over the buffer before that, and once the buffer has wrapped over the demonstrations."""

    def __init__(self, *args: Any, demo_fraction: float = 0.5, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.demo_fraction = float(demo_fraction)
        #: Rows (positions; each holds one transition per env) written with demonstrations; set by their writer.
        self.demo_rows = 0

    def _sample_rows(self, batch_size: int, rows: slice, env: Any) -> DictReplayBufferSamples:
        """HER's own sampling restricted to the buffer's ``rows`` (below :attr:`pos`, the buffer not full): the
        others are hidden (episode length 0, which HER reads as "no whole episode here") for the call. The
        stand-in ends at :attr:`pos`, past which nothing is written yet, so a gradient step does not copy the
        whole preallocated buffer's lengths."""
        lengths = self.ep_length
        hidden = np.zeros_like(lengths[: self.pos])
        hidden[rows] = lengths[rows]
        self.ep_length = hidden
        try:
            return super().sample(batch_size, env)
        finally:
            self.ep_length = lengths

    def sample(self, batch_size: int, env: Any = None) -> DictReplayBufferSamples:  # type: ignore[override]
        demos = slice(0, self.demo_rows)
        own = slice(self.demo_rows, self.pos)
        from_demos = int(round(self.demo_fraction * batch_size))
        mixed = (
            self.demo_rows > 0
            and not self.full
            and 0 < from_demos < batch_size
            and np.any(self.ep_length[demos] > 0)
            and np.any(self.ep_length[own] > 0)
        )
        if not mixed:
            return super().sample(batch_size, env)
        parts = [self._sample_rows(from_demos, demos, env), self._sample_rows(batch_size - from_demos, own, env)]
        return DictReplayBufferSamples(
            observations={key: torch.cat([p.observations[key] for p in parts]) for key in parts[0].observations},
            actions=torch.cat([p.actions for p in parts]),
            next_observations={
                key: torch.cat([p.next_observations[key] for p in parts]) for key in parts[0].next_observations
            },
            dones=torch.cat([p.dones for p in parts]),
            rewards=torch.cat([p.rewards for p in parts]),
        )
