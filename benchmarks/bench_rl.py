"""Short-budget RL baselines (stable-baselines3): PPO on ``control="grasp"``, SAC on ``control="ee"``.

Both policies see the toolcap only through DON keypoints (the two axis-end keypoints of
:class:`don_gym.wrappers.KeypointObservation`), never its true pose; see ``don_gym.agents.rl``.

- PPO: one grasp-and-place per env step (a one-step episode), keypoint-centred normalised
  actions, dense reward for training; ``--ppo-steps`` episodes.
- SAC: 25 Hz Cartesian control from the robot state and the keypoints of the current wrist
  image, dense reward, ``--sac-max-steps`` steps per episode; ``--sac-steps`` env steps.

Each is then evaluated with its deterministic policy on the same seeded held-out episodes
(``reset(seed=EVAL_SEED + i)``) as its baselines, run here too: for PPO a uniform random policy
in the same keypoint-centred action frame, a uniform random grasp in the env's whole action box,
the scripted ``AxisGraspAgent`` on the same keypoint model and images, and
the true-pose oracle grasp (upper bound); for SAC a uniform random policy. The success rate is
``info["is_success"]`` (grasp_and_place) at the end of each episode, with a 95 % Wilson interval.

Learning curves (rolling success rate and return of the training episodes against env steps)
go to ``benchmarks/figures/rl_ppo_grasp.png`` and ``rl_sac_ee.png``; results to the "rl" section
of ``benchmarks/RESULTS.md`` (not with ``--quick``). One torch thread (see CONTRIBUTING).

    python benchmarks/bench_rl.py                      # full run (~50 min on 2 cores at 640x480), records RESULTS.md
    python benchmarks/bench_rl.py --only ppo           # one algorithm (records only with both)
    python benchmarks/bench_rl.py --quick              # smoke run, records nothing
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record_section  # noqa: E402

from don_gym.agents import AxisGraspAgent, rl  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.zoo import read_don_metadata, shipped_names  # noqa: E402

FIGURES = Path(__file__).resolve().parent / "figures"
#: Held-out evaluation episodes are reset with EVAL_SEED + i; training envs draw from seed + i.
EVAL_SEED = 100_000
#: Preferred keypoint model: the shipped supervised network; the oracle until it exists.
PREFERRED_MODEL = "toolcap/supervised-edge"
ORACLE_IMAGE_SIZE = (160, 120)  # no network to match: small images keep the oracle runs cheap


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def _row(name: str, result: rl.EvaluationResult) -> str:
    n = len(result.successes)
    wins = int(sum(result.successes))
    lo, hi = wilson_interval(wins, n)
    counts = result.outcome_counts()
    per_episode = result.wall_s / max(n, 1)
    return (
        f"| {name} | {wins}/{n} = {result.success_rate:.0%} | {lo:.0%}-{hi:.0%} | {counts['grasp_only']} | "
        f"{counts['fail']} | {result.mean_return:.2f} | {per_episode:.2f} |"
    )


TABLE_HEAD = (
    "| policy | success (grasp_and_place) | 95 % interval | grasp_only | fail | mean return | s / episode |\n"
    "|---|---|---|---|---|---|---|"
)


def _axis_grasp_policy(keypoint_model: str, env_kwargs: dict[str, Any]) -> tuple[Any, Any]:
    """(env, policy) of the scripted AxisGraspAgent on the same keypoint model and images."""
    env = gym.make(
        "DONPick-v0",
        object="toolcap",
        control="grasp",
        image_size=env_kwargs["image_size"],
        sensor=env_kwargs["sensor"],
    )
    agent = AxisGraspAgent(env, model=keypoint_model)
    return agent.env, agent.act


def run_ppo(args: argparse.Namespace, keypoint_model: str) -> tuple[str, dict[str, Any]]:
    env_kwargs = {
        "keypoint_model": keypoint_model,
        "image_size": tuple(args.ppo_image_size),
        "sensor": args.sensor,
        "reward_type": "dense",
        "action_frame": "keypoints",
    }
    # Keep the rollout (steps per PPO update) the same whatever the number of envs.
    n_steps = max(1, rl.DEFAULT_ALGO_KWARGS["ppo"]["n_steps"] // args.ppo_envs)
    trained = rl.train(
        "ppo", args.ppo_steps, args.seed, args.ppo_envs, env_kwargs=env_kwargs, algo_kwargs={"n_steps": n_steps}
    )
    env = rl.make_ppo_env(**env_kwargs)
    n = args.ppo_eval_episodes
    results = {"PPO (deterministic)": rl.evaluate(env, rl.model_policy(trained.model), n, EVAL_SEED, "eval PPO")}
    results["random, keypoint frame"] = rl.evaluate(
        env, rl.random_policy(env.action_space, args.seed), n, EVAL_SEED, "eval random (keypoint frame)"
    )
    # A bare env for the policies that act in the env's own action space: same seeds, same episodes.
    base = gym.make(
        "DONPick-v0", object="toolcap", control="grasp", image_size=env_kwargs["image_size"], sensor=args.sensor,
        reward_type="dense",
    ).unwrapped  # fmt: skip
    results["random, whole action box"] = rl.evaluate(
        base, rl.random_policy(base.action_space, args.seed), n, EVAL_SEED, "eval random (box)"
    )
    axis_env, axis_policy = _axis_grasp_policy(keypoint_model, env_kwargs)
    results["AxisGraspAgent (scripted)"] = rl.evaluate(axis_env, axis_policy, n, EVAL_SEED, "eval AxisGraspAgent")
    axis_env.close()
    results["oracle grasp (true pose)"] = rl.evaluate(
        base, lambda _obs: base.oracle_action(), n, EVAL_SEED, "eval oracle"
    )
    env.close()
    base.close()

    curve = trained.curve
    window = max(10, min(50, len(curve.successes) // 5))
    reference = [(f"eval: {name}", r.success_rate, r.mean_return) for name, r in results.items()]
    figure = args.figures / "rl_ppo_grasp.png"
    rl.plot_learning_curve(
        [("PPO training episodes (stochastic policy)", curve)],
        figure,
        window,
        f"PPO, control='grasp', keypoints from {keypoint_model}",
        reference_lines=reference,
    )
    last = curve.successes[-window:]
    n_episodes = len(curve.successes)
    body = [
        f'**PPO on `control="grasp"`**: {args.ppo_steps} training env steps = {n_episodes} grasp-and-place '
        f"episodes (one step each), {trained.wall_s / 60:.1f} min ({trained.wall_s / max(args.ppo_steps, 1):.2f} s "
        f"per episode, {args.ppo_envs} env(s)); success rate of the last {window} training episodes "
        f"(stochastic policy): {np.mean(last):.0%}. Keypoints: `{keypoint_model}`, "
        f"{env_kwargs['image_size'][0]}x{env_kwargs['image_size'][1]} images, sensor `{args.sensor}`; dense "
        f"reward; keypoint-centred actions; PPO rollouts of {n_steps * args.ppo_envs} steps, "
        f"batch {rl.DEFAULT_ALGO_KWARGS['ppo']['batch_size']}, "
        f"{rl.DEFAULT_ALGO_KWARGS['ppo']['n_epochs']} epochs, MLP 64x64, seed {args.seed}. "
        f"Learning curve: `{_shown(figure)}`.",
        "",
        f"Evaluation on the same {n} held-out episodes (seeds {EVAL_SEED}..{EVAL_SEED + n - 1}):",
        "",
        TABLE_HEAD,
        *[_row(name, result) for name, result in results.items()],
    ]
    summary = {name: r.success_rate for name, r in results.items()}
    return "\n".join(body), summary


def run_sac(args: argparse.Namespace, keypoint_model: str) -> tuple[str, dict[str, Any]]:
    env_kwargs = {
        "keypoint_model": keypoint_model,
        "image_size": tuple(args.sac_image_size),
        "sensor": args.sensor,
        "reward_type": "dense",
        "max_steps": args.sac_max_steps,
    }
    sac = rl.DEFAULT_ALGO_KWARGS["sac"] | {"learning_starts": args.sac_learning_starts}
    # One env in this process: SAC takes a gradient step per env step, so a second env would halve them.
    trained = rl.train("sac", args.sac_steps, seed=args.seed, n_envs=1, env_kwargs=env_kwargs, algo_kwargs=sac)
    env = rl.make_sac_env(**env_kwargs)
    n = args.sac_eval_episodes
    results = {
        "SAC (deterministic)": rl.evaluate(env, rl.model_policy(trained.model), n, EVAL_SEED, "eval SAC"),
        "random": rl.evaluate(env, rl.random_policy(env.action_space, args.seed), n, EVAL_SEED, "eval random"),
    }
    env.close()
    curve = trained.curve
    window = max(3, min(20, len(curve.successes) // 5))
    figure = args.figures / "rl_sac_ee.png"
    rl.plot_learning_curve(
        [("SAC training episodes (stochastic policy)", curve)],
        figure,
        window,
        f"SAC, control='ee', keypoints from {keypoint_model}",
        reference_lines=[(f"eval: {name}", r.success_rate, r.mean_return) for name, r in results.items()],
    )
    body = [
        f'**SAC on `control="ee"`**: {args.sac_steps} training env steps (25 Hz) = {len(curve.successes)} '
        f"episodes of at most {args.sac_max_steps} steps, {trained.wall_s / 60:.1f} min "
        f"({1000 * trained.wall_s / max(args.sac_steps, 1):.0f} ms per step including the gradient step). "
        f"Observation: TCP pose, gripper width and the keypoints of the current wrist image "
        f"(`{keypoint_model}`, {env_kwargs['image_size'][0]}x{env_kwargs['image_size'][1]}, sensor `{args.sensor}`); "
        f"dense reward; SAC learning starts {sac['learning_starts']}, batch {sac['batch_size']}, MLP 128x128, "
        f"seed {args.seed}. Learning curve: `{_shown(figure)}`.",
        "",
        f"Evaluation on the same {n} held-out episodes (seeds {EVAL_SEED}..{EVAL_SEED + n - 1}); "
        "grasp_only here means the part was lifted at some point but did not end at rest in the cradle:",
        "",
        TABLE_HEAD,
        *[_row(name, result) for name, result in results.items()],
    ]
    return "\n".join(body), {name: r.success_rate for name, r in results.items()}


def _shown(figure: Path) -> str:
    """A figure's path as RESULTS.md names it (relative to the repository), or as written."""
    return f"benchmarks/figures/{figure.name}" if figure.parent == FIGURES else str(figure)


