"""The headless command: arguments, exit status, files, report, and the bpy-module route."""
import json
import os
import subprocess
import sys

import bpy

import numpy as np
import pytest

from blender_support import REPO_ROOT
from bpy_scenes import black_world, cube, grid, material, mesh_object, sun


@pytest.fixture
def small_blend(clean_scene, tmp_path):
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    path = tmp_path / "small.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


@pytest.mark.parametrize("arguments, message", [
    (["bake", "/no/such/file.blend"], "not found"),
    (["bake", "{blend}", "--directions", "0"], "directions"),
    (["bake", "{blend}", "--passes", "lighting,shine"], "shine"),
    (["bake", "{blend}", "--objects", "Nope"], "Nope"),
    (["bake", "{blend}", "--resolution", "-3"], "resolution"),
    (["bake", "{blend}", "--shadows", "soft"], "invalid choice"),
    (["bake", "{blend}", "--texel-density", "-2"], "texel-density"),
])
def test_bad_input_exits_2_with_one_line(visibake, small_blend, capfd, arguments, message):
    arguments = [a.format(blend=small_blend) for a in arguments]
    assert visibake.cli.main(arguments) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err and message in err[-1]


def test_bake_writes_exrs_report_and_blend(visibake, small_blend, tmp_path):
    out = tmp_path / "out"
    report_path = tmp_path / "report.json"
    saved = tmp_path / "saved.blend"
    status = visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--report", str(report_path),
                                "--save", str(saved), "--resolution", "32", "--directions", "32",
                                "--passes", "lighting,ao", "--no-progress"])
    assert status == 0
    for name in ("Ground", "Block"):
        for pass_name in ("lighting", "ao"):
            assert (out / name / f"{pass_name}.exr").is_file()
    report = json.loads(report_path.read_text())
    assert report["settings"]["directions"] == 32
    assert {o["name"] for o in report["objects"]} == {"Ground", "Block"}
    ground = next(o for o in report["objects"] if o["name"] == "Ground")
    assert ground["uv_map"] == "UVMap" and ground["resolution"] == [32, 32] and ground["texels"] == 32 * 32
    block = next(o for o in report["objects"] if o["name"] == "Block")
    assert block["uv_map"] == "VisiBake" and block["uv_map_created"]
    assert report["rays"]["visibility_cast"] > 0 and report["rays"]["visibility_skipped_below_horizon"] > 0
    assert {"samples", "visibility", "direct", "transport", "outputs"} <= set(report["stage_seconds"])
    assert report["peak_memory_bytes"] > 0
    assert str(out / "Ground" / "lighting.exr") in report["files"]

    # EXR row 0 is the top of the UV square, as Blender saves images: the file read
    # top-down equals the image datablock flipped.
    import OpenEXR
    with OpenEXR.File(str(out / "Ground" / "lighting.exr")) as exr:
        top_down = exr.channels()["RGBA"].pixels
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    image = bpy.data.images["VB_Ground_lighting"]
    pixels = np.empty(32 * 32 * 4, np.float32)
    image.pixels.foreach_get(pixels)
    np.testing.assert_allclose(top_down, pixels.reshape(32, 32, 4)[::-1], rtol=1e-6)
    assert image.packed_file is not None  # the saved .blend carries its results
    assert "VisiBake" in bpy.data.objects["Block"].data.uv_layers
    assert np.all(np.isfinite(top_down))


