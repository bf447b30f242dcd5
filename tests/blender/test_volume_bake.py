"""``visibake volume``: a Volume object's medium read through openvdb, lit, written as grids and
as a baked Volume object; the user's volume and file untouched; bad input refused (exit 2)."""
import hashlib
import importlib
import json
import math

import bpy

import numpy as np
import pytest

from blender_support import extension_module_name
from bpy_scenes import black_world, sun

VOXEL = 0.1
SIDE = 24
RADIUS = 8.0
SUN_STRENGTH = 3.0
DENSITY = 4.0


@pytest.fixture
def vdb(visibake):
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    try:
        return compat.openvdb()
    except compat.FeatureMissing as missing:
        pytest.skip(f"volumes need Blender's openvdb module: {missing}")


def write_vdb(vdb, path, density: np.ndarray | None = None, name="density", origin=(0.5, -0.3, 0.2)):
    """A sphere of density 1 (SIDE^3 voxels of VOXEL, RADIUS voxels) as ``path``."""
    if density is None:
        centre = (SIDE - 1) / 2.0
        index = np.indices((SIDE, SIDE, SIDE)).astype(np.float64)
        inside = np.sqrt(((index - centre) ** 2).sum(axis=0)) <= RADIUS
        density = inside.astype(np.float32)
    grid = vdb.FloatGrid()
    grid.copyFromArray(np.ascontiguousarray(density, np.float32), ijk=(0, 0, 0))
    grid.name = name
    matrix = np.diag([VOXEL, VOXEL, VOXEL, 1.0])
    matrix[3, :3] = origin  # openvdb's row-vector convention
    grid.transform = vdb.createLinearTransform(matrix.tolist())
    vdb.write(str(path), grids=[grid])


def volume_scene(path, name="Cloud"):
    volume = bpy.data.volumes.new(name)
    volume.filepath = str(path)
    obj = bpy.data.objects.new(name, volume)
    obj.location = (0.0, 0.0, 1.0)
    bpy.context.scene.collection.objects.link(obj)
    material = bpy.data.materials.new(name + " material")
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    compat.ensure_node_tree(material)
    tree = material.node_tree
    tree.nodes.clear()
    principled = tree.nodes.new("ShaderNodeVolumePrincipled")
    principled.inputs["Density"].default_value = DENSITY
    principled.inputs["Color"].default_value = (0.9, 0.9, 0.9, 1.0)
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(principled.outputs[0], output.inputs["Volume"])
    volume.materials.append(material)
    return obj


