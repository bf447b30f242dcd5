"""Mesh lights close to a surface (issue 51): per-object VisiBake / Cycles ratios.

    NUMBA_CACHE_DIR=/tmp/numba-cove .venv/bin/python benchmarks/cove_vs_cycles.py
    .venv/bin/python benchmarks/cove_vs_cycles.py --scenes cove --gaps 0.025 0.5 --samples 256
    .venv/bin/python benchmarks/cove_vs_cycles.py --set sharp_contacts=False   # one switch at a time

Scenes (built here, not in benchmarks/scenes.py: their emitters' albedo 0.9 is above the
bench's MAX_ALBEDO):

- ``cove``: a closed white room 6 x 4 x 3 m (albedo 0.75), lit only by an emissive box
  4 x 0.15 x 0.05 m (albedo 0.9, emission strength 12) hanging ``gap`` below the ceiling;
- ``shelf``: the same room, dark but for an LED strip 1 x 0.02 x 0.01 m (emission 40) 1 cm
  under a 1.2 x 0.3 x 0.03 m shelf on the north wall.

Each is baked with VisiBake (atlas, ``--resolution``^2, ``--directions``, 2 bounces, exact
shadows) and with Cycles (benchmarks/reference.py: two halves, cached in benchmarks/cache),
and the mean of each object's texels that both cover is compared: VisiBake / Cycles, with the
Cycles halves' own disagreement (|a - b| / (a + b), the reference's relative noise on that mean;
it underestimates the LED shelf's, whose mean moved 3% between 64 and 256 samples).

Measured (2026-12-07, 2 cores, bpy 5.0.1, 32^2, 128 directions, Cycles 256 samples), before and
after the emitters' light at the contacts' landing points (core.pipeline.transport):
LED 0.574 -> 0.983, shelf 0.915 -> 0.962, cove ceiling (2.5 cm) 0.981 -> 0.992, cove strip
0.998 -> 0.996; the rest unchanged (walls and floor of the cove within 0.93-1.07: the strip's
light through 128 fixed directions, and at 2.5 cm the gap's light read through ceiling texels
that straddle the strip; at 64^2 and 1024 directions they are within 1.02-1.04).
"""
import argparse
import importlib
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

HALF_X, HALF_Y, HEIGHT = 3.0, 2.0, 3.0
WHITE = (0.75, 0.75, 0.75)


