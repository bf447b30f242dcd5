"""The light field's GPU view renderer (gpu_shaders.lightfield) against closed forms and its CPU
twin (core.lightfield.raycast), in bpy with the installed extension (llvmpipe where there is no GPU).

Tolerances, and why:
- Closed forms (a fronto-parallel quad under an affine texture, a world seen one tap per pixel):
  2e-5 absolute on values of order 1, the float32 rounding of perspective-correct interpolation;
  the world's 1e-4 adds GLSL's atan/acos (llvmpipe: a few 1e-7 rad, times a gradient of ~3 per
  unit of u). Depth: 1e-5 relative (1 / gl_FragCoord.w in float32).
- GPU against the twin: the samples are at the same points, but a sample that falls on a
  triangle's edge is given to either side by the rasteriser's tie rule and embree's own; such a
  supersample changes the pixels its filter reaches (+-1.5 px). So: every pixel whose filter
  footprint has no edge (no depth step in the twin's depth) agrees within 1e-4, the mean
  difference is under 1e-3 of the image's peak, and the depth agrees within 1e-5 wherever the
  twin's 3 x 3 supersample neighbourhood holds one surface.
"""
import importlib

import numpy as np
import pytest

from blender_support import gpu_runtime_or_skip


@pytest.fixture(scope="module")
def lf(visibake):
    _, info = gpu_runtime_or_skip(visibake)
    print(f"\nGPU: {info.backend}, {info.renderer}")

    class Modules:
        scene = importlib.import_module(f"{visibake.__name__}.core.lightfield.scene")
        cameras = importlib.import_module(f"{visibake.__name__}.core.lightfield.cameras")
        raycast = importlib.import_module(f"{visibake.__name__}.core.lightfield.raycast")
        gpu = importlib.import_module(f"{visibake.__name__}.gpu_shaders.lightfield")

    return Modules


def _camera(lf, width, height, z=3.0):
    return lf.cameras.CentreCamera(position_m=[0.0, 0.0, z], rotation=np.eye(3), focal_length_mm=50.0,
                                   sensor_size_mm=36.0, resolution_x_px=width, resolution_y_px=height)


def _views(lf, width, height, cams=1, baseline_mm=10.0, focus=3.0, clip=(0.1, 100.0)):
    grid = lf.cameras.LightFieldGrid(cams, cams, baseline_mm, focus)
    return lf.cameras.grid_views(_camera(lf, width, height), grid, *clip)


def _quad(half, z, offset=(0.0, 0.0), uv_lo=(0.0, 0.0), uv_hi=(1.0, 1.0)):
    x0, y0 = offset
    corners = np.array([[x0 - half, y0 - half, z], [x0 + half, y0 - half, z], [x0 + half, y0 + half, z],
                        [x0 - half, y0 + half, z]])
    uv = np.array([[uv_lo[0], uv_lo[1]], [uv_hi[0], uv_lo[1]], [uv_hi[0], uv_hi[1]], [uv_lo[0], uv_hi[1]]])
    order = [0, 1, 2, 0, 2, 3]
    return corners[order].astype(np.float32), uv[order].astype(np.float32)


def _both(lf, scene, width, height, s=3, filter_width=1.5):
    return lf.gpu.ViewRenderer(scene, width, height, s, filter_width), lf.raycast.RaycastRenderer(
        scene, width, height, s, filter_width)


def _pixel_rays(lf, view_matrix, projection_matrix, width, height):
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    m = lf.scene.direction_matrix(view_matrix, projection_matrix)
    d = x[None, :, None] * m[:, 0] + y[:, None, None] * m[:, 1] + m[:, 2]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _affine(u, v):
    u, v = np.broadcast_arrays(u, v)
    return np.stack([0.2 + 0.5 * u + 0.1 * v, 0.9 - 0.3 * u + 0.4 * v, 0.1 + 0.7 * v], axis=-1)


