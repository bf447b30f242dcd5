"""Direct light of each demo lamp, alone: core.transport.direct.lamp_irradiance over the
demo's samples (exact shadows, the footprints), timed per lamp, the first call and the
later ones.

For an A/B comparison of two commits on a machine whose speed drifts, run this script from
two checkouts one after the other, twice each (``git worktree add /tmp/before <commit>``,
copy this script into it if it predates it, then ``.venv/bin/python
/tmp/before/benchmarks/direct_light.py``): each checkout loads its own extension.

Writes ``benchmarks/results/direct_light.json`` with the machine, settings and date.
"""
import argparse
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--directions", type=int, default=128)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=2, help="calls per lamp; the first may load kernels")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "direct_light.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import write_results
    from tools.visibake import loaded_extension

    _, module = loaded_extension()
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = module("operators.adapter.demo_scene").build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    props.directions, props.resolution = args.directions, args.resolution
    props.passes = {"lighting"}
    settings = module("operators.adapter.settings").bake_settings(props)
    scene = module("operators.adapter.extraction").extract_scene(bpy.context, objects).scene
    prepared = module("core.pipeline.prepare").prepare(scene, settings, table_needed=False)
    samples, shadowing = prepared.sample_set(), prepared.shadowing()
    lamp_irradiance = module("core.transport.direct").lamp_irradiance
    lamps = {}
    for light in scene.lights:
        seconds, rays = [], 0
        for _ in range(max(1, args.repeats)):
            started = time.perf_counter()
            _, rays = lamp_irradiance(samples, shadowing, [light])
            seconds.append(round(time.perf_counter() - started, 4))
        lamps[light.name] = {"kind": light.kind, "seconds": seconds, "shadow_rays": int(rays)}
        print(f"{light.name} ({light.kind}): {', '.join(f'{s:.2f} s' for s in seconds)}, {rays} shadow rays")
    write_results(args.out, {"settings": {"directions": args.directions, "resolution": args.resolution,
                                          "shadows": settings.shadows, "footprint_samples": settings.footprint_samples},
                             "samples": len(samples.position), "kernels": module("core.kernels").status().describe(),
                             "lamps": lamps})
    return 0


if __name__ == "__main__":
    sys.exit(main())
