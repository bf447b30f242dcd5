"""Texel footprints (core.sampling.footprint): Cycles' box (a texel wide by default, half a
texel as Blender 4.2 to 5.2.0 bake), clipped to the texel's triangle, and what the table and
exact shadows do with it."""
import dataclasses

import numpy as np
import pytest

from core.pipeline.prepare import prepare
from core.sampling.footprint import BOX_WIDTH, footprint_corners, footprint_offsets
from core.sampling.samples import build_samples
from core.scene import Light, Scene
from core.settings import BakeSettings
from core.transport.direct import lamp_irradiance
from core.visibility.table import TraceRequest, decode_uv, trace_table, update_table
from core_scenes import quad_mesh


def _plane(resolution=16, size=2.0):
    h = size / 2
    return quad_mesh("Plane", [(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], resolution=resolution)


def test_points_fill_the_texel_s_box_around_the_centre_on_the_surface():
    mesh = _plane(resolution=16, size=2.0)
    samples = build_samples(mesh, footprint_samples=16)
    texel = 2.0 / 16
    offsets = samples.footprint.astype(np.float64)
    assert offsets.shape == (len(samples), 16, 3) and samples.footprint.dtype == np.float32
    assert np.all(offsets[..., 2] == 0.0)  # on the plane
    # Within the texel's box.
    assert np.abs(offsets[..., :2]).max() <= BOX_WIDTH / 2 * texel * (1 + 1e-5)
    # Stratified: each quarter of the box holds 4 of the 16 points of every texel the quad's
    # diagonal does not cut and whose box stays off the plane's edge (there, points on the
    # other triangle or within the barycentric inset of the edge were drawn again).
    quarter = (offsets[..., 0] > 0).astype(int) * 2 + (offsets[..., 1] > 0)
    counts = np.stack([(quarter == q).sum(axis=1) for q in range(4)], axis=1)
    x, y = samples.pixel % 16, samples.pixel // 16
    inner = (np.abs(x - y) > 1) & (np.minimum(x, y) > 0) & (np.maximum(x, y) < 15)
    assert np.all(counts[inner] == 4)
    # Scrambled per texel: neighbours do not share a pattern.
    assert not np.allclose(offsets[0], offsets[1])


# Both boxes Cycles' bakes use: half a texel (Blender 4.2 to 5.2.0) and the whole texel (5.2.1 on).
WIDTHS = (0.5, 1.0)


@pytest.mark.parametrize("box_width", WIDTHS)
def test_points_stay_on_the_texel_s_own_triangle_and_are_reproducible(box_width):
    # A triangle whose hypotenuse cuts through texels: every point of a texel whose centre
    # lies inside must stay inside the triangle (Cycles redraws the others).
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    corner_uv = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
    corners = positions[None]
    width = height = 8
    pixel = np.array([y * width + x for y in range(height) for x in range(width) if x + y + 1 < width], np.int64)
    centre_uv = np.stack([(pixel % width + 0.5) / width, (pixel // width + 0.5) / height], axis=1)
    position = np.concatenate([centre_uv, np.zeros((len(pixel), 1))], axis=1)
    triangle = np.zeros(len(pixel), np.int32)
    offsets = footprint_offsets(pixel, triangle, width, height, corner_uv, corners, position, 16,
                                box_width=box_width)
    points = position[:, None, :] + offsets
    assert np.all(points[..., 0] >= -1e-6) and np.all(points[..., 1] >= -1e-6)
    assert np.all(points[..., 0] + points[..., 1] <= 1 + 1e-6)
    # Texels along the hypotenuse had points redrawn: they stay on the triangle's side.
    border = (pixel % width) + (pixel // width) + 1 == width - 1
    assert np.any(border)
    again = footprint_offsets(pixel, triangle, width, height, corner_uv, corners, position, 16,
                              box_width=box_width)
    np.testing.assert_array_equal(offsets, again)
    box = footprint_corners(pixel, triangle, width, height, corner_uv, corners, position, offsets,
                            box_width=box_width)
    # Boxes clear of all three edges (a whole texel's box reaches the legs u = 0 and v = 0).
    low = 0.5 - box_width / 2
    inner = (~border & ((pixel % width) + (pixel // width) + 1 < width - 1)
             & (pixel % width + low > 0) & (pixel // width + low > 0))
    assert inner.sum() >= 10
    np.testing.assert_allclose(np.abs(box[inner][..., :2]), box_width / 2 / width, rtol=1e-3)
    # Corners beyond the hypotenuse are replaced by footprint points, on the triangle.
    corner_points = position[:, None, :] + box
    assert np.all(corner_points[..., 0] + corner_points[..., 1] <= 1 + 1e-6)


def test_a_sliver_too_thin_for_any_point_keeps_the_sample_s_own_position():
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1e-7, 0]], np.float64)
    corner_uv = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1e-7]]])
    offsets = footprint_offsets(np.array([0]), np.array([0], np.int32), 4, 4, corner_uv, positions[None],
                                np.array([[0.1, 0.0, 0.0]]), 8)
    assert np.all(offsets == 0.0)


def test_the_table_starts_each_direction_from_its_footprint_point_and_updates_reproduce_it():
    ground = _plane(resolution=12)
    blocker = quad_mesh("Blocker", [(-0.3, -0.3, 0.5), (-0.3, 0.3, 0.5), (0.3, 0.3, 0.5), (0.3, -0.3, 0.5)],
                        resolution=6)
    settings = BakeSettings(directions=32, bounces=1, footprint_samples=8)
    p = prepare(Scene([ground, blocker], []), settings, table_needed=True)
    request = TraceRequest(p.directions, p.position, p.geometric, _hits(p), footprint=p.footprint[0],
                           rotations=p.rotations, group=p.group)
    fresh = trace_table(p.ray_scene, request)
    np.testing.assert_array_equal(fresh.hit_object, p.table.hit_object)
    centres = trace_table(p.ray_scene, TraceRequest(p.directions, p.position, p.geometric, _hits(p),
                                                    rotations=p.rotations, group=p.group))
    hit = fresh.hit_object >= 0
    moved = np.abs(decode_uv(fresh.hit_uv_code) - decode_uv(centres.hit_uv_code)).max(axis=2)[hit]
    assert np.count_nonzero(moved > 1e-4) > 0.5 * np.count_nonzero(hit)  # the rays did start elsewhere
    # Move the blocker: the incremental update (spheres widened by the footprint's reach)
    # gives exactly the fresh table of the moved scene.
    blocker.positions = blocker.positions + np.array([0.15, 0.0, 0.0])
    q = prepare(Scene([ground, blocker], []), settings, table_needed=True)
    new_request = TraceRequest(q.directions, q.position, q.geometric, _hits(q), footprint=q.footprint[0],
                               rotations=q.rotations, group=q.group)
    changed_scene = type(q.ray_scene)([(blocker.positions, blocker.triangles)], 1, q.ray_scene.centre)
    updated, _ = update_table(fresh, p.sample_offset, q.sample_offset, q.ray_scene, changed_scene, [1], new_request)
    np.testing.assert_array_equal(updated.hit_object, q.table.hit_object)
    np.testing.assert_array_equal(updated.hit_distance_code, q.table.hit_distance_code)


def _hits(p):
    from core.pipeline.prepare import scene_hit_geometry

    return scene_hit_geometry(p.meshes)


def test_a_shadow_edge_through_a_sliver_of_the_box_is_found_by_the_corner_probes():
    # A blocker edge that clips only a thin strip of some texels' boxes: the corner probes
    # must not call those texels fully lit or fully shadowed.
    ground = _plane(resolution=16, size=2.0)
    texel = 2.0 / 16
    half = BOX_WIDTH / 2 * texel
    centre = -1 + 11.5 * texel
    edge = centre + 0.6 * half  # a fifth of the box of the texels at x = centre stays lit
    blocker = quad_mesh("Blocker", [(-2, -2, 0.5), (edge, -2, 0.5), (edge, 2, 0.5), (-2, 2, 0.5)], resolution=4)
    sun = Light("Sun", "SUN", np.ones(3), 1.0)
    p = prepare(Scene([ground, blocker], []), BakeSettings(directions=8, bounces=0, footprint_samples=16),
                table_needed=False)
    irradiance, _ = lamp_irradiance(p.sample_set(), p.shadowing(), [sun])
    x = p.position[:len(p.object_samples[0]), 0]
    value = irradiance[:len(x), 0]
    crossed = np.abs(x - centre) < 1e-6
    assert np.count_nonzero(crossed) >= 8
    assert np.all((value[crossed] > 0.0) & (value[crossed] < 0.5))
    assert np.all(value[x < edge - texel] == 0.0) and np.all(value[x > edge + texel] == 1.0)


@pytest.mark.parametrize("box_width, low, high", [(0.5, 0.3, 0.6), (1.0, 0.7, 0.95)])
def test_a_point_that_finds_no_place_on_a_small_triangle_takes_the_centre_as_cycles_does(box_width, low, high):
    # Cells a fifth of a texel across: a box half a texel wide holds 12.5 triangles, so a draw
    # lands on the texel's own with odds 0.08 and all ten miss with odds 0.43; a whole texel's
    # holds 50 (odds 0.02, all ten miss: 0.82). Cycles then bakes the texel's centre.
    samples = build_samples(_fine_grid(cells=40, resolution=8), footprint_samples=16, footprint_width=box_width)
    at_centre = np.all(samples.footprint == 0.0, axis=2).mean()
    assert low < at_centre < high
    on_plane = samples.position[:, None, :] + samples.footprint
    assert np.all(np.abs(on_plane[..., 2]) < 1e-6)


def _fine_grid(cells=40, resolution=8):
    """A 1 m plane of cells x cells quads (two triangles each), UVs = xy, at ``resolution``²."""
    from core.scene import Material, Mesh
    ticks = np.linspace(0.0, 1.0, cells + 1)
    x, y = np.meshgrid(ticks, ticks)
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange(x.size).reshape(cells + 1, cells + 1)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    uv = positions[:, :2].astype(np.float32)
    return Mesh(name="Grid", positions=positions, triangles=triangles.astype(np.int32),
                corner_normals=np.tile(np.float32([0, 0, 1]), (len(triangles), 3, 1)),
                material_index=np.zeros(len(triangles), np.int32), materials=[Material()],
                uv_maps={"UVMap": uv[triangles]}, bake_uv_map="UVMap", resolution=(resolution, resolution))


def test_points_on_a_smooth_face_take_the_normal_interpolated_where_they_lie():
    mesh = _plane(resolution=8, size=2.0)
    tilted = np.array([[0.3, 0.0, 1.0], [-0.3, 0.0, 1.0], [0.0, 0.3, 1.0]])
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    mesh.corner_normals[:] = tilted.astype(np.float32)  # both triangles smooth
    samples = build_samples(mesh, footprint_samples=16)
    normals = samples.footprint_normals
    assert normals is not None and normals.shape == samples.footprint.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=2), 1.0, rtol=1e-5)
    # Each point's normal is the corner normals weighted by its barycentric coordinates there.
    row, slot = 5, 3
    triangle = mesh.triangles[samples.triangle[row]]
    corners = mesh.positions[triangle]
    point = samples.position[row] + samples.footprint[row, slot]
    weights = np.linalg.lstsq(np.vstack([corners.T, np.ones(3)]), np.append(point, 1.0), rcond=None)[0]
    expected = weights @ tilted
    np.testing.assert_allclose(normals[row, slot], expected / np.linalg.norm(expected), atol=1e-5)
    # The points spread the normal: not every point shades like the centre.
    assert np.einsum("kpd,kd->kp", normals, samples.normal).min() < 0.99999
    flat = build_samples(_plane(resolution=8), footprint_samples=16)
    assert flat.footprint_normals is None


