"""Expert demonstrations with every observation kind, in robomimic's HDF5 layout (docs/demonstrations.md).

:func:`record_demonstrations` runs the Markov :class:`~don_gym.agents.ee_expert.EndEffectorExpert` on the
goal env of a task (``make_goal_env``: the part's true keypoints, ``control="ee"``), keeps the successful
episodes, and writes them with the observations of every requested kind (:data:`OBSERVATION_KINDS`): each kind's
env is reset with the episode's seed and replays its actions (the physics does not depend on what is rendered or
on the sensor noise, which the replay checks against the recorded state). :func:`read_demonstrations` reads a
file back, checked against the task and part a caller trains for.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm.auto import tqdm

from don_gym.agents.ee_expert import EXPERT_GOALS, EndEffectorExpert
from don_gym.errors import DonGymError
from don_gym.io import atomic_path
from don_gym.wrappers.descriptors import DescriptorObservation
from don_gym.wrappers.goals import make_goal_env, make_keypoint_env
from don_gym.wrappers.images import DescriptorImage

__all__ = [
    "DEMO_FORMAT",
    "OBSERVATION_KINDS",
    "Demonstrations",
    "RecordSettings",
    "kind_env",
    "kind_name",
    "read_demonstrations",
    "record_demonstrations",
]

#: ``data`` attribute ``format`` of every file written here.
DEMO_FORMAT = "don_gym-demos-1"
#: Observation kinds (``kinds=`` of :func:`record_demonstrations`; ``<network>``: a shipped name or a checkpoint):
#: "state" (privileged: robot state, part pose, goal), "true" (the part's exact keypoints, always seen), "rgbd"
#: (the wrist camera's RGB and sensor depth at ``rgbd_size``), "simulated:<network>" (SimulatedKeypoints with the
#: network's noise model, field of view and depth range), "don:<network>" (the network's keypoints on the wrist
#: camera at ``don_size``, windowed by ``window_px``), "descriptors:<network>" (the network's descriptor image of
#: the wrist camera at ``don_size``, area-averaged to ``rgbd_size``, uint8). Every keypoint kind carries
#: KeypointMemory's keys.
OBSERVATION_KINDS = ("state", "true", "rgbd", "simulated:<network>", "don:<network>", "descriptors:<network>")
#: Max steps of an episode per goal: lifting takes about 40 steps, the whole place about 110.
EPISODE_STEPS = {"lift": 100, "place": 200}
#: Stream of the DART noise's generator, apart from the seeds' other uses.
NOISE_STREAM = 58
#: Keys of the "state" kind.
STATE_KEYS = ("ee_pose", "gripper_width", "joint_positions", "part_pose", "desired_goal")


def kind_name(kind: str) -> str:
    """The HDF5 name of a kind: ``"don:toolcap/supervised-edge"`` -> ``"don-toolcap-supervised-edge"``."""
    return kind.replace(":", "-").replace("/", "-")


def _check_kinds(kinds: Sequence[str]) -> list[str]:
    out = []
    for kind in kinds:
        source = kind.split(":", 1)
        fixed = kind in ("state", "true", "rgbd")
        if not fixed and not (len(source) == 2 and source[0] in ("simulated", "don", "descriptors") and source[1]):
            raise DonGymError(f"observation kind {kind!r} is unknown; expected one of {list(OBSERVATION_KINDS)}")
        if kind not in out:
            out.append(kind)
    if "state" not in out:
        out.insert(0, "state")  # the replay is checked against it
    return out


@dataclass(frozen=True)
class RecordSettings:
    """How the kinds' envs are made: the wrist image sizes, the window and the sensor."""

    rgbd_size: tuple[int, int] = (128, 96)
    don_size: tuple[int, int] = (640, 480)
    window_px: int | None = 192
    sensor: str = "d435"


