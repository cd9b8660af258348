"""Agents for don_gym tasks (the scripted two-descriptor axis-grasp agent, RL baselines).

Installed as ``don_gym.agents``.

- :class:`AxisGraspAgent`: tracks two descriptors on the part's axis ends and acts through
  ``control="grasp"`` (grasp point and +axis yaw), with any model the wrappers accept::

      env = gym.make("DONToolcapPick-v0", image_size=(320, 240))
      agent = AxisGraspAgent(env, model="oracle")   # or "toolcap/self-supervised", a path
      env = agent.env                                # env wrapped with the agent's keypoints
      obs, info = env.reset(options={"pose_id": 0})
      obs, reward, terminated, truncated, info = env.step(agent.act(obs))

- :class:`PoseGraspAgent`: the same descriptors through a 6D pose estimate (:mod:`don_gym.perception.pose`): the
  grasp point and +axis yaw of the estimated pose; ``PoseGraspAgent(env, model="oracle")`` likewise.

- :class:`BinAxisGraspAgent` and :class:`BinOracleAgent`: pick one part's instances out of a bin
  (``DONBinPick-v0``), one per step, choosing the most graspable instance first (:mod:`don_gym.agents.bin_agent`)::

      env = gym.make("DONBinPick-v0", image_size=(320, 240))
      agent = BinAxisGraspAgent(env, model="oracle")  # or "toolcap/supervised-edge", a multi-part checkpoint
      obs, info = env.reset(seed=0)
      agent.reset()
      obs, reward, terminated, truncated, info = env.step(agent.act(obs, info))
      agent.observe_outcome(info["outcome"])

- :mod:`don_gym.agents.rl` (extra ``rl``): stable-baselines3 baselines, PPO on ``control="grasp"``
  with keypoint observations and SAC on ``control="ee"`` (``rl.train``, ``rl.evaluate``); imported
  on demand so that the core install does not need stable-baselines3.
"""

from don_gym.agents.axis_grasp import AxisGraspAgent
from don_gym.agents.bin_agent import BinAxisGraspAgent, BinOracleAgent
from don_gym.agents.pose_grasp import PoseGraspAgent

__all__ = ["AxisGraspAgent", "BinAxisGraspAgent", "BinOracleAgent", "PoseGraspAgent"]
