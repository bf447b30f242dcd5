"""Hostile input, issue 14 class 3: destinations checked before any work, late failures rolled
back, and inputs that used to give tracebacks (unreadable .blend files, numbers beyond range,
conflicting options). Through the command line and the operator."""
import json
import os

import bpy

import numpy as np
import pytest

from bpy_scenes import black_world, cube, grid, image_pixels, material, mesh_object, point, select_only


def _read_only_folder(tmp_path) -> str:
    from test_destinations import read_only_folder  # tests/core, on the path (tests/conftest.py)

    return read_only_folder(tmp_path)


@pytest.fixture
def scene_file(clean_scene, tmp_path):
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    path = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


SMALL = ["--directions", "16", "--bounces", "1", "--no-progress"]
SIXTEEN = ["--resolution", "16"]


def _refused(visibake, capfd, arguments) -> str:
    """The one line the command printed when refusing ``arguments`` with exit status 2."""
    capfd.readouterr()
    status = visibake.cli.main([str(a) for a in arguments])
    err = capfd.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("visibake: error: ")
    return lines[0]


def _visibake_leftovers() -> list[str]:
    """What a bake leaves in the open file: VisiBake's UV maps and images, VB_ attributes."""
    found = [f"image {i.name}" for i in bpy.data.images if i.name.startswith("VB_")]
    for mesh in bpy.data.meshes:
        found += [f"uv {mesh.name}/{layer.name}" for layer in mesh.uv_layers if layer.name == "VisiBake"]
        found += [f"attribute {mesh.name}/{a.name}" for a in mesh.attributes if a.name.startswith("VB_")]
    return found


def _tree(path) -> list[str]:
    return sorted(os.path.relpath(os.path.join(root, name), path)
                  for root, folders, files in os.walk(path) for name in folders + files)


# --- unreadable .blend files ----------------------------------------------------------------

@pytest.mark.parametrize("content", [b"", b"this is a text file, not a blend\n"], ids=["empty", "text"])
@pytest.mark.parametrize("command", [["bake"], ["relight"], ["preview", "--save", "{out}"], ["clear-cache"]])
def test_an_unreadable_blend_is_refused_with_one_line(visibake, clean_scene, capfd, tmp_path, content, command):
    path = tmp_path / "broken.blend"
    path.write_bytes(content)
    arguments = [command[0], path] + [a.format(out=tmp_path / "out.blend") for a in command[1:]]
    line = _refused(visibake, capfd, arguments)
    assert "not a readable .blend file" in line and "broken.blend" in line
    assert not (tmp_path / "out.blend").exists()


# --- numbers and options ---------------------------------------------------------------------

HUGE = "99999999999999999999"


@pytest.mark.parametrize("option, value, named", [
    ("--directions", HUGE, "--directions"), ("--seed", HUGE, "--seed"), ("--resolution", HUGE, "--resolution"),
    ("--margin", HUGE, "--margin"), ("--threads", HUGE, "--threads"), ("--bounces", HUGE, "--bounces"),
    ("--bounces", "100000", "Cycles' limit"), ("--bounces", "1025", "1024"),
    ("--texel-density", "1e400", "finite"), ("--texel-density", "nan", "--texel-density"),
    ("--directions", "-" + HUGE, "--directions"),
])
def test_numbers_beyond_range_are_refused_before_the_bake(visibake, scene_file, capfd, tmp_path, option, value,
                                                          named):
    cache = tmp_path / "cache"
    line = _refused(visibake, capfd, ["bake", scene_file, "--cache-dir", cache, *SMALL, option, value])
    assert named in line
    assert not cache.exists()


@pytest.mark.parametrize("arguments, named", [
    (["--sun-sweep", f"6:18:{HUGE}"], "at most 1440 steps"), (["--day", HUGE, "--sun-sweep", "6:18:3"], "--day"),
    (["--latitude", "1e400", "--sun-sweep", "6:18:3"], "--latitude"),
])
def test_sun_sweep_numbers_beyond_range_are_refused(visibake, scene_file, capfd, tmp_path, arguments, named):
    line = _refused(visibake, capfd, ["bake", scene_file, *SMALL, *SIXTEEN, "--out", tmp_path / "out", *arguments])
    assert named in line


