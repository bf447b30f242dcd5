"""VisiBake on scenes built outside the project (``../shared/tools/scenegen.py``) against Cycles.

    NUMBA_CACHE_DIR=/tmp/nc .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 10 12
    .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 10 --set sharp_contacts=False   # one switch
    .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 0 1 2 --json out/scenegen.json

Each seed's scene (rooms and exteriors with suns, skies, point, spot and area lamps of random
radii, emissive strips, slats; nothing tuned to any method) is baked by VisiBake at
``--resolution``^2, ``--directions``, ``--bounces`` (2) and exact shadows, every mesh an output, and by
Cycles on VisiBake's UV layout (benchmarks/reference.py: two halves of ``--samples`` in total,
cached in ``--cache``). Printed per seed: the bake's time and its slowest stages, the shadow
rays, the errors per texel and on 4x4-texel blocks (raw, and with the reference's own noise
taken out, sqrt(e^2 - n^2)), and each object's mean against Cycles' (over the texels both cover),
with the reference halves' own disagreement beside it.
"""
import argparse
import ast
import importlib
import importlib.util
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
SCENEGEN = os.path.join(os.path.dirname(ROOT), "shared", "tools", "scenegen.py")


def load_scenegen(path: str):
    """The scene generator module at ``path`` (its ``build(seed)`` makes the scene in bpy)."""
    spec = importlib.util.spec_from_file_location("scenegen", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def append_json_line(path: str | None, row: dict) -> None:
    """Append ``row`` as one JSON line to ``path`` (the --json file; None: nothing)."""
    if path:
        with open(path, "a") as out:
            out.write(json.dumps(row) + "\n")


def measure(seed: int, args, job, scenegen) -> dict:
    """Bake scene ``seed`` with VisiBake and compare it with Cycles; returns the figures."""
    import bpy

    from benchmarks import reference
    from benchmarks.cove_vs_cycles import object_means

    description = scenegen.build(seed)
    if args.lights is not None:  # keep only these lamps (a diagnosis: which light is off)
        for lamp in [o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.name not in args.lights]:
            bpy.data.objects.remove(lamp)
    if args.world_strength is not None and bpy.context.scene.world is not None:
        bpy.context.scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = args.world_strength
    objects = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    props = bpy.context.scene.visibake
    props.passes = {"lighting"}
    props.use_cache, props.mode = False, "atlas"
    props.resolution, props.bounces, props.shadows = args.resolution, args.bounces, "exact"
    props.directions = args.directions
    for assignment in args.set:
        key, value = assignment.split("=", 1)
        setattr(props, key, ast.literal_eval(value))
    started = time.perf_counter()
    outcome = job.run_bake(bpy.context, objects)
    seconds = time.perf_counter() - started
    report = outcome.report
    uv_maps = {o["name"]: o["uv_map"] for o in report["objects"] if o["output"]}
    images = {r.name: r.images["lighting"] for r in outcome.result.objects}
    ref = reference.cached_reference(objects, uv_maps, args.resolution, args.bounces, args.samples, args.cache)
    texel = reference.relative_errors(images, ref.images)
    blocks = reference.block_errors(images, ref)
    ours, theirs = object_means(images, ref.images), object_means(ref.images, images)
    halves = [object_means(h, images) for h in ref.halves]
    per_object = {}
    for name in sorted(uv_maps):
        a, b = halves[0][name], halves[1][name]
        per_object[name] = dict(ratio=ours[name] / max(theirs[name], 1e-12),
                                noise=abs(a - b) / max(a + b, 1e-12), cycles_mean=theirs[name])
    stages = sorted(report.get("stage_seconds", {}).items(), key=lambda item: -item[1])
    passes = sorted(((p["pass"], p["seconds"]) for p in report.get("passes", [])), key=lambda item: -item[1])
    return dict(seed=seed, description=description, seconds=seconds, stages=stages[:6], passes=passes[:6],
                shadow_rays=report.get("rays", {}).get("shadow_rays"), skipped=report.get("skipped", []),
                texel_rmse=texel["relative_rmse"], bias=texel["bias"], texel_noise=blocks["texel_noise"],
                texel_rmse_denoised=blocks["texel_rmse_denoised"], block_rmse=blocks["block_rmse"],
                block_noise=blocks["block_noise"], block_rmse_denoised=blocks["block_rmse_denoised"],
                objects=per_object, settings=list(args.set) + [f"bounces={args.bounces}"]
                + ([f"lights={args.lights}"] if args.lights is not None else []))


def show(row: dict) -> None:
    print(f"\nseed {row['seed']}: {row['description']} ({' '.join(row['settings']) or 'defaults'})")
    print(f"  VisiBake {row['seconds']:.2f} s, shadow rays {row['shadow_rays']}; slowest passes: "
          + ", ".join(f"{name} {sec:.2f} s" for name, sec in row["passes"]))
    print(f"  per texel {100 * row['texel_rmse']:.2f}% (noise {100 * (row['texel_noise'] or 0):.2f}%, "
          f"without it {100 * (row['texel_rmse_denoised'] or 0):.2f}%), bias {100 * row['bias']:+.2f}%; "
          f"blocks {100 * row['block_rmse']:.2f}% (noise {100 * (row['block_noise'] or 0):.2f}%)")
    print("  objects (VisiBake / Cycles, Cycles halves' disagreement): " + ", ".join(
        f"{name} {o['ratio']:.3f} ({o['noise']:.3f})" for name, o in row["objects"].items()))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[10, 12])
    parser.add_argument("--scenegen", default=SCENEGEN, help="the scene generator (default: ../shared/tools)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--directions", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--samples", type=int, default=1024, help="Cycles reference samples per texel (two halves)")
    parser.add_argument("--set", nargs="*", default=[], metavar="PROP=VALUE",
                        help="scene.visibake properties to change (a Python literal each)")
    parser.add_argument("--lights", nargs="*", help="keep only the lamps named (none: no lamp)")
    parser.add_argument("--world-strength", type=float, help="set the world's background strength")
    parser.add_argument("--cache", default=os.path.join(ROOT, "benchmarks", "cache"))
    parser.add_argument("--json", help="append one JSON line a seed to this file")
    args = parser.parse_args(argv)

    from tools.visibake import load_extension

    extension = load_extension()
    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    scenegen = load_scenegen(args.scenegen)
    for seed in args.seeds:
        row = measure(seed, args, job, scenegen)
        show(row)
        append_json_line(args.json, row)
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
