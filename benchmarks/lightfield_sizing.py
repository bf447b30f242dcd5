"""What `lightfield --bake-first --resolution-from-views` saves, and what it costs (issue 19).

    export NUMBA_CACHE_DIR=/tmp/numba-cache
    .venv/bin/python benchmarks/lightfield_sizing.py [--resolution 512] [--directions 64] [--work DIR]

The built-in demo room is baked twice per light field, through the command a user runs:
once at ``--resolution`` for every object the views see, once with ``--resolution-from-views``
(each atlas sized to a texel per pixel where the views see it nearest, never above
``--resolution``). Both at ``--directions`` directions, 2 bounces, the demo's camera as
the centre, baseline 50 mm, focus 3.2 m, for 16 x 16 views at 256^2 and 9 x 9 at 512^2.

Reported per grid: the bake's seconds and texels (atlas objects) of each, the atlas sizes
chosen, and the views of the sized bake against the full one: relative RMSE per pixel and
on 4 x 4-pixel blocks (over the full one's mean) of five views (the corners and the centre);
beside it, the same difference for the full bake with another seed (another rotation of the
direction set): the bake's own noise, which any second bake differs by.
The views' own render time is not part of it. Writes benchmarks/results/lightfield_sizing.json.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

from benchmarks.lightfield_vs_cycles import read_exr, relative_rmse  # noqa: E402

GRIDS = ((16, 16, 256), (9, 9, 512))
BASELINE_MM, FOCUS_M = 50.0, 3.2


def visibake(*arguments: str) -> None:
    command = [sys.executable, os.path.join(ROOT, "tools", "visibake.py"), *arguments]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-3000:]}")


def light_field(blend: str, folder: str, grid: tuple[int, int, int], resolution: int, directions: int,
                sized: bool, seed: int = 0) -> dict:
    columns, rows, size = grid
    report_path = folder + ".json"
    started = time.perf_counter()
    visibake("lightfield", blend, "--out", folder, "--views", f"{columns}x{rows}", "--image-size", f"{size}x{size}",
             "--baseline-mm", str(BASELINE_MM), "--focus-distance-m", str(FOCUS_M), "--bake-first",
             "--resolution", str(resolution), "--directions", str(directions), "--bounces", "2", "--no-cache",
             "--no-progress", "--report", report_path, "--seed", str(seed),
             *(["--resolution-from-views"] if sized else []))
    wall = time.perf_counter() - started
    with open(report_path, encoding="utf-8") as handle:
        report = json.load(handle)
    sizes = report["bake"]["resolutions"]
    return {"bake_s": report["bake"]["seconds"], "command_s": round(wall, 1), "render_s": report["render_s"],
            "atlas_texels": int(sum(w * h for w, h in sizes.values())), "resolutions": sizes}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--directions", type=int, default=64)
    parser.add_argument("--work", help="keep the light fields here (default: a temporary folder, removed)")
    args = parser.parse_args(argv)
    from benchmarks.run import write_results

    work = args.work or tempfile.mkdtemp(prefix="visibake-sizing-")
    os.makedirs(work, exist_ok=True)
    blend = os.path.join(work, "demo.blend")
    visibake("demo", "--out", os.path.join(work, "demo"), "--save", blend, "--directions", "16", "--bounces", "0",
             "--no-progress")
    rows = {}
    for grid in GRIDS:
        key = f"{grid[0]}x{grid[1]}@{grid[2]}"
        full = light_field(blend, os.path.join(work, f"{key}_full"), grid, args.resolution, args.directions, False)
        sized = light_field(blend, os.path.join(work, f"{key}_sized"), grid, args.resolution, args.directions, True)
        # The bake's own noise: the full bake again with another rotation of the direction set.
        reseeded = light_field(blend, os.path.join(work, f"{key}_seed1"), grid, args.resolution, args.directions,
                               False, seed=1)
        count = grid[0] * grid[1]
        chosen = sorted({0, grid[0] - 1, count - grid[0], count - 1, (grid[1] // 2) * grid[0] + grid[0] // 2})

        def difference(folder: str) -> tuple[float, float]:
            pixels, blocks = [], []
            for index in chosen:
                name = f"input_Cam{index:03d}.exr"
                a = read_exr(os.path.join(work, folder, name))
                b = read_exr(os.path.join(work, f"{key}_full", name))
                pixels.append(relative_rmse(a, b, 1))
                blocks.append(relative_rmse(a, b))
            return round(float(np.mean(pixels)), 5), round(float(np.mean(blocks)), 5)

        sized_pixels, sized_blocks = difference(f"{key}_sized")
        seed_pixels, seed_blocks = difference(f"{key}_seed1")
        rows[key] = {"full": full, "sized": sized, "full_seed1_bake_s": reseeded["bake_s"], "views_compared": chosen,
                     "sized_vs_full_pixels": sized_pixels, "sized_vs_full_blocks": sized_blocks,
                     "seed1_vs_full_pixels": seed_pixels, "seed1_vs_full_blocks": seed_blocks,
                     "bake_speedup": round(full["bake_s"] / sized["bake_s"], 2),
                     "texel_ratio": round(sized["atlas_texels"] / full["atlas_texels"], 3)}
        print(f"{key}: bake {full['bake_s']:.1f} s -> {sized['bake_s']:.1f} s, texels {full['atlas_texels']} -> "
              f"{sized['atlas_texels']}; views differ by {100 * sized_pixels:.2f}% per pixel, "
              f"{100 * sized_blocks:.2f}% on blocks (another seed of the full bake: {100 * seed_pixels:.2f}%, "
              f"{100 * seed_blocks:.2f}%); sizes {sized['resolutions']}", flush=True)
    write_results(os.path.join(ROOT, "benchmarks", "results", "lightfield_sizing.json"),
                  {"settings": {"resolution": args.resolution, "directions": args.directions, "bounces": 2,
                                "baseline_mm": BASELINE_MM, "focus_distance_m": FOCUS_M, "cache": False},
                   "grids": rows, "load_average_end": os.getloadavg()[0]})
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
