"""Behaviour cloning at equal demonstrations per input (``don-gym benchmark imitation``), and what each input costs.

(a) ``--parts comparison``: :func:`don_gym.evaluation.imitation.run_imitation` for every input (true state, the
    part's true keypoints, simulated keypoints and DON keypoints with memory of each shipped network, end-to-end
    RGB-D, a CNN on the supervised network's descriptor images) at N in {10, 25, 50, 100, 200} demonstrations, 100
    held-out episodes each, with the generalisation columns at N = 50 (``background="random"``, the shaft).
    Target (issue 58): the supervised DON keypoints at N = 50 within 10 points of true state. Hours on 2 cores
    (the DON and descriptor inputs render 640x480 and run a network every step).
(b) ``--parts cost``: the wall time of an env step with each input (rendering, sensor model, networks, the policy's
    forward pass), over one episode of an untrained policy per input, beside the load other processes put on the
    machine meanwhile.

    python benchmarks/bench_imitation.py                  # both parts, records "imitation" and "imitation-cost"
    python benchmarks/bench_imitation.py --parts cost     # the cost only (minutes), records "imitation-cost"
    python benchmarks/bench_imitation.py --parts comparison --inputs state true don:toolcap/supervised-edge rgbd
                                                          # some inputs only; the section names those left out
    python benchmarks/bench_imitation.py --quick          # the CLI's --quick comparison, a short cost; no record
    python benchmarks/bench_imitation.py --parts comparison --demos-file WORK/demos_toolcap_lift.hdf5 \
        --other-demos-file WORK/demos_shaft_lift.hdf5     # the demonstrations an earlier --work WORK recorded
    python benchmarks/bench_imitation.py --parts comparison --inputs state rgbd descriptors:toolcap/supervised-edge \
        --record-as imitation-images                      # its own section, figure and README block

The comparison clones and evaluates ``--jobs`` policies at once (default: one per core), each in its own process
with one torch thread; each policy is seeded and its episodes fixed, so the figures do not depend on it.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import (  # noqa: E402
    FIGURES,
    REPO_ROOT,
    BlockMarkersError,
    OtherProcessLoad,
    record_section,
    replace_block,
    require_blocks,
)

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.cli import positive_int  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.evaluation.demonstrations import RecordSettings, read_demonstrations, record_demonstrations  # noqa: E402
from don_gym.evaluation.imitation import (  # noqa: E402
    DEVELOPMENT_EVAL_SEED,
    EVAL_SEED,
    ImitationConfig,
    evaluate_policy,
    run_imitation,
)
from don_gym.evaluation.imitation_policy import train_policy  # noqa: E402
from don_gym.plotting import plot_success_against_demonstrations  # noqa: E402

NETWORKS = ("supervised-edge", "supervised-mask", "self-supervised")
#: The quick comparison: the CLI's --quick.
QUICK = {"inputs": ("state", "true", "simulated:{part}/supervised-edge"), "demonstrations": (10, 25),
         "episodes": 10, "train_steps": 1000, "generalisation_n": 10}  # fmt: skip
TARGET_POINTS = 10.0
README = REPO_ROOT / "README.md"
#: The README block each part writes (outside --quick).
README_BLOCKS = {"comparison": "imitation", "cost": "imitation-cost"}


def readme_block(section: str) -> str | None:
    """The README block that the comparison recorded as ``section`` fills: the main one for ``imitation``, else
    the block of the section's own name where the README has one (None: the README is left as it is)."""
    if section == "imitation":
        return README_BLOCKS["comparison"]
    try:
        require_blocks(README, [section])
    except BlockMarkersError:
        return None
    return section


def all_inputs(part: str) -> list[str]:
    """Every input of the comparison, the supervised network's first."""
    inputs = ["state", "true", f"simulated:{part}/supervised-edge"]
    inputs += [f"don:{part}/{network}" for network in NETWORKS]
    return inputs + ["rgbd", f"descriptors:{part}/supervised-edge"]


