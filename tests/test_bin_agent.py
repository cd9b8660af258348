"""Agents that pick among instances in a bin, and the clearing benchmark (issue 33 items 4 and 5): small piles,
small images."""

from __future__ import annotations

import json

import numpy as np
import pytest

from don_gym.agents import BinAxisGraspAgent, BinOracleAgent
from don_gym.agents.bin_agent import InstanceEstimate, pair_ring_candidates, rank_grasps
from don_gym.cli import main
from don_gym.errors import DonGymError
from don_gym.evaluation.bin_benchmark import (
    EPISODE_KEYS,
    BinBenchmarkConfig,
    merge_bin_shards,
    run_bin_benchmark,
    write_bin_outputs,
    write_bin_shard,
)
from don_gym.geometry import make_transform
from don_gym.objects import load_object
from don_gym.perception.descriptor_sources import axis_end_targets
from don_gym.perception.keypoints import local_matches
from don_gym.sim.bin_env import BinPickEnv

SMALL_PILE = {"toolcap": 2, "shaft": 1}
#: A pile of SMALL_PILE with both toolcaps lying in view (the descriptor agent's test) that the oracle clears.
SEED = 1


@pytest.fixture(scope="module")
def env():
    bin_env = BinPickEnv(parts=SMALL_PILE, image_size=(160, 120))
    yield bin_env
    bin_env.close()


def test_oracle_agent_clears_a_small_pile(env):
    agent = BinOracleAgent(env)
    obs, info = env.reset(seed=SEED)
    agent.reset()
    outcomes = []
    for _ in range(env.max_steps):
        action = agent.act(obs, info)
        # The oracle sees the true instances: every estimate is a visible toolcap, and its grasp is one of them.
        assert {e.instance for e in agent.last_estimates} <= {
            i["instance"] for i in info["instances"] if i["part"] == "toolcap" and i["visible_pixels"]
        }
        obs, _, terminated, truncated, info = env.step(action)
        agent.observe_outcome(info["outcome"])
        outcomes.append(info["outcome"])
        if terminated or truncated:
            break
    assert info["end_reason"] == "cleared", outcomes
    assert "wrong_part" not in outcomes


def test_descriptor_agent_finds_the_instances_and_grasps_a_target(env):
    agent = BinAxisGraspAgent(env, model="oracle")
    obs, info = env.reset(seed=SEED)
    agent.reset()
    truth = BinOracleAgent(env).estimates(obs, info)
    found = agent.estimates(obs, info)
    assert len(found) == len(truth) == 2
    for estimate in found:  # each found instance lies on a true one (axis points within 1 cm)
        errors = [np.abs(estimate.axis_points_world - t.axis_points_world).max() for t in truth]
        assert min(errors) < 0.01
    action = agent.act(obs, info)
    _, _, _, _, info = env.step(action)
    assert info["outcome"] in ("grasp_and_place", "grasp_only")
    assert info["part"] == "toolcap"


def test_with_no_instance_at_the_match_fraction_the_agent_searches_once_more_at_the_fallback(env):
    obs, info = env.reset(seed=SEED)
    truth = BinOracleAgent(env).estimates(obs, info)
    # A match fraction no ring pixel meets: without a fallback nothing is found, and act gives up in one line.
    strict = BinAxisGraspAgent(env, model="oracle", match_fraction=1e-3, fallback_match_fraction=None)
    assert strict.estimates(obs, info) == []
    with pytest.raises(DonGymError, match="no instance of 'toolcap' found"):
        strict.act(obs, info)
    # The fallback's looser fraction finds the same instances the default does.
    loose = BinAxisGraspAgent(env, model="oracle", match_fraction=1e-3, fallback_match_fraction=0.4)
    found = loose.estimates(obs, info)
    assert len(found) == len(truth) == 2
    for estimate in found:
        assert min(np.abs(estimate.axis_points_world - t.axis_points_world).max() for t in truth) < 0.01
    for bad in (0.3, 1.5, float("nan")):
        with pytest.raises(DonGymError, match="fallback_match_fraction"):
            BinAxisGraspAgent(env, model="oracle", match_fraction=0.4, fallback_match_fraction=bad)