@pytest.fixture
def cloud_blend(clean_scene, vdb, tmp_path):
    black_world()
    sun(SUN_STRENGTH)  # straight down
    vdb_path = tmp_path / "cloud.vdb"
    write_vdb(vdb, vdb_path)
    volume_scene(vdb_path)
    blend = tmp_path / "cloud.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    return blend, vdb_path


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_volume_bake_writes_its_grids_and_a_baked_object_and_leaves_the_source_alone(
        visibake, vdb, cloud_blend, tmp_path):
    blend, vdb_path = cloud_blend
    before = digest(vdb_path)
    out, report_path, saved = tmp_path / "out", tmp_path / "report.json", tmp_path / "saved.blend"
    status = visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", "24", "--directions", "16",
                                "--bounces", "1", "--report", str(report_path), "--save", str(saved),
                                "--no-progress"])
    assert status == 0
    assert digest(vdb_path) == before
    for grid in ("scattered", "direct", "indirect", "emission", "density", "volume"):
        assert (out / "Cloud" / f"{grid}.vdb").is_file()
    report = json.loads(report_path.read_text())
    entry = report["volumes"][0]
    # openvdb stores the active voxels only: the file's grid is the sphere's bounding box,
    # native voxels 4..19, which is the bake's grid (index t is native t + 4).
    low, count = 4, SIDE - 8
    assert entry["name"] == "Cloud" and entry["grid"] == [count] * 3 and entry["output"] == "Cloud (VisiBake)"
    assert entry["active_voxels"] > 1000

    scattered = vdb.read(str(out / "Cloud" / "direct.vdb"), "direct")
    values = np.zeros((count, count, count, 3), np.float32)
    scattered.copyToArray(values, ijk=(0, 0, 0))
    assert np.all(np.isfinite(values)) and values.min() >= 0
    # The sun shines straight down: the sphere's top voxel (native z 19 on the column x = y =
    # 11) sees it through half a voxel of fading density; a voxel lower down through the
    # voxels above it plus that half.
    column = 11 - low
    top = 19 - low
    expected_top = SUN_STRENGTH / (4 * math.pi) * math.exp(-DENSITY * 0.5 * VOXEL)
    assert values[column, column, top, 0] == pytest.approx(expected_top, rel=0.05)
    lower = top - 6
    depth = (top - lower + 0.5) * VOXEL
    assert values[column, column, lower, 0] == pytest.approx(
        SUN_STRENGTH / (4 * math.pi) * math.exp(-DENSITY * depth), rel=0.05)
    bounced = read_grid(vdb, out / "Cloud" / "indirect.vdb", "indirect", (count, count, count, 3))
    assert np.all(np.isfinite(bounced)) and bounced.min() >= 0 and bounced.max() > 0  # one bounce of light
    # Written in the source grid's index space: the same transform.
    assert np.allclose(scattered.transform.indexToWorld((1.0, 2.0, 3.0)),
                       (0.5 + 0.1 * (1 + low), -0.3 + 0.1 * (2 + low), 0.2 + 0.1 * (3 + low)))

    source = bpy.data.objects["Cloud"]
    assert bpy.path.abspath(source.data.filepath) == str(vdb_path)
    assert source.get("visibake_volume_of") is None
    baked = bpy.data.objects["Cloud (VisiBake)"]
    assert baked.get("visibake_volume_of") == "Cloud"
    assert np.allclose(np.array(baked.matrix_world), np.array(source.matrix_world))
    kinds = {node.bl_idname for node in baked.active_material.node_tree.nodes}
    assert {"ShaderNodeVolumeAbsorption", "ShaderNodeEmission", "ShaderNodeAttribute"} <= kinds
    baked.data.grids.load()
    assert {g.name for g in baked.data.grids} == {"density", "emission"}
    assert saved.is_file()

    # Baking again replaces VisiBake's own object, and makes no second one.
    assert visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", "12", "--directions", "8",
                              "--save", str(saved), "--no-progress"]) == 0
    bpy.ops.wm.open_mainfile(filepath=str(saved))
    assert [o.name for o in bpy.data.objects if o.type == "VOLUME"] == ["Cloud", "Cloud (VisiBake)"]


def test_a_finer_grid_is_box_averaged_to_the_resolution(visibake, vdb, cloud_blend, tmp_path):
    blend, _ = cloud_blend
    out = tmp_path / "out"
    assert visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", "8", "--directions", "8",
                              "--no-progress"]) == 0
    density = vdb.read(str(out / "Cloud" / "density.vdb"), "density")
    low, high = density.evalActiveVoxelBoundingBox()
    assert np.all(np.array(high) - np.array(low) + 1 <= 8)
    # The file's 16^3 voxels (native 4..19), two per voxel of the bake: the centre of bake
    # voxel 0 is between native voxels 4 and 5.
    assert np.allclose(density.transform.indexToWorld((0.0, 0.0, 0.0)), (0.5 + 0.45, -0.3 + 0.45, 0.2 + 0.45))


