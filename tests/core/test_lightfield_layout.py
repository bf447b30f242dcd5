"""The light field's camera grid and HCI files (core.lightfield): view order, parallel off-axis cameras
whose projections give HCI's disparity, parameters.cfg, PFM byte layout and the folder reader."""
import configparser
import math
import os

import numpy as np
import pytest

from core.lightfield.cameras import (
    CentreCamera,
    LightFieldGrid,
    depth_from_depth_buffer,
    depth_to_disparity,
    disparity_per_inverse_depth,
    disparity_to_depth,
    euler_xyz_from_rotation,
    grid_views,
    rotation_from_euler_xyz,
)
from core.lightfield.hci import (
    DEPTH_FILE,
    DISPARITY_FILE,
    PARAMETERS_FILE,
    camera_and_grid,
    disparity_range,
    read_light_field,
    read_parameters,
    read_pfm,
    view_file_name,
    write_ground_truth,
    write_parameters,
    write_pfm,
)

# The HCI dataset's "dino" scene (evaluation-toolkit data/training/dino/parameters.cfg).
DINO_EULER = (1.3526215553283691, 0.016077132895588875, -0.22883984446525574)
DINO_POSITION = (-1.4951000213623047, -6.506796836853027, 2.3541150093078613)


def dino_camera(resolution=(512, 512)) -> CentreCamera:
    return CentreCamera(position_m=DINO_POSITION, rotation=rotation_from_euler_xyz(*DINO_EULER),
                        focal_length_mm=100.0, sensor_size_mm=35.0, resolution_x_px=resolution[0],
                        resolution_y_px=resolution[1], fstop=300.0)


def dino_grid(nx=9, ny=9) -> LightFieldGrid:
    return LightFieldGrid(num_cams_x=nx, num_cams_y=ny, baseline_mm=60.0, focus_distance_m=6.900000095367432)


def project(view, points):
    """Pixel (x right, y down, from the image's top-left corner) and NDC depth of world points
    through the view's OpenGL matrices."""
    homogeneous = np.concatenate([np.atleast_2d(points), np.ones((len(np.atleast_2d(points)), 1))], axis=1)
    clip = (view.projection_matrix @ view.view_matrix @ homogeneous.T).T
    ndc = clip[:, :3] / clip[:, 3:]
    return ndc, clip[:, 3]


def to_pixels(ndc, camera):
    return np.stack([(ndc[:, 0] + 1.0) * camera.resolution_x_px / 2.0,
                     (1.0 - ndc[:, 1]) * camera.resolution_y_px / 2.0], axis=1)


def point_ahead(camera, depth_m, right_m=0.0, up_m=0.0):
    """The world point ``depth_m`` in front of the centre camera (along its optical axis), moved in its
    image plane."""
    return camera.position_m + camera.rotation @ np.array([right_m, up_m, -depth_m])


@pytest.mark.parametrize("n", [3, 9])
def test_views_run_row_by_row_from_the_top_left(n):
    camera, grid = dino_camera(), dino_grid(n, n)
    views = grid_views(camera, grid)
    assert len(views) == n * n == grid.view_count
    right, up = camera.rotation[:, 0], camera.rotation[:, 1]
    half = (n - 1) / 2 * 0.06
    for view in views:
        assert view.index == view.row * n + view.column
        expected = camera.position_m + ((view.column - (n - 1) / 2) * right - (view.row - (n - 1) / 2) * up) * 0.06
        np.testing.assert_allclose(view.position_m, expected, atol=1e-12)
    # The first view is the top-left one (seen from the centre camera), the last the bottom-right.
    np.testing.assert_allclose(views[0].offset_m, [-half, half])
    np.testing.assert_allclose(views[-1].offset_m, [half, -half])
    np.testing.assert_allclose(views[1].offset_m - views[0].offset_m, [0.06, 0.0])
    np.testing.assert_allclose(views[n].offset_m - views[0].offset_m, [0.0, -0.06])
    centre = views[grid.centre_index]
    assert grid.centre_index == (n * n - 1) // 2 and (centre.row, centre.column) == ((n - 1) // 2, (n - 1) // 2)
    np.testing.assert_allclose(centre.position_m, camera.position_m, atol=1e-12)
    assert centre.shift_x == 0.0 and centre.shift_y == 0.0


