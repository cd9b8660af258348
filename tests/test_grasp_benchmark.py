"""Grasp benchmark: a tiny oracle run gives the outcome table and files, and the same results on 1 or 2 workers."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from don_gym.cli import main
from don_gym.errors import DonGymError
from don_gym.grasp_benchmark import (
    DEFAULT_IMAGE_SIZE,
    EpisodeRunner,
    GraspBenchmarkConfig,
    GraspBenchmarkResult,
    episode_seed,
    episode_tasks,
    outcome_table,
    parse_sensor,
    run_grasp_benchmark,
    sweep_table,
    training_image_size,
    write_grasp_outputs,
)

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
    assert "| oracle | 2/2 | 0/2 | 0/2 | 2/2 | 0 |" in outcome_table(result)

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
    assert "| oracle | 1 / 2 | 0 / 1 |" in table


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
