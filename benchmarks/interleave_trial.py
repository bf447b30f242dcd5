"""The interleaved rotations' tile and the filter's window, judged per texel and on 4x4-texel
block means (issue 16, speed part 16).

    .venv/bin/python benchmarks/interleave_trial.py [--scenes interior_opening closed_room_point]
        [--tiles 3 4 5] [--directions 32 128] [--window 3|tile] [--out FILE.jsonl]

Each scene of ``benchmarks/scenes.py`` is baked as ``make bench`` bakes it (64^2, 2 bounces,
exact shadows) at every tile (the Interleaved Rotations setting) and direction count, and
compared with the quick profile's cached 1024-spp Cycles reference (``benchmarks/cache``; it is
baked first where missing): relative RMSE per texel and of the block means, with the
reference's own noise on both. ``--window tile`` filters over the whole tile, as before part 16
(core.transport.interleave.FILTER_WINDOW raised past the tile); ``3`` is the default. Prints
(and appends to ``--out``) one JSON line a bake. Times are the bakes' own and meaningful only
on an otherwise idle machine.
"""
import argparse
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["interior_opening", "closed_room_point", "many_objects"])
    parser.add_argument("--tiles", type=int, nargs="+", default=[3, 4, 5])
    parser.add_argument("--directions", type=int, nargs="+", default=[32, 128])
    parser.add_argument("--window", choices=("3", "tile"), default="3")
    parser.add_argument("--out", default=None, help="a JSON-lines file the rows are appended to")
    args = parser.parse_args(argv)

    sys.path.insert(0, ROOT)
    import bpy

    from benchmarks import reference, scenes
    from tools.visibake import loaded_extension

    _, module = loaded_extension(ROOT)
    job = module("operators.adapter.job")
    if args.window == "tile":
        module("core.transport.interleave").FILTER_WINDOW = 1 << 10
    with module("core.kernels").blas_on_one_thread():
        for name in args.scenes:
            scenes.reset()
            objects = scenes.SCENES[name]("full")
            props = bpy.context.scene.visibake
            props.passes, props.mode, props.use_cache = {"lighting"}, "atlas", False
            props.resolution, props.bounces, props.shadows, props.rotate = 64, 2, "exact", False
            props.directions = 128
            first = job.run_bake(bpy.context, objects)  # lays out the UV maps, as make bench's first bake
            uv_maps = {o["name"]: o["uv_map"] for o in first.report["objects"] if o["output"]}
            ref = reference.cached_reference(objects, uv_maps, 64, 2, 1024, os.path.join(ROOT, "benchmarks", "cache"))
            for tile in args.tiles:
                props.interleave = tile
                for directions in args.directions:
                    props.directions = directions
                    outcome = job.run_bake(bpy.context, objects)
                    images = {r.name: r.images["lighting"] for r in outcome.result.objects}
                    texel = reference.relative_errors(images, ref.images)
                    blocks = reference.block_errors(images, ref)
                    row = {"scene": name, "interleave": tile, "window": args.window, "N": directions,
                           "seconds": outcome.report["total_seconds"], "texel": round(texel["relative_rmse"], 5),
                           "block": round(blocks["block_rmse"], 5), "texel_noise": round(blocks["texel_noise"], 5),
                           "block_noise": round(blocks["block_noise"], 5)}
                    print(json.dumps(row), flush=True)
                    if args.out:
                        with open(args.out, "a") as handle:
                            handle.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
