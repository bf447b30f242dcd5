"""Packaging: the manifest, the built zip, and the extension installed in bpy."""

import importlib
import json
import os
import re
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

from blender_support import (
    REPO_ROOT,
    ensure_built_zip,
    extension_site_packages,
    load_manifest,
    operator_exists,
)

DEV_DIRS = ("tests/", "benchmarks/", "tools/")
NEVER_SHIPPED = DEV_DIRS + ("docs/", ".ci/", ".venv/", "dist/", "out/", ".git", "Makefile", "requirements")
# What the extension's code imports from its wheels; tests/blender/test_extension.py's last
# test imports every top-level module of every installed wheel, these included.
BUNDLED_MODULES = ("xatlas", "embreex", "OpenEXR", "tqdm", "threadpoolctl", "numba", "llvmlite", "dask",
                   "distributed")


def _wheel_names(manifest):
    return [Path(w).name for w in manifest["wheels"]]


def test_manifest_identity():
    manifest = load_manifest()
    assert manifest["id"] == "visibake"
    assert manifest["type"] == "add-on"
    assert manifest["schema_version"] == "1.0.0"
    assert set(manifest["platforms"]) == {"linux-x64", "windows-x64", "macos-arm64"}


def test_manifest_lists_exactly_the_downloaded_wheels():
    manifest = load_manifest()
    assert all(w.startswith("./wheels/") for w in manifest["wheels"])
    on_disk = sorted(p.name for p in (REPO_ROOT / "wheels").glob("*.whl"))
    assert sorted(_wheel_names(manifest)) == on_disk


def test_manifest_wheels_match_pins_one_per_platform():
    pins = dict(
        re.findall(r"^([A-Za-z0-9_.-]+)==(\S+)", (REPO_ROOT / "requirements-wheels.txt").read_text(), re.M)
    )
    def normal(name):  # PEP 503: a wheel's file name writes lazy-importer as lazy_importer
        return re.sub(r"[-_.]+", "-", name).lower()

    pins = {normal(name): version for name, version in pins.items()}
    platform_tag = {"linux-x64": "manylinux", "windows-x64": "win_amd64", "macos-arm64": "macosx"}
    found = set()
    for wheel in _wheel_names(load_manifest()):
        dist, version, *_ = wheel.split("-")
        assert pins.get(normal(dist)) == version, f"{wheel} does not match requirements-wheels.txt"
        if wheel.endswith("-none-any.whl"):
            # A pure-Python wheel (py3 or py2.py3) serves every platform.
            found.update((normal(dist), p) for p in platform_tag)
            continue
        (platform,) = [p for p, tag in platform_tag.items() if tag in wheel]
        found.add((normal(dist), platform))
    assert found == {(d, p) for d in pins for p in platform_tag}


def test_manifest_build_excludes_dev_dirs():
    patterns = load_manifest()["build"]["paths_exclude_pattern"]
    for d in DEV_DIRS:
        assert d in patterns or "/" + d in patterns


def test_zip_ships_package_and_wheels_only():
    names = zipfile.ZipFile(ensure_built_zip()).namelist()
    leaked = [n for n in names if n.startswith(NEVER_SHIPPED) or "__pycache__" in n]
    assert not leaked
    assert "blender_manifest.toml" in names
    assert "__init__.py" in names
    wheels = {f"wheels/{w}" for w in _wheel_names(load_manifest())}
    assert wheels <= set(names)
    assert not [n for n in names if n.startswith("wheels/") and n not in wheels]


def test_bake_operator_registered(visibake):
    assert operator_exists("visibake.bake")


def test_extension_module_name(visibake):
    assert visibake.__name__ == "bl_ext.user_default.visibake"
    assert Path(visibake.__file__).is_relative_to(extension_site_packages().parents[3])


def test_bundled_wheels_importable(visibake):
    # In-process, as the extension's code would import them.
    for name in BUNDLED_MODULES:
        importlib.import_module(name)


