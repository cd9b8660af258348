"""PyBullet simulation. The env (:mod:`~don_gym.sim.env`) joins robot (``robot``), task (``task``,
with ``part`` and the scripted grasp of ``script``), wrist camera (``camera``) and depth sensor
(``sensor``) on its own PyBullet client (``bullet``); ``recorder`` records dataset scenes.
Import-light, and nothing holds global PyBullet state.
"""
