"""No user file lost (issue 51): every command that writes files (volume, brdf, btf, lightfield)
refuses to replace a file VisiBake did not write (``--overwrite`` included, for a file of the
same name), turns a full disk into exit 2 "not enough space" leaving nothing behind, and a
cancel while images are written leaves nothing either (core.outputs.ownership)."""
import errno
import importlib
import json
import os
import subprocess

import bpy

import pytest
from test_brdf_command import FAST, groove_scene, open_groove_for_the_panel
from test_lightfield_command import grid_options, plane_scene
from test_volume_bake import cloud_blend, vdb  # noqa: F401 - fixtures

from blender_support import extension_module_name

VOLUME_FAST = ["--resolution", "16", "--directions", "8", "--bounces", "1", "--no-progress"]
BTF_FAST = ["--format", "png", "--image-size", "8", "--rays-per-pixel", "1", "--directions", "16", "--resolution",
            "4", "--bounces", "1", "--no-progress"]
USERS = b"the user's own bytes"


@pytest.fixture
def full_disk(tmp_path):
    """A 40 KiB file system (tmpfs) at tmp_path/disk: a bake's outputs do not fit on it."""
    folder = tmp_path / "disk"
    folder.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=40k", "tmpfs", str(folder)], capture_output=True,
                              text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as error:
        pytest.skip(f"a small file system needs mount, which failed here: {error}")
    if done.returncode != 0:
        pytest.skip(f"a small file system needs mount (root), which is not permitted here: {done.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True, timeout=60)


def files_under(folder) -> list:
    """Every file and folder below ``folder`` (relative, sorted), hidden ones included."""
    return sorted(os.path.relpath(os.path.join(root, name), folder)
                  for root, dirs, files in os.walk(folder) for name in dirs + files)


# --- volume ---------------------------------------------------------------------------------

def test_volume_refuses_to_replace_a_users_grids_and_writes_nothing(visibake, vdb, cloud_blend, tmp_path,  # noqa: F811
                                                                     capfd):
    blend, _ = cloud_blend
    out = tmp_path / "out"
    mine = out / "Cloud"
    mine.mkdir(parents=True)
    for name in ("density.vdb", "scattered.vdb", "volume.vdb"):
        (mine / name).write_bytes(USERS + name.encode())
    assert visibake.cli.main(["volume", str(blend), "--out", str(out)] + VOLUME_FAST) == 2
    err = capfd.readouterr().err
    assert "VisiBake did not write" in err and "density.vdb" in err
    assert files_under(out) == ["Cloud", "Cloud/density.vdb", "Cloud/scattered.vdb", "Cloud/volume.vdb"]
    for name in ("density.vdb", "scattered.vdb", "volume.vdb"):
        assert (mine / name).read_bytes() == USERS + name.encode()
    assert "Cloud (VisiBake)" not in bpy.data.objects


def test_volume_replaces_its_own_grids_and_a_users_file_beside_them_stays(visibake, vdb, cloud_blend,  # noqa: F811
                                                                          tmp_path):
    blend, _ = cloud_blend
    out = tmp_path / "out"
    report = tmp_path / "report.json"
    assert visibake.cli.main(["volume", str(blend), "--out", str(out), "--report", str(report)] + VOLUME_FAST) == 0
    assert (out / "Cloud" / "visibake-volume.json").is_file()
    # The record is a file the run wrote: the report (and the count printed) include it.
    assert str(out / "Cloud" / "visibake-volume.json") in json.loads(report.read_text())["files"]
    (out / "Cloud" / "notes.txt").write_bytes(USERS)
    assert visibake.cli.main(["volume", str(blend), "--out", str(out)] + VOLUME_FAST) == 0
    assert (out / "Cloud" / "notes.txt").read_bytes() == USERS
    assert not [name for name in files_under(out) if ".partial" in name]


def test_volume_on_a_full_disk_exits_2_and_leaves_nothing(visibake, vdb, cloud_blend, full_disk, capfd):  # noqa: F811
    blend, _ = cloud_blend
    (full_disk / "keep.txt").write_bytes(USERS)
    status = visibake.cli.main(["volume", str(blend), "--out", str(full_disk / "out"), "--no-cache"] + VOLUME_FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert f"not enough space in {full_disk / 'out'}:" in err
    assert files_under(full_disk) == ["keep.txt"]
    assert (full_disk / "keep.txt").read_bytes() == USERS
    assert "Cloud (VisiBake)" not in bpy.data.objects


def test_the_panel_s_bake_volume_refuses_a_users_grids(visibake, vdb, cloud_blend, tmp_path):  # noqa: F811
    blend, _ = cloud_blend
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    props = bpy.context.scene.visibake
    props.volume_resolution, props.volume_directions, props.volume_bounces = 12, 8, 1
    props.output_dir = str(tmp_path / "panel")
    mine = tmp_path / "panel" / "Cloud"
    mine.mkdir(parents=True)
    (mine / "emission.vdb").write_bytes(USERS)
    with pytest.raises(RuntimeError, match="VisiBake did not write"):
        bpy.ops.visibake.bake_volume()
    assert files_under(tmp_path / "panel") == ["Cloud", "Cloud/emission.vdb"]
    assert (mine / "emission.vdb").read_bytes() == USERS
    assert "Cloud (VisiBake)" not in bpy.data.objects


# --- brdf -----------------------------------------------------------------------------------

def test_brdf_on_a_full_disk_exits_2_and_leaves_nothing(visibake, tmp_path, full_disk, capfd):
    blend = groove_scene(tmp_path / "tile.blend")
    (full_disk / "keep.txt").write_bytes(USERS)
    # A MERL table is 1.5 MB: it cannot fit in 40 KiB.
    status = visibake.cli.main(["brdf", str(blend), "--tile", "Groove", "--out", str(full_disk / "cloth.binary")]
                               + FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert "not enough space in" in err and "bug" not in err
    assert files_under(full_disk) == ["keep.txt"]


def test_brdf_overwrite_replaces_the_named_file_but_never_a_users_report_name(visibake, tmp_path, capfd):
    blend = groove_scene(tmp_path / "tile.blend")
    out = tmp_path / "cloth.npz"
    out.write_bytes(USERS)
    sidecar = tmp_path / "cloth.npz.visibake.json"
    sidecar.write_bytes(USERS)
    assert visibake.cli.main(["brdf", str(blend), "--tile", "Groove", "--out", str(out), "--format", "table",
                              "--overwrite"] + FAST) == 2
    assert "cloth.npz.visibake.json" in capfd.readouterr().err
    assert out.read_bytes() == USERS and sidecar.read_bytes() == USERS
    sidecar.unlink()
    # --overwrite names FILE itself: the user asked for it to be replaced.
    assert visibake.cli.main(["brdf", str(blend), "--tile", "Groove", "--out", str(out), "--format", "table",
                              "--overwrite"] + FAST) == 0
    assert out.read_bytes() != USERS and sidecar.is_file()


# --- btf ------------------------------------------------------------------------------------

def test_btf_on_a_full_disk_exits_2_and_leaves_nothing(visibake, tmp_path, full_disk, capfd):
    blend = groove_scene(tmp_path / "tile.blend")
    (full_disk / "keep.txt").write_bytes(USERS)
    status = visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(full_disk / "btf")] + BTF_FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert "not enough space in" in err and "bug" not in err
    assert files_under(full_disk) == ["keep.txt"]


@pytest.mark.parametrize("interrupt", [KeyboardInterrupt, "Cancelled"])
def test_a_btf_cancelled_while_an_image_is_written_leaves_nothing(visibake, tmp_path, monkeypatch, capfd,
                                                                   interrupt):
    """Ctrl-C (or the panel's cancel) arriving while the fifth image is half written."""
    btf = importlib.import_module(extension_module_name() + ".core.appearance.btf")
    errors = importlib.import_module(extension_module_name() + ".core.errors")
    stop = errors.Cancelled if interrupt == "Cancelled" else interrupt
    blend = groove_scene(tmp_path / "tile.blend")
    real_write_png, calls = btf.write_png, []

    def write_then_stop(path, image):
        calls.append(path)
        real_write_png(path, image)
        if len(calls) == 5:
            with open(path, "r+b") as handle:
                handle.truncate(10)  # the signal lands mid-write
            raise stop()

    monkeypatch.setattr(btf, "write_png", write_then_stop)
    out = tmp_path / "btf"
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out)] + BTF_FAST) == 1
    assert "cancelled" in capfd.readouterr().err
    assert len(calls) == 5
    assert not out.exists()
    assert files_under(tmp_path) == ["tile.blend"]


