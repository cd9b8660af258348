"""``don-gym benchmark grasp``: the paper's pick-and-place experiment per method, and a depth-sensor sweep."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from don_gym.cli import positive_int
from don_gym.cli.benchmark_imitation import register_imitation

if TYPE_CHECKING:
    from don_gym.objects import ObjectModel

DESCRIPTION = """\
Benchmarks in simulation.

grasp: the robot experiment of Kupcsik et al. (AAAI 2021): for each method, the two-descriptor
axis-grasp agent grasps the part at the 8 fixed poses (env.reset(options={"pose_id": k})) and places
it in the handover cradle; outcomes fail / grasp only / grasp & place are counted. Repeats differ by
the episode seed (depth-sensor noise and hand-eye calibration error); every method sees the same
seeds. With several --sensors, a sweep from ideal depth to the D435 shows where each method breaks.
--random-poses N adds N random poses (env.reset(seed), seeds derived from --seed: the same poses for
every method and sensor), one episode each, reported in tables of their own. --backgrounds random runs
every episode over the datasets' procedural backdrops (table top and floor) and a random cradle colour,
drawn from the episode's seed (each repeat another background; the part, noise and calibration error stay
those of the plain episode). Rates carry their 95% Wilson interval.
"""

EPILOG = """\
examples:
  don-gym benchmark grasp --quick
  don-gym benchmark grasp --methods oracle toolcap/supervised-edge --repeats 3 --sensors ideal d435 --out bench/
  don-gym benchmark grasp --methods oracle run/model.safetensors --sensors d435@0.25 d435@0.75 --out bench/
  don-gym benchmark grasp --quick --random-poses 16
  don-gym benchmark grasp --quick --backgrounds random
  don-gym benchmark grasp --methods toolcap/supervised-edge pose:toolcap/supervised-edge --repeats 1 \
      --sensors d435 --out bench/     # the two-descriptor axis agent beside the 6D-pose agent