def test_non_square_grid_and_single_view():
    views = grid_views(dino_camera(), dino_grid(4, 3))
    assert [(v.row, v.column) for v in views[:5]] == [(0, 0), (0, 1), (0, 2), (0, 3), (1, 0)]
    np.testing.assert_allclose(views[0].offset_m, [-0.09, 0.06])
    (only,) = grid_views(dino_camera(), dino_grid(1, 1))
    assert only.index == 0 and only.shift_x == 0.0
    np.testing.assert_allclose(only.position_m, DINO_POSITION)


def test_axes_are_parallel_and_the_views_look_where_the_centre_camera_looks():
    camera = dino_camera()
    axis = camera.rotation @ [0.0, 0.0, -1.0]
    for view in grid_views(camera, dino_grid(3, 3)):
        np.testing.assert_array_equal(view.rotation, camera.rotation)
        np.testing.assert_allclose(view.view_matrix[:3, :3].T @ [0.0, 0.0, -1.0], axis, atol=1e-12)
        np.testing.assert_allclose(view.camera_to_world @ view.view_matrix, np.eye(4), atol=1e-12)


def test_shift_is_the_hci_addons_and_matches_the_projection():
    camera, grid = dino_camera((640, 480)), dino_grid(5, 5)
    factor = camera.focal_length_mm / camera.sensor_size_mm / grid.focus_distance_m  # the add-on's
    for view in grid_views(camera, grid):
        x_pos, y_pos = view.offset_m
        assert view.shift_x == pytest.approx(-x_pos * factor, abs=1e-12)
        assert view.shift_y == pytest.approx(-y_pos * factor, abs=1e-12)
        # Blender's shift moves the window by shift * max(res) pixels (sensor fit AUTO).
        ndc, _ = project(view, point_ahead(camera, 3.0, *(view.offset_m)))  # straight ahead of this view
        pixel = to_pixels(ndc, camera)[0]
        np.testing.assert_allclose(pixel - [320.0, 240.0], [-view.shift_x * 640, view.shift_y * 640], atol=1e-6)


@pytest.mark.parametrize("resolution,size", [((512, 512), (3, 3)), ((640, 480), (5, 4)), ((300, 500), (9, 9))])
def test_projected_points_move_by_the_predicted_disparity(resolution, size):
    """A real geometric check: the pixel offset of one point between neighbouring views' projections
    is HCI's disparity (x right: -d per column; y down: -d per row), 0 on the focus plane."""
    camera, grid = dino_camera(resolution), dino_grid(*size)
    views = grid_views(camera, grid, clip_start_m=0.05, clip_end_m=500.0)
    nx = grid.num_cams_x
    rng = np.random.default_rng(5)
    for depth in (0.8, 3.0, grid.focus_distance_m, 25.0, 400.0):
        points = np.array([point_ahead(camera, depth, *(rng.uniform(-0.3, 0.3, 2) * depth / 5)) for _ in range(4)])
        expected = depth_to_disparity(depth, camera, grid)
        pixels = {v.index: to_pixels(project(v, points)[0], camera) for v in views}
        for view in views:
            if view.column + 1 < nx:
                step = pixels[view.index + 1] - pixels[view.index]
                np.testing.assert_allclose(step[:, 0], -expected, atol=1e-6)
                np.testing.assert_allclose(step[:, 1], 0.0, atol=1e-6)
            if view.row + 1 < grid.num_cams_y:
                step = pixels[view.index + nx] - pixels[view.index]
                np.testing.assert_allclose(step[:, 1], -expected, atol=1e-6)
                np.testing.assert_allclose(step[:, 0], 0.0, atol=1e-6)
    assert depth_to_disparity(grid.focus_distance_m, camera, grid) == pytest.approx(0.0, abs=1e-12)
    assert depth_to_disparity(0.8, camera, grid) > 0.0 > depth_to_disparity(25.0, camera, grid)


