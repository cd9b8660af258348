"""The KeypointMemory wrapper: where each keypoint was last seen, and how long ago.

A wrist camera loses the part as the hand descends on it (the D435 returns no depth nearer than about 0.24 m,
and the part then leaves the view), so a policy that sees only the current keypoints is blind for the last
centimetres of a grasp. The part does not move until it is touched, so its last seen place is still where it is.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.wrappers.keypoints import POINT_BOUND_M
from don_gym.wrappers.rl import WORKSPACE_CENTRE_M

__all__ = ["DEFAULT_MAX_AGE_STEPS", "DEFAULT_SEEN_CONFIDENCE", "KeypointMemory", "UNSEEN_POINT_M"]

#: A keypoint counts as seen in a step when its confidence is at least this.
DEFAULT_SEEN_CONFIDENCE = 0.5
#: Ages are counted up to this many steps (an episode's length by default), and a keypoint never seen reads it.
DEFAULT_MAX_AGE_STEPS = 100
#: Last seen place of a keypoint not seen yet in the episode: the workspace's centre on the table (world, m).
UNSEEN_POINT_M = WORKSPACE_CENTRE_M


class KeypointMemory(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Adds each keypoint's last seen world position and its age to a keypoint observation.

    Input: a Dict observation with ``keypoint_points`` (K, 3) world metres and ``keypoint_confidence`` (K,)
    (:class:`~don_gym.wrappers.KeypointObservation` or :class:`~don_gym.wrappers.SimulatedKeypoints`).

    Added keys: ``keypoint_memory_points`` (K, 3) float32, world metres: the keypoint's position at the last step
    it was seen (confidence >= ``seen_confidence``), :data:`UNSEEN_POINT_M` before it was first seen in the
    episode; ``keypoint_age`` (K,) float32, steps since it was seen (0: seen now), at most ``max_age_steps``
    (also the value of a keypoint never seen). A reset forgets everything. Positions are in the world frame, so
    they stay right while the camera moves and as long as the part does not.
    :class:`~don_gym.wrappers.KeypointFeatures` puts both into the flat vector when they are present.
    """

    def __init__(
        self,
        env: gym.Env,
        seen_confidence: float = DEFAULT_SEEN_CONFIDENCE,
        max_age_steps: int = DEFAULT_MAX_AGE_STEPS,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, seen_confidence=seen_confidence, max_age_steps=max_age_steps)
        gym.Wrapper.__init__(self, env)
        space = env.observation_space
        needed = ("keypoint_points", "keypoint_confidence")
        if not isinstance(space, spaces.Dict) or any(key not in space.spaces for key in needed):
            raise DonGymError(
                "KeypointMemory needs observation keys ['keypoint_points', 'keypoint_confidence']: wrap the env in "
                "don_gym.wrappers.KeypointObservation or SimulatedKeypoints first"
            )
        if not (isinstance(seen_confidence, (int, float)) and 0.0 <= seen_confidence <= 1.0):
            raise DonGymError(f"seen_confidence={seen_confidence!r}: expected a confidence in [0, 1]")
        if isinstance(max_age_steps, bool) or not isinstance(max_age_steps, (int, np.integer)) or max_age_steps < 1:
            raise DonGymError(f"max_age_steps={max_age_steps!r}: expected a positive integer number of steps")
        self.seen_confidence = float(seen_confidence)
        self.max_age_steps = int(max_age_steps)
        self.num_keypoints = int(space["keypoint_points"].shape[0])
        entries = dict(space.spaces)
        K = self.num_keypoints
        entries["keypoint_memory_points"] = spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, shape=(K, 3), dtype=np.float32)
        entries["keypoint_age"] = spaces.Box(0.0, float(self.max_age_steps), shape=(K,), dtype=np.float32)
        self.observation_space = spaces.Dict(entries)
        self._points = np.tile(UNSEEN_POINT_M, (K, 1))
        self._age = np.full(K, float(self.max_age_steps))

    def _remember(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        points = np.asarray(obs["keypoint_points"], dtype=np.float64).reshape(-1, 3)
        confidence = np.asarray(obs["keypoint_confidence"], dtype=np.float64).reshape(-1)
        seen = np.isfinite(points).all(axis=1) & (confidence >= self.seen_confidence)
        self._points = np.where(seen[:, None], points, self._points)
        self._age = np.where(seen, 0.0, np.minimum(self._age + 1.0, self.max_age_steps))
        obs = dict(obs)
        obs["keypoint_memory_points"] = np.clip(self._points, -POINT_BOUND_M, POINT_BOUND_M).astype(np.float32)
        obs["keypoint_age"] = self._age.astype(np.float32)
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._points = np.tile(UNSEEN_POINT_M, (self.num_keypoints, 1))
        self._age = np.full(self.num_keypoints, float(self.max_age_steps))
        return self._remember(obs), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._remember(obs), reward, terminated, truncated, info
