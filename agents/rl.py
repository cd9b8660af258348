"""Reinforcement-learning baselines with stable-baselines3 (the ``rl`` extra), seeing the part only
through its axis-end keypoints, never through its true pose.

- PPO on ``control="grasp"`` (:func:`make_ppo_env`): one grasp per episode, flat keypoint features
  and residual actions in the keypoints' own axis frame (:mod:`don_gym.wrappers.rl`).
- SAC on ``control="ee"`` (:func:`make_sac_env`): 25 Hz Cartesian control from the robot state and
  the keypoints of each wrist-camera image; with ``goal=`` goal-conditioned, trained with HER.
- PPO on ``control="grasp"`` from descriptor images through a CNN (:func:`make_image_env`).

Keypoints (``keypoints=``, :data:`don_gym.wrappers.goals.KEYPOINT_SOURCES`): ``"don"`` a DON or the oracle
on rendered images (:class:`~don_gym.wrappers.KeypointObservation`); ``"simulated"`` a model of the DON, no
rendering (:class:`~don_gym.wrappers.SimulatedKeypoints` with the network's measured noise); ``"true"``
exact keypoints always in view. :func:`train` runs SB3 with a tqdm bar and, given ``run_dir``, writes the
learning curve (CSV, PNG), configuration and seeds (JSON) and periodic saves it can resume from;
:func:`evaluate` measures a policy on seeded episodes. ``n_envs > 1`` with ``vectorize="batched"``
steps the sub-envs together and runs the DON once per step on all their images
(:class:`~don_gym.wrappers.VectorKeypointObservation`). stable-baselines3 is imported only inside the
functions that need it (ImportError naming ``pip install "don-gym[rl]"`` without it).

Longer budgets on a GPU machine: the recipe in ``benchmarks/bench_rl.py``'s docstring (SAC+HER with 8
batched envs, the DON on the GPU).
"""

from __future__ import annotations

import csv
import json
import platform
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.agents.rl_demos import check_demonstration_settings, use_demonstrations
from don_gym.agents.rl_envs import (
    ENV_MAKERS,
    VECTORIZE,
    check_n_envs,
    make_batched_sac_vec_env,
    make_batched_vec_env,
    make_image_env,
    make_ppo_env,
    make_sac_env,
    make_vec_env,
)
from don_gym.errors import DonGymError
from don_gym.io import atomic_path, write_text_atomic
from don_gym.sim.task import OUTCOMES
from don_gym.wrappers.rl import POSITION_UNIT_M, WORKSPACE_CENTRE_M

# The env factories live in don_gym.agents.rl_envs; offered here too, beside the training that uses them.
__all__ = [
    "ALGORITHMS",
    "DEFAULT_ALGO_KWARGS",
    "ENV_MAKERS",
    "RL_INSTALL_HINT",
    "RUN_FILES",
    "VECTORIZE",
    "EvaluationResult",
    "LearningCurve",
    "RLTrainResult",
    "evaluate",
    "make_batched_sac_vec_env",
    "make_batched_vec_env",
    "make_image_env",
    "make_ppo_env",
    "make_sac_env",
    "make_vec_env",
    "model_policy",
    "random_policy",
    "require_sb3",
    "save_checkpoint",
    "saved_progress",
    "train",
    "write_run_outputs",
]

#: The pip command that installs stable-baselines3 for these baselines.
RL_INSTALL_HINT = 'pip install "don-gym[rl]"'
ALGORITHMS = ("ppo", "sac", "ppo-images")
#: Files a run directory holds (see :func:`train`).
RUN_FILES = {
    "config": "config.json",
    "curve_csv": "curve.csv",
    "curve_png": "curve.png",
    "model": "model.zip",
    "last_model": "model_last.zip",
    "last_buffer": "replay_buffer_last.pkl",
    "last_curve": "curve_last.csv",
    "last_progress": "progress_last.json",
    "demonstrations": "demonstrations.npz",
}


