"""Seam stitching judged on renders (issue 15, item 4): `make bench BENCH_PROFILE=seams`.

Cycles does not stitch, so texel error against a Cycles bake cannot judge stitching. This
judges it where a seam shows: in a render of the baked lighting. The scene is smooth
shapes (a UV sphere, a cylinder, a torus) on a floor under a sun, whose xatlas charts cut
them along many seams. It is baked with *Stitch Seams* off and on; each bake is rendered
through its textures (operators.adapter.preview_render: emission of the ``lighting``
image, bilinear filtering, no lamps, no bounces); and Cycles renders the real scene, lit
by its sun with the same diffuse bounces, as two independent halves (so the truth's own
noise is known).

Every render has the same camera. The metrics, relative RMSE against the truth over the
objects' pixels:
- all pixels;
- the seam pixels: where stitching changed the render at all (more than 0.2% of the mean),
  chosen by what stitching did, not by either render's error;
and the report's disagreement of the seams' two sides (before and after, per object).

Writes ``seams.json``, ``summary.md`` and ``seams.png`` (off, on, truth, and the
seam pixels) to ``--out`` (default benchmarks/results/seams-<time>).
"""
from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import time
from datetime import datetime, timezone

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

CHANGED = 0.002  # a pixel stitching moved by more than this share of the mean is a seam pixel


def build_scene():
    """Floor, UV sphere, cylinder and torus (all smooth) under a 40-degree sun, and a camera."""
    import bpy

    import bmesh
    from mathutils import Matrix

    from benchmarks import scenes

    scenes.reset()
    col = scenes._collection("smooth_shapes")
    scenes._black_world()
    objects = [scenes._object(col, "Floor", scenes._ground(6.0), scenes._material("Floor", scenes._FLOOR))]
    sphere = bmesh.new()
    bmesh.ops.create_uvsphere(sphere, u_segments=32, v_segments=16, radius=0.6)
    objects.append(scenes._object(col, "Sphere", sphere, scenes._material("Sphere", (0.7, 0.7, 0.7)),
                                  location=(-0.9, 0.2, 0.6), smooth=True))
    cylinder = bmesh.new()
    bmesh.ops.create_cone(cylinder, cap_ends=True, cap_tris=False, segments=32, radius1=0.35, radius2=0.35,
                          depth=1.2, matrix=Matrix.Translation((0.0, 0.0, 0.6)))
    objects.append(scenes._object(col, "Cylinder", cylinder, scenes._material("Cylinder", (0.6, 0.5, 0.4)),
                                  location=(0.6, 0.6, 0.0), smooth=True))
    torus = bmesh.new()
    scenes._torus(torus, 0.45, 0.15, 32, 16)
    objects.append(scenes._object(col, "Torus", torus, scenes._material("Torus", (0.3, 0.5, 0.7)),
                                  location=(0.4, -0.9, 0.15), smooth=True))
    scenes._sun(col, 4.0, elevation=40.0, heading=120.0)
    camera = bpy.data.cameras.new("Camera")
    camera.lens = 40.0
    rig = bpy.data.objects.new("Camera", camera)
    col.objects.link(rig)
    rig.location = (0.2, -4.2, 2.4)
    direction = np.array([-0.1, 0.0, 0.4]) - np.array(rig.location)
    rig.rotation_euler = (math.atan2(math.hypot(direction[0], direction[1]), -direction[2]), 0.0,
                          math.atan2(direction[1], direction[0]) - math.pi / 2)
    bpy.context.scene.camera = rig
    return objects


def read_exr(path: str, width: int, height: int) -> np.ndarray:
    """(height, width, 3) float64 linear pixels of a render saved as EXR, row 0 at the bottom."""
    import bpy

    image = bpy.data.images.load(path, check_existing=False)
    try:
        pixels = np.empty(width * height * 4, np.float32)
        image.pixels.foreach_get(pixels)
        return pixels.reshape(height, width, 4)[..., :3].astype(np.float64)
    finally:
        bpy.data.images.remove(image)


def render_truth(path: str, width: int, height: int, samples: int, seed: int, bounces: int) -> np.ndarray:
    """Cycles' render of the lit scene: diffuse only, ``bounces`` diffuse bounces, as an EXR."""
    import bpy

    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = width, height, 100
    cycles = scene.cycles
    cycles.samples, cycles.seed, cycles.use_denoising, cycles.use_adaptive_sampling = samples, seed, False, False
    cycles.max_bounces, cycles.diffuse_bounces = bounces + 1, bounces
    cycles.glossy_bounces = cycles.transmission_bounces = cycles.volume_bounces = cycles.transparent_max_bounces = 0
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    return read_exr(path, width, height)


def render_bake(preview, path: str, objects, uv_maps, width: int, height: int, samples: int) -> np.ndarray:
    """The render of the baked ``lighting`` textures through the extension's
    ``preview`` (operators.adapter.preview_render), as an EXR (linear, unclipped)."""
    import bpy

    scene = bpy.context.scene
    preview.render_baked_preview(scene, [o.name for o in objects], path, uv_maps, width, height, samples,
                                 file_format="OPEN_EXR")
    return read_exr(path, width, height)


