"""``visibake bake --workers N``: the installed extension's bake on a local Dask cluster (plain
``dask scheduler`` and ``dask worker`` processes that import the extension's core without
Blender), equal bit for bit to the same bake in one process; and the cluster options' refusals."""
import importlib
import json

import bpy

# Pinned in requirements.txt: a broken install fails here rather than skipping the module.
import distributed  # noqa: F401
import numpy as np
import pytest

from blender_support import extension_module_name
from bpy_scenes import black_world, cube, grid, material, mesh_object, point, sun


@pytest.fixture
def room_blend(clean_scene, tmp_path):
    """A ground, a block on it and a lamp: contacts, a bounce, an atlas made by the bake."""
    black_world()
    mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    point(200.0, (0.6, -0.4, 1.5))
    path = tmp_path / "room.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def _channels(path):
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        return {name: np.array(channel.pixels) for name, channel in exr.channels().items()}


def test_a_bake_on_two_local_workers_equals_the_one_process_bake(visibake, room_blend, tmp_path):
    common = ["bake", str(room_blend), "--resolution", "32", "--directions", "48", "--bounces", "2",
              "--passes", "lighting,indirect,ao", "--no-progress", "--no-cache"]
    assert visibake.cli.main(common + ["--out", str(tmp_path / "one"), "--report", str(tmp_path / "one.json")]) == 0
    assert visibake.cli.main(common + ["--out", str(tmp_path / "two"), "--report", str(tmp_path / "two.json"),
                                       "--workers", "2", "--parts", "3"]) == 0
    for name in ("Ground", "Block"):
        for pass_name in ("lighting", "indirect", "ao"):
            ours, theirs = _channels(tmp_path / "two" / name / f"{pass_name}.exr"), _channels(
                tmp_path / "one" / name / f"{pass_name}.exr")
            assert ours.keys() == theirs.keys()
            for channel in ours:
                assert np.array_equal(ours[channel], theirs[channel]), (name, pass_name, channel)
            assert np.any(ours["RGBA"][..., :3] > 0)
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["split"]["ranges"] == 3 and report["split"]["executor"] == "dask"
    assert report["split"]["cluster"]["workers"] == 2
    assert report["split"]["table_bytes_held_by_ranges"] > 0
    assert report["table_bytes"] == 0  # this process held none of the table
    assert report["device"]["used"] == "cpu"
    assert "split" not in json.loads((tmp_path / "one.json").read_text())


@pytest.mark.parametrize("extra, message", [
    (["--workers", "0"], "at least 1 worker"),
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "not both"),
    (["--scheduler", "tcp://10.20.30.40:8786"], "--insecure"),
    (["--scheduler", "tls://10.20.30.40:8786"], "needs the certificates"),
    (["--scheduler", "tls://10.20.30.40:8786", "--tls-cert", "c.pem"], "all of --tls-ca-file"),
    (["--insecure"], "only with --workers or --scheduler"),
    (["--workers", "2", "--parts", "0"], "at least 1 row range"),
    (["--workers", "2", "--sun-sweep", "6:18:3"], "not with relight, --setups or --sun-sweep"),
    (["--workers", "2", "--device", "gpu"], "with the CPU kernels"),
])
def test_cluster_options_that_cannot_run_exit_2_before_any_work(visibake, room_blend, tmp_path, capfd, extra,
                                                              message):
    out = tmp_path / "out"
    status = visibake.cli.main(["bake", str(room_blend), "--resolution", "16", "--directions", "16",
                                "--no-progress", "--out", str(out)] + extra)
    assert status == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err and message in err[-1]
    assert not out.exists() or not any(out.rglob("*.exr"))


def test_a_brdf_run_on_two_local_workers_equals_the_one_process_run(visibake, tmp_path):
    from test_brdf_command import groove_scene

    blend = groove_scene(tmp_path / "groove.blend")
    common = ["brdf", str(blend), "--tile", "Groove", "--format", "table", "--lights", "70", "--views", "5",
              "--directions", "32", "--resolution", "8", "--view-rays", "32", "--no-progress"]
    assert visibake.cli.main(common + ["--out", str(tmp_path / "one.npz")]) == 0
    assert visibake.cli.main(common + ["--out", str(tmp_path / "two.npz"), "--workers", "2",
                                       "--report", str(tmp_path / "two.json")]) == 0
    with np.load(tmp_path / "one.npz") as one, np.load(tmp_path / "two.npz") as two:
        assert sorted(one.files) == sorted(two.files)
        for name in one.files:
            assert np.array_equal(one[name], two[name]), name
        assert np.any(two["values"] > 0)
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["split"] == {"parts": 4, "cluster": {"workers": 2, "scheduler": None, "tls": False,
                                                       "insecure": False}}


