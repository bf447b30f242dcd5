"""Scale-out (issue 20), first measurements: the demo's table traced and gathered by sample
rows on 1, 2 and 4 local Dask worker processes, against the same work in this process.

    export NUMBA_CACHE_DIR=/tmp/numba-cache
    .venv/bin/python benchmarks/scaleout.py [--workers 1,2,4] [--bounces 2]

The built-in demo room at VisiBake's default settings (128 directions, 256^2 atlases,
interleaved rotations, footprints) is extracted in bpy and written as a scene package
(core/distributed/package.py). Then, without Blender:

- in this process: prepare the samples, trace the table (``trace_table``), gather twice
  from made-up radiance (a bounce's worth each);
- per worker count W: a LocalCluster of W processes (1 Dask thread each, and cores / W
  threads for embree and the kernels, so the machine is never oversubscribed), ``RowWork``
  with 2 W row ranges: trace (prepares the samples on every worker, sends the package), then
  the same two gathers. Every table and gather is checked bit for bit against this process's.

Reported: seconds of each stage, the speed-up against this process, each worker's peak
resident memory (``ru_maxrss``) and this process's, the bytes a bounce moves (the atlas out
to every worker, the rows' irradiance back) against its compute. Writes
benchmarks/results/scaleout.json.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def write_demo_package(path: str) -> dict:
    """Extract the demo scene in bpy and package it; returns its settings."""
    import importlib

    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    def module(name):
        return importlib.import_module(f"{extension.__name__}.{name}")

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    settings = module("operators.adapter.settings").bake_settings(props)
    scene = module("operators.adapter.extraction").extract_scene(bpy.context, objects).scene
    module("core.distributed.package").write_package(path, scene, settings)
    return {"directions": settings.directions, "resolution": props.resolution, "interleave": settings.interleave,
            "footprint_samples": settings.footprint_samples}


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workers", default="1,2,4")
    parser.add_argument("--bounces", type=int, default=2)
    args = parser.parse_args(argv)
    from benchmarks.run import write_results

    folder = tempfile.mkdtemp(prefix="visibake-scaleout-")
    path = os.path.join(folder, "demo.vbpkg")
    settings = write_demo_package(path)
    package = open(path, "rb").read()

    # The repository's own core, as the workers import it (not the extension's copy).
    from core.distributed import engine
    from core.distributed.package import read_package
    from core.pipeline.prepare import prepare
    from core.transport.contract import GatherSource
    from core.transport.gather import gather
    from core.visibility.table import trace_table

    cores = os.cpu_count() or 1
    read = read_package(path)
    started = time.perf_counter()
    p = prepare(read.scene, read.settings, table_needed=False)
    prepare_s = time.perf_counter() - started
    started = time.perf_counter()
    p.table = trace_table(p.ray_scene, p.trace_request())
    trace_s = time.perf_counter() - started
    rng = np.random.default_rng(1)
    sources = [GatherSource(rng.uniform(0.0, 4.0, (p.layout.size, 3)).astype(np.float32),
                            rng.uniform(0.0, 1.0, (len(p.directions), 3))) for _ in range(args.bounces)]
    expected, gather_s = [], []
    geometry = p.gather_geometry()
    for source in sources:
        started = time.perf_counter()
        expected.append(gather(geometry, source))
        gather_s.append(time.perf_counter() - started)
    samples = len(p.position)
    atlas_bytes = sources[0].radiance.nbytes
    back_bytes = samples * 3 * 8
    in_process = {"prepare_s": round(prepare_s, 2), "trace_s": round(trace_s, 2),
                  "gather_s": [round(t, 3) for t in gather_s], "table_bytes": int(p.table.nbytes),
                  "peak_rss_mib": round(peak_rss_mib(), 1)}
    print(f"{samples} samples, {len(p.directions)} directions, table {p.table.nbytes / 2**20:.0f} MiB; in process: "
          f"prepare {prepare_s:.1f} s, trace {trace_s:.1f} s, gathers {', '.join(f'{t:.2f}' for t in gather_s)} s",
          flush=True)

    runs = []
    for count in (int(w) for w in args.workers.split(",")):
        threads = max(1, cores // count)
        started = time.perf_counter()
        with engine.cluster_client(workers=count) as client:
            client.wait_for_workers(count)
            startup_s = time.perf_counter() - started
            work = engine.RowWork(client, package, samples, parts=2 * count, threads=threads)
            started = time.perf_counter()
            table = work.trace()
            work_trace_s = time.perf_counter() - started
            same = all(np.array_equal(getattr(table, name), getattr(p.table, name))
                       for name in ("hit_object", "hit_uv_code", "hit_distance_code"))
            del table
            times = []
            for source, reference in zip(sources, expected):
                started = time.perf_counter()
                result = work.gather(source.radiance, source.world)
                times.append(time.perf_counter() - started)
                same = same and np.array_equal(result, reference)
            peaks = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
        run = {"workers": count, "threads_per_worker": threads, "parts": 2 * count, "startup_s": round(startup_s, 2),
               "trace_s": round(work_trace_s, 2), "gather_s": [round(t, 3) for t in times],
               "trace_speedup": round(trace_s / work_trace_s, 2),
               "gather_speedup": round(gather_s[-1] / times[-1], 2),
               "worker_peak_rss_mib": sorted(round(v, 1) for v in peaks.values()), "bit_identical": bool(same)}
        runs.append(run)
        print(f"W = {count}: start {startup_s:.1f} s, trace (with preparing and sending the package) "
              f"{work_trace_s:.1f} s, gathers {', '.join(f'{t:.2f}' for t in times)} s; worker peaks "
              f"{run['worker_peak_rss_mib']} MiB; bit-identical: {same}", flush=True)
    write_results(os.path.join(ROOT, "benchmarks", "results", "scaleout.json"),
                  {"settings": settings, "samples": samples, "package_bytes": len(package),
                   "bytes_per_bounce": {"atlas_out_per_worker": atlas_bytes, "irradiance_back_total": back_bytes},
                   "in_process": in_process, "clusters": runs, "cores": cores,
                   "load_average_end": os.getloadavg()[0]})
    os.remove(path)
    os.rmdir(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