def cost(part: str, inputs: list[str], episodes: int, work: Path) -> str:
    """Markdown: the wall time of an env step per input (an untrained policy's episodes, which run to the limit)."""
    path = record_demonstrations(work / "cost.hdf5", part, "lift", 1, seed=0, kinds=inputs, progress=True)
    demos = read_demonstrations(path)
    lines = ["| input | ms / step (wall) | steps timed | other processes' load (cores) |", "|---|---|---|---|"]
    for kind in inputs:
        policy = train_policy(kind, demos, steps=1)
        with OtherProcessLoad() as load:
            evaluation = evaluate_policy(policy, kind, part, "lift", episodes, seed=DEVELOPMENT_EVAL_SEED)
        lines.append(f"| {kind} | {1000 * evaluation.seconds_per_step:.1f} | {evaluation.steps} | {load.describe()} |")
    settings = RecordSettings()
    return "\n".join(
        [
            f'Part `{part}`, lift, `control="ee"`, D435 sensor model; rgbd at {settings.rgbd_size[0]}x'
            f"{settings.rgbd_size[1]}; DON keypoints at {settings.don_size[0]}x{settings.don_size[1]} in a "
            f"{settings.window_px}-pixel window; descriptor images from the whole {settings.don_size[0]}x"
            f"{settings.don_size[1]} frame, area-averaged to {settings.rgbd_size[0]}x{settings.rgbd_size[1]}. "
            f"A step: the observation (rendering, sensor model, networks), the features and the policy's forward "
            f"pass, and the physics; {episodes} episode(s) of an untrained policy per input, "
            f"`reset(seed={DEVELOPMENT_EVAL_SEED} + i)`; torch threads {torch.get_num_threads()}.",
            "",
            *lines,
        ]
    )


