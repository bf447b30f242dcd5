"""The visibility trace alone, timed on a real bake's request, split into its parts.

    .venv/bin/python benchmarks/trace_timing.py [--scene demo|sun_occluders|...] [--repeats 3]
        [--chunk-rays N] [--scratch DIR] [--out benchmarks/results/trace_timing.json]

Prepares the scene as ``make bench`` bakes its N = 256 row (64^2, exact shadows), or the demo
as ``visibake demo`` bakes it (128 directions), then traces its table ``--repeats`` times in the
same process. Each trace is split into what embree does (``RayScene.intersect_local``), the
ray set-up, the record into the table, the finish (the table's counters) and the rest (from
part 8 also the entry bits, "horizon bits", and each chunk's list of rays, "ray list"). From
part 11 the ray list, the set-up, embree and the record run together, span by span on each
thread: "span trace" is their sum, and the bake's BLAS is held to one thread here as in a bake. The
table's digest is printed, so that two checkouts can be compared: run the script in each
(``git worktree add``), alternately, as docs/benchmarks.md's speed part 7 did; both must
print the same digest. ``--scratch DIR`` traces into a scratch file there, as a bake with a
cache folder does (core.visibility.scratch; from speed part 10), instead of into memory.
"""
import argparse
import collections
import contextlib
import dataclasses
import hashlib
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--chunk-rays", type=int, default=0, help="rays per chunk (default: the bake's setting)")
    parser.add_argument("--scratch", default=None, help="trace into a scratch file in this folder")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "trace_timing.json"))
    args = parser.parse_args(argv)

    from benchmarks import scenes
    from benchmarks.run import write_results
    from tools.visibake import loaded_extension

    extension, module = loaded_extension()
    import bpy

    table_module, rays_module = module("core.visibility.table"), module("core.visibility.rays")
    prepared = scenes.prepared_bake(module, args.scene)
    request, ray_scene = prepared.trace_request(), prepared.ray_scene
    if args.chunk_rays > 0:
        request = dataclasses.replace(request, chunk_rays=args.chunk_rays)
    if args.scratch:
        request = dataclasses.replace(request, scratch_folder=args.scratch)

    seconds = collections.defaultdict(float)

    def timed(owner, name, label):
        function = getattr(owner, name)

        def wrapper(*arguments, **keywords):
            started = time.perf_counter()
            try:
                return function(*arguments, **keywords)
            finally:
                seconds[label] += time.perf_counter() - started
        setattr(owner, name, wrapper)

    timed(rays_module.RayScene, "intersect_local", "embree")
    timed(table_module.TraceRequest, "rays", "ray set-up")
    timed(table_module, "_record", "record")
    timed(table_module, "_finish", "finish")  # the table's counters, backfaces among them
    if hasattr(table_module, "SpanTracer"):  # since part 11: list, set-up, embree, record per span, on each thread
        timed(table_module.SpanTracer, "trace_samples", "span trace")
    if hasattr(table_module, "rays_of_entries"):  # since part 8: the entry bits first, then each chunk's rays
        timed(table_module, "above_horizon", "horizon bits")
        timed(table_module, "rays_of_entries", "ray list")
    kernels = module("core.kernels")
    # As a bake runs it (from speed part 11): numpy's BLAS on one thread, its idle threads not spinning.
    blas = kernels.blas_on_one_thread() if hasattr(kernels, "blas_on_one_thread") else contextlib.nullcontext()
    with blas:
        runs, digest = _timed_traces(args, table_module, ray_scene, request, seconds)
    print(f"table digest {digest}")
    write_results(args.out, {"scene": args.scene, "chunk_rays": request.chunk_rays, "scratch": bool(args.scratch),
                             "rays": int(prepared.table.rays_cast), "digest": digest,
                             "blender": bpy.app.version_string, "runs": runs})
    return 0


def _timed_traces(args, table_module, ray_scene, request, seconds):
    """``args.repeats`` traces of ``request``, each printed; returns their timings and the table's digest."""
    runs, digest = [], None
    for _ in range(args.repeats):
        seconds.clear()
        started = time.perf_counter()
        table = table_module.trace_table(ray_scene, request)
        total = time.perf_counter() - started
        runs.append({"seconds": round(total, 4), **{k: round(v, 4) for k, v in seconds.items()},
                     "rest": round(total - sum(seconds.values()), 4)})
        if digest is None:
            hashed = hashlib.blake2b(digest_size=8)
            for array in (table.hit_object, table.hit_uv_code, table.hit_distance_code):
                hashed.update(np.ascontiguousarray(array).data)
            digest = hashed.hexdigest()
        print(f"{args.scene}: {table.rays_cast} rays in {total:.3f} s ({table.rays_cast / total / 1e6:.2f} M rays/s); "
              + ", ".join(f"{k} {v:.3f} s" for k, v in runs[-1].items() if k != "seconds"), flush=True)
        del table
    return runs, digest


if __name__ == "__main__":
    sys.exit(main())
