"""Soft lamps with exact shadows: every sampler point traced, against probing for penumbrae first.

``.venv/bin/python benchmarks/soft_shadows.py`` (no Blender needed) writes
``benchmarks/results/soft_shadows.json``. The scene is core's: a ground plane under a
floating square blocker. For each lamp, the direct light on the ground is computed three
ways: a reference with 32^2 points traced everywhere, the bake's default 8^2 points traced
everywhere (what VisiBake did before the probes), and 8^2 points with the penumbra probes
(``core.transport.direct``: rays to the lamp's centre and outline first, all points only
where those disagree). Errors are relative to the reference: the mean |relative error|
over lit texels and the RMSE over the largest value.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tests", "core"))

import numpy as np  # noqa: E402

from benchmarks.run import write_results  # noqa: E402
from core.pipeline.prepare import prepare  # noqa: E402
from core.scene import Light, Scene  # noqa: E402
from core.settings import BakeSettings  # noqa: E402
from core.transport import direct  # noqa: E402
from core_scenes import quad_mesh  # noqa: E402

LAMPS = {
    "sun 0.526 deg (Blender's default)": Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(0.526),
                                               direction=np.array([0.6, 0.0, -0.8])),
    "sun 2 deg": Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(2.0), direction=np.array([0.6, 0.0, -0.8])),
    "sun 30 deg": Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(30.0)),
    "point r=0.2": Light("Lamp", "POINT", np.ones(3), 40.0, position=np.array([0.3, 0.2, 1.5]), radius=0.2),
    "area 0.6 x 0.6": Light("Panel", "AREA", np.ones(3), 40.0, position=np.array([0.0, 0.0, 1.2]),
                            direction=np.array([0.0, 0.0, -1.0]), size_x=0.6, size_y=0.6),
}


def ground_light(prepared, light, area_light_samples: int, probes: bool):
    """(irradiance on the ground (texels,), shadow rays, seconds)."""
    saved = direct.ADAPTIVE_MIN_POINTS
    direct.ADAPTIVE_MIN_POINTS = saved if probes else 10**9
    try:
        shadowing = dataclasses.replace(prepared.shadowing(), area_light_samples=area_light_samples)
        started = time.perf_counter()
        irradiance, rays = direct.lamp_irradiance(prepared.sample_set(), shadowing, [light])
        seconds = time.perf_counter() - started
    finally:
        direct.ADAPTIVE_MIN_POINTS = saved
    ground = slice(prepared.sample_offset[0], prepared.sample_offset[1])
    return irradiance[ground, 0], rays, seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128, help="ground texels per side (default 128)")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "soft_shadows.json"))
    args = parser.parse_args(argv)
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=args.resolution)
    blocker = quad_mesh("Blocker", [(-0.3, -0.3, 0.5), (-0.3, 0.3, 0.5), (0.3, 0.3, 0.5), (0.3, -0.3, 0.5)],
                        resolution=8)
    prepared = prepare(Scene([ground, blocker], []), BakeSettings(directions=16, bounces=0, shadows="exact"))
    rows = []
    for name, light in LAMPS.items():
        reference, _, _ = ground_light(prepared, light, 32, probes=False)
        lit = reference > 0.02 * reference.max()
        row = {"lamp": name, "texels": int(len(reference))}
        for label, probes in (("every_point", False), ("probes", True)):
            value, rays, seconds = ground_light(prepared, light, 8, probes)
            row[label] = {"rays": int(rays), "seconds": round(seconds, 3),
                          "mean_relative_error": float(np.mean(np.abs(value[lit] / reference[lit] - 1.0))),
                          "rmse_over_max": float(np.sqrt(np.mean((value - reference) ** 2)) / reference.max())}
        row["ray_ratio"] = row["probes"]["rays"] / row["every_point"]["rays"]
        row["speedup"] = row["every_point"]["seconds"] / max(row["probes"]["seconds"], 1e-9)
        rows.append(row)
        print(f"{name:36s} rays {row['ray_ratio']:.2f}x  time {row['speedup']:.1f}x faster  error "
              f"{row['every_point']['mean_relative_error']:.4f} -> {row['probes']['mean_relative_error']:.4f}")
    write_results(args.out, {"settings": {"resolution": args.resolution, "area_light_samples": 8,
                                          "reference_area_light_samples": 32}, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
