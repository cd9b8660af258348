"""Behaviour cloning at equal demonstrations, one policy class for every input (``don-gym benchmark imitation``).

After Florence, Manuelli and Tedrake 2019: policies cloned from N expert demonstrations
(:mod:`don_gym.evaluation.demonstrations`) for each input, evaluated on held-out episodes with Wilson intervals.
The policy class is the same for every input: an MLP over a short history (:data:`HISTORY` steps) of a feature
vector, the robot's own state (TCP pose, finger opening) plus the input's; image inputs (``"rgbd"``) get a
convolutional encoder with a spatial softmax in front (the reference's end-to-end baseline), trained with it.

Inputs (:data:`INPUTS`): ``"state"`` (the part's true pose: the upper bound), ``"true"`` (its exact keypoints with
memory), ``"simulated:<network>"``, ``"don:<network>"`` (keypoints with :class:`~don_gym.wrappers.KeypointMemory`),
``"rgbd"`` (wrist RGB-D).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import nn
from tqdm.auto import tqdm

from don_gym.errors import DonGymError
from don_gym.objects import load_object
from don_gym.evaluation.demonstrations import (
    RecordSettings,
    kind_env,
    kind_name,
    read_demonstrations,
    record_demonstrations,
)
from don_gym.perception.descriptor_sources import axis_end_targets
from don_gym.stats import wilson_interval
from don_gym.wrappers.goals import LIFT_GOAL_HEIGHT_M, goal_reached
from don_gym.wrappers.simulated_keypoints import axis_points_world

__all__ = [
    "EVAL_SEED",
    "HISTORY",
    "INPUTS",
    "ImitationConfig",
    "ImitationResult",
    "evaluate_policy",
    "run_imitation",
    "train_policy",
]

#: Input kinds (``<network>``: a shipped name or a checkpoint path).
INPUTS = ("state", "true", "simulated:<network>", "don:<network>", "rgbd")
#: Inputs seen through images (a convolutional encoder with a spatial softmax).
IMAGE_KINDS = ("rgbd",)
#: Steps of observation history the policy sees (the current one included).
HISTORY = 2
#: Held-out evaluation episodes are ``reset(seed=EVAL_SEED + i)`` (bench_rl's and bench_expert's).
EVAL_SEED = 100_000
#: Unit (m) of positions in the feature vectors.
POSITION_UNIT_M = 0.05
#: Unit (m) of the near-field copy of the offsets from the TCP.
NEAR_UNIT_M = 0.01


# ------------------------------------------------------------------------------ features
def _hand_rotation(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(3, 3) R_world_hand of the TCP pose ``ee_pose`` (x, y, z, qx, qy, qz, qw)."""
    return Rotation.from_quat(np.asarray(obs["ee_pose"], dtype=np.float64).reshape(7)[3:]).as_matrix()


def _robot_features(obs: dict[str, np.ndarray]) -> np.ndarray:
    """TCP position, the hand's yaw as (cos, sin) (the top-down hand's quaternion flips sign as the yaw passes pi),
    joint 7's angle (rad / pi: which way the wrist can still turn) and the finger opening."""
    ee = np.asarray(obs["ee_pose"], dtype=np.float64).reshape(7)
    hand_x = _hand_rotation(obs)[:2, 0]
    wrist = np.asarray(obs["joint_positions"], dtype=np.float64).reshape(-1)[6:7] / np.pi
    width = np.asarray(obs["gripper_width"], dtype=np.float64).reshape(1) / 0.04
    return np.concatenate([ee[:3] / POSITION_UNIT_M, hand_x / max(np.linalg.norm(hand_x), 1e-9), wrist, width])


def _axis_in_hand(axis_world: np.ndarray, R_world_hand: np.ndarray) -> np.ndarray:
    """The part's axis direction seen from the hand: its angle a from hand x in the hand's xy plane as (cos a,
    sin a, cos 2a, sin 2a). The grasp turns the hand until a is 0 or pi (fingers across the axis); the doubled
    angle is the same for both, the plain one tells them apart: turning is then a smooth function of these."""
    local = R_world_hand.T @ np.asarray(axis_world, dtype=np.float64)
    angle = float(np.arctan2(local[1], local[0]))
    return np.array([np.cos(angle), np.sin(angle), np.cos(2 * angle), np.sin(2 * angle)])


