"""The light field's view picture without Blender: Cycles' pixel filter (core.lightfield.scene) and
the embree renderer (core.lightfield.raycast), against closed forms.

Closed forms used: a fronto-parallel textured quad has UVs affine in the image, so with a texture
that is affine in (u, v) (bilinear reproduces it exactly between the border texels' centres) the
symmetric filter returns the value at the pixel's centre; with one supersample and a filter that
reaches no other (s = 1, width 0.5) a pixel is the plain bilinear sample at its centre's ray, of
any texture and any world. Tolerances are float32 rounding (the directions and barycentrics are
float32 in embree).
"""
import math

import numpy as np
import pytest

from core.lightfield.cameras import CentreCamera, LightFieldGrid, grid_views
from core.lightfield.raycast import RaycastRenderer
from core.lightfield.scene import (
    DrawMesh,
    DrawScene,
    blackman_harris,
    camera_position,
    direction_matrix,
    extended_size,
    filter_margin,
    pixel_filter_offsets,
    pixel_filter_weights,
    resolve,
    sample_bilinear_clamp,
    supersample_ndc,
    world_lookup,
)

BLACK = np.zeros((1, 1, 3), np.float32)


def _camera(width, height, z=3.0, focal=50.0, sensor=36.0):
    """A camera at (0, 0, z) looking down -Z (+Y up in the image, +X right)."""
    return CentreCamera(position_m=[0.0, 0.0, z], rotation=np.eye(3), focal_length_mm=focal,
                        sensor_size_mm=sensor, resolution_x_px=width, resolution_y_px=height)


def _centre_view(width, height, clip=(0.1, 100.0), **camera):
    return grid_views(_camera(width, height, **camera), LightFieldGrid(1, 1, 10.0, 3.0), *clip)[0]


def _quad(half_x, half_y, z, uv_lo=(0.0, 0.0), uv_hi=(1.0, 1.0)):
    """Two triangles of the rectangle |x| <= half_x, |y| <= half_y at height z, UVs spanning uv_lo..uv_hi."""
    corners = np.array([[-half_x, -half_y, z], [half_x, -half_y, z], [half_x, half_y, z], [-half_x, half_y, z]])
    uv = np.array([[uv_lo[0], uv_lo[1]], [uv_hi[0], uv_lo[1]], [uv_hi[0], uv_hi[1]], [uv_lo[0], uv_hi[1]]])
    order = [0, 1, 2, 0, 2, 3]
    return corners[order].astype(np.float32), uv[order].astype(np.float32)


def _pixel_rays(view_matrix, projection_matrix, width, height):
    """(height, width, 3) unit directions through the pixel centres, row 0 at the top."""
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    m = direction_matrix(view_matrix, projection_matrix)
    d = x[None, :, None] * m[:, 0] + y[:, None, None] * m[:, 1] + m[:, 2]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


# ---------------------------------------------------------------- the filter


def test_blackman_harris_is_cycles_window_of_twice_the_width():
    # Cycles: filter_func_blackman_harris(v, width) with filter_table's width *= 2 for this filter.
    v = np.linspace(-1.5, 1.5, 31)
    x = 2.0 * np.pi * (v / 3.0 + 0.5)
    cycles = 0.35875 - 0.48829 * np.cos(x) + 0.14128 * np.cos(2 * x) - 0.01168 * np.cos(3 * x)
    np.testing.assert_allclose(blackman_harris(v, 1.5), cycles, rtol=0, atol=1e-15)
    assert blackman_harris(0.0, 1.5) == pytest.approx(1.0, abs=1e-12)
    assert blackman_harris(1.5, 1.5) == pytest.approx(6e-5, abs=1e-5)
    assert blackman_harris(1.51, 1.5) == 0.0 and blackman_harris(-2.0, 1.5) == 0.0


