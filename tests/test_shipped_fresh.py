"""The shipped networks are never stale: the code that feeds and uses them is what they were made with
(or shown unaffected by), and the behavioural fingerprints that show it still hold on this machine."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import check_shipped  # noqa: E402

from don_gym.wrappers.simulated_keypoints import KeypointNoiseModel, shipped_noise_path  # noqa: E402
from don_gym.zoo import shipped_names  # noqa: E402

RERUN = (
    "Run `python benchmarks/check_shipped.py`: it recomputes the behavioural fingerprints and, if all are within "
    "tolerance (the networks are shown unaffected), records the current sources in don_gym/shipped/MANIFEST.json; "
    "otherwise it tells you to regenerate the networks with `python benchmarks/train_shipped.py`."
)


def test_shipped_networks_were_made_with_the_current_sources() -> None:
    manifest = check_shipped.read_manifest()
    stale = check_shipped.stale_networks(manifest, check_shipped.source_hashes())
    details = "; ".join(f"{name}: {', '.join(changes)}" for name, changes in stale.items())
    assert not stale, (
        f"the code that shapes the shipped networks' inputs or their use changed since they were made or last "
        f"checked ({details}). {RERUN}"
    )


def test_fingerprints_hold_on_this_machine() -> None:
    manifest = check_shipped.read_manifest()
    reference = check_shipped.read_fingerprints()
    assert reference, f"no {check_shipped.FINGERPRINTS_PATH.name} beside the manifest. {RERUN}"
    # A network with other weights than recorded is the first test's business; its output has no reference.
    recorded = [
        n
        for n in shipped_names()
        if manifest["networks"].get(n, {}).get("weights_sha256") == check_shipped.weights_sha256(n)
    ]
    current = check_shipped.compute_fingerprints(recorded, reference[check_shipped.INPUT_KEY])
    problems = check_shipped.compare(reference, current)
    assert not problems, "fingerprints outside their tolerance:\n" + "\n".join(problems) + f"\n{RERUN}"


def test_shipped_noise_models_were_measured_on_the_shipped_networks() -> None:
    stale = []
    for name in shipped_names():
        path = shipped_noise_path(name)
        assert path.is_file(), f"{name}: no default keypoint noise model {path.name}"
        if KeypointNoiseModel.load(path).source_weights_sha256 != check_shipped.weights_sha256(name):
            stale.append(name)
    assert not stale, (
        f"keypoint noise models not measured on the shipped networks' current weights: {', '.join(stale)}. "
        f"Run `python benchmarks/make_keypoint_noise.py {' '.join(stale)}`."
    )


def test_source_hash_ignores_comments_docstrings_and_layout() -> None:
    base = 'def f(x):\n    """Doc."""\n    return x + 1  # one\n'
    same = '"""Module doc."""\n\n\ndef f(x):\n    # why\n    return (x +\n            1)\n'
    assert check_shipped.normalized_source_hash(base) == check_shipped.normalized_source_hash(same)
    assert check_shipped.normalized_source_hash(base) != check_shipped.normalized_source_hash(base.replace("1", "2"))
    hashes = check_shipped.source_hashes()
    assert "don_gym.descriptors.embed" in hashes["descriptor fields"]  # a package stands for all its modules
    assert "don_gym.agents.axis_grasp" in hashes["use"]


def test_check_records_unaffected_networks_and_flags_moved_fingerprints(tmp_path: Path, monkeypatch) -> None:
    """The bookkeeping on a fake state: fingerprints and sources are stand-ins, the networks the real files."""
    monkeypatch.setattr(check_shipped, "MANIFEST_PATH", tmp_path / "MANIFEST.json")
    monkeypatch.setattr(check_shipped, "FINGERPRINTS_PATH", tmp_path / "fingerprints.npz")
    names = shipped_names()
    assert names, "no shipped networks"
    sources = {"use": {"don_gym.perception.keypoints": "a"}}
    fingerprints = {"field/x/descriptors": np.zeros(4), check_shipped.INPUT_KEY: np.zeros((2, 2, 3), np.uint8)}
    fingerprints |= {f"network/{n}": np.zeros(3) for n in names}
    monkeypatch.setattr(check_shipped, "source_hashes", lambda: sources)
    monkeypatch.setattr(check_shipped, "compute_fingerprints", lambda networks, image=None: dict(fingerprints))

    report = check_shipped.check_shipped()  # no manifest yet: every network is recorded, references made
    assert report.ok and report.rebaselined and report.recorded_new == names
    assert not check_shipped.stale_networks(check_shipped.read_manifest(), sources)

    sources = {"use": {"don_gym.perception.keypoints": "b"}}  # a source edit ...
    stale = check_shipped.stale_networks(check_shipped.read_manifest(), sources)
    assert stale == {n: ["use: don_gym.perception.keypoints"] for n in names}
    fingerprints["field/x/descriptors"] = np.full(4, 0.01)  # ... that moves a fingerprint within tolerance
    report = check_shipped.check_shipped(write=False)
    assert report.ok and report.shown_unaffected == names and not report.written
    assert check_shipped.stale_networks(check_shipped.read_manifest(), sources)  # nothing written
    report = check_shipped.check_shipped()
    assert report.ok and not check_shipped.stale_networks(check_shipped.read_manifest(), sources)
    assert check_shipped.read_fingerprints()["field/x/descriptors"].max() == 0.0  # references kept

    sources = {"use": {"don_gym.perception.keypoints": "c"}}  # an edit that moves it too far: stale until regenerated
    fingerprints["field/x/descriptors"] = np.full(4, 0.5)
    report = check_shipped.check_shipped()
    assert not report.ok and report.stale == names and "field/x/descriptors" in report.problems[0]
    assert any("train_shipped.py --objects" in line for line in report.lines())
    assert set(check_shipped.stale_networks(check_shipped.read_manifest(), sources)) == set(names)
    regenerated = [n for n in names if n.startswith(names[0].split("/")[0] + "/")]
    report = check_shipped.check_shipped(regenerated=regenerated)
    still_stale = set(check_shipped.stale_networks(check_shipped.read_manifest(), sources))
    assert still_stale == set(names) - set(regenerated) and not report.rebaselined
    report = check_shipped.check_shipped(regenerated=sorted(still_stale))
    assert report.ok and report.rebaselined
    assert not check_shipped.stale_networks(check_shipped.read_manifest(), sources)
    assert check_shipped.read_fingerprints()["field/x/descriptors"].max() == pytest.approx(0.5)


def test_tolerances_allow_a_few_outlying_pixels_but_not_a_shift() -> None:
    reference = {"dataset/rgb": np.zeros((10, 10, 3)), "network/a/b": np.zeros((3, 3, 3))}
    nearly = {"dataset/rgb": reference["dataset/rgb"].copy(), "network/a/b": np.full((3, 3, 3), 1e-3)}
    nearly["dataset/rgb"][0, 0] = 255.0  # one edge pixel of 100 flipped
    assert check_shipped.compare(reference, nearly) == []
    shifted = {"dataset/rgb": np.full((10, 10, 3), 30.0), "network/a/b": np.full((3, 3, 3), 0.01)}
    assert [p.split(":")[0] for p in check_shipped.compare(reference, shifted)] == ["dataset/rgb", "network/a/b"]
    assert check_shipped.compare(reference, {"dataset/rgb": np.zeros((5, 5, 3))})[0].startswith("dataset/rgb: shape")