def test_bundled_wheels_installed_by_blender(visibake, tmp_path):
    # Blender appends its wheel folder to sys.path, after the venv's copies, so prove the
    # installed wheels themselves work: a fresh bpy process (same user profile) with that
    # folder first on sys.path, importing and running each one.
    site = extension_site_packages()
    assert site.is_dir()
    script = textwrap.dedent(
        """
        import json, os, sys
        import bpy  # sets up sys.path from BLENDER_USER_RESOURCES (inherited)
        import numpy as np
        site = sys.argv[1]
        assert site in sys.path, "Blender did not add its extension site-packages to sys.path"
        sys.path.remove(site)
        sys.path.insert(0, site)
        import xatlas, embreex, OpenEXR, tqdm, numba, llvmlite
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
        tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        _, indices, uvs = xatlas.parametrize(tri, np.array([[0, 1, 2]], np.uint32))
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, tri[None])
        hit = scene.run(np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0, 0, -1.0]], np.float32))
        exr = os.path.join(sys.argv[2], "t.exr")
        OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": np.ones((2, 2, 3), np.float32)}).write(exr)
        with OpenEXR.File(exr) as f:
            shape = list(f.channels()["RGB"].pixels.shape)
        doubled = numba.njit(lambda x: 2 * x)(np.arange(3.0))
        print(json.dumps({
            "files": {m.__name__: m.__file__ for m in (xatlas, embreex, OpenEXR, tqdm, numba, llvmlite)},
            "uvs": list(uvs.shape), "hit": int(hit[0]), "exr": shape, "numba": doubled.tolist(),
        }))
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script, str(site), str(tmp_path)],
        capture_output=True, text=True, timeout=300, env=os.environ.copy(),
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    for name, path in result["files"].items():
        assert Path(path).is_relative_to(site), f"{name} imported from {path}, not from {site}"
    assert result["uvs"] == [3, 2] and result["hit"] == 0 and result["exr"] == [2, 2, 3]
    assert result["numba"] == [0.0, 2.0, 4.0]


def test_every_bundled_wheel_imports_from_the_installed_extension_alone(visibake):
    """Each top-level module of each wheel Blender installed for the extension (dask,
    distributed and their dependencies included) imports in a fresh bpy process that cannot
    see the venv's site-packages, and a Dask client runs a task: a wheel missing from the
    manifest, or one that needs a package nobody bundled, fails here, not on a user's
    Blender. Blender's own modules (bpy, numpy, which Blender ships) are imported first."""
    site = extension_site_packages()
    script = textwrap.dedent(
        """
        import importlib, importlib.metadata, json, os, sys, sysconfig
        import bpy, numpy  # Blender ships these; their folder then leaves sys.path
        site = sys.argv[1]
        venv = {os.path.realpath(sysconfig.get_paths()[key]) for key in ("purelib", "platlib")}
        sys.path[:] = [site] + [p for p in sys.path if os.path.realpath(p) not in venv and p != site]
        shipped = {name.split(".")[0] for name in sys.modules}  # bpy, numpy and what they loaded
        names = set()
        for dist in importlib.metadata.distributions(path=[site]):
            for file in dist.files or ():
                top = file.parts[0]
                if top.endswith((".dist-info", ".data")) or top.startswith("__") or top == "bin":
                    continue
                if len(file.parts) == 1 and file.suffix in (".py", ".so", ".pyd"):
                    names.add(top.split(".")[0])
                elif len(file.parts) == 2 and file.name == "__init__.py":
                    names.add(top)
        for name in sorted(names):
            importlib.import_module(name)
        import dask
        from distributed import Client
        with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as client:
            doubled = client.submit(lambda x: 2 * x, 21).result(timeout=60)
        files = {m: getattr(sys.modules[m], "__file__", None) for m in sys.modules if m.split(".")[0] not in shipped}
        print(json.dumps({"names": sorted(names), "files": files, "doubled": doubled,
                          "dask": dask.__file__}))
        """
    )
    proc = subprocess.run([sys.executable, "-c", script, str(site)], capture_output=True, text=True,
                          timeout=300, env=os.environ.copy())
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"\nimported from {site}: {', '.join(result['names'])} ({len(result['files'])} modules)")
    assert set(BUNDLED_MODULES) <= set(result["names"]), set(BUNDLED_MODULES) - set(result["names"])
    venv_site = Path(importlib.import_module("numpy").__file__).resolve().parents[1]
    from_venv = {m: f for m, f in result["files"].items() if f and Path(f).resolve().is_relative_to(venv_site)}
    assert not from_venv, f"imported from the venv, not from {site}: {sorted(from_venv)}"
    assert Path(result["dask"]).resolve().is_relative_to(site.resolve()) and result["doubled"] == 42