@pytest.mark.parametrize("s", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("width", [0.5, 1.0, 1.5, 2.0, 3.3])
def test_filter_weights_are_normalised_symmetric_and_follow_the_window(s, width):
    w = pixel_filter_weights(s, width)
    offsets = pixel_filter_offsets(s, width)
    r = filter_margin(s, width)
    assert w.dtype == np.float32 and w.shape == offsets.shape == (s + 2 * r,)
    assert math.isclose(float(w.astype(np.float64).sum()), 1.0, abs_tol=1e-6)
    np.testing.assert_array_equal(w, w[::-1])
    np.testing.assert_allclose(offsets, -offsets[::-1], atol=1e-12)
    assert np.all(w > 0)
    # Every tap within the support, and none left out: the next one would be at or past it.
    assert np.all(np.abs(offsets) < width)
    assert abs(offsets[0]) + 1.0 / s >= width - 1e-12
    expected = blackman_harris(offsets, width)
    np.testing.assert_allclose(w, expected / expected.sum(), rtol=1e-6)


def test_default_filter_reaches_the_neighbouring_pixels_supersamples():
    # Blender's default 1.5 px: +-1.5 px from the centre, so with s = 3 three supersamples of each
    # neighbour (at 2/3, 1 and 4/3 px) on each side; with s = 2 two (0.75 and 1.25 px).
    offsets = pixel_filter_offsets(3, 1.5)
    np.testing.assert_allclose(offsets, np.arange(-4, 5) / 3.0, atol=1e-12)
    w = pixel_filter_weights(3, 1.5)
    assert len(w) == 9 and filter_margin(3, 1.5) == 3
    assert w[0] > 0 and w[:3].sum() > 0.05  # the left neighbour's share along one axis
    np.testing.assert_allclose(pixel_filter_offsets(2, 1.5), [-1.25, -0.75, -0.25, 0.25, 0.75, 1.25])
    # 2D: the 8 neighbours together carry a good part of the weight.
    w2 = np.outer(w, w)
    assert w2[3:6, 3:6].sum() < 0.8


def test_a_filter_narrower_than_a_supersample_falls_back_to_the_central_ones():
    np.testing.assert_array_equal(pixel_filter_weights(2, 0.1), [0.5, 0.5])
    np.testing.assert_array_equal(pixel_filter_weights(3, 0.1), [0.0, 1.0, 0.0])
    assert filter_margin(1, 0.2) == 0 and list(pixel_filter_weights(1, 0.2)) == [1.0]


@pytest.mark.parametrize("s, width", [(0, 1.5), (1.5, 1.5), (True, 1.5), ("3", 1.5), (3, 0.0), (3, -1.0),
                                      (3, float("nan")), (3, float("inf")), (3, "1.5")])
def test_filter_arguments_are_checked(s, width):
    with pytest.raises(ValueError):
        pixel_filter_weights(s, width)


def test_resolve_of_an_impulse_is_the_2d_filter_at_the_right_pixels():
    s, width = 3, 1.5
    w = pixel_filter_weights(s, width)
    columns, rows, r = extended_size(5, 4, s, width)
    assert (columns, rows) == (5 * 3 + 6, 4 * 3 + 6)
    grid = np.zeros((rows, columns, 1), np.float32)
    # The centre supersample of pixel (row 1, column 2), in extended coordinates.
    grid[r + 1 * s + 1, r + 2 * s + 1] = 1.0
    out = resolve(grid, s, w)[..., 0]
    assert out.shape == (4, 5)
    # The supersample is tap r+1 of its own pixel, tap r+1-s of the next, r+1+s of the previous.
    np.testing.assert_allclose(out[1, 2], w[r + 1] ** 2, rtol=1e-6)
    np.testing.assert_allclose(out[1, 3], w[r + 1] * w[r + 1 - s], rtol=1e-6)
    np.testing.assert_allclose(out[0, 1], w[r + 1 + s] ** 2, rtol=1e-6)
    assert out[3, :].max() == 0.0 and out[:, 0].max() == 0.0
    constant = resolve(np.full((rows, columns, 3), 0.7, np.float32), s, w)
    np.testing.assert_allclose(constant, 0.7, rtol=1e-6)


def test_supersample_ndc_layout():
    x, y = supersample_ndc(4, 2, 2, 1.5)
    r = filter_margin(2, 1.5)
    assert len(x) == 4 * 2 + 2 * r and len(y) == 2 * 2 + 2 * r
    np.testing.assert_allclose(x, -x[::-1], atol=1e-12)
    # Row 0 is above the image's top edge (NDC y > 1), columns run left to right.
    assert y[0] > 1.0 > y[r] > 0.0 and x[0] < -1.0 < x[r] < x[r + 1]
    np.testing.assert_allclose(x[r], 2.0 * 0.25 / 4 - 1.0)


def test_bilinear_clamp_lookup():
    image = np.arange(2 * 3 * 1, dtype=np.float32).reshape(2, 3, 1)  # rows v, columns u
    uv = np.array([[0.5 / 3, 0.25], [1.5 / 3, 0.75], [1.0 / 3, 0.25], [-5.0, -5.0], [9.0, 9.0], [1e30, -1e30]])
    got = sample_bilinear_clamp(image, uv)[:, 0]
    np.testing.assert_allclose(got, [0.0, 4.0, 0.5, 0.0, 5.0, 2.0], atol=1e-6)


def test_world_lookup_matches_the_environment_layout():
    # Row 0 at the bottom: a world bright only in its top rows is bright up there. (At the poles
    # themselves the periodic lookup blends the top row with the bottom one, as Cycles does.)
    world = np.zeros((8, 16, 3), np.float32)
    world[-2:] = 1.0
    up, down = world_lookup(world, np.array([[0.2, 0.0, 1.0], [0.2, 0.0, -1.0]]))
    assert up[0] == pytest.approx(1.0) and down[0] == pytest.approx(0.0)
    uniform = world_lookup(np.full((1, 1, 3), 0.3, np.float32), np.zeros((5, 3)) + [1, 0, 0])
    np.testing.assert_allclose(uniform, 0.3)


def test_direction_matrix_unprojects_to_the_pixel_rays():
    camera = _camera(40, 30)
    view = grid_views(camera, LightFieldGrid(3, 3, 200.0, 2.0), 0.1, 50.0)[0]  # off axis
    eye = camera_position(view.view_matrix)
    np.testing.assert_allclose(eye, view.position_m, atol=1e-12)
    m = direction_matrix(view.view_matrix, view.projection_matrix)
    inverse = np.linalg.inv(view.projection_matrix @ view.view_matrix)
    for ndc in ([0.3, -0.7], [-1.0, 1.0], [0.0, 0.0]):
        far = inverse @ np.array([*ndc, 1.0, 1.0])
        near = inverse @ np.array([*ndc, -1.0, 1.0])
        expected = far[:3] / far[3] - near[:3] / near[3]
        got = m @ np.array([*ndc, 1.0])
        np.testing.assert_allclose(got / np.linalg.norm(got), expected / np.linalg.norm(expected), atol=1e-9)


# ---------------------------------------------------------------- the scene


def test_draw_mesh_checks_its_arrays():
    quad, uv = _quad(1, 1, 0)
    zeros = np.zeros_like(quad)
    mesh = DrawMesh(quad.astype(np.float64), zeros, uv, np.zeros((2, 2, 3)))
    assert mesh.positions.dtype == np.float32 and mesh.image.dtype == np.float32 and mesh.triangle_count == 2
    with pytest.raises(ValueError, match="3 corners"):
        DrawMesh(quad[:4], zeros[:4])
    with pytest.raises(ValueError, match="radiance"):
        DrawMesh(quad, zeros[:3])
    with pytest.raises(ValueError, match="needs uv"):
        DrawMesh(quad, zeros, None, np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="image"):
        DrawMesh(quad, zeros, uv, np.zeros((2, 2, 4)))
    with pytest.raises(ValueError, match="non-finite"):
        DrawMesh(np.where(quad == quad[0, 0], np.nan, quad), zeros)
    with pytest.raises(ValueError, match="world"):
        DrawScene([mesh], np.zeros((4, 3)))
    with pytest.raises(TypeError):
        DrawScene([quad], BLACK)
    assert DrawScene([], np.full((2, 3, 3), 0.5)).uniform_world.tolist() == [0.5, 0.5, 0.5]
    assert DrawScene([], np.arange(18.0).reshape(2, 3, 3)).uniform_world is None


# ---------------------------------------------------------------- the renderer


def _affine_texture(size=(24, 32)):
    """(h, w, 3) texture whose texel centres hold an affine function of (u, v), and that function."""
    h, w = size

    def f(u, v):
        u, v = np.broadcast_arrays(u, v)
        return np.stack([0.2 + 0.5 * u + 0.1 * v, 0.9 - 0.3 * u + 0.4 * v, 0.1 + 0.7 * v], axis=-1)

    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    return f(u[None, :], v[:, None]).astype(np.float32), f


def test_textured_quad_filling_the_view_shows_the_texture_and_its_depth():
    width, height, depth = 40, 30, 2.5
    view = _centre_view(width, height)
    # The quad at z = 0 (depth 3 from the camera at z = 3 would also do): z = 0.5 -> depth 2.5.
    half_x = 1.2 * 0.5 * 36.0 / 50.0 * depth  # 20% wider than the view
    half_y = half_x
    quad, uv = _quad(half_x, half_y, 3.0 - depth)
    texture, f = _affine_texture()
    scene = DrawScene([DrawMesh(quad, np.zeros_like(quad), uv, texture)], np.full((1, 1, 3), 5.0, np.float32))
    renderer = RaycastRenderer(scene, width, height, 3, 1.5)
    radiance, depth_image = renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
    assert radiance.shape == (height, width, 3) and radiance.dtype == np.float32
    assert depth_image.shape == (height * 3, width * 3) and depth_image.dtype == np.float32
    np.testing.assert_allclose(depth_image, depth, rtol=1e-6)
    # The pixel centres' UVs (affine in the image: the quad faces the camera).
    rays = _pixel_rays(view.view_matrix, view.projection_matrix, width, height)
    t = depth / -rays[..., 2]
    points = np.array([0.0, 0.0, 3.0]) + rays * t[..., None]
    u = (points[..., 0] + half_x) / (2 * half_x)
    v = (points[..., 1] + half_y) / (2 * half_y)
    # Away from the clamped border texels, bilinear = the affine function; the filter keeps it.
    np.testing.assert_allclose(radiance, f(u, v), atol=2e-6)
    # Row 0 at the top: v grows upwards, and the third channel with it.
    assert radiance[0, :, 2].mean() > radiance[-1, :, 2].mean()


def test_one_tap_pixels_are_the_bilinear_sample_at_the_pixel_centre():
    width, height = 24, 18
    view = _centre_view(width, height)
    quad, uv = _quad(2.0, 2.0, 0.0, (-0.1, -0.1), (1.1, 1.1))  # UVs past the texture: clamp-to-edge
    texture = np.random.default_rng(3).random((7, 9, 3)).astype(np.float32)
    scene = DrawScene([DrawMesh(quad, np.zeros_like(quad), uv, texture)], BLACK)
    radiance, depth = RaycastRenderer(scene, width, height, 1, 0.5).render(view.view_matrix, view.projection_matrix,
                                                                            0.1, 100.0)
    assert depth is None
    rays = _pixel_rays(view.view_matrix, view.projection_matrix, width, height)
    points = np.array([0.0, 0.0, 3.0]) + rays * (3.0 / -rays[..., 2])[..., None]
    uv_centre = -0.1 + 1.2 * (points[..., :2] + 2.0) / 4.0
    expected = sample_bilinear_clamp(texture, uv_centre.reshape(-1, 2)).reshape(height, width, 3)
    np.testing.assert_allclose(radiance, expected, atol=2e-5)


def test_world_only_is_the_equirect_lookup_of_each_pixel_direction():
    width, height = 32, 24
    view = grid_views(_camera(width, height), LightFieldGrid(3, 3, 300.0, 2.0), 0.1, 100.0)[2]
    # A camera looking sideways sees the horizon, where the gradient runs.
    tilted = view.view_matrix.copy()
    turn = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])  # world +Y onto camera -Z
    tilted = turn @ tilted
    rows, columns = np.mgrid[0:64, 0:128]
    world = np.stack([rows / 63.0, 0.5 + 0.5 * np.sin(2 * np.pi * columns / 128.0), np.full(rows.shape, 0.25)],
                     axis=-1).astype(np.float32)
    scene = DrawScene([], world)
    rays = _pixel_rays(tilted, view.projection_matrix, width, height)
    expected = world_lookup(world, rays.reshape(-1, 3)).reshape(height, width, 3)
    # One tap: exactly the lookup at the pixel centre.
    exact, depth = RaycastRenderer(scene, width, height, 1, 0.5).render(tilted, view.projection_matrix, 0.1, 100.0,
                                                                         want_depth=True)
    np.testing.assert_allclose(exact, expected, atol=1e-5)
    assert np.all(np.isinf(depth))
    # The default filter averages a smooth world around the centre: close, not equal.
    filtered, _ = RaycastRenderer(scene, width, height, 3, 1.5).render(tilted, view.projection_matrix, 0.1, 100.0)
    np.testing.assert_allclose(filtered, expected, atol=3e-3)
    # Up is up: the top row looks higher than the bottom row, so it is brighter in red.
    assert filtered[0, :, 0].mean() > filtered[-1, :, 0].mean()


