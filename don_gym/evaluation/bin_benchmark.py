"""Clearing benchmark: pick one part's instances out of seeded piles in a bin, per method.

Each episode is one pile (:class:`~don_gym.sim.bin_env.BinPickEnv`, ``control="grasp"``, reset at the pile's seed)
picked by one agent until the env ends it: every target instance out (*cleared*), too many failed attempts in a
row, or the step limit. Method ``oracle`` is :class:`~don_gym.agents.BinOracleAgent` (true poses of the instances
seen), ``oracle-descriptors`` the descriptor agent :class:`~don_gym.agents.BinAxisGraspAgent` on the pile's
optimal descriptors, any other method a descriptor source the agent loads for the target part (a shipped network,
a checkpoint of the part or of several parts including it). Every method picks from the same piles.

Per method, paired on the same piles, the field's metrics (:mod:`don_gym.evaluation.bin_metrics`): placed per
target instance (the headline), picks per attempt, lift success per attempt, piles fully placed, give-ups,
wrong-part lifts, flips, regrasps and their success, each with its 95% Wilson interval, and mean placements per
hour of simulated time (the scripted motion's simulated seconds, the move back to the observation pose and the
method's measured perception and planning time charged per attempt), with each method's ratio to the oracle's
on the same piles.

A job array splits the piles (:func:`run_bin_benchmark` ``shard=(i, n)``: piles i, i+n, ...); every shard writes
its episodes into the same folder (:func:`write_bin_shard`) and :func:`merge_bin_shards` makes the result of the
whole run from them, the same as an unsharded run's.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from don_gym.errors import DonGymError
from don_gym.evaluation.bin_metrics import (
    EPISODE_KEYS,
    RATE_COLUMNS,
    bin_rates,
    paired_ratio,
    placements_per_hour,
    rate_cells,
)
from don_gym.evaluation.episodes import run_tasks

__all__ = [
    "DEFAULT_IMAGE_SIZE",
    "DEFAULT_PARTS",
    "DEFAULT_TARGET",
    "EPISODES_FILE",
    "EPISODE_KEYS",
    "FLIP_THRESHOLD_RAD",
    "ORACLE_DESCRIPTORS_METHOD",
    "ORACLE_METHOD",
    "RATE_COLUMNS",
    "SHARD_DIR",
    "SUPERVISED_METHODS",
    "TARGET_GAVE_UP_SHARE",
    "TARGET_ORACLE_PER_ATTEMPT",
    "TARGET_ORACLE_PER_HOUR",
    "TARGET_ORACLE_PLACED",
    "TARGET_RATIO_TO_ORACLE",
    "TARGET_WRONG_PART_SHARE",
    "BinBenchmarkConfig",
    "BinBenchmarkResult",
    "PileRunner",
    "bin_table",
    "check_targets",
    "describe_methods",
    "make_agent",
    "merge_bin_shards",
    "parse_parts_counts",
    "parse_shard",
    "pile_seed",
    "run_bin_benchmark",
    "run_pile",
    "write_bin_outputs",
    "write_bin_shard",
]

#: Method names the benchmark resolves itself; anything else is a descriptor source of the target part.
ORACLE_METHOD = "oracle"
ORACLE_DESCRIPTORS_METHOD = "oracle-descriptors"
#: Default pile: the issue's 3 toolcaps and 2 shafts, toolcap the target.
DEFAULT_PARTS: tuple[tuple[str, int], ...] = (("toolcap", 3), ("shaft", 2))
DEFAULT_TARGET = "toolcap"
#: Camera size for the oracles alone (networks take the size they were trained at).
DEFAULT_IMAGE_SIZE: tuple[int, int] = (320, 240)
#: A target lift by an axis grasp whose yaw is further than this (rad) from the instance's +axis is flipped.
FLIP_THRESHOLD_RAD = np.pi / 2
#: The targets of "Bin picking that places what it picks" (piles of 3 toolcaps + 2 shafts, target toolcap, D435):
#: the oracle places this share of the target instances, this share of its attempts, at this pace (placements per
#: hour of simulated time, perception charged: Dex-Net 4.0's); a supervised network of several parts reaches this
#: fraction of the oracle's placed-per-target rate and pace on the same piles, lifts another part in at most this
#: share of its lifts and gives up on at most this share of the piles.
TARGET_ORACLE_PLACED = 0.95
TARGET_ORACLE_PER_ATTEMPT = 0.80
TARGET_ORACLE_PER_HOUR = 300.0
TARGET_RATIO_TO_ORACLE = 0.9
TARGET_WRONG_PART_SHARE = 0.02
TARGET_GAVE_UP_SHARE = 0.10
SUPERVISED_METHODS = ("supervised", "supervised-edge", "supervised-mask")
#: File of a shard's episodes in the output folder (``shards/``), and the merged result's files.
SHARD_DIR = "shards"
EPISODES_FILE = "bin_episodes.json"


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/n"`` -> (i, n) with 0 <= i < n, as ``build-dataset --shard`` takes it."""
    from don_gym.data.build import parse_shard as parse

    return parse(text)


