"""``don-gym benchmark imitation``: behaviour cloning at equal demonstrations, one policy class per input."""

from __future__ import annotations

import argparse

from don_gym.cli import positive_int

DESCRIPTION = """\
imitation: behaviour cloning from N demonstrations of the Markov end-effector expert (privileged state, control="ee",
run with DART noise on its motion) for each input, the same policy class for all (an MLP over the last 2 steps'
features: the robot's TCP pose, wrist angle and finger opening plus the input's; images, each channel standardised,
through a convolutional encoder with a spatial softmax first), evaluated on held-out episodes (reset(seed=100000 + i);
--split dev: the development episodes, reset(seed=50000 + i)) with 95% Wilson intervals. Inputs: state (the part's
true pose with its grasp point and axis, the upper bound), true (its exact keypoints), simulated:NETWORK (the
network's noise model, field of view and depth range), don:NETWORK (the network's keypoints on the wrist camera at
640x480, in a 192-pixel window), rgbd (wrist RGB-D at 128x96, end-to-end), descriptors:NETWORK (the network's
descriptor image of the wrist camera at 640x480, area-averaged to 128x96, through the same encoder as rgbd). Keypoint
inputs carry each keypoint's last seen place and age (KeypointMemory). Generalisation columns at one N
(--generalisation-n): the same policies with background="random", and the recipe repeated on the other built-in part
(the shaft for the toolcap: its demonstrations, its networks). The demonstrations are recorded once (the largest N)
into --out (robomimic's HDF5 layout, docs/demonstrations.md), or taken from --demos-file.
"""

EPILOG = """\
examples:
  don-gym benchmark imitation --quick --out bench/
  don-gym benchmark imitation --inputs state true don:toolcap/supervised-edge rgbd \
      descriptors:toolcap/supervised-edge --demos 10 25 50 100 200 --out bench/
  don-gym benchmark imitation --demos-file bench/demos_toolcap_lift.hdf5 --demos 10 25 --out bench/

--out writes the demonstrations, imitation.md (the table) and imitation.png (success against N, one line per input).
"""

QUICK_INPUTS = ("state", "true", "simulated:toolcap/supervised-edge")
#: The N of the generalisation columns unless --generalisation-n says.
GENERALISATION_N = 50
#: --quick: N, evaluation episodes, gradient steps, generalisation N.
QUICK = {"demonstrations": (10, 25), "episodes": 10, "train_steps": 1000, "generalisation_n": 10}


def register_imitation(kinds: argparse._SubParsersAction) -> None:
    parser = kinds.add_parser(
        "imitation",
        help="behaviour cloning at equal demonstrations for each input (state, keypoints, RGB-D)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--object", default="toolcap", help="built-in part (default: toolcap)")
    parser.add_argument("--goal", default="lift", choices=("lift", "place"), help="the task (default: lift)")
    parser.add_argument("--inputs", nargs="+", default=None, metavar="INPUT", help="inputs (default: all but don:)")
    parser.add_argument("--demos", nargs="+", type=positive_int, default=None, metavar="N", help="numbers of demos")
    parser.add_argument("--demos-file", default=None, help="recorded demonstrations to use instead of recording")
    parser.add_argument(
        "--other-demos-file", default=None,
        help="the other part's recorded demonstrations for the generalisation column, instead of recording them",
    )  # fmt: skip
    parser.add_argument("--episodes", type=positive_int, default=None, help="evaluation episodes (default 100)")
    parser.add_argument("--train-steps", type=positive_int, default=None, help="gradient steps (default 4000)")
    parser.add_argument(
        "--action-noise", type=float, default=None, help="DART noise on the expert's motion (default 0.1, action units)"
    )
    parser.add_argument(
        "--generalisation-n", type=positive_int, default=None,
        help="the N of the generalisation columns, one of --demos (default 50, or none if 50 is not among them)",
    )  # fmt: skip
    parser.add_argument("--no-generalisation", action="store_true", help="no generalisation columns")
    parser.add_argument("--split", choices=("test", "dev"), default="test", help="evaluation episodes (default test)")
    parser.add_argument(
        "--quick", action="store_true",
        help=f"inputs {' '.join(QUICK_INPUTS)}, N {' '.join(map(str, QUICK['demonstrations']))}, {QUICK['episodes']} "
        f"episodes, {QUICK['train_steps']} steps, generalisation at N {QUICK['generalisation_n']}",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="first demonstration seed and training seed")
    parser.add_argument("--out", metavar="DIR", default=None, help="write demos, Markdown and the figure here")
    parser.add_argument(
        "--jobs", type=positive_int, default=None, metavar="N",
        help="clone and evaluate N policies at once, one process each with one torch thread (default: one per "
        "core); the figures do not depend on it",
    )  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(run=run_imitation_command)


def run_imitation_command(args: argparse.Namespace) -> int:
    import os
    import tempfile
    from pathlib import Path

    import torch

    from don_gym.evaluation.imitation import DEVELOPMENT_EVAL_SEED, EVAL_SEED, ImitationConfig, run_imitation
    from don_gym.io import atomic_path, check_output_dir
    from don_gym.plotting import plot_success_against_demonstrations

    if args.out is not None:
        check_output_dir(args.out, "--out")
    torch.set_num_threads(1)

    default = ImitationConfig(part=args.object)
    full_inputs = ("state", "true", f"simulated:{args.object}/supervised-edge", "rgbd")
    inputs = args.inputs or (QUICK_INPUTS if args.quick else full_inputs)
    preset = QUICK if args.quick else {}
    demonstrations = tuple(args.demos or preset.get("demonstrations", default.demonstrations))
    generalisation_n = args.generalisation_n or preset.get("generalisation_n", GENERALISATION_N)
    if args.no_generalisation or (args.generalisation_n is None and generalisation_n not in demonstrations):
        generalisation_n = None  # the default N is not among those asked for: no columns rather than an error
    config = ImitationConfig(
        part=args.object,
        goal=args.goal,
        inputs=tuple(inputs),
        demonstrations=demonstrations,
        episodes=args.episodes or preset.get("episodes", default.episodes),
        train_steps=args.train_steps or preset.get("train_steps", default.train_steps),
        seed=args.seed,
        action_noise=default.action_noise if args.action_noise is None else args.action_noise,
        generalisation_n=generalisation_n,
        eval_seed=DEVELOPMENT_EVAL_SEED if args.split == "dev" else EVAL_SEED,
    )
    with tempfile.TemporaryDirectory() as temp:
        work = Path(args.out) if args.out is not None else Path(temp)
        jobs = args.jobs or len(os.sched_getaffinity(0))
        result = run_imitation(
            config, work, demos=args.demos_file, progress=not args.no_progress, jobs=jobs,
            other_demos=args.other_demos_file,
        )  # fmt: skip
        table = result.table()
        episodes = "development" if args.split == "dev" else "held-out"
        print(f"{config.part} {config.goal}: success on {config.episodes} {episodes} episodes (95% Wilson interval)")
        print(table)
        if args.out is not None:
            with atomic_path(work / "imitation.md") as tmp:
                tmp.write_text(table + "\n")
            figure = plot_success_against_demonstrations(
                result.rates(), work / "imitation.png", title=f"behaviour cloning, {config.part} {config.goal}"
            )
            print(f"wrote {work / 'imitation.md'}, {figure}")
    return 0
