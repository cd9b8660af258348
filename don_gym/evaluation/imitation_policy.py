"""The policy class of the imitation benchmark and its inputs' features (:mod:`don_gym.evaluation.imitation`).

One policy class for every input: :class:`HistoryPolicy`, an MLP over the last :data:`HISTORY` steps of a feature
vector, the robot's own state (TCP position, hand yaw, wrist angle, finger opening) plus the input's; image inputs
(:data:`IMAGE_KINDS`: ``"rgbd"``, ``"descriptors:<network>"``) put each step's image, standardised per channel by
the demonstrations' statistics, through a convolutional encoder with a spatial softmax first
(:class:`SpatialSoftmaxEncoder`, the reference's end-to-end baseline), trained with it. :func:`train_policy` clones
the expert by mean squared action error.

Inputs (:data:`INPUTS`; ``<network>``: a shipped name or a checkpoint path): ``"state"`` (the part's true pose, its
grasp point and axis: the upper bound), ``"true"`` (its exact keypoints with memory), ``"simulated:<network>"``,
``"don:<network>"`` (keypoints with :class:`~don_gym.wrappers.KeypointMemory`), ``"rgbd"`` (wrist RGB-D),
``"descriptors:<network>"`` (the network's descriptor image of the wrist camera).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import nn
from tqdm.auto import tqdm

from don_gym.errors import DonGymError
from don_gym.evaluation.demonstrations import kind_name
from don_gym.geometry import transform_from_pose
from don_gym.objects import ObjectModel, load_object
from don_gym.sim.task import grasp_point_object
from don_gym.wrappers.rl import (
    NEAR_UNIT_M,
    POSITION_UNIT_M,
    axis_in_hand,
    hand_keypoint_features,
    hand_rotation,
    robot_features,
    two_scale_offsets,
)

__all__ = [
    "AGE_UNIT_STEPS",
    "HISTORY",
    "IMAGE_KINDS",
    "INPUTS",
    "NEAR_UNIT_M",
    "POSITION_UNIT_M",
    "HistoryPolicy",
    "PartGeometry",
    "SpatialSoftmaxEncoder",
    "check_input",
    "demo_steps",
    "features",
    "image",
    "image_statistics",
    "is_image_kind",
    "live_step",
    "train_policy",
]

#: Input kinds (``<network>``: a shipped name or a checkpoint path).
INPUTS = ("state", "true", "simulated:<network>", "don:<network>", "rgbd", "descriptors:<network>")
#: Inputs seen through images (an encoder with a spatial softmax in front of the MLP); "descriptors:<network>" too.
IMAGE_KINDS = ("rgbd", "descriptors")
#: Steps of observation history the policy sees (the current one included).
HISTORY = 2
#: Unit (steps) of the keypoints' ages in the feature vectors.
AGE_UNIT_STEPS = 100


def check_input(name: str) -> None:
    """A one-line DonGymError unless ``name`` is one of :data:`INPUTS` (with a network named where it needs one)."""
    source = name.split(":", 1)
    fixed = name in ("state", "true", "rgbd")
    if not fixed and not (len(source) == 2 and source[0] in ("simulated", "don", "descriptors") and source[1]):
        raise DonGymError(f"input {name!r} is unknown; expected one of {list(INPUTS)}")


def is_image_kind(kind: str) -> bool:
    """Whether ``kind`` is seen through images (the policy's encoder)."""
    return kind.split(":", 1)[0] in IMAGE_KINDS


# ------------------------------------------------------------------------------ features
def features(kind: str, obs: dict[str, np.ndarray]) -> np.ndarray:
    """The feature vector (float32) of ``kind`` from a step's observation: the robot keys (``ee_pose``,
    ``gripper_width``, ``joint_positions``), for "state" ``part_pose``, ``part_axis`` and ``part_grasp_point``
    (:func:`live_step`), for keypoint kinds the keypoint keys (un-prefixed); for image kinds the robot's state only.

    Positions are offsets from the TCP (:func:`~don_gym.wrappers.rl.two_scale_offsets`); the part's axis as this
    input sees it (the true pose's, or the line through the two keypoints' last seen places) also relative to the
    hand's yaw. Keypoint kinds: :func:`~don_gym.wrappers.rl.hand_keypoint_features`, ages in
    :data:`AGE_UNIT_STEPS`."""
    if is_image_kind(kind):
        return robot_features(obs["ee_pose"], obs["joint_positions"], obs["gripper_width"]).astype(np.float32)
    if kind == "state":
        robot = robot_features(obs["ee_pose"], obs["joint_positions"], obs["gripper_width"])
        tcp = np.asarray(obs["ee_pose"], dtype=np.float64)[:3]
        pose = np.asarray(obs["part_pose"], dtype=np.float64)
        # The rotation's first two columns, not the quaternion: continuous, no sign to flip (Zhou et al. 2019).
        rotation = Rotation.from_quat(pose[3:]).as_matrix()[:, :2].T.ravel()
        axis_world = np.asarray(obs["part_axis"], dtype=np.float64)
        axis = axis_in_hand(axis_world, hand_rotation(obs["ee_pose"]))
        grasp = two_scale_offsets(np.asarray(obs["part_grasp_point"], dtype=np.float64) - tcp)
        return np.concatenate([robot, grasp, rotation, axis_world, axis]).astype(np.float32)
    return hand_keypoint_features(obs, AGE_UNIT_STEPS).astype(np.float32)


def image(kind: str, obs: dict[str, np.ndarray]) -> np.ndarray:
    """(C, H, W) float16 image of an image kind: "rgbd" RGB in [0, 1] and depth in metres; "descriptors:..." the
    descriptor image in [0, 1]."""
    if kind == "rgbd":
        rgb = np.asarray(obs["rgb"], dtype=np.float32).transpose(2, 0, 1) / 255.0
        return np.concatenate([rgb, np.asarray(obs["depth"], dtype=np.float32)[None]], axis=0).astype(np.float16)
    return (np.asarray(obs["descriptors"], dtype=np.float32).transpose(2, 0, 1) / 255.0).astype(np.float16)


@dataclass(frozen=True)
class PartGeometry:
    """What "state" knows of the part in its own frame: its +axis (3,) and its grasp point (3, m,
    :func:`~don_gym.sim.task.grasp_point_object`)."""

    plus_axis: np.ndarray
    grasp_point: np.ndarray

    @classmethod
    def of(cls, model: ObjectModel) -> PartGeometry:
        return cls(np.asarray(model.plus_axis, dtype=np.float64), grasp_point_object(model))

    def world(self, T_world_object: np.ndarray) -> dict[str, np.ndarray]:
        """``part_axis`` and ``part_grasp_point`` in the world frame for the part at ``T_world_object``."""
        T = np.asarray(T_world_object, dtype=np.float64)
        return {"part_axis": T[:3, :3] @ self.plus_axis, "part_grasp_point": T[:3, :3] @ self.grasp_point + T[:3, 3]}


def demo_steps(kind: str, demo: dict[str, np.ndarray], model: ObjectModel) -> list[dict[str, np.ndarray]]:
    """A recorded demo's observations as per-step dicts with the un-prefixed keys :func:`features` and
    :func:`image` read; ``model``: the demonstrations' part."""
    prefix = "" if kind in ("state", "rgbd") else kind_name(kind) + "."
    geometry = PartGeometry.of(model)
    steps = []
    for t in range(len(demo["ee_pose"])):
        step = {key: demo[key][t] for key in ("ee_pose", "gripper_width", "joint_positions", "part_pose")}
        pose = np.asarray(step["part_pose"], dtype=np.float64)
        step.update(geometry.world(transform_from_pose(pose[:3], pose[3:])))
        for key, values in demo.items():
            if prefix and key.startswith(prefix):
                step[key[len(prefix) :]] = values[t]
            elif kind == "rgbd" and key in ("rgb", "depth"):
                step[key] = values[t]
        steps.append(step)
    return steps


def live_step(obs: dict[str, np.ndarray], info: dict[str, Any], geometry: PartGeometry) -> dict[str, np.ndarray]:
    """An env's observation with what "state" sees of the part (its ``geometry``) added from ``info``."""
    step = dict(obs)
    T = np.asarray(info["T_world_object"], dtype=np.float64)
    step["part_pose"] = np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()])
    step.update(geometry.world(T))
    return step


