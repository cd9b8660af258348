"""Agents for don_gym tasks (the scripted two-descriptor axis-grasp agent, RL baselines).

Installed as ``don_gym.agents``.
"""
