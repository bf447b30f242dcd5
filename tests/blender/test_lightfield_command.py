"""`visibake lightfield` and Render Light Field: a baked scene seen from the HCI grid of views,
written in the HCI layout and read back, with ground truth checked against a known plane
(issue 19)."""
import importlib
import json
import math

import bpy

import numpy as np
import pytest

from blender_support import extension_module_name
from bpy_scenes import black_world, cube, grid, material, mesh_object, point
from tools.blender_compat import compat

PLANE_DEPTH = 3.0
SQUARE_DEPTH = 2.0
BASELINE_MM = 200.0
FOCUS_M = 3.0
WIDTH, HEIGHT = 64, 48
FAST_BAKE = ["--directions", "16", "--resolution", "32", "--bounces", "0", "--no-cache", "--no-progress"]


@pytest.fixture
def lf(visibake):
    name = extension_module_name()
    return (importlib.import_module(name + ".core.lightfield.hci"),
            importlib.import_module(name + ".core.lightfield.cameras"),
            importlib.import_module(name + ".core.appearance.btf"))


def plane_scene(path, world_grey=None, far_cube=False):
    """A white ground at z = 0 under a camera 3 m above it looking straight down (its axis is
    -Z), a small bright emissive square 2 m below the camera, a lamp; saved as ``path``."""
    bpy.ops.wm.read_homefile(use_empty=True)
    if world_grey is None:
        black_world()
    else:
        world = bpy.data.worlds.new("Grey")
        compat.ensure_node_tree(world)
        world.node_tree.nodes["Background"].inputs["Color"].default_value = (world_grey, world_grey, world_grey, 1)
        bpy.context.scene.world = world
    mesh_object("Ground", grid(8.0, 4), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Square", grid(0.08), material("Glow", (0.0, 0.0, 0.0), emission=(1.0, 1.0, 1.0), strength=20.0),
                location=(0.0, 0.0, PLANE_DEPTH - SQUARE_DEPTH))
    if far_cube:
        mesh_object("FarAway", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(60.0, 0.0, 0.0))
    point(400.0, (0.7, 0.4, 2.0), name="Lamp")
    data = bpy.data.cameras.new("Camera")
    data.lens, data.sensor_width, data.sensor_fit = 50.0, 36.0, "AUTO"
    camera = bpy.data.objects.new("Camera", data)
    camera.location = (0.0, 0.0, PLANE_DEPTH)
    bpy.context.scene.collection.objects.link(camera)
    bpy.context.scene.camera = camera
    bpy.context.scene.view_settings.view_transform = "Standard"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def grid_options(views="3x3", size=f"{WIDTH}x{HEIGHT}"):
    return ["--views", views, "--image-size", size, "--baseline-mm", str(BASELINE_MM), "--focus-distance-m",
            str(FOCUS_M)]


def bright_centroid(image):
    """(x, y) pixel centroid of the emissive square's pixels (row 0 at the top)."""
    luminance = image.mean(axis=2)
    mask = luminance > 0.5 * luminance.max()
    rows, columns = np.nonzero(mask)
    weights = luminance[mask]
    return np.average(columns, weights=weights), np.average(rows, weights=weights)