def test_a_part_against_a_wall_is_pushed_away_before_it_is_grasped():
    from don_gym.sim.bin_task import bin_inner_bounds, lying_footprint_m
    from don_gym.sim.part import lying_rotation
    from don_gym.sim.task import TABLE_TOP_Z_M

    env = BinPickEnv(parts={"toolcap": 1}, image_size=(160, 120), sensor="ideal", max_steps=6)
    try:
        env.reset(seed=200)
        part, model = env.task.instances[0], env.task.instances[0].model
        # Lying with its end against the wall at x0, its axis 0.3 rad off the wall's normal: the fingers of
        # either grasp would reach past the wall.
        R = lying_rotation(model, 0.3)
        x0 = bin_inner_bounds()[0]
        com = np.array([x0 + lying_footprint_m(model)[0] / 2 - 0.002, 0.02, 0.0])
        T = make_transform(R, com - R @ model.center_of_mass)
        T[2, 3] = TABLE_TOP_Z_M + 0.0005 - float((model.mesh.vertices @ R.T)[:, 2].min())
        part.body.set_pose(T)
        env.task.settle()
        x0, x1, y0, y1 = bin_inner_bounds()
        # A grasp where nothing lies (it fails) to observe the part where it now lies.
        obs, _, _, _, info = env.step(np.array([x1 - 0.03, y1 - 0.03, TABLE_TOP_Z_M + 0.02, 0.0, 0.0], np.float32))
        never = BinOracleAgent(env)
        never.max_pushes_in_a_row = 0
        assert int(never.act(obs, info)[4]) != 3
        agent = BinOracleAgent(env)
        agent.reset()
        kinds = []
        for _ in range(3):
            action = agent.act(obs, info)
            obs, _, terminated, truncated, info = env.step(action)
            agent.observe_outcome(info["outcome"])
            kinds.append((int(action[4]), info["outcome"]))
            if terminated or truncated:
                break
        assert kinds[0] == (3, "pushed") and kinds[-1][1] == "grasp_and_place", kinds
        assert agent.failed_actions == []
    finally:
        env.close()


def test_a_standing_part_is_toppled_where_it_stands_before_the_station_is_used():
    from don_gym.agents.bin_agent import TOPPLE_TRIED_RADIUS_M, times_toppled, topple_standing
    from don_gym.sim.bin_task import BIN_CENTER_XY_M, bin_inner_bounds
    from don_gym.sim.task import TABLE_TOP_Z_M

    env = BinPickEnv(parts={"toolcap": 1}, image_size=(160, 120), sensor="ideal", max_steps=6)
    try:
        env.reset(seed=200)
        part = env.task.instances[0]
        stand_xy = (BIN_CENTER_XY_M[0] - 0.04, BIN_CENTER_XY_M[1] + 0.03)
        env.task.stand(part, stand_xy, plus_up=True)
        x0, x1, y0, y1 = bin_inner_bounds()
        # A grasp where nothing lies (it fails) to observe the part standing.
        obs, _, _, _, info = env.step(np.array([x1 - 0.03, y1 - 0.03, TABLE_TOP_Z_M + 0.02, 0.0, 0.0], np.float32))
        never = BinOracleAgent(env)
        never.max_topples_per_part = 0
        assert int(never.act(obs, info)[4]) == 2  # straight to the station
        agent = BinOracleAgent(env)  # the default: one topple per part
        assert agent.max_topples_per_part == 1
        agent.reset()
        action = agent.act(obs, info)
        # A push at the top, short of its centre on the side away from the bin's middle, towards the middle.
        assert int(action[4]) == 3 and len(agent.topple_actions) == 1
        towards_middle = np.asarray(BIN_CENTER_XY_M) - np.asarray(stand_xy)
        assert abs(np.angle(np.exp(1j * (float(action[3]) - np.arctan2(towards_middle[1], towards_middle[0]))))) < 0.05
        assert float((action[:2] - np.asarray(stand_xy)) @ towards_middle) < 0
        assert np.linalg.norm(action[:2] - np.asarray(stand_xy)) < 0.015
        obs, _, _, _, info = env.step(action)
        assert info["outcome"] == "pushed"
        assert abs(float(part.body.plus_axis_world()[2])) < 0.3  # it lies now
        outcomes = []
        for _ in range(3):  # grasped lying, in the bin (after a push if it fell against a wall)
            action = agent.act(obs, info)
            obs, _, terminated, _, info = env.step(action)
            outcomes.append((int(action[4]), info["outcome"], bool(info["regrasp"])))
            if terminated:
                break
        assert outcomes[-1] in ((0, "grasp_and_place", False), (1, "grasp_and_place", False)), outcomes
    finally:
        env.close()
    # Where the topple did not tip it, the part goes to the station: one topple per place.
    estimate = InstanceEstimate(np.array([[0.5, 0.0, 0.03], [0.5, 0.0, 0.07]]))
    push = topple_standing(estimate, load_object("toolcap"))
    assert times_toppled(estimate, [push]) == 1
    moved = InstanceEstimate(estimate.axis_points_world + [TOPPLE_TRIED_RADIUS_M + 0.02, 0.0, 0.0])
    assert times_toppled(moved, [push]) == 0


