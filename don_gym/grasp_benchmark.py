"""Grasp-and-place benchmark: the paper's robot experiment in simulation, plus a depth-sensor sweep.

Kupcsik et al. 2021 ("Experiment setup") grasp the toolcap at 8 fixed poses with each trained
DON through a two-descriptor axis grasp and count the outcomes ``fail`` (part not lifted),
``grasp only`` (lifted, but dropped or placed with the wrong orientation) and ``grasp & place``.
Here every episode is ``env.reset(seed, options={"pose_id": k})`` of the grasp-mode env
(:class:`don_gym.sim.env.PickPlaceEnv`, ``control="grasp"``) and one step with the action of an
:class:`~don_gym.agents.AxisGraspAgent` built for the method (``"oracle"``, a shipped network
name or a checkpoint path).

Repeats differ only by the episode seed, which draws the depth-sensor noise and the hand-eye
calibration error of the episode: ``seed = SeedSequence([benchmark seed, pose_id, repeat])``.
Every method and sensor sees the same seeds (a paired comparison), and an episode's result
depends on nothing else, so any number of worker processes gives the same results.

Sensors: preset names (``ideal``, ``d435``, ``d435-clean``, ``kinect``) or ``NAME@SEVERITY``,
the preset scaled towards the ideal sensor by :func:`don_gym.sim.sensor.scaled_sensor`
(``d435@0.5``: half the D435's noise, dropout and calibration error). The last sensor listed is
the headline one (the outcome table and bar chart, the paper's figure; the paper's camera is a
D435); with several sensors a sweep table and chart show how each method degrades from ideal
depth to the D435, the experiment the paper could not run on hardware.

Per episode the record holds the outcome and the agent's grasp error against the true pose
(:meth:`~don_gym.sim.env.PickPlaceEnv.oracle_action`): position error of the grasp point and
the error of the +axis yaw (near 180 degrees: the part grasped "upside down").
"""

from __future__ import annotations

import multiprocessing as mp
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from don_gym.errors import DonGymError
from don_gym.sim.task import FIXED_POSES, OUTCOMES

#: The paper's four compared models (for the toolcap; ``{object}`` is replaced by the object name).
DEFAULT_METHODS: tuple[str, ...] = (
    "oracle",
    "{object}/supervised-edge",
    "{object}/supervised-mask",
    "{object}/self-supervised",
)
#: Sensor sweep from ideal depth to the D435 (the last one is the headline sensor).
DEFAULT_SENSORS: tuple[str, ...] = ("ideal", "d435@0.5", "d435")
#: Wrist-camera (width, height) in pixels when no network decides it (the oracle alone).
DEFAULT_IMAGE_SIZE: tuple[int, int] = (320, 240)
#: Yaw errors above this (rad) count as a flipped (+axis reversed) grasp.
FLIP_THRESHOLD_RAD = np.pi / 2


