"""The panel draws from state computed outside draw code: no folder listing, file size
or mesh hash while it draws, and the state still follows bakes, edits and settings."""
import hashlib
import json
import os

import bpy

import pytest
from test_panels import CheckedLayout

from bpy_scenes import black_world, grid, material, mesh_object, select_only, sun


def _forbidden(name):
    def refuse(*args, **kwargs):
        raise AssertionError(f"draw code called {name}")
    return refuse


@pytest.fixture
def draw(visibake, monkeypatch):
    """Draw a panel class with every file-system and hashing call VisiBake could make
    refusing; returns the labels drawn."""
    cache_status = visibake.operators.adapter.cache_status
    job = visibake.operators.adapter.job

    def run(panel_class):
        drawn = []
        with monkeypatch.context() as patch:
            for module, names in ((os, ("listdir", "scandir", "stat", "walk", "makedirs", "mkdir")),
                                  (os.path, ("exists", "isdir", "isfile", "getsize")),
                                  (hashlib, ("blake2b", "sha256", "md5")),
                                  (cache_status, ("status", "fingerprint", "scene_slots", "validity_of")),
                                  (job, ("visibility_cache",))):
                for name in names:
                    patch.setattr(module, name, _forbidden(f"{module.__name__}.{name}"))
            panel = type("PanelStandIn", (), {"layout": CheckedLayout(drawn)})()
            panel_class.draw(panel, bpy.context)
        return [options.get("text", "") for name, options in drawn if name == "label"]

    return run


@pytest.fixture
def ground(visibake, clean_scene, tmp_path):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    sun(3.0)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 16, 1
    props.cache_dir = str(tmp_path / "cache")
    select_only([ground])
    return ground


def _cache_lines(labels):
    return [text for text in labels if text.startswith("Cache:")]


def test_the_cache_state_follows_bakes_edits_settings_and_clear_cache_without_draw_work(visibake, ground, draw):
    main = visibake.panels.main
    bpy.context.view_layer.update()  # the settings reach the panel through the depsgraph handler
    assert _cache_lines(draw(main.VIEW3D_PT_visibake)) == ["Cache: no table for these settings yet"]

    assert bpy.ops.visibake.bake() == {"FINISHED"}
    labels = draw(main.VIEW3D_PT_visibake)
    assert _cache_lines(labels)[0].startswith("Cache: valid for the scene as it is")
    assert any(text.startswith("VisiBake: baked 1 object(s)") for text in labels)
    report = json.loads(bpy.context.scene["visibake_report"])
    assert draw(main.VIEW3D_PT_visibake_report) == [text for text, _ in main.report_lines(report)]

    ground.location.x += 0.5
    bpy.context.view_layer.update()
    labels = draw(main.VIEW3D_PT_visibake)
    assert _cache_lines(labels)[0].startswith("Cache: stale") and "changed: Ground" in labels
    ground.location.x -= 0.5
    bpy.context.view_layer.update()
    assert _cache_lines(draw(main.VIEW3D_PT_visibake))[0].startswith("Cache: valid")

    props = bpy.context.scene.visibake
    props.directions = 24  # another slot, with no table yet
    bpy.context.view_layer.update()
    assert _cache_lines(draw(main.VIEW3D_PT_visibake)) == ["Cache: no table for these settings yet"]
    props.directions = 16
    bpy.context.view_layer.update()
    assert _cache_lines(draw(main.VIEW3D_PT_visibake))[0].startswith("Cache: valid")

    assert bpy.ops.visibake.clear_cache() == {"FINISHED"}
    labels = draw(main.VIEW3D_PT_visibake)
    assert _cache_lines(labels) == ["Cache: no table for these settings yet"]
    assert any(text.startswith("0 setting(s)") for text in labels)


def test_a_scene_without_a_status_gets_one_from_a_timer_after_the_draw(visibake, ground, draw, tmp_path):
    main = visibake.panels.main
    cache_status = visibake.operators.adapter.cache_status
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))  # the cache is named after the file
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    bpy.ops.wm.save_mainfile()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    # Opening the file computed the status of its scene: a table, unknown until the next bake.
    labels = draw(main.VIEW3D_PT_visibake)
    assert _cache_lines(labels)[0].endswith("(checked at the next bake)")

    other = bpy.data.scenes.new("Other")
    other.visibake.cache_dir = str(tmp_path / "cache")
    with bpy.context.temp_override(scene=other):
        assert _cache_lines(draw(main.VIEW3D_PT_visibake)) == ["Cache: looking at the cache folder..."]
        assert bpy.app.timers.is_registered(cache_status.refresh_requested)
        bpy.app.timers.unregister(cache_status.refresh_requested)  # no event loop here: run it by hand
        cache_status.refresh_requested()
        assert _cache_lines(draw(main.VIEW3D_PT_visibake)) == ["Cache: no table for these settings yet"]


def test_a_table_another_process_writes_shows_on_the_folder_timer(visibake, ground, draw, tmp_path):
    main = visibake.panels.main
    cache_status = visibake.operators.adapter.cache_status
    bpy.context.view_layer.update()
    assert _cache_lines(draw(main.VIEW3D_PT_visibake)) == ["Cache: no table for these settings yet"]
    # The command line bakes into the same folder (here in this process, without the operator).
    outcome = visibake.operators.adapter.job.run_bake(bpy.context, [ground])
    assert outcome.report["cache"]["state"] == "miss"
    assert cache_status._refresh_shown_folders() == cache_status.FOLDER_CHECK_SECONDS  # the timer runs again
    assert _cache_lines(draw(main.VIEW3D_PT_visibake))[0].startswith("Cache: table for these settings")
