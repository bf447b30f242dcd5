"""The volume gather before and after it read a dilated 3-channel grid (issue 17): both kernels
in one run, on the same tables, for time and for accuracy against the Monte Carlo reference of
benchmarks/volume_accuracy.py.

The earlier kernel (a density-weighted read of a 4-channel grid, and a division per lookup) is
taken from git at ``--before`` (default aa2a82a, the last commit with it).

    .venv/bin/python benchmarks/volume_gather_ab.py [--before SHA] [--accuracy] [--repeats 7]
"""
import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import benchmarks.volume_accuracy as accuracy  # noqa: E402
from benchmarks.earlier import earlier_module  # noqa: E402
from core import kernels  # noqa: E402
from core.scene import Light  # noqa: E402
from core.visibility.directions import direction_set  # noqa: E402
from core.volume import tables, transport  # noqa: E402
from core.volume.medium import padded  # noqa: E402


def earlier_kernels(sha: str):
    """The volume kernels module as it was at ``sha``."""
    return earlier_module(sha, "core/kernels/volume_kernels.py", "earlier_volume_kernels")


def earlier_gather(module, medium, table, sent):
    """transport.gather as it was: density times the sent light in 3 channels, density in the 4th."""
    source = np.zeros((*medium.shape, 4), np.float32)
    index = tuple(table.voxels.T)
    density = medium.density[index]
    source[index + (slice(0, 3),)] = sent * density[:, None]
    source[index + (3,)] = density
    result = np.zeros((len(table.voxels), 3))
    kernels.run(module.gather_volume, 0, padded(source), table.voxels, table.index_directions, table.distance_codes,
                table.escape_codes, table.distance_per_code, module.BLOCK, result)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="aa2a82a")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--accuracy", action="store_true", help="also the one-bounce error against the reference")
    options = parser.parse_args()
    kernels.volume()
    before = earlier_kernels(options.before)
    medium = accuracy.medium_of(64)
    for points in (1, 2):
        table = tables.build_tables(medium, direction_set(64, rotate=True, seed=3), points=points)
        sent = np.random.default_rng(1).random((len(table.voxels), 3))
        old = earlier_gather(before, medium, table, sent)
        new = transport.gather(medium, table, sent)
        times = {"before": [], "after": []}
        for _ in range(options.repeats):  # interleaved, so the machine's drift hits both alike
            started = time.perf_counter()
            earlier_gather(before, medium, table, sent)
            times["before"].append(time.perf_counter() - started)
            started = time.perf_counter()
            transport.gather(medium, table, sent)
            times["after"].append(time.perf_counter() - started)
        print(json.dumps({"M": points, "largest_relative_difference": float(np.max(np.abs(old - new)) / old.max()),
                          **{f"{key}_min_s": round(min(value), 4) for key, value in times.items()},
                          **{f"{key}_median_s": round(float(np.median(value)), 4) for key, value in times.items()}}),
              flush=True)
    if not options.accuracy:
        return 0
    sun = Light("sun", "SUN", np.ones(3), accuracy.SUN_IRRADIANCE, direction=accuracy.SUN_DIRECTION)
    active = medium.active()
    probes = active[np.random.default_rng(5).choice(len(active), 24, replace=False)]
    reference, noise = accuracy.reference_bounce(medium, probes, 20000)
    print(json.dumps({"reference_relative_noise": float(np.sqrt(np.mean(noise ** 2)) / reference.mean())}))
    for count in (64, 256):
        for points in (1, 2):
            errors = {"before": [], "after": []}
            for seed in (3, 4, 5):
                table = tables.build_tables(medium, direction_set(count, rotate=True, seed=seed), points=points,
                                            jitter_seed=11)
                light = transport.light_medium(medium, table, [sun], bounces=0)
                index = tuple(table.voxels.T)
                sent = medium.albedo[index].astype(np.float64) * light.direct[index].astype(np.float64)
                rows = {tuple(v): i for i, v in enumerate(table.voxels)}
                chosen = [rows[tuple(p)] for p in probes]
                for key, gathered in (("before", earlier_gather(before, medium, table, sent)),
                                      ("after", transport.gather(medium, table, sent))):
                    got = gathered[chosen, 0]
                    errors[key].append(float(np.sqrt(np.mean((got - reference) ** 2)) / reference.mean()))
            print(json.dumps({"directions": count, "M": points,
                              **{f"{key}_relative_rmse": round(float(np.mean(value)), 4)
                                 for key, value in errors.items()},
                              **{f"{key}_per_seed": [round(e, 4) for e in value] for key, value in errors.items()}}),
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
