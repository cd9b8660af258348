"""Physically based rendering (``renderer="pbr"``), a backend of :mod:`don_gym.sim.camera`.

:class:`PbrRenderer` path-traces the RGB image of the scene a PyBullet client holds, with Mitsuba 3: the
same bodies, poses, intrinsics and camera pose as TinyRenderer draws, so masks, depth and descriptor targets
(which still come from TinyRenderer and ray casting) align with the RGB to the pixel. The part's surface is a
metal (rough conductor) when its :class:`Surface` says so; table, backdrops, cradle, bin, distractors and robot
are rough dielectrics in their own colours and textures. Light comes from a procedural environment map
(:func:`environment_map`) and one area lamp (soft shadows), interreflections up to
:attr:`PbrSettings.max_depth` bounces; a colour camera's auto exposure and noise (:func:`expose`) turn the
radiance into 8-bit sRGB.

The pure parts are :func:`environment_map`, :func:`expose`, :func:`mitsuba_sensor_transform` and
:func:`fov_and_principal_point`; :func:`scene_visuals` reads what a client shows. Why Mitsuba's LLVM variant,
and its settings: docs/background.md, "Physically based rendering".
"""

from __future__ import annotations

import importlib.util
import os
import sys
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p

from don_gym.errors import DonGymError
from don_gym.geometry import CameraIntrinsics, transform_from_pose, transform_points

__all__ = [
    "DENOISERS",
    "INSTALL_HINT",
    "PbrRenderer",
    "PbrSettings",
    "denoise",
    "Surface",
    "VisualAssets",
    "VisualShape",
    "environment_map",
    "expose",
    "fov_and_principal_point",
    "mitsuba_available",
    "mitsuba_sensor_transform",
    "scene_visuals",
]

INSTALL_HINT = (
    "renderer='pbr' needs Mitsuba 3 and Open Image Denoise: "
    "install them with pip install -e \".[pbr]\" (or pip install 'don-gym[pbr]')"
)

#: The lamp: a disc of this radius (m), this far (m) from the workspace's centre (world, m) towards the light.
LAMP_RADIUS_M, LAMP_DISTANCE_M, LAMP_TARGET_M = 0.25, 1.5, (0.45, 0.0, 0.0)

#: OpenCV camera (x right, y down, z forward) -> Mitsuba camera (x left, y up, z forward).
_T_CV_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class Surface:
    """How a body's surface scatters light: ``metallic`` 0 (dielectric: plastic, paint, wood) to 1 (metal),
    ``roughness`` 0 (mirror) to 1 (chalk), GGX's perceptual roughness. The colour is the body's PyBullet rgba."""

    metallic: float = 0.0
    roughness: float = 0.6

    def __post_init__(self) -> None:
        for name in ("metallic", "roughness"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating)) or not (0.0 <= float(value) <= 1.0):
                raise DonGymError(f"surface {name}={value!r}: expected a number in [0, 1]")


#: What a body shows without a :class:`Surface` of its own: a rough dielectric.
DEFAULT_SURFACE = Surface()


DENOISERS = ("oidn", "none")


@dataclass(frozen=True)
class PbrSettings:
    """The path tracer's and the camera's settings.

    Attributes:
        samples_per_pixel: Monte Carlo samples per pixel (the noise falls as 1/sqrt of it).
        max_depth: longest light path in bounces (2: direct light only; more: interreflections).
        denoiser: "oidn" (Intel Open Image Denoise, guided by albedo and normals) or "none"; the radiance
            is denoised before the camera adds its own noise.
        exposure_key: auto exposure maps the frame's log-average luminance to this grey level (linear).
        full_well_electrons: the sensor's full-well capacity; photon shot noise follows from it.
        read_noise: the sensor's read noise, a fraction of full scale (linear).
    """

    samples_per_pixel: int = 16
    max_depth: int = 5
    denoiser: str = "oidn"
    exposure_key: float = 0.18
    full_well_electrons: float = 6000.0
    read_noise: float = 0.002

    def __post_init__(self) -> None:
        if not (isinstance(self.samples_per_pixel, (int, np.integer)) and 1 <= self.samples_per_pixel <= 4096):
            raise DonGymError(f"samples_per_pixel={self.samples_per_pixel!r}: expected an integer in 1..4096")
        if not (isinstance(self.max_depth, (int, np.integer)) and 2 <= self.max_depth <= 32):
            raise DonGymError(f"max_depth={self.max_depth!r}: expected an integer in 2..32")
        if self.denoiser not in DENOISERS:
            raise DonGymError(f"denoiser={self.denoiser!r} is unknown; expected one of {list(DENOISERS)}")


