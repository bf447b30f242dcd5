"""Volume lighting (core.volume): run time of each pass, and the one-bounce light against an
independent Monte Carlo estimate, for the table variants (issue 17).

The medium is a 64^3 cloud of Gaussian blobs in a unit cube (optical depth up to ~10
across), albedo 0.9, under a sun (3 W/m^2, from above and to the side) with a black world.

Reference: at ``--probes`` voxels, the one-bounce in-scattered radiance S_1 estimated by
``--paths`` free-flight paths each, marched through the same medium (trilinear density,
zero outside) in quarter-voxel steps, with the sun's transmittance at each scattering point
marched too: plain numpy, nothing from core.volume or core.kernels. Its standard error is
reported beside every error figure.

Variants: direction counts 64 and 256 (a random rotation per bake), and the tables' points per
ray: random within M strata (M = 1 is the paper's table; M = 2, the default, and 4) and the
deterministic quantile midpoints (M = 1, 2, 4).

    .venv/bin/python benchmarks/volume_accuracy.py [--probes 24] [--paths 20000] [--quick]

Writes ``benchmarks/results/volume_accuracy.json`` with the machine, settings and date.
"""
import argparse
import datetime
import json
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.fixed_costs import timed  # noqa: E402
from benchmarks.volume_reference import trilinear  # noqa: E402
from core import kernels  # noqa: E402
from core.scene import Light  # noqa: E402
from core.visibility.directions import direction_set  # noqa: E402
from core.volume import direct, tables, transport  # noqa: E402
from core.volume.medium import make_medium  # noqa: E402
from core.volume.occluders import Occluders, SurfaceMesh, reflected_light  # noqa: E402

SUN_DIRECTION = np.array([0.3, 0.45, -0.84]) / np.linalg.norm([0.3, 0.45, -0.84])
SUN_IRRADIANCE = 3.0
ALBEDO = 0.9
EXTINCTION = 12.0


def cloud(n: int, seed: int = 17) -> np.ndarray:
    """(n, n, n) float32: Gaussian blobs, zero below 2% of the peak."""
    rng = np.random.default_rng(seed)
    axis = (np.arange(n) + 0.5) / n
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    density = np.zeros((n, n, n))
    for _ in range(7):
        centre = rng.uniform(0.3, 0.7, 3)
        width = rng.uniform(0.07, 0.15)
        density += rng.uniform(0.6, 1.4) * np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2
                                                   + (z - centre[2]) ** 2) / (2 * width * width))
    density[density < 0.02 * density.max()] = 0.0
    return density.astype(np.float32)


def medium_of(n: int):
    return make_medium("cloud", cloud(n), np.diag([1.0 / n, 1.0 / n, 1.0 / n, 1.0]), extinction=EXTINCTION,
                       albedo=(ALBEDO,) * 3)


def _march(density, starts, directions, voxel, step=0.25, targets=None):
    """March index-space rays; returns (optical depth to the grid's end, and where each
    reached ``targets`` in optical depth (NaN: escaped first))."""
    n = density.shape[0]
    depth = np.zeros(len(starts))
    where = np.full((len(starts), 3), np.nan)
    before = trilinear(density, starts)
    point = starts.copy()
    live = np.ones(len(starts), bool)
    for _ in range(int(np.ceil(1.8 * (n + 2) / step)) + 2):
        if not live.any():
            break
        moved = point + directions * step
        after = trilinear(density, moved)
        increment = EXTINCTION * voxel * step * 0.5 * (before + after)
        if targets is not None:
            crossing = live & np.isnan(where[:, 0]) & (depth + increment >= targets) & (increment > 0)
            fraction = np.where(crossing, (targets - depth) / np.where(increment > 0, increment, 1.0), 0.0)
            where[crossing] = point[crossing] + directions[crossing] * step * fraction[crossing, None]
        depth = np.where(live, depth + increment, depth)
        before = after
        point = moved
        live &= np.all((point >= -1) & (point <= n), axis=1)
    return depth, where


