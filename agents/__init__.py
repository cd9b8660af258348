"""Agents for don_gym tasks (the scripted two-descriptor axis-grasp agent, RL baselines).

Installed as ``don_gym.agents``.

- :class:`AxisGraspAgent`: tracks two descriptors on the part's axis ends and acts through
  ``control="grasp"`` (grasp point and +axis yaw), with any model the wrappers accept::

      env = gym.make("DONToolcapPick-v0", image_size=(320, 240))
      agent = AxisGraspAgent(env, model="oracle")   # or "toolcap/self-supervised", a path
      env = agent.env                                # env wrapped with the agent's keypoints
      obs, info = env.reset(options={"pose_id": 0})
      obs, reward, terminated, truncated, info = env.step(agent.act(obs))
"""

from don_gym.agents.axis_grasp import AxisGraspAgent

__all__ = ["AxisGraspAgent"]
