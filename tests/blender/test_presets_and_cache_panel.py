"""Presets, the cache status the panel shows, Clear Cache, and the cache-folder preference."""
import json
import os

import bpy

import pytest

from bpy_scenes import black_world, grid, material, mesh_object, select_only, sun


def test_presets_set_their_values_and_a_change_by_hand_makes_them_custom(clean_scene):
    props = bpy.context.scene.visibake
    props.preset = "DRAFT"
    assert (props.directions, props.bounces, props.resolution, props.shadows) == (64, 1, 128, "exact")
    props.preset = "PRODUCTION"
    assert (props.directions, props.bounces, props.resolution, props.rotate) == (256, 3, 512, True)
    props.bounces = 3  # unchanged value: still the preset
    assert props.preset == "PRODUCTION"
    props.directions = 300
    assert props.preset == "CUSTOM" and props.directions == 300 and props.bounces == 3


def test_cli_preset_then_explicit_options(visibake, clean_scene, tmp_path):
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    sun(3.0)
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    report = tmp_path / "report.json"
    assert visibake.cli.main(["bake", str(path), "--preset", "draft", "--directions", "40", "--resolution", "16",
                              "--report", str(report), "--no-progress", "--no-cache"]) == 0
    settings = json.loads(report.read_text())["settings"]
    assert settings["directions"] == 40 and settings["bounces"] == 1  # the option wins over the preset


@pytest.fixture
def baked_saved_scene(visibake, clean_scene, tmp_path):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    sun(3.0)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 16, 1
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return visibake


def test_cache_status_and_clear_cache(baked_saved_scene, tmp_path):
    cache_status = baked_saved_scene.operators.adapter.cache_status
    state = cache_status.status(bpy.context.scene)
    assert state["enabled"] and state["has_table"] and state["table_bytes"] > 0 and state["slots"] == 1
    assert state["folder"] == str(tmp_path / "visibake_cache")
    bystander = tmp_path / "visibake_cache" / "notes.txt"  # not VisiBake's: left alone
    bystander.write_text("mine")
    assert bpy.ops.visibake.clear_cache() == {"FINISHED"}
    state = cache_status.status(bpy.context.scene)
    assert not state["has_table"] and state["slots"] == 0
    assert bystander.read_text() == "mine"
    # Another direction count is another slot; the status follows the settings.
    bpy.context.scene.visibake.directions = 24
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert cache_status.status(bpy.context.scene)["has_table"]
    bpy.context.scene.visibake.directions = 16
    assert not cache_status.status(bpy.context.scene)["has_table"]


def test_the_cache_folder_preference(visibake, clean_scene, tmp_path):
    prefs = visibake.operators.adapter.device.preferences()
    assert prefs is not None
    prefs.cache_dir = str(tmp_path / "fast disk")
    try:
        black_world()
        ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
        sun(3.0)
        props = bpy.context.scene.visibake
        props.directions, props.resolution, props.bounces = 16, 16, 1
        select_only([ground])
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        report = json.loads(bpy.context.scene["visibake_report"])
        assert report["cache"]["path"].startswith(str(tmp_path / "fast disk"))
        # A scene's own folder still wins.
        props.cache_dir = str(tmp_path / "scene folder")
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        report = json.loads(bpy.context.scene["visibake_report"])
        assert report["cache"]["path"].startswith(str(tmp_path / "scene folder"))
    finally:
        prefs.cache_dir = ""
    assert os.path.isdir(tmp_path / "fast disk")


def test_the_default_preset_preference_sets_up_new_scenes_only(visibake, clean_scene, tmp_path):
    untouched_file = tmp_path / "untouched.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(untouched_file), copy=True)  # no VisiBake settings in it
    prefs = visibake.operators.adapter.device.preferences()
    prefs.default_preset = "DRAFT"
    touched = bpy.context.scene
    touched.visibake.directions = 300
    fresh = bpy.data.scenes.new("Fresh")
    visibake.panels.preferences.apply_default_preset_to_new_scenes()
    assert (fresh.visibake.preset, fresh.visibake.directions, fresh.visibake.bounces) == ("DRAFT", 64, 1)
    assert (touched.visibake.preset, touched.visibake.directions) == ("CUSTOM", 300)

    # Opening a file: its scenes without settings get the preset (the load_post handler)...
    bpy.ops.wm.open_mainfile(filepath=str(untouched_file))
    props = bpy.context.scene.visibake
    assert (props.preset, props.directions, props.resolution) == ("DRAFT", 64, 128)
    # ...and a scene with settings keeps them, preset and all.
    props.resolution = 100
    assert props.preset == "CUSTOM"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "touched.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "touched.blend"))
    props = bpy.context.scene.visibake
    assert (props.preset, props.directions, props.resolution) == ("CUSTOM", 64, 100)


def test_with_no_default_preset_new_scenes_keep_the_built_in_settings(visibake, clean_scene):
    assert visibake.operators.adapter.device.preferences().default_preset == "NONE"
    fresh = bpy.data.scenes.new("Fresh")
    visibake.panels.preferences.apply_default_preset_to_new_scenes()
    assert (fresh.visibake.preset, fresh.visibake.directions) == ("CUSTOM", 128)
    assert visibake.panels.properties.settings_untouched(fresh.visibake)


def test_the_cache_status_tells_valid_from_stale(baked_saved_scene):
    cache_status = baked_saved_scene.operators.adapter.cache_status
    scene = bpy.context.scene
    ground = bpy.data.objects["Ground"]

    def state():
        bpy.context.view_layer.update()  # runs the depsgraph handler, as the UI does on every change
        current = cache_status.status(scene)
        return current["validity"], current["reasons"]

    assert state() == ("valid", [])
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}  # materials are not in the table's key
    assert state() == ("valid", [])
    ground.location.x += 0.5
    assert state() == ("stale", ["changed: Ground"])
    ground.location.x -= 0.5
    assert state() == ("valid", [])  # fingerprinted again: as it was
    ground.data.vertices[0].co.z += 0.1
    ground.data.update()
    assert state() == ("stale", ["changed: Ground"])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert state() == ("valid", [])
    scene.visibake.resolution = 20
    assert state() == ("stale", ["resolution or mode changed"])
    scene.visibake.resolution = 16
    mesh_object("Extra", grid(0.2), location=(0, 0, 1))
    assert state() == ("stale", ["added: Extra"])
    bpy.data.objects["Extra"].hide_render = True
    assert state() == ("valid", [])
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=bpy.data.filepath)
    current = cache_status.status(bpy.context.scene)
    assert current["has_table"] and current["validity"] == "unknown"  # known again after the next bake
