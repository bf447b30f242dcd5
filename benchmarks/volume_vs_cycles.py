"""A baked volume against Cycles (issue 17): Cycles path-traces the scattering volume, then
renders VisiBake's baked emission-absorption volume from the same camera, and the two images
are compared.

The scene: a ``--side``^3 VDB sphere (density 1 - (r / R)^2 with R = 0.375 of the side, in a
unit cube) with a Principled Volume (Density ``--density``, colour 0.9), a sun of 3 W/m^2 at
40 degrees, a black world, and a camera 3 m away. The bake: ``visibake volume`` at the grid's
own resolution, once per count in ``--directions``, with ``--bounces``; Cycles' volume
bounces are set to the same count.

With ``--floor``, a grey floor under the cloud: the sun lights it, the cloud shadows it, and
its reflection lights the cloud from below (VisiBake bakes that reflection, first order). It
is a real mesh in both renders; only the pixels the cloud covers are compared.

Error: relative RMSE over the pixels the cloud covers, of the baked render against the
path-traced one. Both renders are noisy (Cycles marches the baked volume stochastically too),
so each is rendered twice with two seeds: its noise is the RMSE of the difference over sqrt 2,
and the error without both noises is sqrt(error^2 - noise_traced^2 - noise_baked^2) (0 where
the noises explain it all). A plot of error against directions and a picture of the renders
are written beside the JSON.

Time at equal error (``--lightings``, default 1 and 16): how long Cycles takes to path-trace
the volume to the bake's own error (its error without both noises), against how long
VisiBake takes to bake that many lightings. Cycles' noise falls as 1/sqrt(samples) (measured
here at two sample counts; the record gives both), so it needs
samples x (noise / error)^2 samples, at its measured seconds per sample, for each lighting.
VisiBake builds its tables once: its first bake's time, plus each further lighting at the
time of a re-bake that reads the cached tables, less its kernel load (run once and counted
K - 1 times; in a session the kernels stay loaded). Neither
side counts rendering the result for viewing: Cycles' image is its result, the bake's grids
render in EEVEE at once, or in Cycles at the ``cycles_baked_render_seconds`` given.

    .venv/bin/python benchmarks/volume_vs_cycles.py [--side 64] [--directions 64,256] [--bounces 1] [--floor]
        [--out DIR]

Writes DIR/volume_vs_cycles.json (default benchmarks/results/) and the EXRs beside it.
"""
import argparse
import datetime
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SIZE = 64