def test_per_corner_radiance_adds_to_the_texture():
    width, height = 20, 16
    view = _centre_view(width, height)
    quad, uv = _quad(3.0, 3.0, 0.0)
    texture, _ = _affine_texture((5, 6))
    glow = np.tile(np.array([[0.5, 0.0, 2.0]], np.float32), (len(quad), 1))
    plain = DrawScene([DrawMesh(quad, np.zeros_like(quad), uv, texture)], BLACK)
    lit = DrawScene([DrawMesh(quad, glow, uv, texture)], BLACK)
    a, _ = RaycastRenderer(plain, width, height, 2, 1.5).render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
    b, _ = RaycastRenderer(lit, width, height, 2, 1.5).render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
    np.testing.assert_allclose(b - a, np.broadcast_to([0.5, 0.0, 2.0], a.shape), atol=2e-6)
    # Vertex-mode only: interpolated per-corner values (a ramp across the quad).
    ramp = np.repeat((quad[:, :1] + 3.0) / 6.0, 3, axis=1)
    c, _ = RaycastRenderer(DrawScene([DrawMesh(quad, ramp)], BLACK), width, height, 1, 0.5).render(
        view.view_matrix, view.projection_matrix, 0.1, 100.0)
    assert np.all(np.diff(c[..., 0], axis=1) > 0)


