"""Gymnasium observation wrappers that add DON descriptors to don_gym observations.

Installed as ``don_gym.wrappers``.

- :class:`DescriptorObservation` adds ``descriptors`` (H, W, D) float32 computed from ``rgb`` by a
  descriptor source: ``"oracle"`` (optimal descriptors rendered from the true poses, the upper
  bound), a shipped network's short name (``"toolcap/supervised-edge"``), a checkpoint path or a
  :class:`~don_gym.model.DenseObjectNet`.
- :class:`KeypointObservation` adds K tracked keypoints: ``keypoint_pixels`` (K, 2),
  ``keypoint_points`` (K, 3) world metres, ``keypoint_confidence`` (K,); by default the two
  axis-end keypoints of :func:`axis_end_targets`; ``keep_images=False`` gives a compact
  observation for RL.
- :func:`load_descriptor_source` and the :class:`DescriptorSource` classes are the model
  abstraction for evaluation code; :func:`reference_descriptors_for` gives any model's descriptors
  of chosen object surface points (from the optimal field, or from a :class:`ReferenceFrame`).

Example::

    env = KeypointObservation(gym.make("DONToolcapPick-v0", image_size=(320, 240)), model="oracle")
    obs, info = env.reset(options={"pose_id": 0})
    obs["keypoint_points"]  # (2, 3): minus-end and plus-end ring of the toolcap, world metres
"""

from don_gym.wrappers.descriptors import (
    DESCRIPTOR_BOUND,
    DescriptorObservation,
    DescriptorSource,
    NetworkDescriptors,
    OracleDescriptors,
    ReferenceFrame,
    descriptor_field_for,
    env_object_model,
    load_descriptor_source,
    reference_descriptors_for,
)
from don_gym.wrappers.keypoints import (
    AxisEndTargets,
    KeypointObservation,
    axis_end_targets,
    default_reference_descriptors,
)

__all__ = [
    "DESCRIPTOR_BOUND",
    "AxisEndTargets",
    "DescriptorObservation",
    "DescriptorSource",
    "KeypointObservation",
    "NetworkDescriptors",
    "OracleDescriptors",
    "ReferenceFrame",
    "axis_end_targets",
    "default_reference_descriptors",
    "descriptor_field_for",
    "env_object_model",
    "load_descriptor_source",
    "reference_descriptors_for",
]
