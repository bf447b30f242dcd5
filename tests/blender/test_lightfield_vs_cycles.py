"""`visibake lightfield` against Cycles (issue 51): benchmarks/lightfield_vs_cycles.py's check
of the views' cameras, off-axis shift and pixel filter, tiny. A baked plane (the scene of
test_lightfield_command.py: a lit ground, a small emitter, 3 x 3 views of 64 x 64 px) and
Cycles rendering the same baked textures (emission only, no lamps) from the camera of a
corner view, whose shift is the largest.

Tolerance: docs/lightfield/lightfield_vs_cycles.json measures the light field against Cycles
of the same baked textures at 0.18 % relative RMSE on 4 x 4-pixel blocks (0.52 % per pixel)
on the demo at 256^2. Here 4 x 4 blocks of a 64 x 64 image, 256 Cycles samples (its
anti-aliasing noise measured from two seeds, beside it): within 1 % beyond that noise away
from the small emitter's blocks and their neighbours (measured under 0.01 %); the emitter at
Cycles' place within 0.1 px (measured 0.03 px) and its light within 10 % (measured 4 %).
"""
import importlib
import json

import bpy

import numpy as np
from test_lightfield_command import BASELINE_MM, FAST_BAKE, FOCUS_M, bright_centroid, grid_options, plane_scene

from benchmarks.lightfield_vs_cycles import (
    BLOCK,
    BakedMaterials,
    blocks,
    cycles_render,
    read_exr,
    relative_rmse,
    view_camera,
    without,
)
from blender_support import extension_module_name

BLOCK_ERROR = 0.01
EMITTER_FLUX = 0.1
SAMPLES = 256
SIZE = 64  # square: cycles_render renders size x size


def test_a_corner_view_of_the_lightfield_command_is_what_cycles_renders_of_the_baked_textures(
        visibake, clean_scene, tmp_path):
    name = extension_module_name()
    hci = importlib.import_module(name + ".core.lightfield.hci")
    lightfield_io = importlib.import_module(name + ".operators.adapter.lightfield_io")
    uv_map = importlib.import_module(name + ".operators.adapter.layout").UV_MAP_NAME
    blend, saved = plane_scene(tmp_path / "scene.blend"), tmp_path / "baked.blend"
    out, report_path = tmp_path / "lightfield", tmp_path / "report.json"
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(out), "--bake-first", "--report",
                              str(report_path), "--save", str(saved)]
                             + grid_options(size=f"{SIZE}x{SIZE}") + FAST_BAKE) == 0
    report = json.loads(report_path.read_text())
    assert report["objects"]["atlas"] == ["Ground", "Square"]
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    scene = bpy.context.scene
    camera, _, views, clip = lightfield_io.plan_views(scene, None, (3, 3), BASELINE_MM, FOCUS_M, (SIZE, SIZE), [])
    corner = views[0]
    assert corner.shift_x != 0 and corner.shift_y != 0
    objects = [scene.objects[name] for name in report["objects"]["atlas"]]
    # The bake's UV map: its own, or the mesh's where that one was fit to bake (as here).
    uv_maps = {obj.name: uv_map if uv_map in obj.data.uv_layers else obj.data.uv_layers.active.name
               for obj in objects}
    baked = BakedMaterials(visibake, objects, uv_maps)
    try:
        halves = [cycles_render(view_camera(corner, camera, clip), SIZE, SAMPLES // 2, seed, 0,
                                str(tmp_path / f"cycles_{seed}.exr"))[0] for seed in (1, 2)]
    finally:
        baked.close()
    reference = 0.5 * (halves[0] + halves[1])
    ours = read_exr(str(out / hci.view_file_name(corner.index, ".exr")))
    assert ours.shape == reference.shape == (SIZE, SIZE, 3)
    # The emitter (1.7 px wide, 13 times the ground's radiance) apart: the light field samples
    # a pixel 3 x 3 times, so its edges fall to 1/3 px and its area within some 10 %, which
    # on blocks this bright outweighs the rest. Its place and its light are checked instead.
    levels = blocks(reference).mean(axis=-1)
    bright = np.pad(levels > 3 * np.median(levels), 1)
    near = np.any([np.roll(bright, (dy, dx), (0, 1)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)[1:-1, 1:-1]
    emitter = np.kron(near, np.ones((BLOCK, BLOCK), bool))  # its blocks and their neighbours (the filter's spill)
    assert 0 < emitter.sum() < emitter.size // 10
    ground = np.where(emitter[..., None], 0.0, 1.0)
    error = relative_rmse(ours * ground, reference * ground)
    noise = relative_rmse(halves[0] * ground, halves[1] * ground) / 2  # of the two halves' mean
    flux = ours[emitter].sum() / reference[emitter].sum()
    shift = np.subtract(bright_centroid(ours), bright_centroid(reference))
    print(f"\nlight field corner view vs Cycles of the baked textures: block relative RMSE {error:.4f} off the "
          f"emitter, Cycles' noise {noise:.4f}; the emitter's light {flux:.3f} of Cycles', moved {shift} px")
    assert without(error, noise) < BLOCK_ERROR
    assert abs(flux - 1.0) < EMITTER_FLUX
    assert np.all(np.abs(shift) < 0.1)