def test_clip_space_depth_is_the_optical_axis_depth():
    camera = dino_camera()
    view = grid_views(camera, dino_grid(3, 3), clip_start_m=0.1, clip_end_m=100.0)[2]
    for depth in (0.1, 1.0, 7.5, 100.0):
        ndc, w = project(view, point_ahead(camera, depth, 0.2, -0.1))
        assert w[0] == pytest.approx(depth)
        assert depth_from_depth_buffer((ndc[0, 2] + 1.0) / 2.0, 0.1, 100.0) == pytest.approx(depth)
    assert project(view, point_ahead(camera, 0.1))[0][0, 2] == pytest.approx(-1.0)
    assert project(view, point_ahead(camera, 100.0))[0][0, 2] == pytest.approx(1.0)


def test_depth_and_disparity_are_hcis_and_round_trip():
    camera, grid = dino_camera(), dino_grid()
    depth = np.array([[0.5, 2.0, 6.9], [10.0, 123.4, np.inf]])
    # The evaluation toolkit's BaseScene.depth2disp / disp2depth, written out.
    f = (grid.baseline_mm / 1000.0) * camera.focal_length_mm * 512
    hci_disp = (f * grid.focus_distance_m / depth - f) / grid.focus_distance_m / camera.sensor_size_mm
    disparity = depth_to_disparity(depth, camera, grid)
    np.testing.assert_allclose(disparity, hci_disp, rtol=1e-12, atol=1e-12)
    q = grid.baseline_mm * camera.focal_length_mm * 512
    with np.errstate(divide="ignore"):  # infinity's disparity: 1 / 0 in their formula as well
        hci_depth = 1.0 / ((1000.0 * camera.sensor_size_mm) * disparity / q + 1.0 / grid.focus_distance_m)
    np.testing.assert_allclose(hci_depth, depth, rtol=1e-12)
    np.testing.assert_allclose(disparity_to_depth(disparity, camera, grid), depth, rtol=1e-12)
    infinity = -disparity_per_inverse_depth(camera, grid) / grid.focus_distance_m
    assert disparity[1, 2] == pytest.approx(infinity)
    assert np.all(np.isinf(disparity_to_depth([infinity, infinity - 1.0], camera, grid)))
    with pytest.raises(ValueError, match="depth_m must be positive"):
        depth_to_disparity([1.0, 0.0], camera, grid)