def test_direct_light_on_a_smooth_face_averages_the_cosine_over_the_footprint():
    # Corner normals spread 35 degrees either way over a 2 m plane at 4² texels: a texel's
    # points see the sun at different angles, and the texel takes their mean, not its centre's.
    mesh = _plane(resolution=4, size=2.0)
    spread = np.array([[0.7, 0.0, 1.0], [-0.7, 0.0, 1.0], [-0.7, 0.0, 1.0], [0.7, 0.0, 1.0]])
    per_vertex = spread / np.linalg.norm(spread, axis=1, keepdims=True)
    mesh.corner_normals[:] = per_vertex[mesh.triangles].astype(np.float32)
    towards = np.array([0.8, 0.0, 0.6])
    sun = Light("Sun", "SUN", np.ones(3), 1.0, direction=-towards)
    p = prepare(Scene([mesh], []), BakeSettings(directions=8, bounces=0, footprint_samples=16), table_needed=False)
    irradiance, _ = lamp_irradiance(p.sample_set(), p.shadowing(), [sun])
    normals = p.sample_set().footprint_normals.astype(np.float64)
    expected = np.clip(normals @ towards, 0.0, None).mean(axis=1)
    np.testing.assert_allclose(irradiance[:, 0], expected, rtol=1e-5, atol=1e-7)
    at_centre = np.clip(p.normal @ towards, 0.0, None)
    assert np.abs(expected - at_centre).max() > 1e-3


