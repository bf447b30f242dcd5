"""Relighting from the visibility cache, in real bpy: operators, the command line, light groups."""
import json
import os

import bpy

import numpy as np
import pytest

from bpy_scenes import assert_same_light, black_world, cube, grid, image_pixels, material, mesh_object, point, sun


@pytest.fixture
def room(clean_scene, tmp_path):
    """A saved scene: ground, a block, a sun and a lamp; its cache goes beside the .blend."""
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    point(80.0, (0.6, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution = 32, 1, 24
    props.passes = {"lighting", "indirect"}
    props.bake_all = True
    path = tmp_path / "room.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return ground, block, path


def _last_report(visibake):
    return json.loads(bpy.context.scene["visibake_report"])


def _bake(operator="bake"):
    return getattr(bpy.ops.visibake, operator)()


def test_second_bake_reuses_the_cache_and_relight_matches_a_fresh_bake(visibake, room, tmp_path):
    ground, block, path = room
    assert _bake() == {"FINISHED"}
    first = _last_report(visibake)
    assert first["cache"]["state"] == "miss"
    cache_dir = tmp_path / "visibake_cache"
    assert cache_dir.is_dir() and first["cache"]["path"].startswith(str(cache_dir))
    # Only the lamp changes: Relight reuses the preparation the bake kept in memory, and traces
    # no visibility ray.
    bpy.data.objects["Lamp"].data.energy = 160.0
    assert _bake("relight") == {"FINISHED"}
    again = _last_report(visibake)
    assert again["cache"]["state"] == "resident" and again["rays"]["visibility_cast"] == 0
    assert any(s.startswith("samples and visibility: geometry, materials and settings unchanged")
               for s in again["skipped"])
    assert "visibility" not in again["stage_seconds"]
    relit = image_pixels("VB_Ground_lighting")
    # With nothing kept in memory, Relight reads the table back from the cache: the same numbers.
    bpy.context.preferences.addons[visibake.__name__].preferences.resident_memory_mib = 0
    bpy.data.objects["Lamp"].data.energy = 150.0
    assert _bake("relight") == {"FINISHED"}
    bpy.data.objects["Lamp"].data.energy = 160.0
    assert _bake("relight") == {"FINISHED"}
    again = _last_report(visibake)
    assert again["cache"]["state"] == "hit" and again["rays"]["visibility_cast"] == 0
    assert_same_light(relit, image_pixels("VB_Ground_lighting"))
    # The same numbers as a bake that traces everything anew.
    bpy.context.scene.visibake.use_cache = False
    assert _bake() == {"FINISHED"}
    assert _last_report(visibake)["rays"]["visibility_cast"] > 0
    assert_same_light(relit, image_pixels("VB_Ground_lighting"))


def test_relight_refuses_after_a_move_and_changes_nothing(visibake, room):
    ground, block, path = room
    assert _bake() == {"FINISHED"}
    before = image_pixels("VB_Ground_lighting")
    block.location.x += 0.2
    with pytest.raises(RuntimeError, match="Block"):
        _bake("relight")
    np.testing.assert_array_equal(before, image_pixels("VB_Ground_lighting"))
    # A bake updates the table: only rays that touch the block are traced again.
    assert _bake() == {"FINISHED"}
    report = _last_report(visibake)
    assert report["cache"]["state"] == "updated" and report["cache"]["changed_objects"] == ["Block"]
    assert any("visibility of unchanged objects" in line for line in report["skipped"])
    updated = image_pixels("VB_Ground_lighting")
    bpy.context.scene.visibake.use_cache = False
    assert _bake() == {"FINISHED"}
    assert_same_light(updated, image_pixels("VB_Ground_lighting"))


def test_a_modifier_change_invalidates_the_cache(visibake, room):
    ground, block, path = room
    assert _bake() == {"FINISHED"}
    modifier = block.modifiers.new("Bevel", "BEVEL")
    modifier.width = 0.05
    assert _bake() == {"FINISHED"}
    report = _last_report(visibake)
    assert report["cache"]["state"] == "updated" and "Block" in report["cache"]["changed_objects"]
    # Not a silent hit: the next bake of the unchanged scene is.
    assert _bake() == {"FINISHED"}
    assert _last_report(visibake)["cache"]["state"] == "hit"


def test_a_new_direction_count_is_a_cache_miss(visibake, room):
    assert _bake() == {"FINISHED"}
    bpy.context.scene.visibake.directions = 48
    with pytest.raises(RuntimeError, match="bake first"):
        _bake("relight")
    assert _bake() == {"FINISHED"}
    assert _last_report(visibake)["cache"]["state"] == "miss"


def test_light_groups_write_per_group_images_that_sum_to_the_total(visibake, room):
    ground, block, path = room
    bpy.data.objects["Sun"].lightgroup = "Key"
    bpy.context.scene.visibake.light_groups = True
    assert _bake() == {"FINISHED"}
    total = image_pixels("VB_Ground_lighting")
    key = image_pixels("VB_Ground_lighting_Key")
    lamp = image_pixels("VB_Ground_lighting_Lamp")
    np.testing.assert_allclose(key[..., :3] + lamp[..., :3], total[..., :3], rtol=1e-5, atol=1e-7)
    # Both groups light the ground (the sun not under the block), and differently.
    assert np.mean(key[..., 0] > 0) > 0.5 and np.mean(lamp[..., 0] > 0) > 0.5
    assert np.any(lamp[..., :3] != key[..., :3])
    # Re-lighting after the lamp alone changed transports only the lamp's group.
    bpy.data.objects["Lamp"].data.energy = 40.0
    assert _bake("relight") == {"FINISHED"}
    assert _last_report(visibake)["cache"]["lighting_reused"] == ["Key"]
    np.testing.assert_array_equal(key, image_pixels("VB_Ground_lighting_Key"))


def test_cli_relight_with_setups_writes_one_folder_per_setup(visibake, room, tmp_path, capfd):
    ground, block, path = room
    cache_dir = tmp_path / "cache"
    common = ["--directions", "32", "--resolution", "24", "--bounces", "1", "--no-progress",
              "--cache-dir", str(cache_dir)]
    assert visibake.cli.main(["relight", str(path), "--out", str(tmp_path / "none"), *common]) == 2
    assert "bake first" in capfd.readouterr().err
    assert visibake.cli.main(["bake", str(path), "--out", str(tmp_path / "base"), *common]) == 0
    setups = {"setups": [
        {"name": "sun only", "lights": [{"object": "Sun"}]},
        {"name": "warm lamp", "lights": [{"object": "Lamp", "strength": 200, "color": [1, 0.5, 0.2]}],
         "world": {"color": [0.1, 0.1, 0.2], "strength": 1}},
        {"name": "new sun", "lights": [{"type": "SUN", "strength": 2, "elevation": 30, "azimuth": 90}]},
    ]}
    setups_path = tmp_path / "setups.json"
    setups_path.write_text(json.dumps(setups))
    report_path = tmp_path / "relight.json"
    out = tmp_path / "setups"
    assert visibake.cli.main(["relight", str(path), "--out", str(out), "--setups", str(setups_path),
                              "--report", str(report_path), *common]) == 0
    report = json.loads(report_path.read_text())
    assert report["cache"]["state"] == "hit" and report["rays"]["visibility_cast"] == 0
    assert [s["name"] for s in report["setups"]] == ["sun only", "warm lamp", "new sun"]
    import OpenEXR

    def read(folder):
        with OpenEXR.File(str(folder / "Ground" / "lighting.exr")) as exr:
            return exr.channels()["RGBA"].pixels

    base = read(tmp_path / "base")
    sun_only, warm, new_sun = read(out / "sun only"), read(out / "warm lamp"), read(out / "new sun")
    for image in (sun_only, warm, new_sun):
        assert np.all(np.isfinite(image)) and image[..., :3].max() > 0
    # The scene's bake has both lamps; lighting is linear in the lamps, and the
    # "sun only" setup is the scene's sun alone.
    assert np.all(base[..., :3] >= sun_only[..., :3] - 1e-6)
    assert warm[..., 0].mean() > warm[..., 2].mean()  # the warm lamp is red-heavy
    # Bad setups: exit 2 with the place of the mistake.
    setups_path.write_text(json.dumps({"setups": [{"name": "x", "lights": [{"object": "Nope"}]}]}))
    assert visibake.cli.main(["relight", str(path), "--out", str(out), "--setups", str(setups_path), *common]) == 2
    assert "setups[0].lights[0].object" in capfd.readouterr().err


def test_cli_sun_sweep(visibake, room, tmp_path):
    ground, block, path = room
    out = tmp_path / "sweep"
    report_path = tmp_path / "sweep.json"
    assert visibake.cli.main(["bake", str(path), "--out", str(out), "--sun-sweep", "4:20:5", "--latitude", "50",
                              "--report", str(report_path), "--directions", "32", "--resolution", "24",
                              "--no-progress", "--passes", "direct"]) == 0
    report = json.loads(report_path.read_text())
    names = [s["name"] for s in report["setups"]]
    assert names == ["sun_0400", "sun_0800", "sun_1200", "sun_1600", "sun_2000"]
    import OpenEXR
    means = {}
    for name in names:
        with OpenEXR.File(str(out / name / "Ground" / "direct.exr")) as exr:
            means[name] = float(exr.channels()["RGBA"].pixels[..., 0].mean())
    # Midsummer at 50 degrees north: the sun is up at 08:00 to 16:00 and highest at noon;
    # the lamp lights the ground in every setup.
    assert means["sun_1200"] > means["sun_0800"] > means["sun_0400"]
    assert means["sun_0800"] == pytest.approx(means["sun_1600"], rel=0.05)


def test_a_damaged_cache_file_is_reported_and_rebuilt(visibake, room):
    # Relight must read the damaged file, not a preparation kept in memory.
    bpy.context.preferences.addons[visibake.__name__].preferences.resident_memory_mib = 0
    assert _bake() == {"FINISHED"}
    path = _last_report(visibake)["cache"]["path"]
    with open(path, "r+b") as handle:  # a bit flipped in the middle of the table
        handle.seek(os.path.getsize(path) // 2)
        byte = handle.read(1)
        handle.seek(-1, os.SEEK_CUR)
        handle.write(bytes([byte[0] ^ 0x01]))
    # The lighting of the unchanged scene is cached and needs no table; a changed lamp
    # makes the transport read it, and the damage is found.
    bpy.data.objects["Lamp"].data.energy = 120.0
    with pytest.raises(RuntimeError, match="damaged"):
        _bake("relight")  # never trusted, not even by Relight
    assert _bake() == {"FINISHED"}
    report = _last_report(visibake)
    assert report["cache"]["state"] == "corrupt"
    assert any("it was rebuilt" in w for w in report["warnings"])
    rebuilt = image_pixels("VB_Ground_lighting")
    bpy.context.scene.visibake.use_cache = False
    assert _bake() == {"FINISHED"}  # a fresh trace, no cache at all
    assert_same_light(rebuilt, image_pixels("VB_Ground_lighting"))
    bpy.context.scene.visibake.use_cache = True
    bpy.data.objects["Lamp"].data.energy = 90.0
    assert _bake() == {"FINISHED"}
    assert _last_report(visibake)["cache"]["state"] == "hit"
