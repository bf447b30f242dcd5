"""Time to simulate and write a full BTF (issue 18's target: 81 x 81 images of 256^2 in <= 10 min
on a 2-core machine, files included).

    .venv/bin/python benchmarks/btf_speed.py [--tile woven|heightfield] [--format exr|png] [--size 256]
        [--out DIR] [--json docs/appearance/btf_speed.json]

The BTF is written to DIR (a temporary folder by default, removed afterwards); the JSON gets
the machine, settings, date, per-stage seconds and the folder's size.
"""
import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks import brdf_tiles  # noqa: E402
from core.appearance import btf, gonio  # noqa: E402
from core.appearance.tile import Tile  # noqa: E402


def heightfield(n: int = 64) -> np.ndarray:
    x = np.arange(n) / n
    rng = np.random.default_rng(1)
    return 0.05 * np.sin(2 * np.pi * x)[None, :] * np.cos(4 * np.pi * x)[:, None] + 0.004 * rng.random((n, n))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tile", choices=("woven", "heightfield"), default="woven")
    parser.add_argument("--format", choices=("exr", "png"), default="exr")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--rays-per-pixel", type=int, default=4)
    parser.add_argument("--out")
    parser.add_argument("--json", default=os.path.join(ROOT, "docs", "appearance", "btf_speed.json"))
    options = parser.parse_args()
    if options.tile == "woven":
        positions, triangles, period = brdf_tiles.woven_tile()
        tile = Tile.of(positions, triangles, period, albedo=(0.7, 0.5, 0.3), specular=0.1, roughness=0.4, smooth=True)
    else:
        positions, triangles, period = brdf_tiles.heightfield_tile(heightfield())
        tile = Tile.of(positions, triangles, period, albedo=0.7, specular=0.3, roughness=-1.0, smooth=True)
    folder = options.out or tempfile.mkdtemp(prefix="visibake-btf-")
    settings = gonio.GonioSettings()
    thetas, phis = btf.ubo_directions()
    directions = btf.unit_vector(thetas, phis)
    started = time.perf_counter()
    writer = btf.BTFWriter(folder, options.format, options.size, options.size, tile.period, overwrite=True)
    stats = gonio.simulate_btf(tile, directions, directions, (options.size, options.size), writer.write, settings,
                               options.rays_per_pixel)
    writer.finish()
    seconds = time.perf_counter() - started
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files)
    record = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average_at_end": os.getloadavg()},
              "tile": options.tile, "triangles": int(len(triangles)), "format": options.format,
              "image_size": options.size, "rays_per_pixel": options.rays_per_pixel,
              "settings": {"directions": settings.directions, "bounces": settings.bounces,
                           "resolution": settings.resolution},
              "images": stats["images"], "seconds": round(seconds, 1), "stats": stats,
              "folder_mib": round(size / 2 ** 20, 1)}
    print(json.dumps(record), flush=True)
    if options.json:
        os.makedirs(os.path.dirname(options.json), exist_ok=True)
        with open(options.json, "w") as handle:
            json.dump(record, handle, indent=1)
    if not options.out:
        shutil.rmtree(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
