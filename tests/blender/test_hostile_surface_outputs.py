"""No user file lost by the surface bake (issue 51): ``bake``, ``demo``, ``relight`` and the panel's
Bake follow the one rule of core.outputs.ownership. A file the bake would write that no VisiBake
record lists is refused before any work (exit 2, named, kept byte for byte); a failure after the
bake takes back only what it created and puts an earlier bake's files back; a killed run's
temporaries neither refuse a folder nor stay."""
import json
import os

import bpy

import pytest
from test_brdf_command import groove_scene
from test_cli import small_blend  # noqa: F401 - fixture
from test_hostile_outputs import BTF_FAST, USERS, files_under, full_disk  # noqa: F401 - fixture
from test_lightfield_command import grid_options, plane_scene

FAST = ["--resolution", "8", "--directions", "8", "--bounces", "0", "--no-cache", "--no-progress"]


def contents(folder) -> dict:
    """{relative path: bytes} of every file below ``folder``."""
    return {name: (folder / name).read_bytes() for name in files_under(folder) if (folder / name).is_file()}


@pytest.mark.parametrize("mode, name", [("atlas", "lighting.exr"), ("vertex", "lighting.ply")])
def test_a_users_file_of_a_result_s_name_is_kept_and_the_bake_exits_2_naming_it(visibake, small_blend, tmp_path,  # noqa: F811 - fixture
                                                                                capfd, mode, name):
    out = tmp_path / "out"
    (out / "Ground").mkdir(parents=True)
    (out / "Ground" / name).write_bytes(USERS)
    status = visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--mode", mode] + FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert "VisiBake did not write" in err and str(out / "Ground" / name) in err and "bug" not in err
    assert files_under(out) == ["Ground", f"Ground/{name}"] and (out / "Ground" / name).read_bytes() == USERS


def test_a_rebake_replaces_its_own_files_and_keeps_a_users_file_beside_them(visibake, small_blend, tmp_path):  # noqa: F811 - fixture
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--previews"] + FAST) == 0
    record = json.loads((out / "visibake-bake.json").read_text())
    assert record["format"] == "visibake-bake" and "Ground/lighting.exr" in record["files"]
    (out / "Ground" / "notes.txt").write_bytes(USERS)
    # A run killed before its rename left a temporary: not a refusal, and gone after the next run.
    leftover = out / "Ground" / ".lighting.0123abcd.partial.exr"
    leftover.write_bytes(b"half")
    assert visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--previews"] + FAST) == 0
    assert (out / "Ground" / "notes.txt").read_bytes() == USERS and not leftover.exists()
    assert not [name for name in files_under(out) if ".partial" in name]
    assert "Ground/notes.txt" not in json.loads((out / "visibake-bake.json").read_text())["files"]


def test_a_failure_after_the_bake_puts_the_earlier_bake_back_and_keeps_the_users_files(visibake, small_blend,  # noqa: F811 - fixture
                                                                                       tmp_path, capfd):
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--objects", "Ground"] + FAST) == 0
    (out / "Ground" / "notes.txt").write_bytes(USERS)
    (out / "mine.txt").write_bytes(USERS)
    before = contents(out)
    # --report names a folder the bake itself creates (Block's): only known once the bake wrote it.
    status = visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--report", str(out / "Block"),
                                "--save", str(tmp_path / "saved.blend")] + FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert contents(out) == before  # the earlier bake's files as they were, the user's too, nothing new
    assert not (tmp_path / "saved.blend").exists()