def test_btf_overwrite_writes_beside_a_users_files_but_never_over_one(visibake, tmp_path, capfd):
    blend = groove_scene(tmp_path / "tile.blend")
    out = tmp_path / "btf"
    out.mkdir()
    (out / "btf.json").write_bytes(USERS)
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out), "--overwrite"]
                             + BTF_FAST) == 2
    assert "btf.json" in capfd.readouterr().err
    assert files_under(out) == ["btf.json"] and (out / "btf.json").read_bytes() == USERS
    # A user's image of a planned name, in a folder the run would share: refused too.
    (out / "btf.json").unlink()
    (out / "tv000_pv000").mkdir()
    image = out / "tv000_pv000" / "tl000_pl000_tv000_pv000.png"
    image.write_bytes(USERS)
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out), "--overwrite"]
                             + BTF_FAST) == 2
    assert image.read_bytes() == USERS and files_under(out) == ["tv000_pv000", "tv000_pv000/" + image.name]
    # Other names are written beside the user's file, which stays.
    image.rename(out / "tv000_pv000" / "notes.png")
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out), "--overwrite"]
                             + BTF_FAST) == 0
    assert (out / "tv000_pv000" / "notes.png").read_bytes() == USERS
    assert (out / "btf.json").is_file() and image.is_file()


