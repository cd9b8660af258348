"""Clearing piles from a bin (issue 33 item 7): piles of 3 toolcaps + 2 shafts, target toolcap, D435 wrist camera.

Per method (the oracle with the true poses of the instances it sees, the descriptor agent on the pile's optimal
descriptors, the toolcap's shipped networks, and the multi-part networks given with ``--multi-part``), the same
seeded piles are picked one instance per step (:func:`don_gym.bin_benchmark.run_bin_benchmark`): piles cleared,
picks per attempt, wrong-part picks and flipped placements, each with its 95% Wilson interval. The piles are the bin
test piles (from :data:`don_gym.evaluation.BIN_TEST_SEED`, used for no decision); ``--split dev`` runs the
development piles (from :data:`~don_gym.evaluation.BIN_DEVELOPMENT_SEED`) into section ``bin-dev``. Records
RESULTS.md section ``bin`` with the issue's targets checked: the oracle clears >= 95% of piles; a supervised network
of several parts reaches >= 85% picks per attempt with wrong-part picks <= 2% of picks. The chart goes to
``benchmarks/figures/bin_rates.png``; the raw outputs to ``--work``.

    python benchmarks/bench_bin.py --multi-part runs/bin/supervised-edge.safetensors   # test piles, section "bin"
    python benchmarks/bench_bin.py --quick        # 2 development piles, the two oracles, temp dir, records nothing
    python benchmarks/bench_bin.py --split dev    # development piles, section "bin-dev"
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _results import FIGURES, freeze_commit_description, record_section  # noqa: E402

from don_gym.bin_benchmark import (  # noqa: E402
    ORACLE_DESCRIPTORS_METHOD,
    ORACLE_METHOD,
    BinBenchmarkConfig,
    bin_table,
    check_targets,
    run_bin_benchmark,
    write_bin_outputs,
)
from don_gym.evaluation import BIN_DEVELOPMENT_SEED, BIN_TEST_SEED  # noqa: E402
from don_gym.grasp_benchmark import default_methods  # noqa: E402
from don_gym.objects import load_object  # noqa: E402
from don_gym.zoo import shipped_names_for  # noqa: E402

PARTS = (("toolcap", 3), ("shaft", 2))
TARGET = "toolcap"
SENSOR = "d435"
#: Piles per method of the full run: enough that 95% clearance is told from 85% (Wilson intervals).
PILES = 60
QUICK_PILES = 2
SPLIT_SEED = {"test": BIN_TEST_SEED, "dev": BIN_DEVELOPMENT_SEED}


def methods(multi_part: list[str], quick: bool) -> list[str]:
    """The oracle, the descriptor agent on optimal descriptors, the target's shipped networks, the multi-part ones."""
    if quick:
        return [ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD, *multi_part]
    shipped = set(shipped_names_for(load_object(TARGET)))
    own = [m for m in default_methods(TARGET) if m in shipped]
    return [ORACLE_METHOD, ORACLE_DESCRIPTORS_METHOD, *own, *multi_part]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--multi-part",
        nargs="*",
        default=[],
        metavar="CHECKPOINT",
        help="networks of several parts (trained on bin datasets) benchmarked beside the single-part ones",
    )
    parser.add_argument(
        "--split",
        choices=("test", "dev"),
        default=None,
        help="the test piles (default) or the development piles (section bin-dev; the default of --quick)",
    )
    parser.add_argument("--piles", type=int, default=None, help=f"piles per method (default: {PILES})")
    parser.add_argument("--quick", action="store_true", help="2 development piles, the two oracles; records nothing")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    parser.add_argument("--device", default="cpu", help="device of the networks (default: cpu)")
    parser.add_argument("--work", default="bench_work/bin", help="folder for the raw outputs (default: bench_work/bin)")
    args = parser.parse_args()
    split = args.split or ("dev" if args.quick else "test")
    piles = args.piles if args.piles is not None else (QUICK_PILES if args.quick else PILES)
    freeze_commit_description()
    chosen = methods(list(args.multi_part), args.quick)
    config = BinBenchmarkConfig(
        parts=PARTS,
        target=TARGET,
        methods=tuple(chosen),
        piles=piles,
        seed=SPLIT_SEED[split],
        sensor=SENSOR,
        # The oracles alone in a quick run: a small camera; otherwise the networks' training size.
        image_size=(160, 120) if args.quick and not args.multi_part else None,
    )
    work = Path(tempfile.mkdtemp(prefix="don_gym_bench_bin_")) if args.quick else Path(args.work) / split
    try:
        result = run_bin_benchmark(config, workers=args.workers, progress=not args.quick, device=args.device)
        paths = write_bin_outputs(result, work)
        table = bin_table(result)
        targets = check_targets(result)
        if not args.multi_part:
            targets.append("no network of several parts given (--multi-part): its targets are not checked")
        body = (
            f"Piles of 3 toolcaps + 2 shafts, target toolcap, sensor {SENSOR}, {split} piles "
            f"(seeds {config.seed}-{config.seed + piles - 1}); {len(result.episodes)} episodes in "
            + (f"{result.seconds:.0f} s" if result.seconds < 120 else f"{result.seconds / 60:.0f} min")
            + f" on {result.workers} worker(s).\n\n"
            + table
            + "\n\nThe issue's targets:\n\n"
            + "\n".join(f"- {line}" for line in targets)
            + "\n"
        )
        print(body)
        if args.quick:
            print("quick run: nothing recorded")
            return
        if split == "test":
            FIGURES.mkdir(parents=True, exist_ok=True)
            figure = FIGURES / "bin_rates.png"
            shutil.copyfile(paths["chart"], figure)
            body += f"\nFigure: `benchmarks/figures/{figure.name}` (each rate per method, with its interval).\n"
            record_section("bin", "Clearing piles from a bin (test piles)", body)
        else:
            record_section("bin-dev", "Clearing piles from a bin (development piles)", body, after="bin")
    finally:
        if args.quick:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
