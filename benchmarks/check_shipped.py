"""Are the networks shipped in don_gym/shipped still what the code that feeds and uses them expects?

``don_gym/shipped/MANIFEST.json`` records per network its weights' sha256 and the sources it was made with
or last shown unaffected by: per concern (:data:`CONCERNS`), the sha256 of each module's AST without
docstrings (comment, docstring and layout edits do not count); ``tests/test_shipped_fresh.py`` fails when
they change. This script then compares behavioural fingerprints (:func:`compute_fingerprints`) with
``don_gym/shipped/fingerprints.npz`` within tolerances: all hold, the networks are shown unaffected and the
current sources recorded; otherwise regenerate them with ``python benchmarks/train_shipped.py``, which
records what it ships (:func:`record_regenerated`).

    python benchmarks/check_shipped.py              # check, and record the sources if unaffected
    python benchmarks/check_shipped.py --dry-run    # check only, write nothing
    python benchmarks/check_shipped.py --baseline   # record everything as it is now (after training)

Training code (``train``, ``losses``, ``augment``, ``torch_data``, ``correspondences``) is not in the
manifest: it decides how well a network learns, not what a shipped network takes in or how it is used.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import importlib.util
import json
import sys
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from don_gym.learning.checkpoints import read_checkpoint_metadata
from don_gym.zoo import SHIPPED_DIR, shipped_names, shipped_path

MANIFEST_PATH = SHIPPED_DIR / "MANIFEST.json"
FINGERPRINTS_PATH = SHIPPED_DIR / "fingerprints.npz"

#: The modules that shape the shipped networks' inputs or their use, by concern (a package stands
#: for all its modules), and the fingerprints that show a change to them left the networks unaffected.
CONCERNS: dict[str, tuple[str, ...]] = {
    # The optimal descriptors: supervised training targets, the oracle and the agent's reference rings.
    "descriptor fields": ("don_gym.descriptors", "don_gym.objects"),
    # What the networks were trained on: recorded scenes, simulated depth, rendered targets, the format.
    "training data": (
        "don_gym.data.bin_dataset",
        "don_gym.data.build",
        "don_gym.data.dataset",
        "don_gym.data.fusion",
        "don_gym.geometry",
        "don_gym.data.render",
        "don_gym.sim.camera",
        "don_gym.sim.recorder",
        "don_gym.sim.sensor",
    ),
    # What the networks see in use: the env's wrist-camera observation of the part at rest.
    "observations": (
        "don_gym.sim.bullet",
        "don_gym.sim.env",
        "don_gym.sim.part",
        "don_gym.sim.robot",
        "don_gym.sim.task",
    ),
    # The networks themselves: architecture, preprocessing, loading.
    "networks": ("don_gym.learning.checkpoints", "don_gym.learning.model"),
    # How their descriptors become keypoints and a grasp.
    "use": (
        "don_gym.agents.axis_grasp",
        "don_gym.agents.bin_agent",
        "don_gym.perception.descriptor_sources",
        "don_gym.perception.keypoints",
        "don_gym.wrappers.descriptors",
        "don_gym.wrappers.keypoints",
    ),
}

#: Fingerprint tolerances by key prefix (the longest matching prefix wins): at most ``max_fraction`` of
#: the elements may differ by more than ``atol``. Never bit identity: floating point differs across
#: machines, and a camera pose a hair off moves the part's outline by a pixel.
TOLERANCES: dict[str, tuple[float, float]] = {
    "field/": (0.02, 0.0),
    "dataset/rgb": (12.0, 0.03),
    "dataset/depth": (0.003, 0.03),
    "dataset/mask": (0.5, 0.03),
    "dataset/target_mask": (0.5, 0.03),
    "dataset/descriptor": (0.03, 0.03),
    "dataset/T_world_camera": (1e-3, 0.0),
    "observation/rgb": (12.0, 0.03),
    "observation/depth": (0.003, 0.03),
    "observation/T_world_object": (1e-3, 0.0),
    "use/": (2e-3, 0.0),
    "network/": (2e-3, 0.0),
}

FIELD_OBJECTS = ("toolcap", "shaft")
FIELD_SAMPLES = 256
DATASET_SIZE = (64, 48)
OBSERVATION_SIZE = (160, 120)
#: Every n-th pixel of the env observation is kept (the networks' fixed input is that too), and of a
#: network's output on it.
OBSERVATION_STRIDE = 2
NETWORK_OUTPUT_STRIDE = 4
INPUT_KEY = "network_input/rgb"

# --- sources ---------------------------------------------------------------------------------------


def _is_string_statement(node: ast.AST) -> bool:
    return isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)


def _canonical(node: object) -> str:
    """A dump of the AST that is the same on every Python version the project supports: fields that
    are None or empty lists are left out (3.13's ``ast.dump`` omits them, 3.12 added ``type_params``)."""
    if isinstance(node, ast.AST):
        parts = []
        for name, value in ast.iter_fields(node):
            if value is None or (isinstance(value, list) and not value):
                continue
            if isinstance(value, list):
                # Docstrings and other bare strings are documentation: they do nothing.
                value = [v for v in value if not _is_string_statement(v)]
            parts.append(f"{name}={_canonical(value)}")
        return f"{type(node).__name__}({', '.join(parts)})"
    if isinstance(node, list):
        return "[" + ", ".join(_canonical(v) for v in node) + "]"
    return repr(node)


def normalized_source_hash(source: str) -> str:
    """sha256 of a module's AST without docstrings: comments, docstrings and layout do not change it."""
    return hashlib.sha256(_canonical(ast.parse(source)).encode()).hexdigest()


def module_files(name: str) -> dict[str, Path]:
    """``{module: file}`` of a module, or of every module of a package (not its subpackages)."""
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(f"{name}: not found; update CONCERNS in benchmarks/check_shipped.py")
    if not spec.submodule_search_locations:
        return {name: Path(spec.origin)}
    directory = Path(spec.origin).parent
    return {
        (name if path.stem == "__init__" else f"{name}.{path.stem}"): path for path in sorted(directory.glob("*.py"))
    }


def source_hashes() -> dict[str, dict[str, str]]:
    """``{concern: {module: sha256 of its normalised source}}`` for :data:`CONCERNS` as they are now."""
    return {
        concern: {
            module: normalized_source_hash(path.read_text())
            for name in names
            for module, path in sorted(module_files(name).items())
        }
        for concern, names in CONCERNS.items()
    }


def sources_version(hashes: Mapping[str, Mapping[str, str]]) -> str:
    """Short id of one state of all sources."""
    return hashlib.sha256(json.dumps(hashes, sort_keys=True).encode()).hexdigest()[:16]


def changed_modules(old: Mapping[str, Mapping[str, str]], new: Mapping[str, Mapping[str, str]]) -> list[str]:
    """``"concern: module"`` for every module added, removed or changed between two source states."""
    out = []
    for concern in sorted(set(old) | set(new)):
        before, after = old.get(concern, {}), new.get(concern, {})
        out += [f"{concern}: {m}" for m in sorted(set(before) | set(after)) if before.get(m) != after.get(m)]
    return out


def weights_sha256(name: str) -> str:
    """sha256 of a shipped network's weights as its metadata records it (the weights alone: the part and
    field tensors that ``train_shipped.py --restamp`` adds beside them are not covered)."""
    return read_checkpoint_metadata(SHIPPED_DIR / f"{name}.safetensors").weights_sha256


# --- fingerprints ----------------------------------------------------------------------------------


def _field_fingerprints() -> dict[str, np.ndarray]:
    from don_gym.descriptors import embed
    from don_gym.objects import load_object

    out = {}
    for name in FIELD_OBJECTS:
        field_ = embed(load_object(name), dim=3, symmetric=True)
        values = np.asarray(field_.vertex_descriptors, dtype=np.float32)
        rows = np.linspace(0, len(values) - 1, FIELD_SAMPLES).round().astype(int)
        out[f"field/{name}/shape"] = np.array(values.shape)
        out[f"field/{name}/descriptors"] = values[rows]
        out[f"field/{name}/background"] = np.asarray(field_.background, dtype=np.float32)
    return out


def _compact(image: np.ndarray) -> np.ndarray:
    """Images as stored: floats in half precision, far finer than their tolerances."""
    image = np.asarray(image)
    return image.astype(np.float16) if image.dtype.kind == "f" else image


def _dataset_fingerprints() -> dict[str, np.ndarray]:
    """One scene of two frames of the toolcap, built and read back as training reads it: the first
    frame's images and both camera poses."""
    from don_gym.data.build import DatasetConfig, build_dataset
    from don_gym.data.dataset import FRAME_KINDS, DONDataset

    config = DatasetConfig(object="toolcap", scenes=1, frames_per_scene=2, image_size=DATASET_SIZE, sensor="d435")
    with tempfile.TemporaryDirectory(prefix="don_gym_fingerprint_") as tmp:
        build_dataset(config, Path(tmp) / "data", progress=False)
        data = DONDataset(Path(tmp) / "data")
        out = {f"dataset/{kind}": _compact(data.image(0, 0, kind)) for kind in FRAME_KINDS}
        out["dataset/T_world_camera"] = data.scenes[0].T_world_camera.astype(np.float64)
    return out


def _observation_fingerprints() -> dict[str, np.ndarray]:
    """The env's first observation at fixed pose 0 (seed 0, D435), and the oracle agent's action on it."""
    from don_gym.agents import AxisGraspAgent
    from don_gym.sim.env import PickPlaceEnv

    env = PickPlaceEnv(object="toolcap", control="grasp", image_size=OBSERVATION_SIZE, sensor="d435")
    try:
        agent = AxisGraspAgent(env, model="oracle")
        obs, info = agent.env.reset(seed=0, options={"pose_id": 0})
        rgb = np.ascontiguousarray(obs["rgb"][::OBSERVATION_STRIDE, ::OBSERVATION_STRIDE])
        return {
            "observation/rgb": rgb,
            "observation/depth": _compact(obs["depth"][::OBSERVATION_STRIDE, ::OBSERVATION_STRIDE]),
            "observation/T_world_object": np.asarray(info["T_world_object"], dtype=np.float64),
            "use/oracle_action": np.asarray(agent.act(obs), dtype=np.float64),
            INPUT_KEY: rgb.copy(),
        }
    finally:
        env.close()


def network_fingerprint(name: str, rgb: np.ndarray) -> np.ndarray:
    """A shipped network's descriptors of ``rgb``, as the env wrappers and agents compute them, every
    :data:`NETWORK_OUTPUT_STRIDE`-th pixel."""
    from don_gym.objects import load_object
    from don_gym.perception.descriptor_sources import load_descriptor_source

    # A network of several parts is fingerprinted on the first part of its space, which its metadata names.
    source = load_descriptor_source(name, load_object(read_checkpoint_metadata(shipped_path(name)).object_name))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fixed image is not the size the network was trained at
        image = source.descriptor_image({"rgb": rgb})
    return np.asarray(image[::NETWORK_OUTPUT_STRIDE, ::NETWORK_OUTPUT_STRIDE], dtype=np.float32)


def compute_fingerprints(networks: Sequence[str], network_input: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Every fingerprint on this machine; the networks' outputs on ``network_input`` (None: this env
    observation's RGB, which then becomes the fixed input)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = _field_fingerprints() | _dataset_fingerprints() | _observation_fingerprints()
        if network_input is not None:
            out[INPUT_KEY] = np.asarray(network_input, dtype=np.uint8)
        out |= {f"network/{name}": network_fingerprint(name, out[INPUT_KEY]) for name in networks}
    finally:
        torch.set_num_threads(threads)
    return out


def tolerance(key: str) -> tuple[float, float]:
    """(atol, max_fraction) of a fingerprint key; exact for keys no prefix covers."""
    matches = [prefix for prefix in TOLERANCES if key.startswith(prefix)]
    return TOLERANCES[max(matches, key=len)] if matches else (0.0, 0.0)


def compare(
    reference: Mapping[str, np.ndarray], current: Mapping[str, np.ndarray], skip: Sequence[str] = ()
) -> list[str]:
    """One line per fingerprint of ``current`` that is missing from ``reference`` or outside its tolerance."""
    problems = []
    for key in sorted(current):
        if key in skip or key == INPUT_KEY:
            continue
        if key not in reference:
            problems.append(f"{key}: no reference fingerprint")
            continue
        ref, now = np.asarray(reference[key], dtype=np.float64), np.asarray(current[key], dtype=np.float64)
        if ref.shape != now.shape:
            problems.append(f"{key}: shape {now.shape}, reference {ref.shape}")
            continue
        atol, max_fraction = tolerance(key)
        if key.startswith("network/"):
            atol *= max(1.0, float(np.abs(ref).max(initial=0.0)))  # descriptors of any scale
        diff = np.abs(now - ref)
        off = float(np.mean(diff > atol)) if diff.size else 0.0
        if off > max_fraction or not np.isfinite(diff).all():
            problems.append(
                f"{key}: {100.0 * off:.1f}% of values differ by more than {atol:g} (allowed "
                f"{100.0 * max_fraction:g}%), largest difference {float(np.nanmax(diff, initial=0.0)):.4g}"
            )
    return problems


# --- manifest --------------------------------------------------------------------------------------


def read_manifest(path: Path | None = None) -> dict:
    """The manifest (default :data:`MANIFEST_PATH`), or an empty one when there is none yet."""
    path = MANIFEST_PATH if path is None else path
    if not path.is_file():
        return {"sources": {}, "networks": {}, "fingerprints": {}}
    return json.loads(path.read_text())


def read_fingerprints(path: Path | None = None) -> dict[str, np.ndarray]:
    """The reference fingerprints (default :data:`FINGERPRINTS_PATH`); empty when there are none yet."""
    path = FINGERPRINTS_PATH if path is None else path
    if not path.is_file():
        return {}
    with np.load(path) as arrays:
        return {key: arrays[key] for key in arrays.files}


def _write(manifest: dict, fingerprints: Mapping[str, np.ndarray]) -> None:
    from don_gym.io import atomic_path, write_text_atomic

    used = {n["sources"] for n in manifest["networks"].values()} | {manifest["fingerprints"].get("sources")}
    manifest["sources"] = {k: v for k, v in manifest["sources"].items() if k in used}
    with atomic_path(FINGERPRINTS_PATH) as tmp:
        np.savez_compressed(tmp, **fingerprints)
    write_text_atomic(MANIFEST_PATH, json.dumps(manifest, indent=1, sort_keys=True) + "\n")


def stale_networks(manifest: Mapping, hashes: Mapping[str, Mapping[str, str]]) -> dict[str, list[str]]:
    """``{network: changed modules}`` for every shipped network not recorded as made with ``hashes``
    (or with other weights than its file's), or why not when it is not in the manifest or has other weights."""
    version = sources_version(hashes)
    out = {}
    for name in shipped_names():
        record = manifest["networks"].get(name)
        if record is None:
            out[name] = ["not in the manifest"]
        elif record["weights_sha256"] != weights_sha256(name):
            out[name] = ["other weights than the manifest records"]
        elif record["sources"] != version:
            out[name] = changed_modules(manifest["sources"].get(record["sources"], {}), hashes)
    return out


@dataclass
class CheckReport:
    """What :func:`check_shipped` found and did."""

    fresh: list[str] = field(default_factory=list)  # made with the current sources (before or now)
    shown_unaffected: list[str] = field(default_factory=list)
    recorded_new: list[str] = field(default_factory=list)
    stale: list[str] = field(default_factory=list)  # still to be regenerated
    problems: list[str] = field(default_factory=list)
    rebaselined: bool = False
    written: bool = False

    @property
    def ok(self) -> bool:
        return not self.stale and not self.problems

    def lines(self) -> list[str]:
        out = []
        if self.shown_unaffected:
            out.append(f"shown unaffected (fingerprints within tolerance): {', '.join(self.shown_unaffected)}")
        if self.recorded_new:
            out.append(f"recorded as made with the current sources: {', '.join(self.recorded_new)}")
        if self.rebaselined:
            out.append("reference fingerprints recomputed: every network is made with the current sources")
        out += [f"  {p}" for p in self.problems]
        if self.stale:
            objects = sorted({n.split("/", 1)[0] for n in self.stale})
            out.append(
                f"STALE: {', '.join(self.stale)}: the fingerprints above moved, so these networks no longer see what "
                f"they were made for; regenerate them with `python benchmarks/train_shipped.py --objects "
                f"{' '.join(objects)}`"
            )
        elif self.problems:
            out.append("the fingerprints above do not hold on this machine although every network is fresh")
        out.append(("manifest written: " if self.written else "nothing written: ") + str(MANIFEST_PATH))
        return out


def check_shipped(regenerated: Sequence[str] = (), baseline: bool = False, write: bool = True) -> CheckReport:
    """Check the shipped networks against the current sources and update the manifest.

    A network in ``regenerated``, or whose weights differ from the manifest's, is new: it is recorded as
    made with the current sources (its output becomes its reference). Every other network made with
    other sources is shown unaffected, and recorded with the current sources, when all fingerprints hold;
    otherwise it stays stale. The reference fingerprints are recomputed when every network is (now)
    made with the current sources and at least one is new, or with ``baseline``.
    """
    manifest = read_manifest()
    hashes = source_hashes()
    version = sources_version(hashes)
    names = shipped_names()
    weights = {name: weights_sha256(name) for name in names}
    reference = read_fingerprints()
    old_input = None if baseline else reference.get(INPUT_KEY)
    current = compute_fingerprints(names, old_input)
    records = manifest["networks"]
    new = [
        n
        for n in names
        if baseline or n in regenerated or n not in records or records[n]["weights_sha256"] != weights[n]
    ]
    old = [n for n in names if n not in new]
    report = CheckReport(recorded_new=new)
    report.problems = compare(reference, current, skip=[f"network/{n}" for n in new])
    if not report.problems:
        report.shown_unaffected = [n for n in old if records[n]["sources"] != version]
    report.stale = [n for n in old if records[n]["sources"] != version and report.problems]
    report.fresh = [n for n in names if n not in report.stale]
    report.rebaselined = baseline or (not report.stale and bool(new) and bool(report.problems))
    if report.rebaselined:
        report.problems = []
    if write:
        manifest["sources"][version] = hashes
        manifest["networks"] = {
            n: {"weights_sha256": weights[n], "sources": version if n in report.fresh else records[n]["sources"]}
            for n in names
        }
        fingerprints = dict(current) if report.rebaselined else dict(reference)
        for n in new:
            fingerprints[f"network/{n}"] = current[f"network/{n}"]
        for key in [k for k in fingerprints if k.startswith("network/") and k.removeprefix("network/") not in names]:
            del fingerprints[key]
        if report.rebaselined or not manifest["fingerprints"]:
            manifest["fingerprints"] = {"sources": version}
        manifest["about"] = (
            "Written by benchmarks/check_shipped.py (do not edit): per shipped network its weights and the "
            "sources it was made with or last shown unaffected by; 'sources' holds per concern the sha256 of "
            "each module's normalised source."
        )
        _write(manifest, fingerprints)
        report.written = True
    return report


def record_regenerated(names: Sequence[str]) -> CheckReport:
    """For ``benchmarks/train_shipped.py``: record the networks it just shipped; prints the report."""
    report = check_shipped(regenerated=names)
    print("\n".join(report.lines()))
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--dry-run", action="store_true", help="check only; write nothing")
    group.add_argument(
        "--baseline",
        action="store_true",
        help="record every network as made with the current sources and recompute every reference "
        "fingerprint (right after training them all; train_shipped.py does this itself)",
    )
    args = parser.parse_args()
    report = check_shipped(baseline=args.baseline, write=not args.dry_run)
    print("\n".join(report.lines()))
    sys.exit(0 if report.ok else 1)


if __name__ == "__main__":
    main()
