"""Behaviour cloning at equal demonstrations (don_gym.evaluation.imitation) and its bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import don_gym  # noqa: F401  (registers the env ids)
from don_gym.errors import DonGymError

pytest.importorskip("h5py")

from don_gym.evaluation.demonstrations import read_demonstrations, record_demonstrations  # noqa: E402
from don_gym.evaluation.imitation import (  # noqa: E402
    HISTORY,
    ImitationConfig,
    evaluate_policy,
    features,
    run_imitation,
    train_policy,
)


@pytest.fixture(scope="module")
def lift_demos(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "lift.hdf5"
    return record_demonstrations(path, "toolcap", "lift", episodes=3, seed=0, kinds=["true"], progress=False)


@pytest.mark.parametrize("kind", ["state", "true"])
def test_cloned_policy_fits_the_expert(lift_demos, kind):
    torch.set_num_threads(1)
    demos = read_demonstrations(lift_demos, count=3)
    policy = train_policy(kind, demos, steps=400, seed=0)
    first = demos.observations[0]
    prefix = "" if kind == "state" else "true."
    rows = [
        features(kind, {**{k: first[k][t] for k in ("ee_pose", "gripper_width", "part_pose")},
                        **{k[len(prefix):]: first[k][t] for k in first if prefix and k.startswith(prefix)}})
        for t in range(len(demos.actions[0]))
    ]  # fmt: skip
    vectors = np.concatenate([np.stack([rows[0]] + rows[:-1]), np.stack(rows)], axis=1)
    assert vectors.shape[1] == HISTORY * len(rows[0])
    with torch.inference_mode():
        predicted = policy(torch.from_numpy(vectors)).numpy()
    expert = demos.actions[0]
    # Far better than the best constant action: the policy learned the expert's map from state to action.
    assert np.mean((predicted - expert) ** 2) < 0.3 * np.mean((expert - expert.mean(axis=0)) ** 2)
    wins = evaluate_policy(policy, kind, "toolcap", "lift", episodes=1)
    assert wins in (0, 1)


def test_bad_imitation_input_is_one_line_errors(lift_demos, tmp_path):
    cases = [
        (ImitationConfig(goal="place", inputs=("true",), demonstrations=(2,), episodes=1), "task 'lift'; expected"),
        (ImitationConfig(part="shaft", inputs=("true",), demonstrations=(2,), episodes=1), "part 'toolcap'; expected"),
        (ImitationConfig(inputs=("true",), demonstrations=(2, 50), episodes=1), "count=50: demonstrations .* hold 3"),
        (ImitationConfig(inputs=("rgbd",), demonstrations=(2,), episodes=1), r"lack the inputs \['rgbd'\]"),
        (ImitationConfig(inputs=("pixels",), demonstrations=(2,), episodes=1), "input 'pixels' is unknown"),
    ]
    for config, message in cases:
        with pytest.raises(DonGymError, match=message) as error:
            run_imitation(config, tmp_path, demos=lift_demos, progress=False)
        assert "\n" not in str(error.value)


def test_cli_refuses_demonstrations_of_another_task(lift_demos, tmp_path):
    command = [sys.executable, "-m", "don_gym.cli", "benchmark", "imitation", "--goal", "place", "--inputs", "true",
               "--demos", "2", "--episodes", "1", "--demos-file", str(lift_demos), "--no-progress"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "expected 'place'" in done.stderr
