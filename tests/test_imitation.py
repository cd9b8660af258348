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

from don_gym.evaluation.demonstrations import RecordSettings, read_demonstrations, record_demonstrations  # noqa: E402
from don_gym.evaluation.imitation import (  # noqa: E402
    GENERALISATION,
    ImitationConfig,
    evaluate_policy,
    input_for_part,
    run_imitation,
)
from don_gym.evaluation.imitation_policy import (  # noqa: E402
    HISTORY,
    demo_steps,
    features,
    image,
    image_statistics,
    train_policy,
)
from don_gym.objects import load_object  # noqa: E402


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
    rows = [features(kind, step) for step in demo_steps(kind, first, load_object("toolcap"))]
    vectors = np.concatenate([np.stack([rows[0]] + rows[:-1]), np.stack(rows)], axis=1)
    assert vectors.shape[1] == HISTORY * len(rows[0])
    with torch.inference_mode():
        predicted = policy(torch.from_numpy(vectors)).numpy()
    expert = demos.actions[0]
    # Far better than the best constant action: the policy learned the expert's map from state to action.
    assert np.mean((predicted - expert) ** 2) < 0.3 * np.mean((expert - expert.mean(axis=0)) ** 2)
    evaluation = evaluate_policy(policy, kind, "toolcap", "lift", episodes=1)
    assert evaluation.wins in (0, 1) and evaluation.steps >= 1 and evaluation.seconds > 0


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


def test_descriptor_image_input_goes_through_the_image_encoder(tmp_path):
    """ "descriptors:<network>": the network's descriptor image of the wrist camera, recorded and fed to the same
    spatial-softmax encoder as RGB-D."""
    torch.set_num_threads(1)
    kind = "descriptors:toolcap/supervised-edge"
    settings = RecordSettings(rgbd_size=(48, 36), don_size=(160, 120))
    # A small DON frame keeps the test fast; the wrapper says the network was trained on larger ones.
    with pytest.warns(UserWarning, match="trained on 640x480 images but gets 160x120"):
        path = record_demonstrations(
            tmp_path / "d.hdf5", "toolcap", "lift", episodes=1, seed=2, kinds=[kind], settings=settings,
            progress=False,
        )  # fmt: skip
    demos = read_demonstrations(path, count=1)
    descriptors = demos.observations[0]["descriptors-toolcap-supervised-edge.descriptors"]
    assert descriptors.dtype == np.uint8 and descriptors.shape[1:] == (36, 48, 3)
    assert descriptors.std() > 5  # an image of the part and the table, not a constant
    policy = train_policy(kind, demos, steps=5, seed=0)
    assert policy.encoder is not None and policy.encoder.net[0].in_channels == 3
    # The encoder sees each channel standardised by the demonstrations' own statistics.
    pixels = descriptors.astype(np.float64).transpose(3, 0, 1, 2).reshape(3, -1) / 255.0
    np.testing.assert_allclose(policy.image_mean.numpy(), pixels.mean(axis=1), atol=2e-3)
    np.testing.assert_allclose(policy.image_std.numpy(), np.maximum(pixels.std(axis=1), 1e-3), rtol=2e-2, atol=2e-3)
    step = demo_steps(kind, demos.observations[0], load_object("toolcap"))[0]
    assert image(kind, step).shape == (3, 36, 48)
    with pytest.warns(UserWarning, match="trained on 640x480 images but gets 160x120"):
        evaluation = evaluate_policy(policy, kind, "toolcap", "lift", episodes=1, settings=settings)
    assert evaluation.steps >= 1


def test_image_statistics_hold_over_millions_of_pixels():
    """A float32 mean over the pixels of a few hundred frames drifts (0.998 for 0.97 at 800x96x128 channels-last);
    the per-channel statistics must not."""
    frames = [np.full((400, 2, 96, 128), 0.97, dtype=np.float16) for _ in range(2)]
    frames[1][:, 1] = 0.25
    mean, std = image_statistics(frames)
    assert mean.shape == std.shape == (2,) and mean.dtype == np.float32
    np.testing.assert_allclose(mean, [0.97, (0.97 + 0.25) / 2], atol=1e-3)
    np.testing.assert_allclose(std, [0.0, 0.36], atol=1e-3)