def relative_rmse(image: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    if not mask.any():
        return 0.0
    return float(np.sqrt(np.mean((image[mask] - truth[mask]) ** 2)) / np.mean(truth[mask]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--directions", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=300)
    parser.add_argument("--truth-samples", type=int, default=512, help="per half of the truth render")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    out = os.path.abspath(args.out or os.path.join(ROOT, "benchmarks", "results", f"seams-{stamp}"))
    os.makedirs(out, exist_ok=True)

    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    from benchmarks.run import machine

    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    preview = importlib.import_module(f"{extension.__name__}.operators.adapter.preview_render")
    objects = build_scene()
    props = bpy.context.scene.visibake
    props.passes = {"lighting"}
    props.use_cache, props.mode = False, "atlas"
    props.resolution, props.bounces, props.shadows, props.directions = (args.resolution, args.bounces, "exact",
                                                                        args.directions)
    renders, reports, seconds = {}, {}, {}
    for stitch in (False, True):
        props.stitch_seams = stitch
        started = time.perf_counter()
        outcome = job.run_bake(bpy.context, objects)
        seconds[stitch] = time.perf_counter() - started
        uv_maps = {o["name"]: o["uv_map"] for o in outcome.report["objects"] if o["output"]}
        reports[stitch] = {o["name"]: {"seam_edges": o.get("seam_edges"), "seam_disagreement": o.get(
            "seam_disagreement")} for o in outcome.report["objects"]}
        stitch_pass = [p for p in outcome.report["passes"] if p["pass"].startswith("seam stitching")]
        reports[stitch]["stitch_seconds"] = stitch_pass[0]["seconds"] if stitch_pass else 0.0
        name = "on" if stitch else "off"
        renders[name] = render_bake(preview, os.path.join(out, f"bake_{name}.exr"), objects, uv_maps, args.width,
                                    args.height, 16)
        print(f"stitching {name}: bake {seconds[stitch]:.1f} s", flush=True)
    started = time.perf_counter()
    halves = [render_truth(os.path.join(out, f"truth_{seed}.exr"), args.width, args.height, args.truth_samples,
                           seed, args.bounces) for seed in (1, 2)]
    truth_seconds = time.perf_counter() - started
    truth = 0.5 * (halves[0] + halves[1])
    # The baked renders hide the lamps; the truth shows the black world where no object is.
    objects_mask = truth.max(axis=2) > 1e-4
    mean = float(truth[objects_mask].mean())
    seam_mask = objects_mask & (np.abs(renders["on"] - renders["off"]).max(axis=2) > CHANGED * mean)
    noise_all = relative_rmse(halves[0], halves[1], objects_mask) / 2.0
    noise_seam = relative_rmse(halves[0], halves[1], seam_mask) / 2.0
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
        "blender": bpy.app.version_string, "resolution": args.resolution, "directions": args.directions,
        "bounces": args.bounces, "render": [args.width, args.height], "truth_samples": 2 * args.truth_samples,
        "truth_seconds": truth_seconds, "bake_seconds": {"off": seconds[False], "on": seconds[True]},
        "stitch_seconds": reports[True].pop("stitch_seconds"), "seams": reports[True],
        "object_pixels": int(objects_mask.sum()), "seam_pixels": int(seam_mask.sum()),
        # The truth's own noise: half the RMS difference of its halves is the noise of their mean.
        "truth_noise": {"all": noise_all, "seam": noise_seam},
        "rmse": {name: {"all": relative_rmse(renders[name], truth, objects_mask),
                        "seam": relative_rmse(renders[name], truth, seam_mask)} for name in ("off", "on")},
    }
    reports[False].pop("stitch_seconds")
    with open(os.path.join(out, "seams.json"), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
    figure(os.path.join(out, "seams.png"), renders, truth, seam_mask)
    with open(os.path.join(out, "summary.md"), "w", encoding="utf-8") as handle:
        handle.write(markdown(result))
    print(markdown(result))
    return 0


def figure(path: str, renders: dict, truth: np.ndarray, seam_mask: np.ndarray) -> None:
    """Off, on, truth (display-encoded, same exposure) and the seam pixels, full frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scale = np.percentile(truth, 99.5)

    def shown(image):
        return np.clip(image / scale, 0, 1) ** (1 / 2.2)

    panels = [("stitching off", shown(renders["off"])), ("stitching on", shown(renders["on"])),
              ("Cycles render (truth)", shown(truth)), ("seam pixels", seam_mask.astype(float))]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.3))
    for axis, (title, image) in zip(axes, panels):
        axis.imshow(image, cmap="gray" if image.ndim == 2 else None, origin="lower")
        axis.set_title(title)
        axis.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def markdown(result: dict) -> str:
    rmse, noise = result["rmse"], result["truth_noise"]
    lines = [f"Blender {result['blender']}, {result['machine'].get('cpus', '?')} CPUs, {result['date']}; "
             f"{result['resolution']}² atlases, N = {result['directions']}, {result['bounces']} bounces; renders "
             f"{result['render'][0]}×{result['render'][1]}, truth {result['truth_samples']} spp "
             f"({result['truth_seconds']:.0f} s).", "",
             "| pixels | count | stitching off | stitching on | truth's noise |", "|---|---|---|---|---|",
             f"| all object pixels | {result['object_pixels']} | {rmse['off']['all']:.2%} | {rmse['on']['all']:.2%} "
             f"| {noise['all']:.2%} |",
             f"| seam pixels | {result['seam_pixels']} | {rmse['off']['seam']:.2%} | {rmse['on']['seam']:.2%} "
             f"| {noise['seam']:.2%} |", "",
             f"Stitching took {result['stitch_seconds']:.3f} s of a {result['bake_seconds']['on']:.1f} s bake.", "",
             "| object | seam edges | sides disagree, before | after |", "|---|---|---|---|"]
    for name, entry in result["seams"].items():
        if entry["seam_edges"]:
            before, after = entry["seam_disagreement"]
            lines.append(f"| {name} | {entry['seam_edges']} | {before:.2%} | {after:.2%} |")
        else:
            lines.append(f"| {name} | 0 (no seam between smooth faces) | | |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat  # bpy is loaded by now

    compat.end_module_process(status)
