"""The extension zip in every supported Blender: install, enable, bake the demo, compare.

    .venv/bin/python benchmarks/versions.py [--bpy 4.2.23,4.5.15,5.0.1,5.3.0] [--zip dist/visibake-0.1.0.zip]

For each version, that version's venv (``make venv BPY=X.Y.Z`` makes it) installs the
zip with ``bpy.ops.extensions.package_install_files`` into a throw-away user profile, as
a user would, enables it, and runs the extension's ``demo`` command (a headless bake of
the built-in demo scene, no cache). Then every ``lighting.exr`` is compared with the
first version's: the largest absolute difference, and the largest as a share of that
image's largest value. Writes ``benchmarks/results/versions.json`` with the machine and
the date.
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

DRIVER = r"""
import os, sys
import bpy
zip_path, out = sys.argv[1], sys.argv[2]
result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
assert result == {"FINISHED"}, result
import importlib
extension = importlib.import_module("bl_ext.user_default.visibake")
status = extension.cli.main(["demo", "--out", out, "--no-cache", "--no-progress"])
print("blender", bpy.app.version_string, "status", status, flush=True)
compat = importlib.import_module("bl_ext.user_default.visibake.operators.adapter.compat")
compat.end_module_process(status)
"""


def venv_python(version: str, default: str) -> str:
    folder = ".venv" if version == default else f".venv-bpy{version}"
    return os.path.join(ROOT, folder, "bin", "python")


def read_exr(path: str) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(path) as exr:
        return np.array(exr.channels()["RGBA"].pixels, np.float64)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bpy", default="4.2.23,4.5.15,5.0.1,5.3.0")
    parser.add_argument("--default", default="5.0.1", help="the version whose venv is .venv")
    parser.add_argument("--zip", default=os.path.join(ROOT, "dist", "visibake-0.1.0.zip"))
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "versions.json"))
    args = parser.parse_args()
    versions = args.bpy.split(",")
    work = tempfile.mkdtemp(prefix="visibake-versions-")
    runs = {}
    for version in versions:
        out = os.path.join(work, version)
        environment = dict(os.environ, BLENDER_USER_RESOURCES=os.path.join(work, f"user-{version}"))
        started = time.perf_counter()
        done = subprocess.run([venv_python(version, args.default), "-c", DRIVER, os.path.abspath(args.zip), out],
                              env=environment, capture_output=True, text=True)
        seconds = time.perf_counter() - started
        print(f"bpy {version}: exit {done.returncode} in {seconds:.1f} s", flush=True)
        if done.returncode != 0:
            print(done.stdout[-3000:], done.stderr[-3000:], file=sys.stderr)
            return 1
        runs[version] = {"seconds": round(seconds, 1), "folder": out}
    first = versions[0]
    images = sorted(os.path.relpath(os.path.join(folder, name), os.path.join(work, first))
                    for folder, _, names in os.walk(os.path.join(work, first)) for name in names
                    if name.endswith(".exr"))
    comparison = {}
    for version in versions[1:]:
        worst_absolute, worst_share, worst_image = 0.0, 0.0, ""
        for image in images:
            a = read_exr(os.path.join(work, first, image))
            b = read_exr(os.path.join(work, version, image))
            difference = float(np.abs(a - b).max())
            share = difference / max(float(np.abs(a).max()), 1e-30)
            worst_absolute = max(worst_absolute, difference)
            if share >= worst_share:
                worst_share, worst_image = share, image
        comparison[version] = {"max_abs_difference": worst_absolute, "max_share_of_image_max": worst_share,
                               "worst_image": worst_image}
        print(f"bpy {version} against {first}: {len(images)} images, max |difference| {worst_absolute:.3g}, "
              f"{worst_share:.3g} of the image's maximum ({worst_image})")
    from benchmarks.run import write_results

    write_results(args.out, {"zip": os.path.relpath(args.zip, ROOT), "reference_version": first, "runs": runs,
                             "images": images, "against_reference": comparison})
    return 0


if __name__ == "__main__":
    sys.exit(main())
