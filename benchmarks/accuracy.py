"""Accuracy at one lighting (issue 15): error against the direction count, one technique at a time.

    .venv/bin/python benchmarks/accuracy.py                                  # ~15 min on 2 cores
    .venv/bin/python benchmarks/accuracy.py --scenes sun_occluders --directions 64 256

For each scene of ``benchmarks/scenes.py`` at one atlas resolution: a converged Cycles
reference (``benchmarks/reference.py``, two halves, cached), then VisiBake at each
direction count with each variant of :data:`VARIANTS` (exact shadows unless ``--shadows
fractions``, no rotation). Every
run records two errors against the reference, with the reference's own noise on the same
metric beside each:

- per texel: relative RMSE over covered texels;
- on 4x4-texel block means: the low-frequency error a denoiser cannot remove.

Where the reference's noise n is not small against an error e, sqrt(e^2 - n^2) is given too.
Writes ``<out>/accuracy.json`` and ``<out>/<scene>.png`` (error against N per variant).
"""
import argparse
import importlib
import json
import os
import sys
import time
from datetime import datetime, timezone

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

# Each variant switches one technique against the one before it; the last is the product's default
# (interleave 4, 4 x 4 rotations, since speed part 16; issue 15's figures were taken at 3).
# Seam stitching is judged on renders (benchmarks/seams.py); its row here shows what it does to
# texel error against Cycles, which does not stitch.
VARIANTS = {
    "texel centres": {"footprint_samples": 1, "sharp_contacts": False, "interleave": 1, "stitch_seams": False},
    "+ footprint": {"footprint_samples": 16, "sharp_contacts": False, "interleave": 1, "stitch_seams": False},
    "+ sharp contacts": {"footprint_samples": 16, "sharp_contacts": True, "interleave": 1, "stitch_seams": False},
    "+ interleaved rotations": {"footprint_samples": 16, "sharp_contacts": True, "interleave": 4,
                                "stitch_seams": False},
    "+ seam stitching": {"footprint_samples": 16, "sharp_contacts": True, "interleave": 4, "stitch_seams": True},
}


