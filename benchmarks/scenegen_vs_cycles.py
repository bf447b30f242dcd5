"""VisiBake on scenes built outside the project (``../shared/tools/scenegen.py``) against Cycles.

    NUMBA_CACHE_DIR=/tmp/nc .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 10 12
    .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 10 --set sharp_contacts=False   # one switch
    .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds 0 1 2 --json out/scenegen.json
    .venv/bin/python benchmarks/scenegen_vs_cycles.py --seeds $(seq 0 19) --target-error 0.03 --sweep 1 4 16 64 256

Each seed's scene (rooms and exteriors with suns, skies, point, spot and area lamps of random
radii, emissive strips, slats; nothing tuned to any method) is baked by VisiBake at
``--resolution``^2, ``--directions``, ``--bounces`` (2) and exact shadows, every mesh an output, and by
Cycles on VisiBake's UV layout (benchmarks/reference.py: two halves of ``--samples`` in total,
cached in ``--cache``). Printed per seed: the bake's time and its slowest stages, the shadow
rays, the errors per texel and on 4x4-texel blocks (raw, and with the reference's own noise
taken out, sqrt(e^2 - n^2)), and each object's mean against Cycles' (over the texels both cover),
with the reference halves' own disagreement beside it; the errors also without the texels no camera
sees wholly (benchmarks/reference.py hidden_texels: inside or face to face with other geometry,
wholly or in part, which each method fills its own way). ``--target-error E`` bakes at that Target Error
(each seed choosing its directions afresh) instead of ``--directions``; ``--sweep S ...`` also times
Cycles at those samples on the same layout and gives its time at VisiBake's error on both metrics
(benchmarks/run.py interpolate_time_at_error), as Cycles / VisiBake; ``--summarize FILE`` prints
the median and worst of those ratios from a --json file.
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
    props.target_error, props.chosen_directions = args.target_error or 0.0, 0
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
    hidden = reference.hidden_texels(objects, uv_maps, args.resolution)
    seen_images, seen_ref = reference.without_hidden(images, ref, hidden)
    seen_blocks = reference.block_errors(seen_images, seen_ref)
    visible = dict(hidden_texels=int(sum(int(m.sum()) for m in hidden.values())),
                   texel_rmse=reference.relative_errors(seen_images, seen_ref.images)["relative_rmse"],
                   texel_rmse_denoised=seen_blocks["texel_rmse_denoised"], texel_noise=seen_blocks["texel_noise"],
                   block_rmse=seen_blocks["block_rmse"], block_rmse_denoised=seen_blocks["block_rmse_denoised"])
    ours, theirs = object_means(images, ref.images), object_means(ref.images, images)
    halves = [object_means(h, images) for h in ref.halves]
    per_object = {}
    for name in sorted(uv_maps):
        a, b = halves[0][name], halves[1][name]
        per_object[name] = dict(ratio=ours[name] / max(theirs[name], 1e-12),
                                noise=abs(a - b) / max(a + b, 1e-12), cycles_mean=theirs[name])
    speed = cycles_speed(objects, uv_maps, args, ref, seconds, texel["relative_rmse"], blocks["block_rmse"]) \
        if args.sweep else {}
    stages = sorted(report.get("stage_seconds", {}).items(), key=lambda item: -item[1])
    passes = sorted(((p["pass"], p["seconds"]) for p in report.get("passes", [])), key=lambda item: -item[1])
    return dict(seed=seed, description=description, seconds=seconds, stages=stages[:6], passes=passes[:6],
                shadow_rays=report.get("rays", {}).get("shadow_rays"), skipped=report.get("skipped", []),
                texel_rmse=texel["relative_rmse"], bias=texel["bias"], texel_noise=blocks["texel_noise"],
                texel_rmse_denoised=blocks["texel_rmse_denoised"], block_rmse=blocks["block_rmse"],
                block_noise=blocks["block_noise"], block_rmse_denoised=blocks["block_rmse_denoised"],
                visible=visible, objects=per_object, settings=list(args.set) + [f"bounces={args.bounces}"]
                + ([f"lights={args.lights}"] if args.lights is not None else []),
                target=report.get("target"), estimated_error=(report.get("estimated_error") or {}).get("total"),
                directions=report["settings"]["directions"], **speed)


def cycles_speed(objects, uv_maps: dict, args, ref, seconds: float, texel_error: float, block_error: float) -> dict:
    """Cycles' sweep at ``args.sweep`` samples on the same layout, and its time at VisiBake's errors
    (per texel and on 4x4 blocks) over VisiBake's ``seconds``: {cycles_over_visibake,
    cycles_over_visibake_blocks, cycles_sweep}."""
    from benchmarks import reference
    from benchmarks.run import interpolate_time_at_error
    from tools.cycles_bake import bake_diffuse

    sweep = []
    for samples in args.sweep:
        started = time.perf_counter()
        images = {}
        for uv_map in sorted(set(uv_maps.values())):
            group = [o for o in objects if uv_maps.get(o.name) == uv_map]
            images.update(bake_diffuse(group, uv_map, args.resolution, args.resolution, args.bounces, samples, seed=3))
        took = time.perf_counter() - started
        sweep.append(dict(samples=samples, seconds=took,
                          relative_rmse=reference.relative_errors(images, ref.images)["relative_rmse"],
                          block_rmse=reference.block_errors(images, ref)["block_rmse"]))
    at_texel = interpolate_time_at_error(sweep, texel_error)
    at_blocks = interpolate_time_at_error([dict(seconds=r["seconds"], relative_rmse=r["block_rmse"]) for r in sweep],
                                          block_error)
    return dict(cycles_over_visibake=at_texel / seconds, cycles_over_visibake_blocks=at_blocks / seconds,
                cycles_sweep=sweep)


def summarize(path: str) -> int:
    """The median and worst Cycles / VisiBake ratios of a --json file's seeds, and the worst named."""
    import statistics

    rows = [json.loads(line) for line in open(path) if line.strip()]
    rows = [r for r in rows if "cycles_over_visibake" in r]
    for key in ("cycles_over_visibake", "cycles_over_visibake_blocks"):
        worst = min(rows, key=lambda r: r[key])
        print(f"{key}: median {statistics.median(r[key] for r in rows):.2f}, worst {worst[key]:.2f} "
              f"(seed {worst['seed']}: {worst['description']})")
    for label, error in (("", lambda r: r["texel_rmse_denoised"]),
                         (" (texels a camera sees)", lambda r: (r.get("visible") or {}).get("texel_rmse_denoised"))):
        measured = [r for r in rows if r.get("target") and error(r) is not None]
        if not measured:
            continue
        over = [r for r in measured if error(r) > 1.2 * r["target"]["target_error"]]
        print(f"{len(measured)} seeds; measured error{label} above 1.2 x the target on {len(over)}: "
              + ", ".join(f"{r['seed']} ({100 * error(r):.1f}%)" for r in over))
    return 0


