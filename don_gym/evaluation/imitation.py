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
#: Steps of observation history the policy sees (the current one included).
HISTORY = 2
#: Held-out evaluation episodes are ``reset(seed=EVAL_SEED + i)`` (bench_rl's and bench_expert's).
EVAL_SEED = 100_000
#: Unit (m) of positions in the feature vectors.
POSITION_UNIT_M = 0.05


# ------------------------------------------------------------------------------ features
def _robot_features(obs: dict[str, np.ndarray]) -> np.ndarray:
    """TCP position, the hand's yaw as (cos, sin) (the top-down hand's quaternion flips sign as the yaw passes pi)
    and the finger opening."""
    ee = np.asarray(obs["ee_pose"], dtype=np.float64).reshape(7)
    hand_x = Rotation.from_quat(ee[3:]).as_matrix()[:2, 0]
    width = np.asarray(obs["gripper_width"], dtype=np.float64).reshape(1) / 0.04
    return np.concatenate([ee[:3] / POSITION_UNIT_M, hand_x / max(np.linalg.norm(hand_x), 1e-9), width])


def features(kind: str, obs: dict[str, np.ndarray]) -> np.ndarray:
    """The feature vector (float32) of ``kind`` from an observation with the robot keys, ``part_pose`` for
    "state" and the keypoint keys (un-prefixed) for keypoint kinds; for "rgbd" the robot's state only."""
    robot = _robot_features(obs)
    if kind == "rgbd":
        return robot.astype(np.float32)
    if kind == "state":
        pose = np.asarray(obs["part_pose"], dtype=np.float64)
        # The rotation's first two columns, not the quaternion: continuous, no sign to flip (Zhou et al. 2019).
        rotation = Rotation.from_quat(pose[3:]).as_matrix()[:, :2].T.ravel()
        tcp = np.asarray(obs["ee_pose"], dtype=np.float64)[:3]
        return np.concatenate([robot, (pose[:3] - tcp) / POSITION_UNIT_M, rotation]).astype(np.float32)
    tcp = np.asarray(obs["ee_pose"], dtype=np.float64)[:3]
    points = (np.asarray(obs["keypoint_points"], dtype=np.float64) - tcp) / POSITION_UNIT_M
    confidence = np.asarray(obs["keypoint_confidence"], dtype=np.float64)
    points = np.where(confidence[:, None] > 0, points, 0.0)
    memory = (np.asarray(obs["keypoint_memory_points"], dtype=np.float64) - tcp) / POSITION_UNIT_M
    age = np.asarray(obs["keypoint_age"], dtype=np.float64) / 100.0
    return np.concatenate([robot, points.ravel(), confidence, memory.ravel(), age]).astype(np.float32)


def _image(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(4, H, W) float32: RGB in [0, 1] and depth in metres."""
    rgb = np.asarray(obs["rgb"], dtype=np.float32).transpose(2, 0, 1) / 255.0
    return np.concatenate([rgb, np.asarray(obs["depth"], dtype=np.float32)[None]], axis=0)


def _demo_steps(kind: str, demo: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    """A demo's observations as per-step dicts with the un-prefixed keys :func:`features` reads."""
    prefix = "" if kind in ("state", "rgbd") else kind_name(kind) + "."
    T = len(demo["ee_pose"])
    steps = []
    for t in range(T):
        step = {key: demo[key][t] for key in ("ee_pose", "gripper_width", "part_pose")}
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
        rows = _demo_steps(kind, demo)
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
def _live_step(kind: str, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
    step = dict(obs)
    T = np.asarray(info["T_world_object"], dtype=np.float64)
    step["part_pose"] = np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()])
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
                step = _live_step(kind, obs, info)
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
