"""Behaviour cloning at equal demonstrations, one policy class for every input (``don-gym benchmark imitation``).

After Florence, Manuelli and Tedrake 2019: policies cloned from N expert demonstrations
(:mod:`don_gym.evaluation.demonstrations`) for each input (:data:`~don_gym.evaluation.imitation_policy.INPUTS`), all
of one policy class (:class:`~don_gym.evaluation.imitation_policy.HistoryPolicy`), evaluated on held-out episodes
with Wilson intervals. The demonstrations run the expert with DART noise on its motion
(:attr:`ImitationConfig.action_noise`, DART): cloned from noise-free ones, even the true state's policy drifts off
the millimetre-narrow path the expert keeps to near the part, where the demonstrations show no correction to learn
(measured on the development episodes, :data:`DEVELOPMENT_EVAL_SEED`). Generalisation columns
(:data:`GENERALISATION`): the policies of one N evaluated with ``background="random"`` (looks never seen in the
demonstrations), and the same recipe on the other built-in part (its own demonstrations, its networks).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from don_gym.errors import DonGymError
from don_gym.evaluation.demonstrations import RecordSettings, kind_env, read_demonstrations, record_demonstrations
from don_gym.evaluation.episodes import run_tasks
from don_gym.evaluation.imitation_policy import (
    HISTORY,
    HistoryPolicy,
    PartGeometry,
    check_input,
    features,
    image,
    is_image_kind,
    live_step,
    train_policy,
)
from don_gym.perception.descriptor_sources import axis_end_targets
from don_gym.stats import wilson_interval
from don_gym.wrappers.goals import LIFT_GOAL_HEIGHT_M, goal_reached
from don_gym.wrappers.simulated_keypoints import axis_points_world

__all__ = [
    "DEVELOPMENT_EVAL_SEED",
    "EVAL_SEED",
    "GENERALISATION",
    "OTHER_PART",
    "ImitationConfig",
    "ImitationResult",
    "PolicyEvaluation",
    "evaluate_policy",
    "input_for_part",
    "run_imitation",
]

#: Held-out evaluation episodes are ``reset(seed=EVAL_SEED + i)`` (bench_rl's and bench_expert's).
EVAL_SEED = 100_000
#: Development episodes (``reset(seed=DEVELOPMENT_EVAL_SEED + i)``), which chose the recipe (features, DART noise,
#: training steps); demonstrations are ``reset(seed=config.seed + i)``, far below both.
DEVELOPMENT_EVAL_SEED = 50_000
#: Generalisation columns: "random background" (the same policies, ``background="random"``) and "other part"
#: (:data:`OTHER_PART`: the recipe repeated on it).
GENERALISATION = ("random background", "other part")
#: The built-in part each part's "other part" column is measured on.
OTHER_PART = {"toolcap": "shaft", "shaft": "toolcap"}


def input_for_part(name: str, part: str, other: str) -> str | None:
    """``name``'s input on the part ``other``: its network ``<part>/<method>`` becomes ``<other>/<method>``; None
    where it names a checkpoint of its own (no counterpart known)."""
    if ":" not in name:
        return name
    source, network = name.split(":", 1)
    if not network.startswith(f"{part}/"):
        return None
    return f"{source}:{other}/{network[len(part) + 1 :]}"


@dataclass(frozen=True)
class PolicyEvaluation:
    """What :func:`evaluate_policy` measured: successes, env steps run, and their wall time (s: the observation,
    rendering and networks included, the policy's forward pass too)."""

    wins: int
    steps: int
    seconds: float

    @property
    def seconds_per_step(self) -> float:
        return self.seconds / max(self.steps, 1)


def evaluate_policy(
    policy: HistoryPolicy,
    kind: str,
    part: str,
    goal: str,
    episodes: int,
    settings: RecordSettings | None = None,
    seed: int = EVAL_SEED,
    progress: bool = False,
    background: str = "plain",
) -> PolicyEvaluation:
    """Successes of ``policy`` on ``episodes`` held-out episodes (``reset(seed=seed + i)``) of ``goal`` seeing
    ``kind``'s observations with ``background``, and the wall time of its steps. Lift:
    :func:`~don_gym.wrappers.goals.goal_reached` for the part's axis points
    :data:`~don_gym.wrappers.goals.LIFT_GOAL_HEIGHT_M` above where they lay, lifted; place: the task's success."""
    env = kind_env(kind, part, goal, settings or RecordSettings(), observe_state=True, background=background)
    model = env.unwrapped.model
    targets = axis_end_targets(model)
    geometry = PartGeometry.of(model)
    images = is_image_kind(kind)
    wins, steps, seconds = 0, 0, 0.0
    try:
        for i in tqdm(range(episodes), desc=f"eval {kind}", disable=not progress):
            obs, info = env.reset(seed=seed + i)
            start = axis_points_world(model, targets, info["T_world_object"])
            desired = (start + [0.0, 0.0, LIFT_GOAL_HEIGHT_M]).reshape(6)
            history: deque = deque(maxlen=HISTORY)
            done, success = False, False
            while not done:
                started = time.perf_counter()
                step = live_step(obs, info, geometry)
                history.append((features(kind, step), image(kind, step) if images else None))
                while len(history) < HISTORY:
                    history.appendleft(history[0])
                vector = torch.from_numpy(np.concatenate([h[0] for h in history]))[None]
                pictures = torch.from_numpy(np.stack([h[1] for h in history]))[None] if images else None
                with torch.inference_mode():
                    action = policy(vector, pictures)[0].numpy()
                obs, _, terminated, truncated, info = env.step(action)
                seconds += time.perf_counter() - started
                steps += 1
                if goal == "lift":
                    achieved = axis_points_world(model, targets, info["T_world_object"]).reshape(6)
                    success = bool(goal_reached(achieved, desired)) and bool(info.get("lifted", False))
                else:
                    success = bool(info.get("is_success", False))
                done = success or terminated or truncated
            wins += success
    finally:
        env.close()
    return PolicyEvaluation(wins, steps, seconds)


# -------------------------------------------------------------------------------- the run
@dataclass
class ImitationConfig:
    """What :func:`run_imitation` compares: ``inputs`` at each of ``demonstrations`` (N), ``episodes`` evaluation
    episodes each (``reset(seed=eval_seed + i)``), behaviour cloning for ``train_steps`` gradient steps from
    demonstrations with DART noise ``action_noise``; the :data:`GENERALISATION` columns at N =
    ``generalisation_n`` (None: none; the benchmark's command asks for them at 50)."""

    part: str = "toolcap"
    goal: str = "lift"
    inputs: tuple[str, ...] = ("state", "true", "simulated:toolcap/supervised-edge", "rgbd")
    demonstrations: tuple[int, ...] = (10, 25, 50, 100, 200)
    episodes: int = 100
    train_steps: int = 4000
    seed: int = 0
    action_noise: float = 0.1
    generalisation_n: int | None = None
    eval_seed: int = EVAL_SEED
    settings: RecordSettings = field(default_factory=RecordSettings)


@dataclass
class ImitationResult:
    """Successes per input and N (``wins[input][n]``) out of ``config.episodes``, per generalisation column and
    input (``generalisation[column][input]``, None where it does not apply), the demonstrations file, and what an
    env step with each input costs."""

    config: ImitationConfig
    wins: dict[str, dict[int, int]]
    demos_path: str
    generalisation: dict[str, dict[str, int | None]] = field(default_factory=dict)
    #: Per input, the wall time (s) of an evaluation step on the config's part with the plain background.
    seconds_per_step: dict[str, float] = field(default_factory=dict)

    def rates(self) -> dict[str, list[tuple[int, float, float, float]]]:
        """Per input, ``(n, rate, low, high)`` with the 95% Wilson interval."""
        episodes = self.config.episodes
        return {
            name: [(n, w / episodes, *wilson_interval(w, episodes)) for n, w in sorted(by_n.items())]
            for name, by_n in self.wins.items()
        }

    def _cell(self, wins: int | None) -> str:
        if wins is None:
            return "n/a"
        low, high = wilson_interval(wins, self.config.episodes)
        return f"{100 * wins / self.config.episodes:.0f}% [{100 * low:.0f}, {100 * high:.0f}]"

    def table(self) -> str:
        """Markdown: one row per input, one column per N, then the generalisation columns at their N, successes
        with their interval, and the wall time of an env step with the input (observation, networks, policy)."""
        ns = sorted(self.config.demonstrations)
        columns = list(self.generalisation)
        other = OTHER_PART.get(self.config.part, "other part")
        names = [f"N = {n}" for n in ns] + [
            f"{other} (N = {self.config.generalisation_n})" if c == "other part" else
            f"{c} (N = {self.config.generalisation_n})" for c in columns
        ]  # fmt: skip
        names.append("ms / step")
        lines = ["| input | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        for name, by_n in self.wins.items():
            cells = [self._cell(by_n[n]) for n in ns] + [self._cell(self.generalisation[c].get(name)) for c in columns]
            cost = self.seconds_per_step.get(name)
            cells.append("-" if cost is None else f"{1000 * cost:.1f}")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        return "\n".join(lines)


def _check_config(config: ImitationConfig) -> None:
    for name in config.inputs:
        check_input(name)
    if not config.demonstrations or any(isinstance(n, bool) or int(n) < 1 for n in config.demonstrations):
        raise DonGymError(f"demonstrations={list(config.demonstrations)}: expected positive numbers")
    if int(config.episodes) < 1:
        raise DonGymError(f"episodes={config.episodes}: expected a positive number of evaluation episodes")
    if config.generalisation_n is not None and config.generalisation_n not in config.demonstrations:
        raise DonGymError(
            f"generalisation_n={config.generalisation_n}: expected one of demonstrations={list(config.demonstrations)}"
        )


def _demonstrations(
    config: ImitationConfig, part: str, inputs: list[str], count: int, path: Path, progress: bool
) -> Path:
    record_demonstrations(
        path, part, config.goal, count, config.seed, ["state", *inputs], config.settings, progress=progress,
        action_noise=config.action_noise,
    )  # fmt: skip
    return path


def _check_demonstrations(path: str | Path, count: int, part: str, goal: str, inputs: list[str]) -> None:
    """One-line DonGymError unless ``path`` holds ``count`` demonstrations of ``goal`` on ``part`` with ``inputs``."""
    kinds = read_demonstrations(path, count=count, part=part, goal=goal, keys=["ee_pose"]).kinds
    missing = [name for name in inputs if name not in kinds]
    if missing:
        raise DonGymError(f"demonstrations {str(path)!r} lack the inputs {missing}; it has {kinds}")


def _other_inputs(config: ImitationConfig) -> dict[str, str | None]:
    """Each input's counterpart on :data:`OTHER_PART`'s part (None: it has none, or the part has no other)."""
    other = OTHER_PART.get(config.part)
    return {name: input_for_part(name, config.part, other) if other else None for name in config.inputs}


def _unit_cost(unit: tuple) -> tuple[int, int]:
    """A rough order of a unit's wall time, for running the longest first: image inputs train a convolutional
    encoder; descriptor images and DON keypoints run a network every step; then by N."""
    kind, n = unit[2], unit[3]
    source = kind.split(":", 1)[0]
    return ({"descriptors": 3, "rgbd": 2, "don": 1}.get(source, 0), n)


class _UnitRunner:
    """Clones and evaluates one (input, N) of a run, in whichever process :func:`run_tasks` gives it.

    ``config`` is ``(ImitationConfig, {part: demonstrations path})``. A unit is ``(column, input, kind, n)``:
    column "main" (``kind`` is the input; the random-background column too at the generalisation N) or
    "other part" (``kind`` is the input's counterpart on the other part)."""

    def __init__(self, config: tuple[ImitationConfig, dict[str, str]], device: str) -> None:
        del device  # the policies are small: every unit trains on the CPU
        self.config, self.paths = config

    def run(self, unit: tuple) -> dict:
        config = self.config
        column, _, kind, n = unit
        part = config.part if column == "main" else OTHER_PART[config.part]
        demos = read_demonstrations(self.paths[part], count=n, part=part, goal=config.goal)
        policy = train_policy(kind, demos, config.train_steps, seed=config.seed)
        evaluation = evaluate_policy(
            policy, kind, part, config.goal, config.episodes, config.settings, config.eval_seed
        )
        record = {"wins": evaluation.wins, "steps": evaluation.steps, "seconds": evaluation.seconds}
        if column == "main" and n == config.generalisation_n:
            record["random background"] = evaluate_policy(
                policy, kind, part, config.goal, config.episodes, config.settings, config.eval_seed,
                background="random",
            ).wins  # fmt: skip
        return record

    def close(self) -> None:
        pass


class _RecordRunner:
    """Records one part's demonstrations (a task: ``(part, inputs, count, path, progress)``) for :func:`run_tasks`."""

    def __init__(self, config: ImitationConfig, device: str) -> None:
        del device
        self.config = config

    def run(self, task: tuple) -> dict:
        part, inputs, count, path, progress = task
        return {"path": str(_demonstrations(self.config, part, list(inputs), count, Path(path), progress))}

    def close(self) -> None:
        pass


def run_imitation(
    config: ImitationConfig,
    work: str | Path,
    demos: str | Path | None = None,
    progress: bool = True,
    jobs: int = 1,
    other_demos: str | Path | None = None,
) -> ImitationResult:
    """Record (or take ``demos``, checked to be of the config's part and goal, with every input) the largest N's
    demonstrations, clone a policy per input and N from the first N of them, evaluate each, and the generalisation
    columns (:data:`GENERALISATION`) at ``config.generalisation_n`` (the other part's demonstrations recorded, or
    taken from ``other_demos``, checked likewise).

    ``jobs`` > 1: the demonstrations of the two parts are recorded side by side, then every (input, N) is cloned
    and evaluated ``jobs`` at a time, each in its own process with one torch thread, the longest first. Each
    policy's training is seeded and its evaluation episodes are fixed, so the figures do not depend on ``jobs``."""
    _check_config(config)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise DonGymError(f"jobs={jobs!r}: expected a positive number of processes")
    largest = max(config.demonstrations)
    work = Path(work)
    others = _other_inputs(config) if config.generalisation_n is not None else {}
    other_kinds = [kind for kind in others.values() if kind is not None]
    # Each part's demonstrations: taken (checked before anything is recorded, and once, so that no worker starts
    # on a file it cannot use) or recorded into ``work``, side by side with ``jobs`` > 1 (only the first file's bar
    # then shows: two processes' bars would write over each other).
    recordings: list[tuple[str, tuple[str, ...], int, str, bool]] = []
    paths: dict[str, str] = {}
    wanted = [(config.part, list(config.inputs), largest, demos)]
    if other_kinds:
        wanted.append((OTHER_PART[config.part], other_kinds, int(config.generalisation_n), other_demos))
    for part, inputs, count, given in wanted:
        if given is not None:
            _check_demonstrations(given, count, part, config.goal, inputs)
            paths[part] = str(given)
        else:
            paths[part] = str(work / f"demos_{part}_{config.goal}.hdf5")
            recordings.append((part, tuple(inputs), count, paths[part], progress and (jobs == 1 or not recordings)))
    if recordings:
        work.mkdir(parents=True, exist_ok=True)
        run_tasks(_RecordRunner, config, "cpu", recordings, jobs, False, "file", "demonstrations")
    demos = paths[config.part]
    units = [("main", name, name, n) for name in config.inputs for n in sorted(config.demonstrations)]
    units += [("other part", name, kind, int(config.generalisation_n)) for name, kind in others.items() if kind]
    order = sorted(range(len(units)), key=lambda i: _unit_cost(units[i]), reverse=True)
    records, _ = run_tasks(
        _UnitRunner, (config, paths), "cpu", [units[i] for i in order], jobs, progress, "policy", "clone and evaluate"
    )
    by_unit = {units[i]: record for i, record in zip(order, records, strict=True)}
    wins: dict[str, dict[int, int]] = {}
    seconds_per_step: dict[str, float] = {}
    generalisation: dict[str, dict[str, int | None]] = {}
    if config.generalisation_n is not None:
        generalisation = {"random background": {}, "other part": dict.fromkeys(config.inputs)}
    for name in config.inputs:
        main = [by_unit[("main", name, name, n)] for n in sorted(config.demonstrations)]
        wins[name] = {n: r["wins"] for n, r in zip(sorted(config.demonstrations), main, strict=True)}
        seconds_per_step[name] = sum(r["seconds"] for r in main) / max(sum(r["steps"] for r in main), 1)
        for record in main:
            if "random background" in record:
                generalisation["random background"][name] = record["random background"]
        kind = others.get(name)
        if kind is not None:
            generalisation["other part"][name] = by_unit[("other part", name, kind, int(config.generalisation_n))][
                "wins"
            ]
    return ImitationResult(config, wins, str(demos), generalisation, seconds_per_step)
