"""The visibility cache on the demo room: what a cold bake, a cache hit, a relight and
a moved object cost, and whether an incrementally updated table equals a fresh one.

    .venv/bin/python benchmarks/cache_update.py [--directions 128] [--resolution 256] [--move Torus]

Runs the core pipeline on the extracted demo scene (the operators' path without the
image write-back), each step timed on its own:

1. cold: no cache; the table is traced and written (``miss``)
2. warm: same scene; the table is read back (``hit``)
3. relight: the lamp's power doubled; transport only, from the warm preparation
3b. resident relight: the Relight button's path in a running session (core.pipeline.resident):
   the preparation kept in memory by the bake is reused, then the same relight; split into
   direct light (lamps, exact shadows over the footprints) and the gathers (table lookups).
   Only the point lamp's power changes, so its direct light is scaled from the memo
   (core.pipeline.light_memo); 3c moves the lamp instead, so its direct light is computed again
4. moved: one object moved; the table is updated (``updated``), compared entry by
   entry with a fresh trace of the moved scene, and timed against that trace.

Writes ``benchmarks/results/cache_update.json`` with the machine, settings and date.
"""
import argparse
import dataclasses
import importlib
import json
import os
import sys
import tempfile
import time
from datetime import datetime, timezone

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--directions", type=int, default=128)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--move", default="Torus", help="the demo object to move for the update case")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "cache_update.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import machine
    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    demo_scene = importlib.import_module(f"{extension.__name__}.operators.adapter.demo_scene")
    extraction = importlib.import_module(f"{extension.__name__}.operators.adapter.extraction")
    adapter_settings = importlib.import_module(f"{extension.__name__}.operators.adapter.settings")
    pipeline = importlib.import_module(f"{extension.__name__}.core.pipeline.relight")
    resident = importlib.import_module(f"{extension.__name__}.core.pipeline.resident")
    VisibilityCache = importlib.import_module(f"{extension.__name__}.core.visibility.cache").VisibilityCache

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = demo_scene.build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = args.directions, args.resolution, args.bounces
    props.passes = {"lighting"}
    settings = adapter_settings.bake_settings(props)
    extracted = extraction.extract_scene(bpy.context, objects)
    scene = extracted.scene
    results = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
               "blender": bpy.app.version_string, "settings": dataclasses.asdict(settings), "moved": args.move}

    def timed(function):
        started = time.perf_counter()
        value = function()
        return value, time.perf_counter() - started

    with tempfile.TemporaryDirectory(prefix="visibake-cache-bench-") as folder:
        cache = VisibilityCache(folder, "demo")
        cold, seconds = timed(lambda: pipeline.prepare(scene, settings, table_needed=True, cache=cache))
        results["cold"] = {"seconds": seconds, "state": cold.cache_status.state,
                           "visibility_seconds": cold.stage_seconds.get("visibility", 0.0),
                           "save_seconds": cold.cache_status.save_seconds,
                           "bytes": cold.cache_status.bytes_on_disk, "rays": cold.visibility_rays}
        del cold
        warm, seconds = timed(lambda: pipeline.prepare(scene, settings, table_needed=True, cache=cache))
        results["warm"] = {"seconds": seconds, "state": warm.cache_status.state,
                           "load_seconds": warm.cache_status.load_seconds}
        lights = [dataclasses.replace(light, strength=light.strength * 2) if light.kind == "POINT" else light
                  for light in scene.lights]
        warm.cache = None  # time the transport, not the lighting cache
        _, seconds = timed(lambda prepared=warm: pipeline.relight(prepared, lights, scene.world))
        results["relight_seconds"] = seconds
        del warm

        kept, seconds = timed(lambda: resident.prepare_or_reuse(scene, settings, table_needed=True, cache=cache,
                                                                keep_bytes=1 << 34, reuse=False))
        reused, reuse_seconds = timed(lambda: resident.prepare_or_reuse(scene, settings, table_needed=True,
                                                                        cache=cache, keep_bytes=1 << 34))
        assert reused is kept and reused.cache_status.state == "resident", reused.cache_status
        reused.cache = None
        # The first relight of a preparation reads a cached table and finds what depends on geometry
        # alone (short and near hits, exposed shares, filter pairs); every later one reuses them.
        _, first_seconds = timed(lambda prepared=reused: pipeline.relight(prepared, lights, scene.world))
        again = [dataclasses.replace(light, strength=light.strength * 0.5) if light.kind == "POINT" else light
                 for light in lights]
        reused, reuse_seconds = timed(lambda: resident.prepare_or_reuse(scene, settings, table_needed=True,
                                                                        cache=cache, keep_bytes=1 << 34))
        reused.cache = None
        outcome, relight_seconds = timed(lambda prepared=reused: pipeline.relight(prepared, again, scene.world))
        passes = outcome.report["passes"]
        results["resident_relight"] = {
            "bake_seconds": seconds, "first_relight_seconds": first_seconds, "reuse_seconds": reuse_seconds,
            "relight_seconds": relight_seconds, "total_seconds": reuse_seconds + relight_seconds,
            "kept_bytes": resident.prepared_bytes(kept),
            "shadow_rays": outcome.report["rays"]["shadow_rays"],
            "passes": passes,
            "direct_seconds": sum(p["seconds"] for p in passes if p["pass"].startswith("direct light")),
            "gather_seconds": sum(p["seconds"] for p in passes if p["pass"].startswith("gather")),
            "stage_seconds": outcome.report["stage_seconds"]}
        # A moved lamp: its direct light is computed again, the other lamps' is scaled from the memo.
        moved_lamp = [dataclasses.replace(light, position=np.asarray(light.position) + np.array([0.1, 0.0, 0.0]))
                      if light.kind == "POINT" else light for light in again]
        outcome, moved_seconds = timed(lambda prepared=reused: pipeline.relight(prepared, moved_lamp, scene.world))
        passes = outcome.report["passes"]
        results["resident_relight_moved_lamp"] = {
            "relight_seconds": moved_seconds,
            "shadow_rays": outcome.report["rays"]["shadow_rays"],
            "passes": passes,
            "direct_seconds": sum(p["seconds"] for p in passes if p["pass"].startswith("direct light")),
            "gather_seconds": sum(p["seconds"] for p in passes if p["pass"].startswith("gather")),
            "stage_seconds": outcome.report["stage_seconds"]}
        del kept, reused, outcome
        resident.forget()

        moved = next(o for o in objects if o.name == args.move)
        moved.location.x += 0.15
        bpy.context.view_layer.update()
        scene_moved = extraction.extract_scene(bpy.context, objects).scene
        updated, seconds = timed(lambda: pipeline.prepare(scene_moved, settings, table_needed=True, cache=cache))
        results["update"] = {"seconds": seconds, "state": updated.cache_status.state,
                             "visibility_seconds": updated.stage_seconds.get("visibility", 0.0),
                             "rays": updated.visibility_rays, "changed": updated.cache_status.changed_objects}
        fresh, seconds = timed(lambda: pipeline.prepare(scene_moved, settings, table_needed=True))
        results["fresh_trace_of_moved_scene"] = {"seconds": seconds, "rays": fresh.visibility_rays,
                                                 "visibility_seconds": fresh.stage_seconds.get("visibility", 0.0)}
        a, b = updated.table, fresh.table
        differing = int(np.count_nonzero((a.hit_object != b.hit_object)
                                         | (a.hit_distance_code != b.hit_distance_code)
                                         | np.any(a.hit_uv_code != b.hit_uv_code, axis=-1)))
        results["entries"] = int(a.hit_object.size)
        results["entries_differing_from_fresh_trace"] = differing
    results["update_speedup"] = (results["fresh_trace_of_moved_scene"]["visibility_seconds"]
                                 / max(results["update"]["visibility_seconds"], 1e-9))
    results["ray_ratio"] = results["update"]["rays"] / max(results["fresh_trace_of_moved_scene"]["rays"], 1)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as handle:
        json.dump(results, handle, indent=2, default=float)
    print(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
