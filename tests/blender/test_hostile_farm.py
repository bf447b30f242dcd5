"""A farm job folder damaged on the farm's shared storage (issue 51, items 7 and 11): a byte
flipped anywhere in a real job's files, a cut file, a pending.json that is not the steps' own,
and a part number beyond the job's parts are each bad input (exit 2) naming the file or the
part, through the commands the farm runs (farm-step, farm-part, farm-check)."""
import importlib
import json
import shutil

import bpy

import numpy as np
import pytest

from blender_support import extension_module_name
from bpy_scenes import black_world, cube, grid, material, mesh_object, sun

OPTIONS = ["--resolution", "16", "--directions", "16", "--no-progress", "--no-cache"]
PARTS = 2


@pytest.fixture(scope="module")
def job(visibake, tmp_path_factory):
    """A job folder after two steps and the parts of the first: call 0 answered by both parts,
    call 1 asked; with the package, both ranges' rows and pending.json, as the steps wrote them."""
    folder = tmp_path_factory.mktemp("farm")
    bpy.ops.wm.read_homefile(use_empty=True)
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    blend = folder / "room.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    for _ in range(2):
        assert visibake.cli.main(_step(blend, folder / "job", folder / "out")) == 0
        if (folder / "job" / "pending.json").read_text() == '{"call": 1}':
            break
        for part in range(PARTS):
            assert visibake.cli.main(["farm-part", "--job", str(folder / "job"), "--part", str(part)]) == 0
    assert json.loads((folder / "job" / "pending.json").read_text()) == {"call": 1}
    return blend, folder / "job"


def _step(blend, job_folder, out):
    return ["farm-step", str(blend), "--job", str(job_folder), "--parts", str(PARTS), "--out", str(out), *OPTIONS]


@pytest.fixture
def modules(visibake):
    name = extension_module_name()
    return (importlib.import_module(name + ".core.distributed.package"),
            importlib.import_module(name + ".core.distributed.rows"))


def _fresh_process(rows) -> None:
    """Forget the packages this process read: each farm command is a process of its own, which
    reads and checks its package whole (the test runs them all in one)."""
    rows._bakes.clear()
    rows._rows.clear()


def byte_positions(data: bytes) -> list[int]:
    """Positions of every kind of byte of a ZIP archive: the first local header's fields
    (signature, version, flags, method, CRC, sizes, name length), a spread through the entries'
    data (deflated and stored), the central directory's (method, local header offset) and the
    end record's (entry count, directory offset), and the last byte."""
    end = len(data) - 22  # no archive comment
    directory = int.from_bytes(data[end + 16:end + 20], "little")
    header = [0, 4, 6, 8, 14, 18, 26, 30]
    spread = np.linspace(31, directory - 1, 12).astype(int).tolist()
    central = [directory, directory + 10, directory + 16, directory + 42]
    record = [end, end + 10, end + 16, len(data) - 1]
    return sorted({p for p in header + spread + central + record if 0 <= p < len(data)})


def _damaged_copy(job_folder, tmp_path, name: str, position: int | None):
    """A copy of the job folder with one byte of ``name`` flipped (``position``), or the file cut
    to half its length (None)."""
    copy = tmp_path / "job"
    if copy.exists():
        shutil.rmtree(copy)
    shutil.copytree(job_folder, copy)
    data = bytearray((copy / name).read_bytes())
    if position is None:
        data = data[:len(data) // 2]
    else:
        data[position] ^= 0xFF
    (copy / name).write_bytes(bytes(data))
    return copy


# (the file, the command that reads it: farm-part answers call 1, farm-step replays call 0)
FILES = [("calls/0001/call.vbv", "farm-part"), ("package.vbpkg", "farm-part"), ("rows/part-0000.vbv", "farm-part"),
         ("calls/0000/part-0000.vbv", "farm-step")]


@pytest.mark.parametrize("name, command", FILES)
def test_a_flipped_byte_anywhere_in_a_job_file_is_bad_input_naming_the_file(visibake, modules, job, tmp_path, capfd,
                                                                           name, command):
    package, rows = modules
    blend, job_folder = job
    data = (job_folder / name).read_bytes()
    positions = byte_positions(data)
    if command == "farm-step":
        positions = positions[::2]  # a step loads the .blend and prepares the scene: fewer
    outcomes = {}
    for position in positions + [None]:
        copy = _damaged_copy(job_folder, tmp_path, name, position)
        _fresh_process(rows)
        arguments = (["farm-part", "--job", str(copy), "--part", "0"] if command == "farm-part"
                     else _step(blend, copy, tmp_path / "out"))
        status = visibake.cli.main(arguments)
        said = capfd.readouterr().err.strip().splitlines()
        outcomes[position] = status
        if status == 0:
            # zipfile ignores that byte (a local header's copy of a size, a time): the file
            # reads back whole, its checksum unchanged, and the job goes on.
            read = package.read_package if name.endswith(".vbpkg") else package.read_values
            read(str(copy / name))
            assert position is not None
        else:
            assert status == 2, (position, said)
            assert said and str(copy / name) in said[-1], (position, said)
            assert not (tmp_path / "out").exists()
    assert sum(status == 2 for status in outcomes.values()) >= len(outcomes) // 2, outcomes


@pytest.mark.parametrize("content", ['{"call": "1"}', '{"call": 1.5}', '{"call": -1}', '{"call": true}', "[1]",
                                     '{"call": 1, "more": 2}', '{"done": "yes"}', "{", "\x00\x01"])
def test_a_damaged_pending_file_is_bad_input_for_every_farm_command(visibake, job, tmp_path, capfd, content):
    blend, job_folder = job
    copy = tmp_path / "job"
    shutil.copytree(job_folder, copy)
    (copy / "pending.json").write_text(content)
    for arguments in (["farm-part", "--job", str(copy), "--part", "0"], ["farm-check", "--job", str(copy)],
                      _step(blend, copy, tmp_path / "out")):
        assert visibake.cli.main(arguments) == 2, (arguments[0], content)
        said = capfd.readouterr().err.strip().splitlines()
        assert said and "pending.json" in said[-1], (arguments[0], said)
    assert (copy / "pending.json").read_text() == content
    assert not (tmp_path / "out").exists()


def test_a_part_beyond_the_job_s_parts_exits_2(visibake, job, tmp_path, capfd):
    _, job_folder = job
    copy = tmp_path / "job"
    shutil.copytree(job_folder, copy)
    assert visibake.cli.main(["farm-part", "--job", str(copy), "--part", "7"]) == 2
    said = capfd.readouterr().err.strip().splitlines()
    assert said and f"--part 7: the farm job in {copy} has parts 0 to {PARTS - 1}" in said[-1], said
    assert not (copy / "calls" / "0001" / "part-0007.vbv").exists()
    # The job's own last part still runs.
    assert visibake.cli.main(["farm-part", "--job", str(copy), "--part", str(PARTS - 1)]) == 0
    assert (copy / "calls" / "0001" / f"part-{PARTS - 1:04d}.vbv").exists()