def _lit_share_of_boxes(centres, normal, offset, half, grid=120):
    """The share of each texel's box (centre (k, 2), half-width ``half``) on the lit side
    n . p > offset of a straight shadow edge, by a fine grid."""
    steps = (np.arange(grid) + 0.5) / grid * 2 - 1
    gx, gy = np.meshgrid(steps * half, steps * half)
    points = centres[:, None, :] + np.stack([gx.ravel(), gy.ravel()], axis=1)[None]
    return (points @ normal > offset).mean(axis=1)


# Measured: dense / sparse RMS 0.49 on half-texel boxes, 0.73 on whole ones, where the edge
# also crosses the 21 more boxes it only clips at a corner (41 texels against 20).
@pytest.mark.parametrize("box_width, gain", [(0.5, 0.6), (1.0, 0.8)])
def test_texels_a_shadow_edge_crosses_take_the_dense_footprint_and_follow_the_edge_closer(box_width, gain):
    from core.transport import direct
    # A slanted blocker edge over a 32² ground under an overhead sun: the lit share of every
    # texel's box is known exactly.
    ground = _plane(resolution=32, size=2.0)
    texel = 2.0 / 32
    normal = np.array([np.cos(0.3), np.sin(0.3)])
    offset = 0.05
    far = 4.0
    # The blocker covers n . p <= offset at height 0.5 (its edge passes through many boxes).
    along = np.array([-normal[1], normal[0]])
    a, b = offset * normal - far * along, offset * normal + far * along
    blocker = quad_mesh("Blocker", [(*a, 0.5), (*(a - far * normal), 0.5), (*(b - far * normal), 0.5), (*b, 0.5)],
                        resolution=4)
    sun = Light("Sun", "SUN", np.ones(3), 1.0)
    p = prepare(Scene([ground, blocker], []),
                BakeSettings(directions=8, bounces=0, footprint_samples=16, footprint_width=box_width),
                table_needed=False)
    count = len(p.object_samples[0])
    exact = _lit_share_of_boxes(p.position[:count, :2], normal, offset, box_width / 2 * texel)
    crossed = (exact > 0) & (exact < 1)
    assert crossed.sum() >= 15
    dense, _ = lamp_irradiance(p.sample_set(), p.shadowing(), [sun])
    sparse_set = dataclasses.replace(p.sample_set(), dense_footprint=None)
    sparse, _ = lamp_irradiance(sparse_set, p.shadowing(), [sun])
    error_dense = np.sqrt(np.mean((dense[:count, 0][crossed] - exact[crossed]) ** 2))
    error_sparse = np.sqrt(np.mean((sparse[:count, 0][crossed] - exact[crossed]) ** 2))
    assert error_dense < gain * error_sparse, (error_dense, error_sparse)
    # Texels the edge does not cross are the same either way.
    np.testing.assert_array_equal(dense[:count][~crossed & (np.abs(exact - 0.5) == 0.5)],
                                  sparse[:count][~crossed & (np.abs(exact - 0.5) == 0.5)])
    assert direct.EDGE_FOOTPRINT_POINTS > 16


