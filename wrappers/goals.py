"""A goal-conditioned view of the pick-and-place task for hindsight experience replay (HER).

:class:`KeypointGoal` turns a keypoint observation (:class:`~don_gym.wrappers.KeypointObservation`,
:class:`~don_gym.wrappers.SimulatedKeypoints`) into the ``observation`` / ``achieved_goal`` /
``desired_goal`` dict that stable-baselines3's ``HerReplayBuffer`` expects, goals being the part's two
axis-end keypoints (6 numbers, world metres), and gives the vectorised ``compute_reward`` HER relabels with.
:class:`HandStarts` starts a share of (training) episodes with the hand at or on the part, HER's device for
tasks a random policy never completes. :func:`make_keypoint_env` joins the env, a start and a keypoint
source; :func:`make_goal_env` adds the goal, and is what the registered lift sub-task ``DONToolcapLift-v0``
(``DONShaftLift-v0``, ``DONLift-v0`` with ``object=``) makes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from don_gym.errors import DonGymError
from don_gym.perception.descriptor_sources import DEFAULT_AXIS_FRACTIONS, axis_end_targets, env_object_model
from don_gym.sim.env import HAND_STARTS
from don_gym.sim.task import seated_pose, within_placement_tolerance
from don_gym.wrappers.keypoints import POINT_BOUND_M, KeypointObservation
from don_gym.wrappers.memory import KeypointMemory
from don_gym.wrappers.rl import KeypointFeatures
from don_gym.wrappers.simulated_keypoints import SimulatedKeypoints, axis_points_world

#: Goals :class:`KeypointGoal` offers: the task's placement, or lifting the part where it lies.
GOALS = ("place", "lift")
#: The lift sub-task's goal: the part's keypoints this far (m) above where they were at reset.
LIFT_GOAL_HEIGHT_M = 0.06
#: Where :func:`make_keypoint_env`'s keypoints come from: ``"don"`` a DON or the oracle on rendered images
#: (:class:`~don_gym.wrappers.KeypointObservation`); ``"simulated"`` a model of the DON, no rendering
#: (:class:`~don_gym.wrappers.SimulatedKeypoints` with the network's measured noise); ``"true"`` exact
#: keypoints always in view.
KEYPOINT_SOURCES = ("don", "simulated", "true")


def goal_reached(achieved_goal: np.ndarray, desired_goal: np.ndarray) -> np.ndarray:
    """Elementwise over leading axes: do two keypoint goals (..., 6) place the part alike?

    Each goal is two axis points (minus end, plus end); the part counts as placed at the desired goal
    when the midpoints are within the task's placement distance and the axis directions within its
    axis tolerance (:func:`don_gym.sim.task.within_placement_tolerance`). The task measures the
    distance horizontally and also asks that the part rest in the cradle; here it is 3D, which
    keeps a part held above the cradle from counting.
    """
    a = np.asarray(achieved_goal, dtype=np.float64)
    d = np.asarray(desired_goal, dtype=np.float64)
    if a.shape[-1:] != (6,) or d.shape[-1:] != (6,):
        raise DonGymError(f"goals: expected (..., 6) keypoint goals, got shapes {a.shape} and {d.shape}")
    a = a.reshape(*a.shape[:-1], 2, 3)
    d = d.reshape(*d.shape[:-1], 2, 3)
    distance = np.linalg.norm(a.mean(axis=-2) - d.mean(axis=-2), axis=-1)
    axis_a, axis_d = a[..., 1, :] - a[..., 0, :], d[..., 1, :] - d[..., 0, :]
    norms = np.linalg.norm(axis_a, axis=-1) * np.linalg.norm(axis_d, axis=-1)
    cosine = np.sum(axis_a * axis_d, axis=-1) / np.maximum(norms, 1e-12)
    return within_placement_tolerance(distance, np.arccos(np.clip(cosine, -1.0, 1.0)))


class KeypointGoal(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Goal-conditioned observations and sparse goal rewards over a keypoint observation.

    Observation: ``observation`` the flat vector of :class:`~don_gym.wrappers.KeypointFeatures`
    (the keypoints the wrapped env reports, relative to the TCP, and the robot state; ``encoding``: its
    encoding, "hand" for the hand-frame one, which needs :class:`~don_gym.wrappers.KeypointMemory`'s keys);
    ``achieved_goal`` (6,) the TRUE axis points of the part at the two keypoints' axial positions
    (:func:`~don_gym.wrappers.simulated_keypoints.axis_points_world`, from ``info``), world metres;
    ``desired_goal`` (6,) the same points of the part where the goal wants it: ``goal="place"``
    seated in the cradle (:func:`don_gym.sim.task.seated_pose`), ``goal="lift"`` (a sub-task)
    :data:`LIFT_GOAL_HEIGHT_M` above where it lay at reset.

    The achieved goal is privileged state, as in the usual HER benchmarks: it serves rewards and
    relabelling; a policy that is to see the part only through the keypoints must leave it out of
    its input (``don_gym.agents.rl`` does).

    Reward: :meth:`compute_reward`, 0 where :func:`goal_reached`, else -1. ``info["is_success"]``:
    for ``"place"`` the env's (the task's ``grasp_and_place``, which implies the goal is reached;
    it also needs the part released and at rest in the cradle); for ``"lift"`` the goal reached
    with the part lifted (``info["lifted"]``), which ends the episode.
    """

    def __init__(
        self,
        env: gym.Env,
        goal: str = "place",
        fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS,
        encoding: str = "plain",
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, goal=goal, fractions=fractions, encoding=encoding)
        gym.Wrapper.__init__(self, env)
        if goal not in GOALS:
            raise DonGymError(f"goal={goal!r} is unknown; expected one of {list(GOALS)}")
        if getattr(env.unwrapped, "control", None) != "ee":
            raise DonGymError("KeypointGoal needs an env with control='ee' (a goal is reached over many steps)")
        self.goal = goal
        self.object_model = env_object_model(env)
        self.targets = axis_end_targets(self.object_model, fractions=fractions)
        self.features = KeypointFeatures(env, relative_to="tcp", robot_state=True, encoding=encoding)
        self._seated_goal = self._goal_of(seated_pose(self.object_model))
        self._desired = self._seated_goal.copy()
        goal_space = spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, shape=(6,), dtype=np.float32)
        self.observation_space = spaces.Dict(
            {"observation": self.features.observation_space, "achieved_goal": goal_space, "desired_goal": goal_space}
        )

    def _goal_of(self, T_world_object: np.ndarray) -> np.ndarray:
        points = axis_points_world(self.object_model, self.targets, T_world_object)
        return np.clip(points.reshape(6), -POINT_BOUND_M, POINT_BOUND_M).astype(np.float32)

    def _observation(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        if "T_world_object" not in info:
            raise DonGymError("KeypointGoal needs the true part pose in info ('T_world_object')")
        return {
            "observation": self.features.observation(obs),
            "achieved_goal": self._goal_of(info["T_world_object"]),
            "desired_goal": self._desired.copy(),
        }

    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Sparse goal reward, vectorised over leading axes: 0 where :func:`goal_reached`, else -1 (float32)."""
        return goal_reached(achieved_goal, desired_goal).astype(np.float32) - 1.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if self.goal == "lift":
            start = self._goal_of(info["T_world_object"]).reshape(2, 3)
            self._desired = (start + np.array([0.0, 0.0, LIFT_GOAL_HEIGHT_M])).reshape(6).astype(np.float32)
        else:
            self._desired = self._seated_goal.copy()
        return self._observation(obs, info), info

    def step(self, action: Any):
        obs, _, terminated, truncated, info = self.env.step(action)
        observation = self._observation(obs, info)
        reward = float(self.compute_reward(observation["achieved_goal"], observation["desired_goal"], info))
        if self.goal == "lift":
            info = dict(info)
            info["is_success"] = bool(reward == 0.0 and info.get("lifted", False))
            terminated = bool(terminated or info["is_success"])
        return observation, reward, terminated, truncated, info


def hand_start_shares(shares: dict[str, float]) -> dict[str, float]:
    """Shares of :data:`~don_gym.sim.env.HAND_STARTS` (non-negative, adding up to at most 1) completed with
    ``"observe"`` (the task's start) to a distribution that adds up to 1; DonGymError naming the bad entry."""
    if not isinstance(shares, dict) or not shares:
        raise DonGymError(f"shares={shares!r}: expected a dict such as {{'in_hand': 0.5}}")
    for name, share in shares.items():
        if name not in HAND_STARTS:
            raise DonGymError(f"shares: hand start {name!r} is unknown; expected one of {list(HAND_STARTS)}")
        if not isinstance(share, (int, float)) or isinstance(share, bool) or not np.isfinite(share) or share < 0:
            raise DonGymError(f"shares[{name!r}]={share!r}: expected a non-negative number")
    total = float(sum(shares.values()))
    if total > 1.0 + 1e-9:
        raise DonGymError(f"shares={shares!r} add up to {total:.3g}; expected at most 1 (the rest: the task start)")
    full = {name: float(share) for name, share in shares.items()}
    full["observe"] = full.get("observe", 0.0) + max(0.0, 1.0 - total)
    full_total = sum(full.values())  # 1 up to rounding: normalised so that sampling accepts it
    return {name: share / full_total for name, share in full.items()}


class HandStarts(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Start each episode with the hand where ``shares`` say: a share of the resets gets
    ``options["hand_start"]`` (see :data:`don_gym.sim.env.HAND_STARTS`: ``"above_part"``, ``"at_part"``,
    ``"in_hand"``), the rest the task's own start (``"observe"``).

    Why: with sparse rewards, a policy that starts 0.45 m above the part and moves at random practically
    never closes the gripper on it (the fingers need ~15 steps to close), so hindsight relabelling has no
    lifted part to learn from; starting some training episodes with the part already between the fingers
    is how the HER paper trains pick-and-place. For training only: evaluate on the task's start.

    The start is drawn from a generator seeded by ``reset(seed=...)``, so two runs (or two policies
    evaluated) with the same seeds get the same starts. A reset whose options already name a
    ``hand_start`` keeps it. ``info["hand_start"]`` tells which start an episode got.

    ``look_first=False``: the env resets with the hand already at the start, so the wrist camera never saw
    the part (near it, the part is inside the sensor's minimum range or outside the view); a
    :class:`~don_gym.wrappers.KeypointMemory` then remembers nothing, unlike on the task's own way down.
    ``look_first=True``: the env resets at the task's start, the hand moves to the start
    (:meth:`PickPlaceEnv.start_hand <don_gym.sim.env.PickPlaceEnv.start_hand>`) and the reset returns the observation
    of one step that holds still (action 0), so that everything wrapped below sees the part from above first.
    Then wrap the keypoints (and their memory) in this wrapper, not this one in them; that step counts
    against the episode's ``max_steps``.
    """

    def __init__(self, env: gym.Env, shares: dict[str, float], look_first: bool = False) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, shares=shares, look_first=look_first)
        gym.Wrapper.__init__(self, env)
        if not isinstance(look_first, bool):
            raise DonGymError(f"look_first={look_first!r}: expected True or False")
        if look_first and getattr(env.unwrapped, "max_steps", 2) < 2:
            raise DonGymError(
                f"look_first=True on an env of max_steps={env.unwrapped.max_steps}: its one step that holds still "
                "would end the episode; expected max_steps >= 2"
            )
        self.shares = hand_start_shares(shares)
        self.look_first = look_first
        self._names = list(self.shares)
        self._probabilities = np.array([self.shares[n] for n in self._names])
        self._rng = np.random.default_rng()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        options = dict(options or {})
        if "hand_start" not in options:
            options["hand_start"] = self._names[int(self._rng.choice(len(self._names), p=self._probabilities))]
        hand_start = options["hand_start"]
        if not self.look_first or hand_start == "observe":
            return self.env.reset(seed=seed, options=options)
        self.env.reset(seed=seed, options=options | {"hand_start": "observe"})
        self.env.unwrapped.start_hand(hand_start)
        hold = np.zeros(self.action_space.shape, dtype=self.action_space.dtype)
        obs, _, _, _, info = self.env.step(hold)
        return obs, dict(info) | {"hand_start": hand_start}


def make_keypoint_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    keypoints: str | None = "don",
    keypoint_model: str | Path = "oracle",
    noise: Any = None,
    image_size: tuple[int, int] | None = (160, 120),
    hand_starts: dict[str, float] | None = None,
    keypoint_kwargs: dict[str, Any] | None = None,
    window_px: int | None = None,
    memory: bool = False,
    look_first: bool = False,
    **env_kwargs: Any,
) -> gym.Env:
    """``DONPick-v0`` of ``object`` (``env_kwargs``: its arguments, e.g. ``control``, ``sensor``) with the part's
    keypoints from ``keypoints`` (one of :data:`KEYPOINT_SOURCES`; None: none yet, the wrist images only, as
    the sub-envs of a :class:`~don_gym.wrappers.VectorKeypointObservation` or a descriptor-image env need).

    ``keypoint_model``: "oracle", a shipped DON name such as "toolcap/supervised-edge", or a checkpoint path;
    for ``"simulated"`` its measured noise model unless ``noise`` names another (None with the oracle: exact
    keypoints, hidden outside the camera's view). ``image_size``: the wrist camera's, used only by ``"don"``
    and None (the others render nothing), as is ``window_px`` (the env's: a window of that image around the part,
    placed by :class:`~don_gym.wrappers.KeypointObservation`). ``hand_starts``: :class:`HandStarts` shares,
    innermost, so that a vector env's automatic resets draw a start too. ``keypoint_kwargs``: more arguments of
    :class:`~don_gym.wrappers.KeypointObservation`. ``memory``: add :class:`~don_gym.wrappers.KeypointMemory` (each
    keypoint's last seen place and age) over the keypoints. ``look_first`` (with ``hand_starts``): the hand starts
    are drawn outermost instead, each after a look from the task's start (:class:`HandStarts`), so that the
    keypoints and their memory have seen the part as on the task's own way down.
    """
    if keypoints is not None and keypoints not in KEYPOINT_SOURCES:
        raise DonGymError(f"keypoints={keypoints!r} is unknown; expected one of {list(KEYPOINT_SOURCES)}")
    images = keypoints in ("don", None)
    if images and window_px is not None:
        env_kwargs["window_px"] = window_px
    env = gym.make("DONPick-v0", object=object, image_size=image_size if images else None, **env_kwargs)
    if hand_starts and not look_first:
        env = HandStarts(env, hand_starts)
    if keypoints is None:
        if memory:
            raise DonGymError("memory=True needs keypoints (keypoints=None makes an env of wrist images only)")
        if look_first:
            raise DonGymError("look_first=True needs keypoints (what would look first is the keypoints' wrapper)")
        return env
    if keypoints == "don":
        env = KeypointObservation(env, model=keypoint_model, keep_images=False, **(keypoint_kwargs or {}))
    elif keypoints == "true":
        env = SimulatedKeypoints(env, noise=None, field_of_view=False, keep_images=False)
    else:
        if noise is None and str(keypoint_model) != "oracle":
            noise = keypoint_model  # the network's default noise model
        env = SimulatedKeypoints(env, noise=noise, keep_images=False)
    if memory:
        env = KeypointMemory(env, max_age_steps=env.unwrapped.max_steps)
    return HandStarts(env, hand_starts, look_first=True) if hand_starts and look_first else env


def make_goal_env(
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    goal: str = "lift",
    keypoints: str = "true",
    keypoint_model: str | Path = "oracle",
    noise: Any = None,
    image_size: tuple[int, int] | None = (160, 120),
    max_steps: int = 100,
    hand_starts: dict[str, float] | None = None,
    keypoint_kwargs: dict[str, Any] | None = None,
    encoding: str = "plain",
    **env_kwargs: Any,
) -> gym.Env:
    """The goal-conditioned pick task for HER: ``control="ee"`` with keypoints (:func:`make_keypoint_env`)
    under :class:`KeypointGoal` (``goal``: "lift", the sub-task, or "place"; ``encoding``: its observation's);
    episodes of at most ``max_steps`` steps. The registered ``DONToolcapLift-v0`` is this with ``goal="lift"``, e.g.
    ``gym.make("DONToolcapLift-v0", keypoints="don", keypoint_model="toolcap/supervised-edge")``."""
    if goal not in GOALS:
        raise DonGymError(f"goal={goal!r} is unknown; expected one of {list(GOALS)}")
    env = make_keypoint_env(
        object, keypoints, keypoint_model, noise, image_size, hand_starts, keypoint_kwargs,
        control="ee", max_steps=max_steps, **env_kwargs,
    )  # fmt: skip
    return KeypointGoal(env, goal=goal, encoding=encoding)
