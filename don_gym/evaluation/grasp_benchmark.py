"""Grasp-and-place benchmark: the paper's robot experiment in simulation, plus a depth-sensor sweep.

Kupcsik et al. 2021 ("Experiment setup") grasp the toolcap at 8 fixed poses with each trained DON
through a two-descriptor axis grasp and count the outcomes; :func:`run_grasp_benchmark` does the same
with an :class:`~don_gym.agents.AxisGraspAgent` per method, for each depth sensor of the sweep. A method
named ``pose:MODEL`` grasps with a :class:`~don_gym.agents.PoseGraspAgent` of that model instead (the
same descriptors through a 6D pose estimate), so both uses are compared on the same episodes.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from don_gym.errors import DonGymError
from don_gym.evaluation.episodes import run_tasks
from don_gym.sim.task import FIXED_POSES, GRASP_STEP_CLEARANCE_M, OUTCOMES

__all__ = [
    "ACCURATE_GRASP_M",
    "ACCURATE_GRASP_YAW_RAD",
    "DEFAULT_IMAGE_SIZE",
    "DEFAULT_METHODS",
    "DEFAULT_SENSORS",
    "FLIP_THRESHOLD_RAD",
    "POSE_AGENT_PREFIX",
    "POSE_SETS",
    "RANDOM_POSE_STREAM",
    "EpisodeRunner",
    "EpisodeTask",
    "GraspBenchmarkConfig",
    "GraspBenchmarkResult",
    "agent_model",
    "default_methods",
    "episode_seed",
    "episode_tasks",
    "parse_sensor",
    "pose_set",
    "random_pose_seed",
    "run_grasp_benchmark",
    "training_image_size",
]

#: The paper's four compared models (for the toolcap; ``{object}`` is replaced by the object name).
DEFAULT_METHODS: tuple[str, ...] = (
    "oracle",
    "{object}/supervised-edge",
    "{object}/supervised-mask",
    "{object}/self-supervised",
)
#: Prefix of a method grasped through a 6D pose estimate (:class:`~don_gym.agents.PoseGraspAgent`).
POSE_AGENT_PREFIX = "pose:"


def agent_model(method: str) -> tuple[str, str]:
    """``("pose", MODEL)`` for a method ``pose:MODEL``, else ``("axis", method)``: which agent grasps, with
    which model."""
    if method.startswith(POSE_AGENT_PREFIX):
        return "pose", method[len(POSE_AGENT_PREFIX) :]
    return "axis", method


#: Sensor sweep from ideal depth to the D435 (the last one is the headline sensor).
DEFAULT_SENSORS: tuple[str, ...] = ("ideal", "d435@0.5", "d435")
#: Wrist-camera (width, height) in pixels when no network decides it (the oracle alone).
DEFAULT_IMAGE_SIZE: tuple[int, int] = (320, 240)
#: Yaw errors above this (rad) count as a flipped (+axis reversed) grasp.
FLIP_THRESHOLD_RAD = np.pi / 2
#: A grasp within this distance (m) of the true grasp point and this yaw (rad) of the true +axis holds the
#: part as the grasp planner meant (the distance is the room it leaves along the axis), so a placement
#: that still fails is the placement's doing (:func:`miss_table`), not the descriptors'.
ACCURATE_GRASP_M = GRASP_STEP_CLEARANCE_M
ACCURATE_GRASP_YAW_RAD = float(np.deg2rad(5.0))


@dataclass(frozen=True)
class GraspBenchmarkConfig:
    """What the benchmark runs.

    Attributes:
        object: built-in part or mesh path (the env's ``object``).
        methods: ``"oracle"``, shipped network names or checkpoint paths.
        poses: fixed pose ids (0..7).
        repeats: episodes per (method, pose, sensor), with different seeds.
        random_poses: seeded random poses evaluated beyond the fixed ones (0: none), one episode each
            per method and sensor, reported apart (:func:`random_pose_seed`).
        sensors: sensor specs (:func:`parse_sensor`); the last is the headline sensor (the outcome
            table and bar chart, the paper's figure; the paper's camera is a D435). With several,
            a sweep table and chart show how each method degrades from ideal depth to the D435,
            the experiment the paper could not run on hardware.
        image_size: wrist-camera (width, height) in pixels; None: the size the networks among
            ``methods`` were trained at (they must agree), :data:`DEFAULT_IMAGE_SIZE` for the oracle alone.
        renderer: PyBullet renderer of the camera images.
        seed: benchmark seed from which every episode seed derives.
        backgrounds: the env's ``background`` in every episode (:data:`don_gym.sim.env.BACKGROUNDS`):
            ``"plain"`` (the plain table, as the paper's figures were measured), ``"random"`` (the datasets'
            classic backdrops on the table top and the floor and a random cradle colour, drawn from the
            episode's seed: each repeat of a pose is another background, the same for every method and
            sensor, and the part, noise and calibration error are those of the plain episode with that
            seed) or ``"random-wide"`` (the wide backdrop families).
    """

    object: str = "toolcap"
    methods: tuple[str, ...] = ("oracle",)
    poses: tuple[int, ...] = tuple(range(len(FIXED_POSES)))
    repeats: int = 3
    random_poses: int = 0
    sensors: tuple[str, ...] = DEFAULT_SENSORS
    image_size: tuple[int, int] | None = None
    renderer: str = "tiny"
    seed: int = 0
    backgrounds: str = "plain"

    def validate(self) -> None:
        if not self.methods:
            raise DonGymError("no methods to benchmark; give 'oracle' and/or network names or checkpoint paths")
        if len(set(self.methods)) != len(self.methods):
            raise DonGymError(f"methods {list(self.methods)}: each method may be given once")
        bad = [p for p in self.poses if not (isinstance(p, (int, np.integer)) and 0 <= p < len(FIXED_POSES))]
        if bad or not self.poses:
            raise DonGymError(f"poses {list(self.poses)}: expected pose ids 0..{len(FIXED_POSES) - 1}")
        for name, minimum in (("repeats", 1), ("random_poses", 0), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
                raise DonGymError(f"{name}={value!r}: expected an integer >= {minimum}")
        if not self.sensors or len(set(self.sensors)) != len(self.sensors):
            raise DonGymError(f"sensors {list(self.sensors)}: expected at least one, each once")
        for spec in self.sensors:
            parse_sensor(spec)
        from don_gym.sim.camera import check_renderer
        from don_gym.sim.env import BACKGROUNDS

        check_renderer(self.renderer)
        if not isinstance(self.backgrounds, str) or self.backgrounds not in BACKGROUNDS:
            raise DonGymError(f"backgrounds={self.backgrounds!r}: expected one of {list(BACKGROUNDS)}")
        if self.image_size is None:
            return
        size = self.image_size
        pair = isinstance(size, (tuple, list)) and len(size) == 2
        if not pair or not all(isinstance(v, (int, np.integer)) for v in size):
            raise DonGymError(f"image_size={size!r}: expected (width, height) in pixels or None")
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
    """A sensor spec as a SensorModel; DonGymError if malformed.

    Specs are preset names (``ideal``, ``d435``, ``d435-clean``, ``kinect``) or ``NAME@SEVERITY``,
    the preset scaled towards the ideal sensor by :func:`don_gym.sim.sensor.scaled_sensor`
    (``d435@0.5``: half the D435's noise, dropout and calibration error).
    """
    from don_gym.sim.sensor import get_sensor, scaled_sensor

    name, at, severity = str(spec).partition("@")
    if not at:
        return get_sensor(name)
    try:
        value = float(severity)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= 1.0:
        raise DonGymError(f"sensor {spec!r}: expected NAME@SEVERITY; the severity must be in [0, 1], e.g. d435@0.5")
    return scaled_sensor(get_sensor(name), value)


def episode_seed(seed: int, pose_id: int, repeat: int) -> int:
    """Seed of one episode, ``SeedSequence([seed, pose_id, repeat])``; the same for every method and sensor.

    Repeats differ only by this seed, which draws the depth-sensor noise and the hand-eye calibration
    error of the episode. Every method and sensor sees the same seeds (a paired comparison), and an
    episode's result depends on nothing else, so any number of worker processes gives the same results.
    """
    return int(np.random.SeedSequence([int(seed), int(pose_id), int(repeat)]).generate_state(1)[0])


#: Second entropy word of :func:`random_pose_seed` (no fixed pose id is this large).
RANDOM_POSE_STREAM = 0x52414E44
#: The two sets of poses a result reports on: the paper's fixed poses (the headline) and the random ones.
POSE_SETS = ("fixed", "random")


def random_pose_seed(seed: int, index: int) -> int:
    """Seed of random pose ``index``, ``SeedSequence([seed, RANDOM_POSE_STREAM, index])``.

    ``env.reset(seed=...)`` without a ``pose_id`` draws the part's pose from this seed (then the sensor
    noise and calibration error), so every method and sensor grasps the part at the same random poses;
    the stream constant keeps them apart from the fixed poses' seeds.
    """
    return int(np.random.SeedSequence([int(seed), RANDOM_POSE_STREAM, int(index)]).generate_state(1)[0])


@dataclass(frozen=True)
class EpisodeTask:
    """One episode: at fixed pose ``pose_id`` (``random_pose`` None) or at random pose ``random_pose``
    (``pose_id`` None, ``repeat`` 0: the seed that draws the pose also draws the noise, so a repeat
    would be another pose), with the env's ``background``."""

    sensor: str
    method: str
    pose_id: int | None
    repeat: int
    seed: int
    random_pose: int | None = None
    background: str = "plain"


def episode_tasks(config: GraspBenchmarkConfig) -> list[EpisodeTask]:
    """All episodes, in the order of the results: sensor, method, then the fixed poses and their
    repeats, then the random poses."""
    tasks = []
    for sensor in config.sensors:
        for method in config.methods:
            tasks += [
                EpisodeTask(
                    sensor, method, int(pose), repeat, episode_seed(config.seed, pose, repeat), None, config.backgrounds
                )
                for pose in config.poses
                for repeat in range(config.repeats)
            ]
            tasks += [
                EpisodeTask(sensor, method, None, 0, random_pose_seed(config.seed, index), index, config.backgrounds)
                for index in range(config.random_poses)
            ]
    return tasks


def pose_set(episode: dict[str, Any]) -> str:
    """``"fixed"`` or ``"random"``: which of :data:`POSE_SETS` an episode record belongs to."""
    return "fixed" if episode.get("random_pose") is None else "random"


class EpisodeRunner:
    """Runs episodes; owns one env per sensor and one agent per (sensor, method), built on first use.

    One per process (each env owns a PyBullet client).
    """

    def __init__(self, config: GraspBenchmarkConfig, device: str = "cpu") -> None:
        self.config = config
        self.device = device
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
                background=self.config.backgrounds,
            )
        return self._envs[sensor]

    def _agent(self, sensor: str, method: str):
        key = (sensor, method)
        if key not in self._agents:
            from don_gym.agents import AxisGraspAgent, PoseGraspAgent
            from don_gym.learning.model import torch_device
            from don_gym.perception.descriptor_sources import NetworkDescriptors

            env = self._env(sensor)
            kind, model = agent_model(method)
            agent = PoseGraspAgent(env, model=model) if kind == "pose" else AxisGraspAgent(env, model=model)
            if isinstance(agent.source, NetworkDescriptors):
                agent.source.network.to(torch_device(self.device))
            self._agents[key] = (agent, agent.wrap(env))
        return self._agents[key]

    def run(self, task: EpisodeTask) -> dict[str, Any]:
        """One episode -> its record (see :class:`GraspBenchmarkResult`)."""
        from don_gym.sim.robot import wrap_angle

        start = time.perf_counter()
        agent, env = self._agent(task.sensor, task.method)
        options = None if task.random_pose is not None else {"pose_id": task.pose_id}
        obs, reset_info = env.reset(seed=task.seed, options=options)
        true_action = env.unwrapped.oracle_action()
        record: dict[str, Any] = asdict(task)
        # What the episode's background was (None: plain), to tell which backdrops a method missed on.
        record["backdrop"] = reset_info["backdrop"]
        # Where the part lay: grasp point (m) and +axis yaw (rad); tells the random poses apart.
        record["true_action"] = [float(v) for v in true_action]
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


