"""bench_rl's training stage: runs trained side by side come out as trained in turn; a failing one is named."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_rl  # noqa: E402

from don_gym.agents import rl  # noqa: E402
from don_gym.errors import DonGymError  # noqa: E402

TINY_SAC = {"learning_starts": 10, "batch_size": 8, "buffer_size": 500, "policy_kwargs": {"net_arch": [8, 8]}}
TINY_PPO = {"n_steps": 8, "batch_size": 8, "policy_kwargs": {"net_arch": [8, 8]}}


def _args(out: Path, *options: str):
    args = bench_rl._parser().parse_args(["--out", str(out), *options])
    args.image_size, args.device = (64, 48), "cpu"
    return args


def _runs() -> list[bench_rl.TrainingRun]:
    sac_env = {"keypoints": "true", "goal": "lift", "max_steps": 5, "image_size": (64, 48)}
    ppo_env = {"keypoints": "true", "image_size": (64, 48), "reward_type": "dense", "action_frame": "axis"}
    return [
        bench_rl.TrainingRun("sac_true", "sac", 30, {"env_kwargs": sac_env, "algo_kwargs": TINY_SAC}),
        bench_rl.TrainingRun("ppo_true", "ppo", 16, {"env_kwargs": ppo_env, "algo_kwargs": TINY_PPO}),
    ]


def _parameters(model) -> np.ndarray:
    return torch.cat([p.detach().flatten() for p in model.policy.parameters()]).numpy()


def test_runs_trained_side_by_side_come_out_as_trained_in_turn(tmp_path: Path) -> None:
    parallel = _args(tmp_path / "parallel")
    bench_rl.train_runs(parallel, _runs(), jobs=2)
    assert parallel.resume  # the parts now load the finished runs
    in_turn = _args(tmp_path / "in_turn")
    torch.set_num_threads(1)
    for run in _runs():
        loaded = bench_rl._train(parallel, run, progress=False)
        trained = bench_rl._train(in_turn, run, progress=False)
        assert loaded.model.num_timesteps == trained.model.num_timesteps == run.steps
        assert loaded.curve.successes == trained.curve.successes and loaded.curve.returns == trained.curve.returns
        np.testing.assert_array_equal(_parameters(loaded.model), _parameters(trained.model))
        assert (tmp_path / "parallel" / f"{run.name}.log").is_file()
        assert loaded.run_wall_s > 0


def test_a_failing_run_is_named_and_stops_the_stage(tmp_path: Path) -> None:
    bad = bench_rl.TrainingRun("ppo_bad", "ppo", 16, {"env_kwargs": {"keypoints": "nonsense"}})
    with pytest.raises(DonGymError, match=r"'ppo_bad' failed: .*nonsense"):
        bench_rl.train_runs(_args(tmp_path), [bad, *_runs()[:1]], jobs=2)
    assert not (tmp_path / "ppo_bad" / rl.RUN_FILES["model"]).exists()


def test_runs_with_other_settings_record_beside_the_default_ones(tmp_path: Path) -> None:
    parser = bench_rl._parser()
    default = parser.parse_args([])
    assert all(bench_rl._custom_settings(parser, default, part) == [] for part in bench_rl.PARTS)
    longer = parser.parse_args(["--sac-steps", "80000", "--jobs", "1", "--resume"])
    assert bench_rl._custom_settings(parser, longer, "sac") == ["sac_steps"]
    assert bench_rl._custom_settings(parser, longer, "ppo") == []
    other_part = parser.parse_args(["--keypoint-model", "oracle"])
    assert bench_rl._custom_settings(parser, other_part, "throughput") == ["keypoint_model"]
    # Each record keeps its own figure: the default run's, a custom run's, and a named section's.
    figures = set()
    for argv in ([], ["--sac-steps", "80000"], ["--sac-steps", "80000", "--section", "rl-sac-demos"]):
        args = parser.parse_args(argv)
        args.figures = tmp_path
        args.custom_parts = {part for part in bench_rl.PARTS if bench_rl._custom_settings(parser, args, part)}
        figures.add(bench_rl._figure(args, "sac", "rl_sac_her_lift").name)
    assert figures == {"rl_sac_her_lift.png", "rl_sac_her_lift_custom.png", "rl_sac_her_lift_rl_sac_demos.png"}


def test_sac_memory_and_window_reach_every_sac_run_and_record_apart(tmp_path: Path) -> None:
    """--sac-memory and --sac-window go into each SAC run's env (memory for every keypoint source; the window only
    changes the DON's), and the runs record beside the default ones; the env they describe is built."""
    parser = bench_rl._parser()
    args = parser.parse_args(["--out", str(tmp_path), "--sac-memory", "--sac-window", "192"])
    assert bench_rl._custom_settings(parser, args, "sac") == ["sac_memory", "sac_window"]
    args.image_size = (64, 48)
    runs = bench_rl.sac_runs(args, "oracle")
    assert [run.kwargs["env_kwargs"]["keypoints"] for run in runs] == list(bench_rl.SAC_SOURCES)
    assert all(run.kwargs["env_kwargs"]["memory"] and run.kwargs["env_kwargs"]["window_px"] == 192 for run in runs)
    default = bench_rl.sac_runs(_args(tmp_path), "oracle")[0].kwargs["env_kwargs"]
    assert not default["memory"] and default["window_px"] is None
    env = rl.make_sac_env(**(runs[0].kwargs["env_kwargs"] | {"max_steps": 5}))
    try:
        obs, _ = env.reset(seed=0)
        plain = rl.make_sac_env(**(default | {"keypoints": "simulated", "max_steps": 5}))
        plain_obs, _ = plain.reset(seed=0)
        plain.close()
        # The memory adds each keypoint's place (3) and age (1) to the policy's observation.
        assert obs["observation"].shape[0] == plain_obs["observation"].shape[0] + 2 * 4
    finally:
        env.close()