def test_tools_script_runs_the_same_command_with_the_bpy_module(small_blend, tmp_path):
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, str(REPO_ROOT / "tools" / "visibake.py"), "bake", str(small_blend),
                             "--out", str(out), "--resolution", "32", "--directions", "16", "--no-progress"],
                            capture_output=True, text=True, timeout=600,
                            env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")})
    assert result.returncode == 0, result.stderr[-2000:]
    assert (out / "Ground" / "lighting.exr").is_file()
    assert "VisiBake bake finished" in result.stdout
    bad = subprocess.run([sys.executable, str(REPO_ROOT / "tools" / "visibake.py"), "bake",
                          str(tmp_path / "missing.blend")],
                         capture_output=True, text=True, timeout=600,
                         env={**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user")})
    assert bad.returncode == 2
    assert "not found" in bad.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize("failure", [RuntimeError("a failure no input explains"),
                                     ValueError("operands could not be broadcast together")],
                         ids=["RuntimeError", "ValueError-from-numpy"])
def test_an_unexpected_failure_is_a_bug_exit_1_where_bad_input_is_exit_2(visibake, small_blend, tmp_path, capfd,
                                                                          monkeypatch, failure):
    out = tmp_path / "out"
    options = ["--out", str(out), "--directions", "16", "--resolution", "8", "--no-progress", "--no-cache"]

    def broken_prepare(*args, **kwargs):
        raise failure

    # A failure inside the bake, where the visibility is computed. A plain ValueError
    # there is a bug too (numpy raises them), not the user's error.
    monkeypatch.setattr(visibake.operators.adapter.job, "prepare_or_reuse", broken_prepare)
    assert visibake.cli.main(["bake", str(small_blend), *options]) == 1
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback (most recent call last)" in err and f"{type(failure).__name__}: {failure}" in err
    assert lines[-1].startswith("visibake: failed") and "error:" not in lines[-1]
    assert "a bug in VisiBake" in lines[-1]
    assert not list(out.rglob("*.exr"))
    monkeypatch.undo()
    # The user's error: exit 2 and one line that says what to change, no traceback.
    assert visibake.cli.main(["bake", str(small_blend), *options, "--directions", "0"]) == 2
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1
    assert lines[0].startswith("visibake: error: ") and "directions" in lines[0]
    assert not list(out.rglob("*.exr"))


def test_blender_s_command_route_runs_the_command(visibake, small_blend, tmp_path, capfd, monkeypatch):
    import addon_utils

    from blender_support import enable_extension, extension_module_name

    # Blender's own command table holds "visibake": registering the id again is reported
    # as a duplicate (an unused id is not), and unregistering the probe makes it usable again.
    capfd.readouterr()
    for probe_id, duplicate in (("visibake", True), ("visibake_unused_probe", False)):
        probe = bpy.utils.register_cli_command(probe_id, lambda argv: 0)
        bpy.utils.unregister_cli_command(probe)
        assert (f'registered duplicate command "{probe_id}"' in capfd.readouterr().err) is duplicate, probe_id
    # What `blender -c visibake ARGS` calls: the callable the extension registers, seen
    # as it registers again (the real registration still happens).
    registered = []
    register = bpy.utils.register_cli_command

    def recording_register(command_id, execute):
        registered.append((command_id, execute))
        return register(command_id, execute)

    monkeypatch.setattr(bpy.utils, "register_cli_command", recording_register)
    addon_utils.disable(extension_module_name(), default_set=True)
    assert enable_extension() is visibake
    monkeypatch.undo()
    assert [command_id for command_id, _ in registered] == ["visibake"]
    assert repr(visibake._cli_handle).startswith('<capsule object "bpy_cli_command"')
    execute = registered[0][1]
    # As Blender calls it: the arguments after the command id; an int is the exit status.
    out, cache = tmp_path / "out", tmp_path / "cache"
    status = execute(["bake", str(small_blend), "--out", str(out), "--directions", "16", "--resolution", "8",
                      "--cache-dir", str(cache), "--no-progress"])
    assert type(status) is int and status == 0
    assert (out / "Ground" / "lighting.exr").is_file() and any(p.is_file() for p in cache.rglob("*"))
    assert execute(["clear-cache", str(small_blend), "--cache-dir", str(cache)]) == 0
    assert not any(p.is_file() for p in cache.rglob("*"))
    assert execute(["bake", str(tmp_path / "missing.blend")]) == 2