def test_textured_quad_filling_the_view_shows_the_texture_and_its_depth(lf):
    width, height, depth = 40, 30, 2.5
    view = _views(lf, width, height)[0]
    half = 1.2 * 0.5 * 36.0 / 50.0 * depth
    quad, uv = _quad(half, 3.0 - depth)
    h, w = 24, 32
    texture = _affine((np.arange(w) + 0.5)[None, :] / w, (np.arange(h) + 0.5)[:, None] / h).astype(np.float32)
    scene = lf.scene.DrawScene([lf.scene.DrawMesh(quad, np.zeros_like(quad), uv, texture)],
                               np.full((1, 1, 3), 5.0, np.float32))
    rays = _pixel_rays(lf, view.view_matrix, view.projection_matrix, width, height)
    points = np.array([0.0, 0.0, 3.0]) + rays * (depth / -rays[..., 2])[..., None]
    expected = _affine((points[..., 0] + half) / (2 * half), (points[..., 1] + half) / (2 * half))
    gpu, cpu = _both(lf, scene, width, height)
    with gpu:
        for renderer in (gpu, cpu):
            radiance, depth_image = renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0,
                                                    want_depth=True)
            assert radiance.shape == (height, width, 3) and radiance.dtype == np.float32
            assert depth_image.shape == (height * 3, width * 3) and depth_image.dtype == np.float32
            np.testing.assert_allclose(radiance, expected, atol=2e-5, err_msg=type(renderer).__name__)
            np.testing.assert_allclose(depth_image, depth, rtol=1e-5, err_msg=type(renderer).__name__)


def test_one_tap_gpu_pixels_are_the_bilinear_sample_at_the_pixel_centre(lf):
    width, height = 24, 18
    view = _views(lf, width, height)[0]
    quad, uv = _quad(2.0, 0.0, uv_lo=(-0.1, -0.1), uv_hi=(1.1, 1.1))  # past the texture: clamp-to-edge
    texture = np.random.default_rng(3).random((7, 9, 3)).astype(np.float32)
    scene = lf.scene.DrawScene([lf.scene.DrawMesh(quad, np.zeros_like(quad), uv, texture)],
                               np.zeros((1, 1, 3), np.float32))
    rays = _pixel_rays(lf, view.view_matrix, view.projection_matrix, width, height)
    points = np.array([0.0, 0.0, 3.0]) + rays * (3.0 / -rays[..., 2])[..., None]
    uv_centre = -0.1 + 1.2 * (points[..., :2] + 2.0) / 4.0
    expected = lf.scene.sample_bilinear_clamp(texture, uv_centre.reshape(-1, 2)).reshape(height, width, 3)
    with lf.gpu.ViewRenderer(scene, width, height, 1, 0.5) as gpu:
        radiance, depth = gpu.render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
    assert depth is None
    np.testing.assert_allclose(radiance, expected, atol=5e-5)


def test_world_only_is_the_equirect_lookup_of_each_pixel_direction(lf):
    width, height = 32, 24
    view = _views(lf, width, height, cams=3, baseline_mm=300.0, focus=2.0)[2]
    turn = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])  # look along world +Y
    tilted = turn @ view.view_matrix
    rows, columns = np.mgrid[0:64, 0:128]
    world = np.stack([rows / 63.0, 0.5 + 0.5 * np.sin(2 * np.pi * columns / 128.0), np.full(rows.shape, 0.25)],
                     axis=-1).astype(np.float32)
    scene = lf.scene.DrawScene([], world)
    rays = _pixel_rays(lf, tilted, view.projection_matrix, width, height)
    expected = lf.scene.world_lookup(world, rays.reshape(-1, 3)).reshape(height, width, 3)
    with lf.gpu.ViewRenderer(scene, width, height, 1, 0.5) as gpu:
        exact, depth = gpu.render(tilted, view.projection_matrix, 0.1, 100.0, want_depth=True)
    np.testing.assert_allclose(exact, expected, atol=1e-4)
    assert np.all(np.isinf(depth))
    gpu, cpu = _both(lf, scene, width, height)
    with gpu:
        filtered, _ = gpu.render(tilted, view.projection_matrix, 0.1, 100.0)
    twin, _ = cpu.render(tilted, view.projection_matrix, 0.1, 100.0)
    np.testing.assert_allclose(filtered, twin, atol=1e-4)
    np.testing.assert_allclose(filtered, expected, atol=3e-3)  # the filter's average of a smooth world
    assert filtered[0, :, 0].mean() > filtered[-1, :, 0].mean()  # up is up


