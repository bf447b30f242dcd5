"""The kernels issue 16's part 6 changed, before and after, on real bakes: the surface gather
(against the bare table walk it is measured by) on the bake's table, and the ray setup on the
first chunk of rays its trace casts. Before and after run in one process, interleaved, best
of ``--rounds`` (this VM's speed drifts within minutes, so separate runs do not compare).

The earlier kernels are taken from git at ``--before`` (default c285482, the last commit with
them). Both must give the same bits; the script exits 1 otherwise.

    .venv/bin/python benchmarks/kernels_ab.py [--before SHA] [--scenes demo sun_occluders ...]
        [--rounds 15] [--threads 2] [--out docs/speed/part6/kernels_ab.json]

The demo is baked as ``visibake demo`` bakes it (128 directions); a benchmark scene at 64^2,
256 directions and exact shadows, as ``make bench`` bakes its N = 256 row.
"""
import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", default="c285482")
    parser.add_argument("--scenes", nargs="+", default=["demo", "sun_occluders", "interior_opening"])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--threads", type=int, default=0, help="kernel threads (0: all cores)")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "kernels_ab.json"))
    args = parser.parse_args(argv)

    from benchmarks import limits, scenes
    from benchmarks.earlier import earlier_module
    from benchmarks.run import write_results
    from tools.visibake import loaded_extension

    extension, module = loaded_extension()
    import bpy

    kernels = module("core.kernels")
    current = kernels.compiled()
    if current is None:
        print(f"compiled kernels unavailable ({kernels.status().reason}): nothing to compare", file=sys.stderr)
        return 2
    earlier = earlier_module(args.before, "core/kernels/transport_kernels.py", "earlier_transport_kernels")
    earlier_table = earlier_module(args.before, "core/kernels/table_kernels.py", "earlier_table_kernels")
    tolerances = module("core.tolerances")
    job, gather = module("operators.adapter.job"), module("core.transport.gather")
    extraction, adapter_settings = module("operators.adapter.extraction"), module("operators.adapter.settings")
    prepare = module("core.pipeline.prepare").prepare
    cpu_backend = module("core.transport.cpu").CPU_BACKEND
    GatherSource = module("core.transport.contract").GatherSource
    rows = []
    for name in args.scenes:
        scenes.reset()
        props = bpy.context.scene.visibake
        props.use_cache = False
        if name == "demo":
            objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
        else:
            objects = scenes.SCENES[name]("full")
            props.passes = {"lighting"}
            props.mode = "atlas"
            props.resolution, props.bounces, props.directions, props.shadows = 64, 2, 256, "exact"
        job.run_bake(bpy.context, objects)  # lays out the UV maps the table is traced on
        scene = extraction.extract_scene(bpy.context, objects).scene
        prepared = prepare(scene, adapter_settings.bake_settings(props), table_needed=True)
        geometry = prepared.gather_geometry()
        # The scene's albedo lit uniformly: any atlas will do, a gather's cost does not depend on it.
        source = GatherSource(prepared.to_atlas(prepared.albedo, cpu_backend.dilate), np.zeros(3))
        chosen = np.arange(len(geometry.normals), dtype=np.int64)
        before, after = gather.gather_kernel_arguments(geometry, source, chosen)
        directions = len(prepared.table.directions)
        outputs = {}

        def kernel_call(kernel, label):
            def call():
                after[-1][:] = 0
                kernels.run(kernel, geometry.threads if not args.threads else args.threads, *before, 0, directions,
                            *after)
                outputs[label] = after[-1].copy()
            return call

        calls = {"before": kernel_call(earlier.gather, "before"), "after": kernel_call(current.gather, "after"),
                 "bare walk": limits.bare_lookup_call(kernels, prepared.table, geometry, source.radiance,
                                                      args.threads)}
        best = dict.fromkeys(calls, np.inf)
        for call in calls.values():
            call()  # compiles the earlier kernel; warms the caches
        for _ in range(args.rounds):
            for label, call in calls.items():
                started = time.perf_counter()
                call()
                best[label] = min(best[label], time.perf_counter() - started)
        bitwise = bool(np.array_equal(outputs["before"], outputs["after"]))
        setup = ray_setup_ab(prepared, earlier_table.ray_setup, tolerances, kernels, args.rounds)
        rows.append({"scene": name, "samples": int(len(chosen)), "directions": directions, **setup,
                     "entries_above_horizon": int(prepared.table.rays_cast),
                     "before_seconds": round(best["before"], 4), "after_seconds": round(best["after"], 4),
                     "bare_walk_seconds": round(best["bare walk"], 4),
                     "before_share_of_bare": round(best["bare walk"] / best["before"], 3),
                     "after_share_of_bare": round(best["bare walk"] / best["after"], 3),
                     "speedup": round(best["before"] / best["after"], 3), "bitwise": bitwise})
        print(f"{name}: before {best['before'] * 1e3:.1f} ms, after {best['after'] * 1e3:.1f} ms, bare walk "
              f"{best['bare walk'] * 1e3:.1f} ms; the gather at {rows[-1]['before_share_of_bare']:.0%} -> "
              f"{rows[-1]['after_share_of_bare']:.0%} of the bare walk; {'bitwise equal' if bitwise else 'DIFFERENT'}; "
              f"ray setup of {setup['setup_rays']} rays {setup['setup_before_seconds'] * 1e3:.1f} -> "
              f"{setup['setup_after_seconds'] * 1e3:.1f} ms, "
              f"{'bitwise equal' if setup['setup_bitwise'] else 'DIFFERENT'}",
              flush=True)
    write_results(args.out, {"settings": {"before": args.before, "rounds": args.rounds, "threads": args.threads},
                             "blender": bpy.app.version_string, "kernels": kernels.status().describe(), "rows": rows})
    return 0 if all(row["bitwise"] and row["setup_bitwise"] for row in rows) else 1