def test_a_baked_plane_gives_the_hci_layout_and_its_ground_truth(visibake, lf, tmp_path, capfd):
    hci, cameras, btf = lf
    blend = plane_scene(tmp_path / "scene.blend", far_cube=True)
    out = tmp_path / "lightfield"
    report_path = tmp_path / "report.json"
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(out), "--bake-first", "--report",
                              str(report_path)] + grid_options() + FAST_BAKE) == 0
    printed = capfd.readouterr().out
    assert "skipped 1 object(s) no view sees: FarAway" in printed
    field = hci.read_light_field(str(out))
    assert len(field["views"][".png"]) == 9 and len(field["views"][".exr"]) == 9
    params = field["parameters"]
    assert (params["num_cams_x"], params["num_cams_y"]) == (3, 3)
    assert (params["image_resolution_x_px"], params["image_resolution_y_px"]) == (WIDTH, HEIGHT)
    assert params["baseline_mm"] == BASELINE_MM and params["focus_distance_m"] == FOCUS_M
    camera, grid_spec = hci.camera_and_grid(params)
    # The ground truth: the plane at its depth with zero disparity (it is the focus plane),
    # the square nearer, with the disparity HCI's formula gives.
    depth = field["depth"]
    assert depth.shape == (HEIGHT, WIDTH)
    assert np.allclose(depth[2:8, 2:8], PLANE_DEPTH, rtol=1e-4)
    assert depth[HEIGHT // 2, WIDTH // 2] == pytest.approx(SQUARE_DEPTH, rel=1e-4)
    expected = cameras.depth_to_disparity(SQUARE_DEPTH, camera, grid_spec)
    assert field["disparity"][HEIGHT // 2, WIDTH // 2] == pytest.approx(expected, rel=1e-4)
    assert np.allclose(field["disparity"][2:8, 2:8], 0.0, atol=1e-4)
    # The views agree: the square moves by -d pixels per column and per row.
    images = [btf.read_exr_rgb(path)[::-1] for path in field["views"][".exr"]]
    centre_x, centre_y = bright_centroid(images[4])
    right_x, right_y = bright_centroid(images[5])
    below_x, below_y = bright_centroid(images[7])
    assert right_x - centre_x == pytest.approx(-expected, abs=0.15)
    assert below_y - centre_y == pytest.approx(-expected, abs=0.15)
    assert right_y == pytest.approx(centre_y, abs=0.05) and below_x == pytest.approx(centre_x, abs=0.05)
    # The emitter shows its own radiance; the lit ground its baked light (not black, finite).
    assert images[4][HEIGHT // 2, WIDTH // 2].mean() == pytest.approx(20.0, rel=0.05)
    assert 0.01 < images[4][3, 3].mean() < 5.0
    # The PNG is the EXR through the scene's view transform (Standard: the sRGB curve).
    png = btf.read_png(field["views"][".png"][4])[::-1]
    dim = images[4] < 0.9
    assert np.allclose(png[dim], images[4][dim], atol=0.01)
    report = json.loads(report_path.read_text())
    assert report["views"] == 9 and report["bake"]["skipped_unseen"] == ["FarAway"]
    # What no view sees is neither drawn nor warned about as unbaked.
    assert report["objects"]["unseen"] == ["FarAway"] and "FarAway" not in report["objects"]["unbaked"]
    assert not any("FarAway" in warning for warning in report["warnings"])
    assert json.loads((out / "lightfield.json").read_text())["files"]


def test_the_world_is_seen_where_no_surface_is(visibake, lf, tmp_path):
    hci, _, btf = lf
    blend = plane_scene(tmp_path / "scene.blend", world_grey=0.25)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    camera = bpy.data.objects["Camera"]
    camera.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # looking along +Y, over the ground: half sky
    far = camera.data.clip_end
    bpy.ops.wm.save_mainfile()
    out = tmp_path / "sky"
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(out), "--views", "1x1", "--image-size", "32x32",
                              "--no-progress"]) == 0
    image = btf.read_exr_rgb(str(out / "input_Cam000.exr"))[::-1]
    assert np.allclose(image[2:12], 0.25, rtol=0.02)  # the upper half: the uniform world
    field = hci.read_light_field(str(out))
    # Where no surface is seen, the far clip distance: finite, as HCI's tools expect (issue 51).
    assert np.all(field["depth"][2:12] == np.float32(far))
    assert np.all(np.isfinite(field["depth"])) and np.all(np.isfinite(field["disparity"]))
    np.testing.assert_allclose(field["disparity"][2:12], hci.depth_to_disparity(
        far, *hci.camera_and_grid(field["parameters"])), rtol=1e-5)


def test_stanford_names_and_refusals(visibake, lf, tmp_path, capfd):
    blend = plane_scene(tmp_path / "scene.blend")
    out = tmp_path / "stanford"
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(out), "--format", "stanford",
                              "--no-progress"] + grid_options("2x1", "16x16")) == 0
    names = sorted(p.name for p in out.glob("*.png"))
    assert len(names) == 2 and names[0].startswith("out_00_00_") and names[1].startswith("out_00_01_")
    assert "object(s) have no baked lighting" in capfd.readouterr().err
    # Bad input: exit 2 with the reason, nothing written.
    for arguments, message in ((["--views", "3by3"], "--views '3by3'"), (["--camera", "Nope"], "no object"),
                               (["--camera", "Ground"], "needs a camera"), (["--baseline-mm", "0"], "--baseline-mm"),
                               (["--image-size", "4x4"], "--image-size"),
                               (["--supersampling", "5"], "--supersampling")):
        target = tmp_path / "refused"
        assert visibake.cli.main(["lightfield", str(blend), "--out", str(target), "--no-progress"] + arguments) == 2
        assert message in capfd.readouterr().err
        assert not target.exists()
    # A folder with someone else's file is refused and left as it was.
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(mine), "--no-progress"]
                             + grid_options("1x1", "16x16")) == 2
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    # Its own folder is VisiBake's to write again, and a smaller grid leaves no stale view.
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(out), "--format", "stanford",
                              "--supersampling", "2", "--no-progress"] + grid_options("1x1", "16x16")) == 0
    assert len(list(out.glob("*.png"))) == 1
    assert json.loads((out / "lightfield.json").read_text())["report"]["supersampling"] == 2