def test_a_push_goes_across_the_perceived_axis_towards_the_bin_s_middle():
    from don_gym.agents.bin_agent import GraspCandidate, push_away_from_walls
    from don_gym.sim.bin_task import bin_inner_bounds

    x0, x1, y0, y1 = bin_inner_bounds()
    middle_y = (y0 + y1) / 2
    # (axis yaw, grasp x, y, the push's yaw): against the wall at x0, at x1, and at y0 (axis along x).
    cases = (
        (np.pi / 2, x0 + 0.02, middle_y, 0.0),
        (np.pi / 2, x1 - 0.02, middle_y, np.pi),
        (0.0, x0 + 0.1, y0 + 0.02, np.pi / 2),
    )
    for axis_yaw, x, y, expected in cases:
        axis = np.array([np.cos(axis_yaw), np.sin(axis_yaw), 0.0])
        estimate = InstanceEstimate(np.array([[x, y, 0.02], [x, y, 0.02]]) + np.outer([-0.01, 0.01], axis))
        candidate = GraspCandidate(np.array([x, y, 0.02, axis_yaw, 0], np.float32), "across", 0.0, False, 0)
        push = push_away_from_walls(candidate, estimate)
        assert push.shape == (5,) and push[4] == 3 and np.allclose(push[:3], [x, y, 0.02])
        assert abs(np.angle(np.exp(1j * (float(push[3]) - expected)))) < 1e-5


def test_local_matches_one_per_spot_best_first():
    distances = np.ones((20, 30), np.float32)
    distances[5, 5], distances[5, 6], distances[15, 25] = 0.1, 0.1, 0.05  # a plateau of two pixels, and a better spot
    uv, best = local_matches(distances, threshold=0.5, window_px=3.0)
    assert len(uv) == 2 and best[0] == pytest.approx(0.05)
    np.testing.assert_allclose(uv[0], [25, 15], atol=1e-6)
    assert uv[1][0] == pytest.approx(5.5, abs=0.01) and uv[1][1] == pytest.approx(5.0)
    assert len(local_matches(distances, threshold=0.01, window_px=3.0)[0]) == 0