@dataclass(frozen=True)
class GraspBenchmarkConfig:
    """What the benchmark runs.

    Attributes:
        object: built-in part or mesh path (the env's ``object``).
        methods: ``"oracle"``, shipped network names or checkpoint paths.
        poses: fixed pose ids (0..7).
        repeats: episodes per (method, pose, sensor), with different seeds.
        sensors: sensor specs (module docstring); the last is the headline sensor.
        image_size: wrist-camera (width, height) in pixels; None: the size the networks among
            ``methods`` were trained at (they must agree), :data:`DEFAULT_IMAGE_SIZE` for the oracle alone.
        renderer: PyBullet renderer of the camera images.
        seed: benchmark seed from which every episode seed derives.
    """

    object: str = "toolcap"
    methods: tuple[str, ...] = ("oracle",)
    poses: tuple[int, ...] = tuple(range(len(FIXED_POSES)))
    repeats: int = 3
    sensors: tuple[str, ...] = DEFAULT_SENSORS
    image_size: tuple[int, int] | None = None
    renderer: str = "tiny"
    seed: int = 0

    def validate(self) -> None:
        if not self.methods:
            raise DonGymError("no methods to benchmark; give 'oracle' and/or network names or checkpoint paths")
        if len(set(self.methods)) != len(self.methods):
            raise DonGymError(f"methods {list(self.methods)}: each method may be given once")
        bad = [p for p in self.poses if not (isinstance(p, (int, np.integer)) and 0 <= p < len(FIXED_POSES))]
        if bad or not self.poses:
            raise DonGymError(f"poses {list(self.poses)}: expected pose ids 0..{len(FIXED_POSES) - 1}")
        if self.repeats < 1:
            raise DonGymError(f"repeats={self.repeats}: expected at least 1")
        if not self.sensors or len(set(self.sensors)) != len(self.sensors):
            raise DonGymError(f"sensors {list(self.sensors)}: expected at least one, each once")
        for spec in self.sensors:
            parse_sensor(spec)
        from don_gym.sim.camera import check_renderer

        check_renderer(self.renderer)
        if self.image_size is None:
            return
        width, height = self.image_size
        if not (16 <= width <= 1280 and 16 <= height <= 960):
            raise DonGymError(f"image size {width}x{height} is out of range; expected 16x16 to 1280x960")


def training_image_size(trained_sizes: dict[str, tuple[int, int]]) -> tuple[int, int]:
    """The one image size the networks (method -> (width, height)) were trained at; a DON is not
    scale invariant, so the wrist camera should show the part at the size the networks learned."""
    sizes = set(trained_sizes.values())
    if not sizes:
        return DEFAULT_IMAGE_SIZE
    if len(sizes) > 1:
        listed = ", ".join(f"{m} {w}x{h}" for m, (w, h) in trained_sizes.items())
        raise DonGymError(f"the networks were trained at different image sizes ({listed}); give the image size")
    return sizes.pop()


def default_methods(object_name: str) -> tuple[str, ...]:
    """``oracle`` and the paper's three networks for ``object_name``."""
    return tuple(m.format(object=object_name) for m in DEFAULT_METHODS)


def parse_sensor(spec: str):  # -> don_gym.sim.sensor.SensorModel
    """A sensor spec (preset name or ``NAME@SEVERITY``) as a SensorModel; DonGymError if malformed."""
    from don_gym.sim.sensor import get_sensor, scaled_sensor

    name, at, severity = str(spec).partition("@")
    if not at:
        return get_sensor(name)
    try:
        value = float(severity)
    except ValueError:
        raise DonGymError(f"sensor {spec!r}: expected NAME@SEVERITY with a severity in [0, 1], e.g. d435@0.5") from None
    return scaled_sensor(get_sensor(name), value)


def episode_seed(seed: int, pose_id: int, repeat: int) -> int:
    """Seed of one episode; the same for every method and sensor."""
    return int(np.random.SeedSequence([int(seed), int(pose_id), int(repeat)]).generate_state(1)[0])


@dataclass(frozen=True)
class EpisodeTask:
    sensor: str
    method: str
    pose_id: int
    repeat: int
    seed: int


def episode_tasks(config: GraspBenchmarkConfig) -> list[EpisodeTask]:
    """All episodes, in the order of the results: sensor, method, pose, repeat."""
    return [
        EpisodeTask(sensor, method, int(pose), repeat, episode_seed(config.seed, pose, repeat))
        for sensor in config.sensors
        for method in config.methods
        for pose in config.poses
        for repeat in range(config.repeats)
    ]