@dataclass
class VisualAssets:
    """What PyBullet does not report back about a world's visuals, recorded as they are made (by the client of
    :class:`don_gym.sim.bullet.Bullet`): textures and surfaces."""

    #: texture id -> the image file it was loaded from.
    texture_files: dict[int, str] = field(default_factory=dict)
    #: (body id, link index) -> texture id shown there.
    textures: dict[tuple[int, int], int] = field(default_factory=dict)
    surfaces: dict[int, Surface] = field(default_factory=dict)


@dataclass
class VisualShape:
    """One visual of the scene: a triangle mesh in its own frame, where it is, and how it looks.

    Attributes:
        key: identifies the mesh (file and scale, or primitive and size), as the mesh cache does.
        vertices_m: (N, 3) float64 vertices in the shape's frame, metres.
        faces: (M, 3) int64 vertex indices.
        uvs: (N, 2) texture coordinates (OpenGL: v up), or None.
        normals: (N, 3) unit vertex normals in the shape's frame for smooth shading, or None (flat faces).
        T_world_shape: (4, 4) pose of the shape's frame.
        rgb: (3,) base colour in [0, 1] (sRGB).
        texture: file of the colour texture, or None.
        surface: the :class:`Surface`.
        body_id: the PyBullet body it belongs to.
    """

    key: tuple
    vertices_m: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None
    normals: np.ndarray | None
    T_world_shape: np.ndarray
    rgb: np.ndarray
    texture: str | None
    surface: Surface
    body_id: int


def mitsuba_available() -> bool:
    """Whether Mitsuba 3 and the denoiser are installed (without importing them)."""
    return importlib.util.find_spec("mitsuba") is not None and importlib.util.find_spec("pyoidn") is not None


def _import_mitsuba() -> tuple[Any, str]:
    """Mitsuba with its vectorised LLVM variant where an LLVM it works with is found, else the scalar one."""
    if not mitsuba_available():
        raise DonGymError(INSTALL_HINT)
    # Dr.Jit needs libLLVM at run time; the "pbr" extra installs one into the environment (the system's
    # LLVM 15 fails on Dr.Jit's kernels). A path the user set wins.
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for name in ("libLLVM.so", "libLLVM.dylib"):
            candidate = Path(sys.prefix) / "lib" / name
            if candidate.exists():
                os.environ["DRJIT_LIBLLVM_PATH"] = str(candidate)
                break
    import mitsuba as mi

    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        if variant in mi.variants():
            try:
                mi.set_variant(variant)
                mi.Float([0.0, 1.0]) + 1.0  # the JIT compiles here when LLVM is unusable
            except (ImportError, RuntimeError, AttributeError) as error:
                warnings.warn(f"Mitsuba variant {variant} unusable ({error}); trying the next", stacklevel=3)
                continue
            return mi, variant
    raise DonGymError(f"Mitsuba has no usable RGB variant (found {mi.variants()}); {INSTALL_HINT}")


def mitsuba_sensor_transform(T_world_camera: np.ndarray) -> np.ndarray:
    """(4, 4) Mitsuba sensor ``to_world`` for an OpenCV ``T_world_camera`` (Mitsuba cameras: x left, y up)."""
    return np.asarray(T_world_camera, dtype=np.float64) @ _T_CV_MITSUBA