def test_scrambled_points_are_each_points_own_scramble():
    """The footprints' jitter, computed a block of samples at a time for every point at once,
    is point j's Sobol pair Owen-scrambled by each sample's own seeds, as one point at a time
    gives it; across block boundaries and for a shadow edge's 64 points alike."""
    from core.lights.sampler import _sobol_point, owen_scramble
    from core.sampling.footprint import _scrambled_points
    rng = np.random.default_rng(3)
    for samples, count in ((5, 64), (3000, 16), (1, 2)):
        seeds = rng.integers(0, 2 ** 32, (2, samples), dtype=np.uint64).astype(np.uint32)
        points = _scrambled_points(count, seeds)
        assert points.shape == (samples, count, 2)
        for index in (0, 1, count - 1):
            for dimension in range(2):
                own = owen_scramble(np.array([_sobol_point(index)[dimension]], np.uint32), seeds[dimension])
                np.testing.assert_array_equal(points[:, index, dimension], (own >> np.uint32(8)) * 2.0 ** -24)


def test_samples_needing_no_shadow_ray_are_summed_in_one_pass_bitwise(monkeypatch):
    """A hard lamp over footprints: the samples whose shadows the probes decided, and those no
    point lights, are summed by one compiled pass (LampPoints.add_untraced) instead of point
    by point. It gives the loop's bits, for suns, points and blended spots, smooth and flat
    faces, a partial shadow and light linking, with the same shadow rays."""
    import pytest

    from core import kernels
    from core.lights.lamps import LampPoints
    if kernels.compiled() is None:
        pytest.skip(f"compiled kernels unavailable: {kernels.status().reason}")
    ground = _plane(resolution=16, size=2.0)
    tilted = np.array([[0.5, 0.0, 1.0], [-0.5, 0.2, 1.0], [0.0, -0.5, 1.0]])
    ground.corner_normals[:] = (tilted / np.linalg.norm(tilted, axis=1, keepdims=True)).astype(np.float32)
    blocker = quad_mesh("Blocker", [(-2, -2, 0.5), (0.1, -2, 0.5), (0.1, 2, 0.5), (-2, 2, 0.5)], resolution=8)
    wall = quad_mesh("Wall", [(1, -1, 0), (1, 1, 0), (1, 1, 1), (1, -1, 1)], resolution=8)
    p = prepare(Scene([ground, blocker, wall], []), BakeSettings(directions=8, bounces=0, footprint_samples=16),
                table_needed=False)
    down = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    lamps = [Light("Sun", "SUN", np.ones(3), 2.0, direction=down),
             Light("Point", "POINT", np.array([1.0, 0.5, 0.2]), 80.0, position=np.array([0.3, 0.2, 0.9])),
             Light("Spot", "SPOT", np.ones(3), 60.0, position=np.array([0.0, 0.0, 1.5]), direction=down,
                   spot_size=1.0, spot_blend=0.4),
             Light("Linked", "POINT", np.ones(3), 50.0, position=np.array([0.5, 0.0, 0.7]), receivers=("Plane",))]
    summed = []
    add_untraced = LampPoints.add_untraced

    def recording(self, *args):
        pending = add_untraced(self, *args)
        summed.append(None if pending is None else int(np.count_nonzero(~pending)))
        return pending

    for lamp in lamps:
        with monkeypatch.context() as patch:
            patch.setattr(LampPoints, "add_untraced", recording)
            fused, fused_rays = lamp_irradiance(p.sample_set(), p.shadowing(), [lamp])
        assert summed[-1], lamp.name  # the one pass ran and took samples
        with monkeypatch.context() as patch:
            patch.setattr(LampPoints, "add_untraced", lambda *args: None)
            looped, looped_rays = lamp_irradiance(p.sample_set(), p.shadowing(), [lamp])
        assert np.array_equal(fused, looped), lamp.name
        assert fused_rays == looped_rays and fused.max() > 0, lamp.name


