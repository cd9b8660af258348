"""The RL baselines' envs (:mod:`don_gym.agents.rl` trains and evaluates on them): the PPO, SAC and image-PPO
envs, and the vector envs SB3 steps, among them the batched ones that run the DON once per step on all
sub-envs' images (:class:`~don_gym.wrappers.VectorKeypointObservation`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.wrappers.goals import GOALS, KeypointGoal, make_goal_env, make_keypoint_env
from don_gym.wrappers.images import DescriptorImage
from don_gym.wrappers.memory import KeypointMemory
from don_gym.wrappers.rl import KeypointFeatures, KeypointGraspAction

__all__ = [
    "ENV_MAKERS",
    "PROXY_ATTRIBUTES",
    "VECTORIZE",
    "check_n_envs",
    "make_batched_sac_vec_env",
    "make_batched_vec_env",
    "make_image_env",
    "make_ppo_env",
    "make_sac_env",
    "make_vec_env",
    "monitored",
]

#: How :func:`make_vec_env` steps several envs.
VECTORIZE = ("dummy", "subproc", "batched", "batched-async")


# ------------------------------------------------------------------------------- the envs
def make_ppo_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoint_model: str | Path = "oracle",
    image_size: tuple[int, int] = (160, 120),
    sensor: str = "d435",
    reward_type: str = "dense",
    action_frame: str = "axis",
    keypoints: str = "don",
    noise: Any = None,
    keypoint_kwargs: dict[str, Any] | None = None,
    window_px: int | None = None,
) -> gym.Env:
    """The PPO baseline's env: ``control="grasp"`` with keypoints, flat observations
    (:class:`~don_gym.wrappers.KeypointFeatures`) and normalised actions in a frame set by the keypoints
    (:class:`~don_gym.wrappers.KeypointGraspAction`; ``"axis"``: residuals about the keypoints' axis,
    ``"keypoints"``: about their centroid with a world yaw, ``"world"``: the whole action box).

    ``keypoint_model``: "oracle" (keypoints from descriptors rendered at the true pose: a check of
    the pipeline, not a perception result), a shipped DON name such as "toolcap/supervised-edge",
    or a checkpoint path; ``keypoints``/``noise``: see the module docstring. ``reward_type="dense"``
    gives failed grasps a graded penalty (the success rate is measured either way by ``info["is_success"]``).
    ``window_px``: the DON sees a window of that many pixels around the part (:func:`make_keypoint_env`).
    """
    env = make_keypoint_env(
        object, keypoints, keypoint_model, noise, image_size, keypoint_kwargs=keypoint_kwargs, window_px=window_px,
        control="grasp", sensor=sensor, reward_type=reward_type,
    )  # fmt: skip
    env = KeypointGraspAction(env, frame=action_frame)
    return KeypointFeatures(env, relative_to="centroid", robot_state=False)


def _sac_head(env: gym.Env, goal: str | None, memory: bool = False, encoding: str = "plain") -> gym.Env:
    if memory:
        env = KeypointMemory(env, max_age_steps=env.unwrapped.max_steps)
    if goal is None:
        return KeypointFeatures(env, relative_to="tcp", robot_state=True, encoding=encoding)
    return KeypointGoal(env, goal=goal, encoding=encoding)


def make_sac_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoint_model: str | Path = "oracle",
    image_size: tuple[int, int] = (160, 120),
    sensor: str = "d435",
    reward_type: str = "dense",
    max_steps: int = 100,
    keypoints: str = "don",
    noise: Any = None,
    goal: str | None = None,
    keypoint_kwargs: dict[str, Any] | None = None,
    hand_starts: dict[str, float] | None = None,
    window_px: int | None = None,
    memory: bool = False,
    look_first: bool = False,
    encoding: str = "plain",
) -> gym.Env:
    """The SAC baseline's env: ``control="ee"``, keypoints of every wrist-camera frame (relative to the
    TCP) plus the robot state as one flat vector; the keypoints move with the camera and vanish when
    the part leaves the view, their confidences let the policy tell. ``goal`` ("place" or the "lift"
    sub-task): the goal-conditioned dict of :class:`~don_gym.wrappers.KeypointGoal` for HER, with its
    sparse goal reward instead of ``reward_type``'s: the env of
    :func:`~don_gym.wrappers.goals.make_goal_env`, which the registered ``DONToolcapLift-v0`` makes.
    ``hand_starts``: shares of episodes that start with the hand at or on the part
    (:class:`~don_gym.wrappers.HandStarts`; for training). ``window_px``: the DON sees a window of that many pixels
    around the part (:func:`~don_gym.wrappers.goals.make_keypoint_env`). ``memory``: the keypoints' last seen places
    and ages too (:class:`~don_gym.wrappers.KeypointMemory`). ``look_first``: each hand start comes after a look
    from the task's start, so that the keypoints' memory holds the part as on the task's own way down
    (:class:`~don_gym.wrappers.HandStarts`). ``encoding``: the flat observation's
    (:class:`~don_gym.wrappers.KeypointFeatures`): "plain", or "hand" (with ``memory``), the imitation benchmark's
    hand-frame features."""
    if goal is not None and goal not in GOALS:
        raise DonGymError(f"goal={goal!r} is unknown; expected None or one of {list(GOALS)}")
    if goal is not None:
        return make_goal_env(
            object, goal, keypoints, keypoint_model, noise, image_size, max_steps, hand_starts, keypoint_kwargs,
            sensor=sensor, reward_type=reward_type, window_px=window_px, memory=memory, look_first=look_first,
            encoding=encoding,
        )  # fmt: skip
    env = make_keypoint_env(
        object, keypoints, keypoint_model, noise, image_size, hand_starts, keypoint_kwargs, window_px, memory,
        look_first, control="ee", sensor=sensor, reward_type=reward_type, max_steps=max_steps,
    )  # fmt: skip
    return _sac_head(env, goal, encoding=encoding)


def make_image_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoint_model: str | Path = "oracle",
    image_size: tuple[int, int] = (160, 120),
    cnn_size: tuple[int, int] = (80, 60),
    sensor: str = "d435",
    reward_type: str = "dense",
) -> gym.Env:
    """The descriptor-image baseline's env: ``control="grasp"``; the observation is the descriptor image
    of ``keypoint_model`` (any model :class:`~don_gym.wrappers.DescriptorObservation` takes) as uint8,
    resized to ``cnn_size`` (:class:`~don_gym.wrappers.DescriptorImage`), for SB3's CNN; the action
    spans the env's action box in [-1, 1]^4 (x, y, z, yaw): the policy must find the part in the image."""
    from don_gym.wrappers import DescriptorObservation

    env = make_keypoint_env(
        object, None, image_size=image_size, control="grasp", sensor=sensor, reward_type=reward_type
    )
    env = DescriptorImage(DescriptorObservation(env, model=keypoint_model), size=cnn_size, keep=())
    ones = np.ones(env.action_space.shape, dtype=np.float32)
    return gym.wrappers.RescaleAction(env, -ones, ones)


