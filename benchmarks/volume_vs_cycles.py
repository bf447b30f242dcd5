"""A baked volume against Cycles (issue 17): Cycles path-traces the scattering volume, then
renders VisiBake's baked emission-absorption volume from the same camera, and the two images
are compared.

The scene: a 32^3 VDB sphere (density 1 - (r/12)^2, in a unit cube) with a Principled Volume
(Density ``--density``, colour 0.9), a sun of 3 W/m^2 at 40 degrees, a black world, and a
camera 3 m away. The bake: ``visibake volume`` with ``--directions`` and ``--bounces``;
Cycles' volume bounces are set to the same count.

Error: relative RMSE over the pixels the cloud covers, of the baked render against the
path-traced one. The path-traced image's own noise is measured by rendering it twice with
two seeds (the RMSE of the difference over sqrt 2), and the error without it is given too.

    .venv/bin/python benchmarks/volume_vs_cycles.py [--directions 64] [--bounces 1] [--out DIR]

Writes DIR/volume_vs_cycles.json (default benchmarks/results/) and the EXRs beside it.
"""
import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SIZE = 64


def build_scene(folder: str, density: float) -> str:
    import bpy

    if hasattr(bpy.utils, "expose_bundled_modules"):
        bpy.utils.expose_bundled_modules()
    import openvdb as vdb

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    side = 32
    centre = (side - 1) / 2
    radius = np.sqrt(((np.indices((side,) * 3).astype(float) - centre) ** 2).sum(axis=0))
    grid = vdb.FloatGrid()
    grid.copyFromArray(np.clip(1.0 - (radius / 12.0) ** 2, 0.0, None).astype(np.float32))
    grid.name = "density"
    matrix = np.diag([1 / side, 1 / side, 1 / side, 1.0])
    matrix[3, :3] = -0.5
    grid.transform = vdb.createLinearTransform(matrix.tolist())
    vdb.write(os.path.join(folder, "cloud.vdb"), grids=[grid])
    volume = bpy.data.volumes.new("Cloud")
    volume.filepath = os.path.join(folder, "cloud.vdb")
    cloud = bpy.data.objects.new("Cloud", volume)
    scene.collection.objects.link(cloud)
    material = bpy.data.materials.new("Cloud")
    material.use_nodes = True
    tree = material.node_tree
    tree.nodes.clear()
    principled = tree.nodes.new("ShaderNodeVolumePrincipled")
    principled.inputs["Density"].default_value = density
    principled.inputs["Color"].default_value = (0.9, 0.9, 0.9, 1.0)
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(principled.outputs[0], output.inputs["Volume"])
    volume.materials.append(material)
    lamp = bpy.data.lights.new("Sun", "SUN")
    lamp.energy = 3.0
    lamp.angle = 0.0
    sun = bpy.data.objects.new("Sun", lamp)
    sun.rotation_euler = (math.radians(40), 0.0, math.radians(30))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("Black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0.0, -3.0, 0.0)
    camera.rotation_euler = (math.radians(90), 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    path = os.path.join(folder, "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    return path


def render(blend: str, which: str, bounces: int, samples: int, seed: int, path: str) -> tuple[np.ndarray, float]:
    import bpy

    bpy.ops.wm.open_mainfile(filepath=blend)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.render.resolution_x = scene.render.resolution_y = SIZE
    scene.render.resolution_percentage = 100
    scene.cycles.volume_bounces = bounces
    scene.cycles.use_denoising = False
    scene.cycles.samples = samples
    scene.cycles.seed = seed
    source, baked = bpy.data.objects["Cloud"], bpy.data.objects["Cloud (VisiBake)"]
    (source if which == "baked" else baked).hide_render = True
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = path
    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - started
    image = bpy.data.images.load(path)
    pixels = np.array(image.pixels[:], np.float64).reshape(SIZE, SIZE, 4)[..., :3]
    return pixels, seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--directions", type=int, default=64)
    parser.add_argument("--bounces", type=int, default=1)
    parser.add_argument("--density", type=float, default=8.0)
    parser.add_argument("--samples", type=int, default=256, help="Cycles samples of the path-traced volume")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    options = parser.parse_args()
    folder = os.path.abspath(os.path.join(options.out, "volume_vs_cycles"))
    os.makedirs(folder, exist_ok=True)
    sys.path.insert(0, ROOT)
    blend = build_scene(folder, options.density)
    baked_blend = os.path.join(folder, "baked.blend")
    started = time.perf_counter()
    subprocess.run([sys.executable, os.path.join(ROOT, "tools", "visibake.py"), "volume", blend, "--out",
                    os.path.join(folder, "grids"), "--resolution", "32", "--directions", str(options.directions),
                    "--bounces", str(options.bounces), "--save", baked_blend, "--report",
                    os.path.join(folder, "report.json"), "--no-progress"], check=True)
    command_seconds = time.perf_counter() - started
    with open(os.path.join(folder, "report.json")) as handle:
        report = json.load(handle)
    traced, traced_seconds = render(baked_blend, "source", options.bounces, options.samples, 0,
                                    os.path.join(folder, "cycles.exr"))
    again, _ = render(baked_blend, "source", options.bounces, options.samples, 7, os.path.join(folder, "cycles_2.exr"))
    baked, baked_seconds = render(baked_blend, "baked", options.bounces, 64, 0, os.path.join(folder, "baked.exr"))
    covered = traced.mean(axis=-1) > 0.01 * traced.max()
    scale = traced[covered].mean()
    error = float(np.sqrt(((baked - traced)[covered] ** 2).mean()) / scale)
    noise = float(np.sqrt(((traced - again)[covered] ** 2).mean()) / scale / np.sqrt(2))
    record = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
              "settings": vars(options), "pixels_covered": int(covered.sum()),
              "relative_rmse": round(error, 4), "cycles_noise": round(noise, 4),
              "relative_rmse_without_cycles_noise": round(float(np.sqrt(max(error ** 2 - noise ** 2, 0.0))), 4),
              "mean_ratio": round(float(baked[covered].mean() / scale), 4),
              "visibake_bake_seconds": report["seconds"], "visibake_command_seconds": round(command_seconds, 1),
              "cycles_path_traced_seconds": round(traced_seconds, 2), "cycles_baked_render_seconds":
                  round(baked_seconds, 2)}
    with open(os.path.join(options.out, "volume_vs_cycles.json"), "w") as handle:
        json.dump(record, handle, indent=1)
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