def kind_env(
    kind: str, part: str, goal: str, settings: RecordSettings, observe_state: bool = False, background: str = "plain"
) -> gym.Env | None:
    """The env (``control="ee"``, ``goal``'s episode length, ``background``) whose observations are ``kind``'s;
    for "state" None (the recorder reads it from the expert's own env), or with ``observe_state`` the env without
    images."""
    steps = EPISODE_STEPS[goal]
    common = {"control": "ee", "max_steps": steps, "sensor": settings.sensor, "background": background}
    if kind == "state":
        return make_keypoint_env(part, None, image_size=None, **common) if observe_state else None
    if kind == "rgbd":
        return make_keypoint_env(part, None, image_size=settings.rgbd_size, **common)
    if kind == "true":
        return make_keypoint_env(part, "true", memory=True, **common)
    source, network = kind.split(":", 1)
    if source == "descriptors":
        env = make_keypoint_env(part, None, image_size=settings.don_size, **common)
        return DescriptorImage(DescriptorObservation(env, model=network), size=settings.rgbd_size)
    if source == "simulated":
        return make_keypoint_env(part, "simulated", network, memory=True, **common)
    return make_keypoint_env(
        part, "don", network, image_size=settings.don_size, window_px=settings.window_px, memory=True, **common
    )


def _kind_observation(kind: str, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if kind == "rgbd":
        return {"rgb": obs["rgb"], "depth": obs["depth"]}
    if kind.startswith("descriptors:"):
        return {"descriptors": obs["descriptors"]}
    return {key: value for key, value in obs.items() if key.startswith("keypoint_")}


def _state(expert_env: gym.Env, obs: dict[str, Any], info: dict[str, Any]) -> dict[str, np.ndarray]:
    base = expert_env.unwrapped
    position, quaternion = base.robot.tcp_position_quaternion()
    T = np.asarray(info["T_world_object"], dtype=np.float64)
    return {
        "ee_pose": np.concatenate([position, quaternion]).astype(np.float32),
        "gripper_width": np.array([base.robot.gripper_width()], np.float32),
        "joint_positions": base.robot.joint_positions().astype(np.float32),
        "part_pose": np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()]).astype(np.float32),
        "desired_goal": np.asarray(obs["desired_goal"], np.float32),
    }


def _expert_episode(env: gym.Env, expert: EndEffectorExpert, seed: int, action_noise: float) -> dict[str, Any]:
    """One expert episode: the states (T + 1), the expert's actions, the actions run (the expert's plus Gaussian
    noise of standard deviation ``action_noise`` on the motion, DART), rewards, dones (T) and whether it
    succeeded. The noise is drawn from ``seed``: a replay runs the same actions."""
    rng = np.random.default_rng([NOISE_STREAM, int(seed)])
    obs, info = env.reset(seed=seed)
    states, actions, executed, rewards, dones = [_state(env, obs, info)], [], [], [], []
    done = False
    while not done:
        action = expert.act(obs)
        run = action.copy()
        if action_noise > 0:
            run[:4] = np.clip(run[:4] + action_noise * rng.standard_normal(4), -1.0, 1.0)
        obs, reward, terminated, truncated, info = env.step(run)
        done = bool(terminated or truncated)
        states.append(_state(env, obs, info))
        actions.append(action)
        executed.append(run)
        rewards.append(float(reward))
        dones.append(bool(terminated))
    return {"states": states, "actions": np.array(actions, np.float32),
            "executed_actions": np.array(executed, np.float32), "rewards": np.array(rewards, np.float32),
            "dones": np.array(dones, np.uint8), "success": bool(info.get("is_success", False))}  # fmt: skip


def _replay(env: gym.Env, kind: str, seed: int, episode: dict[str, Any]) -> list[dict[str, np.ndarray]]:
    """``kind``'s observations (T + 1) along the episode's actions, checked to follow the recorded part poses."""
    obs, info = env.reset(seed=seed)
    observations = [_kind_observation(kind, obs)]
    for t, action in enumerate(episode["executed_actions"]):
        obs, _, _, _, info = env.step(action)
        observations.append(_kind_observation(kind, obs))
        recorded = episode["states"][t + 1]["part_pose"][:3]
        if np.max(np.abs(np.asarray(info["T_world_object"])[:3, 3] - recorded)) > 1e-4:
            raise DonGymError(f"observation kind {kind!r}: its replay of seed {seed} left the recorded episode")
    return observations