def _offsets(offsets_m: np.ndarray) -> np.ndarray:
    """Offsets (m) from the TCP at two scales, flat: in :data:`POSITION_UNIT_M` across the workspace, and squashed
    at :data:`NEAR_UNIT_M` (``tanh``), which spreads the last centimetres of the approach, where the grasp needs
    millimetres, over the whole range of a unit."""
    offsets = np.asarray(offsets_m, dtype=np.float64)
    return np.concatenate([(offsets / POSITION_UNIT_M).ravel(), np.tanh(offsets / NEAR_UNIT_M).ravel()])


def features(kind: str, obs: dict[str, np.ndarray]) -> np.ndarray:
    """The feature vector (float32) of ``kind`` from an observation with the robot keys, ``part_pose`` and
    ``part_axis`` (the part's +axis, world) for "state" and the keypoint keys (un-prefixed) for keypoint kinds; for image kinds the robot's state only.
    Positions are from the TCP in :data:`POSITION_UNIT_M`; the part's axis as this input sees it (the true pose's,
    or the line through the two keypoints' last seen places) also relative to the hand's yaw."""
    robot = _robot_features(obs)
    if kind in IMAGE_KINDS or kind.startswith("descriptors:"):
        return robot.astype(np.float32)
    tcp = np.asarray(obs["ee_pose"], dtype=np.float64)[:3]
    R_world_hand = _hand_rotation(obs)
    if kind == "state":
        pose = np.asarray(obs["part_pose"], dtype=np.float64)
        R_world_part = Rotation.from_quat(pose[3:]).as_matrix()
        # The rotation's first two columns, not the quaternion: continuous, no sign to flip (Zhou et al. 2019).
        rotation = R_world_part[:, :2].T.ravel()
        axis_world = np.asarray(obs["part_axis"], dtype=np.float64)
        axis = _axis_in_hand(axis_world, R_world_hand)
        offset = _offsets(pose[:3] - tcp)
        return np.concatenate([robot, offset, rotation, axis_world, axis]).astype(np.float32)
    confidence = np.asarray(obs["keypoint_confidence"], dtype=np.float64)
    points = np.where(confidence[:, None] > 0, np.asarray(obs["keypoint_points"], dtype=np.float64) - tcp, 0.0)
    remembered = np.asarray(obs["keypoint_memory_points"], dtype=np.float64)
    points, memory = _offsets(points), _offsets(remembered - tcp)
    age = np.asarray(obs["keypoint_age"], dtype=np.float64) / 100.0
    axis = _axis_in_hand(remembered[-1] - remembered[0], R_world_hand)
    return np.concatenate([robot, points.ravel(), confidence, memory.ravel(), age, axis]).astype(np.float32)


