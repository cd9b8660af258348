"""``don-gym benchmark imitation``: behaviour cloning at equal demonstrations, one policy class per input."""

from __future__ import annotations

import argparse

from don_gym.cli import positive_int

DESCRIPTION = """\
imitation: behaviour cloning from N demonstrations of the Markov end-effector expert (privileged state,
control="ee") for each input, the same policy class for all (an MLP over the last 2 steps' features: the
robot's TCP pose and finger opening plus the input's; RGB-D images through a convolutional encoder with a
spatial softmax first), evaluated on held-out episodes (reset(seed=100000 + i)) with 95% Wilson intervals.
Inputs: state (the part's true pose, the upper bound), true (its exact keypoints), simulated:NETWORK (the
network's noise model, field of view and depth range), don:NETWORK (the network's keypoints on the wrist
camera at 640x480, in a 192-pixel window), rgbd (wrist RGB-D at 128x96, end-to-end). Keypoint inputs carry
each keypoint's last seen place and age (KeypointMemory). The demonstrations are recorded once (the largest
N) into --out (robomimic's HDF5 layout, docs/demonstrations.md), or taken from --demos.
"""

EPILOG = """\
examples:
  don-gym benchmark imitation --quick --out bench/
  don-gym benchmark imitation --inputs state true don:toolcap/supervised-edge rgbd --demos 10 25 50 100 200 --out bench/
  don-gym benchmark imitation --demos-file bench/demos_toolcap_lift.hdf5 --demos 10 25 --out bench/

--out writes the demonstrations, imitation.md (the table) and imitation.png (success against N, one line per input).
"""

QUICK_INPUTS = ("state", "true", "simulated:toolcap/supervised-edge")


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
    parser.add_argument("--episodes", type=positive_int, default=None, help="evaluation episodes (default 100)")
    parser.add_argument("--train-steps", type=positive_int, default=None, help="gradient steps (default 2000)")
    parser.add_argument(
        "--quick", action="store_true", help=f"inputs {' '.join(QUICK_INPUTS)}, N 5 10, 10 episodes, 300 steps"
    )
    parser.add_argument("--seed", type=int, default=0, help="first demonstration seed and training seed")
    parser.add_argument("--out", metavar="DIR", default=None, help="write demos, Markdown and the figure here")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(run=run_imitation_command)


def run_imitation_command(args: argparse.Namespace) -> int:
    import tempfile
    from pathlib import Path

    import torch

    from don_gym.evaluation.imitation import ImitationConfig, run_imitation
    from don_gym.io import atomic_path, check_output_dir
    from don_gym.plotting import plot_success_against_demonstrations

    if args.out is not None:
        check_output_dir(args.out, "--out")
    torch.set_num_threads(1)
    default = ImitationConfig(part=args.object)
    full_inputs = ("state", "true", f"simulated:{args.object}/supervised-edge", "rgbd")
    inputs = args.inputs or (QUICK_INPUTS if args.quick else full_inputs)
    config = ImitationConfig(
        part=args.object,
        goal=args.goal,
        inputs=tuple(inputs),
        demonstrations=tuple(args.demos or ((5, 10) if args.quick else default.demonstrations)),
        episodes=args.episodes or (10 if args.quick else default.episodes),
        train_steps=args.train_steps or (300 if args.quick else default.train_steps),
        seed=args.seed,
    )
    with tempfile.TemporaryDirectory() as temp:
        work = Path(args.out) if args.out is not None else Path(temp)
        result = run_imitation(config, work, demos=args.demos_file, progress=not args.no_progress)
        table = result.table()
        print(f"{config.part} {config.goal}: success on {config.episodes} held-out episodes (95% Wilson interval)")
        print(table)
        if args.out is not None:
            with atomic_path(work / "imitation.md") as tmp:
                tmp.write_text(table + "\n")
            figure = plot_success_against_demonstrations(
                result.rates(), work / "imitation.png", title=f"behaviour cloning, {config.part} {config.goal}"
            )
            print(f"wrote {work / 'imitation.md'}, {figure}")
    return 0
