"""The visibility cache under faults, issue 14 class 5, through the command and the bpy side:
crafted headers, writers killed mid-write, Ctrl+C during a bake, and two .blend files of one
name sharing a cache folder."""
import json
import os
import signal
import subprocess
import sys
import time

import bpy

import numpy as np
import pytest

from blender_support import REPO_ROOT
from bpy_scenes import black_world, cube, grid, material, mesh_object, point
from core.visibility.cache import HOLD_WRITE_VARIABLE

SMALL = ["--directions", "16", "--resolution", "32", "--bounces", "1", "--no-progress"]


def _scene(path, block_height=0.4):
    bpy.ops.wm.read_homefile(use_empty=True)
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, block_height))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def _bake(visibake, blend, cache, report, *extra):
    assert visibake.cli.main(["bake", str(blend), "--cache-dir", str(cache), "--report", str(report), *SMALL,
                              *extra]) == 0
    return json.loads(report.read_text())


def _slots(cache):
    return sorted(name for name in os.listdir(cache) if os.path.isdir(os.path.join(cache, name)))


def test_two_blends_of_one_name_in_one_cache_folder_keep_their_own_slots(visibake, clean_scene, tmp_path):
    cache, report = tmp_path / "shared_cache", tmp_path / "report.json"
    first = _scene(tmp_path / "a" / "house.blend")
    second = _scene(tmp_path / "b" / "house.blend", block_height=0.7)  # other geometry, same name
    assert _bake(visibake, first, cache, report)["cache"]["state"] == "miss"
    assert _bake(visibake, second, cache, report)["cache"]["state"] == "miss"
    slots = _slots(cache)
    assert len(slots) == 2 and all(name.startswith("house-") for name in slots)
    # Neither evicted the other: both are hits now, in either order.
    assert _bake(visibake, first, cache, report)["cache"]["state"] == "hit"
    assert _bake(visibake, second, cache, report)["cache"]["state"] == "hit"
    # The panel's status finds the open file's own slot, not the other's.
    bpy.ops.wm.open_mainfile(filepath=str(first))
    bpy.context.scene.visibake.cache_dir = str(cache)
    found = visibake.operators.adapter.cache_status.scene_slots(bpy.context.scene)
    assert len(found) == 1 and os.path.basename(found[0]) in slots
    report_first = _bake(visibake, first, cache, report)
    assert os.path.dirname(report_first["cache"]["path"]) == found[0]


def _rewrite_header(path, change) -> None:
    with np.load(path) as data:
        header = json.loads(bytes(data["meta"]).decode())
        arrays = {name: data[name] for name in data.files if name != "meta"}
    change(header)
    with open(path, "wb") as stream:
        np.savez(stream, meta=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)


@pytest.mark.parametrize("change", [
    lambda h: h.update(object_names=None), lambda h: h.update(sample_offset="0,1"), lambda h: h.pop("counters"),
    lambda h: h["counters"].update(rays_cast=[1]), lambda h: h.update(digests=[]),
], ids=["names null", "offsets a string", "no counters", "a counter a list", "digests a list"])
def test_a_crafted_header_is_corrupt_and_rebuilt_by_the_command(visibake, clean_scene, tmp_path, change):
    blend = _scene(tmp_path / "scene.blend")
    cache, report = tmp_path / "cache", tmp_path / "report.json"
    path = _bake(visibake, blend, cache, report)["cache"]["path"]
    _rewrite_header(path, change)
    again = _bake(visibake, blend, cache, report)
    assert again["cache"]["state"] == "corrupt"
    assert any("rebuilt" in warning for warning in again["warnings"])
    assert _bake(visibake, blend, cache, report)["cache"]["state"] == "hit"


def test_half_written_files_of_a_killed_bake_are_removed_by_the_next_and_counted(visibake, clean_scene, tmp_path):
    blend = _scene(tmp_path / "scene.blend")
    cache, report = tmp_path / "cache", tmp_path / "report.json"
    slot = os.path.dirname(_bake(visibake, blend, cache, report)["cache"]["path"])
    # What a SIGKILL in the middle of the write leaves (the writer's lock died with it).
    left = os.path.join(slot, ".writing-killed.npz")
    with open(left, "wb") as stream:
        stream.write(b"PK\x03\x04 half a table")
    stamp = time.time() - 600
    os.utime(left, (stamp, stamp))
    again = _bake(visibake, blend, cache, report)
    assert again["cache"]["state"] == "hit" and again["cache"]["abandoned_writes_removed"] == 1
    assert not os.path.exists(left)


def _command(*arguments, env=None):
    # SIGINT back to its default in the child: a test run started in the background of a
    # shell without job control inherits it ignored, and Python then never sees a Ctrl+C.
    return subprocess.Popen([sys.executable, str(REPO_ROOT / "tools" / "visibake.py"), *arguments],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=str(REPO_ROOT),
                            env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


HELD = "visibake: test hook: holding the write of .writing-"


def _held_command(tmp_path, *arguments):
    """The command with its first cache write held open (core.visibility.cache's test hook):
    its half-written, locked file exists until the process is signalled."""
    fifo = tmp_path / "hold"
    os.mkfifo(fifo)
    return _command(*arguments, env={**os.environ, HOLD_WRITE_VARIABLE: str(fifo)})


def _signal_inside_the_cache_write(process, signal_number) -> str:
    """Send ``signal_number`` once the process holds its first cache write (the hook's line
    on stderr); returns everything the process printed on stderr."""
    lines = []
    for line in process.stderr:
        lines.append(line)
        if line.startswith(HELD):
            process.send_signal(signal_number)
            break
    rest = process.stderr.read()
    process.wait(timeout=300)
    printed = "".join(lines) + rest
    assert HELD in printed, printed  # the signal landed inside the write, not before or after it
    return printed


BAKE = ["bake", "--directions", "128", "--resolution", "128", "--bounces", "1"]


def test_ctrl_c_during_a_bake_prints_no_stray_exception_and_leaves_no_half_file(tmp_path):
    cache = tmp_path / "cache"
    process = _held_command(tmp_path, *BAKE, "--cache-dir", str(cache), "--out", str(tmp_path / "out"))
    err = _signal_inside_the_cache_write(process, signal.SIGINT)
    assert process.returncode == 1, err
    assert "visibake: cancelled" in err
    assert "Exception ignored" not in err and "Traceback" not in err, err
    assert not [name for _, _, files in os.walk(cache) for name in files if name.startswith(".writing-")]


def test_a_bake_killed_while_writing_its_table_leaves_nothing_the_next_bake_keeps(tmp_path):
    cache = tmp_path / "cache"
    process = _held_command(tmp_path, *BAKE, "--cache-dir", str(cache))
    _signal_inside_the_cache_write(process, signal.SIGKILL)
    assert process.returncode == -signal.SIGKILL
    report = tmp_path / "report.json"
    after = _command(*BAKE, "--cache-dir", str(cache), "--report", str(report))
    err = after.stderr.read()
    assert after.wait(timeout=300) == 0, err
    left = [name for _, _, files in os.walk(cache) for name in files if name.startswith(".writing-")]
    assert left == []
    assert json.loads(report.read_text())["cache"]["abandoned_writes_removed"] == 1