def show(row: dict) -> None:
    print(f"\nseed {row['seed']}: {row['description']} ({' '.join(row['settings']) or 'defaults'})")
    if row.get("cycles_over_visibake") is not None:
        print(f"  {row['directions']} directions, estimated {100 * (row['estimated_error'] or 0):.2f}%; "
              f"Cycles / VisiBake at equal error: per texel {row['cycles_over_visibake']:.2f}, "
              f"on blocks {row['cycles_over_visibake_blocks']:.2f}")
    print(f"  VisiBake {row['seconds']:.2f} s, shadow rays {row['shadow_rays']}; slowest passes: "
          + ", ".join(f"{name} {sec:.2f} s" for name, sec in row["passes"]))
    print(f"  per texel {100 * row['texel_rmse']:.2f}% (noise {100 * (row['texel_noise'] or 0):.2f}%, "
          f"without it {100 * (row['texel_rmse_denoised'] or 0):.2f}%), bias {100 * row['bias']:+.2f}%; "
          f"blocks {100 * row['block_rmse']:.2f}% (noise {100 * (row['block_noise'] or 0):.2f}%)")
    if row.get("visible"):
        seen = row["visible"]
        print(f"  without the {seen['hidden_texels']} texels no camera sees (inside or face to face with other "
              f"geometry, wholly or in part): per texel {100 * seen['texel_rmse']:.2f}% (without the reference's noise "
              f"{100 * (seen['texel_rmse_denoised'] or 0):.2f}%), blocks {100 * seen['block_rmse']:.2f}%")
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
    parser.add_argument("--target-error", type=float, help="bake at this Target Error (choosing the directions)")
    parser.add_argument("--sweep", type=int, nargs="*", help="Cycles samples to time against (e.g. 1 4 16 64 256)")
    parser.add_argument("--summarize", metavar="JSONL", help="only print the ratios' median and worst of a --json file")
    args = parser.parse_args(argv)
    if args.summarize:
        return summarize(args.summarize)

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