def ray_setup_ab(prepared, earlier_setup, tolerances, kernels, rounds: int) -> dict:
    """The first chunk of the trace's rays set up by the earlier kernel (with its two (n, 3)
    scratch arrays) and by the current one, on the same arguments as TraceRequest.rays makes
    them, each with fresh outputs as a trace allocates them: best seconds and whether the rays
    are the same bits."""
    request = prepared.trace_request()
    scene = prepared.ray_scene
    chunk = max(1, request.chunk_rays // max(len(request.directions), 1))
    direction_index, sample_index = np.nonzero((request.directions @ request.horizon_normals()[:chunk].T) > 0.0)
    footprint = (np.zeros((len(request.positions), 0, 3), np.float32) if request.footprint is None
                 else np.ascontiguousarray(request.footprint, np.float32))
    arguments = (np.ascontiguousarray(direction_index, np.int64), np.ascontiguousarray(sample_index, np.int64),
                 np.ascontiguousarray(request.positions, np.float64), footprint,
                 np.ascontiguousarray(request.geometric_normals, np.float64), request._frame_directions(),
                 request._frame_group(), scene.centre, np.float32(tolerances.RAY_OFFSET_INT_SCALE),
                 np.float32(tolerances.RAY_OFFSET_FLOAT_SCALE), np.float32(tolerances.RAY_OFFSET_ORIGIN))
    count = len(direction_index)
    current_setup = kernels.compiled().ray_setup

    def earlier():
        rays = np.empty((count, 3), np.float32), np.empty((count, 3), np.float32)
        kernels.run(earlier_setup, scene.threads, *arguments, *rays, np.empty((count, 3), np.int32),
                    np.empty((count, 3), np.float32))
        return rays

    def current():
        rays = np.empty((count, 3), np.float32), np.empty((count, 3), np.float32)
        kernels.run(current_setup, scene.threads, *arguments, *rays)
        return rays

    bitwise = all(np.array_equal(a.view(np.int32), b.view(np.int32)) for a, b in zip(earlier(), current()))
    best = {"before": np.inf, "after": np.inf}
    for _ in range(rounds):
        for label, call in (("before", earlier), ("after", current)):
            started = time.perf_counter()
            call()
            best[label] = min(best[label], time.perf_counter() - started)
    return {"setup_rays": count, "setup_before_seconds": round(best["before"], 4),
            "setup_after_seconds": round(best["after"], 4), "setup_bitwise": bool(bitwise)}


if __name__ == "__main__":
    sys.exit(main())