@pytest.mark.parametrize("case, message", [
    ("missing file", "was not found"),
    ("no density grid", "has no 'density' grid"),
    ("NaN density", "NaN or infinite"),
    ("negative density", "negative"),
    ("huge grid", "more than VisiBake"),
    ("empty grid", "empty"),
    ("a user object in the way", "is not VisiBake's"),
])
def test_bad_volumes_exit_2_with_the_reason_and_write_nothing(visibake, vdb, clean_scene, tmp_path, capfd, case,
                                                              message):
    black_world()
    sun(SUN_STRENGTH)
    path = tmp_path / "bad.vdb"
    if case == "no density grid":
        write_vdb(vdb, path, name="heat")
    elif case == "NaN density":
        grid = vdb.FloatGrid()
        grid.name = "density"
        grid.copyFromArray(np.ones((8, 8, 8), np.float32), ijk=(0, 0, 0))
        grid.getAccessor().setValueOn((3, 4, 5), float("nan"))
        vdb.write(str(path), grids=[grid])
    elif case == "negative density":
        write_vdb(vdb, path, -np.ones((8, 8, 8)))
    elif case == "huge grid":
        grid = vdb.FloatGrid()
        grid.name = "density"
        accessor = grid.getAccessor()
        accessor.setValueOn((0, 0, 0), 1.0)
        accessor.setValueOn((999_999, 999_999, 999_999), 1.0)
        vdb.write(str(path), grids=[grid])
    elif case == "empty grid":
        grid = vdb.FloatGrid()
        grid.name = "density"
        vdb.write(str(path), grids=[grid])
    elif case in ("a user object in the way",):
        write_vdb(vdb, path)
        bpy.context.scene.collection.objects.link(bpy.data.objects.new("Cloud (VisiBake)", None))
    volume_scene(path)
    blend = tmp_path / "bad.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    out = tmp_path / "out"
    assert visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", "16", "--directions", "8",
                              "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert err and message in err[-1], err
    assert not out.exists() or not list(out.rglob("*.vdb"))
    assert "Cloud (VisiBake)" not in bpy.data.objects or case == "a user object in the way"


def test_a_scene_without_volumes_is_refused(visibake, vdb, clean_scene, tmp_path, capfd):
    black_world()
    blend = tmp_path / "empty.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    assert visibake.cli.main(["volume", str(blend), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert "no Volume object" in capfd.readouterr().err


def read_grid(vdb, path, name, shape):
    grid = vdb.read(str(path), name)
    values = np.zeros(shape, np.float32)
    grid.copyToArray(values, ijk=(0, 0, 0))
    return values


def test_the_panel_s_bake_volume_does_what_the_command_does(visibake, vdb, cloud_blend, tmp_path):
    blend, _ = cloud_blend
    assert visibake.cli.main(["volume", str(blend), "--out", str(tmp_path / "cli"), "--resolution", "12",
                              "--directions", "8", "--bounces", "2", "--no-progress"]) == 0
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    props = bpy.context.scene.visibake
    props.volume_resolution, props.volume_directions, props.volume_bounces = 12, 8, 2
    props.output_dir = str(tmp_path / "panel")
    cloud = bpy.data.objects["Cloud"]
    cloud.select_set(True)
    assert bpy.ops.visibake.bake_volume() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_volume_report"])
    assert report["volumes"][0]["output"] == "Cloud (VisiBake)"
    for grid in ("scattered", "indirect"):
        from_panel = read_grid(vdb, tmp_path / "panel" / "Cloud" / f"{grid}.vdb", grid, (8, 8, 8, 3))
        from_cli = read_grid(vdb, tmp_path / "cli" / "Cloud" / f"{grid}.vdb", grid, (8, 8, 8, 3))
        assert from_panel.any()
        np.testing.assert_array_equal(from_panel, from_cli)


def test_the_modal_volume_bake_runs_its_tables_on_a_worker_and_a_cancel_leaves_nothing(visibake, vdb, cloud_blend,
                                                                                      tmp_path):
    import time

    blend, _ = cloud_blend
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    adapter = visibake.operators.adapter
    progress_module = importlib.import_module(extension_module_name() + ".core.pipeline.progress")
    cloud = bpy.data.objects["Cloud"]
    for cancel in (False, True):
        progress = progress_module.Progress()
        job = adapter.volume_job.VolumeJob(bpy.context.scene, [cloud], str(tmp_path / f"out{cancel}"), 16, 16, 1,
                                           progress=progress)
        modal = adapter.modal.ModalBake(job, progress)
        assert not modal.tick()  # read on the main thread; the tables and light now run on a worker
        assert modal._thread is not None
        if cancel:
            progress.cancel()
        while not modal.tick():
            time.sleep(0.02)
        if cancel:
            assert type(modal.error).__name__ == "Cancelled"
            assert not list((tmp_path / f"out{cancel}").rglob("*.vdb"))
            assert "Cloud (VisiBake)" not in bpy.data.objects
        else:
            assert modal.error is None and modal.outcome.report["volumes"][0]["output"] == "Cloud (VisiBake)"
            assert (tmp_path / f"out{cancel}" / "Cloud" / "volume.vdb").is_file()
            adapter.volume_io.remove_baked_object(bpy.data.objects["Cloud (VisiBake)"])