def test_direct_light_by_chunks_of_samples_is_bitwise_the_whole_pass(monkeypatch):
    """lamp_irradiance evaluates exact shadows DIRECT_LIGHT_CHUNK samples at a time, to bound its
    working memory: the light, the shadow rays and what it keeps for the next relight (the
    curved footprints) are those of one pass over every sample, for hard and soft lamps over
    smooth footprints with penumbrae and edge texels."""
    from core.transport import direct

    ground = _plane(resolution=16, size=2.0)
    tilted = np.array([[0.5, 0.0, 1.0], [-0.5, 0.2, 1.0], [0.0, -0.5, 1.0]])
    ground.corner_normals[:] = (tilted / np.linalg.norm(tilted, axis=1, keepdims=True)).astype(np.float32)
    blocker = quad_mesh("Blocker", [(-2, -2, 0.5), (0.1, -2, 0.5), (0.1, 2, 0.5), (-2, 2, 0.5)], resolution=8)
    p = prepare(Scene([ground, blocker], []), BakeSettings(directions=8, bounces=0, footprint_samples=16,
                                                          area_light_samples=3), table_needed=False)
    down = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    lights = [Light("Sun", "SUN", np.ones(3), 2.0, direction=down, angle=np.radians(8.0)),
              Light("Point", "POINT", np.array([1.0, 0.5, 0.2]), 80.0, position=np.array([0.3, 0.2, 0.9]),
                    radius=0.2)]
    whole_set = p.sample_set()
    whole, whole_rays = lamp_irradiance(whole_set, p.shadowing(), lights)
    monkeypatch.setattr(direct, "DIRECT_LIGHT_CHUNK", 37)  # chunks that split objects and leave a remainder
    chunked_set = dataclasses.replace(whole_set, derived={})
    chunked, chunked_rays = lamp_irradiance(chunked_set, p.shadowing(), lights)
    assert len(whole_set) > 5 * 37 and whole.max() > 0
    np.testing.assert_array_equal(chunked, whole)
    assert chunked_rays == whole_rays
    assert "curved_footprints" in whole_set.derived
    assert set(chunked_set.derived) == set(whole_set.derived)
    for name, value in whole_set.derived.items():
        np.testing.assert_array_equal(chunked_set.derived[name], value)
    # A second pass over the chunks reads back what the first kept, with the same light.
    again, _ = lamp_irradiance(chunked_set, p.shadowing(), lights)
    np.testing.assert_array_equal(again, whole)