def reference_bounce(medium, probes: np.ndarray, paths: int, seed: int = 1):
    """(P,) mean and standard error of S_1 at ``probes`` (P, 3) int voxels, by free-flight paths."""
    rng = np.random.default_rng(seed)
    n = medium.shape[0]
    voxel = 1.0 / n
    means, errors = [], []
    towards_sun = -SUN_DIRECTION
    for probe in probes:
        values = []
        for start in range(0, paths, 20000):
            count = min(20000, paths - start)
            z = rng.uniform(-1, 1, count)
            phi = rng.uniform(0, 2 * np.pi, count)
            r = np.sqrt(1 - z * z)
            directions = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
            targets = -np.log(1.0 - rng.uniform(0, 1, count))
            starts = np.broadcast_to(probe.astype(np.float64), (count, 3)).copy()
            _, where = _march(medium.density, starts, directions, voxel, targets=targets)
            scattered = ~np.isnan(where[:, 0])
            value = np.zeros(count)
            if scattered.any():
                points = where[scattered]
                depth, _ = _march(medium.density, points, np.broadcast_to(towards_sun, points.shape).copy(), voxel)
                value[scattered] = ALBEDO * SUN_IRRADIANCE / (4 * np.pi) * np.exp(-depth)
            values.append(value)
        values = np.concatenate(values)
        means.append(values.mean())
        errors.append(values.std() / np.sqrt(len(values)))
    return np.array(means), np.array(errors)