def _stack(rows: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.stack([row[key] for row in rows]) for key in rows[0]}


def record_demonstrations(
    path: str | Path,
    part: str = "toolcap",
    goal: str = "lift",
    episodes: int = 10,
    seed: int = 0,
    kinds: Sequence[str] = ("state", "true"),
    settings: RecordSettings | None = None,
    progress: bool = True,
    action_noise: float = 0.0,
) -> Path:
    """Record ``episodes`` successful expert demonstrations of ``goal`` on ``part`` (seeds from ``seed`` up;
    failed episodes are skipped, at most as many as ``episodes``) with the observations of ``kinds`` into the
    HDF5 file ``path`` (written atomically; layout: docs/demonstrations.md). Returns the path.

    ``action_noise`` > 0: the episodes run the expert's actions with Gaussian noise of that standard deviation
    (action units) on the motion (dx, dy, dz, dyaw), and ``actions`` holds the expert's own for each state
    reached: DART (Laskey et al. 2017), demonstrations that show how the expert corrects the errors a cloned
    policy will make."""
    import h5py

    if goal not in EXPERT_GOALS:
        raise DonGymError(f"goal={goal!r} is unknown; expected one of {list(EXPERT_GOALS)}")
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise DonGymError(f"episodes={episodes!r}: expected a positive number of demonstrations")
    if isinstance(action_noise, bool) or not isinstance(action_noise, (int, float)) or not 0 <= action_noise <= 1:
        raise DonGymError(f"action_noise={action_noise!r}: expected a standard deviation in [0, 1] (action units)")
    kinds, settings = _check_kinds(kinds), settings or RecordSettings()
    expert_env = make_goal_env(part, goal=goal, keypoints="true", max_steps=EPISODE_STEPS[goal], sensor=settings.sensor)
    kind_envs = {kind: kind_env(kind, part, goal, settings) for kind in kinds}
    expert = EndEffectorExpert(expert_env, goal)
    path = Path(path)
    attempts, kept = 0, 0
    try:
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            bar = tqdm(total=int(episodes), desc=f"demos {part} {goal}", disable=not progress)
            while kept < episodes and attempts < 2 * episodes:
                episode_seed = int(seed) + attempts
                attempts += 1
                episode = _expert_episode(expert_env, expert, episode_seed, float(action_noise))
                if not episode["success"]:
                    continue
                observations = {"state": episode["states"]}
                for kind, env in kind_envs.items():
                    if env is not None:
                        observations[kind] = _replay(env, kind, episode_seed, episode)
                _write_demo(data.create_group(f"demo_{kept}"), kinds, observations, episode, episode_seed)
                kept += 1
                bar.update()
            bar.close()
            if kept < episodes:
                raise DonGymError(
                    f"the expert succeeded in {kept} of {attempts} episodes of {goal!r} on {part!r}; expected "
                    f"{episodes} demonstrations"
                )
            total = int(sum(data[name].attrs["num_samples"] for name in data))
            data.attrs["total"] = total
            data.attrs["format"] = DEMO_FORMAT
            data.attrs["env_args"] = json.dumps(
                {"env_name": "DONPick-v0", "type": "don_gym",
                 "env_kwargs": {"object": part, "control": "ee", "max_steps": EPISODE_STEPS[goal],
                                "sensor": settings.sensor}, "goal": goal}
            )  # fmt: skip
            data.attrs["part"], data.attrs["goal"] = part, goal
            data.attrs["kinds"] = json.dumps(kinds)
            data.attrs["settings"] = json.dumps(
                {"rgbd_size": list(settings.rgbd_size), "don_size": list(settings.don_size),
                 "window_px": settings.window_px, "sensor": settings.sensor}
            )  # fmt: skip
            data.attrs["expert_attempts"] = attempts
            data.attrs["action_noise"] = float(action_noise)
            f.create_dataset("mask/all", data=np.array([f"demo_{i}" for i in range(kept)], dtype="S"))
    finally:
        expert_env.close()
        for env in kind_envs.values():
            if env is not None:
                env.close()
    return path


