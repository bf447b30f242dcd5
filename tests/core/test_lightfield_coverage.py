"""The texel density a light field's views need (core.lightfield.coverage), against closed
forms: a fronto-parallel plane at a known depth, a quad nearer the camera that hides part of
it, and one hidden entirely."""
import numpy as np
import pytest

from core.lightfield.cameras import CentreCamera, LightFieldGrid, grid_views
from core.lightfield.coverage import focal_pixels, nearest_depths, probe_views, texel_densities

WIDTH, HEIGHT = 64, 48


def _views(columns=3, rows=3, baseline_mm=100.0):
    camera = CentreCamera(position_m=[0.0, 0.0, 5.0], rotation=np.eye(3), focal_length_mm=50.0, sensor_size_mm=36.0,
                          resolution_x_px=WIDTH, resolution_y_px=HEIGHT)
    return grid_views(camera, LightFieldGrid(columns, rows, baseline_mm, 4.0), 0.1, 100.0)


def _square(half, z, x=0.0, y=0.0):
    corners = np.array([[x - half, y - half, z], [x + half, y - half, z], [x + half, y + half, z],
                        [x - half, y + half, z]], np.float32)
    return corners[[0, 1, 2, 0, 2, 3]]


def test_probes_are_the_corners_and_the_centre():
    views = _views(5, 4)
    assert [v.index for v in probe_views(views, 5, 4)] == [0, 4, 12, 15, 19]
    single = _views(1, 1)
    assert [v.index for v in probe_views(single, 1, 1)] == [0]


def test_depths_of_a_plane_a_nearer_card_and_a_hidden_one():
    views = _views()
    ground = _square(20.0, 0.0)            # fills every view, 5 m from the cameras
    card = _square(0.3, 2.0)               # 3 m away, in the middle of the views
    hidden = _square(0.05, 1.0)            # right under the card: no view's pixel centre reaches it
    off = _square(0.5, 2.0, x=50.0)        # outside every frustum
    depths = nearest_depths([ground, card, hidden, off, np.zeros((0, 3), np.float32)],
                            probe_views(views, 3, 3), (0.1, 100.0), WIDTH, HEIGHT)
    assert depths[0] == pytest.approx(5.0, rel=1e-5) and depths[1] == pytest.approx(3.0, rel=1e-5)
    assert np.isinf(depths[2]) and np.isinf(depths[3]) and np.isinf(depths[4])


def test_density_is_a_texel_per_pixel_at_the_nearest_depth():
    view = _views(1, 1)[0]
    pixels = focal_pixels(view.projection_matrix, WIDTH, HEIGHT)
    # 50 mm over 36 mm across 64 pixels: f = 50 / 36 * 64 pixels at 1 m per metre.
    assert pixels == pytest.approx(50.0 / 36.0 * WIDTH, rel=1e-9)
    densities = texel_densities(np.array([2.0, np.inf, 4.0]), pixels, texels_per_pixel=1.5)
    np.testing.assert_allclose(densities, [1.5 * pixels / 2.0, 0.0, 1.5 * pixels / 4.0])