def _image(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(4, H, W) float32: RGB in [0, 1] and depth in metres."""
    rgb = np.asarray(obs["rgb"], dtype=np.float32).transpose(2, 0, 1) / 255.0
    return np.concatenate([rgb, np.asarray(obs["depth"], dtype=np.float32)[None]], axis=0)


def _part_axis(part_pose: np.ndarray, plus_axis: np.ndarray) -> np.ndarray:
    """(3,) the part's +axis in the world frame from its pose (x, y, z, qx, qy, qz, qw)."""
    return Rotation.from_quat(np.asarray(part_pose, dtype=np.float64)[3:]).as_matrix() @ plus_axis


def _demo_steps(kind: str, demo: dict[str, np.ndarray], plus_axis: np.ndarray) -> list[dict[str, np.ndarray]]:
    """A demo's observations as per-step dicts with the un-prefixed keys :func:`features` reads."""
    prefix = "" if kind in ("state", "rgbd") else kind_name(kind) + "."
    T = len(demo["ee_pose"])
    steps = []
    for t in range(T):
        step = {key: demo[key][t] for key in ("ee_pose", "gripper_width", "joint_positions", "part_pose")}
        step["part_axis"] = _part_axis(step["part_pose"], plus_axis)
        for key, values in demo.items():
            if prefix and key.startswith(prefix):
                step[key[len(prefix) :]] = values[t]
            elif kind == "rgbd" and key in ("rgb", "depth"):
                step[key] = values[t]
        steps.append(step)
    return steps


def _with_history(rows: np.ndarray, history: int) -> np.ndarray:
    """(T, history * F): each step's features after those of the steps before it (the first repeated)."""
    padded = np.concatenate([np.repeat(rows[:1], history - 1, axis=0), rows], axis=0)
    return np.concatenate([padded[i : i + len(rows)] for i in range(history)], axis=1)


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
    encoded by a :class:`SpatialSoftmaxEncoder` first) to an action in [-1, 1]^5."""

    def __init__(self, feature_size: int, history: int = HISTORY, images: bool = False, hidden: int = 256) -> None:
        super().__init__()
        self.history = history
        self.encoder = SpatialSoftmaxEncoder() if images else None
        step = feature_size + (self.encoder.out_features if self.encoder is not None else 0)
        self.head = nn.Sequential(
            nn.Linear(history * step, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
            nn.Linear(hidden, 5), nn.Tanh(),
        )  # fmt: skip
        self.register_buffer("mean", torch.zeros(history * feature_size))
        self.register_buffer("std", torch.ones(history * feature_size))

    def forward(self, vectors: torch.Tensor, images: torch.Tensor | None = None) -> torch.Tensor:
        x = (vectors - self.mean) / self.std
        if self.encoder is not None:
            b = images.shape[0]  # images (B, history, C, H, W)
            codes = self.encoder(images.flatten(0, 1)).reshape(b, self.history, -1)
            steps = x.reshape(b, self.history, -1)
            x = torch.cat([steps, codes], dim=-1).flatten(1)
        return self.head(x)


def train_policy(
    kind: str, demos: Any, steps: int = 2000, batch: int = 64, seed: int = 0, progress: bool = False
) -> HistoryPolicy:
    """Behaviour cloning (mean squared action error, Adam) of a :class:`HistoryPolicy` on ``kind``'s features of
    the :class:`~don_gym.evaluation.demonstrations.Demonstrations`, ``steps`` gradient steps."""
    torch.manual_seed(seed)
    vectors, images, actions = [], [], []
    for demo, action in zip(demos.observations, demos.actions, strict=True):
        rows = _demo_steps(kind, demo, load_object(demos.part).plus_axis)
        vectors.append(_with_history(np.stack([features(kind, r) for r in rows]), HISTORY))
        if kind == "rgbd":
            frames = np.stack([_image(r) for r in rows])
            padded = np.concatenate([np.repeat(frames[:1], HISTORY - 1, axis=0), frames], axis=0)
            images.append(np.stack([padded[i : i + len(rows)] for i in range(HISTORY)], axis=1))
        actions.append(action)
    x = torch.from_numpy(np.concatenate(vectors))
    y = torch.from_numpy(np.concatenate(actions))
    pictures = torch.from_numpy(np.concatenate(images)) if images else None
    policy = HistoryPolicy(x.shape[1] // HISTORY, HISTORY, images=kind == "rgbd")
    policy.mean.copy_(x.mean(dim=0))
    policy.std.copy_(x.std(dim=0).clamp_min(1e-3))
    optimiser = torch.optim.Adam(policy.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    for _ in tqdm(range(steps), desc=f"BC {kind}", disable=not progress):
        index = torch.randint(0, len(x), (batch,), generator=generator)
        prediction = policy(x[index], None if pictures is None else pictures[index])
        loss = torch.mean((prediction - y[index]) ** 2)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return policy.eval()


# ------------------------------------------------------------------------------ evaluation
def _live_step(obs: dict[str, np.ndarray], info: dict[str, Any], plus_axis: np.ndarray) -> dict[str, np.ndarray]:
    step = dict(obs)
    T = np.asarray(info["T_world_object"], dtype=np.float64)
    step["part_pose"] = np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()])
    step["part_axis"] = T[:3, :3] @ plus_axis
    return step


def evaluate_policy(
    policy: HistoryPolicy,
    kind: str,
    part: str,
    goal: str,
    episodes: int,
    settings: RecordSettings | None = None,
    seed: int = EVAL_SEED,
    progress: bool = False,
) -> int:
    """Successes of ``policy`` on ``episodes`` held-out episodes (``reset(seed=seed + i)``) of ``goal`` seeing
    ``kind``'s observations. Lift: :func:`~don_gym.wrappers.goals.goal_reached` for the part's axis points
    :data:`~don_gym.wrappers.goals.LIFT_GOAL_HEIGHT_M` above where they lay, lifted; place: the task's success."""
    env = kind_env(kind, part, goal, settings or RecordSettings(), observe_state=True)
    targets = axis_end_targets(env.unwrapped.model)
    wins = 0
    try:
        for i in tqdm(range(episodes), desc=f"eval {kind}", disable=not progress):
            obs, info = env.reset(seed=seed + i)
            start = axis_points_world(env.unwrapped.model, targets, info["T_world_object"])
            desired = (start + [0.0, 0.0, LIFT_GOAL_HEIGHT_M]).reshape(6)
            history: deque = deque(maxlen=HISTORY)
            done, success = False, False
            while not done:
                step = _live_step(obs, info, env.unwrapped.model.plus_axis)
                history.append((features(kind, step), _image(step) if kind == "rgbd" else None))
                while len(history) < HISTORY:
                    history.appendleft(history[0])
                vector = torch.from_numpy(np.concatenate([h[0] for h in history]))[None]
                images = torch.from_numpy(np.stack([h[1] for h in history]))[None] if kind == "rgbd" else None
                with torch.inference_mode():
                    action = policy(vector, images)[0].numpy()
                obs, _, terminated, truncated, info = env.step(action)
                if goal == "lift":
                    achieved = axis_points_world(env.unwrapped.model, targets, info["T_world_object"]).reshape(6)
                    success = bool(goal_reached(achieved, desired)) and bool(info.get("lifted", False))
                else:
                    success = bool(info.get("is_success", False))
                done = success or terminated or truncated
            wins += success
    finally:
        env.close()
    return wins


