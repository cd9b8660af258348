"""Which path tracer for ``renderer="pbr"``: Mitsuba 3 (scalar and LLVM variants) against Blender's Cycles.

One scene in each engine: a steel cylinder with a flange (the toolcap's size, a rough metal) on a brown
table, a bright disc lamp and an even grey environment, seen by a 640x480 pinhole camera from 0.45 m, at 16
samples per pixel (Cycles also at its own adaptive default with its built-in OIDN). Per engine: seconds
per frame (median of 3 after a warm-up frame), whether two renders with the same seed are identical, and
the size of the installed packages. Only engines that import are measured: run it in an environment with
``pip install mitsuba karellen-llvm-core bpy`` (bpy is no dependency of don_gym; its wheel needs the Python
version Blender was built for).

    python benchmarks/bench_pbr_candidates.py            # records the "pbr-candidates" section
    python benchmarks/bench_pbr_candidates.py --quick    # 160x120, records nothing

It imports nothing of don_gym, so it runs in an environment made for it alone.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import record_section  # noqa: E402

SPP = 16
#: Camera 0.45 m above the table centre looking down; lamp up and to the side.
EYE_M, LAMP_M = (0.0, -0.15, 0.45), (0.6, -0.45, 1.4)


def _package_mb(*names: str) -> float:
    total = 0
    for name in names:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            continue
        for root in spec.submodule_search_locations:
            for path in Path(root).rglob("*"):
                if path.is_file():
                    total += path.stat().st_size
    llvm = Path(sys.prefix) / "lib" / "libLLVM.so"
    if "drjit" in names and llvm.exists():
        total += llvm.resolve().stat().st_size
    return total / 2**20


def _timed(render, repeats: int = 3) -> tuple[float, bool]:
    first = render()
    times, images = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        images.append(render())
        times.append(time.perf_counter() - start)
    return float(np.median(times)), bool(all(np.array_equal(first, image) for image in images))


def mitsuba_engine(variant: str, size: tuple[int, int]):
    # Dr.Jit reads the path when it is imported: the system's LLVM 15 cannot compile its kernels.
    candidate = Path(sys.prefix) / "lib" / "libLLVM.so"
    if candidate.exists():
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", str(candidate))
    import mitsuba as mi

    mi.set_variant(variant)
    T = mi.ScalarTransform4f
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 5},
            "sensor": {
                "type": "perspective",
                "fov": 69.0,
                "to_world": T().look_at(origin=list(EYE_M), target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": size[0], "height": size[1], "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": SPP},
            },
            "environment": {"type": "constant", "radiance": {"type": "rgb", "value": 0.5}},
            "lamp": {
                "type": "disk",
                "to_world": T().look_at(origin=list(LAMP_M), target=[0, 0, 0], up=[0, 0, 1]) @ T().scale(0.25),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 15.0}},
            },
            "table": {
                "type": "rectangle",
                "to_world": T().scale(0.6),
                "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": [0.55, 0.45, 0.35]}},
            },
            "shaft": {
                "type": "cylinder",
                "radius": 0.01,
                "p0": [0, 0, 0.0],
                "p1": [0, 0, 0.04],
                "bsdf": {
                    "type": "principled",
                    "base_color": {"type": "rgb", "value": [0.72, 0.73, 0.76]},
                    "metallic": 1.0,
                    "roughness": 0.3,
                },
            },
        }
    )
    return lambda: np.asarray(mi.render(scene, seed=1))


def cycles_engine(size: tuple[int, int], adaptive: bool):
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.render.threads_mode = "FIXED"
    scene.render.threads = os.cpu_count() or 1
    scene.render.resolution_x, scene.render.resolution_y = size
    scene.cycles.samples = SPP if not adaptive else 64
    scene.cycles.use_adaptive_sampling = adaptive
    scene.cycles.use_denoising = True
    scene.cycles.seed = 1
    scene.cycles.max_bounces = 5
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs[0].default_value = (0.5, 0.5, 0.5, 1.0)
    scene.world = world
    bpy.ops.mesh.primitive_plane_add(size=1.2)
    table = bpy.data.materials.new("table")
    table.use_nodes = True
    table.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.55, 0.45, 0.35, 1)
    bpy.context.object.data.materials.append(table)
    bpy.ops.mesh.primitive_cylinder_add(radius=0.01, depth=0.04, location=(0, 0, 0.02), vertices=64)
    bpy.ops.object.shade_smooth()
    steel = bpy.data.materials.new("steel")
    steel.use_nodes = True
    principled = steel.node_tree.nodes["Principled BSDF"]
    principled.inputs["Base Color"].default_value = (0.72, 0.73, 0.76, 1)
    principled.inputs["Metallic"].default_value = 1.0
    principled.inputs["Roughness"].default_value = 0.3
    bpy.context.object.data.materials.append(steel)
    bpy.ops.object.light_add(type="AREA", location=LAMP_M)
    bpy.context.object.data.energy = 200.0
    bpy.context.object.data.size = 0.5
    bpy.ops.object.camera_add(location=EYE_M)
    camera = bpy.context.object
    direction = -np.asarray(EYE_M)
    camera.rotation_mode = "QUATERNION"
    camera.rotation_quaternion = bpy.data.objects[camera.name].matrix_world.to_quaternion()
    import mathutils

    camera.rotation_quaternion = mathutils.Vector(direction.tolist()).to_track_quat("-Z", "Y")
    scene.camera = camera
    output = Path(os.environ.get("TMPDIR", "/tmp")) / "don_gym_cycles_frame.exr"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = str(output)

    def render() -> np.ndarray:
        bpy.ops.render.render(write_still=True)
        image = bpy.data.images.load(str(output), check_existing=False)
        pixels = np.asarray(image.pixels[:], dtype=np.float32)
        bpy.data.images.remove(image)
        return pixels

    return render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="160x120; records nothing")
    args = parser.parse_args()
    size = (160, 120) if args.quick else (640, 480)
    rows = []
    engines = []
    if importlib.util.find_spec("mitsuba") is not None:
        engines += [
            ("Mitsuba 3 scalar_rgb", lambda: mitsuba_engine("scalar_rgb", size), ("mitsuba", "drjit")),
            ("Mitsuba 3 llvm_ad_rgb", lambda: mitsuba_engine("llvm_ad_rgb", size), ("mitsuba", "drjit")),
        ]
    if importlib.util.find_spec("bpy") is not None:
        engines += [
            (f"Cycles (bpy), {SPP} spp, OIDN", lambda: cycles_engine(size, adaptive=False), ("bpy",)),
            ("Cycles (bpy), adaptive <= 64 spp, OIDN", lambda: cycles_engine(size, adaptive=True), ("bpy",)),
        ]
    for name, make, packages in engines:
        try:
            seconds, same = _timed(make())
        except Exception as error:  # an engine that fails here is reported, not fatal
            rows.append(f"| {name} | failed: {str(error).splitlines()[0][:80]} | | {_package_mb(*packages):.0f} |")
            continue
        rows.append(f"| {name} | {seconds:.2f} | {'yes' if same else 'no'} | {_package_mb(*packages):.0f} |")
        print(rows[-1], flush=True)
    body = (
        f"{size[0]}x{size[1]}, {SPP} samples per pixel unless said, {os.cpu_count()} threads; seconds per frame are "
        "the median of 3 after a warm-up frame; same image: two renders with one seed are identical; MB: the "
        "installed packages (Mitsuba's with the libLLVM its LLVM variant loads; OIDN adds about 170 MB to it)\n\n"
        "| engine | s per frame | same image | installed MB |\n|---|---|---|---|\n" + "\n".join(rows)
    )
    print(body)
    if not args.quick:
        record_section("pbr-candidates", "Physically based rendering: the candidate engines", body, after="env")


if __name__ == "__main__":
    main()