def test_a_report_on_a_full_disk_exits_2_and_the_earlier_bake_stays(visibake, small_blend, tmp_path,  # noqa: F811 - fixture
                                                                    full_disk, capfd):  # noqa: F811
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(small_blend), "--out", str(out)] + FAST) == 0
    (out / "Ground" / "notes.txt").write_bytes(USERS)
    before = contents(out)
    (full_disk / "keep.txt").write_bytes(USERS)
    try:  # whatever space (or file count) is left goes to a filler
        with open(full_disk / "filler", "wb") as filler:
            while True:
                filler.write(b"x" * 1024)
                filler.flush()
    except OSError:
        pass
    left = sorted(os.listdir(full_disk))
    status = visibake.cli.main(["bake", str(small_blend), "--out", str(out), "--report",
                                str(full_disk / "report.json")] + FAST)
    err = capfd.readouterr().err
    assert status == 2, err
    assert "bug" not in err
    assert contents(out) == before
    assert sorted(os.listdir(full_disk)) == left and (full_disk / "keep.txt").read_bytes() == USERS


def test_the_demo_twice_into_one_folder_and_over_an_earlier_version_s_demo(visibake, tmp_path, capfd):
    out = tmp_path / "demo"
    demo = ["demo", "--out", str(out), "--resolution", "64", "--directions", "8", "--bounces", "0", "--no-progress"]
    assert visibake.cli.main(demo) == 0, capfd.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert str(out / "visibake-bake.json") in report["files"]
    assert visibake.cli.main(demo) == 0, capfd.readouterr().err
    # An earlier version wrote no record: its report.json, which lists its files, stands for one.
    (out / "visibake-bake.json").unlink()
    assert visibake.cli.main(demo) == 0, capfd.readouterr().err
    # A user's file in a demo's place is refused all the same.
    (out / "report.json").unlink()
    (out / "visibake-bake.json").unlink()
    (out / "preview_render.png").write_bytes(USERS)
    assert visibake.cli.main(demo) == 2
    err = capfd.readouterr().err
    assert "preview_render.png" in err and "VisiBake did not write" in err
    assert (out / "preview_render.png").read_bytes() == USERS


def test_the_panel_s_bake_refuses_a_users_file_with_a_report(visibake, small_blend, tmp_path):  # noqa: F811 - fixture
    bpy.ops.wm.open_mainfile(filepath=str(small_blend))
    props = bpy.context.scene.visibake
    props.resolution, props.directions, props.bounces, props.use_cache, props.bake_all = 8, 8, 0, False, True
    props.output_dir = str(tmp_path / "panel")
    (tmp_path / "panel" / "Ground").mkdir(parents=True)
    (tmp_path / "panel" / "Ground" / "lighting.exr").write_bytes(USERS)
    with pytest.raises(RuntimeError, match="VisiBake did not write"):
        bpy.ops.visibake.bake()
    assert files_under(tmp_path / "panel") == ["Ground", "Ground/lighting.exr"]
    assert (tmp_path / "panel" / "Ground" / "lighting.exr").read_bytes() == USERS
    assert not [i for i in bpy.data.images if i.get("visibake_image")]


def test_btf_and_lightfield_take_back_a_killed_run_s_temporaries(visibake, tmp_path):
    blend = groove_scene(tmp_path / "tile.blend")
    out = tmp_path / "btf"
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out)] + BTF_FAST) == 0
    leftovers = [out / ".btf.0123abcd.partial.json", out / "tv000_pv000" / ".tl000_pl000.89abcdef.partial.png"]
    for leftover in leftovers:
        leftover.write_bytes(b"half")
    assert visibake.cli.main(["btf", str(blend), "--tile", "Groove", "--out", str(out)] + BTF_FAST) == 0
    assert not any(leftover.exists() for leftover in leftovers)
    blend = plane_scene(tmp_path / "plane.blend")
    views = tmp_path / "views"
    arguments = ["lightfield", str(blend), "--out", str(views), "--no-progress"] + grid_options("1x1", "16x16")
    assert visibake.cli.main(arguments) == 0
    leftover = views / ".gt_depth_lowres.0123abcd.partial.pfm"
    leftover.write_bytes(b"half")
    assert visibake.cli.main(arguments) == 0
    assert not leftover.exists()