def keypoint_image_size(keypoint_model: str) -> tuple[int, int]:
    """(width, height) the keypoint network was trained at; 160x120 for the oracle (no network)."""
    if keypoint_model == "oracle":
        return ORACLE_IMAGE_SIZE
    # The benchmark's envs show the toolcap: a network for another part is refused here, before training.
    return tuple(read_don_metadata(keypoint_model, expect_object="toolcap").image_size)


def _pixels(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive number of pixels")
    return value


def _add_image_size_option(parser: argparse.ArgumentParser, algorithm: str) -> None:
    parser.add_argument(
        f"--{algorithm}-image-size",
        type=_pixels,
        nargs=2,
        default=None,
        metavar=("W", "H"),
        help="wrist camera size (default: the size the keypoint network was trained at; 160x120 for the oracle)",
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=rl.ALGORITHMS, help="run one algorithm (then nothing is recorded)")
    parser.add_argument(
        "--keypoint-model", default=None, help=f"default: {PREFERRED_MODEL!r} if shipped, else 'oracle'"
    )
    parser.add_argument("--sensor", default="d435")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--ppo-envs", type=int, default=2, help="PPO envs, in subprocesses when > 1 (SAC: always one env in-process)"
    )
    parser.add_argument("--ppo-steps", type=int, default=1024, help="grasp episodes (one env step each)")
    parser.add_argument("--ppo-eval-episodes", type=int, default=50)
    _add_image_size_option(parser, "ppo")
    parser.add_argument("--sac-steps", type=int, default=10000)
    parser.add_argument("--sac-max-steps", type=int, default=100)
    parser.add_argument("--sac-learning-starts", type=int, default=rl.DEFAULT_ALGO_KWARGS["sac"]["learning_starts"])
    parser.add_argument("--sac-eval-episodes", type=int, default=20)
    _add_image_size_option(parser, "sac")
    parser.add_argument("--quick", action="store_true", help="tiny budgets, records nothing")
    args = parser.parse_args(argv)
    rl.require_sb3()
    torch.set_num_threads(1)
    if args.quick:
        args.ppo_steps, args.ppo_eval_episodes = 32, 4
        args.sac_steps, args.sac_max_steps, args.sac_eval_episodes, args.sac_learning_starts = 300, 50, 2, 100
    # Runs that record nothing keep their figures out of benchmarks/figures too.
    args.figures = FIGURES if not (args.quick or args.only) else Path(tempfile.mkdtemp(prefix="don_gym_rl_"))
    keypoint_model = args.keypoint_model or (PREFERRED_MODEL if PREFERRED_MODEL in shipped_names() else "oracle")
    if keypoint_model == "oracle":
        print("keypoints from the oracle (true-pose descriptors): a pipeline check, not a perception result")
    # A DON is not scale invariant: by default the camera shows the part at the network's training size.
    try:
        default_size = keypoint_image_size(keypoint_model)
    except DonGymError as exc:  # unknown name, checkpoint for another object: say so before any training
        parser.error(str(exc))
    args.ppo_image_size = tuple(args.ppo_image_size or default_size)
    args.sac_image_size = tuple(args.sac_image_size or default_size)

    start = time.perf_counter()
    sections, summary = [], {}
    for algorithm, runner in (("ppo", run_ppo), ("sac", run_sac)):
        if args.only in (None, algorithm):
            text, rates = runner(args, keypoint_model)
            sections.append(text)
            summary |= rates
    oracle_note = (
        " The keypoints come from the oracle (descriptors rendered from the true pose): this checks the "
        "pipeline, it is not a perception result."
        if keypoint_model == "oracle"
        else ""
    )
    intro = (
        "stable-baselines3 baselines on the toolcap with a short CPU budget; the policies see the part only "
        f"through the two axis-end DON keypoints from `{keypoint_model}`.{oracle_note} Success = "
        "`info['is_success']` (grasp_and_place) at the end of an episode. Budgets are far below what these "
        "algorithms usually need: read the numbers as where a short run gets, not as what RL can reach."
    )
    body = intro + "\n\n" + "\n\n".join(sections) + f"\n\nTotal wall time {(time.perf_counter() - start) / 60:.1f} min."
    print(body)
    if args.quick or args.only is not None:
        print("(--quick or --only: RESULTS.md not updated)")
    else:
        record_section("rl", "RL baselines (stable-baselines3)", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