def test_nearest_surface_both_faces_and_the_clip_planes():
    width, height = 16, 12
    view = _centre_view(width, height, clip=(0.5, 4.0))
    red = _quad(5, 5, 1.0)[0]  # depth 2
    green = _quad(5, 5, 2.0)[0][[0, 2, 1, 3, 5, 4]]  # depth 1, wound the other way: its back faces us
    far_blue = _quad(5, 5, -2.0)[0]  # depth 5, past clip_end
    near_white = _quad(5, 5, 2.8)[0]  # depth 0.2, before clip_start

    def colour(quad, rgb):
        return DrawMesh(quad, np.tile(np.array([rgb], np.float32), (len(quad), 1)))

    sky = np.full((1, 1, 3), 0.125, np.float32)
    render = RaycastRenderer(DrawScene([colour(red, [1, 0, 0]), colour(green, [0, 1, 0]), colour(far_blue, [0, 0, 1]),
                                        colour(near_white, [1, 1, 1])], sky), width, height, 2, 1.5)
    radiance, depth = render.render(view.view_matrix, view.projection_matrix, 0.5, 4.0, want_depth=True)
    np.testing.assert_allclose(radiance, np.broadcast_to([0, 1, 0], radiance.shape), atol=1e-6)
    np.testing.assert_allclose(depth, 1.0, rtol=1e-6)
    only_far = RaycastRenderer(DrawScene([colour(far_blue, [0, 0, 1]), colour(near_white, [1, 1, 1])], sky),
                               width, height, 2, 1.5)
    radiance, depth = only_far.render(view.view_matrix, view.projection_matrix, 0.5, 4.0, want_depth=True)
    np.testing.assert_allclose(radiance, 0.125, atol=1e-6)
    assert np.all(np.isinf(depth))