def pile_seed(seed: int, pile: int) -> int:
    """The env seed of pile ``pile`` of a run with benchmark seed ``seed``: ``seed + pile``, so that a range of
    piles is a range of seeds (development seeds from :data:`~don_gym.evaluation.splits.BIN_DEVELOPMENT_SEED`, test
    seeds
    from :data:`~don_gym.evaluation.splits.BIN_TEST_SEED`)."""
    return int(seed) + int(pile)


@dataclass(frozen=True)
class BinBenchmarkConfig:
    """What the clearing benchmark runs.

    Attributes:
        parts: (part, count) pairs of every pile (a built-in name or a mesh path; the env's ``parts``).
        target: the part to pick.
        methods: ``oracle``, ``oracle-descriptors``, shipped network names or checkpoint paths.
        piles: number of piles (pile ``i`` is ``reset(seed=pile_seed(seed, i))``).
        seed: seed of pile 0.
        sensor: depth-sensor preset of the wrist camera.
        image_size: (width, height); None: the size the networks among ``methods`` were trained at,
            :data:`DEFAULT_IMAGE_SIZE` for the oracles alone.
        renderer: PyBullet renderer.
        max_failed_attempts: failed attempts in a row that end a pile (the env's).
    """

    parts: tuple[tuple[str, int], ...] = DEFAULT_PARTS
    target: str = DEFAULT_TARGET
    methods: tuple[str, ...] = (ORACLE_METHOD,)
    piles: int = 20
    seed: int = 0
    sensor: str = "d435"
    image_size: tuple[int, int] | None = None
    renderer: str = "tiny"
    max_failed_attempts: int = 3

    def validate(self) -> None:
        if not self.methods:
            raise DonGymError("methods: none given; expected 'oracle' and/or network names or checkpoint paths")
        if len(set(self.methods)) != len(self.methods):
            raise DonGymError(f"methods {list(self.methods)}: each method may be given once")
        for name, minimum in (("piles", 1), ("seed", 0), ("max_failed_attempts", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
                raise DonGymError(f"{name}={value!r}: expected an integer >= {minimum}")
        if self.image_size is not None:
            size = self.image_size
            if not (isinstance(size, (tuple, list)) and len(size) == 2 and all(isinstance(v, int) for v in size)):
                raise DonGymError(f"image_size={size!r}: expected (width, height) in pixels or None")

    def env_kwargs(self) -> dict[str, Any]:
        """Arguments of the :class:`~don_gym.sim.bin_env.BinPickEnv` every episode runs in."""
        return {
            "parts": dict(self.parts),
            "target": self.target,
            "control": "grasp",
            "image_size": self.image_size,
            "sensor": self.sensor,
            "renderer": self.renderer,
            "max_failed_attempts": self.max_failed_attempts,
        }


def parse_parts_counts(parts: Mapping[str, int] | Sequence[tuple[str, int]]) -> tuple[tuple[str, int], ...]:
    """A config's ``parts`` from a dict or pairs (order kept)."""
    items = parts.items() if isinstance(parts, Mapping) else parts
    return tuple((str(name), int(count)) for name, count in items)


def _make_env(config: BinBenchmarkConfig):
    from don_gym.sim.bin_env import BinPickEnv

    return BinPickEnv(**config.env_kwargs())


def make_agent(env: Any, method: str, device: str = "cpu") -> Any:
    """The agent of a method (module docstring) for a bin env."""
    from don_gym.agents import BinAxisGraspAgent, BinOracleAgent

    if method == ORACLE_METHOD:
        return BinOracleAgent(env)
    agent = BinAxisGraspAgent(env, model="oracle" if method == ORACLE_DESCRIPTORS_METHOD else method)
    network = getattr(agent.source, "network", None)
    if network is not None:
        from don_gym.learning.model import torch_device

        network.to(torch_device(device))
    return agent


def _yaw_error(action_yaw: float, T_world_object: np.ndarray, plus_axis: np.ndarray) -> float:
    from don_gym.sim.robot import wrap_angle

    axis = np.asarray(T_world_object, dtype=np.float64)[:3, :3] @ plus_axis
    return abs(wrap_angle(float(action_yaw) - float(np.arctan2(axis[1], axis[0]))))


def run_pile(env: Any, agent: Any, method: str, pile: int, seed: int) -> dict[str, Any]:
    """One pile picked by one agent until the env ends the episode -> its record (:data:`EPISODE_KEYS`). The
    agent's time is measured around each of its ``act`` calls; the motion's from the env's ``info``
    (``sim_time_s`` and ``observation_move_s``)."""
    start = time.perf_counter()
    obs, info = env.reset(seed=seed)
    agent.reset()
    base = env.unwrapped
    plus_axis = np.asarray(base.models[base.target].plus_axis, dtype=np.float64)
    counts = {"grasp_and_place": 0, "grasp_only": 0, "fail": 0, "wrong_part": 0}
    axis_lifts = flipped = attempts = regrasps = regrasp_placed = pushes = topples = 0
    motion_s = perception_s = 0.0
    targets = int(info["targets_left"])
    agent_error, end_reason = None, None
    while True:
        poses = {i["instance"]: i["T_world_object"] for i in info["instances"]}
        act_start = time.perf_counter()
        try:
            action = agent.act(obs, info)
        except DonGymError as exc:
            # No instance found: the robot has nothing to grasp, and the pile stays as it is.
            agent_error, end_reason = str(exc), "agent_gave_up"
            break
        finally:
            perception_s += time.perf_counter() - act_start
        kind = agent.last_ranking[0].kind
        obs, _, terminated, truncated, info = env.step(action)
        agent.observe_outcome(info["outcome"])
        motion_s += float(info["sim_time_s"]) + float(info["observation_move_s"])
        if info["outcome"] == "set_down":
            continue  # the attempt goes on at the regrasp station
        if info["outcome"] == "pushed":
            pushes += 1  # no attempt: its motion is charged to the pace all the same
            topples += kind == "standing"  # a push that topples a standing part (the agent's choice)
        else:
            attempts += 1
            counts[info["outcome"]] += 1
            if info.get("regrasp"):
                regrasps += 1
                regrasp_placed += info["outcome"] == "grasp_and_place"
            if info["outcome"] in ("grasp_and_place", "grasp_only") and kind in ("across", "along"):
                axis_lifts += 1
                flipped += _yaw_error(float(action[3]), poses[info["instance"]], plus_axis) > FLIP_THRESHOLD_RAD
        if terminated or truncated:
            end_reason = info["end_reason"]
            break
    return {
        "method": method,
        "pile": int(pile),
        "seed": int(seed),
        "cleared": end_reason == "cleared",
        "end_reason": end_reason,
        "targets": targets,
        "attempts": attempts,
        "picks": counts["grasp_and_place"],
        "grasp_only": counts["grasp_only"],
        "fails": counts["fail"],
        "wrong_part_picks": counts["wrong_part"],
        "target_axis_lifts": axis_lifts,
        "flipped": int(flipped),
        "regrasps": regrasps,
        "regrasp_placed": int(regrasp_placed),
        "pushes": pushes,
        "topples": topples,
        "motion_seconds": motion_s,
        "perception_seconds": perception_s,
        "agent_error": agent_error,
        "seconds": time.perf_counter() - start,
    }


class PileRunner:
    """Runs piles in one process: one env, one agent per method (built on first use).

    The env is reused: ``BinPickEnv.reset(seed)`` gives the same episode whatever ran before in it (it rebuilds
    its physics world), so a result does not depend on the piles run before it in the process and a sharded
    run equals an unsharded one (tests/test_bin_agent.py)."""

    def __init__(self, config: BinBenchmarkConfig, device: str = "cpu") -> None:
        self.config = config
        self.device = device
        self._env: Any = None
        self._agents: dict[str, Any] = {}

    def run(self, task: tuple[str, int]) -> dict[str, Any]:
        """One ``(method, pile)`` task's episode record."""
        method, pile = task
        if self._env is None:
            self._env = _make_env(self.config)
        if method not in self._agents:
            self._agents[method] = make_agent(self._env, method, self.device)
        return run_pile(self._env, self._agents[method], method, pile, pile_seed(self.config.seed, pile))

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env, self._agents = None, {}


@dataclass
class BinBenchmarkResult:
    """Every episode record (method order, then pile order), the run's time and what each method is."""

    config: BinBenchmarkConfig
    episodes: list[dict[str, Any]]
    seconds: float = 0.0
    workers: int = 1
    method_info: dict[str, dict[str, Any]] = field(default_factory=dict)
    shard: tuple[int, int] = (0, 1)

    def select(self, method: str) -> list[dict[str, Any]]:
        return [e for e in self.episodes if e["method"] == method]

    def rates(self, method: str) -> dict[str, tuple[int, int]]:
        """``{name: (count, out of)}`` of a method's episodes (:func:`~don_gym.evaluation.bin_metrics.bin_rates`)."""
        return bin_rates(self.select(method))

    def per_hour(self, method: str) -> dict[str, Any]:
        """A method's placements per hour of simulated time and its charges
        (:func:`~don_gym.evaluation.bin_metrics.placements_per_hour`)."""
        return placements_per_hour(self.select(method))

    def ratio_to_oracle(self, method: str, measure: str) -> dict[str, Any] | None:
        """A method's ``measure`` ("placed_per_target" or "per_hour") over the oracle's on the same piles
        (:func:`~don_gym.evaluation.bin_metrics.paired_ratio`); None without an oracle in the run."""
        if ORACLE_METHOD not in self.config.methods:
            return None
        return paired_ratio(self.select(method), self.select(ORACLE_METHOD), measure)

    def summary(self) -> dict[str, Any]:
        """Per method every rate with its count, total and 95% Wilson interval (:mod:`don_gym.stats`), the hourly
        rate with its charges, and the ratios to the oracle on the same piles."""
        out: dict[str, Any] = {
            "config": asdict(self.config),
            "shard": list(self.shard),
            "seconds": self.seconds,
            "workers": self.workers,
            "methods": self.method_info,
            "results": {},
        }
        for method in self.config.methods:
            episodes = self.select(method)
            per: dict[str, Any] = rate_cells(episodes)
            per["placements_per_hour"] = self.per_hour(method)
            per["ratio_to_oracle"] = {
                measure: self.ratio_to_oracle(method, measure) for measure in ("placed_per_target", "per_hour")
            }
            per["piles"] = len(episodes)
            per["agent_errors"] = sum(e["agent_error"] is not None for e in episodes)
            out["results"][method] = per
        return out


def describe_methods(config: BinBenchmarkConfig) -> dict[str, dict[str, Any]]:
    """Every method loaded once for the target part (a wrong name, or a network that does not describe the
    target part, is refused here in one line): ``{method: {"method": kind, "parts": [...], ...}}``."""
    from don_gym.perception.descriptor_sources import load_descriptor_source
    from don_gym.sim.bin_env import resolve_parts

    models, _, target = resolve_parts(dict(config.parts), config.target, None)
    info: dict[str, dict[str, Any]] = {}
    for method in config.methods:
        if method in (ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD):
            info[method] = {"method": "oracle", "agent": "oracle" if method == ORACLE_METHOD else "descriptors"}
            continue
        source = load_descriptor_source(method, models[target])
        metadata = getattr(source, "metadata", None)
        entry: dict[str, Any] = {"method": source.method, "agent": "descriptors"}
        if metadata is not None:
            from don_gym.learning.checkpoints import checkpoint_part_space

            space = checkpoint_part_space(metadata)
            entry |= {
                "image_size": list(metadata.image_size),
                "training_steps": metadata.training_steps,
                "parts": list(space.names) if space is not None else [target],
            }
        info[method] = entry
    return info


def _shard_tasks(config: BinBenchmarkConfig, shard: tuple[int, int]) -> list[tuple[str, int]]:
    index, count = shard
    piles = [p for p in range(config.piles) if p % count == index]
    return [(method, pile) for method in config.methods for pile in piles]


def run_bin_benchmark(
    config: BinBenchmarkConfig,
    workers: int = 2,
    progress: bool = True,
    device: str = "cpu",
    shard: tuple[int, int] = (0, 1),
) -> BinBenchmarkResult:
    """Run the piles of ``config`` (of ``shard`` (i, n): piles i, i+n, ...) for every method on ``workers``
    processes, the networks on ``device``. Every method is loaded first, so a bad one is refused before any pile."""
    config.validate()
    from don_gym.data.build import check_run_options
    from don_gym.learning.model import torch_device

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise DonGymError(f"workers={workers!r}: expected an integer >= 1")
    shard = check_run_options(1, shard)
    torch_device(device)
    method_info = describe_methods(config)
    if config.image_size is None:
        from don_gym.evaluation.grasp_benchmark import training_image_size

        sizes = {m: tuple(i["image_size"]) for m, i in method_info.items() if "image_size" in i}
        config = replace(config, image_size=training_image_size(sizes) if sizes else DEFAULT_IMAGE_SIZE)
    start = time.perf_counter()
    episodes, workers = run_tasks(
        PileRunner, config, device, _shard_tasks(config, shard), workers, progress, "pile", "bin benchmark"
    )
    return BinBenchmarkResult(config, episodes, time.perf_counter() - start, workers, method_info, shard)


# --- reporting ------------------------------------------------------------------------------------


def _format_ratio(ratio: dict[str, Any] | None) -> str:
    if ratio is None or ratio["ratio"] is None:
        return "-"
    low, high = ratio["interval_95"]
    return f"{ratio['ratio']:.2f} [{low:.2f}, {high:.2f}]" if np.isfinite(low) else f"{ratio['ratio']:.2f}"


def bin_table(result: BinBenchmarkResult) -> str:
    """Markdown: per method every rate as ``count/total (Wilson 95% interval)``, then per method the hourly rate,
    what an attempt is charged, and the ratios to the oracle on the same piles."""
    from don_gym.stats import format_rate

    c = result.config
    width, height = c.image_size or DEFAULT_IMAGE_SIZE
    pile = " + ".join(f"{n} {p}" for p, n in c.parts)
    lines = [
        f"Piles of {pile}, target `{c.target}`, sensor `{c.sensor}`, {width}x{height} wrist camera, "
        f"{c.piles} piles (seeds {c.seed}-{c.seed + c.piles - 1}), the same piles for every method; rates with "
        "their 95% Wilson interval.",
        "",
        "| method | " + " | ".join(label for _, label in RATE_COLUMNS) + " | attempts | pushes (of them topples) |",
        "|---|" + "---|" * (len(RATE_COLUMNS) + 2),
    ]
    for method in c.methods:
        rates = result.rates(method)
        cells = [format_rate(*rates[name]) for name, _ in RATE_COLUMNS]
        pushes = sum(int(e.get("pushes", 0)) for e in result.select(method))
        topples = sum(int(e.get("topples", 0)) for e in result.select(method))
        pushed = f"{pushes} ({topples})"
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {rates['picks_per_attempt'][1]} | {pushed} |")
    lines += [
        "",
        "Pace in simulated time: per attempt the scripted motion's simulated seconds (grasp, lift, carry, place, "
        "retract; and the pushes': a part against a wall rolled away from it or a standing part toppled, not an "
        "attempt) plus the move back to "
        "the observation pose at the script's free-space speed (*motion*), and the "
        "method's perception and planning time measured on this machine (*perception*); placements per hour = "
        "placements / (motion + perception) x 3600, with a 95% interval from resampling piles. Ratios to the "
        "oracle: on the same piles, the same resamples for both (paired).",
        "",
        "| method | placements per hour | s per attempt (motion + perception) | placed per target / oracle's "
        "| placements per hour / oracle's |",
        "|---|---|---|---|---|",
    ]
    for method in c.methods:
        hour = result.per_hour(method)
        if hour["per_hour"] is None:
            pace, cycle = "-", "-"
        else:
            low, high = hour["interval_95"]
            pace = f"{hour['per_hour']:.0f}" + (f" [{low:.0f}, {high:.0f}]" if np.isfinite(low) else "")
            cycle = (
                f"{hour['cycle_s']:.1f} ({hour['motion_s_per_attempt']:.1f} + {hour['perception_s_per_attempt']:.2f})"
            )
        ratios = [_format_ratio(result.ratio_to_oracle(method, m)) for m in ("placed_per_target", "per_hour")]
        lines.append(f"| {method} | {pace} | {cycle} | " + " | ".join(ratios) + " |")
    return "\n".join(lines)


def _is_multi_part_supervised(info: Mapping[str, Any]) -> bool:
    return info.get("method") in SUPERVISED_METHODS and len(info.get("parts", [])) > 1


def check_targets(result: BinBenchmarkResult) -> list[str]:
    """Lines comparing the result with the targets (``TARGET_*``): the oracle's placed per target instance, picks
    per attempt and placements per hour; a supervised network of several parts' ratios to the oracle's on the
    same piles (point figures), its wrong-part lifts per lift and its piles given up."""
    lines = []
    for method in result.config.methods:
        rates = result.rates(method)
        hour = result.per_hour(method)["per_hour"] or 0.0
        multi_part = _is_multi_part_supervised(result.method_info.get(method, {}))
        if method == ORACLE_METHOD:
            (placed, targets), (picks, attempts) = rates["placed_per_target"], rates["picks_per_attempt"]
            ok = (
                targets
                and attempts
                and placed / targets >= TARGET_ORACLE_PLACED
                and picks / attempts >= TARGET_ORACLE_PER_ATTEMPT
                and hour >= TARGET_ORACLE_PER_HOUR
            )
            lines.append(
                f"{method}: places {placed}/{targets} target instances (target >= {TARGET_ORACLE_PLACED:.0%}), "
                f"{picks}/{attempts} per attempt (target >= {TARGET_ORACLE_PER_ATTEMPT:.0%}), {hour:.0f} placements "
                f"per hour (target >= {TARGET_ORACLE_PER_HOUR:.0f}): " + ("met" if ok else "MISSED")
            )
        elif multi_part and ORACLE_METHOD not in result.config.methods:
            lines.append(f"{method}: its targets are ratios to the oracle's on the same piles; no oracle in the run")
        elif multi_part:
            placed_ratio = (result.ratio_to_oracle(method, "placed_per_target") or {}).get("ratio") or 0.0
            hour_ratio = (result.ratio_to_oracle(method, "per_hour") or {}).get("ratio") or 0.0
            (wrong, lifts), (gave_up, piles) = rates["wrong_part"], rates["gave_up"]
            ok = (
                placed_ratio >= TARGET_RATIO_TO_ORACLE
                and hour_ratio >= TARGET_RATIO_TO_ORACLE
                and wrong <= TARGET_WRONG_PART_SHARE * lifts
                and gave_up <= TARGET_GAVE_UP_SHARE * piles
            )
            lines.append(
                f"{method}: placed per target {placed_ratio:.2f}x and placements per hour {hour_ratio:.2f}x the "
                f"oracle's (targets >= {TARGET_RATIO_TO_ORACLE:g}x), wrong-part lifts {wrong}/{lifts} (target <= "
                f"{TARGET_WRONG_PART_SHARE:.0%}), gave up on {gave_up}/{piles} piles (target <= "
                f"{TARGET_GAVE_UP_SHARE:.0%}): " + ("met" if ok else "MISSED")
            )
    return lines


def _result_json(result: BinBenchmarkResult) -> str:
    return json.dumps({"summary": result.summary(), "episodes": result.episodes}, indent=1) + "\n"


def write_bin_outputs(result: BinBenchmarkResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``bin_episodes.json`` (summary and every episode), ``bin.md`` (the table) and ``bin_rates.png``."""
    from don_gym import plotting
    from don_gym.io import check_output_dir, write_text_atomic
    from don_gym.stats import wilson_interval

    out = check_output_dir(out_dir, "out_dir")
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / EPISODES_FILE, "table": out / "bin.md"}
    write_text_atomic(paths["json"], _result_json(result))
    write_text_atomic(paths["table"], "### Clearing piles\n\n" + bin_table(result) + "\n")
    rates = {
        method: {
            label: (count / total if total else float("nan"), *wilson_interval(count, total))
            for (name, label), (count, total) in zip(
                RATE_COLUMNS, (result.rates(method)[n] for n, _ in RATE_COLUMNS), strict=True
            )
        }
        for method in result.config.methods
    }
    c = result.config
    paths["chart"] = plotting.plot_rate_bars(
        rates,
        out / "bin_rates.png",
        title=f"{c.target} from piles of " + " + ".join(f"{n} {p}" for p, n in c.parts) + f", {c.piles} piles",
    )
    return paths


def write_bin_shard(result: BinBenchmarkResult, out_dir: str | Path) -> Path:
    """Write one shard's episodes to ``OUT/shards/bin_episodes.IofN.json`` for :func:`merge_bin_shards`."""
    from don_gym.io import check_output_dir, write_text_atomic

    index, count = result.shard
    folder = check_output_dir(out_dir, "out_dir") / SHARD_DIR
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"bin_episodes.{index}of{count}.json"
    write_text_atomic(path, _result_json(result))
    return path


def merge_bin_shards(out_dir: str | Path) -> BinBenchmarkResult:
    """The result of a sharded run from the shard files in ``OUT/shards/`` (:func:`write_bin_shard`): every
    shard of one run present, the same config; episodes in the unsharded run's order. DonGymError otherwise."""
    folder = Path(out_dir) / SHARD_DIR
    files = sorted(folder.glob("bin_episodes.*of*.json")) if folder.is_dir() else []
    if not files:
        raise DonGymError(f"{folder}: no shard files (bin_episodes.IofN.json); run with --shard i/n --out {out_dir}")
    shards, config_dict, count, method_info, seconds = {}, None, None, {}, 0.0
    for path in files:
        try:
            data = json.loads(path.read_text())
            summary = data["summary"]
            index, n = (int(v) for v in summary["shard"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DonGymError(f"{path}: not a bin benchmark shard file ({exc})") from None
        if config_dict is None:
            config_dict, count = summary["config"], n
        elif summary["config"] != config_dict or n != count:
            raise DonGymError(f"{path}: its run's settings differ from {files[0].name}'s; expected shards of one run")
        shards[index] = data["episodes"]
        method_info |= summary["methods"]
        seconds += float(summary["seconds"])
    missing = [i for i in range(count) if i not in shards]
    if missing:
        raise DonGymError(f"{folder}: shards {missing} of {count} are missing; run them with --shard i/{count} first")
    config = _config_from_dict(config_dict)
    order = {(m, p): k for k, (m, p) in enumerate(_shard_tasks(config, (0, 1)))}
    episodes = sorted((e for i in range(count) for e in shards[i]), key=lambda e: order[(e["method"], e["pile"])])
    return BinBenchmarkResult(config, episodes, seconds, 1, method_info, (0, 1))


def _config_from_dict(data: Mapping[str, Any]) -> BinBenchmarkConfig:
    values = dict(data)
    values["parts"] = tuple((str(p), int(n)) for p, n in values["parts"])
    values["methods"] = tuple(values["methods"])
    if values.get("image_size") is not None:
        values["image_size"] = tuple(int(v) for v in values["image_size"])
    return BinBenchmarkConfig(**values)
