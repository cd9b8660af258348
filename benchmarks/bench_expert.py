"""The Markov end-effector expert (``don_gym.agents.ee_expert``) on the lift and place tasks.

Success of the closed-loop expert with privileged state on ``--episodes`` held-out episodes per task (the
episodes the RL and imitation policies are evaluated on, ``reset(seed=EVAL_SEED + i)``), with 95 % Wilson
intervals, the steps an episode took and its outcomes, against a random policy on the same episodes. Target:
>= 95 % on 100 episodes each. The expert was developed on other seeds (0-20 and 1000-1099).

    python benchmarks/bench_expert.py            # full run (100 episodes per task), records "expert" in RESULTS.md
    python benchmarks/bench_expert.py --quick    # 5 episodes per task, records nothing
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record_section  # noqa: E402

import don_gym  # noqa: E402,F401  (registers the env ids)
from don_gym.agents.ee_expert import EXPERT_GOALS, EndEffectorExpert  # noqa: E402
from don_gym.evaluation.demonstrations import EPISODE_STEPS  # noqa: E402
from don_gym.stats import wilson_interval  # noqa: E402
from don_gym.wrappers import make_goal_env  # noqa: E402

#: The held-out evaluation episodes of benchmarks/bench_rl.py and the imitation benchmark.
EVAL_SEED = 100_000
TARGET = 0.95


def run(goal: str, episodes: int, part: str, policy: str) -> dict:
    env = make_goal_env(part, goal=goal, keypoints="true", max_steps=EPISODE_STEPS[goal])
    expert = EndEffectorExpert(env, goal)
    rng = np.random.default_rng(0)
    wins, steps, outcomes, t0 = 0, [], Counter(), time.perf_counter()
    for i in tqdm(range(episodes), desc=f"{policy} {goal}"):
        obs, info = env.reset(seed=EVAL_SEED + i)
        step, done = 0, False
        while not done:
            action = expert.act(obs) if policy == "expert" else rng.uniform(-1, 1, 5).astype(np.float32)
            obs, _, terminated, truncated, info = env.step(action)
            step, done = step + 1, terminated or truncated
        wins += bool(info["is_success"])
        outcomes[info.get("outcome", "?")] += 1
        if info["is_success"]:
            steps.append(step)
    env.close()
    return {"wins": wins, "n": episodes, "steps": steps, "outcomes": outcomes, "s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="5 episodes per task, print only")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per task (default 100)")
    parser.add_argument("--part", default="toolcap")
    args = parser.parse_args(argv)
    episodes = args.episodes or (5 if args.quick else 100)
    lines = [
        f'Part `{args.part}`, `control="ee"`, episodes `reset(seed={EVAL_SEED} + i)`, i < {episodes}; episode '
        f"limits {', '.join(f'{g} {EPISODE_STEPS[g]}' for g in EXPERT_GOALS)} steps; lift: the "
        "`KeypointGoal` lift sub-task (part's axis points 6 cm up), place: the task's `grasp_and_place` at rest.",
        "",
        "| task | policy | success | 95% interval | steps (median, max) of successes | outcomes | wall s |",
        "|---|---|---|---|---|---|---|",
    ]
    met = True
    for goal in EXPERT_GOALS:
        for policy in ("expert", "random"):
            r = run(goal, episodes, args.part, policy)
            low, high = wilson_interval(r["wins"], r["n"])
            steps = f"{int(np.median(r['steps']))}, {max(r['steps'])}" if r["steps"] else "-"
            outcomes = ", ".join(f"{k} {v}" for k, v in sorted(r["outcomes"].items()))
            lines.append(
                f"| {goal} | {policy} | {r['wins']}/{r['n']} ({100 * r['wins'] / r['n']:.0f}%) | "
                f"[{100 * low:.0f}, {100 * high:.0f}]% | {steps} | {outcomes} | {r['s']:.0f} |"
            )
            if policy == "expert":
                met = met and r["wins"] / r["n"] >= TARGET
    lines += ["", f"Target: the expert >= {100 * TARGET:.0f}% on each task: {'met' if met else 'NOT met'}."]
    body = "\n".join(lines)
    print(body)
    if not args.quick:
        record_section("expert", "Markov end-effector expert, lift and place (bench_expert)", body)
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