def _small_scene(lf, world):
    """Overlapping triangles: two textured (one image shared), one vertex-coloured, one both, at
    several depths, and a quad behind them all."""
    rng = np.random.default_rng(11)
    image = rng.random((16, 20, 3)).astype(np.float32)
    other = rng.random((5, 7, 3)).astype(np.float32) * 2.0
    meshes = []
    triangles = [([-0.9, -0.6, 0.4], [0.7, -0.5, 0.2], [0.1, 0.8, 0.3]),
                 ([-0.2, -0.9, 0.8], [0.9, 0.3, 0.9], [-0.6, 0.6, 0.6]),
                 ([-1.1, 0.1, 0.0], [0.2, -1.0, 1.0], [0.5, 0.9, 0.5]),
                 ([0.3, -0.3, 1.2], [1.0, -0.1, 1.1], [0.6, 0.5, 1.3])]
    for number, corners in enumerate(triangles):
        positions = np.array(corners, np.float32)
        radiance = np.zeros((3, 3), np.float32) if number in (0, 1) else rng.random((3, 3)).astype(np.float32)
        uv = rng.random((3, 2)).astype(np.float32) * 1.2 - 0.1
        texture = image if number in (0, 1) else (other if number == 3 else None)
        meshes.append(lf.scene.DrawMesh(positions, radiance, uv if texture is not None else None, texture))
    back, back_uv = _quad(1.0, -0.5, offset=(0.3, 0.2))
    meshes.append(lf.scene.DrawMesh(back, np.full_like(back, 0.05), back_uv, other))
    return lf.scene.DrawScene(meshes, world)


def _edges(depth, radius):
    """(grown, step): (h s, w s) bool masks of the supersamples next to an edge of the twin's depth,
    and those grown by ``radius`` supersamples (the filter's reach).

    An edge: the world on one side only, or a kink of the inverse depth, which is affine in the
    image on a plane (so its second difference vanishes inside a triangle)."""
    finite = np.isfinite(depth)
    inverse = np.where(finite, 1.0 / np.where(finite, depth, 1.0), 0.0)
    step = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        changes = np.diff(finite, axis=axis)
        second = np.abs(np.diff(inverse, n=2, axis=axis)) > 1e-5 * np.abs(inverse).max()
        if axis == 0:
            step[1:] |= changes
            step[:-1] |= changes
            step[:-2] |= second
            step[1:-1] |= second
            step[2:] |= second
        else:
            step[:, 1:] |= changes
            step[:, :-1] |= changes
            step[:, :-2] |= second
            step[:, 1:-1] |= second
            step[:, 2:] |= second
    grown = step.copy()
    for _ in range(radius):
        grown[1:] |= grown[:-1].copy()
        grown[:-1] |= grown[1:].copy()
        grown[:, 1:] |= grown[:, :-1].copy()
        grown[:, :-1] |= grown[:, 1:].copy()
    return grown, step


@pytest.mark.parametrize("s", [2, 3])
@pytest.mark.parametrize("world_kind", ["image", "uniform"])
def test_gpu_matches_the_cpu_twin_on_overlapping_triangles_off_axis(lf, s, world_kind):
    width, height = 45, 31  # odd and not square: a transposed or flipped layout cannot pass
    if world_kind == "image":
        rows, columns = np.mgrid[0:32, 0:64]
        world = np.stack([rows / 31.0, columns / 63.0, 0.3 + 0.2 * np.cos(rows / 5.0)], -1).astype(np.float32)
    else:
        world = np.full((1, 1, 3), 0.4, np.float32)
    scene = _small_scene(lf, world)
    views = _views(lf, width, height, cams=5, baseline_mm=150.0, focus=2.5)
    gpu, cpu = _both(lf, scene, width, height, s)
    r = lf.scene.filter_margin(s, 1.5)
    with gpu:
        for view in (views[0], views[12], views[19]):
            a, da = gpu.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
            b, db = cpu.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
            assert a.shape == b.shape == (height, width, 3) and da.shape == db.shape == (height * s, width * s)
            assert np.all(np.isfinite(a))
            grown, step = _edges(db, r)
            footprint_edge = grown.reshape(height, s, width, s).any(axis=(1, 3))
            difference = np.abs(a - b)
            assert (~footprint_edge).mean() > 0.3  # the test means something
            assert difference[~footprint_edge].max() < 1e-4
            assert difference.mean() < 1e-3 * b.max()
            # The layout: the same image, not a mirrored one (mirrored, the edge pixels would disagree).
            assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
            smooth = ~step & np.isfinite(db)
            np.testing.assert_allclose(da[smooth], db[smooth], rtol=1e-5)
            np.testing.assert_array_equal(np.isinf(da[~step]), np.isinf(db[~step]))
            # Each renderer produces the same image again (no state left from the previous view).
            again, _ = gpu.render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
            np.testing.assert_array_equal(again, a)


