"""An HDR world image holding infinite or NaN texels (issue 51, item 11): they light nothing,
and the bake says so, naming the image and how many, through the command and the panel."""
import json

import bpy

import numpy as np
import OpenEXR  # pinned (requirements.txt): writes the test's HDR image
import pytest

from bpy_scenes import grid, material, mesh_object


def sky_blend(tmp_path, bad_texels: int):
    """A ground under an Environment Texture world of a grey EXR with ``bad_texels`` +Inf texels
    (and one NaN where there are two or more), saved as sky.blend."""
    pixels = np.full((16, 32, 3), 0.5, np.float32)
    if bad_texels:
        pixels.reshape(-1, 3)[7:7 + bad_texels] = np.inf
    if bad_texels > 1:
        pixels[12, 20] = (np.nan, 0.5, 0.5)
        pixels.reshape(-1, 3)[7] = (np.inf, 0.5, 0.5)  # a texel counts once, whichever channels are bad
    path = tmp_path / "sky.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": pixels}) as exr:
        exr.write(str(path))
    bpy.ops.wm.read_homefile(use_empty=True)
    world = bpy.data.worlds.new("Sky")
    world.use_nodes = True
    tree = world.node_tree
    texture = tree.nodes.new("ShaderNodeTexEnvironment")
    texture.image = bpy.data.images.load(str(path))
    tree.links.new(texture.outputs["Color"], tree.nodes["Background"].inputs["Color"])
    bpy.context.scene.world = world
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    blend = tmp_path / "sky.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    return blend


def _bake(visibake, blend, tmp_path):
    report = tmp_path / "report.json"
    assert visibake.cli.main(["bake", str(blend), "--out", str(tmp_path / "out"), "--report", str(report),
                              "--resolution", "16", "--directions", "16", "--bounces", "0", "--no-cache",
                              "--no-progress"]) == 0
    return json.loads(report.read_text())


@pytest.mark.parametrize("bad_texels, said", [(1, "has 1 texel that is infinite or NaN"),
                                              (3, "has 4 texels that are infinite or NaN")])
def test_the_bake_warns_naming_the_world_image_and_its_bad_texels(visibake, clean_scene, tmp_path, bad_texels, said):
    report = _bake(visibake, sky_blend(tmp_path, bad_texels), tmp_path)
    notes = [warning for warning in report["warnings"] if "sky.exr" in warning]
    assert notes == [f"world: image 'sky.exr' {said}; they light nothing (replace them with finite values to keep "
                     "their light)"], report["warnings"]
    # The rest of the world still lights the ground.
    assert report["objects"][0]["output"]


def test_a_finite_world_image_gives_no_such_warning(visibake, clean_scene, tmp_path):
    report = _bake(visibake, sky_blend(tmp_path, 0), tmp_path)
    assert not [warning for warning in report["warnings"] if "infinite" in warning], report["warnings"]


def test_the_panel_s_bake_warns_too(visibake, clean_scene, tmp_path):
    bpy.ops.wm.open_mainfile(filepath=str(sky_blend(tmp_path, 1)))
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.use_cache = 16, 0, False
    bpy.data.objects["Ground"].select_set(True)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    warnings = json.loads(bpy.context.scene["visibake_report"])["warnings"]
    assert any("image 'sky.exr' has 1 texel that is infinite or NaN" in warning for warning in warnings), warnings
