"""Expert demonstrations for off-policy RL: the replay buffer seeded with the expert's episodes, and a
behaviour-cloning term on the actor that only imitates where the critic rates the expert's action higher.

SAC+HER on the lift task from the task's own start rarely sees a grasp by exploration alone: the hand must go
down some 25 cm, turn across the part and close within millimetres of the grasp point. Two devices of the field
bring the expert's experience in (Vecerik et al. 2017, "Leveraging demonstrations for deep RL on robotics
problems with sparse rewards"; Nair et al. 2018, "Overcoming exploration in RL with demonstrations"):

- :func:`add_expert_episodes`: episodes of :class:`~don_gym.agents.ee_expert.EndEffectorExpert` (privileged state)
  stepped in the training env's own observation pipeline and written into the model's replay buffer before
  learning, so HER relabels them as it does the policy's own;
- :func:`behaviour_cloning_callback`: after each gradient step, one more actor step on a batch of the
  demonstrations, the squared error between the actor's deterministic action and the expert's, kept only where
  the critic prefers the expert's action to the actor's (the "Q-filter"), so the term fades where the policy has
  learned better.

Both run in :func:`don_gym.agents.rl.train` (``demonstrations=``, ``bc_weight=``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.agents.ee_expert import EndEffectorExpert
from don_gym.agents.rl_envs import make_vec_env
from don_gym.errors import DonGymError
from don_gym.io import atomic_path

__all__ = [
    "DEMO_SEED_OFFSET",
    "ExpertEpisodes",
    "add_expert_episodes",
    "behaviour_cloning_callback",
    "check_demonstration_settings",
    "use_demonstrations",
]

#: The demonstrations' envs are first reset with ``seed + DEMO_SEED_OFFSET + i``: apart from the training envs'
#: ``seed + i`` and the benchmarks' held-out episodes (100,000 and up).
DEMO_SEED_OFFSET = 1_000_000
#: Demonstration transitions in each behaviour-cloning batch.
BC_BATCH_SIZE = 128


@dataclass
class ExpertEpisodes:
    """The expert's transitions as the policy sees them: ``observations`` (key -> (N, ...) arrays, the training
    env's observation dict), ``actions`` (N, A) float32 in [-1, 1], and per episode its success."""

    observations: dict[str, np.ndarray]
    actions: np.ndarray
    successes: list[bool]

    def save(self, path: str | Path) -> None:
        """Write to ``path`` (.npz, atomically)."""
        arrays = {f"obs/{key}": value for key, value in self.observations.items()}
        with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
            np.savez(f, actions=self.actions, successes=np.asarray(self.successes, bool), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> ExpertEpisodes:
        with np.load(path) as data:
            observations = {key[4:]: data[key] for key in data.files if key.startswith("obs/")}
            return cls(observations, data["actions"], [bool(s) for s in data["successes"]])


def check_demonstration_settings(
    demonstrations: Any, bc_weight: Any, algorithm: str, goal: str | None, demo_fraction: Any = 0.0
) -> None:
    """Refuse ``demonstrations`` (episodes, >= 0), ``bc_weight`` (>= 0) or ``demo_fraction`` (in [0, 1]) that are
    not numbers of the right kind, and any of them for a run other than SAC on a goal env (the expert acts in
    ``control="ee"``, lift or place)."""
    if isinstance(demonstrations, bool) or not isinstance(demonstrations, (int, np.integer)) or demonstrations < 0:
        raise DonGymError(f"demonstrations={demonstrations!r}: expected a number of expert episodes >= 0")
    if (
        isinstance(bc_weight, bool)
        or not isinstance(bc_weight, (int, float))
        or not np.isfinite(bc_weight)
        or (bc_weight < 0)
    ):
        raise DonGymError(f"bc_weight={bc_weight!r}: expected a finite weight >= 0")
    if (demonstrations or bc_weight) and (algorithm != "sac" or goal is None):
        raise DonGymError(
            f"demonstrations serve SAC on the lift or place goal (the expert's tasks), not algorithm={algorithm!r} "
            f"with goal={goal!r}"
        )
    if bc_weight and not demonstrations:
        raise DonGymError(f"bc_weight={bc_weight!r} needs demonstrations > 0 to imitate")
    if (
        isinstance(demo_fraction, bool)
        or not isinstance(demo_fraction, (int, float))
        or not 0.0 <= float(demo_fraction) <= 1.0
    ):
        raise DonGymError(f"demo_fraction={demo_fraction!r}: expected a share of each batch in [0, 1]")
    if demo_fraction and not demonstrations:
        raise DonGymError(f"demo_fraction={demo_fraction!r} needs demonstrations > 0 to sample from")


def add_expert_episodes(model: Any, env_kwargs: dict[str, Any], episodes: int, seed: int) -> ExpertEpisodes:
    """Step the expert for ``episodes`` episodes in ``model.n_envs`` envs made like the training envs (from the
    task's start: no ``hand_starts``), write each transition into ``model.replay_buffer`` as SB3 writes its own
    (the terminal observation as the last next observation), and return the transitions.

    The envs run in this process, each with its own expert reading its true state; episode seeds start at
    ``seed + DEMO_SEED_OFFSET``. Episodes still running when ``episodes`` have ended are cut (HER sees them
    as ended), so the buffer holds whole episodes only."""
    goal = env_kwargs.get("goal")
    n_envs = int(model.n_envs)
    demo_kwargs = {**env_kwargs, "hand_starts": None}
    vec_env = make_vec_env("sac", n_envs, int(seed) + DEMO_SEED_OFFSET, demo_kwargs, vectorize="dummy")
    experts = [EndEffectorExpert(env, goal) for env in vec_env.envs]
    observations: dict[str, list[np.ndarray]] = {}
    actions: list[np.ndarray] = []
    successes: list[bool] = []
    try:
        obs = vec_env.reset()
        while len(successes) < int(episodes):
            action = np.stack(
                [experts[i].act({key: value[i] for key, value in obs.items()}) for i in range(n_envs)]
            ).astype(np.float32)
            new_obs, reward, done, infos = vec_env.step(action)
            next_obs = {key: np.array(value, copy=True) for key, value in new_obs.items()}
            for i in np.flatnonzero(done):
                for key in next_obs:
                    next_obs[key][i] = infos[i]["terminal_observation"][key]
                successes.append(bool(infos[i].get("is_success", False)))
            model.replay_buffer.add(obs, next_obs, action, reward, done, infos)
            for key, value in obs.items():
                observations.setdefault(key, []).append(np.array(value, copy=True))
            actions.append(action)
            obs = new_obs
        truncate = getattr(model.replay_buffer, "truncate_last_trajectory", None)
        if truncate is not None and n_envs > 1:
            with warnings.catch_warnings():
                # The other envs' episodes still running are cut here on purpose.
                warnings.filterwarnings("ignore", message="The last trajectory in the replay buffer")
                truncate()
        if hasattr(model.replay_buffer, "demo_rows"):
            # A DemonstrationHerReplayBuffer: its batches draw a share from these rows.
            model.replay_buffer.demo_rows = int(model.replay_buffer.pos)
    finally:
        vec_env.close()
    return ExpertEpisodes(
        {key: np.concatenate(value) for key, value in observations.items()}, np.concatenate(actions), successes
    )


def behaviour_cloning_callback(demos: ExpertEpisodes, weight: float, seed: int) -> Any:
    """SB3 callback: after each env step once the model trains, one actor step on ``weight`` times the mean
    squared error between the actor's deterministic actions and the expert's on a batch of ``demos``, over the
    transitions where the critic's Q of the expert's action (min of the two critics) exceeds the actor's."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    rng = np.random.default_rng(int(seed))
    n = len(demos.actions)

    class _BehaviourCloning(BaseCallback):
        def _on_step(self) -> bool:
            model = self.model
            if model.num_timesteps <= model.learning_starts:
                return True
            index = rng.integers(0, n, size=min(BC_BATCH_SIZE, n))
            obs, _ = model.policy.obs_to_tensor({key: value[index] for key, value in demos.observations.items()})
            expert = torch.as_tensor(demos.actions[index], device=model.device)
            model.policy.set_training_mode(True)
            predicted = model.actor(obs, deterministic=True)
            with torch.no_grad():
                q_expert = torch.min(torch.cat(model.critic(obs, expert), dim=1), dim=1).values
                q_actor = torch.min(torch.cat(model.critic(obs, predicted), dim=1), dim=1).values
                keep = (q_expert > q_actor).float()
            if float(keep.sum()) == 0.0:
                return True
            error = ((predicted - expert) ** 2).sum(dim=1)
            loss = weight * (error * keep).sum() / keep.sum()
            model.actor.optimizer.zero_grad()
            loss.backward()
            model.actor.optimizer.step()
            self.logger.record("train/bc_loss", loss.item())
            self.logger.record("train/bc_kept", float(keep.mean()))
            return True

    return _BehaviourCloning()


def use_demonstrations(
    model: Any,
    callback: Any,
    env_kwargs: dict[str, Any],
    episodes: int,
    bc_weight: float,
    seed: int,
    path: Path | None,
    resume: bool,
) -> Any:
    """Put ``episodes`` expert episodes into ``model``'s replay buffer (:func:`add_expert_episodes`, saved to
    ``path`` when given), or with ``resume`` read them back from ``path`` (the resumed buffer already holds them);
    return ``callback``, followed by the behaviour-cloning step when ``bc_weight`` > 0."""
    if resume and path is not None and path.is_file():
        demos = ExpertEpisodes.load(path)
    elif resume:
        raise DonGymError(f"resume: {str(path)!r} is missing; the run's demonstrations cannot be restored")
    else:
        demos = add_expert_episodes(model, env_kwargs, episodes, seed)
        if path is not None:
            demos.save(path)
    if not bc_weight:
        return callback
    from stable_baselines3.common.callbacks import CallbackList

    return CallbackList([callback, behaviour_cloning_callback(demos, bc_weight, seed)])