def test_rings_pair_by_spacing_and_tried_grasps_go_last():
    toolcap = load_object("toolcap")
    targets = axis_end_targets(toolcap)
    spacing = float(targets.axial_positions_m[1] - targets.axial_positions_m[0])
    # Two parts lying along x, seen from straight above: surface points one radius above their axis points.
    camera = np.eye(4)
    camera[:3, 3] = [0.0, 0.0, 0.5]
    r = float(targets.radii_m[0])
    minus = np.array([[0.0, 0.0, r], [0.0, 0.1, r]])
    plus = np.array([[0.0, 0.1 + spacing, r], [spacing, 0.0, r]])  # listed the other way round
    pixels = [np.array([[10.0, 10.0], [10.0, 40.0]]), np.array([[10.0, 48.0], [18.0, 10.0]])]
    depth = np.full((60, 60), 0.5 - r, np.float32)
    found = pair_ring_candidates([minus, plus], pixels, [np.zeros(2), np.zeros(2)], depth, camera, targets)
    assert len(found) == 2
    for estimate in found:
        assert np.linalg.norm(estimate.axis_points_world[1] - estimate.axis_points_world[0]) == pytest.approx(
            spacing, abs=1e-3
        )
    # A deep gap between two rings (the floor) makes them two parts.
    depth[:, 10:40] = 0.9
    assert (
        pair_ring_candidates(
            [minus[:1], plus[1:]], [pixels[0][:1], pixels[1][1:]], [[0.0], [0.0]], depth, camera, targets
        )
        == []
    )
    from don_gym.agents.bin_agent import GraspCandidate

    estimates = [
        InstanceEstimate(np.array([[0, 0, 0.05], [0.02, 0, 0.05]])),
        InstanceEstimate(np.array([[0, 0.1, 0.02], [0.02, 0.1, 0.02]])),
    ]
    high = GraspCandidate(np.array([0.01, 0, 0.05, 0], np.float32), "across", 0.0, True, 0)
    low = GraspCandidate(np.array([0.01, 0.1, 0.02, 0], np.float32), "across", 0.0, True, 1)
    assert rank_grasps([low, high], estimates)[0] is high  # the top of the pile first
    assert rank_grasps([low, high], estimates, failed_actions=[high.action])[0] is low
    # Clear fingers come before the kind: a neighbour under a finger of the across grasp (below CROWDED) puts a
    # clear grasp along the axis first; with both clear, across wins.
    near_neighbour = GraspCandidate(np.array([0.01, 0, 0.05, 0], np.float32), "across", 0.2, True, 0)
    along = GraspCandidate(np.array([0.01, 0, 0.05, 1.57], np.float32), "along", 0.0, True, 0)
    assert rank_grasps([near_neighbour, along], estimates)[0] is along
    assert rank_grasps([along, high], estimates)[0] is high


def _config(**kwargs):
    values = dict(parts=tuple(SMALL_PILE.items()), methods=("oracle",), piles=3, seed=1, image_size=(96, 72))
    return BinBenchmarkConfig(**(values | kwargs))


def test_benchmark_json_and_shards_merge_to_the_unsharded_run(tmp_path):
    config = _config(piles=2)
    whole = run_bin_benchmark(config, workers=1, progress=False)
    paths = write_bin_outputs(whole, tmp_path / "whole")
    data = json.loads(paths["json"].read_text())
    assert len(data["episodes"]) == 2
    for record in data["episodes"]:
        assert set(EPISODE_KEYS) <= set(record)
        assert isinstance(record["cleared"], bool) and record["method"] == "oracle"
        assert (
            record["picks"] + record["grasp_only"] + record["fails"] + record["wrong_part_picks"] == record["attempts"]
        )
    assert [r["seed"] for r in data["episodes"]] == [1, 2]
    summary = data["summary"]["results"]["oracle"]
    assert summary["clearance"]["total"] == 2 and len(summary["clearance"]["interval_95"]) == 2
    table = paths["table"].read_text()
    assert paths["chart"].stat().st_size > 0
    assert "placed per target instance" in table and "placements per hour" in table
    # A job array: each shard through the CLI into one folder, then the merge; the same episodes as one run.
    sharded = tmp_path / "sharded"
    common = ["benchmark", "bin", "--methods", "oracle", "--parts", "toolcap:2,shaft:1", "--piles", "2", "--seed", "1",
              "--image-size", "96x72", "--workers", "1", "--no-progress", "--out", str(sharded)]  # fmt: skip
    for index in range(2):
        assert main([*common, "--shard", f"{index}/2"]) == 0
    assert not (sharded / "bin_episodes.json").exists()
    assert main(["benchmark", "bin", "--merge", "--out", str(sharded)]) == 0
    merged = json.loads((sharded / "bin_episodes.json").read_text())
    drop = ("seconds", "perception_seconds")  # wall times
    assert [{k: v for k, v in e.items() if k not in drop} for e in merged["episodes"]] == [
        {k: v for k, v in e.items() if k not in drop} for e in whole.episodes
    ]
    timed = ("placements_per_hour", "ratio_to_oracle")  # they charge the measured perception time

    def untimed(results: dict) -> dict:
        return {m: {k: v for k, v in per.items() if k not in timed} for m, per in results.items()}

    assert untimed(merged["summary"]["results"]) == untimed(whole.summary()["results"])