def plot(path: str, title: str, rows, noise: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6.5, 4.5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for index, variant in enumerate(dict.fromkeys(r["variant"] for r in rows)):
        chosen = sorted((r for r in rows if r["variant"] == variant), key=lambda r: r["directions"])
        colour = colours[index % len(colours)]
        axes.plot([r["directions"] for r in chosen], [r["relative_rmse"] for r in chosen], "o-", color=colour,
                  label=f"{variant}, per texel")
        axes.plot([r["directions"] for r in chosen], [r["block_rmse"] for r in chosen], "s--", color=colour,
                  label=f"{variant}, 4x4 blocks")
    for key, style in (("texel_noise", ":"), ("block_noise", "-.")):
        if noise.get(key):
            axes.axhline(noise[key], color="black", linewidth=0.8, linestyle=style,
                         label=f"reference noise ({'texel' if key == 'texel_noise' else 'blocks'})")
    from benchmarks.run import finish_error_plot

    finish_error_plot(figure, axes, path, title, "directions N", dpi=100, x_base=2)


def markdown(result: dict) -> str:
    """The results as one table per scene: error per texel and on blocks (raw, then with the
    reference's noise removed) and seconds, per variant and direction count."""
    lines = [f"Blender {result['blender']}, {result['machine']['cpus']} CPUs, {result['date']}; "
             f"{result['resolution']}² atlases, {result['bounces']} bounces, {result.get('shadows', 'exact')} shadows, "
             f"references {result['reference_samples']} spp.", ""]
    for name, scene in result["scenes"].items():
        lines += [f"**{name}** (reference noise: {100 * scene['texel_noise']:.2f}% per texel, "
                  f"{100 * scene['block_noise']:.2f}% on 4×4 blocks)", "",
                  "| variant | N | per texel | noise removed | 4×4 blocks | noise removed | seconds |",
                  "|---|---|---|---|---|---|---|"]
        for run in scene["runs"]:
            lines.append(f"| {run['variant']} | {run['directions']} | {100 * run['relative_rmse']:.2f}% | "
                         f"{100 * run['relative_rmse_denoised']:.2f}% | {100 * run['block_rmse']:.2f}% | "
                         f"{100 * run['block_rmse_denoised']:.2f}% | {run['seconds']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", help="subset of benchmarks/scenes.py SCENES")
    parser.add_argument("--size", choices=["smoke", "full"], default="full", help="scene size (smoke: the tests')")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--directions", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--reference-samples", type=int, default=2048)
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), help="default: all")
    parser.add_argument("--shadows", choices=["exact", "fractions"], default="exact")
    parser.add_argument("--out", help="results folder (default benchmarks/results/accuracy-<time>)")
    parser.add_argument("--cache", default=os.path.join(ROOT, "benchmarks", "cache"), help="reference cache")
    parser.add_argument("--summarize", metavar="DIR", help="only write DIR/summary.md from DIR/accuracy.json")
    args = parser.parse_args(argv)
    if args.summarize:
        with open(os.path.join(args.summarize, "accuracy.json"), encoding="utf-8") as handle:
            text = markdown(json.load(handle))
        with open(os.path.join(args.summarize, "summary.md"), "w", encoding="utf-8") as handle:
            handle.write(text)
        print(text)
        return 0
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    out = args.out or os.path.join(ROOT, "benchmarks", "results", f"accuracy-{stamp}")
    os.makedirs(out, exist_ok=True)

    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    from benchmarks import reference, scenes
    from benchmarks.run import machine

    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    names = args.scenes or scenes.SCENE_NAMES
    variants = args.variants or list(VARIANTS)
    result = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
              "blender": bpy.app.version_string, "resolution": args.resolution, "bounces": args.bounces,
              "reference_samples": args.reference_samples, "shadows": args.shadows,
              "variants": {v: VARIANTS[v] for v in variants},
              "scenes": {}}
    for name in names:
        scenes.reset()
        objects = scenes.SCENES[name](args.size)
        props = bpy.context.scene.visibake
        props.passes = {"lighting"}
        props.use_cache, props.mode = False, "atlas"
        props.resolution, props.bounces, props.shadows, props.rotate = args.resolution, args.bounces, "exact", False
        props.directions = 128
        first = job.run_bake(bpy.context, objects)  # lays out the UV maps every run and Cycles use
        uv_maps = {o["name"]: o["uv_map"] for o in first.report["objects"] if o["output"]}
        ref = reference.cached_reference(objects, uv_maps, args.resolution, args.bounces, args.reference_samples,
                                         args.cache)
        noise = reference.block_errors(ref.images, ref)
        noise = {"texel_noise": noise["texel_noise"], "block_noise": noise["block_noise"]}
        print(f"{name}: reference {args.reference_samples} spp ({'cached' if ref.cached else f'{ref.seconds:.0f} s'}),"
              f" noise {noise['texel_noise']:.4f} per texel, {noise['block_noise']:.4f} on blocks", flush=True)
        rows = []
        for variant in variants:
            for key, value in VARIANTS[variant].items():
                setattr(props, key, value)
            props.shadows = args.shadows
            for directions in args.directions:
                props.directions = directions
                started = time.perf_counter()
                outcome = job.run_bake(bpy.context, objects)
                seconds = time.perf_counter() - started
                images = {r.name: r.images["lighting"] for r in outcome.result.objects}
                texel = reference.relative_errors(images, ref.images)
                blocks = reference.block_errors(images, ref)
                rows.append({"variant": variant, "directions": directions, "seconds": seconds,
                             "stage_seconds": outcome.report["stage_seconds"],
                             "peak_memory_bytes": outcome.report.get("peak_memory_bytes"),
                             "relative_rmse": texel["relative_rmse"], "bias": texel["bias"],
                             "relative_rmse_denoised": blocks["texel_rmse_denoised"],
                             "block_rmse": blocks["block_rmse"], "block_rmse_denoised": blocks["block_rmse_denoised"]})
                print(f"  {variant}, N={directions}: {seconds:.2f} s, texel {texel['relative_rmse']:.4f}, "
                      f"blocks {blocks['block_rmse']:.4f}", flush=True)
        result["scenes"][name] = {"reference_seconds": ref.seconds, **noise, "runs": rows}
        plot(os.path.join(out, f"{name}.png"), f"{name}, {args.resolution}², {args.bounces} bounces", rows, noise)
        with open(os.path.join(out, "accuracy.json"), "w", encoding="utf-8") as handle:
            json.dump(result, handle, indent=2)
    with open(os.path.join(out, "summary.md"), "w", encoding="utf-8") as handle:
        handle.write(markdown(result))
    print(f"wrote {out}/accuracy.json and summary.md")
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat  # bpy is loaded by now

    compat.end_module_process(status)