def fov_and_principal_point(intrinsics: CameraIntrinsics) -> tuple[float, float, float]:
    """Mitsuba's ``fov`` (degrees, along x) and principal point offsets (fractions of the film's width and
    height) for OpenCV ``intrinsics``, whose pixel centres sit at integer coordinates (Mitsuba's at +0.5).

    Mitsuba's pinhole has square pixels, so ``fx`` must equal ``fy`` (to 0.1%)."""
    if abs(intrinsics.fx - intrinsics.fy) > 1e-3 * intrinsics.fx:
        raise DonGymError(f"renderer='pbr' needs square pixels, got fx={intrinsics.fx} and fy={intrinsics.fy}")
    W, H = float(intrinsics.width), float(intrinsics.height)
    fov_deg = float(np.degrees(2.0 * np.arctan(W / (2.0 * intrinsics.fx))))
    # Mitsuba moves the image's content the other way than the offset's sign reads (checked against the
    # ray cast: tests/test_pbr.py, silhouette IoU).
    offset_x = -((intrinsics.cx + 0.5) - W / 2.0) / W
    offset_y = -((intrinsics.cy + 0.5) - H / 2.0) / H
    return fov_deg, offset_x, offset_y


def _smooth_field(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    coarse = rng.uniform(0.0, 1.0, size=(cells, 2 * cells))
    import cv2

    return cv2.resize(coarse, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def environment_map(index: int, height_px: int = 128) -> np.ndarray:
    """A procedural workshop environment: ``(height_px, 2 * height_px, 3)`` float32 linear radiance,
    equirectangular (row 0 straight up, column 0 azimuth 0, Mitsuba's ``envmap`` layout).

    Each index draws a room from ``default_rng(index)`` (index 0: the fixed lighting's): the ceiling's tint
    and brightness, dark and light walls and shelves around the horizon, a darker floor, and 2-5 bright
    windows or light panels whose reflections a metal part shows.
    """
    height, width = int(height_px), 2 * int(height_px)
    rng = np.random.default_rng(int(index))
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from straight up
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    elevation = (np.pi / 2 - theta)[:, None] * np.ones((1, width))
    azimuth = np.ones((height, 1)) * phi[None, :]
    ceiling = rng.uniform(0.3, 0.8) * rng.uniform(0.85, 1.0, 3)
    floor = rng.uniform(0.03, 0.15) * rng.uniform(0.8, 1.0, 3)
    blend = np.clip(0.5 + elevation / 0.6, 0.0, 1.0)[..., None]
    image = floor * (1 - blend) + ceiling * blend
    # Walls and shelves: smooth blocks of two colours around the horizon, dark and light, the surroundings
    # whose contrast a metal part mirrors (an evenly lit room makes steel look like grey plastic).
    walls = _smooth_field(rng, (height, width), int(rng.integers(3, 9)))
    band = np.exp(-(((elevation - rng.uniform(-0.1, 0.3)) / rng.uniform(0.25, 0.6)) ** 2))[..., None]
    colour_a, colour_b = rng.uniform(0.01, 0.1, 3), rng.uniform(0.2, 0.6, 3)
    wall_colour = colour_a * walls[..., None] + colour_b * (1 - walls[..., None])
    image = image * (1 - 0.9 * band) + wall_colour * 0.9 * band
    for _ in range(int(rng.integers(2, 6))):
        centre_az, centre_el = rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 1.4)
        half_az, half_el, strength = rng.uniform(0.1, 0.5), rng.uniform(0.05, 0.3), rng.uniform(8.0, 30.0)
        d_az = np.angle(np.exp(1j * (azimuth - centre_az)))
        inside = (np.abs(d_az) < half_az) & (np.abs(elevation - centre_el) < half_el)
        image[inside] = strength * rng.uniform(0.85, 1.0, 3)
    return image.astype(np.float32)


def expose(radiance_rgb: np.ndarray, settings: PbrSettings, rng: np.random.Generator, gain: float = 1.0) -> np.ndarray:
    """A colour camera's image of linear ``radiance_rgb`` (H, W, 3): auto exposure (the log-average luminance
    to :attr:`PbrSettings.exposure_key`, times ``gain``), photon shot noise and read noise, clipping at full
    scale, the sRGB curve, 8 bits. Returns (H, W, 3) uint8."""
    radiance = np.nan_to_num(np.asarray(radiance_rgb, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    luminance = radiance @ np.array([0.2126, 0.7152, 0.0722])
    log_average = float(np.exp(np.mean(np.log(np.maximum(luminance, 1e-4)))))
    linear = np.clip(radiance * (settings.exposure_key * float(gain) / log_average), 0.0, 1.0)
    # Shot noise as a Gaussian of the Poisson's variance: a fixed number of draws per pixel, so the noise of
    # one pixel does not depend on the values of the others (as a Poisson sampler's rejection loop would).
    sigma = np.sqrt(linear / settings.full_well_electrons + settings.read_noise**2)
    noisy = np.clip(linear + sigma * rng.standard_normal(size=linear.shape), 0.0, 1.0)
    srgb = np.where(noisy <= 0.0031308, 12.92 * noisy, 1.055 * np.power(noisy, 1.0 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


# ------------------------------------------------------------------- the scene's visuals
def _primitive_mesh(geometry_type: int, dimensions: np.ndarray) -> tuple[Any, bool]:
    import trimesh

    if geometry_type == p.GEOM_BOX:
        return trimesh.creation.box(extents=dimensions[:3]), False
    if geometry_type == p.GEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=3, radius=float(dimensions[0])), True
    if geometry_type == p.GEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=float(dimensions[1]), height=float(dimensions[0]), sections=48), True
    if geometry_type == p.GEOM_CAPSULE:
        return trimesh.creation.capsule(radius=float(dimensions[1]), height=float(dimensions[0]), count=[48, 24]), True
    return None, False


def _file_mesh(path: str, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Vertices, faces, uvs and the mean colour of the materials (None: none) of a mesh file."""
    import trimesh

    loaded = trimesh.load(path, force="mesh", process=False)
    colour = None
    material = getattr(loaded.visual, "material", None)
    if material is not None:
        main = getattr(material, "main_color", None)
        if main is not None:
            colour = np.asarray(main[:3], dtype=np.float64) / 255.0
    uvs = getattr(loaded.visual, "uv", None)
    return np.asarray(loaded.vertices) * scale, np.asarray(loaded.faces), uvs, colour


@dataclass
class _LocalMesh:
    """A mesh in its own frame as the renderer draws it: smooth meshes split at sharp edges, with normals."""

    vertices_m: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None
    normals: np.ndarray | None
    colour: np.ndarray | None


def _local_mesh(
    vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray | None, smooth: bool, colour: np.ndarray | None
) -> _LocalMesh:
    import trimesh

    if not smooth or len(faces) == 0:
        return _LocalMesh(np.asarray(vertices, float), np.asarray(faces, np.int64), uvs, None, colour)
    # Interpolated normals make a faceted cylinder's highlight a smooth stripe, as on the real part; the
    # split at edges sharper than trimesh's default angle keeps end faces and chamfers crisp.
    shaded = trimesh.Trimesh(vertices, faces, process=False).smooth_shaded
    return _LocalMesh(
        np.asarray(shaded.vertices, float),
        np.asarray(shaded.faces, np.int64),
        None,
        np.asarray(shaded.vertex_normals, float),
        colour,
    )


class _MeshCache:
    """Meshes by key, prepared once per renderer (files and primitives do not change while a world lives)."""

    def __init__(self) -> None:
        self.meshes: dict[tuple, _LocalMesh] = {}

    def get(self, key: tuple, make) -> _LocalMesh:
        if key not in self.meshes:
            self.meshes[key] = _local_mesh(*make())
        return self.meshes[key]


def _link_transform(client: Any, body_id: int, link: int) -> np.ndarray:
    if link < 0:
        return _pose(*client.getBasePositionAndOrientation(body_id))
    state = client.getLinkState(body_id, link, computeForwardKinematics=1)
    return _pose(state[0], state[1])


def scene_visuals(client: Any, assets: VisualAssets, cache: Any | None = None) -> list[VisualShape]:
    """Every visible shape of the world behind ``client`` (alpha > 0), in world poses.

    PyBullet reports a shape's frame relative to its link's inertial frame (base: the body's base frame);
    mesh files are read with trimesh; textures come from ``assets`` (meshes given to PyBullet as arrays
    are not drawn: PyBullet does not report them back, and the EGL renderer skips them too)."""
    cache = cache if cache is not None else _MeshCache()
    shapes: list[VisualShape] = []
    for body_index in range(client.getNumBodies()):
        body_id = client.getBodyUniqueId(body_index)
        for data in client.getVisualShapeData(body_id):
            link, geometry_type, dimensions = int(data[1]), int(data[2]), np.asarray(data[3], dtype=np.float64)
            filename = data[4].decode() if isinstance(data[4], bytes) else str(data[4])
            rgba = np.asarray(data[7], dtype=np.float64)
            if rgba[3] <= 0.0:
                continue
            if geometry_type == p.GEOM_MESH and filename:
                key: tuple = ("file", filename, tuple(np.round(dimensions, 9)))

                def load(path=filename, scale=dimensions):
                    vertices, faces, uvs, colour = _file_mesh(path, scale)
                    # Textured meshes keep their texture coordinates (flat shading); the rest shade smooth.
                    return vertices, faces, uvs, uvs is None, colour

                entry = cache.get(key, load)
            else:
                key = ("primitive", geometry_type, tuple(np.round(dimensions, 9)))

                def make(kind=geometry_type, dims=dimensions):
                    mesh, smooth = _primitive_mesh(kind, dims)
                    if mesh is None:
                        return np.zeros((0, 3)), np.zeros((0, 3), int), None, False, None
                    return np.asarray(mesh.vertices), np.asarray(mesh.faces), None, smooth, None

                entry = cache.get(key, make)
            if len(entry.faces) == 0:
                continue
            T_link_shape = _pose(data[5], data[6])
            texture_id = assets.textures.get((body_id, link))
            texture = None if texture_id is None else assets.texture_files.get(texture_id)
            # A mesh file's own material colour shows through PyBullet's default white.
            rgb = rgba[:3] if entry.colour is None else rgba[:3] * entry.colour
            shapes.append(
                VisualShape(
                    key=key,
                    vertices_m=entry.vertices_m,
                    faces=entry.faces,
                    uvs=entry.uvs if texture is not None else None,
                    normals=entry.normals,
                    T_world_shape=_link_transform(client, body_id, link) @ T_link_shape,
                    rgb=np.clip(rgb, 0.0, 1.0),
                    texture=texture,
                    surface=assets.surfaces.get(body_id, DEFAULT_SURFACE),
                    body_id=body_id,
                )
            )
    return shapes


def _pose(position: Any, quaternion_xyzw: Any) -> np.ndarray:
    return transform_from_pose(np.asarray(position, dtype=np.float64), np.asarray(quaternion_xyzw, dtype=np.float64))


def _lighting_seed(lighting: Any) -> int:
    if lighting is None:
        return 0
    values = np.asarray([*lighting.direction_world, *lighting.colour_rgb, lighting.ambient, lighting.diffuse])
    return int(zlib.crc32(np.round(values, 9).tobytes()))


class PbrRenderer:
    """Mitsuba path tracing of one PyBullet world's RGB; made and owned by its client
    (:class:`don_gym.sim.bullet.Bullet` with ``renderer="pbr"``).

    The environment map follows the :class:`~don_gym.sim.camera.Lighting`: the fixed default light gets
    environment 0, any other light an environment drawn from a hash of its values (so a recorder's
    ``--lighting random`` draws a room per scene without touching the scene's random stream). The lamp is a
    disc 1.5 m away towards the light's direction, its brightness from the light's diffuse coefficient and
    colour; the environment's from its ambient coefficient. The path tracer's seed and the camera noise come
    from a hash of the camera pose and the light, so the same scene gives the same image on the same machine.
    """

    def __init__(self, assets: VisualAssets, settings: PbrSettings | None = None) -> None:
        self.mi, self.variant = _import_mitsuba()
        self.assets = assets
        self.settings = settings or PbrSettings()
        self._meshes = _MeshCache()
        self._bitmaps: dict[str, Any] = {}
        self._environments: dict[int, Any] = {}

    # ------------------------------------------------------------- pieces
    def _bitmap(self, path: str) -> Any:
        if path not in self._bitmaps:
            if len(self._bitmaps) > 16:  # a recorder's backdrops bring new textures at every scene
                self._bitmaps.clear()
            self._bitmaps[path] = self.mi.load_dict({"type": "bitmap", "filename": str(path)})
        return self._bitmaps[path]

    def _environment(self, index: int) -> Any:
        if len(self._environments) > 32:  # a recorder's random lighting draws a room per scene
            self._environments.clear()
        if index not in self._environments:
            self._environments[index] = self.mi.Bitmap(environment_map(index))
        return self._environments[index]

    def _bsdf(self, shape: VisualShape) -> dict[str, Any]:
        colour: Any = {"type": "rgb", "value": [float(v) for v in shape.rgb]}
        if shape.texture is not None:
            colour = self._bitmap(shape.texture)
        return {
            "type": "principled",
            "base_color": colour,
            "metallic": float(shape.surface.metallic),
            "roughness": float(shape.surface.roughness),
        }

    def _mesh(self, shape: VisualShape, index: int) -> Any:
        mi = self.mi
        vertices = transform_points(shape.T_world_shape, shape.vertices_m)
        faces, uvs = shape.faces, shape.uvs
        normals = None if shape.normals is None else shape.normals @ shape.T_world_shape[:3, :3].T
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(self._bsdf(shape))
        mesh_object = mi.Mesh(f"shape_{index}", len(vertices), len(faces), props, normals is not None, uvs is not None)
        params = mi.traverse(mesh_object)
        params["vertex_positions"] = mi.Float(np.asarray(vertices, dtype=np.float32).ravel())
        params["faces"] = mi.UInt32(np.asarray(faces, dtype=np.uint32).ravel())
        if normals is not None:
            params["vertex_normals"] = mi.Float(np.asarray(normals, dtype=np.float32).ravel())
        if uvs is not None:
            # OpenGL's texture v points up the image, Mitsuba's down.
            flipped = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], axis=1)
            params["vertex_texcoords"] = mi.Float(np.asarray(flipped, dtype=np.float32).ravel())
        params.update()
        return mesh_object

    def _lights(self, lighting: Any) -> dict[str, Any]:
        from don_gym.sim.camera import Lighting

        light = lighting if lighting is not None else Lighting()
        direction = np.asarray(light.direction_world, dtype=np.float64)
        direction /= np.linalg.norm(direction)
        centre = np.asarray(LAMP_TARGET_M) + LAMP_DISTANCE_M * direction
        up = [0.0, 0.0, 1.0] if abs(direction[2]) < 0.99 else [1.0, 0.0, 0.0]
        lamp_to_world = self.mi.ScalarTransform4f().look_at(
            origin=[float(v) for v in centre], target=list(LAMP_TARGET_M), up=up
        ) @ self.mi.ScalarTransform4f().scale([LAMP_RADIUS_M, LAMP_RADIUS_M, 1.0])
        lamp_radiance = [float(40.0 * light.diffuse * c) for c in light.colour_rgb]
        return {
            "environment": {
                "type": "envmap",
                "bitmap": self._environment(_lighting_seed(lighting) % 100000),
                "scale": float(light.ambient / 0.6),
                # Mitsuba's environment's "up" is +y; the world's is +z.
                "to_world": self.mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0),
            },
            "lamp": {
                "type": "disk",
                "to_world": lamp_to_world,
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": lamp_radiance}},
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            },
        }

    # ------------------------------------------------------------- render
    def render_layers(
        self,
        client: Any,
        intrinsics: CameraIntrinsics,
        T_world_camera: np.ndarray,
        lighting: Any = None,
        samples_per_pixel: int | None = None,
        seed: int | None = None,
        hide_environment: bool = False,
    ) -> dict[str, np.ndarray]:
        """Path-trace the world behind ``client`` seen from ``T_world_camera``; (H, W, C) float32 layers:
        ``radiance`` (C=3, linear), ``coverage`` (C=1: the share of the pixel showing a surface rather than the
        environment; meaningful with ``hide_environment``, which keeps the environment out of direct view,
        else Mitsuba counts it as covered), ``albedo`` (C=3) and ``normal`` (C=3, world frame) at the first hit,
        the denoiser's guides. ``seed`` None: from the camera pose and the light."""
        mi = self.mi
        fov_deg, offset_x, offset_y = fov_and_principal_point(intrinsics)
        spp = int(samples_per_pixel or self.settings.samples_per_pixel)
        scene: dict[str, Any] = {
            "type": "scene",
            "integrator": {
                "type": "aov",
                "aovs": "albedo:albedo,normal:sh_normal",
                "integrator": {
                    "type": "path",
                    "max_depth": int(self.settings.max_depth),
                    "hide_emitters": bool(hide_environment),
                },
            },
            "sensor": {
                "type": "perspective",
                "fov": fov_deg,
                "fov_axis": "x",
                "principal_point_offset_x": offset_x,
                "principal_point_offset_y": offset_y,
                "near_clip": 0.01,
                "far_clip": 100.0,
                "to_world": mi.ScalarTransform4f(mitsuba_sensor_transform(T_world_camera).tolist()),
                "film": {
                    "type": "hdrfilm",
                    "width": int(intrinsics.width),
                    "height": int(intrinsics.height),
                    # The box filter keeps each sample in its own pixel, which Mitsuba sums in a fixed order:
                    # the same seed gives the same image (a Gaussian's splats add up in thread order).
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgba",
                },
                "sampler": {"type": "independent", "sample_count": spp},
            },
            **self._lights(lighting),
        }
        for index, shape in enumerate(scene_visuals(client, self.assets, self._meshes)):
            scene[f"shape_{index}"] = self._mesh(shape, index)
        if seed is None:
            seed = _frame_seed(T_world_camera, lighting)
        image = np.asarray(mi.render(mi.load_dict(scene), seed=int(seed) % (2**31)), dtype=np.float32)
        return {
            "radiance": image[..., 0:3],
            "coverage": image[..., 3:4],
            "albedo": image[..., 4:7],
            "normal": image[..., 7:10],
        }

    def render(
        self, client: Any, intrinsics: CameraIntrinsics, T_world_camera: np.ndarray, lighting: Any = None
    ) -> np.ndarray:
        """(H, W, 3) uint8 sRGB: :meth:`render_layers`, denoised as the settings say, then :func:`expose`."""
        seed = _frame_seed(T_world_camera, lighting)
        layers = self.render_layers(client, intrinsics, T_world_camera, lighting, seed=seed)
        radiance = denoise(layers, self.settings.denoiser)
        return expose(radiance, self.settings, np.random.default_rng(seed))


def denoise(layers: dict[str, np.ndarray], denoiser: str = "oidn") -> np.ndarray:
    """(H, W, 3) float32 linear radiance with the Monte Carlo noise of ``layers["radiance"]`` removed.

    "oidn": Intel Open Image Denoise (its ray-tracing filter, HDR, guided by the first hit's albedo and
    normal, deterministic on the CPU); "none": as rendered."""
    radiance = np.ascontiguousarray(np.maximum(layers["radiance"], 0.0), dtype=np.float32)
    if denoiser == "none":
        return radiance
    import pyoidn

    albedo = np.ascontiguousarray(np.clip(layers["albedo"], 0.0, 1.0), dtype=np.float32)
    normal = np.ascontiguousarray(np.clip(layers["normal"], -1.0, 1.0), dtype=np.float32)
    return np.asarray(pyoidn.denoise(radiance, albedo, normal, hdr=True, quality="high"), dtype=np.float32)


def _frame_seed(T_world_camera: np.ndarray, lighting: Any) -> int:
    T = np.round(np.asarray(T_world_camera, dtype=np.float64), 9)
    return int(zlib.crc32(T.tobytes(), _lighting_seed(lighting)))
