"""Gymnasium wrappers that add DON descriptors and keypoints to don_gym observations (``don_gym.wrappers``).

- :class:`DescriptorObservation` adds ``descriptors`` (H, W, D) from a descriptor source: ``"oracle"``,
  a shipped network (``"toolcap/supervised-edge"``), a checkpoint path or a DenseObjectNet.
- :class:`KeypointObservation` adds K tracked keypoints (``keypoint_pixels``, ``keypoint_points`` in
  world metres, ``keypoint_confidence``); by default the two axis-end rings of :func:`axis_end_targets`.
- :class:`KeypointFeatures` and :class:`KeypointGraspAction`: flat observations and normalised grasp
  actions for RL policies.
- :class:`KeypointMemory`: each keypoint's last seen world position and its age in steps, for the descent
  that the wrist camera cannot follow.
- :class:`SimulatedKeypoints` (a model of the DON, no rendering), :class:`KeypointGoal` (goals for HER),
  :class:`DescriptorImage` (uint8 descriptor images for CNN policies), :class:`VectorKeypointObservation`
  (one DON pass per vector-env step).
- :func:`make_keypoint_env` (an env with a keypoint source) and :func:`make_goal_env` (the goal-conditioned
  task for HER, which the registered ``DONToolcapLift-v0`` makes).

The descriptor sources and reference descriptors live in :mod:`don_gym.perception.descriptor_sources`; their
names are re-exported here. Example::

    env = KeypointObservation(gym.make("DONToolcapPick-v0", image_size=(320, 240)), model="oracle")
    obs, info = env.reset(options={"pose_id": 0})
    obs["keypoint_points"]  # (2, 3): minus-end and plus-end ring of the toolcap, world metres
"""

from don_gym.perception.descriptor_sources import (
    AxisEndTargets,
    DescriptorSource,
    NetworkDescriptors,
    OracleDescriptors,
    ReferenceFrame,
    axis_end_targets,
    default_reference_descriptors,
    descriptor_field_for,
    env_object_model,
    load_descriptor_source,
    reference_descriptors_for,
)
from don_gym.wrappers.descriptors import DESCRIPTOR_BOUND, DescriptorObservation
from don_gym.wrappers.goals import HandStarts, KeypointGoal, make_goal_env, make_keypoint_env
from don_gym.wrappers.images import DescriptorImage
from don_gym.wrappers.keypoints import KeypointObservation, KeypointSettings
from don_gym.wrappers.memory import KeypointMemory
from don_gym.wrappers.rl import KeypointFeatures, KeypointGraspAction
from don_gym.wrappers.simulated_keypoints import KeypointNoiseModel, SimulatedKeypoints
from don_gym.wrappers.vector import VectorKeypointObservation

__all__ = [
    "DESCRIPTOR_BOUND",
    "AxisEndTargets",
    "DescriptorImage",
    "DescriptorObservation",
    "DescriptorSource",
    "HandStarts",
    "KeypointFeatures",
    "KeypointGoal",
    "KeypointGraspAction",
    "KeypointMemory",
    "KeypointNoiseModel",
    "KeypointObservation",
    "KeypointSettings",
    "NetworkDescriptors",
    "OracleDescriptors",
    "ReferenceFrame",
    "SimulatedKeypoints",
    "VectorKeypointObservation",
    "axis_end_targets",
    "default_reference_descriptors",
    "descriptor_field_for",
    "env_object_model",
    "load_descriptor_source",
    "make_goal_env",
    "make_keypoint_env",
    "reference_descriptors_for",
]
