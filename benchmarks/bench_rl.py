"""RL baselines (stable-baselines3) on the toolcap, seeing the part only through its two axis-end keypoints.

Parts (``--only``, repeatable; all by default):

- ``throughput``: env steps/s of ``control="ee"`` with DON keypoints for 1, 4 and 8 envs, the DON run per
  env (today's wrappers) and once per step on all envs' images (``VectorKeypointObservation``), same run.
- ``ppo``: PPO on ``control="grasp"`` with residual actions in the keypoints' axis frame, from DON keypoints,
  and from a model of the DON (``SimulatedKeypoints``, no rendering) evaluated with the real DON (transfer).
  Baselines on the same held-out episodes: random, the scripted ``AxisGraspAgent``, the true-pose grasp.
- ``sac``: SAC with HER on ``control="ee"`` (goal ``--sac-goal``: the ``lift`` sub-task by default, the full
  ``place`` task being beyond this budget), learning curves from simulated keypoints, DON keypoints and the
  true keypoints side by side; the simulated-keypoint policy is also evaluated with the DON (transfer).
  Training episodes start in shares ``--sac-hand-starts`` with the hand at or on the part (``HandStarts``,
  the HER paper's device); every policy is evaluated from the task's start and with the part in the hand.

PPO from descriptor images with actions in the whole action box is no longer a part: it learned nothing in 1024
episodes (0%, random actions hit the grasp tolerance about once in 10^4), and pixel PPO in the field needs about
10^7 env steps with a shaped reward, some ten days of env steps alone at the ~85 ms a descriptor-image step costs
on 2 cores (RESULTS.md, "imitation-cost"). Policies from descriptor images are compared where demonstrations make
them learnable: ``benchmarks/bench_imitation.py`` (README, "Policy learning").

Every policy is evaluated on the same held-out seeds (``reset(seed=EVAL_SEED + i)``) with 95 % Wilson
intervals. Every training run writes its learning curve (CSV, PNG), configuration and seeds (JSON) and
periodic saves into ``--out`` (``runs/rl`` by default, a temporary directory with ``--quick``);
``--resume`` continues interrupted runs there. The training runs of all parts run ``--jobs`` at a time (one
process each, one torch thread each: the same runs as one after the other; by default as many as there are
CPUs), then each part evaluates. Figures go to ``benchmarks/figures/``, results to one section of
``benchmarks/RESULTS.md`` per part that ran (``rl-throughput``, ``rl-ppo``, ``rl-sac``; not with
``--quick``); a part run with settings other than the defaults (e.g. the longer recipes below) records into
``rl-<part>-custom`` and ``<figure>_custom.png`` instead (with ``--section KEY``: that section and
``<figure>_<KEY>.png``), beside the default run's figures.

    python benchmarks/bench_rl.py                      # full CPU run, all parts (~1.5 h on 2 cores)
    python benchmarks/bench_rl.py --only sac --resume  # one part, continuing its runs in runs/rl
    python benchmarks/bench_rl.py --quick              # smoke run of every part (a few minutes), records nothing

Longer CPU recipe for the SAC part, continuing the default runs in ``runs/rl`` (a finished run is only evaluated
again): the DON-keypoint run from its 20,000 default steps to 40,000 (~60 min more on 2 cores), the simulated and
true runs from 40,000 to 80,000 (~40 min more), at which the true-keypoint policy also lifts from the task's own
start, then the DON-keypoint run to 60,000 and 80,000 (~60 min more each), at which the DON-trained policy lifts
the part from the hand as the others do (recorded 2026-11-30 at commit c13dabf, beside the default budgets'
"rl-sac": true 75% from the task's start; DON-trained from the hand 25% at 40,000, 65% at 60,000, 100% at 80,000;
random 10%). Times are of the runs one after the other; ``--jobs`` trains the three side by side::

    python benchmarks/bench_rl.py --only sac --sac-don-steps 40000 --resume
    python benchmarks/bench_rl.py --only sac --sac-don-steps 40000 --sac-steps 80000 --resume
    python benchmarks/bench_rl.py --only sac --sac-don-steps 60000 --sac-steps 80000 --resume
    python benchmarks/bench_rl.py --only sac --sac-don-steps 80000 --sac-steps 80000 --resume

With each keypoint's last seen place and age (``--sac-memory``) and the DON on a 192-pixel window
(``--sac-window 192``), 80,000 steps for every source take about 70 min with ``--jobs 2`` (RESULTS
"rl-sac-custom", issue 58 item 5)::

    python benchmarks/bench_rl.py --only sac --sac-memory --sac-window 192 --sac-steps 80000 \
        --sac-don-steps 80000 --out runs/rl-mem --jobs 2

Expert demonstrations (``--sac-demos N``): each SAC run's replay buffer starts with N episodes of the privileged
``EndEffectorExpert`` from the task's start, stepped in the run's own observation pipeline (``demonstrations.npz``
in the run's directory); ``--sac-bc W`` adds a Q-filtered behaviour-cloning step on them (``agents/rl_demos.py``);
``--sac-demo-fraction F`` draws that share of every batch from them (``agents/rl_buffer.py``);
``--sac-updates-per-step K`` takes K gradient steps per env step (more learning from the same samples);
``--section`` names the RESULTS.md section so such a run does not replace ``rl-sac-custom``::

    python benchmarks/bench_rl.py --only sac --sac-memory --sac-window 192 --sac-steps 80000 \
        --sac-don-steps 80000 --sac-demos 300 --sac-bc 1.0 --sac-demo-fraction 0.5 --sac-eval-episodes 50 \
        --out runs/rl-demos --jobs 2 --section rl-sac-demos

(about 76 min with ``--jobs 2``; RESULTS "rl-sac-demos": from the task's start 86% with true keypoints, 4% with
the DON's, 0% with simulated ones.) At those hand starts the camera had never seen the part (too near), so the
keypoints' memory was empty there, unlike on the task's own way down; ``--sac-look-first`` resets each hand start
at the task's start first (``HandStarts(look_first=True)``)::

    python benchmarks/bench_rl.py --only sac --sac-memory --sac-window 192 --sac-steps 80000 \
        --sac-don-steps 80000 --sac-demos 300 --sac-bc 1.0 --sac-demo-fraction 0.5 --sac-look-first \
        --sac-eval-episodes 50 --out runs/rl-look --jobs 2 --section rl-sac-look

(about 97 min with ``--jobs 2``; RESULTS "rl-sac-look": from the task's start 92% with true keypoints, 42% with
the DON's, 36% with simulated ones.)
With the imitation benchmark's features (``--sac-features hand``) and its lift episodes of 100 steps, measured on a
fresh held-out set (``--eval-seed 200000``: episodes 100000.. had guided the choices before)::

    python benchmarks/bench_rl.py --only sac --sac-memory --sac-window 192 --sac-steps 80000 \
        --sac-don-steps 80000 --sac-demos 300 --sac-bc 1.0 --sac-demo-fraction 0.5 --sac-look-first \
        --sac-features hand --sac-max-steps 100 --sac-eval-episodes 50 --eval-seed 200000 --out runs/rl-hand \
        --jobs 2 --section rl-sac-hand

(about 91 min with ``--jobs 2``; RESULTS "rl-sac-hand": from the task's start 98% with true keypoints, 46% trained
and run with the DON's, 70% trained on simulated keypoints and run with the DON's.)

Longer recipe for a GPU machine (16 cores, one GPU: the DON on the GPU on 8 envs' images at once, their
physics in 8 subprocesses, a gradient step per env step)::

    python benchmarks/bench_rl.py --device cuda --vectorize batched-async --sac-envs 8 \\
        --sac-steps 1000000 --sac-don-steps 300000 --sac-goal place --ppo-steps 4096
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import FIGURES, REPO_ROOT, freeze_commit_description, record_section  # noqa: E402

from don_gym.agents import AxisGraspAgent, rl  # noqa: E402
from don_gym.agents.rl_demos import check_demonstration_settings  # noqa: E402
from don_gym.cli import nonnegative_int, positive_int  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402
from don_gym.io import write_text_atomic  # noqa: E402
from don_gym.objects import load_object  # noqa: E402
from don_gym.plotting import plot_learning_curve  # noqa: E402
from don_gym.stats import wilson_interval  # noqa: E402
from don_gym.wrappers.goals import hand_start_shares  # noqa: E402
from don_gym.wrappers.rl import ENCODINGS  # noqa: E402
from don_gym.zoo import read_don_metadata, shipped_names  # noqa: E402

DEFAULT_OUT = REPO_ROOT / "runs" / "rl"
#: Held-out evaluation episodes are reset with EVAL_SEED + i; training envs draw from seed + i.
EVAL_SEED = 100_000
#: Preferred keypoint model: the shipped supervised network; the oracle until it exists.
PREFERRED_MODEL = "toolcap/supervised-edge"
ORACLE_IMAGE_SIZE = (160, 120)  # no network to match: small images keep the oracle runs cheap
PARTS = ("throughput", "ppo", "sac")
#: The training stage's progress bar: runs done (fractions for the running ones' saved steps), elapsed time.
RUNS_BAR = "{desc}: {n:.1f}/{total} runs |{bar}| [{elapsed}{postfix}]"
#: SAC keypoint sources, in the order of the curves.
SAC_SOURCES = ("simulated", "don", "true")
#: Training episodes at the end of each SAC learning curve compared with the random policy on the same starts.
CURVE_END_EPISODES = 100
#: SAC evaluation starts: the task's own (the hand observing from above), and the part in the closed hand.
SAC_EVAL_STARTS = {"task start": None, "part in hand": {"in_hand": 1.0}}
#: SAC training starts (HandStarts shares; the rest start from the task's start).
DEFAULT_HAND_STARTS = {"in_hand": 0.5, "at_part": 0.25}
#: Titles of the RESULTS.md sections, one per part.
PART_TITLES = {
    "throughput": "RL: batched DON inference (bench_rl.py)",
    "ppo": "RL: PPO from DON keypoints (bench_rl.py)",
    "sac": "RL: SAC with HER (bench_rl.py)",
}
TABLE_HEAD = (
    "| policy | success (`is_success`) | 95 % interval | grasp_only | fail | mean return | s / episode |\n"
    "|---|---|---|---|---|---|---|"
)


def _rate_cells(wins: int, n: int) -> tuple[str, str]:
    """(``wins/n = rate``, ``low-high``, its 95 % Wilson interval): the two table cells of a success rate."""
    lo, hi = wilson_interval(wins, n)
    return f"{wins}/{n} = {wins / max(n, 1):.0%}", f"{lo:.0%}-{hi:.0%}"


def _row(name: str, result: rl.EvaluationResult) -> str:
    n = len(result.successes)
    counts = result.outcome_counts()
    per_episode = result.wall_s / max(n, 1)
    return (
        f"| {name} | {' | '.join(_rate_cells(int(sum(result.successes)), n))} | {counts['grasp_only']} | "
        f"{counts['fail']} | {result.mean_return:.2f} | {per_episode:.2f} |"
    )


def _summary(result: rl.EvaluationResult) -> dict[str, Any]:
    n, wins = len(result.successes), int(sum(result.successes))
    interval = list(wilson_interval(wins, n))
    return {"successes": wins, "episodes": n, "wilson_95": interval, "mean_return": result.mean_return}


def _shown(path: Path) -> str:
    """A path as RESULTS.md names it: relative to the repository when inside it (no machine's own
    directories in the record), else as written."""
    try:
        return str(Path(path).resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


@dataclass(frozen=True)
class TrainingRun:
    """One training run of a part: its directory under ``--out``, the algorithm, its env steps and the
    other arguments of :func:`rl.train`."""

    name: str
    algorithm: str
    steps: int
    kwargs: dict[str, Any] = field(default_factory=dict)

    @property
    def renders(self) -> bool:
        """Whether its envs render wrist images and run the DON: the slow runs, started first."""
        return self.kwargs.get("env_kwargs", {}).get("keypoints") == "don"


def _train(args: argparse.Namespace, run: TrainingRun, progress: bool = True) -> rl.RLTrainResult:
    """Train ``run`` in this process, or load it when finished (``--resume``, or trained by :func:`train_runs`)."""
    run_dir = args.out / run.name
    resume = args.resume and (run_dir / rl.RUN_FILES["last_model"]).is_file()
    return rl.train(
        run.algorithm, run.steps, seed=args.seed, run_dir=run_dir, resume=resume, device=args.train_device,
        don_device=args.device, progress=progress, **run.kwargs,
    )  # fmt: skip


def _train_in_child(args: argparse.Namespace, run: TrainingRun, log_path: Path, owner_pid: int) -> None:
    """A worker process of :func:`train_runs`: its output (and its env subprocesses') goes to ``log_path``; it ends
    with ``owner_pid`` (this script), also when that is killed with kill -9."""
    from don_gym.processes import end_with_parent

    end_with_parent(owner_pid)
    log = open(log_path, "a", buffering=1)  # noqa: SIM115 -- held open for the life of the process
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    sys.stdout = sys.stderr = log
    torch.set_num_threads(1)  # as the parent: a run repeats exactly, wherever it trains
    try:
        _train(args, run, progress=False)
    except DonGymError as exc:
        print(f"{run.name}: {exc}")
        sys.exit(2)


def _run_progress(run_dir: Path) -> int:
    """Env steps of a run's last save (0 before its first)."""
    progress = rl.saved_progress(run_dir)
    return 0 if progress is None else progress[0]


def _last_line(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return lines[-1].strip() if lines else ""


def train_runs(args: argparse.Namespace, runs: list[TrainingRun], jobs: int) -> None:
    """Train ``runs`` ``jobs`` at a time, each in its own process with one torch thread, the rendering ones
    (the slowest) first, then by their steps; each process writes its output to ``<run>.log`` in ``--out``.
    Every run ends saved and finished, so that the parts then load it (``args.resume`` is set). A run that
    fails stops the others (their last saves stay, for ``--resume``) and raises :class:`DonGymError` naming
    it."""
    from tqdm import tqdm

    context = multiprocessing.get_context("spawn")  # no PyBullet client or torch state is forked
    pending = sorted(runs, key=lambda run: (not run.renders, -run.steps))  # the longest first, roughly
    running: dict[str, tuple[Any, TrainingRun]] = {}
    args.out.mkdir(parents=True, exist_ok=True)
    # Counted in runs, each running one by the share of its steps saved so far: steps of the runs cost
    # from milliseconds (SAC on true keypoints) to a second (a PPO grasp with the DON).
    bar = tqdm(total=len(runs), desc=f"training, {jobs} runs at once", unit="run", bar_format=RUNS_BAR)
    try:
        while pending or running:
            while pending and len(running) < jobs:
                run = pending.pop(0)
                log_path = args.out / f"{run.name}.log"
                child_args = (args, run, log_path, os.getpid())
                process = context.Process(target=_train_in_child, args=child_args, name=run.name)
                process.start()
                running[run.name] = (process, run)
            time.sleep(2.0)
            for name, (process, _run) in list(running.items()):
                if process.is_alive():
                    continue
                process.join()
                del running[name]
                if process.exitcode != 0:
                    reason = _last_line(args.out / f"{name}.log") or f"exit status {process.exitcode}"
                    raise DonGymError(f"training run {name!r} failed: {reason} (log: {args.out / f'{name}.log'})")
            shares = {n: min(_run_progress(args.out / n) / r.steps, 1.0) for n, (_, r) in running.items()}
            bar.n = len(runs) - len(pending) - len(running) + sum(shares.values())
            bar.set_postfix_str(", ".join(f"{n} {share:.0%}" for n, share in shares.items()), refresh=False)
            bar.refresh()
    finally:
        for process, _run in running.values():
            process.terminate()
            process.join()
        bar.close()
    args.resume = True  # every run is now finished in --out: the parts load them


def _figure(args: argparse.Namespace, part: str, stem: str) -> Path:
    """Where a part's figure goes: ``<stem>_custom.png`` when the part runs with other settings (its RESULTS
    section is ``rl-<part>-custom``), ``<stem>_<section>.png`` with ``--section``, so that it never overwrites
    another run's figure."""
    if part not in getattr(args, "custom_parts", ()):
        return args.figures / f"{stem}.png"
    section = getattr(args, "section", None)
    return args.figures / f"{stem}_{section.replace('-', '_') if section else 'custom'}.png"


def _curve_entry(label: str, curve: rl.LearningCurve, window: int) -> tuple[str, Any]:
    return label, curve.rolling(window)


# ------------------------------------------------------------------------------------ throughput
def _networks_to(vec_env: Any, device: str) -> None:
    """Move the DON of every per-env keypoint wrapper of a DummyVecEnv to ``device``."""
    for env in getattr(vec_env, "envs", []):
        source = env.get_wrapper_attr("source")
        network = getattr(source, "network", None)
        if network is not None:
            network.to(device)


def run_throughput(args: argparse.Namespace, keypoint_model: str) -> tuple[str, dict[str, Any]]:
    """Steps/s of the SAC env (``control="ee"``, DON keypoints) under random actions, per-env inference vs
    one batched DON pass per step, for each number of envs, in this run."""
    env_kwargs = {"keypoint_model": keypoint_model, "image_size": args.image_size, "sensor": args.sensor}
    rows, summary = [], {}
    device = args.device
    for n_envs in args.throughput_envs:
        measured = {}
        for mode, vectorize in (("per-env", "dummy"), ("batched", args.vectorize)):
            vec_env = rl.make_vec_env("sac", n_envs, args.seed, env_kwargs, vectorize, don_device=device)
            if mode == "per-env":
                _networks_to(vec_env, device)
            rng = np.random.default_rng(args.seed)
            actions = rng.uniform(-1, 1, size=(args.throughput_steps + 1, n_envs, 5)).astype(np.float32)
            try:
                vec_env.reset()
                vec_env.step(actions[0])  # warm-up: first network call, caches
                start = time.perf_counter()
                for action in actions[1:]:
                    vec_env.step(action)
                elapsed = time.perf_counter() - start
            finally:
                vec_env.close()
            measured[mode] = n_envs * args.throughput_steps / elapsed
            print(f"throughput: {n_envs} env(s), {mode}: {measured[mode]:.1f} steps/s")
        rows.append(
            f"| {n_envs} | {measured['per-env']:.1f} | {measured['batched']:.1f} | "
            f"{measured['batched'] / measured['per-env']:.2f}x |"
        )
        summary[str(n_envs)] = measured
    body = [
        f'**Throughput** of `control="ee"` with keypoints from `{keypoint_model}` '
        f"({args.image_size[0]}x{args.image_size[1]}, sensor `{args.sensor}`), random actions, "
        f"{args.throughput_steps} steps after one warm-up step, env steps per second over all envs; the DON on "
        f"`{device}`; sub-envs stepped one after another in this process (`batched`: vectorize `{args.vectorize}`).",
        "",
        "| envs | per-env DON (steps/s) | one DON pass per step (steps/s) | speed-up |",
        "|---|---|---|---|",
        *rows,
    ]
    return "\n".join(body), {"throughput_steps_per_s": summary}


# ------------------------------------------------------------------------------------------ PPO
def _axis_grasp_policy(keypoint_model: str, image_size: tuple[int, int], sensor: str) -> tuple[Any, Any]:
    """(env, policy) of the scripted AxisGraspAgent on the same keypoint model and images."""
    env = gym.make("DONPick-v0", object="toolcap", control="grasp", image_size=image_size, sensor=sensor)
    agent = AxisGraspAgent(env, model=keypoint_model)
    return agent.env, agent.act


def _ppo_env_kwargs(args: argparse.Namespace, keypoint_model: str) -> dict[str, Any]:
    return {
        "keypoint_model": keypoint_model,
        "image_size": args.image_size,
        "sensor": args.sensor,
        "reward_type": "dense",
        "action_frame": "axis",
    }


def _ppo_rollout(args: argparse.Namespace, algorithm: str) -> dict[str, int]:
    """PPO's ``n_steps`` (per env) and ``batch_size`` for ``--ppo-rollout`` env steps over ``--ppo-envs``."""
    n_steps = max(1, args.ppo_rollout // args.ppo_envs)
    batch_size = min(rl.DEFAULT_ALGO_KWARGS[algorithm]["batch_size"], n_steps * args.ppo_envs)
    return {"n_steps": n_steps, "batch_size": batch_size}


def ppo_runs(args: argparse.Namespace, keypoint_model: str) -> list[TrainingRun]:
    """The PPO part's runs: from DON keypoints, and from the model of the DON."""
    base_kwargs = _ppo_env_kwargs(args, keypoint_model)
    return [
        TrainingRun(
            f"ppo_{source}",
            "ppo",
            args.ppo_steps,
            {
                "n_envs": args.ppo_envs,
                "env_kwargs": base_kwargs | {"keypoints": source},
                "algo_kwargs": _ppo_rollout(args, "ppo"),
            },
        )
        for source in ("don", "simulated")
    ]


def run_ppo(args: argparse.Namespace, keypoint_model: str) -> tuple[str, dict[str, Any]]:
    """PPO on grasp from DON keypoints and from a model of the DON, residual actions in the keypoints' axis
    frame, dense reward, ``--ppo-steps`` one-step episodes each; evaluated with baselines on held-out seeds."""
    base_kwargs = _ppo_env_kwargs(args, keypoint_model)
    don_kwargs = base_kwargs | {"keypoints": "don"}
    sim_kwargs = base_kwargs | {"keypoints": "simulated"}
    n_steps = _ppo_rollout(args, "ppo")["n_steps"]
    trained, simulated = (_train(args, run) for run in ppo_runs(args, keypoint_model))
    n = args.ppo_eval_episodes
    env = rl.make_ppo_env(**don_kwargs)
    results = {"PPO, DON keypoints": rl.evaluate(env, rl.model_policy(trained.model), n, args.eval_seed, "eval PPO")}
    results["PPO trained on the model of the DON, run with the DON"] = rl.evaluate(
        env, rl.model_policy(simulated.model), n, args.eval_seed, "eval PPO (simulated -> DON)"
    )
    sim_env = rl.make_ppo_env(**sim_kwargs)
    results["PPO trained on the model of the DON, run on it"] = rl.evaluate(
        sim_env, rl.model_policy(simulated.model), n, args.eval_seed, "eval PPO (simulated)"
    )
    sim_env.close()
    results["zero residual (keypoint axis grasp)"] = rl.evaluate(
        env, lambda _obs: np.zeros(4, np.float32), n, args.eval_seed, "eval zero residual"
    )
    results["random residual"] = rl.evaluate(
        env, rl.random_policy(env.action_space, args.seed), n, args.eval_seed, "eval random (axis frame)"
    )
    base = gym.make(
        "DONPick-v0", object="toolcap", control="grasp", image_size=args.image_size, sensor=args.sensor,
        reward_type="dense",
    ).unwrapped  # fmt: skip
    results["random, whole action box"] = rl.evaluate(
        base, rl.random_policy(base.action_space, args.seed), n, args.eval_seed, "eval random (box)"
    )
    axis_env, axis_policy = _axis_grasp_policy(keypoint_model, args.image_size, args.sensor)
    results["AxisGraspAgent (scripted)"] = rl.evaluate(axis_env, axis_policy, n, args.eval_seed, "eval AxisGraspAgent")
    axis_env.close()
    results["oracle grasp (true pose)"] = rl.evaluate(
        base, lambda _obs: base.oracle_action(), n, args.eval_seed, "eval oracle"
    )
    env.close()
    base.close()

    window = max(10, min(50, len(trained.curve.successes) // 5))
    figure = _figure(args, "ppo", "rl_ppo_grasp")
    plot_learning_curve(
        [
            _curve_entry("PPO, DON keypoints (stochastic policy)", trained.curve, window),
            _curve_entry("PPO, model of the DON (stochastic policy)", simulated.curve, window),
        ],
        figure,
        window,
        f"PPO, control='grasp', axis-frame residuals, keypoints of {keypoint_model}",
        reference_lines=[(f"eval: {name}", r.success_rate, r.mean_return) for name, r in results.items()],
    )
    last = trained.curve.successes[-window:]
    gap = (
        results["PPO trained on the model of the DON, run on it"].success_rate
        - results["PPO trained on the model of the DON, run with the DON"].success_rate
    )
    body = [
        f'**PPO on `control="grasp"`**: {args.ppo_steps} one-step grasp-and-place episodes per run, '
        f"{args.ppo_envs} env(s); DON keypoints: {trained.run_wall_s / 60:.1f} min, success of the last {window} "
        f"training episodes (stochastic policy) {np.mean(last):.0%}; model of the DON (`SimulatedKeypoints` with "
        f"the network's default noise model, no rendering): {simulated.run_wall_s / 60:.1f} min. Keypoints: "
        f"`{keypoint_model}`, {args.image_size[0]}x{args.image_size[1]}, sensor `{args.sensor}`; dense reward; "
        "actions are residuals about the keypoints' own grasp (midpoint lowered to the axis, axis yaw: action 0 "
        "grasps there; in the former centroid frame the MLP had to compute the world yaw from the keypoints' "
        "difference and explored with 3 cm noise, and reached 24 % in this budget); PPO "
        f"rollouts of {n_steps * args.ppo_envs} steps, MLP 64x64, seed {args.seed}. "
        f"Runs: `{_shown(args.out / 'ppo_don')}`, "
        f"`{_shown(args.out / 'ppo_simulated')}`. Learning curves: `{_shown(figure)}`.",
        "",
        f"Evaluation on the same {n} held-out episodes (seeds {args.eval_seed}..{args.eval_seed + n - 1}); "
        "transfer gap of "
        f"the policy trained on the model of the DON (its success there minus with the DON): {gap:+.0%}.",
        "",
        TABLE_HEAD,
        *[_row(name, result) for name, result in results.items()],
    ]
    return "\n".join(body), {f"ppo/{name}": _summary(r) for name, r in results.items()}


# ------------------------------------------------------------------------------------------ SAC
def _sac_env_kwargs(args: argparse.Namespace, keypoint_model: str) -> dict[str, Any]:
    return (
        {
            "keypoint_model": keypoint_model,
            "image_size": args.image_size,
            "sensor": args.sensor,
            "max_steps": args.sac_max_steps,
            "goal": args.sac_goal,
            "memory": args.sac_memory,
            "window_px": args.sac_window,
        }
        | ({"look_first": True} if args.sac_look_first else {})
        | ({"encoding": args.sac_features} if args.sac_features != "plain" else {})
    )


def _sac_steps(args: argparse.Namespace) -> dict[str, int]:
    return {"simulated": args.sac_steps, "true": args.sac_steps, "don": args.sac_don_steps}


def sac_runs(args: argparse.Namespace, keypoint_model: str) -> list[TrainingRun]:
    """The SAC part's runs, one per keypoint source in :data:`SAC_SOURCES`' order, same seeds and settings."""
    algo = {"learning_starts": args.sac_learning_starts, "gamma": args.sac_gamma}
    # Gradient steps per env step of every env: updates per step times the envs stepped together.
    algo["gradient_steps"] = args.sac_updates_per_step * args.sac_envs
    train_kwargs = _sac_env_kwargs(args, keypoint_model)
    if args.sac_hand_starts:
        train_kwargs["hand_starts"] = args.sac_hand_starts
    steps = _sac_steps(args)
    return [
        TrainingRun(
            f"sac_{args.sac_goal}_{source}",
            "sac",
            steps[source],
            {
                "n_envs": args.sac_envs,
                "env_kwargs": train_kwargs | {"keypoints": source},
                "algo_kwargs": algo,
                "vectorize": args.vectorize if (source == "don" and args.sac_envs > 1) else None,
                "demonstrations": args.sac_demos,
                "bc_weight": args.sac_bc,
                "demo_fraction": args.sac_demo_fraction,
            },
        )
        for source in SAC_SOURCES
    ]


def run_sac(args: argparse.Namespace, keypoint_model: str) -> tuple[str, dict[str, Any]]:
    """SAC + HER on ee with goal ``--sac-goal``, one run per keypoint source, same seeds and settings."""
    base_kwargs = _sac_env_kwargs(args, keypoint_model)
    steps = _sac_steps(args)
    runs = {source: _train(args, run) for source, run in zip(SAC_SOURCES, sac_runs(args, keypoint_model), strict=True)}
    n = args.sac_eval_episodes
    results = {}
    for start, hand_starts in SAC_EVAL_STARTS.items():
        for source in SAC_SOURCES:
            env = rl.make_sac_env(**base_kwargs, keypoints=source, hand_starts=hand_starts)
            results[f"{start}: SAC+HER, {source} keypoints"] = rl.evaluate(
                env, rl.model_policy(runs[source].model), n, args.eval_seed, f"eval SAC ({source}, {start})"
            )
            if source == "don":
                results[f"{start}: SAC+HER trained on simulated keypoints, run with the DON"] = rl.evaluate(
                    env, rl.model_policy(runs["simulated"].model), n, args.eval_seed, f"eval SAC (sim -> DON, {start})"
                )
            if source == "true":
                # Random actions ignore the observation, and nothing in the physics depends on the keypoints'
                # source: the fastest env gives the same episodes.
                results[f"{start}: random"] = rl.evaluate(
                    env, rl.random_policy(env.action_space, args.seed), n, args.eval_seed, f"eval random ({start})"
                )
            env.close()
    # The learning curves mix the training starts: their random baseline is a random policy on that mix,
    # not on either evaluation start.
    curve_baseline, random_episodes = "task start: random", 5 * n
    if args.sac_hand_starts:
        curve_baseline = "training starts: random"
        env = rl.make_sac_env(**base_kwargs, keypoints="true", hand_starts=args.sac_hand_starts)
        # Cheap (no rendering, no network): more episodes than the policies get, for a steadier line.
        random_policy = rl.random_policy(env.action_space, args.seed)
        results[curve_baseline] = rl.evaluate(
            env, random_policy, random_episodes, args.eval_seed, "eval random (training starts)"
        )
        env.close()
    window = max(3, min(50, min(len(r.curve.successes) for r in runs.values()) // 5))
    figure = _figure(args, "sac", f"rl_sac_her_{args.sac_goal}")
    baseline = results[curve_baseline]
    baseline_label = f"random policy, {curve_baseline.split(':')[0]} ({len(baseline.successes)} episodes)"
    plot_learning_curve(
        [_curve_entry(f"{source} keypoints", runs[source].curve, window) for source in SAC_SOURCES],
        figure,
        window,
        f"SAC+HER, control='ee', goal '{args.sac_goal}', keypoints: simulated / {keypoint_model} / true",
        reference_lines=[(baseline_label, baseline.success_rate, baseline.mean_return)],
    )

    curve_end = _curve_end(runs, baseline)

    def transfer_gap(start: str) -> float:
        on_model = results[f"{start}: SAC+HER, simulated keypoints"].success_rate
        return on_model - results[f"{start}: SAC+HER trained on simulated keypoints, run with the DON"].success_rate

    gaps = ", ".join(f"{start} {transfer_gap(start):+.0%}" for start in SAC_EVAL_STARTS)
    starts_text = (
        "training episodes start with the hand "
        + ", ".join(f"{name} {share:.0%}" for name, share in args.sac_hand_starts.items())
        + " of the time (`HandStarts`; the rest from the task's start"
        + (", each hand start after one look from the task's start, `look_first`)" if args.sac_look_first else ")")
        if args.sac_hand_starts
        else "training episodes start from the task's start"
    ) + (
        f"; {args.sac_demos} episodes of the privileged expert (`EndEffectorExpert`, from the task's start) in each "
        "replay buffer before learning"
        + (f", with a Q-filtered behaviour-cloning step of weight {args.sac_bc:g} on them" if args.sac_bc else "")
        + (f", {args.sac_demo_fraction:.0%} of every batch from them" if args.sac_demo_fraction else "")
        if args.sac_demos
        else ""
    )
    times = ", ".join(
        f"{source} {steps[source]} steps in {runs[source].run_wall_s / 60:.1f} min "
        f"({1000 * runs[source].run_wall_s / max(steps[source], 1):.0f} ms/step)"
        for source in SAC_SOURCES
    )
    goal_text = (
        "the `lift` sub-task (the part's keypoints 6 cm above where it lay; the full `place` task is beyond "
        "this CPU budget)"
        if args.sac_goal == "lift"
        else "the full `place` task (keypoints of the part seated in the cradle)"
    )
    body = [
        f'**SAC with HER on `control="ee"`**, goal: {goal_text}; sparse goal reward, episodes of at most '
        f"{args.sac_max_steps} steps, {args.sac_envs} env(s); policy input: TCP pose, gripper width and the "
        "keypoints of each frame (the true `achieved_goal` only relabels and rewards, it is not a policy input)"
        + (", each keypoint's last seen place and age (`KeypointMemory`)" if args.sac_memory else "")
        + (
            " in the hand-frame encoding (`encoding='hand'`: hand yaw as cos/sin, wrist angle, offsets from the TCP "
            "also at a 1 cm tanh scale, the remembered axis seen from the hand)"
            if args.sac_features == "hand"
            else ""
        )
        + f" plus the desired goal. Keypoints: `simulated` (a model of `{keypoint_model}`, no rendering; hidden "
        f"outside the camera's view and the sensor's depth range), `don` (`{keypoint_model}` on "
        f"{args.image_size[0]}x{args.image_size[1]} wrist images"
        + (f", in a {args.sac_window}-pixel window around the part" if args.sac_window else "")
        + f"), `true` (exact, always seen). {times}; {starts_text}. Learning starts {args.sac_learning_starts}, "
        f"discount {args.sac_gamma:g}, {args.sac_updates_per_step} gradient step(s) per env step, MLP 256x256, "
        f"seed {args.seed}. "
        f"Runs: `{_shown(args.out)}/sac_{args.sac_goal}_*`. Learning curves "
        f"(training episodes, all starts, beside a random policy on the same starts): `{_shown(figure)}`.",
        "",
        f"Evaluation on the same {n} held-out episodes (seeds {args.eval_seed}..{args.eval_seed + n - 1}) from two "
        "starts: the task's own (the hand 0.45 m above the table, open) and the part in the closed hand (`hand_start="
        "'in_hand'`); every policy with its own keypoints unless said; transfer gap of the simulated-keypoint "
        f"policy (there minus with the DON): {gaps}. Success: `info['is_success']` at the episode's end."
        + (
            f" *training starts: random* = a random policy on the training episodes' mix of starts (seeds "
            f"{args.eval_seed}..{args.eval_seed + random_episodes - 1}), the baseline of the learning curves."
            if args.sac_hand_starts
            else ""
        ),
        "",
        TABLE_HEAD,
        *[_row(name, result) for name, result in results.items()],
        "",
        f"**End of the learning curves**: success in each run's last {curve_end['don']['episodes']} training "
        f"episodes against *{curve_baseline}* ({len(baseline.successes)} episodes), 95 % Wilson intervals; "
        "*clearly above random* when the run's interval lies wholly above the random policy's.",
        "",
        "| keypoints | last training episodes | 95 % interval | random policy | clearly above random |",
        "|---|---|---|---|---|",
        *[_curve_end_row(source, end, baseline) for source, end in curve_end.items()],
    ]
    summary = {f"sac/{name}": _summary(r) for name, r in results.items()}
    return "\n".join(body), summary | {f"sac/curve end: {source}": end for source, end in curve_end.items()}


def _curve_end(runs: dict[str, rl.RLTrainResult], baseline: rl.EvaluationResult) -> dict[str, dict[str, Any]]:
    """Per keypoint source: success in the run's last :data:`CURVE_END_EPISODES` training episodes (fewer
    when a run has fewer), its Wilson interval, and whether that lies wholly above ``baseline``'s (the
    random policy on the training starts)."""
    count = min(CURVE_END_EPISODES, *(len(run.curve.successes) for run in runs.values()))
    random_hi = _summary(baseline)["wilson_95"][1]
    ends = {}
    for source, run in runs.items():
        wins = int(sum(run.curve.successes[-count:])) if count else 0
        interval = wilson_interval(wins, count)
        ends[source] = {
            "successes": wins, "episodes": count, "wilson_95": list(interval),
            "clearly_above_random": bool(interval[0] > random_hi),
        }  # fmt: skip
    return ends


def _curve_end_row(source: str, end: dict[str, Any], baseline: rl.EvaluationResult) -> str:
    rate, interval = _rate_cells(end["successes"], end["episodes"])
    random_rate, random_interval = _rate_cells(int(sum(baseline.successes)), len(baseline.successes))
    return (
        f"| {source} | {rate} | {interval} | {random_rate} ({random_interval}) | "
        f"{'yes' if end['clearly_above_random'] else 'no'} |"
    )


# ----------------------------------------------------------------------------------------- main
#: The training runs of each part that has any.
PART_RUNS = {"ppo": ppo_runs, "sac": sac_runs}
#: The options that shape each part's figures: a run with any of them off its default records its part in a
#: section of its own (``rl-<part>-custom``), beside the default run's.
PART_SETTINGS = {
    "throughput": ("throughput_envs", "throughput_steps", "device", "vectorize"),
    "ppo": ("ppo_envs", "ppo_steps", "ppo_rollout", "ppo_eval_episodes"),
    "sac": (
        "sac_goal", "sac_envs", "sac_steps", "sac_don_steps", "sac_max_steps", "sac_learning_starts",
        "sac_eval_episodes", "sac_hand_starts", "sac_memory", "sac_window", "vectorize", "sac_demos", "sac_bc",
        "sac_demo_fraction", "sac_gamma", "sac_updates_per_step", "sac_look_first", "sac_features",
    ),
}  # fmt: skip
COMMON_SETTINGS = ("keypoint_model", "sensor", "seed", "image_size", "train_device", "eval_seed")


def _custom_settings(parser: argparse.ArgumentParser, args: argparse.Namespace, part: str) -> list[str]:
    """The options of ``part`` (and those common to every part) that differ from their defaults; ``args`` as
    parsed, before main resolves the defaults left to it (``None``)."""
    return [name for name in COMMON_SETTINGS + PART_SETTINGS[part] if getattr(args, name) != parser.get_default(name)]


def keypoint_image_size(keypoint_model: str) -> tuple[int, int]:
    """(width, height) the keypoint network was trained at; 160x120 for the oracle (no network)."""
    if keypoint_model == "oracle":
        return ORACLE_IMAGE_SIZE
    # The benchmark's envs show the toolcap: a network for another part is refused here, before training.
    return tuple(read_don_metadata(keypoint_model, expect_part=load_object("toolcap")).image_size)


def _hand_starts(text: str) -> dict[str, float]:
    """``in_hand=0.5,at_part=0.25`` -> {"in_hand": 0.5, "at_part": 0.25}; ``none`` -> {}."""
    if text.strip().lower() == "none":
        return {}
    shares = {}
    for item in text.split(","):
        name, _, share = item.partition("=")
        if name.strip() in shares:
            raise argparse.ArgumentTypeError(f"{item!r}: hand start {name.strip()!r} given twice")
        try:
            shares[name.strip()] = float(share)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{item!r}: expected START=SHARE with a number") from None
    try:  # names, ranges and the total, as the wrapper checks them
        hand_start_shares(shares)
    except DonGymError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return shares


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", action="append", choices=PARTS, help="run these parts (repeatable)")
    parser.add_argument(
        "--keypoint-model", default=None, help=f"default: {PREFERRED_MODEL!r} if shipped, else 'oracle'"
    )
    parser.add_argument("--sensor", default="d435")
    parser.add_argument("--seed", type=nonnegative_int, default=0)
    parser.add_argument(
        "--eval-seed", type=nonnegative_int, default=EVAL_SEED, metavar="S",
        help=f"held-out episodes are reset(seed=S + i) (default {EVAL_SEED}); a fresh S gives a fresh held-out set "
        "when the default's has guided choices",
    )  # fmt: skip
    parser.add_argument(
        "--image-size", type=positive_int, nargs=2, default=None, metavar=("W", "H"),
        help="wrist camera size (default: the size the keypoint network was trained at; 160x120 for the oracle)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help=f"run directories (default {DEFAULT_OUT})")
    parser.add_argument("--resume", action="store_true", help="continue the runs saved in --out")
    parser.add_argument("--device", default=None, help="where the DON runs (default: cuda if available, else cpu)")
    parser.add_argument("--train-device", default="cpu", help="where the policies train")
    parser.add_argument("--vectorize", choices=("batched", "batched-async"), default="batched")
    parser.add_argument("--throughput-envs", type=positive_int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--throughput-steps", type=positive_int, default=20)
    parser.add_argument("--ppo-envs", type=positive_int, default=2, help="PPO envs, in subprocesses when > 1")
    parser.add_argument("--ppo-steps", type=positive_int, default=1024, help="grasp episodes (one env step each)")
    parser.add_argument("--ppo-rollout", type=positive_int, default=32, help="env steps per PPO update, all envs")
    parser.add_argument("--ppo-eval-episodes", type=positive_int, default=50)
    parser.add_argument("--sac-goal", choices=("lift", "place"), default="lift")
    parser.add_argument("--sac-envs", type=positive_int, default=1)
    parser.add_argument(
        "--sac-steps", type=positive_int, default=40_000, help="env steps, simulated and true keypoints"
    )
    parser.add_argument("--sac-don-steps", type=positive_int, default=20_000, help="env steps, DON keypoints")
    parser.add_argument("--sac-max-steps", type=positive_int, default=50)
    parser.add_argument("--sac-learning-starts", type=int, default=rl.DEFAULT_ALGO_KWARGS["sac-her"]["learning_starts"])
    parser.add_argument("--sac-eval-episodes", type=positive_int, default=20)
    parser.add_argument(
        "--sac-gamma", type=float, default=rl.DEFAULT_ALGO_KWARGS["sac-her"]["gamma"],
        help="SAC's discount (default %(default)s; an episode of N steps wants about 1 - 1/N)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-updates-per-step", type=positive_int, default=1,
        help="SAC's gradient steps per env step (the update-to-data ratio; default %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-memory", action="store_true",
        help="the policies also see each keypoint's last seen place and age (KeypointMemory), so they still know "
        "where the part is once the camera has lost it",
    )  # fmt: skip
    parser.add_argument(
        "--sac-window", type=positive_int, default=None, metavar="PX",
        help="the DON runs on a PX-pixel window around the part instead of the whole frame (e.g. 192)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-hand-starts", type=_hand_starts, default=DEFAULT_HAND_STARTS, metavar="START=SHARE,...",
        help="shares of SAC training episodes that start with the hand at or on the part (HandStarts; "
        f"'none' for none; default {','.join(f'{k}={v}' for k, v in DEFAULT_HAND_STARTS.items())})",
    )  # fmt: skip
    parser.add_argument(
        "--sac-look-first", action="store_true",
        help="each hand start comes after one look from the task's start (HandStarts(look_first=True)), so that "
        "with --sac-memory the policy remembers the part at a hand start as on the task's own way down (without it "
        "the camera never saw the part there: too near, or out of view)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-features", choices=ENCODINGS, default="plain",
        help="the SAC policy's observation encoding (KeypointFeatures(encoding=...)): 'plain' (TCP quaternion, "
        "offsets in 5 cm units) or 'hand' (the imitation benchmark's features: hand yaw as cos/sin, wrist angle, "
        "offsets also at a 1 cm tanh scale, the remembered axis seen from the hand; needs --sac-memory)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-demos", type=int, default=0, metavar="N",
        help="episodes of the privileged expert (EndEffectorExpert) written into each SAC run's replay buffer before "
        "learning, stepped in the run's own observation pipeline from the task's start (default 0: none)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-bc", type=float, default=0.0, metavar="WEIGHT",
        help="with --sac-demos: weight of a behaviour-cloning step on the demonstrations after each gradient step, "
        "kept where the critic prefers the expert's action (Q-filter; default 0: none)",
    )  # fmt: skip
    parser.add_argument(
        "--sac-demo-fraction", type=float, default=0.0, metavar="SHARE",
        help="with --sac-demos: this share of every batch drawn from the demonstrations (RLPD's symmetric sampling "
        "at 0.5; default 0: a uniform draw over the whole buffer)",
    )  # fmt: skip
    parser.add_argument(
        "--section", default=None, metavar="KEY",
        help="record into the RESULTS.md section KEY instead of rl-<part> / rl-<part>-custom (one part only)",
    )  # fmt: skip
    parser.add_argument(
        "--jobs", type=positive_int, default=None,
        help="training runs at once, each in its own process with one torch thread (default: the number of CPUs, "
        "at most the number of runs); 1 trains them in turn in this process. The runs come out the same either way",
    )  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="tiny budgets into a temporary directory, records nothing")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    rl.require_sb3()
    torch.set_num_threads(1)
    parts = list(dict.fromkeys(args.only or PARTS))
    args.custom_parts = {part for part in parts if _custom_settings(parser, args, part)}
    if args.section is not None and (len(parts) != 1 or not args.custom_parts):
        parser.error(f"--section {args.section!r}: names the section of one part run with other settings (--only)")
    try:  # the check rl.train makes, before any part runs
        check_demonstration_settings(args.sac_demos, args.sac_bc, "sac", args.sac_goal, args.sac_demo_fraction)
    except DonGymError as exc:
        parser.error(
            f"--sac-demos {args.sac_demos} --sac-bc {args.sac_bc} --sac-demo-fraction {args.sac_demo_fraction}: {exc}"
        )
    if args.sac_features == "hand" and not args.sac_memory:
        parser.error("--sac-features hand reads the keypoints' memory: add --sac-memory")
    if args.sac_look_first and not args.sac_hand_starts:
        parser.error("--sac-look-first needs hand starts to look before (--sac-hand-starts, not 'none')")
    if args.sac_look_first and args.sac_envs > 1:
        parser.error(
            f"--sac-look-first with --sac-envs {args.sac_envs}: the DON run's envs are batched and find the keypoints "
            "outside their sub-envs, so a hand start cannot look first; use --sac-envs 1"
        )
    if args.quick:
        args.throughput_envs, args.throughput_steps = [1, 2], 2
        args.ppo_envs, args.ppo_rollout, args.ppo_steps, args.ppo_eval_episodes = 1, 8, 8, 2
        args.sac_steps, args.sac_don_steps, args.sac_max_steps = 100, 20, 10
        args.sac_learning_starts, args.sac_eval_episodes = 20, 2
    records = not args.quick
    if records:
        freeze_commit_description()  # the code the runs start from, whatever is committed during hours of training
    scratch = Path(tempfile.mkdtemp(prefix="don_gym_rl_")) if args.quick else None
    args.out = args.out or (scratch / "runs" if scratch else DEFAULT_OUT)
    # Runs that record nothing keep their figures out of benchmarks/figures too.
    args.figures = FIGURES if records else (scratch or args.out) / "figures"
    args.figures.mkdir(parents=True, exist_ok=True)
    keypoint_model = args.keypoint_model or (PREFERRED_MODEL if PREFERRED_MODEL in shipped_names() else "oracle")
    if keypoint_model == "oracle":
        print("keypoints from the oracle (true-pose descriptors): a pipeline check, not a perception result")
    try:  # unknown name, checkpoint for another object: say so before any training
        default_size = keypoint_image_size(keypoint_model)
    except DonGymError as exc:
        parser.error(str(exc))
    args.image_size = tuple(args.image_size or default_size)
    if args.device is None:
        args.device = "cuda" if torch.cuda.is_available() else "cpu"

    # Parts run on their own (--only) add to the summary of the runs in --out instead of replacing it; read
    # before any training, so that an unreadable one stops the run now rather than after hours.
    summary_path = args.out / "summary.json"
    try:
        previous_summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
        if not isinstance(previous_summary, dict):
            raise ValueError("expected a JSON object")
    except (OSError, ValueError) as exc:
        parser.error(f"{summary_path}: not a readable summary ({exc}); move it away or pass another --out")

    start = time.perf_counter()
    runners = {"throughput": run_throughput, "ppo": run_ppo, "sac": run_sac}
    training = [run for part in parts if part in PART_RUNS for run in PART_RUNS[part](args, keypoint_model)]
    jobs = min(args.jobs or len(os.sched_getaffinity(0)), max(len(training), 1))
    sections, summary = {}, {"keypoint_model": keypoint_model, "eval_seeds": [args.eval_seed], "seed": args.seed}
    part_wall_s: dict[str, float] = {}
    training_wall_s = None  # the training stage's, once it has run (not with one job: each part trains its own)
    # The throughput part times the DON: it runs first, alone, before any training starts.
    for part in sorted(parts, key=lambda part: part != "throughput"):
        part_start = time.perf_counter()
        try:
            if part in PART_RUNS and jobs > 1 and training_wall_s is None:
                train_runs(args, training, jobs)
                training_wall_s = time.perf_counter() - part_start
                part_start = time.perf_counter()
            text, results = runners[part](args, keypoint_model)
        except DonGymError as exc:
            print(f"bench_rl: {part}: {exc}", file=sys.stderr)
            return 2
        sections[part], part_wall_s[part] = text, time.perf_counter() - part_start
        summary |= results
    total_wall_s = time.perf_counter() - start
    for part in sections:
        if part in PART_RUNS and training_wall_s is not None:
            wall = (
                f"Wall time: the {len(training)} training runs of this command, {jobs} at once (`--jobs`), "
                f"{training_wall_s / 60:.1f} min; then this part's evaluation {part_wall_s[part] / 60:.1f} min; "
                f"the whole command {total_wall_s / 60:.1f} min."
            )
        else:
            wall = (
                f"Wall time of this part {part_wall_s[part] / 60:.1f} min; "
                f"the whole command {total_wall_s / 60:.1f} min."
            )
        sections[part] += "\n\n" + wall
    sections = {part: sections[part] for part in parts}  # the order asked, throughput first or not
    write_text_atomic(summary_path, json.dumps(previous_summary | summary, indent=1) + "\n")
    oracle_note = (
        " The keypoints come from the oracle (descriptors rendered from the true pose): this checks the "
        "pipeline, it is not a perception result."
        if keypoint_model == "oracle"
        else ""
    )
    intro = (
        "stable-baselines3 baselines on the toolcap; the policies see the part only through the two axis-end "
        f"keypoints of `{keypoint_model}`.{oracle_note} Success = "
        "`info['is_success']` (grasp_and_place, or the lift goal) at the end of an episode, 95 % Wilson intervals."
    )
    print(intro + "\n\n" + "\n\n".join(sections.values()))
    print(f"Total wall time {total_wall_s / 60:.1f} min")
    print(f"runs, figures and summary.json: {args.out} {args.figures}")
    if records:
        for part, text in sections.items():
            # A new section goes after the one of the part before it, keeping PARTS' order in RESULTS.md.
            after = f"rl-{PARTS[PARTS.index(part) - 1]}" if PARTS.index(part) else None
            key, title = f"rl-{part}", PART_TITLES[part]
            if part in args.custom_parts:
                # Beside the default run's figures, not over them (e.g. the longer recipes of the docstring).
                key, after = args.section or f"{key}-custom", key
                title = title.replace(" (bench_rl.py)", ", other settings (bench_rl.py)")
            record_section(key, title, intro + "\n\n" + text, after=after)
    else:
        print("(--quick: RESULTS.md not updated)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