def test_generalisation_columns_and_the_cost_of_a_step(lift_demos, tmp_path):
    assert input_for_part("don:toolcap/supervised-edge", "toolcap", "shaft") == "don:shaft/supervised-edge"
    assert input_for_part("state", "toolcap", "shaft") == "state"
    assert input_for_part("don:runs/mine.safetensors", "toolcap", "shaft") is None
    config = ImitationConfig(inputs=("state", "true"), demonstrations=(1, 2), episodes=1, train_steps=5,
                             generalisation_n=2)  # fmt: skip
    result = run_imitation(config, tmp_path, demos=lift_demos, progress=False)
    assert set(result.generalisation) == set(GENERALISATION)
    assert all(result.generalisation[c][name] in (0, 1) for c in GENERALISATION for name in config.inputs)
    assert (tmp_path / "demos_shaft_lift.hdf5").is_file()
    assert read_demonstrations(tmp_path / "demos_shaft_lift.hdf5").part == "shaft"
    assert all(result.seconds_per_step[name] > 0 for name in config.inputs)
    header = result.table().splitlines()[0]
    assert "random background (N = 2)" in header and "shaft (N = 2)" in header and "ms / step" in header
    assert len(result.table().splitlines()) == 2 + len(config.inputs)


def test_policies_cloned_side_by_side_give_the_figures_of_one_process(lift_demos, tmp_path):
    torch.set_num_threads(1)  # as in each worker: the same training arithmetic
    config = ImitationConfig(inputs=("state", "true"), demonstrations=(2, 3), episodes=2, train_steps=300,
                             generalisation_n=3)  # fmt: skip
    alone = run_imitation(config, tmp_path / "one", demos=lift_demos, progress=False, jobs=1)
    shaft_demos = tmp_path / "one" / "demos_shaft_lift.hdf5"  # the other part's, recorded by the first run
    side_by_side = run_imitation(
        config, tmp_path / "two", demos=lift_demos, progress=False, jobs=2, other_demos=shaft_demos
    )
    assert not (tmp_path / "two" / "demos_shaft_lift.hdf5").exists()  # taken, not recorded again
    assert side_by_side.wins == alone.wins and side_by_side.generalisation == alone.generalisation
    with pytest.raises(DonGymError, match="are of the part 'toolcap'; expected 'shaft'") as error:
        run_imitation(config, tmp_path, demos=lift_demos, progress=False, other_demos=lift_demos)
    assert "\n" not in str(error.value)
    assert set(side_by_side.seconds_per_step) == set(config.inputs)
    with pytest.raises(DonGymError, match="jobs=0: expected a positive number") as error:
        run_imitation(config, tmp_path, demos=lift_demos, progress=False, jobs=0)
    assert "\n" not in str(error.value)


def test_bad_generalisation_and_input_names_are_one_line_errors(lift_demos, tmp_path):
    cases = [
        (ImitationConfig(inputs=("true",), demonstrations=(2,), generalisation_n=3), r"generalisation_n=3: expected"),
        (ImitationConfig(inputs=("descriptors:",), demonstrations=(2,)), "input 'descriptors:' is unknown"),
    ]
    for config, message in cases:
        with pytest.raises(DonGymError, match=message) as error:
            run_imitation(config, tmp_path, demos=lift_demos, progress=False)
        assert "\n" not in str(error.value)


def test_cli_refuses_more_demonstrations_than_recorded(lift_demos):
    command = [sys.executable, "-m", "don_gym.cli", "benchmark", "imitation", "--inputs", "true", "--demos", "2", "9",
               "--episodes", "1", "--demos-file", str(lift_demos), "--no-progress"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "count=9" in done.stderr and "hold 3" in done.stderr


def test_training_on_an_input_the_demonstrations_lack_is_a_one_line_error(lift_demos):
    demos = read_demonstrations(lift_demos, count=1)
    for kind, message in [("rgbd", r"lack the input 'rgbd'; they have \['state', 'true'\]"),
                          ("pixels", "input 'pixels' is unknown")]:  # fmt: skip
        with pytest.raises(DonGymError, match=message) as error:
            train_policy(kind, demos, steps=1)
        assert "\n" not in str(error.value)
