"""Reinforcement-learning baselines with stable-baselines3 (the ``rl`` extra).

Two baselines, both seeing the part only through DON keypoints
(:class:`don_gym.wrappers.KeypointObservation`), never through its true pose:

- **PPO on** ``control="grasp"`` (:func:`make_ppo_env`): a one-step episode per grasp. The
  policy sees the keypoints of the observation image as a flat vector (:class:`KeypointFeatures`)
  and outputs a normalised action in [-1, 1]^5 (:class:`KeypointGraspAction`): an offset of the
  grasp point from the confidence-weighted keypoint centroid (x, y within +-5 cm, z within
  +-3 cm) and the yaw as a (cos, sin) pair, so that yaw is a smooth function of the keypoints
  without a jump at +-pi. ``action_frame="world"`` instead spans the env's whole action box.
- **SAC on** ``control="ee"`` (:func:`make_sac_env`): 25 Hz Cartesian control. The policy sees the
  robot state (TCP pose, gripper width) and the keypoints found in the current wrist-camera
  image, also relative to the TCP. The keypoints move with the camera and vanish when the part
  leaves the view; the policy gets their confidences so it can tell.

Flat observations: positions relative to a reference, in units that make the inputs of the
networks of order one: absolute positions (relative to the workspace centre) and keypoints
relative to the TCP in :data:`POSITION_UNIT_M` (5 cm), keypoints relative to their centroid in
:data:`KEYPOINT_OFFSET_UNIT_M` (1 cm: the two keypoints of the toolcap are 2.4 cm apart, and
the yaw the policy must read off them is in that difference).

Train with :func:`train` (seeded, tqdm progress bar, learning curve of the training episodes
recorded by :class:`LearningCurve`) and measure with :func:`evaluate` on seeded episodes
(``reset(seed=seed + i)`` for episode ``i``: any two policies evaluated with the same seed face
the same part poses and calibration errors). ``benchmarks/bench_rl.py`` runs both baselines.

stable-baselines3 is imported only inside the functions that need it; without it they raise
ImportError naming ``pip install "don-gym[rl]"``. The env wrappers work without it.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.sim.task import TABLE_TOP_Z_M, WORKSPACE_M

#: The pip command that installs stable-baselines3 for these baselines.
RL_INSTALL_HINT = 'pip install "don-gym[rl]"'
ALGORITHMS = ("ppo", "sac")
ACTION_FRAMES = ("keypoints", "world")
#: Length unit (m) of positions in the flat observations, except keypoints relative to their centroid.
POSITION_UNIT_M = 0.05
#: Length unit (m) of keypoints relative to their centroid in the flat observations.
KEYPOINT_OFFSET_UNIT_M = 0.01
#: Workspace centre (m, world): the reference of absolute positions in the flat observations.
WORKSPACE_CENTRE_M = np.array(
    [(WORKSPACE_M[0] + WORKSPACE_M[1]) / 2, (WORKSPACE_M[2] + WORKSPACE_M[3]) / 2, TABLE_TOP_Z_M]
)
#: Keypoint action frame: largest offset (m) of the grasp point from the keypoint centroid in x, y
#: and in z. The toolcap is 34 mm across and 40 mm long, and a grasp succeeds within about 1 cm.
GRASP_OFFSET_XY_M = 0.05
GRASP_OFFSET_Z_M = 0.03
#: Keypoints with a confidence at or below this count as not found.
MIN_CONFIDENCE = 0.0


def require_sb3() -> Any:
    """Import stable_baselines3, or raise ImportError telling the user how to install it."""
    try:
        import stable_baselines3
    except ImportError as exc:
        raise ImportError(
            f"the RL baselines need stable-baselines3, which is not installed: {RL_INSTALL_HINT}"
        ) from exc
    return stable_baselines3


# ------------------------------------------------------------------------------ observations
def keypoint_centroid(points_m: np.ndarray, confidence: np.ndarray) -> np.ndarray | None:
    """Confidence-weighted mean (3,) of the found keypoints (K, 3), or None when none was found."""
    found = _found(points_m, confidence)
    if not found.any():
        return None
    weights = confidence[found].astype(np.float64)
    return (points_m[found].astype(np.float64) * weights[:, None]).sum(axis=0) / weights.sum()


def _found(points_m: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    return np.isfinite(points_m).all(axis=1) & np.isfinite(confidence) & (confidence > MIN_CONFIDENCE)


class KeypointFeatures(gym.ObservationWrapper):
    """Flatten a keypoint observation into the float32 vector an MLP policy reads.

    Input: a Dict observation with ``keypoint_points`` (K, 3) world m and ``keypoint_confidence``
    (K,) (from :class:`don_gym.wrappers.KeypointObservation`) and, for ``relative_to="tcp"`` or
    ``robot_state=True``, ``ee_pose`` (7,) and ``gripper_width`` (1,).

    Output, in this order (lengths in units of :data:`POSITION_UNIT_M` unless said otherwise):

    - keypoint centroid relative to the workspace centre (3,),
    - each keypoint relative to the centroid (``relative_to="centroid"``, in units of
      :data:`KEYPOINT_OFFSET_UNIT_M`) or to the TCP (``"tcp"``) (K*3,),
    - confidences (K,),
    - with ``robot_state``: TCP position relative to the workspace centre (3,), TCP quaternion
      (4,), gripper width in units of 4 cm (1,).

    Keypoints not found (confidence 0 or non-finite) read as zeros with confidence 0; the
    centroid of a frame without any keypoint reads as zeros.
    """

    def __init__(self, env: gym.Env, relative_to: str = "centroid", robot_state: bool = False):
        super().__init__(env)
        if relative_to not in ("centroid", "tcp"):
            raise DonGymError(f"relative_to={relative_to!r}: expected 'centroid' or 'tcp'")
        space = env.observation_space
        needed = ["keypoint_points", "keypoint_confidence"]
        if relative_to == "tcp" or robot_state:
            needed += ["ee_pose", "gripper_width"]
        missing = [key for key in needed if not isinstance(space, spaces.Dict) or key not in space.spaces]
        if missing:
            raise DonGymError(
                f"KeypointFeatures needs observation keys {missing}: wrap the env in "
                "don_gym.wrappers.KeypointObservation first"
            )
        self.relative_to = relative_to
        self.robot_state = robot_state
        self.num_keypoints = int(space["keypoint_points"].shape[0])
        size = 3 + 4 * self.num_keypoints + (8 if robot_state else 0)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float32)

    def observation(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        points = np.asarray(observation["keypoint_points"], dtype=np.float64).reshape(-1, 3)
        confidence = np.asarray(observation["keypoint_confidence"], dtype=np.float64).reshape(-1)
        found = _found(points, confidence)
        centroid = keypoint_centroid(points, confidence)
        if self.relative_to == "tcp":
            reference, unit = np.asarray(observation["ee_pose"], dtype=np.float64)[:3], POSITION_UNIT_M
        else:
            reference = WORKSPACE_CENTRE_M if centroid is None else centroid
            unit = KEYPOINT_OFFSET_UNIT_M
        relative = np.where(found[:, None], points - reference, 0.0) / unit
        parts = [
            np.zeros(3) if centroid is None else (centroid - WORKSPACE_CENTRE_M) / POSITION_UNIT_M,
            relative.reshape(-1),
            np.where(found, confidence, 0.0),
        ]
        if self.robot_state:
            ee_pose = np.asarray(observation["ee_pose"], dtype=np.float64)
            parts += [
                (ee_pose[:3] - WORKSPACE_CENTRE_M) / POSITION_UNIT_M,
                ee_pose[3:7],
                np.asarray(observation["gripper_width"], dtype=np.float64).reshape(1) / 0.04,
            ]
        return np.concatenate(parts).astype(np.float32)


# -------------------------------------------------------------------------------- actions
class KeypointGraspAction(gym.Wrapper):
    """Grasp-mode actions in [-1, 1]^5 for a policy: (x, y, z, cos yaw, sin yaw).

    ``frame="keypoints"``: the grasp point is the keypoint centroid of the reset observation plus
    (x, y) * :data:`GRASP_OFFSET_XY_M` and z * :data:`GRASP_OFFSET_Z_M`; a frame without keypoints
    falls back to the workspace centre at table height. ``frame="world"``: (x, y, z) span the
    env's action box linearly. In both, the yaw of the believed +axis is ``atan2(sin, cos)``
    (a zero vector reads as yaw 0). Must wrap an env whose observations still hold
    ``keypoint_points`` and ``keypoint_confidence`` (put it below :class:`KeypointFeatures`).
    """

    def __init__(self, env: gym.Env, frame: str = "keypoints"):
        super().__init__(env)
        if frame not in ACTION_FRAMES:
            raise DonGymError(f"action_frame={frame!r} is unknown; expected one of {list(ACTION_FRAMES)}")
        if getattr(env.unwrapped, "control", None) != "grasp":
            raise DonGymError("KeypointGraspAction needs an env with control='grasp'")
        self.frame = frame
        self.action_space = spaces.Box(-1.0, 1.0, shape=(5,), dtype=np.float32)
        self._centroid = WORKSPACE_CENTRE_M.copy()

    def reset(self, **kwargs: Any):
        observation, info = self.env.reset(**kwargs)
        centroid = keypoint_centroid(
            np.asarray(observation["keypoint_points"]), np.asarray(observation["keypoint_confidence"])
        )
        self._centroid = WORKSPACE_CENTRE_M.copy() if centroid is None else centroid
        return observation, info

    def grasp_action(self, action: np.ndarray) -> np.ndarray:
        """The env action [x, y, z, yaw] (world m, rad) of a normalised action."""
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        if action.shape != (5,):
            raise DonGymError(f"action has shape {action.shape}, expected (5,)")
        if self.frame == "keypoints":
            offset = action[:3] * np.array([GRASP_OFFSET_XY_M, GRASP_OFFSET_XY_M, GRASP_OFFSET_Z_M])
            point = self._centroid + offset
        else:
            low, high = self.env.action_space.low[:3], self.env.action_space.high[:3]
            point = low + (action[:3] + 1.0) * 0.5 * (high - low)
        yaw = float(np.arctan2(action[4], action[3]))
        return np.array([*point, yaw], dtype=np.float32)

    def step(self, action: np.ndarray):
        return self.env.step(self.grasp_action(action))


# ------------------------------------------------------------------------------- the envs
def _keypoint_env(
    object: str | Path, keypoint_model: str | Path, keypoint_kwargs: dict[str, Any] | None, **env_kwargs: Any
) -> gym.Env:
    import don_gym  # noqa: F401 - registers the env ids
    from don_gym.wrappers import KeypointObservation

    env = gym.make("DONPick-v0", object=object, **env_kwargs)
    return KeypointObservation(env, model=keypoint_model, keep_images=False, **(keypoint_kwargs or {}))


def make_ppo_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoint_model: str | Path = "oracle",
    image_size: tuple[int, int] = (160, 120),
    sensor: str = "d435",
    reward_type: str = "dense",
    action_frame: str = "keypoints",
    keypoint_kwargs: dict[str, Any] | None = None,
) -> gym.Env:
    """The PPO baseline's env: ``control="grasp"`` with keypoints, flat observations and
    normalised actions (see the module docstring).

    ``keypoint_model``: "oracle" (keypoints from descriptors rendered at the true pose: a check of
    the pipeline, not a perception result), a shipped DON name such as
    "toolcap/supervised-edge", or a checkpoint path. ``reward_type="dense"`` gives failed grasps a
    graded penalty (the success rate is measured either way by ``info["is_success"]``).
    """
    env = _keypoint_env(
        object, keypoint_model, keypoint_kwargs, control="grasp", image_size=image_size, sensor=sensor,
        reward_type=reward_type,
    )  # fmt: skip
    env = KeypointGraspAction(env, frame=action_frame)
    return KeypointFeatures(env, relative_to="centroid", robot_state=False)


def make_sac_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoint_model: str | Path = "oracle",
    image_size: tuple[int, int] = (160, 120),
    sensor: str = "d435",
    reward_type: str = "dense",
    max_steps: int = 100,
    keypoint_kwargs: dict[str, Any] | None = None,
) -> gym.Env:
    """The SAC baseline's env: ``control="ee"``, keypoints from the wrist camera at every step
    (relative to the TCP) plus the robot state, as one flat vector (see the module docstring)."""
    env = _keypoint_env(
        object, keypoint_model, keypoint_kwargs, control="ee", image_size=image_size, sensor=sensor,
        reward_type=reward_type, max_steps=max_steps,
    )  # fmt: skip
    return KeypointFeatures(env, relative_to="tcp", robot_state=True)


ENV_MAKERS: dict[str, Callable[..., gym.Env]] = {"ppo": make_ppo_env, "sac": make_sac_env}

#: Defaults sized for a short CPU budget. PPO on grasp: every step is a whole episode (a one-step
#: bandit), so small rollouts keep updates frequent; gamma does not matter. SAC on ee: small nets
#: so one gradient step per env step stays cheaper than the rendering of that step.
DEFAULT_ALGO_KWARGS: dict[str, dict[str, Any]] = {
    "ppo": {
        "n_steps": 32,
        "batch_size": 16,
        "n_epochs": 10,
        "learning_rate": 3e-4,
        "gamma": 0.99,
        "ent_coef": 0.0,
        "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -0.5},
    },
    "sac": {
        "learning_starts": 500,
        "buffer_size": 100_000,
        "batch_size": 128,
        "learning_rate": 3e-4,
        "gamma": 0.98,
        "train_freq": 1,
        "gradient_steps": 1,
        "policy_kwargs": {"net_arch": [128, 128]},
    },
}


# ------------------------------------------------------------------------- learning curve
@dataclass
class LearningCurve:
    """Training episodes in the order they ended: env steps so far (all envs), return, success."""

    env_steps: list[int] = field(default_factory=list)
    returns: list[float] = field(default_factory=list)
    successes: list[bool] = field(default_factory=list)

    def add(self, env_steps: int, episode_return: float, success: bool) -> None:
        self.env_steps.append(int(env_steps))
        self.returns.append(float(episode_return))
        self.successes.append(bool(success))

    def rolling(self, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(env steps, success rate, mean return) over the last ``window`` episodes at each episode end."""
        n = len(self.env_steps)
        if n == 0:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        window = max(1, min(int(window), n))
        kernel = np.ones(window)
        counts = np.convolve(np.ones(n), kernel)[:n]
        success = np.convolve(np.asarray(self.successes, dtype=np.float64), kernel)[:n] / counts
        returns = np.convolve(np.asarray(self.returns, dtype=np.float64), kernel)[:n] / counts
        return np.asarray(self.env_steps), success, returns