# --- lightfield -----------------------------------------------------------------------------

def test_lightfield_overwrite_never_replaces_a_users_view_of_the_same_name(visibake, tmp_path, capfd):
    blend = plane_scene(tmp_path / "scene.blend")
    out = tmp_path / "lf"
    out.mkdir()
    (out / "input_Cam000.png").write_bytes(USERS)
    (out / "notes.txt").write_bytes(USERS)
    arguments = ["lightfield", str(blend), "--out", str(out), "--overwrite", "--no-progress"] + grid_options(
        "1x1", "16x16")
    assert visibake.cli.main(arguments) == 2
    assert "input_Cam000.png" in capfd.readouterr().err
    assert files_under(out) == ["input_Cam000.png", "notes.txt"]
    assert (out / "input_Cam000.png").read_bytes() == USERS
    # Without the same-named file the run writes beside the user's other file.
    (out / "input_Cam000.png").unlink()
    assert visibake.cli.main(arguments) == 0
    assert (out / "notes.txt").read_bytes() == USERS and (out / "input_Cam000.png").read_bytes() != USERS


def test_lightfield_on_a_full_disk_exits_2_and_leaves_nothing(visibake, tmp_path, full_disk, capfd):
    blend = plane_scene(tmp_path / "scene.blend")
    (full_disk / "keep.txt").write_bytes(USERS)
    status = visibake.cli.main(["lightfield", str(blend), "--out", str(full_disk / "lf"), "--no-progress"]
                               + grid_options("3x3", "64x48"))
    err = capfd.readouterr().err
    assert status == 2, err
    assert "not enough space in" in err and "bug" not in err
    assert files_under(full_disk) == ["keep.txt"]


def test_a_space_error_reads_as_one(visibake):
    """The errors a full disk raises, from Python and from a library's message."""
    ownership = importlib.import_module(extension_module_name() + ".core.outputs.ownership")
    assert ownership.is_space_error(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
    assert ownership.is_space_error(OSError(errno.EFBIG, os.strerror(errno.EFBIG)))
    assert ownership.is_space_error(RuntimeError(f"Failed to write pixel data. {os.strerror(errno.ENOSPC)}."))
    assert not ownership.is_space_error(OSError(errno.EACCES, os.strerror(errno.EACCES)))


# --- the panel's operators ------------------------------------------------------------------

def test_the_panel_s_simulate_btf_on_a_full_disk_says_so_and_leaves_nothing(visibake, tmp_path, full_disk):
    open_groove_for_the_panel(tmp_path, full_disk / "materials")
    (full_disk / "keep.txt").write_bytes(USERS)
    with pytest.raises(RuntimeError, match="not enough space in"):
        bpy.ops.visibake.simulate_btf()
    assert files_under(full_disk) == ["keep.txt"]
    assert "visibake_btf_report" not in bpy.context.scene


def test_the_panel_s_light_field_on_a_full_disk_says_so_and_leaves_nothing(visibake, tmp_path, full_disk):
    blend = plane_scene(tmp_path / "scene.blend")
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    props = bpy.context.scene.visibake
    props.output_dir = str(full_disk)
    props.lightfield_columns, props.lightfield_rows = 3, 3
    props.lightfield_width, props.lightfield_height = 64, 48
    (full_disk / "keep.txt").write_bytes(USERS)
    with pytest.raises(RuntimeError, match="not enough space in"):
        bpy.ops.visibake.render_lightfield()
    assert files_under(full_disk) == ["keep.txt"]
