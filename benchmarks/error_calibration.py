"""The bake's estimate of its own error against the error measured against Cycles (issue 52).

    NUMBA_CACHE_DIR=/tmp/nc .venv/bin/python benchmarks/error_calibration.py                 # 8 scenes, 64 + 256
    .venv/bin/python benchmarks/error_calibration.py --scenes atrium seed:10 --directions 256
    .venv/bin/python benchmarks/error_calibration.py --summarize runs.jsonl   # the table again, and the spread

Each scene (a name of ``benchmarks/scenes.py`` SCENES, or ``seed:N`` for scene N of
``../shared/tools/scenegen.py``) is baked at ``--resolution``^2, ``--bounces`` (2) and exact
shadows at each direction count, every mesh an output, with seam stitching off (Cycles does not
stitch, and the estimate does not see it). The report's ``estimated_error`` (core.transport.estimate)
is set beside the per-texel relative RMS error against a Cycles bake of ``--samples`` on the same
UV layout (benchmarks/reference.py, two halves, cached in ``--cache``), raw and with the
reference's own noise taken out (sqrt(e^2 - n^2)). The ratio estimate / measured is the
calibration: 1 is an honest estimate, below 1 an error the bake does not see (a bias).
Prints a markdown table; ``--json`` appends one line a run.
"""
import argparse
import importlib
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def build(name: str, scenegen_path: str):
    """Make scene ``name`` in the current bpy scene; returns its mesh objects and a description."""
    import bpy

    from benchmarks import scenes

    scenes.reset()
    if name.startswith("seed:"):
        from benchmarks.scenegen_vs_cycles import load_scenegen

        description = load_scenegen(scenegen_path).build(int(name.split(":", 1)[1]))
        return [o for o in bpy.context.scene.objects if o.type == "MESH"], description
    return scenes.SCENES[name]("full"), scenes.SCENES[name].__doc__.split("\n")[0]


def measure(name: str, args, job) -> list[dict]:
    """Bake scene ``name`` at each direction count; the estimate and the measured error of each."""
    import bpy

    from benchmarks import reference

    objects, description = build(name, args.scenegen)
    props = bpy.context.scene.visibake
    props.passes = {"lighting"}
    props.use_cache, props.mode, props.stitch_seams = False, "atlas", False
    props.resolution, props.bounces, props.shadows = args.resolution, args.bounces, "exact"
    rows = []
    ref = None
    for directions in args.directions:
        props.directions = directions
        started = time.perf_counter()
        outcome = job.run_bake(bpy.context, objects)
        seconds = time.perf_counter() - started
        report = outcome.report
        uv_maps = {o["name"]: o["uv_map"] for o in report["objects"] if o["output"]}
        if ref is None:
            ref = reference.cached_reference(objects, uv_maps, args.resolution, args.bounces, args.samples, args.cache)
        images = {r.name: r.images["lighting"] for r in outcome.result.objects}
        texel = reference.relative_errors(images, ref.images)
        blocks = reference.block_errors(images, ref)
        measured = blocks["texel_rmse_denoised"]
        estimate = report.get("estimated_error") or {}
        per_object = {}
        for entry in report["objects"]:
            if not entry["output"] or not entry.get("estimated_error"):
                continue
            one = {entry["name"]: images[entry["name"]]}
            theirs = {entry["name"]: ref.images[entry["name"]]}
            per_object[entry["name"]] = dict(estimated=entry["estimated_error"]["total"],
                                             measured=reference.relative_errors(one, theirs)["relative_rmse"])
        rows.append(dict(scene=name, description=description, directions=directions, seconds=seconds,
                         measured=texel["relative_rmse"], noise=blocks["texel_noise"], measured_denoised=measured,
                         bias=texel["bias"], estimated=estimate.get("total"), estimated_lamps=estimate.get("lamps"),
                         estimated_gathered=estimate.get("gathered"),
                         unestimated_share=estimate.get("unestimated_share"),
                         ratio=(estimate["total"] / measured) if estimate.get("total") and measured else None,
                         objects=per_object, blender=bpy.app.version_string, samples=args.samples,
                         resolution=args.resolution, bounces=args.bounces))
        show(rows[-1])
    return rows


def show(row: dict) -> None:
    def percent(value):
        return "-" if value is None else f"{100 * value:.2f}%"

    ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}"
    print(f"| {row['scene']} | {row['directions']} | {row['seconds']:.1f} s | {percent(row['measured'])} "
          f"| {percent(row['noise'])} | {percent(row['measured_denoised'])} | {percent(row['estimated'])} "
          f"({percent(row.get('estimated_lamps', row.get('estimated_direct')))} + "
          f"{percent(row.get('estimated_gathered', row.get('estimated_indirect')))}) | {ratio} |", flush=True)


def summarize(paths: list[str]) -> int:
    """Print the runs of ``paths`` (--json files) as the table, then how the estimate / measured
    ratios spread: their median, range, and how many lie within a factor of 1.5 either way."""
    rows = [json.loads(line) for path in paths for line in open(path) if line.strip()]
    print(HEADER)
    for row in rows:
        show(row)
    ratios = sorted(r["ratio"] for r in rows if r["ratio"] is not None)
    if ratios:
        within = sum(1 / 1.5 <= r <= 1.5 for r in ratios)
        print(f"\n{len(ratios)} runs: estimate / measured median {ratios[len(ratios) // 2]:.2f}, range "
              f"{ratios[0]:.2f}-{ratios[-1]:.2f}, {within} within a factor of 1.5")
    return 0


HEADER = ("| scene | directions | VisiBake | measured per texel | Cycles' noise | measured without it "
          "| estimated (lamps + gathered) | estimated / measured |\n|---|---|---|---|---|---|---|---|")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="benchmarks/scenes.py names or seed:N (default: all eight benchmark scenes)")
    parser.add_argument("--directions", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--samples", type=int, default=2048, help="Cycles reference samples per texel (two halves)")
    parser.add_argument("--scenegen", default=os.path.join(os.path.dirname(ROOT), "shared", "tools", "scenegen.py"))
    parser.add_argument("--cache", default=os.path.join(ROOT, "benchmarks", "cache"))
    parser.add_argument("--json", help="append one JSON line a run to this file")
    parser.add_argument("--summarize", nargs="+", metavar="JSONL",
                        help="only print the table and the calibration's spread from these --json files")
    args = parser.parse_args(argv)
    if args.summarize:
        return summarize(args.summarize)

    from tools.visibake import load_extension

    extension = load_extension()
    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    from benchmarks import scenes

    names = args.scenes or list(scenes.SCENES)
    print(HEADER)
    from benchmarks.scenegen_vs_cycles import append_json_line

    for name in names:
        for row in measure(name, args, job):
            append_json_line(args.json, row)
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