def emissive_material(name, color, strength):
    """A Lambert material (Principled, Roughness 1, no specular layer) that emits ``strength``
    times its base colour's white."""
    import bpy

    from tools.blender_compat import compat

    mat = bpy.data.materials.new(name)
    bsdf = compat.ensure_node_tree(mat).nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bsdf.inputs["Emission Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bsdf.inputs["Emission Strength"].default_value = strength
    return mat


def _white_room(collection):
    from benchmarks import scenes

    scenes._black_world()
    white = emissive_material("White", WHITE, 0.0)
    walls = ("Floor", "Ceiling", "WallWest", "WallEast", "WallNorth", "WallSouth")
    return scenes._room(collection, HALF_X, HALF_Y, HEIGHT, {name: white for name in walls})


def cove(gap: float = 0.025):
    """The issue's probe: the room and a 4 x 0.15 x 0.05 m emissive strip ``gap`` m under the
    ceiling, along x. Returns the objects to bake (the room's six faces and the strip)."""
    from benchmarks import scenes

    collection = scenes._collection("cove")
    objects = _white_room(collection)
    top = HEIGHT - gap
    strip = scenes._solid_box((-2.0, -0.075, top - 0.05), (2.0, 0.075, top))
    objects.append(scenes._object(collection, "Strip", strip, emissive_material("Strip", (0.9, 0.9, 0.9), 12.0)))
    return objects


def shelf():
    """A shelf on the north wall with an LED strip 1 cm under it, the only light of the room."""
    from benchmarks import scenes

    collection = scenes._collection("shelf")
    objects = _white_room(collection)
    y = HALF_Y
    board = scenes._solid_box((-0.6, y - 0.3, 1.20), (0.6, y, 1.23))
    objects.append(scenes._object(collection, "Shelf", board, emissive_material("Wood", (0.6, 0.5, 0.4), 0.0)))
    led = scenes._solid_box((-0.5, y - 0.28, 1.18), (0.5, y - 0.26, 1.19))
    objects.append(scenes._object(collection, "LED", led, emissive_material("LED", (0.9, 0.9, 0.9), 40.0)))
    return objects


def object_means(images, reference) -> dict:
    """{name: mean RGB of ``images`` over the texels both it and ``reference`` cover} of
    {name: (H, W, 4) images} (VisiBake's dilated margins are not Cycles' texels)."""
    means = {}
    for name, image in images.items():
        covered = (image[..., 3] > 0) & (reference[name][..., 3] > 0)
        means[name] = float(image[..., :3][covered].mean()) if covered.any() else 0.0
    return means


def compare(objects, props, resolution, samples, cache, job, reference, dump=None) -> list[tuple]:
    """(name, VisiBake mean, Cycles mean, ratio, reference noise) of each baked object; with
    ``dump`` (a path), both bakes' images are written there (npz, ``ours/<name>``, ``cycles/<name>``)."""
    import numpy as np

    outcome = job.run_bake(__import__("bpy").context, objects)
    uv_maps = {o["name"]: o["uv_map"] for o in outcome.report["objects"] if o["output"]}
    images = {r.name: r.images["lighting"] for r in outcome.result.objects}
    ref = reference.cached_reference(objects, uv_maps, resolution, props.bounces, samples, cache)
    ours = object_means(images, ref.images)
    if dump:
        np.savez(dump, **{f"ours/{k}": v for k, v in images.items()},
                 **{f"cycles/{k}": v for k, v in ref.images.items()})
    theirs = object_means(ref.images, images)
    halves = [object_means(h, images) for h in ref.halves]
    rows = []
    for name in uv_maps:
        a, b = halves[0][name], halves[1][name]
        noise = abs(a - b) / max(a + b, 1e-12)
        rows.append((name, ours[name], theirs[name], ours[name] / max(theirs[name], 1e-12), noise))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=["cove", "shelf"], default=["cove", "shelf"])
    parser.add_argument("--gaps", type=float, nargs="+", default=[0.025, 0.5], help="cove: strip to ceiling (m)")
    parser.add_argument("--resolution", type=int, default=32)
    parser.add_argument("--directions", type=int, default=128)
    parser.add_argument("--samples", type=int, default=256, help="Cycles samples per texel (two halves)")
    parser.add_argument("--set", nargs="*", default=[], metavar="PROP=VALUE",
                        help="scene.visibake properties to change (a Python literal each)")
    parser.add_argument("--dump", metavar="DIR", help="write each case's images to DIR/<case>.npz")
    parser.add_argument("--cache", default=os.path.join(ROOT, "benchmarks", "cache"))
    args = parser.parse_args(argv)

    from tools.visibake import load_extension

    extension = load_extension()
    import ast

    import bpy

    from benchmarks import reference, scenes

    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    cases = [(f"cove, gap {gap * 100:g} cm", lambda g=gap: cove(g)) for gap in args.gaps if "cove" in args.scenes]
    if "shelf" in args.scenes:
        cases.append(("shelf with an LED strip", shelf))
    for title, build in cases:
        scenes.reset()
        objects = build()
        props = bpy.context.scene.visibake
        props.passes = {"lighting"}
        props.use_cache, props.mode = False, "atlas"
        props.resolution, props.bounces, props.shadows = args.resolution, 2, "exact"
        props.directions = args.directions
        for assignment in args.set:
            key, value = assignment.split("=", 1)
            setattr(props, key, ast.literal_eval(value))
        dump = None
        if args.dump:
            os.makedirs(args.dump, exist_ok=True)
            dump = os.path.join(args.dump, title.replace(",", "").replace(" ", "_") + ".npz")
        rows = compare(objects, props, args.resolution, args.samples, args.cache, job, reference, dump)
        print(f"\n{title} ({args.resolution}^2, {args.directions} directions, Cycles {args.samples} spp"
              f"{', ' + ' '.join(args.set) if args.set else ''})")
        print("| object | VisiBake | Cycles | ratio | Cycles noise |")
        for name, ours, theirs, ratio, noise in rows:
            print(f"| {name} | {ours:.4f} | {theirs:.4f} | {ratio:.3f} | {noise:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