def _curve_callback(curve: LearningCurve, total_timesteps: int, description: str, progress: bool) -> Any:
    """SB3 callback: records finished episodes into ``curve`` and drives a tqdm bar of env steps."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    class _Callback(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(total=total_timesteps, desc=description, unit="step", disable=not progress)

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            for info in self.locals["infos"]:
                episode = info.get("episode")  # set by Monitor when an episode ends
                if episode is not None:
                    curve.add(self.num_timesteps, episode["r"], info.get("is_success", False))
            if curve.successes:
                self.bar.set_postfix(episodes=len(curve.successes), success=f"{np.mean(curve.successes[-50:]):.2f}")
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return _Callback()


def _monitored(maker: Callable[..., gym.Env], env_kwargs: dict[str, Any]) -> gym.Env:
    from stable_baselines3.common.monitor import Monitor

    return Monitor(maker(**env_kwargs), info_keywords=("is_success",))


@dataclass
class TrainResult:
    model: Any
    curve: LearningCurve
    wall_s: float


def train(
    algorithm: str,
    total_timesteps: int,
    seed: int = 0,
    n_envs: int = 1,
    env_kwargs: dict[str, Any] | None = None,
    algo_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
) -> TrainResult:
    """Train the PPO (grasp) or SAC (ee) baseline for ``total_timesteps`` env steps.

    ``env_kwargs`` go to :func:`make_ppo_env` / :func:`make_sac_env`; ``algo_kwargs`` override
    :data:`DEFAULT_ALGO_KWARGS`. Env ``i`` is seeded ``seed + i`` and the algorithm ``seed``: a
    run with the same arguments and one torch thread repeats exactly. ``n_envs > 1`` steps the
    envs in subprocesses (worth it only with a free core per env: the physics dominates).
    """
    if algorithm not in ALGORITHMS:
        raise DonGymError(f"algorithm={algorithm!r} is unknown; expected one of {list(ALGORITHMS)}")
    if int(total_timesteps) < 1 or int(n_envs) < 1:
        raise DonGymError(f"total_timesteps={total_timesteps!r} and n_envs={n_envs!r} must be positive")
    sb3 = require_sb3()
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    maker = ENV_MAKERS[algorithm]
    env_fn = functools.partial(_monitored, maker, dict(env_kwargs or {}))
    vec_env = SubprocVecEnv([env_fn] * n_envs) if n_envs > 1 else DummyVecEnv([env_fn])
    kwargs = DEFAULT_ALGO_KWARGS[algorithm] | dict(algo_kwargs or {})
    algo_class = sb3.PPO if algorithm == "ppo" else sb3.SAC
    curve = LearningCurve()
    start = time.perf_counter()
    try:
        model = algo_class("MlpPolicy", vec_env, seed=seed, device="cpu", verbose=0, **kwargs)
        callback = _curve_callback(curve, int(total_timesteps), f"{algorithm.upper()} train", progress)
        model.learn(total_timesteps=int(total_timesteps), callback=callback)
    finally:
        vec_env.close()
    return TrainResult(model=model, curve=curve, wall_s=time.perf_counter() - start)


# ------------------------------------------------------------------------------ evaluation
@dataclass
class EvaluationResult:
    """Per-episode outcomes of :func:`evaluate` (episode i was reset with ``seed + i``)."""

    returns: list[float]
    successes: list[bool]
    outcomes: list[str]
    lengths: list[int]
    wall_s: float

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else 0.0

    @property
    def mean_return(self) -> float:
        return float(np.mean(self.returns)) if self.returns else 0.0

    def outcome_counts(self) -> dict[str, int]:
        names = ("fail", "grasp_only", "grasp_and_place")
        return {name: sum(outcome == name for outcome in self.outcomes) for name in names}


def evaluate(
    env: gym.Env,
    policy: Callable[[Any], np.ndarray],
    n_episodes: int,
    seed: int,
    description: str = "evaluate",
    progress: bool = True,
) -> EvaluationResult:
    """Run ``policy(observation) -> action`` for ``n_episodes`` episodes, episode ``i`` reset with
    ``seed + i``. Success is ``info["is_success"]`` at the episode's last step."""
    from tqdm import tqdm

    if int(n_episodes) < 1:
        raise DonGymError(f"n_episodes={n_episodes!r}: expected a positive number of episodes")
    result = EvaluationResult([], [], [], [], 0.0)
    start = time.perf_counter()
    for i in tqdm(range(int(n_episodes)), desc=description, unit="episode", disable=not progress):
        observation, info = env.reset(seed=int(seed) + i)
        total, length, done = 0.0, 0, False
        while not done:
            observation, reward, terminated, truncated, info = env.step(policy(observation))
            total += float(reward)
            length += 1
            done = terminated or truncated
        result.returns.append(total)
        result.successes.append(bool(info.get("is_success", False)))
        result.outcomes.append(str(info.get("outcome", "")))
        result.lengths.append(length)
    result.wall_s = time.perf_counter() - start
    return result


