"""VisiBake on the demo scene against a converged Cycles bake of the same UV layout.

    .venv/bin/python benchmarks/demo_vs_cycles.py --directions 128 256 --samples 1024 --sweep 16 64 256

For each direction count and shadow mode: VisiBake's stage times and its relative
RMSE / mean bias / max error of ``lighting`` against Cycles (DIFFUSE, DIRECT+INDIRECT+COLOR,
same bounces, units as in DESIGN.md), over texels both cover, per texel and on the means of
4x4-texel blocks (benchmarks/reference.py). Cycles is baked at each ``--sweep`` sample count
too, and the time it needs for VisiBake's error is interpolated from that sweep as ``make
bench`` does (benchmarks/run.py: log-log, extrapolated as error ~ samples^-1/2 beyond it):
the ratio Cycles / VisiBake at equal error, per texel and on blocks. Writes JSON (and prints
a table). The reference is baked as two halves with different seeds, cached in --cache (.npz
keyed by samples, seed, resolution, bounces) like the sweep's bakes (with their times); half
the RMS difference of the halves is the reference's own noise, printed beside the errors
(they include it).
"""
import argparse
import json
import os
import platform
import sys
import time
from datetime import datetime, timezone

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

from benchmarks import reference as references  # noqa: E402
from benchmarks.limits import embree_rays_per_second  # noqa: E402
from benchmarks.run import interpolate_time_at_error  # noqa: E402
from tools.visibake import load_extension  # noqa: E402