class EpisodeRunner:
    """Runs episodes; owns one env per sensor and one agent per (sensor, method), built on first use.

    One per process (each env owns a PyBullet client).
    """

    def __init__(self, config: GraspBenchmarkConfig) -> None:
        self.config = config
        self._envs: dict[str, Any] = {}
        self._agents: dict[tuple[str, str], tuple[Any, Any]] = {}

    def _env(self, sensor: str):
        if sensor not in self._envs:
            from don_gym.sim.env import PickPlaceEnv

            self._envs[sensor] = PickPlaceEnv(
                object=self.config.object,
                control="grasp",
                image_size=self.config.image_size,
                sensor=parse_sensor(sensor),
                renderer=self.config.renderer,
            )
        return self._envs[sensor]

    def _agent(self, sensor: str, method: str):
        key = (sensor, method)
        if key not in self._agents:
            from don_gym.agents import AxisGraspAgent

            env = self._env(sensor)
            agent = AxisGraspAgent.for_env(env, model=method)
            self._agents[key] = (agent, agent.wrap(env))
        return self._agents[key]

    def run(self, task: EpisodeTask) -> dict[str, Any]:
        """One episode -> its record (see :class:`GraspBenchmarkResult`)."""
        from don_gym.sim.robot import wrap_angle

        start = time.perf_counter()
        agent, env = self._agent(task.sensor, task.method)
        obs, _ = env.reset(seed=task.seed, options={"pose_id": task.pose_id})
        true_action = env.unwrapped.oracle_action()
        record: dict[str, Any] = asdict(task)
        try:
            action = np.asarray(agent.act(obs), dtype=np.float64)
        except DonGymError as exc:
            # No usable grasp from the perception (e.g. both keypoints on one pixel): the robot
            # does not move and the part stays untouched, which the paper counts as "fail".
            record |= {"outcome": "fail", "lifted": False, "agent_error": str(exc)}
            record |= {"position_error_m": None, "yaw_error_rad": None, "flipped": None}
            record |= {"placement_axis_error_rad": None, "placement_distance_m": None}
        else:
            _, _, _, _, info = env.step(action.astype(np.float32))
            yaw_error = abs(wrap_angle(float(action[3]) - float(true_action[3])))
            record |= {
                "outcome": str(info["outcome"]),
                "lifted": bool(info["lifted"]),
                "agent_error": None,
                "position_error_m": float(np.linalg.norm(action[:3] - true_action[:3])),
                "yaw_error_rad": float(yaw_error),
                "flipped": bool(yaw_error > FLIP_THRESHOLD_RAD),
                "placement_axis_error_rad": float(info["placement_axis_error_rad"]),
                "placement_distance_m": float(info["placement_distance_m"]),
            }
        record["seconds"] = time.perf_counter() - start
        return record

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()
        self._agents.clear()


_RUNNER: EpisodeRunner | None = None


def _worker_init(config: GraspBenchmarkConfig) -> None:
    global _RUNNER  # one runner per worker process, kept for all its episodes
    import torch

    # The workers already fill the cores; more threads per worker only contend.
    torch.set_num_threads(1)
    _RUNNER = EpisodeRunner(config)


def _worker_run(indexed: tuple[int, EpisodeTask]) -> tuple[int, dict[str, Any]]:
    assert _RUNNER is not None
    index, task = indexed
    return index, _RUNNER.run(task)


@dataclass
class GraspBenchmarkResult:
    """All episode records (in :func:`episode_tasks` order) and how long the run took.

    Each record: ``sensor, method, pose_id, repeat, seed, outcome, lifted, agent_error``,
    ``position_error_m`` (grasp point vs the true one), ``yaw_error_rad`` (|+axis yaw error|, in
    [0, pi]), ``flipped``, ``placement_axis_error_rad``, ``placement_distance_m``, ``seconds``.
    """

    config: GraspBenchmarkConfig
    episodes: list[dict[str, Any]]
    seconds: float
    workers: int = 1
    method_info: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def headline_sensor(self) -> str:
        return self.config.sensors[-1]

    def select(self, sensor: str, method: str) -> list[dict[str, Any]]:
        return [e for e in self.episodes if e["sensor"] == sensor and e["method"] == method]

    def counts(self, sensor: str) -> dict[str, dict[str, int]]:
        """``{method: {outcome: episodes}}`` for one sensor."""
        return {
            method: {o: sum(e["outcome"] == o for e in self.select(sensor, method)) for o in OUTCOMES}
            for method in self.config.methods
        }

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "config": asdict(self.config),
            "headline_sensor": self.headline_sensor,
            "episodes_per_cell": len(self.config.poses) * self.config.repeats,
            "seconds": self.seconds,
            "workers": self.workers,
            "methods": self.method_info,
            "results": {},
        }
        for sensor in self.config.sensors:
            per_method = {}
            for method in self.config.methods:
                episodes = self.select(sensor, method)
                position = [e["position_error_m"] for e in episodes if e["position_error_m"] is not None]
                yaw = [e["yaw_error_rad"] for e in episodes if e["yaw_error_rad"] is not None]
                per_method[method] = {
                    "counts": {o: sum(e["outcome"] == o for e in episodes) for o in OUTCOMES},
                    "grasped": sum(e["outcome"] != "fail" for e in episodes),
                    "flipped": sum(bool(e["flipped"]) for e in episodes),
                    "agent_errors": sum(e["agent_error"] is not None for e in episodes),
                    "median_position_error_mm": float(np.median(position) * 1000.0) if position else None,
                    "median_yaw_error_deg": float(np.degrees(np.median(yaw))) if yaw else None,
                }
            out["results"][sensor] = per_method
        return out