def test_look_first_reaches_every_sac_run_and_needs_hand_starts_on_single_envs(tmp_path: Path, capsys) -> None:
    parser = bench_rl._parser()
    args = parser.parse_args(["--out", str(tmp_path), "--sac-memory", "--sac-look-first"])
    assert bench_rl._custom_settings(parser, args, "sac") == ["sac_memory", "sac_look_first"]
    args.image_size = (64, 48)
    assert all(run.kwargs["env_kwargs"]["look_first"] for run in bench_rl.sac_runs(args, "oracle"))
    assert "look_first" not in bench_rl.sac_runs(_args(tmp_path), "oracle")[0].kwargs["env_kwargs"]
    for options, message in (
        (["--sac-hand-starts", "none"], "--sac-look-first needs hand starts"),
        (["--sac-envs", "2"], "--sac-look-first with --sac-envs 2"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            bench_rl.main(["--only", "sac", "--sac-look-first", *options, "--out", str(tmp_path)])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err


def test_the_hand_encoding_reaches_every_sac_run_and_needs_the_memory(tmp_path: Path, capsys) -> None:
    parser = bench_rl._parser()
    args = parser.parse_args(["--out", str(tmp_path), "--sac-memory", "--sac-features", "hand", "--eval-seed", "7"])
    assert bench_rl._custom_settings(parser, args, "sac") == ["eval_seed", "sac_memory", "sac_features"]
    args.image_size = (64, 48)
    assert all(run.kwargs["env_kwargs"]["encoding"] == "hand" for run in bench_rl.sac_runs(args, "oracle"))
    assert "encoding" not in bench_rl.sac_runs(_args(tmp_path), "oracle")[0].kwargs["env_kwargs"]
    for options, message in (
        (["--sac-features", "hand"], "--sac-features hand reads the keypoints' memory"),
        (["--eval-seed", "-1"], "argument --eval-seed"),  # refused before hours of training, not at evaluation
        (["--seed", "-1"], "argument --seed"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            bench_rl.main(["--only", "sac", *options, "--out", str(tmp_path)])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err


def test_demonstrations_and_discount_reach_every_sac_run_and_bad_options_are_refused(tmp_path: Path, capsys) -> None:
    parser = bench_rl._parser()
    options = ["--sac-demos", "5", "--sac-bc", "0.5", "--sac-gamma", "0.98", "--sac-updates-per-step", "2"]
    args = parser.parse_args(["--out", str(tmp_path), *options, "--sac-envs", "3"])
    custom = ["sac_envs", "sac_demos", "sac_bc", "sac_gamma", "sac_updates_per_step"]
    assert sorted(bench_rl._custom_settings(parser, args, "sac")) == sorted(custom)
    args.image_size = (64, 48)
    for run in bench_rl.sac_runs(args, "oracle"):
        assert run.kwargs["demonstrations"] == 5 and run.kwargs["bc_weight"] == 0.5
        assert run.kwargs["algo_kwargs"]["gamma"] == 0.98
        assert run.kwargs["algo_kwargs"]["gradient_steps"] == 6  # 2 per env step of each of the 3 envs
    for options, message in (
        (["--only", "sac", "--sac-bc", "1"], "bc_weight=1.0 needs demonstrations > 0"),
        (["--only", "sac", "--sac-demos", "-1"], "--sac-demos -1"),
        (["--only", "sac", "--sac-demos", "2", "--sac-bc", "nan"], "bc_weight=nan"),
        (["--only", "sac", "--section", "rl-sac-x"], "--section 'rl-sac-x'"),
        (["--only", "sac", "--sac-updates-per-step", "0"], "--sac-updates-per-step"),
        (["--sac-demos", "2", "--section", "rl-sac-x"], "--section 'rl-sac-x'"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            bench_rl.main([*options, "--out", str(tmp_path)])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err


@pytest.mark.parametrize("jobs", ["0", "-1", "x", "1.5"])
def test_jobs_must_be_a_positive_integer(jobs: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        bench_rl._parser().parse_args(["--jobs", jobs])
    assert exit_info.value.code == 2
    assert f"argument --jobs: '{jobs}': expected a positive whole number" in capsys.readouterr().err


def test_curve_end_compares_each_runs_last_episodes_with_random():
    def run(successes: list[bool]) -> rl.RLTrainResult:
        curve = rl.LearningCurve()
        for i, success in enumerate(successes):
            curve.add(10 * (i + 1), 0.0, success)
        return rl.RLTrainResult(model=None, curve=curve, wall_s=0.0, run_wall_s=0.0)

    random_policy = rl.EvaluationResult([0.0] * 100, [i < 3 for i in range(100)], ["fail"] * 100, [5] * 100, 0.0)
    early_failures = [False] * 400
    runs = {
        "learns": run(early_failures + [i % 4 == 0 for i in range(200)]),  # 25 % at the end: above 3/100
        "barely": run(early_failures + [i % 20 == 0 for i in range(200)]),  # 5 %: within random's interval
    }
    ends = bench_rl._curve_end(runs, random_policy)
    assert ends["learns"]["episodes"] == bench_rl.CURVE_END_EPISODES == 100
    assert ends["learns"]["successes"] == 25 and ends["learns"]["clearly_above_random"]
    assert ends["barely"]["successes"] == 5 and not ends["barely"]["clearly_above_random"]
    assert "| learns | 25/100 = 25% |" in bench_rl._curve_end_row("learns", ends["learns"], random_policy)
    # A run shorter than the window is compared over all its episodes, every run over the same count.
    short = bench_rl._curve_end({"short": run([True] * 30), "learns": runs["learns"]}, random_policy)
    assert short["short"]["episodes"] == short["learns"]["episodes"] == 30
