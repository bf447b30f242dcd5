"""Bakes of benchmark scenes as ``make bench`` bakes them, timed stage by stage, for A/B runs of
two trees (issue 16, part 12): run it once per tree, alternating, and compare the medians.

    .venv/bin/python benchmarks/bake_ab.py [--root TREE] [--scenes many_objects dense_mesh]
        [--directions 32] [--repeats 5] [--out FILE.jsonl]

``--root`` is the tree whose extension is loaded (default: this one), so that an earlier commit
checked out in a second worktree runs with this script. Each scene is baked once to lay out its
UV maps (not timed, as in ``make bench``), then ``--repeats`` times at 64^2, 2 bounces, exact
shadows and ``--directions`` directions (the scene ``demo``: as ``visibake demo`` bakes it, at
``--preset``); prints (and appends to ``--out``) one JSON line a scene:
the median total and the median of each stage. With ``--direct-only``, each lamp's direct light
alone instead (core.transport.direct.lamp_irradiance on the scene's preparation; each small
emitter's, core.lights.emitters.emitter_irradiance, where samples integrate it directly), best of
``--repeats``, and the digest of its light (equal digests: bitwise the same light).
"""
import argparse
import json
import os
import statistics
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", default=ROOT, help="the tree whose extension is baked with")
    parser.add_argument("--scenes", nargs="+", default=["many_objects", "dense_mesh"])
    parser.add_argument("--directions", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=None, help="a JSON-lines file the rows are appended to")
    parser.add_argument("--direct-only", action="store_true", help="time each lamp's direct light alone")
    parser.add_argument("--preset", choices=("draft", "production"), help="the demo's preset (scene demo only)")
    args = parser.parse_args(argv)

    sys.path.insert(0, ROOT)
    import bpy

    from benchmarks import scenes
    from tools.visibake import loaded_extension

    _, module = loaded_extension(os.path.abspath(args.root))
    job = module("operators.adapter.job")
    with module("core.kernels").blas_on_one_thread():
        for name in args.scenes:
            scenes.reset()
            props = bpy.context.scene.visibake
            if name == "demo":  # as visibake demo bakes it
                objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
                props = bpy.context.scene.visibake
                if args.preset:
                    props.preset = args.preset.upper()
            else:
                objects = scenes.SCENES[name]("full")
                props.passes, props.mode = {"lighting"}, "atlas"
                props.resolution, props.bounces, props.shadows, props.rotate = 64, 2, "exact", False
                props.directions = args.directions
            props.use_cache = False
            if args.direct_only:
                # The UV maps laid out at the bake's resolution, by a bake that gathers little.
                kept = props.directions, props.bounces
                props.directions, props.bounces = 16, 0
                job.run_bake(bpy.context, objects)
                props.directions, props.bounces = kept
            else:
                job.run_bake(bpy.context, objects)  # lays out the UV maps, as make bench's first bake
            if args.direct_only:
                _write(args.out, {"tree": os.path.abspath(args.root), "scene": name, "directions": props.directions,
                                  "resolution": props.resolution,
                                  "lamps": _direct_light(module, bpy, objects, args.repeats)})
                continue
            reports = [job.run_bake(bpy.context, objects).report for _ in range(args.repeats)]
            stages = {stage: round(statistics.median(r["stage_seconds"][stage] for r in reports), 3)
                      for stage in reports[0]["stage_seconds"]}
            row = {"tree": os.path.abspath(args.root), "scene": name, "directions": props.directions,
                   "median_total": round(statistics.median(r["total_seconds"] for r in reports), 3),
                   "totals": [r["total_seconds"] for r in reports], "stages": stages,
                   "shadow_rays": reports[0]["rays"]["shadow_rays"]}
            _write(args.out, row)
    return 0


def _direct_light(module, bpy, objects, repeats: int) -> list[dict]:
    """Each lamp's direct light at the scene's samples, alone: best seconds of ``repeats``, the
    shadow rays, and a digest of the (K, 3) float64 light."""
    import hashlib
    import time

    extraction = module("operators.adapter.extraction")
    settings = module("operators.adapter.settings").bake_settings(bpy.context.scene.visibake)
    scene = extraction.extract_scene(bpy.context, objects).scene
    # Exact shadows trace their own rays: the table is only traced where shadow fractions need it.
    prepared = module("core.pipeline.prepare").prepare(scene, settings, table_needed=settings.shadows == "fractions")
    samples, shadowing = prepared.sample_set(), prepared.shadowing()
    unit_lamp, lamp_irradiance = module("core.lights.lamps").unit_lamp, module("core.transport.direct").lamp_irradiance
    lamps = []
    for light in scene.lights:
        best = float("inf")
        for _ in range(repeats):
            started = time.perf_counter()
            light_at, rays = lamp_irradiance(samples, shadowing, [unit_lamp(light)])
            best = min(best, time.perf_counter() - started)
        lamps.append({"lamp": light.name, "kind": light.kind, "best_seconds": round(best, 4), "shadow_rays": rays,
                      "light_digest": hashlib.sha256(light_at.tobytes()).hexdigest()[:16]})
    # Small emitters, at the samples that integrate them directly (core.pipeline.transport).
    emitters, p = module("core.lights.emitters"), prepared
    for emitter in emitters.find_emitters(p.meshes, settings.emitter_samples):
        chosen = emitters.sampled_directly(emitter, p.position, settings.directions).nonzero()[0]
        if not len(chosen):
            continue
        best = float("inf")
        for _ in range(repeats):
            started = time.perf_counter()
            light_at, rays = emitters.emitter_irradiance(emitter, p.position[chosen], p.normal[chosen],
                                                         p.geometric[chosen], p.origins[chosen], p.ray_scene)
            best = min(best, time.perf_counter() - started)
        lamps.append({"lamp": p.meshes[emitter.object_index].name, "kind": "EMITTER", "samples": len(chosen),
                      "best_seconds": round(best, 4), "shadow_rays": rays,
                      "light_digest": hashlib.sha256(light_at.tobytes()).hexdigest()[:16]})
    return lamps


def _write(path: str | None, row: dict) -> None:
    print(json.dumps(row), flush=True)
    if path:
        with open(path, "a") as out:
            out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    sys.exit(main())