def covered_error(ours: dict, reference: dict) -> dict:
    squared, total, count, worst = 0.0, 0.0, 0, 0.0
    ours_sum = 0.0
    for name, image in ours.items():
        ref = reference[name]
        mask = (image[..., 3] > 0) & (ref[..., 3] > 0)
        a, b = image[mask][:, :3].astype(np.float64), ref[mask][:, :3].astype(np.float64)
        squared += float(np.sum((a - b) ** 2))
        total += float(np.sum(b))
        ours_sum += float(np.sum(a))
        count += a.size
        worst = max(worst, float(np.max(np.abs(a - b))) if a.size else 0.0)
    mean = total / count
    return {"relative_rmse": np.sqrt(squared / count) / mean, "bias": ours_sum / total - 1.0,
            "max_abs_error": worst, "reference_mean": mean, "values": count}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--directions", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--shadows", nargs="+", default=["exact"])
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--interleave", type=int, default=None, help="interleaved rotations (default: the setting's)")
    parser.add_argument("--samples", type=int, default=1024, help="Cycles samples of the reference")
    parser.add_argument("--sweep", type=int, nargs="+", default=[16, 64, 256],
                        help="Cycles sample counts baked and timed, to interpolate its time at VisiBake's error")
    parser.add_argument("--cache", default=os.path.join(ROOT, "benchmarks", "cache"))
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "demo_vs_cycles.json"))
    args = parser.parse_args()

    extension = load_extension()
    import importlib

    import bpy

    from tools.cycles_bake import bake_diffuse

    demo_scene = importlib.import_module(f"{extension.__name__}.operators.adapter.demo_scene")
    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = demo_scene.build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    props.bounces, props.resolution, props.passes = args.bounces, args.resolution, {"lighting"}
    props.use_cache = False  # every run traces its own table, so its timing is the method's
    if args.interleave is not None:
        props.interleave = args.interleave

    runs = []
    for directions in args.directions:
        for shadows in args.shadows:
            props.directions, props.shadows = directions, shadows
            outcome = job.run_bake(bpy.context, objects)
            images = {r.name: r.images["lighting"] for r in outcome.result.objects if r.domain is None}
            runs.append({"directions": directions, "shadows": shadows, "images": images,
                         "stage_seconds": outcome.report["stage_seconds"],
                         "total_seconds": outcome.report["total_seconds"],
                         "rays": outcome.report["rays"], "peak_memory_bytes": outcome.report["peak_memory_bytes"]})
            print(f"VisiBake N={directions} {shadows}: {outcome.report['total_seconds']:.1f} s", flush=True)
    # Atlas objects only: the vertex-mode dome has no image (tests/blender/test_vertex_mode.py
    # compares vertex colours with Cycles).
    uv_maps = {o["name"]: o["uv_map"] for o in outcome.report["objects"] if o.get("mode", "atlas") == "atlas"}

    def cycles(samples, seed=0):
        result, started = {}, time.perf_counter()
        for uv_map in sorted(set(uv_maps.values())):
            group = [o for o in objects if uv_maps.get(o.name) == uv_map]
            result.update(bake_diffuse(group, uv_map, args.resolution, args.resolution, args.bounces, samples,
                                       seed=seed))
        return result, time.perf_counter() - started

    # The reference is two independent halves (different seeds): their mean is the
    # reference, and half the RMS of their difference is the reference's own noise.
    os.makedirs(args.cache, exist_ok=True)
    halves = []
    reference_seconds = 0.0
    for seed in (1, 2):
        key = f"demo_cycles_s{args.samples // 2}_seed{seed}_r{args.resolution}_b{args.bounces}.npz"
        cached = os.path.join(args.cache, key)
        if os.path.isfile(cached):
            data = np.load(cached)
            half = {k: data[k] for k in data.files if k != "__seconds__"}
            seconds = float(data["__seconds__"])
        else:
            half, seconds = cycles(args.samples // 2, seed)
            np.savez_compressed(cached, __seconds__=seconds, **half)
        halves.append(half)
        reference_seconds += seconds
    reference = {name: 0.5 * (halves[0][name] + halves[1][name]) for name in halves[0]}
    reference_noise = 0.5 * covered_error(halves[0], halves[1])["relative_rmse"]
    whole = references.Reference(images=reference, seconds=reference_seconds, noise=reference_noise, cached=True,
                                 halves=tuple(halves))
    block_noise = references.block_errors(reference, whole)["block_noise"]
    print(f"Cycles {args.samples} spp: {reference_seconds:.1f} s, relative noise {reference_noise:.4f} per texel, "
          f"{block_noise:.4f} on 4x4 blocks", flush=True)
    sweep = []
    for samples in args.sweep:
        # Cached like the reference's halves: a second run (another VisiBake setting) reuses them.
        cached = os.path.join(args.cache, f"demo_cycles_s{samples}_seed3_r{args.resolution}_b{args.bounces}.npz")
        if os.path.isfile(cached):
            data = np.load(cached)
            images, seconds = {k: data[k] for k in data.files if k != "__seconds__"}, float(data["__seconds__"])
        else:
            images, seconds = cycles(samples, seed=3)
            np.savez_compressed(cached, __seconds__=seconds, **images)
        sweep.append({"samples": samples, "seconds": seconds, **covered_error(images, reference),
                      "block_rmse": references.block_errors(images, whole)["block_rmse"]})
        print(f"Cycles {samples} spp: {seconds:.1f} s, RMSE {sweep[-1]['relative_rmse']:.4f}, "
              f"blocks {sweep[-1]['block_rmse']:.4f}", flush=True)

    extract = importlib.import_module(f"{extension.__name__}.operators.adapter.extract")
    depsgraph = bpy.context.evaluated_depsgraph_get()
    meshes = [extract.read_mesh(o, depsgraph, "", (0, 0), True, []) for o in objects]
    raw_rate = embree_rays_per_second(meshes)
    print(f"embreex alone: {raw_rate / 1e6:.2f} Mrays/s", flush=True)

    rows = []
    for run in runs:
        visibility_seconds = max(run["stage_seconds"]["visibility"], 1e-9)
        run["visibility_rays_per_second"] = run["rays"]["visibility_cast"] / visibility_seconds
        run["visibility_fraction_of_embree"] = run["visibility_rays_per_second"] / raw_rate
        images = run.pop("images")
        error = covered_error(images, reference)
        blocks = references.block_errors(images, whole)["block_rmse"]
        at = interpolate_time_at_error(sweep, error["relative_rmse"])
        at_blocks = interpolate_time_at_error([{"seconds": c["seconds"], "relative_rmse": c["block_rmse"]}
                                               for c in sweep], blocks)
        rows.append({**run, **error, "block_rmse": blocks, "cycles_seconds_at_error": at,
                     "cycles_over_visibake": at / run["total_seconds"], "cycles_seconds_at_block_error": at_blocks,
                     "cycles_over_visibake_on_blocks": at_blocks / run["total_seconds"]})
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()},
        "blender": bpy.app.version_string,
        "settings": {"bounces": args.bounces, "resolution": args.resolution, "reference_samples": args.samples,
                     "interleave": props.interleave},
        "embree_rays_per_second": raw_rate,
        "cycles_reference_seconds": reference_seconds,
        "cycles_reference_relative_noise": reference_noise,
        "cycles_reference_block_noise": block_noise,
        "cycles_sweep": sweep,
        "visibake": rows,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as handle:
        json.dump(result, handle, indent=2, default=float)
    print(f"\n{'run':<28}{'seconds':>9}{'rel.RMSE':>10}{'bias':>9}{'blocks':>9}")
    for row in rows:
        print(f"VisiBake N={row['directions']:<4} {row['shadows']:<10}{row['total_seconds']:>9.1f}"
              f"{row['relative_rmse']:>10.4f}{row['bias']:>+9.4f}{row['block_rmse']:>9.4f}"
              f"  Cycles / VisiBake at equal error {row['cycles_over_visibake']:.1f} per texel, "
              f"{row['cycles_over_visibake_on_blocks']:.1f} on blocks; stages {row['stage_seconds']}"
              f"  visibility at {row['visibility_fraction_of_embree']:.0%} of embreex alone")
    for point in sweep:
        print(f"{'Cycles ' + str(point['samples']) + ' spp':<28}{point['seconds']:>9.1f}"
              f"{point['relative_rmse']:>10.4f}{point['bias']:>+9.4f}{point['block_rmse']:>9.4f}")
    print(f"{'Cycles ' + str(args.samples) + ' spp (reference)':<28}{reference_seconds:>9.1f}"
          f"{reference_noise:>10.4f}  (its own noise, from two independent halves)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