ENV_MAKERS: dict[str, Callable[..., gym.Env]] = {"ppo": make_ppo_env, "sac": make_sac_env, "ppo-images": make_image_env}


# ---------------------------------------------------------------- batched vector envs for SB3
class _SubEnvProxy(gym.Env):
    """One sub-env of a vector env as seen by per-env wrappers: it returns what the vector env
    produced for it (set by :class:`BatchedVecEnv`) and carries the attributes wrappers look up."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, attributes: dict[str, Any]):
        self.observation_space = observation_space
        self.action_space = action_space
        for name, value in attributes.items():
            setattr(self, name, value)
        self.pending_reset: tuple[Any, dict] | None = None
        self.pending_step: tuple[Any, float, bool, bool, dict] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        out, self.pending_reset = self.pending_reset, None
        if out is None:
            raise RuntimeError("sub-env reset outside BatchedVecEnv")
        return out

    def step(self, action: Any):
        out, self.pending_step = self.pending_step, None
        if out is None:
            raise RuntimeError("sub-env step outside BatchedVecEnv")
        return out


#: Sub-env attributes the per-env wrappers on top of a batched vector env may look up.
PROXY_ATTRIBUTES = ("model", "control", "intrinsics", "max_steps", "render_mode", "image_size")


def make_batched_vec_env(
    vector_env: gym.vector.VectorEnv, head: Callable[[gym.Env], gym.Env], monitor: bool = True
) -> Any:
    """An SB3 VecEnv over a ``gymnasium.vector`` env made with ``autoreset_mode=SAME_STEP`` (e.g. a
    :class:`~don_gym.wrappers.VectorKeypointObservation`): each sub-env gets ``head`` (observation and
    reward wrappers only, such as :class:`~don_gym.wrappers.KeypointFeatures` or
    :class:`~don_gym.wrappers.KeypointGoal`; actions pass through unchanged), wrapped in SB3's Monitor.
    ``env_method`` reaches the heads (HER's ``compute_reward``)."""
    from gymnasium.vector import AutoresetMode
    from gymnasium.vector.utils import iterate
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from don_gym.wrappers.vector import unbatch_info

    if vector_env.metadata.get("autoreset_mode") != AutoresetMode.SAME_STEP:
        raise DonGymError("make_batched_vec_env needs a vector env made with autoreset_mode=AutoresetMode.SAME_STEP")
    attributes = {}
    for name in PROXY_ATTRIBUTES:
        try:
            attributes[name] = vector_env.unwrapped.get_attr(name)[0]
        except AttributeError:
            pass
    proxies = [
        _SubEnvProxy(vector_env.single_observation_space, vector_env.single_action_space, attributes)
        for _ in range(vector_env.num_envs)
    ]

    def wrapped(proxy: _SubEnvProxy) -> Callable[[], gym.Env]:
        env = head(proxy)
        if monitor:
            env = Monitor(env, info_keywords=("is_success",))
        return lambda: env

    class BatchedVecEnv(DummyVecEnv):
        def reset(self):
            seeds = None if all(s is None for s in self._seeds) else [s for s in self._seeds]
            options = self._options[0] if self._options and self._options[0] else None
            observations, infos = vector_env.reset(seed=seeds, options=options)
            for i, obs in enumerate(iterate(vector_env.observation_space, observations)):
                proxies[i].pending_reset = (obs, unbatch_info(infos, i))
            return super().reset()

        def step_async(self, actions: np.ndarray) -> None:
            observations, rewards, terminations, truncations, infos = vector_env.step(np.asarray(actions))
            final = np.asarray(infos.get("_final_obs", np.zeros(self.num_envs, bool)))
            for i, obs in enumerate(iterate(vector_env.observation_space, observations)):
                info = unbatch_info(infos, i)
                for key in ("final_obs", "final_info"):
                    info.pop(key, None)
                if final[i]:
                    final_info = unbatch_info(infos["final_info"], i)
                    proxies[i].pending_step = (
                        infos["final_obs"][i], float(rewards[i]), bool(terminations[i]), bool(truncations[i]),
                        final_info,
                    )  # fmt: skip
                    proxies[i].pending_reset = (obs, info)
                else:
                    proxies[i].pending_step = (
                        obs, float(rewards[i]), bool(terminations[i]), bool(truncations[i]), info
                    )  # fmt: skip
            super().step_async(actions)

        def close(self) -> None:
            super().close()
            vector_env.close()

    return BatchedVecEnv([wrapped(p) for p in proxies])


def make_batched_sac_vec_env(
    n_envs: int,
    env_kwargs: dict[str, Any] | None = None,
    asynchronous: bool = False,
    device: str | None = None,
    monitor: bool = True,
) -> Any:
    """The SAC env (:func:`make_sac_env` arguments in ``env_kwargs``, ``keypoints="don"``) as an SB3
    VecEnv of ``n_envs`` sub-envs whose images go through the DON together, on ``device``."""
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

    from don_gym.wrappers.vector import VectorKeypointObservation

    check_n_envs(n_envs)
    kwargs = dict(env_kwargs or {})
    if kwargs.get("keypoints", "don") != "don":
        raise DonGymError(
            f"batched envs run a DON; keypoints={kwargs['keypoints']!r} needs none (use vectorize='dummy')"
        )
    if kwargs.get("window_px") is not None:
        raise DonGymError(
            f"window_px={kwargs['window_px']!r}: batched envs see whole frames (each window follows its own part); "
            "use vectorize='dummy' or 'subproc' for windowed observations"
        )
    if kwargs.get("look_first") and kwargs.get("hand_starts"):
        raise DonGymError(
            "look_first=True: batched envs find the keypoints outside their sub-envs, so a hand start cannot look "
            "first; use vectorize='dummy' or 'subproc'"
        )
    goal = kwargs.get("goal")
    if goal is not None and goal not in GOALS:
        raise DonGymError(f"goal={goal!r} is unknown; expected None or one of {list(GOALS)}")
    base = functools.partial(
        make_keypoint_env,
        kwargs.get("object", "toolcap"),
        None,
        image_size=kwargs.get("image_size", (160, 120)),
        hand_starts=kwargs.get("hand_starts"),
        control="ee",
        sensor=kwargs.get("sensor", "d435"),
        reward_type=kwargs.get("reward_type", "dense"),
        max_steps=kwargs.get("max_steps", 100),
    )
    vector_class = AsyncVectorEnv if asynchronous else SyncVectorEnv
    vector_env = vector_class([base] * int(n_envs), autoreset_mode=AutoresetMode.SAME_STEP)
    try:
        keypoint_env = VectorKeypointObservation(
            vector_env,
            kwargs.get("keypoint_model", "oracle"),
            keep_images=False,
            device=device,
            **(kwargs.get("keypoint_kwargs") or {}),
        )
    except Exception:
        vector_env.close()
        raise
    head = functools.partial(
        _sac_head, goal=goal, memory=bool(kwargs.get("memory", False)), encoding=kwargs.get("encoding", "plain")
    )
    return make_batched_vec_env(keypoint_env, head, monitor=monitor)


def check_n_envs(n_envs: Any) -> None:
    """Refuse a number of envs that is not a positive integer (a bool is not), naming ``n_envs``."""
    if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or int(n_envs) < 1:
        raise DonGymError(f"n_envs={n_envs!r}: expected a positive number of envs")


def monitored(maker: Callable[..., gym.Env], env_kwargs: dict[str, Any]) -> gym.Env:
    from stable_baselines3.common.monitor import Monitor

    return Monitor(maker(**env_kwargs), info_keywords=("is_success",))


def make_vec_env(
    algorithm: str,
    n_envs: int,
    seed: int,
    env_kwargs: dict[str, Any],
    vectorize: str | None = None,
    don_device: str | None = None,
) -> Any:
    """The SB3 VecEnv :func:`train` trains on (``vectorize``: see :data:`VECTORIZE`; None: one env in
    this process, or a subprocess per env; ``don_device``: where batched envs run the DON)."""
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    check_n_envs(n_envs)
    vectorize = vectorize or ("dummy" if int(n_envs) == 1 else "subproc")
    if vectorize not in VECTORIZE:
        raise DonGymError(f"vectorize={vectorize!r} is unknown; expected one of {list(VECTORIZE)}")
    if vectorize.startswith("batched"):
        if algorithm != "sac":
            raise DonGymError(f"vectorize={vectorize!r} serves the SAC env (control='ee'), not {algorithm!r}")
        vec_env = make_batched_sac_vec_env(
            int(n_envs), env_kwargs, asynchronous=vectorize == "batched-async", device=don_device
        )
    else:
        env_fn = functools.partial(monitored, ENV_MAKERS[algorithm], dict(env_kwargs))
        vec_class = SubprocVecEnv if vectorize == "subproc" else DummyVecEnv
        vec_env = vec_class([env_fn] * int(n_envs))
    vec_env.seed(int(seed))
    return vec_env
