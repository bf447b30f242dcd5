"""How far the GPU direct-light pass is from its numpy twin, case by case.

    .venv/bin/python benchmarks/gpu_direct_twin.py [--out benchmarks/results/gpu_direct_twin.json]

The cases of ``tests/gpu/test_direct_twin.py`` (every lamp kind over the open and the
box scene, both shadow modes, and all lamps at once), built by that test module's own
helpers so that the figures are those of the inputs the test checks. The test asserts
the tolerance (1e-4 relative plus 1e-5 of the largest value); this records, for each
case, the largest difference as a share of the largest value, the largest relative
difference among values above 1e-3 of the largest, the samples, the shadow rays and
the seconds both passes took together.

Needs a GPU context (any OpenGL 4.3 or Vulkan device; Mesa's llvmpipe will do).
Writes the JSON with the machine, the GPU and the date, and prints a table.
"""
import argparse
import importlib
import importlib.util
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
TEST_MODULE = os.path.join(ROOT, "tests", "gpu", "test_direct_twin.py")

import numpy as np  # noqa: E402


def _test_helpers():
    spec = importlib.util.spec_from_file_location("gpu_direct_twin_cases", TEST_MODULE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _measure(twin_module, extension, direct, p, lights) -> dict:
    started = time.perf_counter()
    ours, _, twin, twin_rays = twin_module.evaluate(extension, direct, p, lights)
    seconds = time.perf_counter() - started
    peak = float(np.abs(twin).max())
    difference = np.abs(ours - twin)
    above = twin > 1e-3 * peak
    relative = difference[above] / np.abs(twin[above])
    return {"samples": len(p.position), "shadow_rays": int(twin_rays), "peak": peak,
            "max_diff_of_max": float(difference.max() / peak) if peak > 0 else None,
            "max_relative_diff": float(relative.max()) if relative.size else None,
            "seconds_both_passes": round(seconds, 4)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "gpu_direct_twin.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import write_results
    from tools.visibake import load_extension

    extension = load_extension()
    runtime = importlib.import_module(f"{extension.__name__}.gpu_shaders.runtime")
    try:
        info = runtime.device_info()
    except runtime.GPUUnavailable as error:
        print(f"no GPU context on this machine: {error}", file=sys.stderr)
        return 1
    direct = importlib.import_module(f"{extension.__name__}.gpu_shaders.direct")
    cases = _test_helpers()
    core = extension.core

    prepared = {}
    results = {}
    for shadows in ("exact", "fractions"):
        for scene in cases.SCENES:
            prepared[scene, shadows] = cases.prepare_scene(core, scene, shadows)
            spec = cases.SCENES[scene]
            for kind in cases.KINDS:
                if (kind, scene) == ("sun", "box"):  # no sunlight in a closed box, as in the test
                    continue
                light = cases._light(core, kind, spec["height"], spec["area_scale"], spec["spot_aim"])
                label = f"{kind} {scene} {shadows}"
                results[label] = _measure(cases, extension, direct, prepared[scene, shadows], [light])
        lights = [cases._light(core, kind, 1.2) for kind in cases.KINDS]
        lights.append(cases._light(core, "sun", 1.2))
        lights[-1].direction = cases._unit([-0.4, 0.1, -1.0])
        results[f"all lamps {shadows}"] = _measure(cases, extension, direct, prepared["open", shadows], lights)

    for label, row in sorted(results.items()):
        print(f"{label:32s} |diff|/max {row['max_diff_of_max']:.2e}  relative {row['max_relative_diff']:.2e}  "
              f"{row['samples']} samples, {row['shadow_rays']} shadow rays, {row['seconds_both_passes']:.3f} s")
    write_results(args.out, {
        "gpu": {"backend": info.backend, "renderer": info.renderer, "vendor": info.vendor, "version": info.version},
        "tolerance": {"rtol": cases.RTOL, "atol_of_max": cases.ATOL_OF_MAX}, "cases": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