sensors: presets (ideal, d435, d435-clean, kinect) or NAME@SEVERITY, the preset scaled towards the ideal
sensor (d435@0.5 = half the D435's noise, holes and calibration error). The last sensor is the headline
one (outcome table and bar chart). --out writes grasp_episodes.json (every episode), grasp.md (tables),
grasp_outcomes.png, with several sensors grasp_sweep.png and with --random-poses grasp_outcomes_random.png.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "benchmark",
        help="simulation benchmarks (grasp: the paper's pick-and-place experiment per method)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kinds = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    grasp = kinds.add_parser(
        "grasp",
        help="grasp-and-place outcomes per method on the 8 fixed poses, and a depth-sensor sweep",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    grasp.add_argument("--object", default="toolcap", help="built-in part or mesh path (default: toolcap)")
    grasp.add_argument(
        "--methods",
        nargs="+",
        default=None,
        metavar="MODEL",
        help="'oracle', shipped network names or checkpoint paths, grasped by the two-descriptor axis agent; "
        "pose:MODEL grasps with the same model's 6D pose estimate instead (PoseGraspAgent), e.g. "
        "--methods toolcap/supervised-edge pose:toolcap/supervised-edge (default: oracle and the shipped "
        "supervised-edge, supervised-mask and self-supervised networks of the object)",
    )
    grasp.add_argument("--poses", nargs="+", type=int, default=None, help="fixed pose ids (default: 0..7)")
    grasp.add_argument("--repeats", type=int, default=None, help="episodes per method and pose (default: 3)")
    grasp.add_argument(
        "--random-poses",
        type=positive_int,
        default=0,
        metavar="N",
        help="also N seeded random poses, one episode each, in tables of their own (default: none)",
    )
    grasp.add_argument(
        "--sensors",
        nargs="+",
        default=None,
        metavar="SENSOR",
        help="depth sensors; the last is the headline one (default: ideal d435@0.5 d435)",
    )
    grasp.add_argument(
        "--quick",
        action="store_true",
        help="1 repeat, the d435 sensor only, no sweep (unless --repeats/--sensors say otherwise)",
    )
    grasp.add_argument(
        "--image-size",
        default=None,
        help="wrist camera WIDTHxHEIGHT (default: the size the networks were trained at; 320x240 for the oracle alone)",
    )
    grasp.add_argument(
        "--renderer",
        default="tiny",
        help="renderer of the wrist camera's RGB: tiny (TinyRenderer, default), egl (OpenGL) or pbr (path-traced, "
        "the pbr extra)",
    )
    grasp.add_argument(
        "--backgrounds",
        default="plain",
        metavar="BACKGROUND",
        help="the env's background: plain (default, the plain table), random (the datasets' classic backdrops "
        "and a random cradle colour per episode) or random-wide (the nine wide backdrop families)",
    )
    grasp.add_argument("--seed", type=int, default=0, help="benchmark seed (default: 0)")
    grasp.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    grasp.add_argument("--device", default="cpu", help="device of the networks: cpu (default), cuda, cuda:N or auto")
    grasp.add_argument("--out", metavar="DIR", default=None, help="write JSON, Markdown and charts here")
    grasp.add_argument("--no-progress", action="store_true", help="no progress bar")
    grasp.set_defaults(run=run)
    register_bin(kinds)
    register_imitation(kinds)


def default_methods(part: ObjectModel) -> list[str]:
    """``oracle`` and those of the paper's three networks that are shipped for ``part`` (matched by its geometry;
    the part's own networks, not those of several parts)."""
    from don_gym.evaluation.grasp_benchmark import DEFAULT_METHODS
    from don_gym.zoo import shipped_multi_part_names, shipped_names_for

    several = set(shipped_multi_part_names())
    by_method = {name.split("/", 1)[1]: name for name in shipped_names_for(part) if name not in several}
    methods = [m.split("/", 1)[-1] for m in DEFAULT_METHODS]
    return [by_method.get(m, m) for m in methods if m == "oracle" or m in by_method]


def run(args: argparse.Namespace) -> int:
    import torch

    from don_gym.cli import parse_size
    from don_gym.errors import DonGymError
    from don_gym.evaluation.grasp_benchmark import DEFAULT_SENSORS, GraspBenchmarkConfig, run_grasp_benchmark
    from don_gym.evaluation.grasp_report import outcome_table, sweep_table, write_grasp_outputs
    from don_gym.io import check_output_dir
    from don_gym.learning.model import torch_device
    from don_gym.objects import load_object
    from don_gym.sim.task import FIXED_POSES

    if args.workers < 1:
        raise DonGymError(f"--workers {args.workers}: expected at least 1")
    torch_device(args.device)  # a bad or absent device is refused before the work
    if args.out is not None:
        check_output_dir(args.out, "--out")
    torch.set_num_threads(1)
    repeats = args.repeats if args.repeats is not None else (1 if args.quick else 3)
    sensors = args.sensors if args.sensors is not None else (["d435"] if args.quick else list(DEFAULT_SENSORS))
    methods = args.methods if args.methods is not None else default_methods(load_object(args.object))
    if args.methods is None and len(methods) == 1:
        print(f"note: no shipped networks for {args.object!r}; benchmarking the oracle only")
    config = GraspBenchmarkConfig(
        object=args.object,
        methods=tuple(methods),
        poses=tuple(args.poses) if args.poses is not None else tuple(range(len(FIXED_POSES))),
        repeats=repeats,
        random_poses=args.random_poses,
        sensors=tuple(sensors),
        image_size=None if args.image_size is None else parse_size(args.image_size, "--image-size"),
        renderer=args.renderer,
        seed=args.seed,
        backgrounds=args.backgrounds,
    )
    result = run_grasp_benchmark(config, workers=args.workers, progress=not args.no_progress, device=args.device)
    print(outcome_table(result))
    if len(config.sensors) > 1:
        print()
        print(sweep_table(result))
    if config.random_poses:
        print()
        print(outcome_table(result, poses="random"))
    print()
    print(f"{len(result.episodes)} episodes in {result.seconds:.0f} s on {result.workers} worker(s)")
    if args.out is not None:
        paths = write_grasp_outputs(result, args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


BIN_DESCRIPTION = """\
bin: the clearing benchmark. Per method, seeded piles of parts in a bin (DONBinPick-v0, pile i is
reset(seed=SEED+i)) are picked one instance per attempt (a part lifted standing regrasped at the station)
until no target part is left (cleared), the env's failed attempts in a row run out, or its step limit.
Methods: oracle (true poses of the instances seen), oracle-descriptors (the descriptor agent on the pile's
optimal descriptors), shipped network names or checkpoint paths of the target part, or of several parts
including it (the descriptor agent, don_gym.agents.BinAxisGraspAgent). Reported per method, on the same
piles: placed per target instance (the headline), picks and lift success per attempt, piles fully placed,
piles given up, wrong-part lifts, flips, regrasps and their success, each with its 95% Wilson interval;
the pushes (parts rolled away from a wall, not attempts); placements per hour of simulated time (motion and
the method's measured perception time charged) and the ratios to the oracle's. --shard i/n runs piles i, i+n,
... into OUT/shards/; --merge then makes the whole run's outputs.
"""

BIN_EPILOG = """\
examples:
  don-gym benchmark bin --quick --out bench/
  don-gym benchmark bin --piles 40 --methods oracle toolcap/supervised-edge --out bench/
  don-gym benchmark bin --parts toolcap:3,shaft:2 --target shaft --piles 20 --out bench/
  don-gym benchmark bin --piles 100 --shard 0/4 --out bench/   # ... --shard 3/4, then:
  don-gym benchmark bin --merge --out bench/

--out writes bin_episodes.json (summary and one record per episode: method, seed, targets, attempts,
picks, wrong_part_picks, flipped, regrasps, motion_seconds, perception_seconds, ...), bin.md (the table)
and bin_rates.png (the chart).
"""


def register_bin(kinds: argparse._SubParsersAction) -> None:
    parser = kinds.add_parser(
        "bin",
        help="clearing piles of parts from a bin per method: clearance, picks per attempt, wrong-part picks",
        description=BIN_DESCRIPTION,
        epilog=BIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        metavar="MODEL",
        help="oracle, oracle-descriptors, shipped network names or checkpoint paths (default: oracle, "
        "oracle-descriptors and the target part's shipped networks; --quick: the two oracles)",
    )
    parser.add_argument(
        "--parts", default=None, help="the pile, PART:COUNT[,PART:COUNT...] (default: toolcap:3,shaft:2)"
    )
    parser.add_argument("--target", default="toolcap", help="the part to pick (default: toolcap)")
    parser.add_argument("--piles", type=positive_int, default=None, help="piles per method (default: 20; --quick: 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of pile 0; pile i is seed + i (default: 0)")
    parser.add_argument("--sensor", default="d435", help="depth-sensor preset (default: d435)")
    parser.add_argument(
        "--image-size",
        default=None,
        help="wrist camera WIDTHxHEIGHT (default: the size the networks were trained at; 320x240 for the oracles "
        "alone; --quick: 160x120 for the oracles alone)",
    )
    parser.add_argument(
        "--renderer",
        default="tiny",
        help="renderer of the wrist camera's RGB: tiny (TinyRenderer, default), egl (OpenGL) or pbr (path-traced, "
        "the pbr extra)",
    )
    parser.add_argument("--quick", action="store_true", help="2 piles, the two oracles at 160x120 (about a minute)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    parser.add_argument("--device", default="cpu", help="device of the networks: cpu (default), cuda, cuda:N or auto")
    parser.add_argument(
        "--shard",
        default=None,
        metavar="i/n",
        help="run only piles i, i+n, ... into OUT/shards/ (a job array's task); --merge makes the outputs",
    )
    parser.add_argument(
        "--merge", action="store_true", help="make OUT's outputs from the shard files of OUT/shards/, run nothing"
    )
    parser.add_argument("--out", metavar="DIR", default=None, help="write JSON, Markdown and the chart here")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(run=run_bin)


def run_bin(args: argparse.Namespace) -> int:
    import torch

    from don_gym.cli import parse_size
    from don_gym.errors import DonGymError
    from don_gym.evaluation.bin_benchmark import (
        DEFAULT_PARTS,
        ORACLE_DESCRIPTORS_METHOD,
        ORACLE_METHOD,
        BinBenchmarkConfig,
        bin_table,
        check_targets,
        merge_bin_shards,
        parse_parts_counts,
        parse_shard,
        run_bin_benchmark,
        write_bin_outputs,
        write_bin_shard,
    )
    from don_gym.io import check_output_dir
    from don_gym.learning.model import torch_device

    if args.merge:
        if args.out is None or args.shard is not None:
            raise DonGymError("--merge: expected --out DIR (the folder the shards wrote into) and no --shard")
        result = merge_bin_shards(args.out)
        print(bin_table(result))
        paths = write_bin_outputs(result, args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
        return 0
    shard = parse_shard(args.shard) if args.shard is not None else (0, 1)
    if shard[1] > 1 and args.out is None:
        raise DonGymError(f"--shard {args.shard}: expected --out DIR, where the shards and the merge meet")
    if args.workers < 1:
        raise DonGymError(f"--workers {args.workers}: expected at least 1")
    torch_device(args.device)
    if args.out is not None:
        check_output_dir(args.out, "--out")
    torch.set_num_threads(1)
    if args.parts is None:
        parts = DEFAULT_PARTS
    else:
        from don_gym.data.bin_dataset import parse_parts

        parts = parse_parts_counts(parse_parts(args.parts))
    if args.methods is not None:
        methods = list(args.methods)
    elif args.quick:
        methods = [ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD]
    else:
        from don_gym.sim.bin_env import resolve_parts

        models, _, target = resolve_parts(dict(parts), args.target, None)
        methods = default_methods(models[target])
        methods.insert(1, ORACLE_DESCRIPTORS_METHOD)
    image_size = None if args.image_size is None else parse_size(args.image_size, "--image-size")
    if image_size is None and args.quick and set(methods) <= {ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD}:
        image_size = (160, 120)
    config = BinBenchmarkConfig(
        parts=tuple(parts),
        target=args.target,
        methods=tuple(methods),
        piles=args.piles if args.piles is not None else (2 if args.quick else 20),
        seed=args.seed,
        sensor=args.sensor,
        image_size=image_size,
        renderer=args.renderer,
    )
    result = run_bin_benchmark(
        config, workers=args.workers, progress=not args.no_progress, device=args.device, shard=shard
    )
    if shard[1] > 1:
        path = write_bin_shard(result, args.out)
        print(f"shard {shard[0]}/{shard[1]}: {len(result.episodes)} episodes in {result.seconds:.0f} s; wrote {path}")
        return 0
    print(bin_table(result))
    for line in check_targets(result):
        print(line)
    print(f"{len(result.episodes)} episodes in {result.seconds:.0f} s on {result.workers} worker(s)")
    if args.out is not None:
        paths = write_bin_outputs(result, args.out)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0