def test_merge_refuses_missing_shards(tmp_path):
    write_bin_shard(run_bin_benchmark(_config(piles=1), workers=1, progress=False, shard=(0, 2)), tmp_path)
    with pytest.raises(DonGymError, match=r"shards \[1\] of 2 are missing"):
        merge_bin_shards(tmp_path)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--parts", "toolcap:3,bolt:2"], "bolt"),
        (["--parts", "toolcap:-1,shaft:2"], "-1"),
        (["--target", "shaft", "--parts", "toolcap:3"], "target='shaft'"),
        (["--methods", "shaft/supervised-edge"], "shaft"),
        (["--shard", "2/2"], "--shard '2/2'"),
        (["--shard", "x"], "--shard 'x'"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, args, message):
    capsys.readouterr()
    code = main(["benchmark", "bin", "--quick", "--no-progress", "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code != 0 and len(lines) == 1 and message in lines[0], err
    assert not (tmp_path / "o" / "bin_episodes.json").exists()


def test_a_network_of_several_parts_benchmarks_for_its_target(tmp_path):
    from don_gym.data.bin_dataset import build_bin_dataset
    from don_gym.data.build import DatasetConfig
    from don_gym.evaluation.bin_benchmark import check_targets, describe_methods
    from don_gym.learning.train import TrainConfig, train

    data = tmp_path / "data"
    build_bin_dataset(DatasetConfig(scenes=1, frames_per_scene=2, image_size=(64, 48), seed=17), SMALL_PILE, data,
                      progress=False)  # fmt: skip
    config = TrainConfig(
        method="supervised-edge", data=str(data), out=str(tmp_path / "run"), steps=2, batch_size=2,
        crop_size=(64, 48), device="cpu", threads=1, checkpoint_every=100,
    )  # fmt: skip
    train(config, progress=False)
    network = str(tmp_path / "run" / "model.safetensors")
    for target in ("toolcap", "shaft"):  # one network, either part the target
        info = describe_methods(_config(methods=(network,), target=target))[network]
        assert info["method"] == "supervised-edge" and sorted(info["parts"]) == ["shaft", "toolcap"]
    result = run_bin_benchmark(_config(methods=(network,), piles=1, image_size=None), workers=1, progress=False)
    assert result.config.image_size == (64, 48)  # the network's training size
    assert len(result.episodes) == 1 and set(EPISODE_KEYS) <= set(result.episodes[0])
    # A supervised network of several parts is held to targets relative to the oracle on the same piles.
    assert any("no oracle in the run" in line for line in check_targets(result))
    both = run_bin_benchmark(_config(methods=("oracle", network), piles=1, image_size=None), workers=1, progress=False)
    lines = check_targets(both)
    assert any(line.startswith(f"{network}: placed per target") and "the oracle's" in line for line in lines)
    assert any(line.startswith("oracle: places") for line in lines)


def _standing_toolcap_top():
    """The toolcap, its targets, and the observed points of it standing on the floor (z = 0) with its axis at
    (0.10, 0.20) (a disc of points at its length's height, the floor around it), and a point on its top's rim."""
    from don_gym.sim.bin_task import lying_footprint_m

    toolcap = load_object("toolcap")
    length, diameter = lying_footprint_m(toolcap)
    r, a = np.meshgrid(np.linspace(0, diameter / 2, 8), np.linspace(0, 2 * np.pi, 24))
    disc = np.stack([0.10 + r.ravel() * np.cos(a.ravel()), 0.20 + r.ravel() * np.sin(a.ravel())], axis=1)
    floor = np.stack(np.meshgrid(np.linspace(0.0, 0.2, 40), np.linspace(0.1, 0.3, 40)), axis=-1).reshape(-1, 2)
    cloud = np.concatenate([np.c_[disc, np.full(len(disc), length)], np.c_[floor, np.zeros(len(floor))]])
    return toolcap, axis_end_targets(toolcap), cloud, np.array([[0.10 + 0.8 * diameter / 2, 0.20, length]])


def test_a_part_standing_upright_is_found_from_its_top():
    from don_gym.agents.bin_agent import standing_from_coincident_rings

    # Both rings' candidates coincide on the top's rim.
    toolcap, targets, cloud, rim = _standing_toolcap_top()
    found = standing_from_coincident_rings([rim, rim + [0, 0.002, 0]], [], cloud, toolcap, targets, 0.0)
    assert len(found) == 1 and found[0].standing
    np.testing.assert_allclose(found[0].axis_points_world[:, :2], [[0.10, 0.20]] * 2, atol=0.003)
    # The same top 6 mm lower is a part lying down (its top is its diameter high), not one standing.
    lower = cloud - [0, 0, 0.006]
    assert standing_from_coincident_rings([rim - [0, 0, 0.006]] * 2, [], lower, toolcap, targets, 0.0) == []


def test_one_end_ring_and_the_middle_ring_give_the_axis_when_the_other_end_falls_short():
    from don_gym.agents.bin_agent import pair_with_middle_ring

    toolcap = load_object("toolcap")
    targets = axis_end_targets(toolcap)
    a_minus, a_plus = (float(v) for v in targets.axial_positions_m)
    middle = (a_minus + a_plus) / 2
    camera = np.eye(4)
    camera[:3, 3] = [0.0, 0.0, 0.5]
    # A part lying along +x, axis 0.02 m above the floor, seen from straight above. Its plus ring's match fell 15 mm
    # short, towards the middle (as a network's did on development piles): the two ends do not pair.
    axis_z, r, r_middle = 0.02, float(targets.radii_m[0]), float(np.max(targets.radii_m))
    minus = np.array([[a_minus, 0.0, axis_z + r]])
    plus_short = np.array([[a_plus - 0.015, 0.0, axis_z + float(targets.radii_m[1])]])
    middle_point = np.array([[middle, 0.0, axis_z + r_middle]])
    depth = np.full((60, 60), 0.5 - axis_z - r, np.float32)
    pixels = [np.array([[10.0, 30.0]]), np.array([[25.0, 30.0]]), np.array([[18.0, 30.0]])]
    zero = [np.zeros(1)] * 2
    assert pair_ring_candidates([minus, plus_short], pixels[:2], zero, depth, camera, targets) == []
    found = pair_with_middle_ring(
        [(minus, pixels[0], np.zeros(1)), (plus_short, pixels[1], np.zeros(1))],
        (middle_point, pixels[2], np.zeros(1)), depth, camera, targets, floor_z_m=0.0,
    )  # fmt: skip
    assert len(found) == 1  # one middle match, one instance
    np.testing.assert_allclose(found[0].axis_points_world, [[a_minus, 0, axis_z], [a_plus, 0, axis_z]], atol=1e-3)
    # The plus end with the middle gives it the other way round when the minus ring is not matched at all.
    plus = np.array([[a_plus, 0.0, axis_z + float(targets.radii_m[1])]])
    found = pair_with_middle_ring(
        [(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)), (plus, pixels[1], np.zeros(1))],
        (middle_point, pixels[2], np.zeros(1)), depth, camera, targets, floor_z_m=0.0,
    )  # fmt: skip
    assert len(found) == 1
    np.testing.assert_allclose(found[0].axis_points_world, [[a_minus, 0, axis_z], [a_plus, 0, axis_z]], atol=1e-3)
    # A middle match a whole spacing away is no partner.
    far_middle = middle_point + [0.03, 0, 0]
    assert (
        pair_with_middle_ring(
            [(minus, pixels[0], np.zeros(1)), (np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0))],
            (far_middle, pixels[2], np.zeros(1)),
            depth,
            camera,
            targets,
            floor_z_m=0.0,
        )  # fmt: skip
        == []
    )


