"""The surface gather kernel before and after a change (issue 16's parts 6 and 8), on the tables of real bakes,
against the bare table walk it is measured by: all three in one process, interleaved, best
of ``--rounds`` (this VM's speed drifts within minutes, so separate runs do not compare).

The earlier kernel is taken from git at ``--before`` (default c285482, the last commit with
part 6's earlier kernel). An earlier kernel that reads the dense (directions, samples) table
(before part 8) is given the same table's dense arrays. Both must give the same bits; the
script exits 1 otherwise.

    .venv/bin/python benchmarks/gather_ab.py [--before SHA] [--scenes demo sun_occluders ...]
        [--rounds 15] [--threads 2] [--out docs/speed/part6/gather_ab.json]

The demo is baked as ``visibake demo`` bakes it (128 directions); a benchmark scene at 64^2,
256 directions and exact shadows, as ``make bench`` bakes its N = 256 row.
"""
import argparse
import inspect
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
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "gather_ab.json"))
    args = parser.parse_args(argv)

    from benchmarks import limits, scenes
    from benchmarks.earlier import earlier_module
    from benchmarks.run import write_results
    from tools.visibake import loaded_extension

    _, module = loaded_extension()
    import bpy

    kernels = module("core.kernels")
    current = kernels.compiled()
    if current is None:
        print(f"compiled kernels unavailable ({kernels.status().reason}): nothing to compare", file=sys.stderr)
        return 2
    earlier = earlier_module(args.before, "core/kernels/transport_kernels.py", "earlier_transport_kernels")
    gather = module("core.transport.gather")
    cpu_backend = module("core.transport.cpu").CPU_BACKEND
    GatherSource = module("core.transport.contract").GatherSource
    rows = []
    for name in args.scenes:
        prepared = scenes.prepared_bake(module, name)
        geometry = prepared.gather_geometry()
        # The scene's albedo lit uniformly: any atlas will do, a gather's cost does not depend on it.
        source = GatherSource(prepared.to_atlas(prepared.albedo, cpu_backend.dilate), np.zeros(3))
        chosen = np.arange(len(geometry.normals), dtype=np.int64)
        before, after = gather.gather_kernel_arguments(geometry, source, chosen)
        directions = len(prepared.table.directions)
        outputs = {}

        earlier_before = before
        if inspect.signature(earlier.gather.py_func).parameters.keys().__iter__().__next__() == "hit_object":
            # Before part 8 the gather read the dense table: the same entries, every direction of every sample.
            entries = prepared.table.entries
            earlier_before = (entries.dense("hit_object"), entries.dense("hit_uv_code"), *before[4:])

        def kernel_call(kernel, label, arguments=before):
            def call():
                after[-1][:] = 0
                kernels.run(kernel, geometry.threads if not args.threads else args.threads, *arguments, 0,
                            directions, *after)
                outputs[label] = after[-1].copy()
            return call

        calls = {"before": kernel_call(earlier.gather, "before", earlier_before),
                 "after": kernel_call(current.gather, "after"),
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
        rows.append({"scene": name, "samples": int(len(chosen)), "directions": directions,
                     "entries_above_horizon": int(prepared.table.rays_cast),
                     "before_seconds": round(best["before"], 4), "after_seconds": round(best["after"], 4),
                     "bare_walk_seconds": round(best["bare walk"], 4),
                     "before_share_of_bare": round(best["bare walk"] / best["before"], 3),
                     "after_share_of_bare": round(best["bare walk"] / best["after"], 3),
                     "speedup": round(best["before"] / best["after"], 3), "bitwise": bitwise})
        print(f"{name}: before {best['before'] * 1e3:.1f} ms, after {best['after'] * 1e3:.1f} ms, bare walk "
              f"{best['bare walk'] * 1e3:.1f} ms; the gather at {rows[-1]['before_share_of_bare']:.0%} -> "
              f"{rows[-1]['after_share_of_bare']:.0%} of the bare walk; {'bitwise equal' if bitwise else 'DIFFERENT'}",
              flush=True)
    write_results(args.out, {"settings": {"before": args.before, "rounds": args.rounds, "threads": args.threads},
                             "blender": bpy.app.version_string, "kernels": kernels.status().describe(), "rows": rows})
    return 0 if all(row["bitwise"] for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
