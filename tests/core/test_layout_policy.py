"""core.sampling.layout: atlas sizes and when mode auto takes vertex tables."""
import numpy as np
import pytest

from core.geometry import triangle_areas
from core.sampling import layout
from core.settings import LayoutSettings


def grid(segments: int, size: float = 1.0):
    """A flat (segments x segments)-quad square of side ``size``: positions (n, 3), triangles (m, 3)."""
    ticks = np.linspace(0.0, size, segments + 1)
    x, y = np.meshgrid(ticks, ticks, indexing="ij")
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange((segments + 1) ** 2).reshape(segments + 1, segments + 1)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return positions, triangles


def test_triangle_areas_in_uv_and_world_space():
    uv = np.array([[[0, 0], [1, 0], [0, 1]], [[0, 0], [2, 0], [2, 2]]], float)
    np.testing.assert_allclose(triangle_areas(uv), [0.5, 2.0])
    world = np.array([[[0, 0, 0], [0, 3, 0], [0, 0, 4]], [[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]]], float)
    areas = triangle_areas(world)
    assert areas[0] == pytest.approx(6.0) and np.isfinite(areas[1])


def test_the_surface_area_of_a_mesh():
    positions, triangles = grid(4, size=2.0)
    assert layout.surface_area(positions, triangles) == pytest.approx(4.0)
    assert layout.surface_area(positions, triangles[:0]) == 0.0


@pytest.mark.parametrize("own_resolution, own_density, scene, expected", [
    (64, 5.0, LayoutSettings(resolution=32, texel_density=7.0), (64, 64)),  # the object's resolution wins
    (0, 10.0, LayoutSettings(resolution=32, texel_density=7.0), (20, 20)),  # then its density: 2 m x 10/m
    (0, 0.0, LayoutSettings(resolution=32, texel_density=7.0), (14, 14)),  # then the scene's density
    (0, 0.0, LayoutSettings(resolution=32), (32, 32)),  # then the scene's resolution
    (0, 0.1, LayoutSettings(resolution=32), (8, 8)),  # never below 8 texels a side...
    (0, 1e5, LayoutSettings(resolution=32), (8192, 8192)),  # ...nor above 8192
])
def test_object_resolution_takes_the_object_s_own_first(own_resolution, own_density, scene, expected):
    assert layout.object_resolution(own_resolution, own_density, scene, 4.0, 1.0) == expected


@pytest.mark.parametrize("own_resolution, own_density, scene, view_density, expected", [
    (0, 0.0, LayoutSettings(resolution=256), 10.0, (20, 20)),  # the cameras need 2 m x 10/m: lowered
    (0, 0.0, LayoutSettings(resolution=16), 10.0, (16, 16)),  # never raised above the scene's size
    (0, 0.0, LayoutSettings(resolution=64, texel_density=50.0), 10.0, (20, 20)),  # the scene's density lowered
    (0, 0.0, LayoutSettings(resolution=256), 1e-9, (16, 16)),  # unseen: the smallest view-sized atlas
    (64, 0.0, LayoutSettings(resolution=256), 10.0, (64, 64)),  # the object's own resolution stays
    (0, 50.0, LayoutSettings(resolution=256), 10.0, (100, 100)),  # and so does its own density
    (0, 0.0, LayoutSettings(resolution=256), 0.0, (256, 256)),  # no cameras: the scene's size
])
def test_cameras_lower_an_atlas_to_what_they_see(own_resolution, own_density, scene, view_density, expected):
    assert layout.object_resolution(own_resolution, own_density, scene, 4.0, 1.0, view_density) == expected
    assert layout.MIN_VIEW_SIZED_RESOLUTION == 16


def test_the_planned_resolution_assumes_the_typical_packed_share():
    positions, triangles = grid(2, size=2.0)
    planned = layout.planned_resolution(0, 10.0, LayoutSettings(), positions, triangles)
    side = int(np.ceil(np.sqrt(4.0 / layout.TYPICAL_PACKED_UV_AREA) * 10.0))
    assert planned == (side, side)
    # Without a density the area does not matter.
    assert layout.planned_resolution(0, 0.0, LayoutSettings(resolution=48), positions, triangles) == (48, 48)


def test_auto_keeps_an_atlas_for_a_coarse_mesh():
    positions, triangles = grid(8)
    assert layout.auto_vertex_reason(positions, triangles, 0, 0.0, LayoutSettings(resolution=256)) is None


def test_auto_takes_vertex_tables_where_vertices_are_finer_than_texels():
    positions, triangles = grid(40)  # 1681 vertices, 1/40 apart
    assert len(positions) >= layout.DENSE_MIN_VERTICES
    reason = layout.auto_vertex_reason(positions, triangles, 0, 0.0, LayoutSettings(resolution=16))
    assert reason is not None and "finer than a texel" in reason and "16x16" in reason
    # An object's own resolution makes the texels fine enough again.
    assert layout.auto_vertex_reason(positions, triangles, 256, 0.0, LayoutSettings(resolution=16)) is None


def test_auto_takes_vertex_tables_for_a_mesh_too_big_to_unwrap():
    positions, triangles = grid(8)
    many = np.repeat(triangles, layout.UNWRAP_TRIANGLE_BUDGET // len(triangles) + 1, axis=0)
    reason = layout.auto_vertex_reason(positions, many, 0, 0.0, LayoutSettings())
    assert reason.startswith(f"{len(many)} triangles")


def test_unwrap_seconds_grow_faster_than_the_triangles():
    assert layout.unwrap_seconds(20_000) == pytest.approx(2.2)
    assert layout.unwrap_seconds(40_000) > 2 * layout.unwrap_seconds(20_000)


@pytest.mark.parametrize("own_resolution", [0, 48])
@pytest.mark.parametrize("own_density", [0.0, 30.0])
@pytest.mark.parametrize("texel_density", [0.0, 20.0])
@pytest.mark.parametrize("view_density", [0.0, 10.0])
def test_the_areas_are_measured_wherever_the_atlas_size_reads_them(own_resolution, own_density, texel_density,
                                                                   view_density):
    """Callers skip measuring the areas where needs_areas says the size does not read them:
    there, any areas give the size that none do."""
    settings = LayoutSettings(resolution=64, texel_density=texel_density)
    sizes = {layout.object_resolution(own_resolution, own_density, settings, world, uv, view_density)
             for world, uv in ((0.0, 0.0), (3.0, 0.4), (900.0, 0.7))}
    if not layout.needs_areas(own_resolution, own_density, settings, view_density):
        assert len(sizes) == 1
    elif own_resolution == 0:
        assert len(sizes) > 1