def run_grasp_benchmark(config: GraspBenchmarkConfig, workers: int = 2, progress: bool = True) -> GraspBenchmarkResult:
    """Run every episode of ``config`` on ``workers`` processes (1: in this process).

    Every method is loaded once here first, so a wrong name or a network for another object fails
    before any episode runs.
    """
    config.validate()
    if workers < 1:
        raise DonGymError(f"workers={workers}: expected at least 1")
    from don_gym.objects import load_object
    from don_gym.wrappers import load_descriptor_source

    object_model = load_object(config.object)
    method_info = {}
    trained_sizes = {}
    for method in config.methods:
        source = load_descriptor_source(method, object_model)
        metadata = getattr(source, "metadata", None)
        method_info[method] = {"method": source.method, "descriptor_dim": source.descriptor_dim} | (
            {"training_steps": metadata.training_steps, "arch": metadata.arch} if metadata is not None else {}
        )
        if metadata is not None:
            trained_sizes[method] = tuple(metadata.image_size)
    if config.image_size is None:
        config = replace(config, image_size=training_image_size(trained_sizes))
    tasks = episode_tasks(config)
    records: list[dict[str, Any] | None] = [None] * len(tasks)
    start = time.perf_counter()
    workers = min(workers, len(tasks))
    with tqdm(total=len(tasks), unit="episode", desc="grasp benchmark", disable=not progress) as bar:
        if workers == 1:
            runner = EpisodeRunner(config)
            try:
                for index, task in enumerate(tasks):
                    records[index] = runner.run(task)
                    bar.update(1)
            finally:
                runner.close()
        else:
            from don_gym.build import single_threaded_children

            context = mp.get_context("spawn")
            with (
                single_threaded_children(),
                context.Pool(workers, initializer=_worker_init, initargs=(config,)) as pool,
            ):
                for index, record in pool.imap_unordered(_worker_run, list(enumerate(tasks))):
                    records[index] = record
                    bar.update(1)
                pool.close()  # clean shutdown: leaving the with-block terminates (leaked-semaphore warning)
                pool.join()
    episodes = [r for r in records if r is not None]
    return GraspBenchmarkResult(config, episodes, time.perf_counter() - start, workers, method_info)


# --- reporting ------------------------------------------------------------------------------------


