"""The axis agent locates its keypoints with the same settings as the wrapper it makes (one place for them):
a non-default depth window reaches both, so the agent's own fallback and the wrapper's keypoints agree."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import don_gym  # noqa: F401
from don_gym.agents import AxisGraspAgent
from don_gym.wrappers import KeypointSettings


def test_the_agent_and_its_wrapper_locate_keypoints_with_one_set_of_settings() -> None:
    env = gym.make("DONToolcapPick-v0", image_size=(96, 72))
    try:
        agent = AxisGraspAgent(env, model="oracle")
        settings = KeypointSettings(agent.settings.window_m, min_radius_px=0, max_radius_px=1, border_margin_px=2)
        agent.settings = settings
        wrapped = agent.wrap(env)
        assert wrapped.settings == settings
        obs, _ = wrapped.reset(options={"pose_id": 3})
        # The agent's fallback (descriptors and depth, no keypoints) gives what the wrapper observed.
        images = {k: obs[k] for k in ("descriptors", "depth", "camera_intrinsics", "camera_pose")}
        np.testing.assert_allclose(agent.keypoints(images), obs["keypoint_points"], atol=1e-6)
    finally:
        env.close()
