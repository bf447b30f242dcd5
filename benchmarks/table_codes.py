"""What a change of the table's storage costs in accuracy: the same bakes from two source trees.

    git worktree add /tmp/before 5f1f02e     # float32 coordinates and distances (cache format 5)
    .venv/bin/python benchmarks/table_codes.py --before /tmp/before     # ~5 min on 2 cores

Bakes every scene of ``benchmarks/scenes.py`` (64², 256 directions, 2 bounces, exact
shadows, the default techniques, one seed) once with the extension of the ``--before``
tree and once with this tree's, each in its own Blender process, and reports per scene
the relative RMS difference of the lighting over covered texels, and the largest texel
difference relative to the scene's mean. Everything but the tree is the same, so the
difference is what the change did (for the compact table: quantising the landing
coordinates to 16 bits and the distances to 16-bit logarithmic codes). Writes
``<out>/table_codes.json``.
"""
import argparse
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def bake_all(tree: str, out: str, resolution: int, directions: int, bounces: int, size: str) -> None:
    """Bake every benchmark scene with the extension in ``tree``; save the lighting to ``out`` (.npz)."""
    from tools.visibake import load_extension

    load_extension(tree)
    import bpy

    from benchmarks import scenes

    job = sys.modules["visibake.operators.adapter.job"]
    arrays = {}
    for name in scenes.SCENE_NAMES:
        scenes.reset()
        objects = scenes.SCENES[name](size)
        props = bpy.context.scene.visibake
        props.passes = {"lighting"}
        props.use_cache, props.mode = False, "atlas"
        props.resolution, props.bounces, props.shadows, props.rotate = resolution, bounces, "exact", False
        props.directions = directions
        outcome = job.run_bake(bpy.context, objects)
        for result in outcome.result.objects:
            arrays[f"{name}/{result.name}"] = np.asarray(result.images["lighting"], np.float32)
        print(f"{tree}: {name} baked", flush=True)
    np.savez(out, **arrays)


def compare(before: dict, after: dict) -> dict:
    """Per scene: relative RMS and largest difference of the lighting on covered texels.

    before, after : {"scene/object": (H, W, 4) float32 RGB + coverage alpha}
    """
    scenes = sorted({key.split("/")[0] for key in after})
    result = {}
    for scene in scenes:
        a, b = [], []
        for key in after:
            if key.startswith(scene + "/"):
                covered = after[key][..., 3] > 0
                a.append(before[key][covered][:, :3].ravel())
                b.append(after[key][covered][:, :3].ravel())
        a, b = np.concatenate(a).astype(np.float64), np.concatenate(b).astype(np.float64)
        scale = np.sqrt(np.mean(a * a))
        result[scene] = {"relative_rms_difference": float(np.sqrt(np.mean((b - a) ** 2)) / scale),
                         "max_difference_over_mean": float(np.max(np.abs(b - a)) / np.mean(np.abs(a))),
                         "texels": int(len(a) // 3)}
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="a checkout of the earlier tree (git worktree add DIR COMMIT)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--directions", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--size", choices=["smoke", "full"], default="full")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "table_codes"))
    parser.add_argument("--bake", nargs=2, metavar=("TREE", "NPZ"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.bake:
        bake_all(os.path.abspath(args.bake[0]), args.bake[1], args.resolution, args.directions, args.bounces,
                 args.size)
        return 0
    if not args.before:
        parser.error("--before DIR is required")
    from benchmarks.run import write_results

    saved = {}
    with tempfile.TemporaryDirectory() as folder:
        for side, tree in (("before", args.before), ("after", ROOT)):
            path = os.path.join(folder, f"{side}.npz")
            subprocess.run([sys.executable, os.path.abspath(__file__), "--bake", tree, path,
                            "--resolution", str(args.resolution), "--directions", str(args.directions),
                            "--bounces", str(args.bounces), "--size", args.size], check=True)
            with np.load(path) as data:
                saved[side] = {key: data[key] for key in data.files}
    result = compare(saved["before"], saved["after"])
    for scene, entry in result.items():
        print(f"{scene:>20}: relative RMS difference {entry['relative_rms_difference']:.2e}, "
              f"largest {entry['max_difference_over_mean']:.2e} of the mean")
    write_results(os.path.join(args.out, "table_codes.json"),
                  {"before": os.path.abspath(args.before), "resolution": args.resolution,
                   "directions": args.directions, "bounces": args.bounces, "size": args.size, "scenes": result})
    return 0


if __name__ == "__main__":
    status = main()
    if "bpy" in sys.modules:
        from tools.blender_compat import compat

        compat.end_module_process(status)
    sys.exit(status)