def test_the_flamenco_job_run_task_by_task_equals_the_one_process_bake(visibake, room_blend, tmp_path, capfd):
    """The task list the job type compiles (tests/flamenco_support.py), run in its order here
    as a farm's workers would run it (each task's command, minus Blender's own arguments)."""
    from flamenco_support import compile_job

    options = "--resolution 32 --directions 48 --bounces 2 --passes lighting,indirect,ao --no-progress --no-cache"
    compiled = compile_job({"blendfile": str(room_blend), "job_folder": str(tmp_path / "job"),
                            "output_folder": str(tmp_path / "farm"), "parts": 2, "steps": 12, "bake_args": options})
    said = []
    for task in compiled["tasks"]:
        arguments = task["commands"][0]["parameters"]["args"]
        assert arguments[:2] == ["-c", "visibake"]
        assert visibake.cli.main(arguments[2:]) == 0, task["name"]
        said.append(capfd.readouterr().out)
    assert visibake.cli.main(["bake", str(room_blend), "--out", str(tmp_path / "one")] + options.split()) == 0
    for name in ("Ground", "Block"):
        for pass_name in ("lighting", "indirect", "ao"):
            ours = _channels(tmp_path / "farm" / name / f"{pass_name}.exr")
            theirs = _channels(tmp_path / "one" / name / f"{pass_name}.exr")
            for channel in ours:
                assert np.array_equal(ours[channel], theirs[channel]), (name, pass_name, channel)
    # The steps after the one that finished, and their parts, had nothing to do.
    finished = next(i for i, text in enumerate(said) if "files: " in text)
    assert all("nothing to do" in text for text in said[finished + 1:-1])
    assert "finished" in said[-1]


def test_a_farm_job_with_too_few_steps_fails_its_check(visibake, room_blend, tmp_path, capfd):
    from flamenco_support import compile_job

    compiled = compile_job({"blendfile": str(room_blend), "job_folder": str(tmp_path / "job"),
                            "output_folder": str(tmp_path / "farm"), "parts": 2, "steps": 2,
                            "bake_args": "--resolution 16 --directions 16 --no-progress"})
    statuses = [visibake.cli.main(task["commands"][0]["parameters"]["args"][2:]) for task in compiled["tasks"]]
    assert statuses[:-1] == [0] * (len(statuses) - 1) and statuses[-1] == 2
    assert "did not finish within the job's steps" in capfd.readouterr().err
    assert not (tmp_path / "farm").exists()  # no half of a bake was written


def test_a_btf_on_two_local_workers_writes_the_one_process_images(visibake, tmp_path):
    from test_brdf_command import groove_scene

    blend = groove_scene(tmp_path / "groove.blend")
    common = ["btf", str(blend), "--tile", "Groove", "--format", "exr", "--image-size", "8", "--rays-per-pixel", "1",
              "--directions", "16", "--resolution", "4", "--bounces", "1", "--no-progress"]
    assert visibake.cli.main(common + ["--out", str(tmp_path / "one")]) == 0
    assert visibake.cli.main(common + ["--out", str(tmp_path / "two"), "--workers", "2", "--parts", "3",
                                       "--report", str(tmp_path / "two.json")]) == 0
    ones = sorted(p.relative_to(tmp_path / "one").as_posix() for p in (tmp_path / "one").rglob("*.exr"))
    twos = sorted(p.relative_to(tmp_path / "two").as_posix() for p in (tmp_path / "two").rglob("*.exr"))
    assert ones == twos and len(ones) == 81 * 81
    for relative in ones[::97] + [ones[-1]]:
        ours, theirs = _channels(tmp_path / "two" / relative), _channels(tmp_path / "one" / relative)
        for channel in ours:
            assert np.array_equal(ours[channel], theirs[channel]), (relative, channel)
    manifest = json.loads((tmp_path / "two" / "btf.json").read_text())
    assert manifest["complete"] and len(manifest["files"]) == 81 * 81
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["split"]["parts"] == 3 and report["images"] == 81 * 81