def floor_mesh(side: int = 100, height: float = -0.05, low=(-1.0, -1.0), high=(2.0, 2.0)):
    """A horizontal grid of ``side``^2 quads (2 side^2 triangles) over [low, high] in x and y at
    ``height`` (by default a floor under the cloud's unit cube), grey (albedo 0.5)."""
    u, v = np.meshgrid(np.linspace(low[0], high[0], side + 1), np.linspace(low[1], high[1], side + 1),
                       indexing="ij")
    positions = np.stack([u.ravel(), v.ravel(), np.full(u.size, height)], axis=1)
    index = np.arange((side + 1) ** 2).reshape(side + 1, side + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    triangles = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return SurfaceMesh(positions, triangles, albedo=np.full((len(triangles), 3), 0.5, np.float32))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--probes", type=int, default=24)
    parser.add_argument("--paths", type=int, default=20000)
    parser.add_argument("--quick", action="store_true", help="32^3, fewer probes and paths (a smoke run)")
    parser.add_argument("--timings", action="store_true", help="the timings only (no Monte Carlo reference)")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "volume_accuracy.json"))
    options = parser.parse_args()
    n = 32 if options.quick else 64
    if options.quick:
        options.probes, options.paths = min(options.probes, 6), min(options.paths, 4000)
    started = time.perf_counter()
    kernels.volume()
    record = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "python": platform.python_version()},
              "kernels": kernels.status().describe(), "volume_kernel_load_s": round(time.perf_counter() - started, 2),
              "grid": n, "extinction": EXTINCTION, "albedo": ALBEDO, "probes": options.probes, "paths": options.paths}
    medium = medium_of(n)
    sun = Light("sun", "SUN", np.ones(3), SUN_IRRADIANCE, direction=SUN_DIRECTION)
    lamp = Light("lamp", "POINT", np.ones(3), 20.0, position=np.array([0.55, 0.4, 0.6]))
    active = medium.active()
    record["active_voxels"] = int(len(active))

    floor = Occluders.from_meshes([floor_mesh()])
    record["floor_triangles"] = floor.triangles
    timings = {}
    timings["sun_sweep_s"], _ = timed(lambda: direct.transmittance(medium, sun))
    timings["point_sweep_s"], _ = timed(lambda: direct.transmittance(medium, lamp))
    big = make_medium("cloud256", cloud(256), np.diag([1 / 256, 1 / 256, 1 / 256, 1.0]), extinction=EXTINCTION)
    if not options.quick:
        timings["sun_sweep_256_s"], _ = timed(lambda: direct.transmittance(big, sun), repeats=1)
        timings["point_sweep_256_s"], _ = timed(lambda: direct.transmittance(big, lamp), repeats=1)
        # What meshes add to a lamp's direct light: a shadow ray per active voxel (a point lamp
        # has one light point). The lamp is above the cloud and a roof of 20k triangles
        # between them covers half of it, so half the rays meet it and the rest pass it close by.
        big_voxels = big.active()
        high_lamp = Light("high lamp", "POINT", np.ones(3), 20.0, position=np.array([0.5, 0.5, 1.3]))
        roof = Occluders.from_meshes([floor_mesh(height=0.9, low=(-1.0, -1.0), high=(0.5, 2.0))])
        timings["point_direct_256_s"], _ = timed(lambda: direct.lamp_inscatter(big, high_lamp, big_voxels),
                                                 repeats=1)
        timings["point_direct_256_with_roof_s"], shaded = timed(
            lambda: direct.lamp_inscatter(big, high_lamp, big_voxels, occluders=roof), repeats=1)
        record["voxels_under_the_roof_share"] = round(float(np.mean(shaded[:, 0] == 0.0)), 3)
        record["active_voxels_256"] = int(len(big_voxels))
        big_voxels = None
    big = None  # free its grids before the tables
    directions = direction_set(64, rotate=True, seed=3)
    timings["tables_64_m1_s"], table = timed(lambda: tables.build_tables(medium, directions, points=1), repeats=1)
    timings["tables_64_m2_s"], table_m2 = timed(lambda: tables.build_tables(medium, directions), repeats=1)
    timings["tables_64_m2_with_floor_s"], floored = timed(
        lambda: tables.build_tables(medium, directions, occluders=floor), repeats=1)
    # The floor's light: a shadow ray and a march through the cloud per table ray that ends at it.
    timings["floor_light_s"], _ = timed(lambda: reflected_light(medium, floored, floor, [sun]), repeats=1)
    record["rays_ending_at_the_floor"] = int((~floored.sees_world).sum())
    floored = None
    record["table_mib"] = round(table_m2.nbytes / 2 ** 20, 1)
    timings["direct_s"], _ = timed(lambda: transport.light_medium(medium, table, [sun], bounces=0), repeats=1)
    timings["one_bounce_gather_m1_s"], _ = timed(
        lambda: transport.gather(medium, table, np.ones((len(table.voxels), 3))))
    timings["one_bounce_gather_m2_s"], _ = timed(
        lambda: transport.gather(medium, table_m2, np.ones((len(table.voxels), 3))))
    record["timings"] = {key: round(value, 3) for key, value in timings.items()}
    print(json.dumps(record["timings"]), flush=True)
    if options.timings:
        print(json.dumps({key: record.get(key) for key in ("active_voxels", "active_voxels_256",
                                                           "voxels_under_the_roof_share", "floor_triangles",
                                                           "rays_ending_at_the_floor")}))
        return 0

    rng = np.random.default_rng(5)
    probes = active[rng.choice(len(active), options.probes, replace=False)]
    reference, noise = reference_bounce(medium, probes, options.paths)
    record["reference_mean"] = float(reference.mean())
    record["reference_relative_noise"] = float(np.sqrt(np.mean(noise ** 2)) / reference.mean())
    variants = []
    for count in (64, 256):
        for label, points, jitter in (("random", 1, 11), ("random", 2, 11), ("random", 4, 11),
                                      ("midpoint", 1, None), ("midpoint", 2, None), ("midpoint", 4, None)):
            errors = []
            for seed in (3, 4, 5):
                dirs = direction_set(count, rotate=True, seed=seed)
                built = tables.build_tables(medium, dirs, points=points, jitter_seed=jitter)
                light = transport.light_medium(medium, built, [sun], bounces=1)
                got = light.indirect[tuple(probes.T)][:, 0].astype(np.float64)
                errors.append(np.sqrt(np.mean((got - reference) ** 2)) / reference.mean())
            variants.append({"directions": count, "points": label, "M": points,
                             "relative_rmse": round(float(np.mean(errors)), 4),
                             "per_seed": [round(float(e), 4) for e in errors]})
            print(json.dumps(variants[-1]), flush=True)
    record["one_bounce_vs_reference"] = variants
    os.makedirs(os.path.dirname(options.out), exist_ok=True)
    with open(options.out, "w") as handle:
        json.dump(record, handle, indent=1)
    print(json.dumps({key: record[key] for key in ("reference_mean", "reference_relative_noise", "active_voxels",
                                                    "table_mib")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