def roof_over_low_x(name="Roof", casts_shadow=True):
    """A plane high above the cloud covering native voxel columns x <= 11 (world x < 1.62)."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-10.0, -10.0, 5.0), (1.62, -10.0, 5.0), (1.62, 10.0, 5.0), (-10.0, 10.0, 5.0)], [],
                     [(0, 1, 2, 3)])
    obj = bpy.data.objects.new(name, mesh)
    obj.visible_shadow = casts_shadow
    bpy.context.scene.collection.objects.link(obj)
    return obj


@pytest.mark.parametrize("casts_shadow", [True, False])
def test_a_mesh_between_the_sun_and_the_cloud_shadows_it_unless_it_casts_no_shadow(
        visibake, vdb, cloud_blend, tmp_path, casts_shadow):
    blend, _ = cloud_blend
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    roof_over_low_x(casts_shadow=casts_shadow)
    roofed = tmp_path / "roofed.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(roofed), copy=True)
    out, report_path = tmp_path / "out", tmp_path / "report.json"
    status = visibake.cli.main(["volume", str(roofed), "--out", str(out), "--resolution", "24", "--directions", "16",
                                "--bounces", "0", "--report", str(report_path), "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    assert report["occluders"] == {"meshes": 1, "triangles": 2}
    count, low = SIDE - 8, 4
    direct = read_grid(vdb, out / "Cloud" / "direct.vdb", "direct", (count, count, count, 3))
    density = read_grid(vdb, out / "Cloud" / "density.vdb", "density", (count, count, count))
    under = np.arange(count)[:, None, None] + low <= 11
    shaded = direct[..., 0][under & (density > 0)]
    sunny = direct[..., 0][~under & (density > 0)]
    assert sunny.max() > 0.1 * SUN_STRENGTH / (4 * math.pi)
    if casts_shadow:
        assert shaded.max() == 0.0
    else:
        assert shaded.max() > 0.1 * SUN_STRENGTH / (4 * math.pi)


def test_a_second_bake_after_the_sun_changed_reads_the_cached_tables(visibake, vdb, cloud_blend, tmp_path):
    blend, _ = cloud_blend
    runs = []
    for strength in (SUN_STRENGTH, 2 * SUN_STRENGTH):
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        next(o for o in bpy.context.scene.objects if o.type == "LIGHT").data.energy = strength
        changed = tmp_path / "relit.blend"  # one file, as a user would save it (the cache is per file)
        bpy.ops.wm.save_as_mainfile(filepath=str(changed), copy=True)
        out, report_path = tmp_path / f"out{strength}", tmp_path / f"report{strength}.json"
        status = visibake.cli.main(["volume", str(changed), "--out", str(out), "--resolution", "24",
                                    "--directions", "16", "--bounces", "1", "--report", str(report_path),
                                    "--cache-dir", str(tmp_path / "cache"), "--no-progress"])
        assert status == 0
        count = SIDE - 8
        runs.append((json.loads(report_path.read_text()),
                     read_grid(vdb, out / "Cloud" / "scattered.vdb", "scattered", (count, count, count, 3))))
    (first, once), (second, twice) = runs
    assert first["volumes"][0]["tables"] == "built" and second["volumes"][0]["tables"] == "cached"
    assert first["cache"] == second["cache"] == str(tmp_path / "cache")
    # The light is linear in the sun: the same tables give exactly twice the light.
    np.testing.assert_allclose(twice, 2 * once, rtol=1e-5, atol=1e-9)
    assert once.max() > 0


def test_no_cache_builds_the_tables_and_writes_no_cache(visibake, vdb, cloud_blend, tmp_path):
    blend, _ = cloud_blend
    report_path = tmp_path / "report.json"
    status = visibake.cli.main(["volume", str(blend), "--out", str(tmp_path / "out"), "--resolution", "16",
                                "--directions", "8", "--report", str(report_path), "--cache-dir",
                                str(tmp_path / "cache"), "--no-cache", "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    assert report["volumes"][0]["tables"] == "built" and report["cache"] is None
    assert not (tmp_path / "cache").exists()


def test_the_gpu_sweep_gives_the_cpu_kernel_s_light(visibake, vdb, cloud_blend, tmp_path):
    """``--device gpu`` runs the lamps' slice sweeps on Blender's gpu module (llvmpipe here);
    the grids match the CPU kernels' within float32 rounding of the carried depth."""
    blend, _ = cloud_blend
    count = SIDE - 8
    grids, reports = {}, {}
    for name in ("cpu", "gpu"):
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        report_path = tmp_path / f"report_{name}.json"
        status = visibake.cli.main(["volume", str(blend), "--out", str(tmp_path / name), "--resolution", "24",
                                    "--directions", "8", "--bounces", "1", "--device", name, "--no-cache",
                                    "--report", str(report_path), "--no-progress"])
        assert status == 0
        reports[name] = json.loads(report_path.read_text())
        grids[name] = read_grid(vdb, tmp_path / name / "Cloud" / "scattered.vdb", "scattered", (count, count, count, 3))
    assert reports["gpu"]["device"]["used"] == "gpu" and reports["cpu"]["device"]["used"] == "cpu"
    assert grids["cpu"].max() > 0
    np.testing.assert_allclose(grids["gpu"], grids["cpu"], rtol=1e-4, atol=1e-6 * grids["cpu"].max())