def comparison(
    config: ImitationConfig,
    work: Path,
    quick: bool,
    jobs: int,
    demos: str | None,
    other_demos: str | None,
    section: str = "imitation",
) -> str:
    """Markdown: the comparison's table, its target and its figure (``FIGURES/<section>.png``)."""
    result = run_imitation(config, work, demos=demos, progress=True, jobs=jobs, other_demos=other_demos)
    figure = FIGURES / f"{section}.png"
    if not quick:
        plot_success_against_demonstrations(
            result.rates(), figure, title=f"behaviour cloning, {config.part} {config.goal}"
        )
    left_out = [name for name in all_inputs(config.part) if name not in config.inputs]
    lines = [
        f"Part `{config.part}`, {config.goal}; demonstrations of the Markov expert with DART noise "
        f"{config.action_noise} on its motion, seeds from {config.seed}; behaviour cloning {config.train_steps} "
        f"gradient steps per policy, one policy class (an MLP over 2 steps of features; images through a "
        f"spatial-softmax encoder); success on {config.episodes} episodes `reset(seed={config.eval_seed} + i)` with "
        f"95% Wilson intervals. Generalisation columns at N = {config.generalisation_n}: the same policies with "
        f'`background="random"`, and the recipe on the shaft (its demonstrations, its networks). ms / step: the '
        f"wall time of an evaluation step with the input, {jobs} policies cloned and evaluated at once (`--jobs`, "
        f"one torch thread each; the cost table below times each input alone).",
        *(["", f"Inputs not run this time (`--inputs`): {', '.join(f'`{n}`' for n in left_out)}"
               + ("." if section == "imitation" else "; the section `imitation` has the others.")]
          if left_out and not quick else []),
        "",
        result.table(),
    ]  # fmt: skip
    state, don = result.wins.get("state", {}), result.wins.get(f"don:{config.part}/supervised-edge", {})
    if 50 in state and 50 in don:
        gap = 100.0 * (state[50] - don[50]) / config.episodes
        verdict = "met" if gap <= TARGET_POINTS else "NOT met"
        lines += ["", f"Target: supervised DON keypoints at N = 50 within {TARGET_POINTS:.0f} points of true state: "
                      f"{gap:.0f} points, {verdict}."]  # fmt: skip
    if not quick:
        lines += ["", f"![success against demonstrations]({figure.relative_to(REPO_ROOT)})"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", choices=("comparison", "cost"), default=["comparison", "cost"])
    parser.add_argument("--part", default="toolcap", choices=("toolcap", "shaft"))
    parser.add_argument("--quick", action="store_true", help="the CLI's --quick comparison, a short cost; no record")
    parser.add_argument("--split", choices=("test", "dev"), default="test", help="evaluation episodes")
    parser.add_argument("--work", default=None, help="keep the demonstrations here (default: a temporary folder)")
    parser.add_argument(
        "--inputs", nargs="+", default=None, metavar="INPUT",
        help="run the comparison for these of its inputs only (the recorded section names those left out; "
        "the cost part always times every input); default: all of "
        "state, true, simulated:<part>/supervised-edge, don:<part>/<network> for each shipped network, rgbd, "
        "descriptors:<part>/supervised-edge",
    )  # fmt: skip
    parser.add_argument(
        "--demos-file", default=None, metavar="HDF5",
        help="the part's demonstrations, recorded before (e.g. WORK/demos_toolcap_lift.hdf5 of an earlier --work), "
        "instead of recording them; checked for the part, the task, 200 demonstrations and every input",
    )  # fmt: skip
    parser.add_argument(
        "--other-demos-file", default=None, metavar="HDF5",
        help="likewise the other part's, for the generalisation column (e.g. WORK/demos_shaft_lift.hdf5)",
    )  # fmt: skip
    parser.add_argument(
        "--record-as", default="imitation", metavar="SECTION",
        help="record the comparison as this RESULTS.md section, with its figure benchmarks/figures/SECTION.png "
        "(default: imitation; another name leaves that section as it is, for an input run on its own beside state as "
        "its baseline); the README block of the same name is filled where the README has one",
    )  # fmt: skip
    parser.add_argument(
        "--jobs", type=positive_int, default=None, metavar="N",
        help="clone and evaluate N policies at once, one process each (default: one per core); the figures do not "
        "depend on it",
    )  # fmt: skip
    args = parser.parse_args(argv)
    jobs = args.jobs or len(os.sched_getaffinity(0))
    every = all_inputs(args.part)
    if args.inputs is not None:
        unknown = [name for name in args.inputs if name not in every]
        if unknown or args.quick:
            parser.exit(2, f"bench_imitation.py: error: --inputs {' '.join(args.inputs)}: "
                           + (f"expected some of {every}\n" if unknown else "not with --quick\n"))  # fmt: skip
    if not re.fullmatch(r"imitation(-[a-z0-9]+)*", args.record_as):
        parser.exit(2, f"bench_imitation.py: error: --record-as {args.record_as!r}: expected imitation or "
                       "imitation-<lowercase words with dashes>\n")  # fmt: skip
    inputs = every if args.inputs is None else [name for name in every if name in args.inputs]
    torch.set_num_threads(1)
    if not args.quick:
        require_blocks(README, [README_BLOCKS[part] for part in args.parts])
    eval_seed = DEVELOPMENT_EVAL_SEED if args.split == "dev" else EVAL_SEED
    with tempfile.TemporaryDirectory() as temp:
        work = Path(args.work or temp)
        work.mkdir(parents=True, exist_ok=True)
        if "cost" in args.parts:
            timed = [k.format(part=args.part) for k in QUICK["inputs"]] if args.quick else every
            body = cost(args.part, timed, 1, work)
            print(body)
            if not args.quick:
                record_section("imitation-cost", "Imitation inputs: the cost of an env step (bench_imitation)", body)
                replace_block(README, README_BLOCKS["cost"], body.split("\n\n", 1)[1])
        if "comparison" in args.parts:
            if args.quick:
                preset = {**QUICK, "inputs": tuple(k.format(part=args.part) for k in QUICK["inputs"])}
                config = ImitationConfig(part=args.part, eval_seed=eval_seed, **preset)
            else:
                config = ImitationConfig(part=args.part, inputs=tuple(inputs), generalisation_n=50, eval_seed=eval_seed)
            body = comparison(config, work, args.quick, jobs, args.demos_file, args.other_demos_file, args.record_as)
            print(body)
            if not args.quick:
                own = args.record_as == "imitation"
                title = "Behaviour cloning at equal demonstrations (bench_imitation)"
                record_section(args.record_as, title if own else f"{title}: {', '.join(config.inputs)}", body,
                               after=None if own else "imitation")  # fmt: skip
                block = readme_block(args.record_as)
                if block is not None:
                    replace_block(README, block, body)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except DonGymError as exc:  # a bad --demos-file, --other-demos-file: one line, no traceback
        sys.exit(f"bench_imitation.py: {exc}")