def test_threads_beyond_the_machine_are_refused_and_the_preference_offers_no_more(visibake, scene_file, capfd):
    cores = os.cpu_count()
    assert visibake.core.settings.CPU_COUNT == cores
    line = _refused(visibake, capfd, ["bake", scene_file, *SMALL, *SIXTEEN, "--threads", cores + 1])
    assert f"<= {cores}" in line and "cores" in line
    prefs = visibake.operators.adapter.device.preferences()
    assert prefs.bl_rna.properties["threads"].hard_max == cores


def test_bounces_stop_at_cycles_own_limit_on_the_panel_too(visibake, clean_scene):
    cycles_limit = bpy.context.scene.cycles.bl_rna.properties["diffuse_bounces"].hard_max
    assert visibake.core.settings.MAX_BOUNCES == cycles_limit
    assert bpy.context.scene.visibake.bl_rna.properties["bounces"].hard_max == cycles_limit


def test_resolution_and_texel_density_together_are_refused(visibake, scene_file, capfd):
    line = _refused(visibake, capfd, ["bake", scene_file, *SMALL, *SIXTEEN, "--texel-density", "20"])
    assert "--resolution" in line and "--texel-density" in line and "not both" in line


# --- destinations, before any work -----------------------------------------------------------

def _destination_cases(tmp_path):
    """(arguments after the input, what the refusal names) for each kind of bad destination."""
    (tmp_path / "a_file").write_text("mine")
    (tmp_path / "a_folder").mkdir()
    read_only = _read_only_folder(tmp_path)
    setups = tmp_path / "setups.json"
    setups.write_text(json.dumps({"setups": [{"name": "one"}]}))
    return [
        (["--out", tmp_path / "a_file"], "--out"),
        (["--out", tmp_path / "a_file" / "deeper"], "--out"),
        (["--out", os.path.join(read_only, "out")], "--out"),
        (["--save", tmp_path / "a_folder"], "--save"),
        (["--save", os.path.join(read_only, "saved.blend")], "--save"),
        (["--report", tmp_path / "a_folder"], "--report"),
        (["--report", os.path.join(read_only, "report.json")], "--report"),
        (["--report", tmp_path / "a_file" / "report.json"], "--report"),
        (["--setups", setups, "--out", tmp_path / "a_file"], "--out"),
    ]


def test_every_destination_is_checked_before_any_work(visibake, scene_file, capfd, tmp_path):
    for arguments, named in _destination_cases(tmp_path):
        cache = tmp_path / "cache"
        before = _tree(tmp_path)
        line = _refused(visibake, capfd, ["bake", scene_file, "--cache-dir", cache, *SMALL, *SIXTEEN, *arguments])
        assert named in line, (arguments, line)
        # No work began: no cache folder, no output, nothing new anywhere.
        assert _tree(tmp_path) == before, arguments
        assert not cache.exists()


def test_the_operator_refuses_an_output_folder_that_is_a_file_and_changes_nothing(visibake, clean_scene, tmp_path):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 16, 1
    props.cache_dir = str(tmp_path / "cache")
    select_only([ground, block])
    (tmp_path / "out").write_text("mine")
    props.output_dir = str(tmp_path / "out")
    with pytest.raises(RuntimeError, match="output folder .* is a file, not a folder"):
        bpy.ops.visibake.bake()
    assert _visibake_leftovers() == []
    assert (tmp_path / "out").read_text() == "mine" and not (tmp_path / "cache").exists()


# --- a failure at the end rolls back ---------------------------------------------------------