@dataclass
class GraspBenchmarkResult:
    """All episode records (in :func:`episode_tasks` order) and how long the run took.

    Each record: ``sensor, method, pose_id, repeat, seed, random_pose, background`` (the env's option),
    ``backdrop`` (None for ``"plain"``, else the drawn texture families, their mean colours and the cradle's
    colour), ``true_action`` (the oracle's ``[x, y, z, yaw]``: where the part lay), ``outcome, lifted, agent_error``,
    ``position_error_m`` (grasp point vs the true one), ``yaw_error_rad`` (|+axis yaw error|, in
    [0, pi]), ``flipped``, ``placement_axis_error_rad``, ``placement_distance_m``, ``seconds``.
    The agent's errors are against the true pose (:meth:`~don_gym.sim.env.PickPlaceEnv.oracle_action`);
    a yaw error near 180 degrees is the part grasped "upside down".
    """

    config: GraspBenchmarkConfig
    episodes: list[dict[str, Any]]
    seconds: float
    workers: int = 1
    method_info: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def headline_sensor(self) -> str:
        return self.config.sensors[-1]

    def select(self, sensor: str, method: str, poses: str = "fixed") -> list[dict[str, Any]]:
        """The episodes of one sensor and method at the fixed or the random poses (:data:`POSE_SETS`)."""
        return [e for e in self.episodes if e["sensor"] == sensor and e["method"] == method and pose_set(e) == poses]

    def episodes_per_cell(self, poses: str = "fixed") -> int:
        """Episodes per (sensor, method) at the fixed or the random poses."""
        return len(self.config.poses) * self.config.repeats if poses == "fixed" else self.config.random_poses

    def counts(self, sensor: str, poses: str = "fixed") -> dict[str, dict[str, int]]:
        """``{method: {outcome: episodes}}`` for one sensor."""
        return {
            method: {o: sum(e["outcome"] == o for e in self.select(sensor, method, poses)) for o in OUTCOMES}
            for method in self.config.methods
        }

    def summary(self) -> dict[str, Any]:
        """``results`` at the fixed poses (the paper's experiment) and, with random poses, ``random_pose_results``;
        per sensor and method the counts and their 95% Wilson intervals (:mod:`don_gym.stats`)."""
        from don_gym.stats import wilson_interval

        out: dict[str, Any] = {
            "config": asdict(self.config),
            "headline_sensor": self.headline_sensor,
            "episodes_per_cell": self.episodes_per_cell("fixed"),
            "random_pose_episodes_per_cell": self.episodes_per_cell("random"),
            "seconds": self.seconds,
            "workers": self.workers,
            "methods": self.method_info,
        }
        for poses, key in (("fixed", "results"), ("random", "random_pose_results")):
            if poses == "random" and not self.config.random_poses:
                continue
            out[key] = {}
            for sensor in self.config.sensors:
                per_method = {}
                for method in self.config.methods:
                    episodes = self.select(sensor, method, poses)
                    position = [e["position_error_m"] for e in episodes if e["position_error_m"] is not None]
                    yaw = [e["yaw_error_rad"] for e in episodes if e["yaw_error_rad"] is not None]
                    counts = {o: sum(e["outcome"] == o for e in episodes) for o in OUTCOMES}
                    grasped = sum(e["outcome"] != "fail" for e in episodes)
                    per_method[method] = {
                        "counts": counts,
                        "grasped": grasped,
                        "interval_95": {
                            name: list(wilson_interval(count, len(episodes)))
                            for name, count in (*counts.items(), ("grasped", grasped))
                        },
                        "flipped": sum(bool(e["flipped"]) for e in episodes),
                        "agent_errors": sum(e["agent_error"] is not None for e in episodes),
                        "median_position_error_mm": float(np.median(position) * 1000.0) if position else None,
                        "median_yaw_error_deg": float(np.degrees(np.median(yaw))) if yaw else None,
                    }
                out[key][sensor] = per_method
        return out