def test_the_panel_renders_the_light_field_of_the_scene_camera(visibake, lf, tmp_path):
    hci, _, _ = lf
    blend = plane_scene(tmp_path / "scene.blend")
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    props = bpy.context.scene.visibake
    props.output_dir = str(tmp_path / "outputs")
    (tmp_path / "outputs").mkdir()
    props.lightfield_columns, props.lightfield_rows = 2, 2
    props.lightfield_width, props.lightfield_height = 16, 16
    assert bpy.ops.visibake.render_lightfield() == {"FINISHED"}
    field = hci.read_light_field(str(tmp_path / "outputs" / "lightfield"))
    assert len(field["views"][".png"]) == 4
    assert "visibake_lightfield_report" in bpy.context.scene
    bpy.context.scene.camera = None
    with pytest.raises(RuntimeError, match="needs a camera"):
        bpy.ops.visibake.render_lightfield()


def test_views_are_planned_from_where_a_script_just_moved_things(visibake, tmp_path):
    """A script's move leaves matrix_world stale until the view layer is evaluated: the grid
    and the seen objects must follow the new places, not the last evaluated ones."""
    io = importlib.import_module(extension_module_name() + ".operators.adapter.lightfield_io")
    plane_scene(tmp_path / "scene.blend", far_cube=True)
    scene = bpy.context.scene
    camera = bpy.data.objects["Camera"]
    far = bpy.data.objects["FarAway"]
    camera.location = (1.0, 2.0, PLANE_DEPTH)
    far.location = (1.0, 2.0, 0.5)  # now right under the camera
    _, _, views, clip = io.plan_views(scene, None, (3, 3), BASELINE_MM, FOCUS_M, (WIDTH, HEIGHT), [])
    assert np.allclose(np.linalg.inv(views[4].view_matrix)[:3, 3], (1.0, 2.0, PLANE_DEPTH))
    seen, unseen = io.objects_in_views([far], views, *clip)
    assert seen == [far] and unseen == []


def test_resolution_from_views_gives_a_texel_per_pixel_at_the_nearest_depth(visibake, tmp_path, capfd):
    """The ground, fronto-parallel 3 m from every view, gets f / 3 texels per metre (f: the focal
    length in pixels) over its full-square UV map; the small emitter, below the smallest
    camera-sized atlas, gets that; nothing is sized above --resolution."""
    blend = plane_scene(tmp_path / "scene.blend")
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    ground_area = sum(polygon.area for polygon in bpy.data.objects["Ground"].data.polygons)
    report_path = tmp_path / "report.json"
    bake = ["--directions", "16", "--bounces", "0", "--no-cache", "--no-progress"]
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(tmp_path / "lf"), "--bake-first",
                              "--resolution-from-views", "--resolution", "1024", "--report", str(report_path)]
                             + grid_options() + bake) == 0
    focal_pixels = 50.0 / 36.0 * WIDTH
    expected = math.ceil(math.sqrt(ground_area) * focal_pixels / PLANE_DEPTH)
    sizes = json.loads(report_path.read_text())["bake"]["resolutions"]
    assert sizes["Ground"] == [expected, expected] and expected < 1024
    assert sizes["Square"] == [16, 16]
    assert f"atlases of Ground {expected}" in capfd.readouterr().out
    # It sizes a bake: without --bake-first it is refused.
    assert visibake.cli.main(["lightfield", str(blend), "--out", str(tmp_path / "no"), "--resolution-from-views",
                              "--no-progress"] + grid_options()) == 2
    assert "needs --bake-first" in capfd.readouterr().err