# -------------------------------------------------------------------------------- policy
class SpatialSoftmaxEncoder(nn.Module):
    """Conv layers and a spatial softmax: the expected image coordinates (x, y in [-1, 1]) of each of
    ``keypoints`` feature maps, the end-to-end visuomotor policies' encoder (Levine et al. 2016)."""

    def __init__(self, channels: int = 4, keypoints: int = 16) -> None:
        super().__init__()
        # Small and strided: trained from scratch on CPU at 128x96 in seconds per hundred steps.
        self.net = nn.Sequential(
            nn.Conv2d(channels, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 16, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(16, keypoints, 3, padding=1),
        )  # fmt: skip
        self.out_features = 2 * keypoints

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        maps = self.net(images)
        b, k, h, w = maps.shape
        weights = torch.softmax(maps.reshape(b, k, h * w), dim=-1).reshape(b, k, h, w)
        ys = torch.linspace(-1.0, 1.0, h, device=maps.device)
        xs = torch.linspace(-1.0, 1.0, w, device=maps.device)
        x = (weights.sum(dim=2) * xs).sum(dim=-1)
        y = (weights.sum(dim=3) * ys).sum(dim=-1)
        return torch.cat([x, y], dim=1)


class HistoryPolicy(nn.Module):
    """The policy class of every input: an MLP over ``history`` steps of features (each step's image, if any,
    encoded by a :class:`SpatialSoftmaxEncoder` of ``image_channels`` first) to an action in [-1, 1]^5."""

    def __init__(self, feature_size: int, history: int = HISTORY, image_channels: int = 0, hidden: int = 256) -> None:
        super().__init__()
        self.history = history
        self.encoder = SpatialSoftmaxEncoder(image_channels) if image_channels else None
        step = feature_size + (self.encoder.out_features if self.encoder is not None else 0)
        self.head = nn.Sequential(
            nn.Linear(history * step, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 5), nn.Tanh(),
        )  # fmt: skip
        self.register_buffer("mean", torch.zeros(history * feature_size))
        self.register_buffer("std", torch.ones(history * feature_size))
        # Images are standardised per channel like the vectors: a descriptor image whose background sits near 1 in
        # every channel, with the part a small patch a few hundredths below it, leaves the encoder almost nothing
        # to see otherwise (development screen, N = 50: 7/50 and 12/50 successes unstandardised, 28/50 and 32/50).
        self.register_buffer("image_mean", torch.zeros(max(image_channels, 1)))
        self.register_buffer("image_std", torch.ones(max(image_channels, 1)))

    def forward(self, vectors: torch.Tensor, images: torch.Tensor | None = None) -> torch.Tensor:
        """``vectors`` (B, history * F) and, with an encoder, ``images`` (B, history, C, H, W) -> actions (B, 5)."""
        x = (vectors - self.mean) / self.std
        if self.encoder is not None:
            b = images.shape[0]
            pixels = (images.flatten(0, 1).float() - self.image_mean[:, None, None]) / self.image_std[:, None, None]
            codes = self.encoder(pixels).reshape(b, self.history, -1)
            steps = x.reshape(b, self.history, -1)
            x = torch.cat([steps, codes], dim=-1).flatten(1)
        return self.head(x)


def image_statistics(frames: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel mean and standard deviation, (C,) float32 each, over every pixel of ``frames`` (a list of
    (T, C, H, W) arrays).

    Accumulated in float64 one frame at a time: a float32 mean over the millions of pixel values of a few dozen
    demonstrations drifts by several hundredths, as large as the descriptor images' spread."""
    channels = frames[0].shape[1]
    count, total, squares = 0, np.zeros(channels), np.zeros(channels)
    for clip in frames:
        for frame in clip:
            values = frame.reshape(channels, -1).astype(np.float64)
            count += values.shape[1]
            total += values.sum(axis=1)
            squares += np.square(values).sum(axis=1)
    mean = total / count
    std = np.sqrt(np.maximum(squares / count - np.square(mean), 0.0))
    return mean.astype(np.float32), std.astype(np.float32)


def _history_index(lengths: list[int], history: int) -> np.ndarray:
    """(sum(lengths), history) row indices of each step's history in the concatenated steps, oldest first (an
    episode's first step repeated before it)."""
    rows = []
    start = 0
    for length in lengths:
        t = np.arange(length)
        rows.append(start + np.stack([np.maximum(t - lag, 0) for lag in range(history - 1, -1, -1)], axis=1))
        start += length
    return np.concatenate(rows)


def train_policy(
    kind: str, demos: Any, steps: int = 2000, batch: int = 64, seed: int = 0, progress: bool = False
) -> HistoryPolicy:
    """Behaviour cloning (mean squared action error, Adam) of a :class:`HistoryPolicy` on ``kind``'s features of
    the :class:`~don_gym.evaluation.demonstrations.Demonstrations` (their ``actions``: the expert's), ``steps``
    gradient steps of ``batch`` steps each."""
    check_input(kind)
    if kind not in demos.kinds:
        raise DonGymError(f"the demonstrations lack the input {kind!r}; they have {demos.kinds}")
    if not demos.actions:
        raise DonGymError("no demonstrations to clone: expected at least one")
    torch.manual_seed(seed)
    model = load_object(demos.part)
    vectors, frames, lengths = [], [], []
    for demo in demos.observations:
        rows = demo_steps(kind, demo, model)
        vectors.append(np.stack([features(kind, r) for r in rows]))
        if is_image_kind(kind):
            frames.append(np.stack([image(kind, r) for r in rows]))
        lengths.append(len(rows))
    index = torch.from_numpy(_history_index(lengths, HISTORY))
    x = torch.from_numpy(np.concatenate(vectors))
    y = torch.from_numpy(np.concatenate(demos.actions).astype(np.float32))
    pictures = torch.from_numpy(np.concatenate(frames)) if frames else None
    policy = HistoryPolicy(x.shape[1], HISTORY, image_channels=0 if pictures is None else pictures.shape[1])
    stacked = x[index].flatten(1)
    policy.mean.copy_(stacked.mean(dim=0))
    policy.std.copy_(stacked.std(dim=0).clamp_min(1e-3))
    if pictures is not None:
        channel_mean, channel_std = image_statistics(frames)
        policy.image_mean.copy_(torch.from_numpy(channel_mean))
        policy.image_std.copy_(torch.from_numpy(channel_std).clamp_min(1e-3))
    optimiser = torch.optim.Adam(policy.parameters(), lr=1e-3)
    # The rate decays to 0 (cosine): a policy taken from a still-noisy optimiser varies a lot from run to run.
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, max(int(steps), 1))
    generator = torch.Generator().manual_seed(seed)
    for _ in tqdm(range(steps), desc=f"BC {kind}", disable=not progress):
        chosen = torch.randint(0, len(x), (batch,), generator=generator)
        prediction = policy(stacked[chosen], None if pictures is None else pictures[index[chosen]])
        loss = torch.mean((prediction - y[chosen]) ** 2)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    return policy.eval()