def run_grasp_benchmark(
    config: GraspBenchmarkConfig, workers: int = 2, progress: bool = True, device: str = "cpu"
) -> GraspBenchmarkResult:
    """Run every episode of ``config`` on ``workers`` processes (1: in this process), the networks on
    ``device`` (:func:`~don_gym.learning.model.torch_device`; each worker process then holds its own copy there).

    An episode is ``env.reset(seed, options={"pose_id": k})`` (a random pose: ``env.reset(seed)``) of the grasp-mode env
    (:class:`don_gym.sim.env.PickPlaceEnv`, ``control="grasp"``) and one step with the action of an
    :class:`~don_gym.agents.AxisGraspAgent` built for the method (``"oracle"``, a shipped network
    name or a checkpoint path; ``pose:MODEL``: a :class:`~don_gym.agents.PoseGraspAgent`). Outcomes:
    ``fail`` (part not lifted), ``grasp only`` (lifted, but dropped or placed with the wrong orientation)
    and ``grasp & place``.

    Every method is loaded once here first, so a wrong name or a network for another object fails
    before any episode runs.
    """
    config.validate()
    if workers < 1:
        raise DonGymError(f"workers={workers}: expected at least 1")
    from don_gym.learning.model import torch_device

    torch_device(device)  # a bad or absent device is refused before any episode
    from don_gym.objects import load_object
    from don_gym.perception.descriptor_sources import load_descriptor_source

    object_model = load_object(config.object)
    method_info = {}
    trained_sizes = {}
    for method in config.methods:
        kind, model = agent_model(method)
        source = load_descriptor_source(model, object_model)
        metadata = getattr(source, "metadata", None)
        # A pose agent's kind keeps its prefix: the paper's targets are the axis agent's.
        method_kind = f"{POSE_AGENT_PREFIX}{source.method}" if kind == "pose" else source.method
        method_info[method] = {"method": method_kind, "agent": kind, "descriptor_dim": source.descriptor_dim} | (
            {"training_steps": metadata.training_steps, "arch": metadata.arch} if metadata is not None else {}
        )
        if metadata is not None:
            trained_sizes[method] = tuple(metadata.image_size)
    if config.image_size is None:
        config = replace(config, image_size=training_image_size(trained_sizes))
    start = time.perf_counter()
    episodes, workers = run_tasks(
        EpisodeRunner, config, device, episode_tasks(config), workers, progress, "episode", "grasp benchmark"
    )
    return GraspBenchmarkResult(config, episodes, time.perf_counter() - start, workers, method_info)