def test_layout_row_zero_is_the_top_and_the_focus_plane_has_no_disparity():
    width, height = 30, 20
    camera = _camera(width, height)
    views = grid_views(camera, LightFieldGrid(3, 3, 100.0, 3.0), 0.1, 100.0)
    # A small square above and right of the optical axis, on the focus plane (z = 0: depth 3).
    square = _quad(0.15, 0.15, 0.0)[0] + np.array([0.5, 0.3, 0.0], np.float32)
    scene = DrawScene([DrawMesh(square, np.ones_like(square))], BLACK)
    renderer = RaycastRenderer(scene, width, height, 3, 1.5)
    images = [renderer.render(v.view_matrix, v.projection_matrix, 0.1, 100.0)[0][..., 0] for v in views]
    rows, columns = np.nonzero(images[4] > 0.5)
    assert rows.max() < height // 2 and columns.min() > width // 2  # top right
    for image in images:
        np.testing.assert_allclose(image, images[4], atol=1e-5)


def test_renderer_arguments_are_checked():
    scene = DrawScene([], BLACK)
    with pytest.raises(ValueError):
        RaycastRenderer(scene, 0, 10)
    with pytest.raises(ValueError):
        RaycastRenderer(scene, 10, 10, 0)
    renderer = RaycastRenderer(scene, 4, 4, 1, 0.5)
    view = _centre_view(4, 4)
    with pytest.raises(ValueError, match="clip"):
        renderer.render(view.view_matrix, view.projection_matrix, 1.0, 0.5)
    with pytest.raises(ValueError, match="matrix"):
        renderer.render(view.view_matrix[:3], view.projection_matrix, 0.1, 1.0)
    with renderer as same:
        radiance, depth = same.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
    assert np.all(radiance == 0) and np.all(np.isinf(depth))
