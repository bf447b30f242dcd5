"""A lights-only re-bake through the whole job, as an artist makes one: bake, change a lamp, bake again.

    .venv/bin/python benchmarks/rebake.py --scene atrium --directions 512 --resolution 96

On a scene of ``benchmarks/scenes.py`` (or ``demo``), through ``job.run_bake`` (what the Bake
button and the CLI run: layout, extraction, table, lighting, write-back), with the
visibility cache in a temporary folder:

1. cold: the first bake as the panel's Bake makes it: the table is traced and written to
   the cache, and the preparation kept in memory (within the preference Resident Memory);
2. Relight (the panel's button, same session): the sun turned 10 degrees about the vertical;
   the kept preparation is reused, with everything in it that does not depend on the lights;
3. Bake again (the panel's button, same session): the sun turned again; a Bake reads the
   table back from the cache file (which the OS still holds in its page cache) and checks the
   geometry again; it keeps its preparation, so it transports by the parts a Relight reuses;
4. Bake in a new session (the kept preparation forgotten), as the panel's button;
5. a command's bake in a new process (``visibake bake``: nothing kept, so no parts).

Each case runs twice (the second time with the sun turned once more): the first of a kind
may load kernels no earlier step used. Each re-bake's speed-up is the cold bake's time over
its own; each bake's peak resident memory is its own (reset before it, as ``make bench``
does). Writes JSON with the machine, settings and date (``--out``) and prints it.
"""
import argparse
import importlib
import json
import math
import os
import sys
import tempfile
import time
from datetime import datetime, timezone

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="atrium", help="a benchmarks/scenes.py scene, or demo")
    parser.add_argument("--directions", type=int, default=512)
    parser.add_argument("--resolution", type=int, default=96)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "rebake.json"))
    args = parser.parse_args(argv)

    from benchmarks import limits, scenes
    from benchmarks.run import machine
    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    module = lambda name: importlib.import_module(f"{extension.__name__}.{name}")  # noqa: E731
    job, resident = module("operators.adapter.job"), module("core.pipeline.resident")
    scenes.reset()
    if args.scene == "demo":
        objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
    else:
        objects = scenes.SCENES[args.scene]("full")
    props = bpy.context.scene.visibake
    props.passes = {"lighting"}
    if args.scene != "demo":
        props.mode = "atlas"  # as make bench bakes them; the demo keeps its own (its dome in vertex mode)
    props.directions, props.resolution, props.bounces = args.directions, args.resolution, args.bounces
    props.use_cache = True
    sun = next(o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.data.type == "SUN")
    results = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
               "blender": bpy.app.version_string, "scene": args.scene, "directions": args.directions,
               "resolution": args.resolution, "bounces": args.bounces, "changed": sun.name}

    def bake(label: str, **options) -> None:
        limits.reset_peak_memory()  # each bake's own peak, not the process's so far
        started = time.perf_counter()
        outcome = job.run_bake(bpy.context, objects, **options)
        seconds = time.perf_counter() - started
        report = outcome.report
        results.setdefault(label, []).append({
            "seconds": round(seconds, 3), "cache": (report.get("cache") or {}).get("state"),
            "stage_seconds": {k: round(v, 3) for k, v in report.get("stage_seconds", {}).items()},
            "peak_memory_bytes": limits.peak_memory_bytes() or report.get("peak_memory_bytes")})
        print(f"{label}: {seconds:.2f} s, cache {results[label][-1]['cache']}", flush=True)

    def turned(label: str, **options) -> None:
        for _ in range(2):
            sun.rotation_euler.z += math.radians(10.0)
            bake(label, **options)

    with tempfile.TemporaryDirectory(prefix="visibake-rebake-") as folder:
        props.cache_dir = folder
        try:
            bake("cold", keep_preparation=True)
            turned("relight_same_session", relight_only=True, keep_preparation=True)
            turned("bake_same_session", keep_preparation=True)
            resident.forget()
            turned("bake_new_session", keep_preparation=True)
            resident.forget()
            turned("command_bake")
        finally:
            resident.forget()
    cold = results["cold"][0]["seconds"]
    results["speedup"] = {label: [round(cold / run["seconds"], 2) for run in results[label]] for label in
                          ("relight_same_session", "bake_same_session", "bake_new_session", "command_bake")}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as stream:
        json.dump(results, stream, indent=1)
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
