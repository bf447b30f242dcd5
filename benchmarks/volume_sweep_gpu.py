"""Time the volume slice sweep on the CPU (the numba kernel) and on the GPU (its GLSL twin).

    .venv/bin/python benchmarks/volume_sweep_gpu.py [--sizes 128,256] [--repeats 2] [--out FILE.json]

For each grid side n, an n^3 cloud of Gaussian blobs in a unit cube (optical depth up to
~10 across), lit by an oblique sun (one sweep) and by a point lamp inside the cloud (six
sweeps, one per pyramid): the seconds of core.volume.direct.transmittance with the CPU
kernel on all cores and with gpu_shaders.volume_sweep as its sweep pass (each the best of
``--repeats``, after a warm-up on a small grid, so neither includes compiling), and the
largest difference between the two. The GPU time includes uploading the padded density and
reading the results back, as a bake would pay them.

Runs in bpy (the GPU module needs it) with a context made as in background mode; on
machines without a GPU that is Mesa's llvmpipe, which runs the shader on the CPU and is
expected to be slower than the kernel. Prints a table; ``--out`` also writes it as JSON.
"""
import argparse
import importlib
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402


def cloud(n: int, seed: int = 3) -> np.ndarray:
    """(n, n, n) float32: five Gaussian blobs (separable, so a 256^3 grid costs no 3D coordinates)."""
    rng = np.random.default_rng(seed)
    axis = np.arange(n, dtype=np.float64)
    density = np.zeros((n, n, n))
    for _ in range(5):
        centre = rng.uniform(0.25 * n, 0.75 * n, 3)
        width = rng.uniform(0.1, 0.2) * n
        x, y, z = (np.exp(-(axis - c) ** 2 / (2 * width * width)) for c in centre)
        density += rng.uniform(0.5, 1.5) * x[:, None, None] * y[None, :, None] * z[None, None, :]
    density[density < 0.05] = 0.0
    return density.astype(np.float32)


def best_seconds(call, repeats: int):
    """(fastest wall time of ``repeats`` calls, the last result)."""
    fastest, result = float("inf"), None
    for _ in range(repeats):
        started = time.perf_counter()
        result = call()
        fastest = min(fastest, time.perf_counter() - started)
    return fastest, result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="128,256", help="grid sides, comma-separated")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", default=None, help="also write the table as JSON here")
    args = parser.parse_args(argv)

    from tools.visibake import load_extension

    extension = load_extension()
    runtime = importlib.import_module(f"{extension.__name__}.gpu_shaders.runtime")
    try:
        info = runtime.device_info()
    except runtime.GPUUnavailable as error:
        print(f"no GPU context on this machine: {error}", file=sys.stderr)
        return 1
    volume_sweep = importlib.import_module(f"{extension.__name__}.gpu_shaders.volume_sweep")
    direct = importlib.import_module(f"{extension.__name__}.core.volume.direct")
    make_medium = importlib.import_module(f"{extension.__name__}.core.volume.medium").make_medium
    Light = importlib.import_module(f"{extension.__name__}.core.scene").Light
    kernels = importlib.import_module(f"{extension.__name__}.core.kernels")

    sun = Light("sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.5, -0.8]) / np.linalg.norm([0.3, 0.5, -0.8]))
    lamp = Light("lamp", "POINT", np.ones(3), 100.0, position=np.array([0.45, 0.55, 0.4]))

    def medium_of(n):
        # A unit cube whatever n: the same optical depths at every resolution.
        return make_medium("cloud", cloud(n), np.diag([1.0 / n, 1.0 / n, 1.0 / n, 1.0]), extinction=6.0)

    # Warm-up: the kernels load (or compile) and the shader compiles here, outside the timings.
    started = time.perf_counter()
    small = medium_of(16)
    for light in (sun, lamp):
        direct.transmittance(small, light)
    kernel_seconds = time.perf_counter() - started
    started = time.perf_counter()
    for light in (sun, lamp):
        direct.transmittance(small, light, sweep_pass=volume_sweep.sweep_transmittance)
    shader_seconds = time.perf_counter() - started

    rows = []
    for n in (int(side) for side in args.sizes.split(",")):
        medium = medium_of(n)
        for label, light in (("sun", sun), ("point lamp", lamp)):
            cpu_seconds, cpu = best_seconds(lambda: direct.transmittance(medium, light), args.repeats)
            gpu_seconds, gpu = best_seconds(
                lambda: direct.transmittance(medium, light, sweep_pass=volume_sweep.sweep_transmittance), args.repeats)
            rows.append({"grid": f"{n}^3", "light": label, "cpu_seconds": round(cpu_seconds, 4),
                         "gpu_seconds": round(gpu_seconds, 4), "gpu_over_cpu": round(gpu_seconds / cpu_seconds, 2),
                         "max_abs_difference": float(np.abs(gpu.astype(np.float64) - cpu).max()),
                         "min_transmittance": float(cpu.min())})

    print(f"GPU: {info.backend}, {info.renderer}; CPU kernel on {kernels.thread_count(0)} threads "
          f"({kernels.status().describe()})")
    print(f"warm-up on a 16^3 grid (not timed below): kernels {kernel_seconds:.2f} s, GPU pass with its "
          f"shader's compile {shader_seconds:.2f} s")
    print(f"{'grid':>6} {'light':>11} {'CPU s':>8} {'GPU s':>8} {'GPU/CPU':>8} {'max |diff|':>11} {'min T':>9}")
    for row in rows:
        print(f"{row['grid']:>6} {row['light']:>11} {row['cpu_seconds']:8.3f} {row['gpu_seconds']:8.3f} "
              f"{row['gpu_over_cpu']:8.2f} {row['max_abs_difference']:11.2e} {row['min_transmittance']:9.2e}")
    if args.out:
        from benchmarks.run import write_results

        write_results(args.out, {
            "gpu": {"backend": info.backend, "renderer": info.renderer, "vendor": info.vendor, "version": info.version},
            "cpu_threads": kernels.thread_count(0), "repeats": args.repeats, "rows": rows})
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