def test_euler_angles_follow_blender_xyz():
    # Blender's (90, 0, -90) degrees camera looks along +X with +Z up (the Cycles manual's panorama hint).
    rotation = rotation_from_euler_xyz(math.pi / 2, 0.0, -math.pi / 2)
    np.testing.assert_allclose(rotation @ [0, 0, -1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rotation @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    for angles in (DINO_EULER, (0.3, -1.2, 2.9), (-2.0, 0.0, 0.1)):
        np.testing.assert_allclose(euler_xyz_from_rotation(rotation_from_euler_xyz(*angles)), angles, atol=1e-12)
    for locked in ((0.4, math.pi / 2, 0.7), (-0.4, -math.pi / 2, 1.1)):  # gimbal lock: same matrix back
        again = rotation_from_euler_xyz(*euler_xyz_from_rotation(rotation_from_euler_xyz(*locked)))
        np.testing.assert_allclose(again, rotation_from_euler_xyz(*locked), atol=1e-9)


def test_parameters_round_trip_and_read_as_hcis_tools_do(tmp_path):
    camera, grid = dino_camera((640, 480)), dino_grid(9, 7)
    path = str(tmp_path / PARAMETERS_FILE)
    write_parameters(path, camera, grid, disp_min=-1.9, disp_max=1.9, frustum_disp_min=-2.0, frustum_disp_max=2.0,
                     depth_map_scale=10.0, scene="dino", category="training", date="2017-03-14",
                     authors=("Ada", "Bob"), contact="a@b.c")
    params = read_parameters(path)
    assert params["image_resolution_x_px"] == 640 and params["num_cams_y"] == 7
    assert params["focus_distance_m"] == grid.focus_distance_m and params["disp_min"] == -1.9
    assert params["authors"] == ["Ada", "Bob"] and params["date"] == "2017-03-14"
    np.testing.assert_allclose([params[f"center_cam_r{a}_rad"] for a in "xyz"], DINO_EULER, atol=1e-12)
    again_camera, again_grid = camera_and_grid(params)
    assert again_grid == grid
    np.testing.assert_allclose(again_camera.rotation, camera.rotation, atol=1e-12)
    np.testing.assert_array_equal(again_camera.position_m, camera.position_m)
    assert (again_camera.focal_length_mm, again_camera.fstop) == (100.0, 300.0)
    # HCI's python-tools read_parameters: interpolating ConfigParser, int() and float() of the text.
    text = (tmp_path / PARAMETERS_FILE).read_text()
    assert text.startswith("[intrinsics]\nfocal_length_mm = 100.0\nimage_resolution_x_px = 640\n")
    hci = configparser.ConfigParser()
    hci.read_string(text)
    assert [s for s in hci.sections()] == ["intrinsics", "extrinsics", "meta"]
    for key in ("image_resolution_x_px", "image_resolution_y_px"):
        int(hci.get("intrinsics", key))
    for key in ("num_cams_x", "num_cams_y"):
        int(hci.get("extrinsics", key))
    for key in ("disp_min", "disp_max", "frustum_disp_min", "frustum_disp_max", "depth_map_scale", "cycles_seed"):
        float(hci.get("meta", key))
    for key in ("scene", "category", "date", "version", "authors", "contact"):
        hci.get("meta", key)


def test_parameters_refuse_what_hcis_readers_would_misread(tmp_path):
    camera, grid = dino_camera(), dino_grid()
    path = str(tmp_path / PARAMETERS_FILE)
    with pytest.raises(ValueError, match="'%'"):
        write_parameters(path, camera, grid, disp_min=-1.0, disp_max=1.0, scene="100% dino")
    with pytest.raises(ValueError, match="authors"):
        write_parameters(path, camera, grid, disp_min=-1.0, disp_max=1.0, authors=("A, B",))
    with pytest.raises(ValueError, match="disp_min"):
        write_parameters(path, camera, grid, disp_min=1.0, disp_max=-1.0)
    assert not os.listdir(tmp_path)
    (tmp_path / PARAMETERS_FILE).write_text("[intrinsics]\nfocal_length_mm = 100\n")
    with pytest.raises(ValueError, match=r"lacks \[intrinsics\] image_resolution_x_px"):
        read_parameters(path)


@pytest.mark.parametrize("shape", [(5, 7), (3, 1), (5, 7, 1), (4, 9, 3), (1, 1, 3)])
def test_pfm_round_trip(tmp_path, shape):
    data = np.random.default_rng(1).normal(size=shape).astype(np.float32)
    data.flat[0] = np.inf
    path = str(tmp_path / "map.pfm")
    write_pfm(path, data)
    back = read_pfm(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, data[:, :, 0] if shape[-1:] == (1,) and len(shape) == 3 else data)


def test_pfm_bytes_are_hcis_bottom_row_first(tmp_path):
    data = np.arange(15, dtype=np.float32).reshape(3, 5)  # 3 rows, 5 columns, top row 0..4
    path = tmp_path / "d.pfm"
    write_pfm(str(path), data)
    raw = path.read_bytes()
    header = b"Pf\n5 3\n-1\n"
    assert raw.startswith(header) and len(raw) == len(header) + 15 * 4
    stored = np.frombuffer(raw[len(header):], dtype="<f4").reshape(3, 5)
    np.testing.assert_array_equal(stored[0], data[2])  # the file starts with the image's bottom row
    np.testing.assert_array_equal(stored[2], data[0])
    colour = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    write_pfm(str(path), colour)
    raw = path.read_bytes()
    assert raw.startswith(b"PF\n3 2\n-1\n")
    np.testing.assert_array_equal(np.frombuffer(raw[10:22], dtype="<f4"), colour[1, 0])  # bottom-left pixel, RGB
    # A big-endian file (positive scale) with a comment, as other writers make them; the scale multiplies.
    big = b"Pf\n# made elsewhere\n2 2\n2.0\n" + np.array([1, 2, 3, 4], dtype=">f4").tobytes()
    path.write_bytes(big)
    np.testing.assert_array_equal(read_pfm(str(path)), [[6.0, 8.0], [2.0, 4.0]])


def test_pfm_refuses_bad_input(tmp_path):
    path = tmp_path / "bad.pfm"
    with pytest.raises(ValueError, match="shape"):
        write_pfm(str(path), np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="float32"):
        write_pfm(str(path), np.array([[1e300]]))
    assert not path.exists()
    path.write_bytes(b"P6\n2 2\n255\n")
    with pytest.raises(ValueError, match="not a PFM"):
        read_pfm(str(path))
    path.write_bytes(b"Pf\n2 2\n-1\n" + bytes(12))
    with pytest.raises(ValueError, match="12 bytes of pixels"):
        read_pfm(str(path))


def make_folder(folder, camera, grid, extensions=(".png", ".exr")):
    for index in range(grid.view_count):
        for extension in extensions:
            (folder / view_file_name(index, extension)).write_bytes(b"")
    depth = np.full((camera.resolution_y_px, camera.resolution_x_px), 4.0)
    depth[0, :] = 2.0  # a nearer top row: the disparity map keeps its orientation
    disp_min, disp_max = write_ground_truth(str(folder), depth, camera, grid, far_m=100.0)
    write_parameters(str(folder / PARAMETERS_FILE), camera, grid, disp_min=disp_min, disp_max=disp_max)
    return depth


def test_folder_round_trip(tmp_path):
    camera, grid = dino_camera((7, 5)), dino_grid(3, 3)
    depth = make_folder(tmp_path, camera, grid)
    (tmp_path / "notes.txt").write_text("ignored")
    light_field = read_light_field(str(tmp_path))
    assert light_field["views"][".png"] == [str(tmp_path / f"input_Cam{i:03d}.png") for i in range(9)]
    assert light_field["views"][".exr"][4].endswith("input_Cam004.exr")
    np.testing.assert_allclose(light_field["depth"], depth)
    np.testing.assert_allclose(light_field["disparity"], depth_to_disparity(depth, camera, grid), rtol=1e-6)
    assert light_field["disparity"][0, 0] > light_field["disparity"][-1, 0]
    params = light_field["parameters"]
    assert disparity_range(light_field["disparity"]) == (params["disp_min"], params["disp_max"])


def test_where_the_view_sees_the_sky_the_maps_hold_the_far_clip_not_infinity(tmp_path):
    camera, grid = dino_camera((7, 5)), dino_grid(3, 3)
    depth = np.full((5, 7), 4.0)
    depth[:2, 3:] = np.inf  # the sky above the horizon
    disp_min, _ = write_ground_truth(str(tmp_path), depth, camera, grid, far_m=50.0)
    written = read_pfm(str(tmp_path / DEPTH_FILE))
    disparity = read_pfm(str(tmp_path / DISPARITY_FILE))
    assert np.all(np.isfinite(written)) and np.all(np.isfinite(disparity))
    assert np.all(written[:2, 3:] == 50.0) and np.all(written[2:] == 4.0)
    np.testing.assert_allclose(disparity[0, 3], depth_to_disparity(50.0, camera, grid), rtol=1e-6)
    assert disp_min <= disparity.min()
    with pytest.raises(ValueError, match="NaN"):
        write_ground_truth(str(tmp_path), np.full((5, 7), np.nan), camera, grid, far_m=50.0)


def test_folder_reader_refuses_missing_extra_and_misnamed_views(tmp_path):
    camera, grid = dino_camera((7, 5)), dino_grid(3, 3)
    make_folder(tmp_path, camera, grid, extensions=(".png",))
    (tmp_path / "input_Cam004.png").unlink()
    with pytest.raises(ValueError, match="1 of 9 views missing: input_Cam004.png"):
        read_light_field(str(tmp_path))
    (tmp_path / "input_Cam004.png").write_bytes(b"")
    (tmp_path / "input_Cam009.png").write_bytes(b"")
    with pytest.raises(ValueError, match="beyond the 3x3 grid"):
        read_light_field(str(tmp_path))
    (tmp_path / "input_Cam009.png").unlink()
    (tmp_path / "input_Cam4.png").write_bytes(b"")
    with pytest.raises(ValueError, match="unexpected view file 'input_Cam4.png'"):
        read_light_field(str(tmp_path))
    (tmp_path / "input_Cam4.png").unlink()
    (tmp_path / "input_Cam000.exr").write_bytes(b"")  # a second format must be complete too
    with pytest.raises(ValueError, match="8 of 9 views missing: input_Cam001.exr"):
        read_light_field(str(tmp_path))
    (tmp_path / "input_Cam000.exr").unlink()
    write_pfm(str(tmp_path / DISPARITY_FILE), np.zeros((7, 5)))  # transposed
    with pytest.raises(ValueError, match=r"expected the views' \(5, 7\)"):
        read_light_field(str(tmp_path))
    (tmp_path / DISPARITY_FILE).unlink()
    (tmp_path / DEPTH_FILE).unlink()
    assert read_light_field(str(tmp_path))["disparity"] is None  # like HCI's test scenes
    (tmp_path / PARAMETERS_FILE).unlink()
    with pytest.raises(ValueError, match="no parameters.cfg"):
        read_light_field(str(tmp_path))


def test_disparity_range_rounds_outward_like_the_addon():
    assert disparity_range(np.array([[-1.234, 0.91], [np.nan, 0.3]])) == (-1.4, 1.1)
    assert disparity_range([0.3]) == (0.2, 0.4)
    with pytest.raises(ValueError, match="no finite value"):
        disparity_range([np.nan])


@pytest.mark.parametrize("change,message", [
    (dict(focal_length_mm=0.0), "focal_length_mm must be a positive finite number"),
    (dict(sensor_size_mm=-35.0), "sensor_size_mm must be a positive"),
    (dict(resolution_x_px=0), "resolution_x_px must be a whole number >= 1"),
    (dict(resolution_y_px=12.5), "resolution_y_px must be a whole number >= 1"),
    (dict(fstop=math.inf), "fstop must be a positive finite"),
    (dict(rotation=np.diag([1.0, 1.0, -1.0])), "proper rotation"),
    (dict(rotation=2.0 * np.eye(3)), "proper rotation"),
    (dict(position_m=(0.0, 1.0)), r"position_m must be a finite array of shape \(3,\)"),
])
def test_camera_validation(change, message):
    arguments = dict(position_m=(0.0, 0.0, 0.0), rotation=np.eye(3), focal_length_mm=50.0, sensor_size_mm=36.0,
                     resolution_x_px=64, resolution_y_px=48)
    with pytest.raises(ValueError, match=message):
        CentreCamera(**{**arguments, **change})


@pytest.mark.parametrize("change,message", [
    (dict(num_cams_x=0), "num_cams_x must be a whole number >= 1"),
    (dict(num_cams_y=True), "num_cams_y must be a whole number >= 1"),
    (dict(baseline_mm=0.0), "baseline_mm must be a positive finite number"),
    (dict(focus_distance_m=0.0), "focus_distance_m must be a positive finite number"),
])
def test_grid_validation(change, message):
    with pytest.raises(ValueError, match=message):
        LightFieldGrid(**{**dict(num_cams_x=3, num_cams_y=3, baseline_mm=50.0, focus_distance_m=2.0), **change})


def test_clip_and_ground_truth_validation(tmp_path):
    camera, grid = dino_camera((8, 6)), dino_grid(3, 3)
    with pytest.raises(ValueError, match="clip_end_m .* must be greater than clip_start_m"):
        grid_views(camera, grid, clip_start_m=1.0, clip_end_m=1.0)
    with pytest.raises(ValueError, match=r"views' shape \(6, 8\)"):
        write_ground_truth(str(tmp_path), np.ones((8, 6)), camera, grid, far_m=100.0)
    with pytest.raises(ValueError, match="extension"):
        view_file_name(0, ".jpg")
