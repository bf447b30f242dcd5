"""Under CI, the installed extension runs what the suite's skips would otherwise hide.

The compiled kernels of the *installed* extension (its own numba wheels, not the source
tree's), and Blender's openvdb on every Blender CI tests but 4.2, which ships none
(operators/adapter/compat.openvdb says so): without it the volume tests skip.
Outside CI (CI unset) these checks skip, as tests/expected_skips.toml allows there only.
"""
import importlib
import os

import bpy

import pytest

ci_only = pytest.mark.skipif(not os.environ.get("CI"), reason="checked under CI only (CI is not set)")


@ci_only
def test_the_installed_extension_s_compiled_kernels_load_in_ci(visibake):
    kernels = importlib.import_module(f"{visibake.__name__}.core.kernels")
    assert kernels.compiled() is not None, f"the numpy fallback runs: {kernels.status().reason}"


@ci_only
def test_openvdb_imports_on_every_blender_but_4_2_in_ci(visibake):
    if bpy.app.version[:2] == (4, 2):
        pytest.skip("Blender 4.2's bpy ships no openvdb module (volumes need 4.5 or later)")
    compat = importlib.import_module(f"{visibake.__name__}.operators.adapter.compat")
    try:
        vdb = compat.openvdb()
    except compat.FeatureMissing as missing:
        pytest.fail(f"the volume tests would all skip: {missing}")
    grid = vdb.FloatGrid()
    grid.name = "density"
    assert grid.name == "density"