def build_scene(folder: str, density: float, side: int, floor: bool = False) -> str:
    import bpy

    if hasattr(bpy.utils, "expose_bundled_modules"):
        bpy.utils.expose_bundled_modules()
    import openvdb as vdb

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    centre = (side - 1) / 2
    radius = np.sqrt(((np.indices((side,) * 3).astype(float) - centre) ** 2).sum(axis=0))
    grid = vdb.FloatGrid()
    grid.copyFromArray(np.clip(1.0 - (radius / (0.375 * side)) ** 2, 0.0, None).astype(np.float32))
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
    if floor:
        # A grey floor just under the sphere (density zero below z = -0.375): the sun lights it,
        # the cloud shadows it, and it lights the cloud from below.
        mesh = bpy.data.meshes.new("Floor")
        mesh.from_pydata([(-10, -10, -0.42), (10, -10, -0.42), (10, 10, -0.42), (-10, 10, -0.42)], [], [(0, 1, 2, 3)])
        # A Diffuse BSDF (Lambert, as VisiBake reflects): a Principled BSDF's specular layer
        # takes about a tenth of the light from its diffuse part.
        grey = bpy.data.materials.new("Grey")
        grey.use_nodes = True
        nodes = grey.node_tree.nodes
        nodes.remove(nodes["Principled BSDF"])
        diffuse = nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
        grey.node_tree.links.new(diffuse.outputs[0], nodes["Material Output"].inputs["Surface"])
        mesh.materials.append(grey)
        scene.collection.objects.link(bpy.data.objects.new("Floor", mesh))
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0.0, -3.0, 0.0)
    camera.rotation_euler = (math.radians(90), 0.0, 0.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    path = os.path.join(folder, "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    return path


def render(blend: str, which: str, bounces: int, samples: int, seed: int, path: str,
           hide: tuple = ()) -> tuple[np.ndarray, float]:
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
    scene.cycles.use_adaptive_sampling = False  # every pixel gets its samples: the noise is what they leave
    scene.cycles.seed = seed
    source, baked = bpy.data.objects["Cloud"], bpy.data.objects["Cloud (VisiBake)"]
    (source if which == "baked" else baked).hide_render = True
    for name in hide:
        bpy.data.objects[name].hide_render = True
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.filepath = path
    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    seconds = time.perf_counter() - started
    image = bpy.data.images.load(path)
    pixels = np.array(image.pixels[:], np.float64).reshape(SIZE, SIZE, 4)[..., :3]
    return pixels, seconds


def _plot(record: dict, traced: np.ndarray, images: dict, stem: str) -> None:
    """``stem``.png: error against directions; ``stem``_renders.png: the renders side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bakes = record["bakes"]
    figure, axis = plt.subplots(figsize=(5, 3.5))
    counts = [b["directions"] for b in bakes]
    axis.plot(counts, [100 * b["relative_rmse"] for b in bakes], "o-", label="baked vs path-traced")
    axis.plot(counts, [100 * b["relative_rmse_without_noise"] for b in bakes], "s-", label="without both noises")
    axis.axhline(100 * record["cycles_noise"], color="grey", linestyle=":", label="path-traced noise")
    axis.axhline(5.0, color="red", linestyle="--", label="issue 17's bound")
    axis.set_xscale("log", base=2)
    axis.set_xlabel("directions")
    axis.set_ylabel("relative RMSE (%)")
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(stem + ".png", dpi=120)
    plt.close(figure)
    panels = [("Cycles, path-traced", traced)] + [(f"VisiBake, {n} directions", image) for n, image in images.items()]
    figure, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.8))
    top = max(float(image.max()) for _, image in panels) or 1.0
    for axis, (title, image) in zip(np.atleast_1d(axes), panels):
        axis.imshow(np.clip(image[::-1] / top, 0, 1) ** (1 / 2.2))
        axis.set_title(title, fontsize=8)
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(stem + "_renders.png", dpi=120)
    plt.close(figure)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--directions", default="64,256", help="comma-separated direction counts")
    parser.add_argument("--side", type=int, default=64, help="voxels per side of the VDB sphere")
    parser.add_argument("--bounces", type=int, default=1)
    parser.add_argument("--density", type=float, default=8.0)
    parser.add_argument("--samples", type=int, default=1024, help="Cycles samples of the path-traced volume")
    parser.add_argument("--baked-samples", type=int, default=256, help="Cycles samples of the baked volume")
    parser.add_argument("--lightings", default="1,16", help="lighting counts for the time at equal error")
    parser.add_argument("--floor", action="store_true",
                        help="a grey floor under the cloud (it shadows, and lights the cloud from below)")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    options = parser.parse_args()
    folder = os.path.abspath(os.path.join(options.out, "volume_vs_cycles"))
    os.makedirs(folder, exist_ok=True)
    sys.path.insert(0, ROOT)
    blend = build_scene(folder, options.density, options.side, options.floor)
    record = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
              "settings": vars(options), "bakes": []}
    traced = again = covered = None
    images = {}
    cache = os.path.join(folder, "cache")
    for count in [int(c) for c in str(options.directions).split(",")]:
        baked_blend = os.path.join(folder, f"baked_{count}.blend")
        report_path = os.path.join(folder, f"report_{count}.json")
        if os.path.isdir(cache):
            shutil.rmtree(cache)  # the first bake builds its tables
        reports = []
        for attempt in ("built", "cached"):
            started = time.perf_counter()
            subprocess.run([sys.executable, os.path.join(ROOT, "tools", "visibake.py"), "volume", blend, "--out",
                            os.path.join(folder, f"grids_{count}"), "--resolution", str(options.side),
                            "--directions", str(count), "--bounces", str(options.bounces), "--save", baked_blend,
                            "--report", report_path, "--cache-dir", cache, "--no-progress"], check=True)
            if attempt == "built":
                command_seconds = time.perf_counter() - started
            with open(report_path) as handle:
                reports.append(json.load(handle))
            assert reports[-1]["volumes"][0]["tables"] == attempt, reports[-1]["volumes"][0]["tables"]
        report, relit = reports
        if traced is None:
            traced, traced_seconds = render(baked_blend, "source", options.bounces, options.samples, 0,
                                            os.path.join(folder, "cycles.exr"))
            again, _ = render(baked_blend, "source", options.bounces, options.samples, 7,
                              os.path.join(folder, "cycles_2.exr"))
            covered = traced.mean(axis=-1) > 0.01 * traced.max()
            if options.floor:
                # The cloud's pixels only: the floor around it is the same mesh in both renders.
                alone, _ = render(baked_blend, "baked", options.bounces, 16, 0, os.path.join(folder, "mask.exr"),
                                  hide=("Floor",))
                covered = alone.mean(axis=-1) > 0.01 * alone.max()
            scale = traced[covered].mean()
            noise = float(np.sqrt(((traced - again)[covered] ** 2).mean()) / scale / np.sqrt(2))
            quarter, quarter_seconds = render(baked_blend, "source", options.bounces, options.samples // 4, 3,
                                              os.path.join(folder, "cycles_quarter.exr"))
            # Against the mean of the two full renders (whose own noise is noise / sqrt 2).
            quarter_noise = float(np.sqrt(max(((quarter - 0.5 * (traced + again))[covered] ** 2).mean() / scale ** 2
                                              - noise ** 2 / 2, 0.0)))
            record.update(pixels_covered=int(covered.sum()), cycles_noise=round(noise, 4),
                          cycles_path_traced_seconds=round(traced_seconds, 2),
                          cycles_quarter_samples_noise=round(quarter_noise, 4),
                          cycles_quarter_samples_seconds=round(quarter_seconds, 2),
                          cycles_noise_falls_as=("1/sqrt(samples): expect the quarter's noise to be twice the full "
                                                 "render's"))
        baked, baked_seconds = render(baked_blend, "baked", options.bounces, options.baked_samples, 0,
                                      os.path.join(folder, f"baked_{count}.exr"))
        baked_again, _ = render(baked_blend, "baked", options.bounces, options.baked_samples, 7,
                                os.path.join(folder, f"baked_{count}_2.exr"))
        images[count] = baked
        error = float(np.sqrt(((baked - traced)[covered] ** 2).mean()) / scale)
        baked_noise = float(np.sqrt(((baked - baked_again)[covered] ** 2).mean()) / scale / np.sqrt(2))
        own_error = float(np.sqrt(max(error ** 2 - noise ** 2 - baked_noise ** 2, 0.0)))
        # Cycles' samples (and seconds) to path-trace to the bake's own error, from the full render's noise.
        floor = max(own_error, 1e-3)
        cycles_seconds = traced_seconds * (noise / floor) ** 2
        # In a session (the panel) the kernels stay loaded: a further lighting does not load them again.
        relight_seconds = round(relit["seconds"] - relit.get("volume_kernel_load_s", 0.0), 3)
        timing = {}
        for lightings in [int(k) for k in str(options.lightings).split(",")]:
            visibake_seconds = report["seconds"] + (lightings - 1) * relight_seconds
            timing[str(lightings)] = {"cycles_seconds": round(lightings * cycles_seconds, 1),
                                      "visibake_seconds": round(visibake_seconds, 2),
                                      "cycles_over_visibake": round(lightings * cycles_seconds / visibake_seconds, 2)}
        record["bakes"].append({
            "directions": count, "relative_rmse": round(error, 4), "baked_render_noise": round(baked_noise, 4),
            "relative_rmse_without_noise": round(own_error, 4),
            "cycles_samples_to_equal_error": int(round(options.samples * (noise / floor) ** 2)),
            "relight_seconds_with_cached_tables": relight_seconds,
            "relight_volume_seconds": relit["volumes"][0]["seconds"],
            "relight_kernel_load_seconds": relit.get("volume_kernel_load_s"),
            "first_bake_kernel_load_seconds": report.get("volume_kernel_load_s"),
            "time_at_equal_error": timing,
            "mean_ratio": round(float(baked[covered].mean() / scale), 4),
            "visibake_bake_seconds": report["seconds"], "visibake_command_seconds": round(command_seconds, 1),
            "volume_seconds": report["volumes"][0]["seconds"], "cycles_baked_render_seconds": round(baked_seconds, 2)})
        print(json.dumps(record["bakes"][-1]), flush=True)
    _plot(record, traced, images, os.path.join(options.out, "volume_vs_cycles"))
    with open(os.path.join(options.out, "volume_vs_cycles.json"), "w") as handle:
        json.dump(record, handle, indent=1)
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
