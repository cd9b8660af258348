"""A model of the DON for fast RL iteration: keypoints from the true pose plus measured DON errors.

:class:`SimulatedKeypoints` adds the same keys as :class:`~don_gym.wrappers.KeypointObservation`
(``keypoint_pixels``, ``keypoint_points``, ``keypoint_confidence``) without rendering or running a
network: the true axis-end keypoints, hidden outside the wrist camera's view, plus errors drawn
from a :class:`KeypointNoiseModel`, a DON's keypoint errors measured by :func:`measure_keypoint_noise`
and stored as a small ``.npz`` file (defaults for the shipped networks: ``benchmarks/make_keypoint_noise.py``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from tqdm.auto import tqdm

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, invert_transform, transform_points
from don_gym.io import atomic_path
from don_gym.learning.model import DenseObjectNet
from don_gym.objects import ObjectModel
from don_gym.perception.descriptor_sources import (
    DEFAULT_AXIS_FRACTIONS,
    AxisEndTargets,
    DescriptorSource,
    axis_end_targets,
    env_object_model,
)
from don_gym.sim.sensor import SensorModel, depth_range_m
from don_gym.wrappers.keypoints import IMAGE_KEYS, POINT_BOUND_M, KeypointObservation
from don_gym.zoo import SHIPPED_DIR

#: Format tag stored in every noise-model file.
NOISE_FORMAT = "don_gym-keypoint-noise-1"
#: Suffix of noise-model files; the shipped networks' defaults are ``don_gym/shipped/<object>/<method><suffix>``.
NOISE_SUFFIX = ".keypoint-noise.npz"


# ------------------------------------------------------------------------------ true keypoints
def axis_points_world(object_model: ObjectModel, targets: AxisEndTargets, T_world_object: np.ndarray) -> np.ndarray:
    """(2, 3) world points on the part's axis at the two keypoints' axial positions (minus end first)."""
    axis = np.asarray(object_model.plus_axis, dtype=np.float64)
    local = object_model.center_of_mass + np.outer(targets.axial_positions_m, axis)
    return transform_points(np.asarray(T_world_object, dtype=np.float64), local)


def ring_points_facing(
    object_model: ObjectModel, targets: AxisEndTargets, T_world_object: np.ndarray, camera_position_world: np.ndarray
) -> np.ndarray:
    """(2, 3) world point of each keypoint ring that faces the camera: on the ring, in the plane of the
    axis and the camera centre. An exact descriptor image puts the soft match there (the middle of the
    ring's visible arc), so this is what a perfect DON's keypoints are."""
    T = np.asarray(T_world_object, dtype=np.float64)
    axis_world = T[:3, :3] @ np.asarray(object_model.plus_axis, dtype=np.float64)
    centres = axis_points_world(object_model, targets, T)
    towards = np.asarray(camera_position_world, dtype=np.float64)[None] - centres
    towards -= np.outer(towards @ axis_world, axis_world)
    norm = np.linalg.norm(towards, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    # A camera on the axis line sees the rings edge-on; any direction across the axis will do then.
    fallback = up - (up @ axis_world) * axis_world
    towards = np.where(norm > 1e-9, towards / np.maximum(norm, 1e-12), fallback / max(np.linalg.norm(fallback), 1e-12))
    return centres + targets.radii_m[:, None] * towards


def in_view(
    points_world: np.ndarray, T_world_camera: np.ndarray, intrinsics: CameraIntrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """``(uv, visible)``: (K, 2) float pixels of world points in a pinhole camera and (K,) bool, True
    where the point lies in front of the camera and projects inside the image. A field-of-view test
    only: nothing is checked for occlusion."""
    points_camera = transform_points(invert_transform(T_world_camera), np.asarray(points_world).reshape(-1, 3))
    z = points_camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack(
            [
                intrinsics.fx * points_camera[:, 0] / z + intrinsics.cx,
                intrinsics.fy * points_camera[:, 1] / z + intrinsics.cy,
            ],
            axis=1,
        )
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < intrinsics.width - 0.5)
    inside &= (uv[:, 1] >= -0.5) & (uv[:, 1] < intrinsics.height - 0.5)
    visible = (z > 0) & np.isfinite(uv).all(axis=1) & inside
    return np.where(np.isfinite(uv), uv, 0.0), visible


# -------------------------------------------------------------------------------- noise model
@dataclass(frozen=True)
class KeypointNoiseModel:
    """A DON's measured keypoint errors, to be resampled: a model of the DON, not the DON.

    Rows are keypoint observations in which the keypoint was in view, as measured by
    :func:`measure_keypoint_noise` (or converted from a tracking evaluation, :meth:`from_tracking`).

    Attributes:
        keypoint: (M,) int, which keypoint (0 minus end, 1 plus end) a row is of.
        error_camera_m: (M, 3) reported minus true point in the true camera frame (OpenCV axes), metres;
            a NaN row: the DON did not find the keypoint (no depth near its match, confidence 0). Frames
            whose two keypoints were swapped count as flips, their rows relative to the swapped truth.
        confidence: (M,) the DON's confidence in each row's match.
        flip_rate: fraction of frames with both keypoints found whose keypoints were swapped (the
            "upside down" confusion of the part's ends).
        object_name, object_mesh_hash: the part the errors were measured on.
        fractions: axial fractions of the two keypoints
        (:func:`~don_gym.perception.descriptor_sources.axis_end_targets`).
        source: what was measured (a network name), for reports.
        frames: frames measured.
        source_weights_sha256: the measured network's ``weights_sha256`` (its checkpoint metadata), so that
            a model left behind when the network is retrained is told apart; empty when the source was not a
            checkpoint (the oracle, a network object) or for files written before it was recorded.
    """

    keypoint: np.ndarray
    error_camera_m: np.ndarray
    confidence: np.ndarray
    flip_rate: float
    object_name: str
    object_mesh_hash: str
    fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS
    source: str = ""
    frames: int = 0
    source_weights_sha256: str = ""

    def __post_init__(self) -> None:
        keypoint = np.asarray(self.keypoint)
        errors = np.asarray(self.error_camera_m)
        confidence = np.asarray(self.confidence)
        m = len(keypoint)
        if keypoint.ndim != 1 or errors.shape != (m, 3) or confidence.shape != (m,):
            raise DonGymError(
                f"keypoint noise model: expected keypoint (M,), error_camera_m (M, 3), confidence (M,); got "
                f"{keypoint.shape}, {errors.shape}, {confidence.shape}"
            )
        if m and not set(np.unique(keypoint)) <= {0, 1}:
            raise DonGymError("keypoint noise model: keypoint indices must be 0 or 1 (the two axis-end keypoints)")
        if not 0.0 <= float(self.flip_rate) <= 1.0:
            raise DonGymError(f"keypoint noise model: flip_rate={self.flip_rate!r}, expected a fraction in [0, 1]")

    # ------------------------------------------------------------- files
    def save(self, path: str | Path) -> Path:
        """Write the model as ``.npz`` (arrays plus a JSON ``meta`` entry), atomically."""
        path = Path(path)
        meta = {
            "format": NOISE_FORMAT,
            "object_name": self.object_name,
            "object_mesh_hash": self.object_mesh_hash,
            "fractions": list(self.fractions),
            "flip_rate": float(self.flip_rate),
            "source": self.source,
            "frames": int(self.frames),
            "source_weights_sha256": self.source_weights_sha256,
        }
        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(
                tmp,
                meta=np.array(json.dumps(meta)),
                keypoint=np.asarray(self.keypoint, dtype=np.int8),
                error_camera_m=np.asarray(self.error_camera_m, dtype=np.float32),
                confidence=np.asarray(self.confidence, dtype=np.float32),
            )
        return path

    @classmethod
    def load(cls, path: str | Path) -> KeypointNoiseModel:
        """Read a file written by :meth:`save`; DonGymError naming the file when it is not one."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                arrays = {k: np.array(data[k]) for k in ("keypoint", "error_camera_m", "confidence")}
        except (OSError, KeyError, ValueError) as exc:
            raise DonGymError(f"keypoint noise model {str(path)!r}: not a readable noise-model file ({exc})") from exc
        if meta.get("format") != NOISE_FORMAT:
            raise DonGymError(
                f"keypoint noise model {str(path)!r}: format {meta.get('format')!r}, expected {NOISE_FORMAT!r}"
            )
        try:
            return cls(
                keypoint=arrays["keypoint"].astype(np.int64),
                error_camera_m=arrays["error_camera_m"].astype(np.float64),
                confidence=arrays["confidence"].astype(np.float64),
                flip_rate=float(meta["flip_rate"]),
                object_name=str(meta["object_name"]),
                object_mesh_hash=str(meta["object_mesh_hash"]),
                fractions=tuple(float(f) for f in meta["fractions"]),
                source=str(meta.get("source", "")),
                frames=int(meta.get("frames", 0)),
                source_weights_sha256=str(meta.get("source_weights_sha256", "")),
            )
        except DonGymError as exc:
            raise DonGymError(f"keypoint noise model {str(path)!r}: {exc}") from exc

    def check_fits(self, object_model: ObjectModel, fractions: tuple[float, float], what: str = "noise model") -> None:
        """DonGymError naming ``what`` unless the model was measured on this part and these keypoints."""
        if self.object_mesh_hash != object_model.mesh_hash:
            raise DonGymError(
                f"{what}: measured on object {self.object_name!r} (mesh {self.object_mesh_hash}), but the env's "
                f"part is {object_model.name!r} (mesh {object_model.mesh_hash})"
            )
        if not np.allclose(self.fractions, fractions):
            raise DonGymError(
                f"{what}: measured for keypoints at axial fractions {self.fractions}, expected {fractions}"
            )
        for k in (0, 1):
            if not np.any(np.asarray(self.keypoint) == k):
                raise DonGymError(f"{what}: holds no measurement of keypoint {k}")

    # ----------------------------------------------------------- making
    @classmethod
    def from_tracking(
        cls,
        error_3d_m: np.ndarray,
        depth_valid: np.ndarray,
        object_model: ObjectModel,
        flip_rate: float = 0.0,
        source: str = "tracking evaluation",
        seed: int = 0,
    ) -> KeypointNoiseModel:
        """A model from a tracking evaluation's per-match 3D errors
        (:class:`don_gym.evaluation.tracking_metrics.TrackingMatches` ``error_3d_m`` and ``depth_valid``): error
        magnitudes of random surface points in random directions (fixed here by ``seed``), matches
        without depth as misses, confidence 1. Coarser than :func:`measure_keypoint_noise`, which
        measures the two keypoints themselves (their soft match, their confidence and their flips);
        ``flip_rate`` has to be given."""
        magnitude = np.asarray(error_3d_m, dtype=np.float64).reshape(-1)
        valid = np.asarray(depth_valid, dtype=bool).reshape(-1) & np.isfinite(magnitude)
        rng = np.random.default_rng(seed)
        direction = rng.normal(size=(len(magnitude), 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        errors = np.where(valid[:, None], direction * np.where(valid, magnitude, 0.0)[:, None], np.nan)
        # Every match serves for both keypoints: the tracking protocol does not know them apart.
        return cls(
            keypoint=np.repeat([0, 1], len(errors)),
            error_camera_m=np.concatenate([errors, errors]),
            confidence=np.concatenate([valid, valid]).astype(np.float64),
            flip_rate=float(flip_rate),
            object_name=object_model.name,
            object_mesh_hash=object_model.mesh_hash,
            source=source,
            frames=0,
        )

    # --------------------------------------------------------- sampling
    def rows_of(self, k: int) -> np.ndarray:
        return np.flatnonzero(np.asarray(self.keypoint) == k)

    def summary(self) -> dict[str, Any]:
        """Error percentiles (mm) per keypoint, miss rate and flip rate, for reports."""
        out: dict[str, Any] = {"source": self.source, "frames": int(self.frames), "flip_rate": float(self.flip_rate)}
        for k in (0, 1):
            rows = self.rows_of(k)
            errors = np.asarray(self.error_camera_m)[rows]
            found = np.isfinite(errors).all(axis=1)
            magnitude_mm = 1000 * np.linalg.norm(errors[found], axis=1)
            out[f"keypoint_{k}"] = {
                "rows": int(len(rows)),
                "miss_rate": float(1 - found.mean()) if len(rows) else None,
                **{
                    f"p{p}_mm": (float(np.percentile(magnitude_mm, p)) if len(magnitude_mm) else None)
                    for p in (50, 90, 99)
                },
            }
        return out


def shipped_noise_path(name: str) -> Path:
    """Where the default noise model of shipped network ``name`` (``"toolcap/supervised-edge"``) lives."""
    return SHIPPED_DIR / f"{name}{NOISE_SUFFIX}"


def load_noise_model(noise: str | Path | KeypointNoiseModel) -> KeypointNoiseModel:
    """A noise model from a shipped network's name (its default model), a ``.npz`` path or a model."""
    if isinstance(noise, KeypointNoiseModel):
        return noise
    text = str(noise)
    shipped = shipped_noise_path(text)
    if "/" in text and not Path(text).suffix and shipped.is_file():
        return KeypointNoiseModel.load(shipped)
    if Path(text).is_file():
        return KeypointNoiseModel.load(text)
    files = sorted(SHIPPED_DIR.glob(f"*/*{NOISE_SUFFIX}"))
    available = [f"{p.parent.name}/{p.name[: -len(NOISE_SUFFIX)]}" for p in files]
    raise DonGymError(
        f"keypoint noise model {text!r}: neither a noise-model file nor a shipped network with a default model "
        f"(available: {', '.join(available) or 'none; run benchmarks/make_keypoint_noise.py'})"
    )


# ---------------------------------------------------------------------------------- the wrapper
class SimulatedKeypoints(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """A model of the DON: the axis-end keypoints from the true pose, no rendering, no network.

    Each step, for each of the two keypoints of :func:`~don_gym.perception.descriptor_sources.axis_end_targets`:
    the true point a perfect DON would report (:func:`ring_points_facing`, from the true object
    and camera poses in ``info``); hidden (confidence 0, point at the reported camera centre, as
    :class:`~don_gym.wrappers.KeypointObservation` reports a keypoint without depth) when it lies
    outside the wrist camera's view (:func:`in_view`: the env's intrinsics, no occlusion test: the
    gripper, hidden in the wrist images, and the part itself are not modelled as occluders) or outside
    the depth sensor's range (:func:`~don_gym.sim.sensor.depth_range_m` of the env's sensor preset: the
    D435 returns no depth nearer than 0.24 m at 640x480, so the real path loses the part there); else
    plus an error row drawn from ``noise`` (its camera-frame error, or a miss, and its confidence),
    independently per step and keypoint. With probability ``noise.flip_rate`` an episode has its
    two keypoints swapped throughout (the DON confusing the part's ends). ``noise=None``: exact
    keypoints, confidence 1.

    Args:
        env: a don_gym env (images not needed: make it with ``image_size=None`` for speed).
        noise: None, a :class:`KeypointNoiseModel`, a ``.npz`` path or a shipped network's name
            (its default model); checked to be of the env's part (DonGymError otherwise).
        field_of_view: False reports every keypoint as seen, wherever the camera looks and however near ("true
            state"); True hides those outside the camera's view or the sensor's depth range.
        keep_images: False drops ``rgb``/``depth`` if the env has them.
        fractions: axial fractions of the keypoints.

    The noise draws come from the wrapper's own generator, seeded by ``reset(seed=...)``, so the env's
    random stream is untouched.
    """

    def __init__(
        self,
        env: gym.Env,
        noise: str | Path | KeypointNoiseModel | None = None,
        *,
        field_of_view: bool = True,
        keep_images: bool = True,
        fractions: tuple[float, float] = DEFAULT_AXIS_FRACTIONS,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self, noise=noise, field_of_view=field_of_view, keep_images=keep_images, fractions=fractions
        )
        gym.Wrapper.__init__(self, env)
        self.object_model = env_object_model(env)
        self.targets = axis_end_targets(self.object_model, fractions=fractions)
        self.noise = None if noise is None else load_noise_model(noise)
        if self.noise is not None:
            self.noise.check_fits(self.object_model, self.targets.fractions, f"noise={str(noise)!r}")
            self._rows = [self.noise.rows_of(0), self.noise.rows_of(1)]
        self.field_of_view = bool(field_of_view)
        self.keep_images = bool(keep_images)
        sensor = getattr(env.unwrapped, "sensor", None)
        intrinsics_now = getattr(env.unwrapped, "intrinsics", None)
        #: (nearest, farthest) camera-frame depth (m) at which a keypoint can be seen: the sensor preset's range.
        self.depth_range_m = (
            depth_range_m(sensor, intrinsics_now)
            if isinstance(sensor, SensorModel) and isinstance(intrinsics_now, CameraIntrinsics)
            else (0.0, float("inf"))
        )
        self._rng = np.random.default_rng()
        self._flipped = False
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "camera_intrinsics" not in space.spaces:
            raise DonGymError("SimulatedKeypoints needs a don_gym env (observations with 'camera_intrinsics')")
        intrinsics = getattr(env.unwrapped, "intrinsics", None)
        if not isinstance(intrinsics, CameraIntrinsics):
            raise DonGymError(f"{type(env.unwrapped).__name__} has no camera intrinsics; expected a don_gym env")
        entries = dict(space.spaces)
        if not self.keep_images:
            for key in IMAGE_KEYS:
                entries.pop(key, None)
        entries["keypoint_pixels"] = spaces.Box(
            np.zeros((2, 2), np.float32),
            np.tile(np.array([intrinsics.width - 1, intrinsics.height - 1], np.float32), (2, 1)),
            dtype=np.float32,
        )
        entries["keypoint_points"] = spaces.Box(-POINT_BOUND_M, POINT_BOUND_M, shape=(2, 3), dtype=np.float32)
        entries["keypoint_confidence"] = spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = spaces.Dict(entries)

    @property
    def method(self) -> str:
        return "simulated" if self.noise is None else f"simulated ({self.noise.source or 'noise model'})"

    def _keypoints(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any]) -> dict[str, np.ndarray]:
        if "T_world_object" not in info or "T_world_camera" not in info:
            raise DonGymError("SimulatedKeypoints needs the true poses in info ('T_world_object', 'T_world_camera')")
        intrinsics = CameraIntrinsics.from_array(obs["camera_intrinsics"])
        T_world_camera = np.asarray(info["T_world_camera"], dtype=np.float64)
        truth = ring_points_facing(self.object_model, self.targets, info["T_world_object"], T_world_camera[:3, 3])
        _, visible = in_view(truth, T_world_camera, intrinsics)
        depth = transform_points(invert_transform(T_world_camera), truth)[:, 2]
        visible &= (depth >= self.depth_range_m[0]) & (depth <= self.depth_range_m[1])
        if not self.field_of_view:
            visible[:] = True
        if self._flipped:
            truth, visible = truth[::-1].copy(), visible[::-1].copy()
        reported_camera = np.asarray(obs["camera_pose"], dtype=np.float64)
        points = np.repeat(reported_camera[None, :3, 3], 2, axis=0)
        confidence = np.zeros(2, dtype=np.float32)
        for k in range(2):
            if not visible[k]:
                continue
            if self.noise is None:
                points[k], confidence[k] = truth[k], 1.0
                continue
            row = int(self._rng.choice(self._rows[k]))
            error = np.asarray(self.noise.error_camera_m[row], dtype=np.float64)
            if not np.all(np.isfinite(error)):
                continue  # a miss: no depth near the match
            points[k] = truth[k] + T_world_camera[:3, :3] @ error
            confidence[k] = float(self.noise.confidence[row])
        uv, _ = in_view(points, reported_camera, intrinsics)
        out = {k: v for k, v in obs.items() if self.keep_images or k not in IMAGE_KEYS}
        high = np.array([intrinsics.width - 1, intrinsics.height - 1], dtype=np.float64)
        out["keypoint_pixels"] = np.clip(uv, 0.0, high).astype(np.float32)
        out["keypoint_points"] = np.clip(points, -POINT_BOUND_M, POINT_BOUND_M).astype(np.float32)
        out["keypoint_confidence"] = confidence
        return out

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x4B50]))
        flip_rate = 0.0 if self.noise is None else float(self.noise.flip_rate)
        self._flipped = bool(self._rng.random() < flip_rate)
        return self._keypoints(obs, info), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._keypoints(obs, info), reward, terminated, truncated, info


# ------------------------------------------------------------------------------- measuring
def measure_keypoint_noise(
    model: str | Path | DenseObjectNet | DescriptorSource,
    object: str | Path = "toolcap",  # noqa: A002 - the env's own kwarg name
    image_size: tuple[int, int] = (640, 480),
    sensor: str = "d435",
    episodes: int = 40,
    steps_per_episode: int = 8,
    seed: int = 20_000,
    action_scale: float = 0.4,
    progress: bool = True,
) -> KeypointNoiseModel:
    """Measure a DON's keypoint errors: :class:`~don_gym.wrappers.KeypointObservation`'s two keypoints
    against :func:`ring_points_facing` of the true pose, on ``episodes`` ``control="ee"`` episodes
    (reset with ``seed + i``: a random part pose) at the reset frame and after each of
    ``steps_per_episode`` random hand motions (actions uniform in ``+-action_scale``, the gripper
    open), so that views from the observation pose and from nearer and tilted-away cameras count.

    A keypoint in view (:func:`in_view`) gives a row: its reported minus true point in the true
    camera frame, or NaN when not found (confidence 0). A frame whose two found keypoints lie each
    nearer the other's true point than their own counts as a flip; its rows are taken against the
    swapped truth.
    """
    env = gym.make("DONPick-v0", object=object, control="ee", image_size=image_size, sensor=sensor)
    wrapped = KeypointObservation(env, model=model, keep_images=False)
    object_model = wrapped.object_model
    targets = wrapped.targets
    if targets is None:
        raise DonGymError("measure_keypoint_noise measures the default axis-end keypoints")
    name = model if isinstance(model, (str, Path)) else wrapped.method
    metadata = getattr(wrapped.source, "metadata", None)  # a checkpoint's, for NetworkDescriptors
    rng = np.random.default_rng(seed)
    keypoint, errors, confidences = [], [], []
    frames = flips = both_found = 0
    total = int(episodes) * (int(steps_per_episode) + 1)
    try:
        with tqdm(total=total, desc=f"measure {name}", unit="frame", disable=not progress) as bar:
            for episode in range(int(episodes)):
                obs, info = wrapped.reset(seed=int(seed) + episode)
                for step in range(int(steps_per_episode) + 1):
                    if step > 0:
                        action = rng.uniform(-action_scale, action_scale, size=5)
                        action[4] = 1.0  # gripper open
                        obs, _, terminated, truncated, info = wrapped.step(action.astype(np.float32))
                    bar.update(1)
                    T_world_camera = np.asarray(info["T_world_camera"], dtype=np.float64)
                    truth = ring_points_facing(object_model, targets, info["T_world_object"], T_world_camera[:3, 3])
                    _, visible = in_view(truth, T_world_camera, CameraIntrinsics.from_array(obs["camera_intrinsics"]))
                    found = np.asarray(obs["keypoint_confidence"]) > 0
                    points = np.asarray(obs["keypoint_points"], dtype=np.float64)
                    frames += 1
                    if visible.all() and found.all():
                        both_found += 1
                        direct = np.linalg.norm(points - truth, axis=1).sum()
                        swapped = np.linalg.norm(points - truth[::-1], axis=1).sum()
                        if swapped < direct:
                            flips += 1
                            truth = truth[::-1]
                    R_camera_world = T_world_camera[:3, :3].T
                    for k in np.flatnonzero(visible):
                        keypoint.append(k)
                        confidences.append(float(obs["keypoint_confidence"][k]))
                        errors.append(R_camera_world @ (points[k] - truth[k]) if found[k] else np.full(3, np.nan))
                    if step > 0 and (terminated or truncated):
                        break
    finally:
        wrapped.close()
    if not keypoint:
        raise DonGymError(f"measure_keypoint_noise: no keypoint of {name!r} was ever in view")
    return KeypointNoiseModel(
        keypoint=np.asarray(keypoint, dtype=np.int64),
        error_camera_m=np.asarray(errors, dtype=np.float64),
        confidence=np.asarray(confidences, dtype=np.float64),
        flip_rate=flips / max(both_found, 1),
        object_name=object_model.name,
        object_mesh_hash=object_model.mesh_hash,
        fractions=targets.fractions,
        source=str(name),
        frames=frames,
        source_weights_sha256=metadata.weights_sha256 if metadata is not None else "",
    )
