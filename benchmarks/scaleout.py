"""Scale-out (issue 20): the demo baked whole on 1, 2 and 4 local Dask worker processes
(the table traced and read by sample rows where each range is kept), against the same bake
in this process; and a BRDF run in parts.

    export NUMBA_CACHE_DIR=/tmp/numba-cache
    .venv/bin/python benchmarks/scaleout.py [--workers 1,2,4] [--brdf-lights 256]

The built-in demo room at VisiBake's default settings (128 directions, 256^2 atlases,
interleaved rotations, footprints, 2 bounces) is extracted in bpy and written as a scene
package (core/distributed/package.py). Then, without Blender, with the kernels loaded first:

- in this process: ``bake(scene, settings)``, and the same with the table held by 2 row
  ranges in this process (``InProcessRows``: the split's own overhead, no cluster);
- per worker count W: a local cluster of W ``dask worker`` processes (1 Dask thread each,
  and cores / W threads for embree and the kernels, so the machine is never
  oversubscribed), and ``bake(..., split=ClusterRows(client, package, 2 W))``. Every image is
  checked bit for bit against the one-process bake's;
- a V-groove BRDF (Lambert, 64 directions, 3 bounces, L lights x 32 views) whole and in
  2 W parts on the same clusters, checked bit for bit.

Reported: seconds (cluster start apart), the speed-up against this process, how much of a
cluster bake this process spent on its own (waiting on no range: the serial share), each worker's
peak resident memory (``ru_maxrss``) and this process's, and the bytes a bounce moves (the
atlas out to every worker, the rows' irradiance back). Writes benchmarks/results/scaleout.json.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from dataclasses import replace

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def write_demo_package(path: str) -> dict:
    """Extract the demo scene in bpy and package it; returns its settings."""

    from tools.visibake import loaded_extension

    _, module = loaded_extension()
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    settings = module("operators.adapter.settings").bake_settings(props)
    scene = module("operators.adapter.extraction").extract_scene(bpy.context, objects).scene
    module("core.distributed.package").write_package(path, scene, settings)
    return {"directions": settings.directions, "resolution": props.resolution, "interleave": settings.interleave,
            "footprint_samples": settings.footprint_samples}


def _time_calls(rows) -> list:
    """Wrap ``rows.run`` (every call the bake makes on its ranges) to add its seconds to the
    returned one-element list."""
    spent = [0.0]
    run = rows.run

    def timed(*arguments, **options):
        started = time.perf_counter()
        try:
            return run(*arguments, **options)
        finally:
            spent[0] += time.perf_counter() - started

    rows.run = timed
    return spent


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workers", default="1,2,4")
    parser.add_argument("--brdf-lights", type=int, default=256)
    args = parser.parse_args(argv)
    from benchmarks.run import write_results

    folder = tempfile.mkdtemp(prefix="visibake-scaleout-")
    path = os.path.join(folder, "demo.vbpkg")
    settings = write_demo_package(path)
    package = open(path, "rb").read()

    # The repository's own core, as the workers import it (not the extension's copy).
    from benchmarks import brdf_tiles
    from core import kernels
    from core.appearance import gonio
    from core.appearance.tile import Tile
    from core.distributed import engine
    from core.distributed.package import read_package
    from core.distributed.split import InProcessRows
    from core.pipeline.relight import bake
    from core.version import visibake_version

    cores = os.cpu_count() or 1
    kernels.status()
    read = read_package(path)
    scene, bake_settings = read.scene, read.settings

    def images(result):
        return [image for o in result.objects for _, image in sorted(o.images.items())]

    def timed_bake(split=None):
        started = time.perf_counter()
        result = bake(scene, bake_settings, split=split)
        return result, time.perf_counter() - started

    whole, whole_s = timed_bake()
    reference = images(whole)
    stages = {k: round(v, 2) for k, v in whole.report["stage_seconds"].items()}
    in_rows, in_rows_s = timed_bake(InProcessRows(2))
    same_in_rows = all(np.array_equal(a, b) for a, b in zip(images(in_rows), reference))
    samples = sum(o["texels"] for o in whole.report["objects"])
    table_bytes = whole.report["table_bytes"]
    # The radiance atlas a bounce sends every worker: each object's texels, 3 float32 channels.
    atlas_bytes = sum(int(np.prod(o["resolution"])) for o in whole.report["objects"]) * 3 * 4
    in_process = {"bake_s": round(whole_s, 2), "stage_seconds": stages, "split_in_process_s": round(in_rows_s, 2),
                  "split_in_process_bit_identical": bool(same_in_rows), "table_bytes": int(table_bytes),
                  "peak_rss_mib": round(peak_rss_mib(), 1)}
    print(f"{samples} samples, {bake_settings.directions} directions, table {table_bytes / 2**20:.0f} MiB; in "
          f"process: bake {whole_s:.1f} s ({stages}); by 2 row ranges in process {in_rows_s:.1f} s "
          f"(bit-identical: {same_in_rows})", flush=True)

    tile = Tile.of(*brdf_tiles.v_groove_tile(0.5), albedo=0.7)
    lights, views = gonio.hemisphere_directions(args.brdf_lights), gonio.hemisphere_directions(32)
    brdf_settings = gonio.GonioSettings(directions=64, bounces=3, resolution=32, view_rays=64, seed=1)
    started = time.perf_counter()
    brdf_whole = gonio.simulate_brdf(tile, lights, views, brdf_settings)
    brdf_s = time.perf_counter() - started
    print(f"BRDF {args.brdf_lights} x 32 in process: {brdf_s:.1f} s", flush=True)

    runs = []
    for count in (int(w) for w in args.workers.split(",")):
        threads = max(1, cores // count)
        started = time.perf_counter()
        with engine.cluster_client(workers=count) as client:
            startup_s = time.perf_counter() - started
            rows = engine.ClusterRows(client, package, parts=2 * count, threads=threads)
            waited = _time_calls(rows)
            split, split_s = timed_bake(rows)
            same = all(np.array_equal(a, b) for a, b in zip(images(split), reference))
            peaks = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
            parts_settings = replace(brdf_settings, threads=threads)
            arguments = [(visibake_version(), tile, lights, views, parts_settings, index, 2 * count)
                         for index in range(2 * count)]
            started = time.perf_counter()
            joined = gonio.join_brdf_parts(engine.run_parts(client, "brdf_part", arguments))
            brdf_split_s = time.perf_counter() - started
            brdf_same = bool(np.array_equal(joined.values, brdf_whole.values))
        run = {"workers": count, "threads_per_worker": threads, "parts": 2 * count, "startup_s": round(startup_s, 2),
               "bake_s": round(split_s, 2),
               "stage_seconds": {k: round(v, 2) for k, v in split.report["stage_seconds"].items()},
               "speedup": round(whole_s / split_s, 2), "bit_identical": bool(same),
               # What this process did itself while no range task ran: the bake's serial share.
               "driver_only_s": round(split_s - waited[0], 2), "waiting_on_ranges_s": round(waited[0], 2),
               "table_bytes_on_workers": split.report["split"]["table_bytes_held_by_ranges"],
               "worker_peak_rss_mib": sorted(round(v, 1) for v in peaks.values()),
               "brdf_s": round(brdf_split_s, 2), "brdf_speedup": round(brdf_s / brdf_split_s, 2),
               "brdf_bit_identical": brdf_same}
        runs.append(run)
        print(f"W = {count}: start {startup_s:.1f} s, bake {split_s:.1f} s ({run['stage_seconds']}; this process "
              f"alone {run['driver_only_s']} s, waiting on ranges {run['waiting_on_ranges_s']} s), speed-up "
              f"{run['speedup']}x, bit-identical: {same}; worker peaks {run['worker_peak_rss_mib']} MiB; BRDF "
              f"{brdf_split_s:.1f} s ({run['brdf_speedup']}x), bit-identical: {brdf_same}", flush=True)
    write_results(os.path.join(ROOT, "benchmarks", "results", "scaleout.json"),
                  {"settings": settings, "samples": samples, "package_bytes": len(package),
                   "bytes_per_bounce": {"atlas_out_per_worker": atlas_bytes, "irradiance_back_total": samples * 24},
                   "in_process": in_process, "brdf": {"lights": args.brdf_lights, "views": 32, "whole_s":
                                                      round(brdf_s, 2)},
                   "clusters": runs, "cores": cores, "load_average_end": os.getloadavg()[0],
                   "peak_rss_mib_end": round(peak_rss_mib(), 1)})
    os.remove(path)
    os.rmdir(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