# -------------------------------------------------------------------------------- the run
@dataclass
class ImitationConfig:
    """What :func:`run_imitation` compares: ``inputs`` at each of ``demonstrations`` (N), ``episodes`` held-out
    evaluation episodes each, behaviour cloning for ``train_steps`` gradient steps."""

    part: str = "toolcap"
    goal: str = "lift"
    inputs: tuple[str, ...] = ("state", "true", "simulated:toolcap/supervised-edge", "rgbd")
    demonstrations: tuple[int, ...] = (10, 25, 50, 100, 200)
    episodes: int = 100
    train_steps: int = 2000
    seed: int = 0
    settings: RecordSettings = field(default_factory=RecordSettings)


@dataclass
class ImitationResult:
    """Successes per input and N (``wins[input][n]``) out of ``config.episodes``, and the demonstrations file."""

    config: ImitationConfig
    wins: dict[str, dict[int, int]]
    demos_path: str

    def rates(self) -> dict[str, list[tuple[int, float, float, float]]]:
        """Per input, ``(n, rate, low, high)`` with the 95% Wilson interval."""
        episodes = self.config.episodes
        return {
            name: [(n, w / episodes, *wilson_interval(w, episodes)) for n, w in sorted(by_n.items())]
            for name, by_n in self.wins.items()
        }

    def table(self) -> str:
        """Markdown: one row per input, one column per N, successes with their interval."""
        ns = sorted(self.config.demonstrations)
        lines = ["| input | " + " | ".join(f"N = {n}" for n in ns) + " |", "|---|" + "---|" * len(ns)]
        for name, points in self.rates().items():
            cells = [f"{100 * r:.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]" for _, r, lo, hi in points]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _check_config(config: ImitationConfig) -> None:
    for name in config.inputs:
        source = name.split(":", 1)
        if name not in ("state", "true", "rgbd") and not (len(source) == 2 and source[0] in ("simulated", "don")):
            raise DonGymError(f"input {name!r} is unknown; expected one of {list(INPUTS)}")
    if not config.demonstrations or any(isinstance(n, bool) or int(n) < 1 for n in config.demonstrations):
        raise DonGymError(f"demonstrations={list(config.demonstrations)}: expected positive numbers")
    if int(config.episodes) < 1:
        raise DonGymError(f"episodes={config.episodes}: expected a positive number of evaluation episodes")


def run_imitation(
    config: ImitationConfig, work: str | Path, demos: str | Path | None = None, progress: bool = True
) -> ImitationResult:
    """Record (or take ``demos``, checked to be of the config's part and goal, with every input) the largest N's
    demonstrations, clone a policy per input and N from the first N of them, and evaluate each."""
    _check_config(config)
    largest = max(config.demonstrations)
    if demos is None:
        demos = Path(work) / f"demos_{config.part}_{config.goal}.hdf5"
        record_demonstrations(
            demos, config.part, config.goal, largest, config.seed, ["state", *config.inputs], config.settings,
            progress=progress,
        )  # fmt: skip
    everything = read_demonstrations(demos, count=largest, part=config.part, goal=config.goal)
    missing = [name for name in config.inputs if name not in everything.kinds]
    if missing:
        raise DonGymError(f"demonstrations {str(demos)!r} lack the inputs {missing}; it has {everything.kinds}")
    wins: dict[str, dict[int, int]] = {}
    for name in config.inputs:
        wins[name] = {}
        for n in sorted(config.demonstrations):
            subset = read_demonstrations(demos, count=n)
            policy = train_policy(name, subset, config.train_steps, seed=config.seed)
            wins[name][n] = evaluate_policy(
                policy, name, config.part, config.goal, config.episodes, config.settings, progress=progress
            )
    return ImitationResult(config, wins, str(demos))