def _median_text(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def outcome_table(result: GraspBenchmarkResult, sensor: str | None = None) -> str:
    """Markdown: per method the outcome counts for one sensor (default: the headline sensor)."""
    sensor = result.headline_sensor if sensor is None else sensor
    summary = result.summary()["results"][sensor]
    total = len(result.config.poses) * result.config.repeats
    width, height = result.config.image_size
    lines = [
        f"Sensor `{sensor}`, {width}x{height} wrist camera, {len(result.config.poses)} poses x "
        f"{result.config.repeats} repeats = {total} episodes per method.",
        "",
        "| method | grasp & place | grasp only | fail | grasped | flipped +axis "
        "| median grasp position error (mm) | median yaw error (deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for method, s in summary.items():
        c = s["counts"]
        lines.append(
            f"| {method} | {c['grasp_and_place']}/{total} | {c['grasp_only']}/{total} | {c['fail']}/{total} "
            f"| {s['grasped']}/{total} | {s['flipped']} | {_median_text(s['median_position_error_mm'])} "
            f"| {_median_text(s['median_yaw_error_deg'])} |"
        )
    return "\n".join(lines)


def sweep_table(result: GraspBenchmarkResult) -> str:
    """Markdown: per method and sensor, ``grasp & place / grasped`` out of the episodes per cell."""
    summary = result.summary()["results"]
    sensors = list(result.config.sensors)
    total = len(result.config.poses) * result.config.repeats
    lines = [
        f"Cells: grasp & place / grasped, out of {total} episodes.",
        "",
        "| method | " + " | ".join(f"`{s}`" for s in sensors) + " |",
        "|---|" + "---|" * len(sensors),
    ]
    for method in result.config.methods:
        cells = [
            f"{summary[s][method]['counts']['grasp_and_place']} / {summary[s][method]['grasped']}" for s in sensors
        ]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_grasp_outputs(result: GraspBenchmarkResult, out_dir: str | Path) -> dict[str, Path]:
    """Write ``grasp_episodes.json`` (summary and every episode), ``grasp.md`` (tables),
    ``grasp_outcomes.png`` (headline sensor, one bar per method) and, with several sensors,
    ``grasp_sweep.png``."""
    import json

    from don_gym import plots
    from don_gym.io import write_text_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "grasp_episodes.json", "table": out / "grasp.md"}
    write_text_atomic(
        paths["json"], json.dumps({"summary": result.summary(), "episodes": result.episodes}, indent=1) + "\n"
    )
    tables = "### Outcomes\n\n" + outcome_table(result)
    if len(result.config.sensors) > 1:
        tables += "\n\n### Depth-sensor sweep\n\n" + sweep_table(result)
    write_text_atomic(paths["table"], tables + "\n")
    sensor = result.headline_sensor
    paths["outcomes"] = plots.plot_outcome_bars(
        result.counts(sensor),
        out / "grasp_outcomes.png",
        title=f"{result.config.object}: {len(result.config.poses)} poses x {result.config.repeats} repeats, "
        f"sensor {sensor}",
    )
    if len(result.config.sensors) > 1:
        paths["sweep"] = plots.plot_sweep(
            {s: result.counts(s) for s in result.config.sensors},
            out / "grasp_sweep.png",
            title=f"{result.config.object}: depth-sensor sweep, {len(result.config.poses)} poses x "
            f"{result.config.repeats} repeats",
        )
    return paths


def check_targets(result: GraspBenchmarkResult) -> list[str]:
    """Lines comparing the headline counts with the issue's targets (per 8 poses, scaled by repeats):
    oracle 8/8 grasp & place; supervised networks 8/8 grasped and >= 7/8 grasp & place."""
    summary = result.summary()["results"][result.headline_sensor]
    per_pose_set = result.config.repeats * len(result.config.poses) / 8.0
    lines = []
    for method, s in summary.items():
        kind = result.method_info.get(method, {}).get("method", method)
        if kind == "oracle":
            want_place, want_grasp = 8, 8
        elif kind in ("supervised", "supervised-edge", "supervised-mask"):
            want_place, want_grasp = 7, 8
        else:
            continue
        need_place, need_grasp = want_place * per_pose_set, want_grasp * per_pose_set
        place, grasped = s["counts"]["grasp_and_place"], s["grasped"]
        ok = place >= need_place and grasped >= need_grasp
        lines.append(
            f"{method}: grasp & place {place} (target >= {need_place:g}), grasped {grasped} "
            f"(target >= {need_grasp:g}): {'met' if ok else 'MISSED'}"
        )
    return lines