def test_a_white_floor_under_the_cloud_lights_its_underside(visibake, vdb, cloud_blend, tmp_path):
    """The sun lights a white floor below the cloud, and the floor's reflection reaches the
    cloud from below (in the first bounce, as Cycles counts it): its lowest voxels get more
    light than without the floor, its top ones (which the floor reaches through the cloud, or
    past it at grazing angles) less."""
    blend, _ = cloud_blend
    count = SIDE - 8
    grids = {}
    for name in ("alone", "floored"):
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        if name == "floored":
            mesh = bpy.data.meshes.new("Floor")
            mesh.from_pydata([(-20, -20, 1.0), (20, -20, 1.0), (20, 20, 1.0), (-20, 20, 1.0)], [], [(0, 1, 2, 3)])
            material = bpy.data.materials.new("White")
            material.diffuse_color = (1.0, 1.0, 1.0, 1.0)
            compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
            compat.ensure_node_tree(material)
            material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (1.0, 1.0, 1.0, 1.0)
            mesh.materials.append(material)
            bpy.context.scene.collection.objects.link(bpy.data.objects.new("Floor", mesh))
        changed = tmp_path / f"{name}.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(changed), copy=True)
        status = visibake.cli.main(["volume", str(changed), "--out", str(tmp_path / name), "--resolution", "24",
                                    "--directions", "32", "--bounces", "1", "--no-progress"])
        assert status == 0
        grids[name] = read_grid(vdb, tmp_path / name / "Cloud" / "indirect.vdb", "indirect",
                                (count, count, count, 3))
    column = count // 2
    bottom, top = 0, count - 1  # native z 4 and 19: world z 1.6 and 3.1 (the floor is at z 1)
    gained = grids["floored"][column, column, :, 0] - grids["alone"][column, column, :, 0]
    assert gained.min() >= -1e-7
    # The floor's radiance is 3 / pi under the sun; the bottom voxel sees it over about half its sky.
    assert gained[bottom] > 0.1 * 3.0 / np.pi / 2
    assert gained[top] < 0.5 * gained[bottom]