def _write_demo(group: Any, kinds: list[str], observations: dict, episode: dict[str, Any], seed: int) -> None:
    """One ``data/demo_i`` group: ``obs/<key>`` (T) and ``next_obs/<key>`` (T) per kind, actions, rewards, dones,
    ``states`` (the privileged state, flat)."""
    T = len(episode["actions"])
    group.attrs["num_samples"] = T
    group.attrs["seed"] = seed
    group.create_dataset("actions", data=episode["actions"])
    group.create_dataset("executed_actions", data=episode["executed_actions"])
    group.create_dataset("rewards", data=episode["rewards"])
    group.create_dataset("dones", data=episode["dones"])
    states = _stack(episode["states"])
    group.create_dataset("states", data=np.concatenate([states[k].reshape(T + 1, -1) for k in STATE_KEYS], 1)[:T])
    for kind in kinds:
        stacked = _stack(observations[kind])
        for key, values in stacked.items():
            name = key if kind in ("state", "rgbd") else f"{kind_name(kind)}.{key}"
            images = kind == "rgbd" or kind.startswith("descriptors:")
            options = {"compression": "gzip", "compression_opts": 4} if values.ndim >= 3 and images else {}
            group.create_dataset(f"obs/{name}", data=values[:T], **options)
            group.create_dataset(f"next_obs/{name}", data=values[1:], **options)


@dataclass
class Demonstrations:
    """Demonstrations read by :func:`read_demonstrations`: per demo, ``obs`` (key -> (T, ...)) and ``actions``
    (T, 5, the expert's); the file's part, goal, kinds and the DART noise its episodes ran with."""

    part: str
    goal: str
    kinds: list[str]
    observations: list[dict[str, np.ndarray]]
    actions: list[np.ndarray]
    seeds: list[int]
    action_noise: float = 0.0


def read_demonstrations(
    path: str | Path,
    count: int | None = None,
    part: str | None = None,
    goal: str | None = None,
    keys: Sequence[str] | None = None,
) -> Demonstrations:
    """The first ``count`` demonstrations of the file (None: all), with the observation ``keys`` (None: all).
    ``part``/``goal`` given: the file must hold that part's demonstrations of that goal. Every mismatch is a
    one-line DonGymError."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise DonGymError(f"demonstrations {str(path)!r}: no such file")
    with h5py.File(path, "r") as f:
        data = f.get("data")
        if data is None or data.attrs.get("format") != DEMO_FORMAT:
            raise DonGymError(f"demonstrations {str(path)!r}: not a don_gym demonstrations file ({DEMO_FORMAT})")
        file_part, file_goal = str(data.attrs["part"]), str(data.attrs["goal"])
        if part is not None and str(part) != file_part:
            raise DonGymError(f"demonstrations {str(path)!r} are of the part {file_part!r}; expected {part!r}")
        if goal is not None and goal != file_goal:
            raise DonGymError(f"demonstrations {str(path)!r} are of the task {file_goal!r}; expected {goal!r}")
        names = sorted(data, key=lambda name: int(name.split("_")[1]))
        if count is not None:
            if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
                raise DonGymError(f"count={count!r}: expected a positive number of demonstrations")
            if count > len(names):
                raise DonGymError(
                    f"count={count}: demonstrations {str(path)!r} hold {len(names)}; record more or ask for fewer"
                )
            names = names[:count]
        available = list(data[names[0]]["obs"])
        missing = [key for key in (keys or []) if key not in available]
        if missing:
            raise DonGymError(f"observation keys {missing}: not in {str(path)!r}; it has {available}")
        wanted = list(keys) if keys is not None else available
        observations = [{key: data[name]["obs"][key][()] for key in wanted} for name in names]
        actions = [data[name]["actions"][()] for name in names]
        seeds = [int(data[name].attrs["seed"]) for name in names]
        kinds = json.loads(data.attrs["kinds"])
        noise = float(data.attrs.get("action_noise", 0.0))
    return Demonstrations(file_part, file_goal, kinds, observations, actions, seeds, noise)