def test_a_light_field_baked_and_rendered_on_two_workers_equals_the_cpu_one(visibake, tmp_path):
    from test_lightfield_command import FAST_BAKE, grid_options, plane_scene

    blend = plane_scene(tmp_path / "scene.blend")
    common = ["lightfield", str(blend), "--bake-first", "--device", "cpu"] + grid_options() + FAST_BAKE
    assert visibake.cli.main(common + ["--out", str(tmp_path / "one")]) == 0
    assert visibake.cli.main(common + ["--out", str(tmp_path / "two"), "--workers", "2", "--parts", "4",
                                       "--report", str(tmp_path / "two.json")]) == 0
    files = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "two").iterdir())
    views = [name for name in files if name.endswith(".exr")]
    assert len(views) == 9
    for name in views:
        ours, theirs = _channels(tmp_path / "two" / name), _channels(tmp_path / "one" / name)
        for channel in ours:
            assert np.array_equal(ours[channel], theirs[channel]), (name, channel)
    for name in ("gt_depth_lowres.pfm", "gt_disp_lowres.pfm"):
        assert (tmp_path / "two" / name).read_bytes() == (tmp_path / "one" / name).read_bytes()
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["split"]["parts"] == 4 and report["renderer"] == "cpu (embree), on a cluster"


def test_a_volume_on_two_local_workers_writes_the_one_process_grids(visibake, tmp_path):
    from test_volume_bake import read_grid, volume_scene, write_vdb

    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    try:
        openvdb = compat.openvdb()
    except compat.FeatureMissing as missing:
        pytest.skip(f"volumes need Blender's openvdb module: {missing}")
    bpy.ops.wm.read_homefile(use_empty=True)
    black_world()
    sun(3.0)
    point(300.0, (0.5, 0.0, 2.5))
    write_vdb(openvdb, tmp_path / "cloud.vdb")
    volume_scene(tmp_path / "cloud.vdb")
    blend = tmp_path / "cloud.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    common = ["volume", str(blend), "--resolution", "16", "--directions", "16", "--bounces", "2", "--no-progress",
              "--no-cache"]
    assert visibake.cli.main(common + ["--out", str(tmp_path / "one")]) == 0
    assert visibake.cli.main(common + ["--out", str(tmp_path / "two"), "--workers", "2", "--parts", "3",
                                       "--report", str(tmp_path / "two.json")]) == 0
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["split"]["parts"] == 3 and report["volumes"][0]["tables"] == "built on the cluster"
    shape = tuple(report["volumes"][0]["grid"]) + (3,)
    for name in ("direct", "indirect", "scattered"):
        ours = read_grid(openvdb, tmp_path / "two" / "Cloud" / f"{name}.vdb", name, shape)
        theirs = read_grid(openvdb, tmp_path / "one" / "Cloud" / f"{name}.vdb", name, shape)
        assert np.array_equal(ours, theirs), name
        assert ours.max() > 0


def _panel_scene():
    """The panel tests' ground, block (made an atlas by the bake) and lamp, at 48 directions,
    2 bounces and no cache. Returns (ground, block)."""
    from bpy_scenes import ground_block_lamp

    objects = ground_block_lamp()
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.use_cache = 48, 2, False
    return objects


def _baked_pixels(visibake, objects):
    name = visibake.operators.adapter.writeback.image_name
    return {o.name: np.array(bpy.data.images[name(o.name, "lighting")].pixels[:]) for o in objects}


def _remove_baked_images():
    for name in [n for n in bpy.data.images.keys() if n.startswith("VB_")]:
        bpy.data.images.remove(bpy.data.images[name])


def _modal_bake(visibake, objects, cluster=None):
    """A ModalBake of ``objects`` as the panel runs it (without the resident preparation, whose
    transport is summed per lamp: the same light to float rounding, not bitwise)."""
    progress = visibake.core.pipeline.progress.Progress()
    bake_job = visibake.operators.adapter.job.BakeJob(bpy.context, list(objects), progress=progress, cluster=cluster)
    return visibake.operators.adapter.modal.ModalBake(bake_job, progress), progress


def _tick(modal, deadline, on_tick=None):
    import time

    while not modal.tick():
        assert time.perf_counter() < deadline, "the bake never ended"
        if on_tick is not None:
            on_tick()
        time.sleep(0.05)


