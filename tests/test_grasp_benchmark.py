"""Grasp benchmark: a tiny oracle run gives the outcome table and files, and the same results on 1 or 2 workers."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from don_gym.cli import build_parser, main
from don_gym.errors import DonGymError
from don_gym.evaluation.grasp_benchmark import (
    DEFAULT_IMAGE_SIZE,
    EpisodeRunner,
    GraspBenchmarkConfig,
    GraspBenchmarkResult,
    episode_seed,
    episode_tasks,
    parse_sensor,
    random_pose_seed,
    run_grasp_benchmark,
    training_image_size,
)
from don_gym.evaluation.grasp_report import miss_table, outcome_table, sweep_table, write_grasp_outputs

torch.set_num_threads(1)

TINY = GraspBenchmarkConfig(
    methods=("oracle",), poses=(0, 3), repeats=1, sensors=("ideal", "d435"), image_size=(160, 120)
)


def _without_time(episodes: list[dict]) -> list[dict]:
    return [{k: v for k, v in e.items() if k != "seconds"} for e in episodes]


def test_tiny_oracle_benchmark_counts_files_and_determinism(tmp_path: Path) -> None:
    config = dataclasses.replace(TINY, sensors=("ideal",))
    result = run_grasp_benchmark(config, workers=2, progress=False)
    assert [(e["pose_id"], e["repeat"]) for e in result.episodes] == [(0, 0), (3, 0)]
    # Perfect descriptors and exact depth: every grasp lands within millimetres and places.
    assert all(e["outcome"] == "grasp_and_place" for e in result.episodes), result.episodes
    assert all(e["position_error_m"] < 0.003 and not e["flipped"] for e in result.episodes)
    assert result.counts("ideal") == {"oracle": {"fail": 0, "grasp_only": 0, "grasp_and_place": 2}}
    assert "| oracle | 2/2 (34-100%) | 0/2 (0-66%) | 0/2 (0-66%) | 2/2 (34-100%) | 0 |" in outcome_table(result)

    # One process, episodes in the reverse order (another env history): identical records.
    runner = EpisodeRunner(config)
    try:
        again = [runner.run(task) for task in reversed(episode_tasks(config))][::-1]
    finally:
        runner.close()
    assert _without_time(again) == _without_time(result.episodes)

    paths = write_grasp_outputs(result, tmp_path / "out")
    saved = json.loads(paths["json"].read_text())
    assert _without_time(saved["episodes"]) == _without_time(result.episodes)
    assert saved["summary"]["results"]["ideal"]["oracle"]["counts"]["grasp_and_place"] == 2
    assert paths["outcomes"].read_bytes()[:4] == b"\x89PNG"
    assert "sweep" not in paths  # one sensor: no sweep chart
    assert "| oracle |" in paths["table"].read_text()


def test_sweep_table_and_seeds() -> None:
    tasks = episode_tasks(TINY)
    assert [(t.sensor, t.pose_id) for t in tasks] == [("ideal", 0), ("ideal", 3), ("d435", 0), ("d435", 3)]
    # Paired design: every sensor and method sees the same seed for a (pose, repeat).
    assert tasks[0].seed == tasks[2].seed == episode_seed(0, 0, 0) != episode_seed(0, 0, 1)
    assert parse_sensor("d435@0.5").stereo_subpixel_rms_px == pytest.approx(0.04)
    assert parse_sensor("ideal").is_ideal
    fake = [
        {**dataclasses.asdict(t), "outcome": o, "flipped": False, "agent_error": None}
        | {"position_error_m": 0.001, "yaw_error_rad": 0.01}
        for t, o in zip(tasks, ("grasp_and_place", "grasp_only", "grasp_only", "fail"), strict=True)
    ]
    table = sweep_table(GraspBenchmarkResult(TINY, fake, 1.0))
    assert "| oracle | 1 (9-91%) / 2 (34-100%) | 0 (0-66%) / 1 (9-91%) |" in table


def test_miss_table_tells_placement_failures_from_grasps_off_the_part() -> None:
    tasks = episode_tasks(TINY)
    episodes = [
        {**dataclasses.asdict(t), "outcome": outcome, "flipped": False}
        | {"position_error_m": error_m, "yaw_error_rad": yaw_rad}
        for t, (outcome, error_m, yaw_rad) in zip(
            tasks,
            (
                ("grasp_and_place", 0.001, 0.01),
                ("grasp_only", 0.004, 0.02),  # accurate grasp, then the placement failed
                ("grasp_only", 0.004, 3.0),  # flipped: the descriptors' doing
                ("fail", None, None),
            ),
            strict=True,
        )
    ]
    table = miss_table(GraspBenchmarkResult(TINY, episodes, 1.0))
    assert "| oracle | 4 | 3 | 1 | 1 | 1 |" in table


def test_bad_inputs_fail_before_any_episode(tmp_path: Path, capsys) -> None:
    for config, message in (
        (GraspBenchmarkConfig(methods=("toolcap/nonsense",)), "neither 'oracle'"),
        (GraspBenchmarkConfig(poses=(8,)), "pose ids 0..7"),
        (GraspBenchmarkConfig(sensors=("d435@2",)), "severity must be in"),
        (GraspBenchmarkConfig(sensors=("lidar",)), "unknown depth sensor"),
        (GraspBenchmarkConfig(repeats=0), "repeats"),
    ):
        with pytest.raises(DonGymError, match=message):
            run_grasp_benchmark(config, workers=1, progress=False)
    capsys.readouterr()
    for argv in (["--methods", "shaft/nonsense"], ["--sensors", "d435@x"], ["--image-size", "big"]):
        assert main(["benchmark", "grasp", *argv, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("don-gym benchmark: error: ") and err.count("\n") == 1


def test_image_size_defaults_to_the_networks_training_size() -> None:
    assert training_image_size({}) == DEFAULT_IMAGE_SIZE
    assert training_image_size({"a": (640, 480), "b": (640, 480)}) == (640, 480)
    with pytest.raises(DonGymError, match=r"different image sizes \(a 640x480, b 320x240\)"):
        training_image_size({"a": (640, 480), "b": (320, 240)})


def test_random_poses_are_seeded_shared_by_every_method_and_not_the_fixed_ones(tmp_path: Path) -> None:
    from don_gym.sim.task import FIXED_POSES

    config = dataclasses.replace(TINY, poses=(0,), random_poses=1)
    tasks = episode_tasks(dataclasses.replace(config, methods=("oracle", "toolcap/supervised-edge")))
    random_tasks = [t for t in tasks if t.random_pose is not None]
    # Every (sensor, method) gets random pose 0, with one seed derived from the benchmark seed alone.
    assert len(random_tasks) == 4 and {t.seed for t in random_tasks} == {random_pose_seed(0, 0)}
    assert all(t.pose_id is None and t.repeat == 0 for t in random_tasks)
    assert random_pose_seed(0, 0) not in {episode_seed(0, p, r) for p in range(8) for r in range(3)}
    assert random_pose_seed(1, 0) != random_pose_seed(0, 0) != random_pose_seed(0, 1)

    result = run_grasp_benchmark(config, workers=1, progress=False)
    fixed = [e for e in result.episodes if e["random_pose"] is None]
    random = [e for e in result.episodes if e["random_pose"] is not None]
    assert [e["sensor"] for e in random] == ["ideal", "d435"] and len(fixed) == 2
    # The same part pose under both sensors (the seed draws the pose before any sensor noise) ...
    assert random[0]["true_action"] == random[1]["true_action"]
    # ... and not one of the fixed poses: its grasp point is centimetres from each of theirs.
    x, y = random[0]["true_action"][:2]
    assert min(np.hypot(x - px, y - py) for px, py, _ in FIXED_POSES) > 0.01
    assert result.counts("ideal", "random") == {"oracle": {"fail": 0, "grasp_only": 0, "grasp_and_place": 1}}
    assert result.counts("ideal") == {"oracle": {"fail": 0, "grasp_only": 0, "grasp_and_place": 1}}
    random_table = outcome_table(result, poses="random")
    assert "1 random poses" in random_table and "| oracle | 1/1 (21-100%) |" in random_table
    assert "1 fixed poses x 1 repeats" in outcome_table(result)
    paths = write_grasp_outputs(result, tmp_path)
    assert "### Outcomes at random poses" in paths["table"].read_text()
    assert paths["outcomes_random"].read_bytes()[:4] == b"\x89PNG"
    summary = json.loads(paths["json"].read_text())["summary"]["random_pose_results"]
    assert summary["d435"]["oracle"]["interval_95"]["grasped"][0] == pytest.approx(0.2065, abs=1e-4)


def test_random_poses_option_parsing(capsys) -> None:
    args = build_parser().parse_args(["benchmark", "grasp", "--random-poses", "3"])
    assert args.random_poses == 3
    assert build_parser().parse_args(["benchmark", "grasp"]).random_poses == 0
    for value in ("0", "-2", "1.5", "many"):
        with pytest.raises(SystemExit) as exit_info:
            main(["benchmark", "grasp", "--random-poses", value])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("don-gym benchmark grasp: error: argument --random-poses: ") and err.count("\n") == 1
        assert "positive whole number" in err


def test_random_backgrounds_are_recorded_per_episode_and_keep_the_seeds_draws(tmp_path: Path, capsys) -> None:
    # Through the CLI: the oracle at one pose, two repeats (two background seeds), D435.
    argv = ["benchmark", "grasp", "--quick", "--backgrounds", "random", "--methods", "oracle", "--poses", "0"]
    argv += ["--repeats", "2", "--image-size", "160x120", "--workers", "1", "--no-progress", "--out", str(tmp_path)]
    assert main(argv) == 0
    assert "background `random`" in capsys.readouterr().out
    saved = json.loads((tmp_path / "grasp_episodes.json").read_text())
    episodes = saved["episodes"]
    assert saved["summary"]["config"]["backgrounds"] == "random"
    assert [e["background"] for e in episodes] == ["random", "random"]
    assert all(e["outcome"] == "grasp_and_place" for e in episodes), episodes
    # Each repeat another backdrop, drawn from the episode's seed.
    assert episodes[0]["backdrop"] != episodes[1]["backdrop"]
    assert {e["backdrop"]["table_texture_family"] for e in episodes} <= {"noise", "stripes", "checks"}
    assert "background `random`" in (tmp_path / "grasp.md").read_text()

    # The same seeds on the plain table: the same part pose, no backdrop.
    plain = GraspBenchmarkConfig(methods=("oracle",), poses=(0,), repeats=2, sensors=("d435",), image_size=(160, 120))
    runner = EpisodeRunner(plain)
    try:
        plain_episodes = [runner.run(task) for task in episode_tasks(plain)]
    finally:
        runner.close()
    assert [e["background"] for e in plain_episodes] == ["plain", "plain"]
    assert [e["backdrop"] for e in plain_episodes] == [None, None]
    assert [e["seed"] for e in plain_episodes] == [e["seed"] for e in episodes]
    assert [e["true_action"] for e in plain_episodes] == [e["true_action"] for e in episodes]
    with pytest.raises(DonGymError, match=r"backgrounds='wood': expected one of \['plain', 'random', 'random-wide'\]"):
        run_grasp_benchmark(dataclasses.replace(plain, backgrounds="wood"), workers=1, progress=False)
