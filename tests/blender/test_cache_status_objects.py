"""The cache status the panel shows for a baked object that leaves the bake: hidden from
renders or deleted, the cached table no longer matches the scene, and the reason names it."""
import bpy

import pytest

from bpy_scenes import black_world, cube, grid, material, mesh_object, select_only, sun


@pytest.fixture
def baked_pair(visibake, clean_scene, tmp_path):
    """Ground and Block baked with the cache on, beside a saved scene.blend."""
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.4), uv_map=None)
    sun(3.0)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 16, 1
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    select_only([ground, block])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return visibake.operators.adapter.cache_status


def _state(cache_status):
    bpy.context.view_layer.update()  # runs the depsgraph handler, as the UI does on every change
    current = cache_status.status(bpy.context.scene)
    assert current["has_table"]
    return current["validity"], current["reasons"]


def test_a_baked_object_hidden_from_renders_makes_the_table_stale_by_name(baked_pair):
    block = bpy.data.objects["Block"]
    assert _state(baked_pair) == ("valid", [])
    block.hide_render = True  # out of the bake, as for the bake itself (extract.scene_meshes)
    assert _state(baked_pair) == ("stale", ["removed or hidden: Block"])
    block.hide_render = False
    assert _state(baked_pair) == ("valid", [])
    # Hidden in the viewport only, it is still baked: nothing changes.
    block.hide_set(True)
    assert _state(baked_pair) == ("valid", [])


def test_a_deleted_baked_object_makes_the_table_stale_by_name(baked_pair):
    bpy.data.objects.remove(bpy.data.objects["Block"])
    assert _state(baked_pair) == ("stale", ["removed or hidden: Block"])
    # Baking what is left makes the table match the scene again.
    select_only([bpy.data.objects["Ground"]])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert _state(baked_pair) == ("valid", [])