def test_the_panel_s_bake_with_cluster_workers_equals_the_bake_in_blender_s_process(visibake, clean_scene):
    import time

    objects = _panel_scene()
    modal, _ = _modal_bake(visibake, objects)
    _tick(modal, time.perf_counter() + 300)
    assert modal.error is None, modal.error
    alone = _baked_pixels(visibake, objects)
    prefs = visibake.operators.adapter.device.preferences()
    assert prefs.cluster_workers == 0  # off unless asked for
    prefs.cluster_workers = 2
    try:
        assert bpy.ops.visibake.bake() == {"FINISHED"}
    finally:
        prefs.cluster_workers = 0
    report = json.loads(bpy.context.scene["visibake_report"])
    assert report["split"]["cluster"]["workers"] == 2 and report["split"]["ranges"] == 4
    rays = report["rays"]["visibility_cast"]
    assert rays > 0 and f"{rays} visibility rays" in bpy.context.scene["visibake_last_report"]
    on_workers = _baked_pixels(visibake, objects)
    for name, pixels in alone.items():
        assert np.array_equal(on_workers[name], pixels), name
    # Without the preference, the panel's bake keeps its preparation for relights, summing
    # the transport per lamp: the same light to float rounding.
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert "split" not in json.loads(bpy.context.scene["visibake_report"]) or \
        json.loads(bpy.context.scene["visibake_report"])["split"] is None
    for name, pixels in _baked_pixels(visibake, objects).items():
        np.testing.assert_allclose(pixels, alone[name], rtol=1e-6, atol=1e-7)


def test_a_modal_bake_on_local_workers_ticks_to_the_same_images_and_a_cancel_stops_its_processes(
        visibake, clean_scene):
    import time

    import psutil

    objects = _panel_scene()
    deadline = time.perf_counter() + 600
    modal, _ = _modal_bake(visibake, objects)
    _tick(modal, deadline)
    alone = _baked_pixels(visibake, objects)
    _remove_baked_images()
    engine = importlib.import_module(f"{extension_module_name()}.core.distributed.engine")

    modal, _ = _modal_bake(visibake, objects, engine.ClusterOptions(workers=2))
    assert [name for name, _, _ in modal.steps] == ["plan", "unwrap", "extract", "visibility and lighting", "finish"]
    _tick(modal, deadline)
    assert modal.error is None, modal.error
    for name, pixels in _baked_pixels(visibake, objects).items():
        assert np.array_equal(pixels, alone[name]), name
    _remove_baked_images()

    before = {child.pid for child in psutil.Process().children(recursive=True)}

    def started_since():
        return [child for child in psutil.Process().children(recursive=True) if child.pid not in before]

    def cluster_processes(children):
        found = []
        for child in children:
            try:
                if "distributed.cli" in " ".join(child.cmdline()):
                    found.append(child)
            except psutil.Error:
                pass
        return found

    uv_names = list(objects[1].data.uv_layers.keys())
    atlas = np.zeros(2 * len(objects[1].data.loops), np.float32)
    objects[1].data.uv_layers["VisiBake"].data.foreach_get("uv", atlas)
    modal, progress = _modal_bake(visibake, objects, engine.ClusterOptions(workers=2))
    started = []

    def cancel_once_the_cluster_runs():
        if modal.steps[modal.next_step - 1][0] == "visibility and lighting" and not started:
            children = started_since()
            if len(cluster_processes(children)) >= 3:  # its scheduler and two workers
                started.extend(children)
                progress.cancel()

    _tick(modal, deadline, cancel_once_the_cluster_runs)
    assert isinstance(modal.error, visibake.core.errors.Cancelled), modal.error
    assert started, "the cluster never started"
    _, alive = psutil.wait_procs(started, timeout=60)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE]
    assert not [n for n in bpy.data.images.keys() if n.startswith("VB_")]  # nothing written
    # The block's bake atlas, made by the first bake, is as that bake left it.
    assert list(objects[1].data.uv_layers.keys()) == uv_names
    atlas_after = np.zeros(2 * len(objects[1].data.loops), np.float32)
    objects[1].data.uv_layers["VisiBake"].data.foreach_get("uv", atlas_after)
    assert np.array_equal(atlas_after, atlas)