def test_a_standing_part_is_found_under_a_single_ring_s_match_as_a_last_resort():
    from don_gym.agents.bin_agent import standing_from_coincident_rings
    from don_gym.sim.bin_task import lying_footprint_m

    toolcap, targets, cloud, rim = _standing_toolcap_top()
    diameter = lying_footprint_m(toolcap)[1]
    # The minus ring matched on the rim; the plus ring's match lies at the part's foot, on the floor beside it.
    foot = np.array([[0.10 + diameter / 2 + 0.004, 0.20 - 0.02, 0.005]])
    assert standing_from_coincident_rings([rim, foot], [], cloud, toolcap, targets, 0.0) == []
    found = standing_from_coincident_rings([rim, foot], [], cloud, toolcap, targets, 0.0, single_ring=True)
    assert len(found) == 1 and found[0].standing  # one part, however many of its matches
    np.testing.assert_allclose(found[0].axis_points_world[:, :2], [[0.10, 0.20]] * 2, atol=0.003)
    # The plus ring's match alone on the rim is enough too; a top a lying part's height is not a standing part.
    assert len(standing_from_coincident_rings([np.zeros((0, 3)), rim], [], cloud, toolcap, targets, 0.0, True)) == 1
    lower = cloud - [0, 0, 0.006]
    assert standing_from_coincident_rings([rim - [0, 0, 0.006], foot], [], lower, toolcap, targets, 0.0, True) == []


