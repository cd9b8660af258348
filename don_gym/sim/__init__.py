"""PyBullet simulation: the Panda pick-and-place scene, cameras and depth sensor models.

- :mod:`don_gym.sim.env`: ``PickPlaceEnv``, the Gymnasium env behind ``DONToolcapPick-v0``,
  ``DONShaftPick-v0`` and ``DONPick-v0`` (control modes "grasp" and "ee").
- :mod:`don_gym.sim.bullet`: ``Bullet``, one ``BulletClient(p.DIRECT)`` with named bodies,
  snapshots (bit-exact resets) and the renderer plugin.
- :mod:`don_gym.sim.camera`: ``render_camera`` (RGB, metric depth, segmentation from OpenCV
  intrinsics and ``T_world_camera``), segmentation helpers, renderer choice.
- :mod:`don_gym.sim.robot`: ``Panda`` (IK, gripper with gear-coupled fingers, wrist camera mount).
- :mod:`don_gym.sim.part`: ``PartBody`` (a part's collision pieces, mass, inertia, pose).
- :mod:`don_gym.sim.task`: table, handover cradle, part poses (random and the 8 fixed ones), outcome.
- :mod:`don_gym.sim.script`: the scripted grasp-and-place of ``control="grasp"``.
- :mod:`don_gym.sim.sensor`: depth-sensor models (ideal, D435, Kinect).

Nothing here holds global PyBullet state; import-light (no PyBullet client at import).
"""
