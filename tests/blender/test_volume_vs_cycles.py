"""`visibake volume` against Cycles (issue 51): benchmarks/volume_vs_cycles.py's scene and
measure, tiny. The cloud (a 16^3 VDB sphere, density 8, one volume bounce, a sun) is
path-traced by Cycles, and the baked emission-absorption volume rendered by Cycles from the
same camera, each twice with two seeds at 64 samples (64 x 64 px): seconds of Cycles.

Tolerances: docs/benchmarks.md (volume, part 1) measures 2.45 % relative RMSE with both
renders' noise and 0.71 % without at 64^3, 1024 samples, mean ratio 1.00. At 64 samples
each render's noise is about 5 %, so the error of the two seeds' means is judged beside
the noise those means keep: what the bake adds beyond it is at most 5 %, and the mean
brightness agrees within 3 %. Measured (2026-12-07): the means' relative RMSE 0.067 beside
their noise 0.066 under Cycles 5.0.1 (1.1 % added), 0.071 beside 0.065 under Cycles 5.3.0
(2.9 % added); 5 % is that with the margin of a 16^3 grid's coarser voxels, against the
documented 0.71 % at 64^3.
"""
import importlib

import numpy as np
import pytest

from benchmarks.volume_vs_cycles import build_scene, render
from blender_support import extension_module_name

ADDED_ERROR = 0.05
MEAN_RATIO = 0.03
SIDE = 16
SAMPLES = 64


def test_the_volume_command_agrees_with_cycles_path_tracing(visibake, clean_scene, tmp_path):
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    try:
        compat.openvdb()
    except compat.FeatureMissing as missing:
        pytest.skip(f"volumes need Blender's openvdb module: {missing}")
    blend = build_scene(str(tmp_path), 8.0, SIDE)
    baked_blend = str(tmp_path / "baked.blend")
    assert visibake.cli.main(["volume", blend, "--out", str(tmp_path / "grids"), "--resolution", str(SIDE),
                              "--directions", "64", "--bounces", "1", "--save", baked_blend, "--no-cache",
                              "--no-progress"]) == 0
    traced, again, baked, baked_again = (
        render(baked_blend, which, 1, SAMPLES, seed, str(tmp_path / f"{which}_{seed}.exr"))[0]
        for which, seed in (("source", 0), ("source", 7), ("baked", 0), ("baked", 7)))
    covered = traced.mean(axis=-1) > 0.01 * traced.max()
    assert covered.sum() > 100
    scale = traced[covered].mean()

    def relative_rms(difference):
        return float(np.sqrt((difference[covered] ** 2).mean()) / scale)

    traced_noise = relative_rms(traced - again) / np.sqrt(2)
    baked_noise = relative_rms(baked - baked_again) / np.sqrt(2)
    # The two seeds' means: their difference keeps half of each render's noise variance.
    error = relative_rms((baked + baked_again) / 2 - (traced + again) / 2)
    ratio = float(baked[covered].mean() / scale)
    print(f"\nvolume vs Cycles: relative RMSE {error:.4f}, noise {traced_noise:.4f} (path-traced) and "
          f"{baked_noise:.4f} (baked), mean ratio {ratio:.4f}")
    assert error ** 2 <= (traced_noise ** 2 + baked_noise ** 2) / 2 + ADDED_ERROR ** 2
    assert abs(ratio - 1.0) < MEAN_RATIO