def require_sb3() -> Any:
    """Import stable_baselines3, or raise ImportError telling the user how to install it."""
    try:
        import stable_baselines3
    except ImportError as exc:
        raise ImportError(
            f"the RL baselines need stable-baselines3, which is not installed: {RL_INSTALL_HINT}"
        ) from exc
    return stable_baselines3


#: Defaults sized for a short CPU budget. PPO on grasp: every step is a whole episode (a one-step
#: bandit), so small rollouts keep updates frequent; gamma does not matter; a small initial action
#: noise, as the axis frame's action 0 already grasps. SAC on ee: small nets so one gradient step
#: per env step stays cheaper than the rendering of that step. SAC with HER (``goal=``): the usual
#: goal-conditioned settings (future strategy, 4 relabelled goals per transition, soft target
#: updates of 0.05, gamma 0.95).
DEFAULT_ALGO_KWARGS: dict[str, dict[str, Any]] = {
    "ppo": {
        "n_steps": 32,
        "batch_size": 16,
        "n_epochs": 10,
        "learning_rate": 3e-4,
        "gamma": 0.99,
        "ent_coef": 0.0,
        "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -1.0},
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
    "sac-her": {
        "learning_starts": 1000,
        "buffer_size": 300_000,
        "batch_size": 256,
        "learning_rate": 1e-3,
        "gamma": 0.95,
        "tau": 0.05,
        "train_freq": 1,
        "gradient_steps": 1,
        "policy_kwargs": {"net_arch": [256, 256]},
        "replay_buffer_kwargs": {"n_sampled_goal": 4, "goal_selection_strategy": "future"},
    },
    "ppo-images": {
        "n_steps": 32,
        "batch_size": 16,
        "n_epochs": 4,
        "learning_rate": 3e-4,
        "gamma": 0.99,
        "ent_coef": 0.0,
        "policy_kwargs": {"net_arch": [64, 64], "log_std_init": -0.5},
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

    def default_window(self) -> int:
        """A rolling window of about a fifth of the episodes, 3..50."""
        return max(3, min(50, len(self.successes) // 5))

    def write_csv(self, path: str | Path) -> Path:
        """``episode, env_steps, return, success`` per episode, atomically."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["episode", "env_steps", "return", "success"])
            for i, (steps, ret, ok) in enumerate(zip(self.env_steps, self.returns, self.successes, strict=True)):
                writer.writerow([i, steps, f"{ret:.6g}", int(ok)])
        return path

    @classmethod
    def read_csv(cls, path: str | Path) -> LearningCurve:
        curve = cls()
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                curve.add(int(row["env_steps"]), float(row["return"]), bool(int(row["success"])))
        return curve


def _curve_callback(
    curve: LearningCurve,
    total_timesteps: int,
    description: str,
    progress: bool,
    run_dir: Path | None,
    save_every: int | None,
    run_wall_s: Callable[[], float],
) -> Any:
    """SB3 callback: records finished episodes into ``curve``, drives a tqdm bar of env steps and,
    with a run directory, saves the model (and replay buffer), the curve and ``run_wall_s()`` (the
    run's training time so far) every ``save_every`` steps."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    class _Callback(BaseCallback):
        def _on_training_start(self) -> None:
            self.bar = tqdm(
                total=total_timesteps, initial=self.model.num_timesteps, desc=description, unit="step",
                disable=not progress,
            )  # fmt: skip
            self.last_save = self.model.num_timesteps

        def _on_step(self) -> bool:
            self.bar.update(self.training_env.num_envs)
            for info in self.locals["infos"]:
                episode = info.get("episode")  # set by Monitor when an episode ends
                if episode is not None:
                    curve.add(self.num_timesteps, episode["r"], info.get("is_success", False))
            if curve.successes:
                self.bar.set_postfix(episodes=len(curve.successes), success=f"{np.mean(curve.successes[-50:]):.2f}")
            if run_dir is not None and save_every and self.num_timesteps - self.last_save >= save_every:
                self.last_save = self.num_timesteps
                save_checkpoint(self.model, curve, run_dir, run_wall_s())
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return _Callback()


def save_checkpoint(model: Any, curve: LearningCurve, run_dir: str | Path, wall_s: float = 0.0) -> None:
    """The resumable state of a run: ``model_last.zip``, the replay buffer of an off-policy algorithm,
    ``curve_last.csv`` and ``progress_last.json`` (env steps and ``wall_s``, the run's training time
    in seconds over all its sessions), each written atomically."""
    run_dir = Path(run_dir)
    with atomic_path(run_dir / RUN_FILES["last_model"]) as tmp:
        model.save(tmp)
    if getattr(model, "replay_buffer", None) is not None:
        with atomic_path(run_dir / RUN_FILES["last_buffer"]) as tmp:
            model.save_replay_buffer(tmp)
    curve.write_csv(run_dir / RUN_FILES["last_curve"])
    progress = {"timesteps": int(model.num_timesteps), "wall_s": float(wall_s)}
    write_text_atomic(run_dir / RUN_FILES["last_progress"], json.dumps(progress) + "\n")


def saved_progress(run_dir: str | Path) -> tuple[int, float] | None:
    """``(env steps, training time in s)`` of a run's last periodic save (:func:`save_checkpoint`);
    None before its first save or when the file cannot be read."""
    try:
        progress = json.loads((Path(run_dir) / RUN_FILES["last_progress"]).read_text())
        return int(progress["timesteps"]), float(progress["wall_s"])
    except (OSError, KeyError, TypeError, ValueError):
        return None


def _wall_s_before(run_dir: Path, saved_config: dict[str, Any]) -> float:
    """Training time (s) of a run's earlier sessions: from its last saved progress, else from the
    config of a finished run saved before progress files existed (0 when neither says)."""
    progress = saved_progress(run_dir)
    if progress is not None:
        return progress[1]
    try:
        return float(saved_config["wall_s"])
    except (KeyError, TypeError, ValueError):
        return 0.0


@dataclass
class RLTrainResult:
    """A trained baseline: the SB3 model, the :class:`LearningCurve` of its training episodes, the
    wall time in seconds of this call (``wall_s``) and of the whole run over its resumed sessions
    (``run_wall_s``), and its run directory, if any (not :class:`don_gym.learning.train.TrainResult`, a DON
    training run)."""

    model: Any
    curve: LearningCurve
    wall_s: float
    run_wall_s: float
    run_dir: Path | None = None


def _policy_inputs_extractor() -> type:
    """SB3 features extractor for goal dicts that leaves ``achieved_goal`` (the true keypoints) out and gives
    ``desired_goal`` (world metres) in the units of the ``observation`` vector's positions
    (:data:`~don_gym.wrappers.rl.POSITION_UNIT_M` from :data:`~don_gym.wrappers.rl.WORKSPACE_CENTRE_M`)."""
    import torch
    from stable_baselines3.common.torch_layers import CombinedExtractor

    class PolicyInputs(CombinedExtractor):
        def __init__(self, observation_space: spaces.Dict, **kwargs: Any) -> None:
            kept = spaces.Dict({k: v for k, v in observation_space.spaces.items() if k != "achieved_goal"})
            super().__init__(kept, **kwargs)
            # Raw metres put a 6 cm lift goal at 0.06 beside observation entries of order 1: the goal
            # then barely moves the first layer, and the critic learns it slowly.
            centre = torch.as_tensor(np.tile(WORKSPACE_CENTRE_M, 2), dtype=torch.float32)
            self.register_buffer("goal_centre", centre, persistent=False)

        def forward(self, observations: dict[str, Any]) -> Any:
            inputs = dict(observations)
            if "desired_goal" in inputs:
                inputs["desired_goal"] = (inputs["desired_goal"] - self.goal_centre) / POSITION_UNIT_M
            return super().forward(inputs)

    return PolicyInputs


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    return str(value)


def _algorithm_setup(algorithm: str, env_kwargs: dict[str, Any], algo_kwargs: dict[str, Any] | None):
    """(SB3 class name, policy name, keyword arguments) of an algorithm and env."""
    her = algorithm == "sac" and env_kwargs.get("goal") is not None
    key = "sac-her" if her else algorithm
    kwargs = {**DEFAULT_ALGO_KWARGS[key], **dict(algo_kwargs or {})}
    kwargs["policy_kwargs"] = dict(kwargs.get("policy_kwargs") or {})
    if her:
        kwargs["replay_buffer_kwargs"] = dict(kwargs.get("replay_buffer_kwargs") or {})
        return "SAC", "MultiInputPolicy", kwargs
    if algorithm == "ppo-images":
        return "PPO", "MultiInputPolicy", kwargs
    return ("PPO" if algorithm == "ppo" else "SAC"), "MlpPolicy", kwargs


def _use_her(kwargs: dict[str, Any], demo_fraction: float) -> None:
    """Set SAC's ``kwargs`` for a goal env: HER's replay buffer (with ``demo_fraction`` > 0, the one that draws that
    share of each batch from the demonstrations) and the extractor that hides ``achieved_goal`` from the policy."""
    from stable_baselines3 import HerReplayBuffer

    kwargs["replay_buffer_class"] = HerReplayBuffer
    if demo_fraction:
        from don_gym.agents.rl_buffer import DemonstrationHerReplayBuffer

        kwargs["replay_buffer_class"] = DemonstrationHerReplayBuffer
        kwargs["replay_buffer_kwargs"] = {**kwargs["replay_buffer_kwargs"], "demo_fraction": float(demo_fraction)}
    kwargs["policy_kwargs"]["features_extractor_class"] = _policy_inputs_extractor()


def _resumed_state(run_path: Path, config: dict[str, Any]) -> tuple[LearningCurve, float]:
    """The learning curve and training time (s) of the run ``train(resume=True)`` continues, checked to be a
    run of the same algorithm, envs and env settings."""
    if not (run_path / RUN_FILES["last_model"]).is_file():
        raise DonGymError(f"resume: {str(run_path)!r} holds no {RUN_FILES['last_model']} to resume from")
    saved = json.loads((run_path / RUN_FILES["config"]).read_text())
    # A run saved before demonstrations existed had none.
    saved.setdefault("demonstrations", {"episodes": 0, "bc_weight": 0.0})
    saved["demonstrations"].setdefault("demo_fraction", 0.0)
    differs = [k for k in ("algorithm", "n_envs", "env_kwargs", "demonstrations") if saved.get(k) != config[k]]
    if differs:
        raise DonGymError(f"resume: {str(run_path)!r} was a run with other {differs}; start a new run_dir")
    return LearningCurve.read_csv(run_path / RUN_FILES["last_curve"]), _wall_s_before(run_path, saved)


def _load_replay_buffer(model: Any, buffer: Path) -> None:
    """The saved replay buffer into an off-policy ``model`` (PPO has none)."""
    if getattr(model, "replay_buffer", None) is not None and buffer.is_file():
        with warnings.catch_warnings():
            # HER cuts the episode that was running at the save: the envs restart, as it assumes.
            warnings.filterwarnings("ignore", message="The last trajectory in the replay buffer")
            model.load_replay_buffer(buffer)


def _run_config(
    algorithm: str,
    total_timesteps: int,
    n_envs: int,
    vectorize: str | None,
    env_kwargs: dict[str, Any],
    algo_kwargs: dict[str, Any],
    seed: int,
    demonstrations: tuple[int, float, float],
) -> dict[str, Any]:
    """A run's ``config.json``: its arguments, seeds and versions (stable-baselines3's added by the caller)."""
    return {
        "algorithm": algorithm,
        "total_timesteps": int(total_timesteps),
        "n_envs": int(n_envs),
        "vectorize": vectorize,
        "env_kwargs": _jsonable(env_kwargs),
        "algo_kwargs": _jsonable({k: v for k, v in algo_kwargs.items() if k != "replay_buffer_class"}),
        "seeds": {"algorithm": int(seed), "envs_first_reset": [int(seed) + i for i in range(int(n_envs))]},
        "demonstrations": {
            "episodes": int(demonstrations[0]),
            "bc_weight": float(demonstrations[1]),
            "demo_fraction": float(demonstrations[2]),
        },
        "versions": {"python": platform.python_version()},
    }


def train(
    algorithm: str,
    total_timesteps: int,
    seed: int = 0,
    n_envs: int = 1,
    env_kwargs: dict[str, Any] | None = None,
    algo_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
    run_dir: str | Path | None = None,
    save_every: int | None = None,
    resume: bool = False,
    vectorize: str | None = None,
    device: str = "cpu",
    don_device: str | None = None,
    demonstrations: int = 0,
    bc_weight: float = 0.0,
    demo_fraction: float = 0.0,
) -> RLTrainResult:
    """Train a baseline of :data:`ALGORITHMS` for ``total_timesteps`` env steps.

    ``env_kwargs`` go to :func:`make_ppo_env` / :func:`make_sac_env` / :func:`make_image_env` (SAC
    with ``goal`` trains with HER, its policy not seeing ``achieved_goal``); ``algo_kwargs`` override
    :data:`DEFAULT_ALGO_KWARGS`. Env ``i`` is reset first with seed ``seed + i`` and the algorithm
    seeded with ``seed``: a run with the same arguments and one torch thread repeats exactly.
    ``vectorize``, ``don_device``: see :func:`make_vec_env`. ``device``: where the policy trains.

    ``run_dir``: writes ``config.json`` (arguments, seeds, versions), ``curve.csv`` and ``curve.png``
    (the training episodes), ``model.zip`` at the end, and every ``save_every`` env steps (default
    about a tenth of the run) ``model_last.zip``, the replay buffer and ``curve_last.csv``.
    ``resume=True`` continues from those to ``total_timesteps``; a resumed run goes on from the
    saved model and buffer but does not repeat the uninterrupted run bit for bit (the envs restart).

    ``demonstrations``, ``bc_weight`` (SAC on a goal env): expert episodes in the replay buffer and a Q-filtered
    behaviour-cloning step on them (:func:`~don_gym.agents.rl_demos.use_demonstrations`); ``demo_fraction`` > 0:
    that share of every batch drawn from the demonstrations
    (:class:`~don_gym.agents.rl_buffer.DemonstrationHerReplayBuffer`), instead of a uniform draw over the buffer.
    """
    if algorithm not in ALGORITHMS:
        raise DonGymError(f"algorithm={algorithm!r} is unknown; expected one of {list(ALGORITHMS)}")
    check_n_envs(n_envs)
    if int(total_timesteps) < 1:
        raise DonGymError(f"total_timesteps={total_timesteps!r}: expected a positive number of env steps")
    if resume and run_dir is None:
        raise DonGymError("resume=True needs the run_dir of the run to resume")
    env_kwargs = dict(env_kwargs or {})
    check_demonstration_settings(demonstrations, bc_weight, algorithm, env_kwargs.get("goal"), demo_fraction)
    sb3 = require_sb3()
    class_name, policy, kwargs = _algorithm_setup(algorithm, env_kwargs, algo_kwargs)
    algo_class = getattr(sb3, class_name)
    if policy == "MultiInputPolicy" and class_name == "SAC":
        _use_her(kwargs, demo_fraction)
    run_path = Path(run_dir) if run_dir is not None else None
    config = _run_config(
        algorithm, total_timesteps, n_envs, vectorize, env_kwargs, kwargs, seed,
        (demonstrations, bc_weight, demo_fraction),
    )  # fmt: skip
    config["versions"]["stable_baselines3"] = sb3.__version__
    curve, wall_s_before = LearningCurve(), 0.0
    if resume:
        curve, wall_s_before = _resumed_state(run_path, config)
        last = run_path / RUN_FILES["last_model"]
    elif run_path is not None:
        run_path.mkdir(parents=True, exist_ok=True)
    save_every = save_every or max(1, int(total_timesteps) // 10)
    vec_env = make_vec_env(algorithm, int(n_envs), seed, env_kwargs, vectorize, don_device)
    start = time.perf_counter()

    def run_wall_s() -> float:
        return wall_s_before + time.perf_counter() - start

    try:
        if resume:
            custom = {"policy_kwargs": kwargs["policy_kwargs"]}
            model = algo_class.load(last, env=vec_env, device=device, custom_objects=custom)
        else:
            model = algo_class(policy, vec_env, seed=seed, device=device, verbose=0, **kwargs)
        remaining = int(total_timesteps) - int(model.num_timesteps)
        if remaining > 0 and run_path is not None:
            # A new run, or one going on to a new total (a finished run is only loaded and keeps its config).
            write_text_atomic(run_path / RUN_FILES["config"], json.dumps(_jsonable(config), indent=1) + "\n")
        if remaining > 0 and resume:
            _load_replay_buffer(model, run_path / RUN_FILES["last_buffer"])
        if remaining > 0:
            description = f"{algorithm.upper()} train"
            callback = _curve_callback(
                curve, int(total_timesteps), description, progress, run_path, save_every, run_wall_s
            )  # fmt: skip
            if demonstrations:
                demos_path = run_path / RUN_FILES["demonstrations"] if run_path is not None else None
                callback = use_demonstrations(
                    model, callback, env_kwargs, int(demonstrations), float(bc_weight), seed, demos_path, resume
                )  # fmt: skip
            model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=not resume)
    finally:
        vec_env.close()
    wall_s = time.perf_counter() - start
    if remaining <= 0:
        # A finished run is only loaded: its files, its training time and its config stay as they were.
        return RLTrainResult(model=model, curve=curve, wall_s=wall_s, run_dir=run_path, run_wall_s=wall_s_before)
    total_wall_s = wall_s_before + wall_s
    if run_path is not None:
        # The last state is the final one: --resume on a finished run trains no further.
        save_checkpoint(model, curve, run_path, total_wall_s)
        finished = {"wall_s": total_wall_s, "wall_s_this_session": wall_s, "finished": True}
        write_run_outputs(run_path, model, curve, algorithm, config | finished)
    return RLTrainResult(model=model, curve=curve, wall_s=wall_s, run_dir=run_path, run_wall_s=total_wall_s)


def write_run_outputs(
    run_dir: Path, model: Any, curve: LearningCurve, title: str, config: dict[str, Any] | None = None
) -> None:
    """The final files of a run: ``model.zip``, ``curve.csv``, ``curve.png`` (and ``config.json``)."""
    from don_gym.plotting import plot_learning_curve

    with atomic_path(run_dir / RUN_FILES["model"]) as tmp:
        model.save(tmp)
    curve.write_csv(run_dir / RUN_FILES["curve_csv"])
    window = curve.default_window()
    plot_learning_curve([("training episodes", curve.rolling(window))], run_dir / RUN_FILES["curve_png"], window, title)
    if config is not None:
        write_text_atomic(run_dir / RUN_FILES["config"], json.dumps(_jsonable(config), indent=1) + "\n")


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
        return {name: sum(outcome == name for outcome in self.outcomes) for name in OUTCOMES}


def evaluate(
    env: gym.Env,
    policy: Callable[[Any], np.ndarray],
    n_episodes: int,
    seed: int,
    description: str = "evaluate",
    progress: bool = True,
) -> EvaluationResult:
    """Run ``policy(observation) -> action`` for ``n_episodes`` episodes, episode ``i`` reset with
    ``seed + i`` (two policies evaluated with the same seed face the same part poses and calibration
    errors). Success is ``info["is_success"]`` at the episode's last step."""
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