@pytest.mark.parametrize("compiled", [True, False], ids=["kernels", "numpy"])
def test_corners_given_per_sample_with_their_seed_triangles_place_the_same_points(compiled, monkeypatch):
    """build_samples hands the footprint each sample's own triangle's UVs and corners (the
    triangles indexed 0..k-1) and seeds the draws with the mesh's triangles: the points, box
    corners and point normals are bitwise those of the whole mesh's arrays indexed by triangle."""
    from core import kernels
    from core.sampling.footprint import footprint_normals
    if not compiled:
        monkeypatch.setattr(kernels, "compiled", lambda: None)
    rng = np.random.default_rng(5)
    width = height = 16
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 9), np.linspace(0, 1, 9)), -1).reshape(-1, 2)
    positions = np.column_stack([grid, 0.1 * rng.random(len(grid))])
    cells = [(y * 9 + x) for y in range(8) for x in range(8)]
    triangles = np.array([t for c in cells for t in ((c, c + 1, c + 10), (c, c + 10, c + 9))], np.int64)
    corner_uv = grid[triangles]
    corners = positions[triangles]
    normals = rng.normal(size=(len(triangles), 3, 3)).astype(np.float32) + np.float32([0, 0, 4])
    pixel = np.arange(width * height, dtype=np.int64)
    centre = np.stack([(pixel % width + 0.5) / width, (pixel // width + 0.5) / height], axis=1)
    # Each texel's triangle: the grid cell's, then the side of its diagonal.
    cell = np.minimum((centre * 8).astype(int), 7)
    local = centre * 8 - cell
    triangle = ((cell[:, 1] * 8 + cell[:, 0]) * 2 + (local[:, 1] > local[:, 0])).astype(np.int32)
    a, b, c = (corners[triangle, i] for i in range(3))
    position = (a + b + c) / 3
    normal = np.tile([0.0, 0.0, 1.0], (len(pixel), 1))
    smooth = np.ones(len(pixel), bool)

    whole = footprint_offsets(pixel, triangle, width, height, corner_uv, corners, position, 16)
    own = np.arange(len(pixel))
    mine = footprint_offsets(pixel, own, width, height, corner_uv[triangle], corners[triangle], position, 16,
                             seed_triangle=triangle)
    np.testing.assert_array_equal(mine, whole)
    np.testing.assert_array_equal(
        footprint_corners(pixel, own, width, height, corner_uv[triangle], corners[triangle], position, mine),
        footprint_corners(pixel, triangle, width, height, corner_uv, corners, position, whole))
    np.testing.assert_array_equal(
        footprint_normals(mine, position, own, corners[triangle], normals[triangle], normal, smooth),
        footprint_normals(whole, position, triangle, corners, normals, normal, smooth))
    # The seed matters: seeded by 0..k-1 instead, the points differ.
    assert not np.array_equal(
        footprint_offsets(pixel, own, width, height, corner_uv[triangle], corners[triangle], position, 16), whole)