def model_policy(model: Any) -> Callable[[Any], np.ndarray]:
    """The deterministic policy of a trained SB3 model, as ``observation -> action``."""
    return lambda observation: model.predict(observation, deterministic=True)[0]


def random_policy(action_space: spaces.Space, seed: int) -> Callable[[Any], np.ndarray]:
    """Uniform random actions from ``action_space``, seeded."""
    space = spaces.Box(action_space.low, action_space.high, dtype=action_space.dtype)
    space.seed(int(seed))
    return lambda observation: space.sample()


def plot_learning_curve(
    curves: Sequence[tuple[str, LearningCurve]],
    path: str | Path,
    window: int,
    title: str,
    reference_lines: Sequence[tuple[str, float, float]] = (),
) -> None:
    """Success rate and mean return (rolling over ``window`` training episodes) against env steps.

    ``reference_lines``: (label, success rate, mean return) of baselines drawn as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from don_gym.io import atomic_path

    figure, (ax_success, ax_return) = plt.subplots(1, 2, figsize=(10, 4.4))
    for label, curve in curves:
        steps, success, returns = curve.rolling(window)
        ax_success.plot(steps, success, label=label)
        ax_return.plot(steps, returns, label=label)
    for k, (label, success_rate, mean_return) in enumerate(reference_lines):
        colour = f"C{k + len(curves)}"
        ax_success.axhline(success_rate, linestyle="--", color=colour, label=label)
        ax_return.axhline(mean_return, linestyle="--", color=colour, label=label)
    ax_success.set(xlabel="env steps", ylabel=f"success rate (last {window} episodes)", ylim=(-0.02, 1.02))
    ax_return.set(xlabel="env steps", ylabel=f"episode return (mean of last {window})")
    handles, labels = ax_success.get_legend_handles_labels()
    rows = (len(labels) + 2) // 3
    # One legend under both plots, so that no line is hidden behind it.
    figure.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    figure.suptitle(title)
    figure.tight_layout(rect=(0.0, 0.06 * rows, 1.0, 1.0))
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=110)
    plt.close(figure)