def test_a_lying_instance_s_axis_is_fitted_to_the_observed_surface():
    import time

    from don_gym.agents.bin_agent import radial_profile_m, refine_axis_with_depth

    toolcap = load_object("toolcap")
    targets = axis_end_targets(toolcap)
    profile = radial_profile_m(toolcap)
    a0, a1 = (float(v) for v in targets.axial_positions_m)
    # The upper half of a toolcap's outer surface, lying along +x with its axis 14 mm above the floor at (0.5, 0),
    # sampled as a camera above would see it, and the floor around it.
    axial, angle = np.meshgrid(np.linspace(-0.02, 0.02, 60), np.linspace(0.05, np.pi - 0.05, 40))
    position = axial.ravel() + (a0 + a1) / 2
    r = np.interp(position, *profile)
    surface = np.stack(
        [0.5 + axial.ravel(), r * np.cos(angle.ravel()), 0.014 + r * np.sin(angle.ravel())], axis=1
    )  # fmt: skip
    floor = np.stack(np.meshgrid(np.linspace(0.44, 0.56, 50), np.linspace(-0.06, 0.06, 50)), -1).reshape(-1, 2)
    cloud = np.concatenate([surface, np.c_[floor, np.zeros(len(floor))]])
    true_axis = np.array([[0.5 + a0 - (a0 + a1) / 2, 0, 0.014], [0.5 + a1 - (a0 + a1) / 2, 0, 0.014]])
    # The descriptors' estimate: 20 degrees off in yaw and 3 mm to the side.
    yaw = np.deg2rad(20.0)
    turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    centre = true_axis.mean(axis=0)
    off = (true_axis - centre) @ turn.T + centre + [0, 0.003, 0]
    start = time.perf_counter()
    refined = refine_axis_with_depth(InstanceEstimate(off, occlusion=0.1), cloud, targets, profile, 0.0)
    assert time.perf_counter() - start < 1.0
    assert refined.occlusion == 0.1  # only the axis changes
    error_deg = np.degrees(np.arccos(abs(refined.direction @ [1.0, 0, 0])))
    assert error_deg < 3.0 and refined.direction[0] > 0  # which end is which stays the estimate's
    np.testing.assert_allclose(refined.axis_points_world.mean(axis=0), centre, atol=0.0015)
    # A standing estimate, or one with hardly a point near it, is kept as it is.
    standing = InstanceEstimate(np.array([[0.5, 0, 0.01], [0.5, 0, 0.03]]))
    assert refine_axis_with_depth(standing, cloud, targets, profile, 0.0) is standing
    lonely = InstanceEstimate(off + [0.3, 0, 0])
    assert refine_axis_with_depth(lonely, cloud, targets, profile, 0.0) is lonely