def test_per_corner_radiance_adds_to_the_texture(lf):
    width, height = 20, 16
    view = _views(lf, width, height)[0]
    quad, uv = _quad(3.0, 0.0)
    texture = np.random.default_rng(5).random((6, 5, 3)).astype(np.float32)
    glow = np.tile(np.array([[0.5, 0.0, 2.0]], np.float32), (len(quad), 1))
    black = np.zeros((1, 1, 3), np.float32)
    plain = lf.scene.DrawScene([lf.scene.DrawMesh(quad, np.zeros_like(quad), uv, texture)], black)
    lit = lf.scene.DrawScene([lf.scene.DrawMesh(quad, glow, uv, texture)], black)
    with lf.gpu.ViewRenderer(plain, width, height, 2) as first, lf.gpu.ViewRenderer(lit, width, height, 2) as second:
        a, _ = first.render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
        b, _ = second.render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
    np.testing.assert_allclose(b - a, np.broadcast_to([0.5, 0.0, 2.0], a.shape), atol=2e-6)


def test_uniform_world_and_clip_planes(lf):
    width, height = 16, 12
    view = _views(lf, width, height, clip=(0.5, 4.0))[0]
    far_quad = _quad(5.0, -2.0)[0]  # depth 5: past clip_end
    near_quad = _quad(5.0, 2.8)[0]  # depth 0.2: before clip_start
    scene = lf.scene.DrawScene([lf.scene.DrawMesh(far_quad, np.ones_like(far_quad)),
                                lf.scene.DrawMesh(near_quad, np.ones_like(near_quad))],
                               np.full((1, 1, 3), 0.125, np.float32))
    with lf.gpu.ViewRenderer(scene, width, height, 2) as gpu:
        for want_depth in (False, True, False):
            radiance, depth = gpu.render(view.view_matrix, view.projection_matrix, 0.5, 4.0, want_depth=want_depth)
            np.testing.assert_allclose(radiance, 0.125, atol=1e-7)
            assert (depth is None) if not want_depth else np.all(np.isinf(depth))


def test_state_is_restored_and_close_frees(lf):
    import gpu

    width, height = 8, 6
    view = _views(lf, width, height)[0]
    quad = _quad(1.0, 0.0)[0]
    scene = lf.scene.DrawScene([lf.scene.DrawMesh(quad, np.ones_like(quad))], np.zeros((2, 4, 3), np.float32))
    before = (gpu.state.depth_test_get(), gpu.state.depth_mask_get(), gpu.state.blend_get())
    renderer = lf.gpu.ViewRenderer(scene, width, height)
    renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
    assert (gpu.state.depth_test_get(), gpu.state.depth_mask_get(), gpu.state.blend_get()) == before
    renderer.close()
    renderer.close()  # twice is fine
    with pytest.raises(RuntimeError, match="closed"):
        renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0)
    with pytest.raises(ValueError):
        lf.gpu.ViewRenderer(scene, 0, 4)
    with pytest.raises(lf.gpu.DeviceError):
        lf.gpu.ViewRenderer(scene, 6000, 10, 3)  # an 18006-wide target


def test_empty_scene_and_meshes_without_triangles(lf):
    width, height = 10, 10
    view = _views(lf, width, height)[0]
    empty = lf.scene.DrawMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    scene = lf.scene.DrawScene([empty], np.full((1, 1, 3), 0.5, np.float32))
    with lf.gpu.ViewRenderer(scene, width, height) as renderer:
        radiance, depth = renderer.render(view.view_matrix, view.projection_matrix, 0.1, 100.0, want_depth=True)
    np.testing.assert_allclose(radiance, 0.5, atol=1e-7)
    assert np.all(np.isinf(depth))