def _panel_scene(tmp_path, mode="atlas"):
    black_world()
    ground = mesh_object("Ground", grid(1.0, segments=8), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    lamp = point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces, props.use_cache = 16, 32, 1, False
    ground.visibake.mode, block.visibake.mode = mode, "atlas"
    select_only([ground, block])
    return ground, block, lamp


def _attribute(mesh, name):
    values = np.empty(len(mesh.attributes[name].data) * 4, np.float32)
    mesh.attributes[name].data.foreach_get("color", values)
    return values


def test_a_late_write_failure_rolls_back_a_first_bake(visibake, clean_scene, tmp_path):
    """The results are written object by object; the last object's folder cannot be made (a file
    of the user's is in its place), after the first object's image and file were written."""
    ground, block, _ = _panel_scene(tmp_path)
    props = bpy.context.scene.visibake
    out = tmp_path / "out"
    out.mkdir()
    (out / "Block").write_text("the user's file, in the way of Block's folder")
    (out / "notes.txt").write_text("mine")
    props.output_dir = str(out)
    before = _tree(out)
    with pytest.raises(RuntimeError, match="could not be written.*nothing was changed"):
        bpy.ops.visibake.bake()
    assert _visibake_leftovers() == []
    assert _tree(out) == before and (out / "Block").read_text().startswith("the user's file")


def test_a_late_write_failure_of_a_rebake_restores_the_previous_results(visibake, clean_scene, tmp_path):
    """The re-bake adds a light group whose file's name (``Block/lighting_Key.exr``) is a file
    of the user's: a pass known only once the lights are read, so it is refused at the write,
    after the re-bake's compute. Everything the first bake made must be as it was."""
    ground, block, lamp = _panel_scene(tmp_path, mode="vertex")
    props = bpy.context.scene.visibake
    out = tmp_path / "out"
    props.output_dir = str(out)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_report"])
    assert {e["name"]: e["mode"] for e in report["objects"]} == {"Ground": "vertex", "Block": "atlas"}
    first_image, first_colours = image_pixels("VB_Block_lighting"), _attribute(ground.data, "VB_lighting")
    first_files = {path: open(path, "rb").read() for path in report["files"]}
    uv_maps = [layer.name for layer in block.data.uv_layers]
    lamp.data.energy = 400.0  # the re-bake's results differ from the first
    lamp.lightgroup, props.light_groups = "Key", True
    users = out / "Block" / "lighting_Key.exr"
    users.write_bytes(b"the user's own image")
    with pytest.raises(RuntimeError, match="VisiBake did not write"):
        bpy.ops.visibake.bake()
    np.testing.assert_array_equal(image_pixels("VB_Block_lighting"), first_image)
    np.testing.assert_array_equal(_attribute(ground.data, "VB_lighting"), first_colours)
    assert [layer.name for layer in block.data.uv_layers] == uv_maps  # the first bake's map stays
    assert not [i.name for i in bpy.data.images if i.name.startswith("VB_") and i.name != "VB_Block_lighting"]
    # The first bake's files are as they were, byte for byte, and the user's file too.
    for path, content in first_files.items():
        assert open(path, "rb").read() == content, path
    assert users.read_bytes() == b"the user's own image"
    assert not [name for name in os.listdir(out / "Block") if ".partial" in name]
    # And with the user's file gone the same bake goes through, with the brighter lamp.
    users.unlink()
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert image_pixels("VB_Block_lighting")[..., :3].sum() > first_image[..., :3].sum()


def test_the_command_rolls_back_when_its_own_last_steps_fail(visibake, scene_file, capfd, tmp_path):
    """--report names the folder the bake makes for Ground's results: the check before the bake
    passes (nothing is there yet), writing the report at the end fails."""
    out = tmp_path / "out"
    saved = tmp_path / "new" / "saved.blend"
    line = _refused(visibake, capfd, ["bake", scene_file, *SMALL, *SIXTEEN, "--no-cache", "--out", out, "--save", saved,
                                      "--report", out / "Ground", "--previews"])
    assert "could not write" in line and "Ground" in line
    assert not out.exists() and not saved.exists() and not saved.parent.exists()
    assert _visibake_leftovers() == []
