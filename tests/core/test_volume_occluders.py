"""Meshes around a medium (core.volume.occluders): they shadow lamps and end table rays.

The expected values are geometric: which voxels lie under a quad, where a ray meets a wall.
"""
from __future__ import annotations

import numpy as np
import pytest

from core import kernels
from core.scene import Light, World
from core.visibility.directions import direction_set
from core.volume import tables, transport
from core.volume.medium import make_medium
from core.volume.occluders import Occluders

pytestmark = pytest.mark.skipif(kernels.compiled() is None,
                                reason=f"numba kernels unavailable here: {kernels.status().reason}")

N = 16  # voxels per side; voxel size 0.1, so the grid's centres span [0, 1.5]
TO_WORLD = np.diag([0.1, 0.1, 0.1, 1.0])


def quad(x0, x1, y0, y1, z, casts_shadow=True):
    """A horizontal quad (two triangles) at height ``z``, as Occluders.from_meshes takes it."""
    positions = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    return positions, np.array([[0, 1, 2], [0, 2, 3]], np.int32), casts_shadow


def slab(extinction=0.5):
    return make_medium("slab", np.ones((N, N, N)), TO_WORLD, extinction=extinction, albedo=(0.8, 0.8, 0.8))


def overhead_sun() -> Light:
    return Light("sun", "SUN", np.ones(3), 2.0, direction=np.array([0.0, 0.0, -1.0]))


def test_a_quad_over_half_the_grid_shadows_that_half_from_a_sun():
    medium = slab()
    roof = Occluders.from_meshes([quad(-1.0, 0.72, -1.0, 3.0, 2.0)])  # over voxel columns x <= 7
    table = tables.build_tables(medium, direction_set(8, rotate=True, seed=1), points=1)
    lit = transport.light_medium(medium, table, [overhead_sun()], bounces=0, occluders=roof)
    free = transport.light_medium(medium, table, [overhead_sun()], bounces=0)
    shaded = lit.direct[:7, ..., 0]
    sunny = lit.direct[8:, ..., 0]
    assert shaded.max() == 0.0
    np.testing.assert_array_equal(sunny, free.direct[8:, ..., 0])
    assert sunny.min() > 0.0


def test_a_mesh_that_casts_no_shadow_lets_the_lamp_through():
    medium = slab()
    roof = Occluders.from_meshes([quad(-1.0, 3.0, -1.0, 3.0, 2.0, casts_shadow=False)])
    assert roof.shadows is None
    table = tables.build_tables(medium, direction_set(8, rotate=True, seed=1), points=1)
    lit = transport.light_medium(medium, table, [overhead_sun()], bounces=0, occluders=roof)
    free = transport.light_medium(medium, table, [overhead_sun()], bounces=0)
    np.testing.assert_array_equal(lit.direct, free.direct)


def test_a_point_lamp_below_a_floor_does_not_light_the_medium_above_it():
    medium = slab()
    floor = Occluders.from_meshes([quad(-5.0, 5.0, -5.0, 5.0, -0.3)])
    lamp = Light("lamp", "POINT", np.ones(3), 100.0, position=np.array([0.75, 0.75, -1.0]))
    table = tables.build_tables(medium, direction_set(8, rotate=True, seed=1), points=1)
    lit = transport.light_medium(medium, table, [lamp], bounces=0, occluders=floor)
    assert lit.direct.max() == 0.0
    assert transport.light_medium(medium, table, [lamp], bounces=0).direct.min() > 0.0


def test_a_wall_ends_the_table_rays_and_hides_the_world_behind_it():
    # A thin medium (little scatters) with a wall at x = 0.95 (between voxel columns 9 and 10):
    # rays going +x from columns <= 9 meet it, so their points stay before it and they do
    # not see the world; so do the rays going -x from columns >= 10.
    medium = slab(extinction=0.05)
    wall_positions = np.array([[0.95, -5.0, -5.0], [0.95, 5.0, -5.0], [0.95, 5.0, 5.0], [0.95, -5.0, 5.0]])
    wall = Occluders.from_meshes([(wall_positions, np.array([[0, 1, 2], [0, 2, 3]], np.int32), True)])
    directions = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    table = tables.build_tables(medium, directions, points=2, occluders=wall)
    x = table.voxels[:, 0]
    before = x <= 9
    assert not table.sees_world[0, before].any() and table.sees_world[0, ~before].all()
    np.testing.assert_array_equal(table.sees_world[1], before)
    reach = table.distances()[0, :, :].max(axis=1)  # index units along +x
    assert np.all(x[before] + reach[before] <= 9.5 + 1e-3)
    assert np.any(x[before] + reach[before] > 9.0)  # the points do reach up to the wall
    world = World(color=np.ones(3))
    lit = transport.light_medium(medium, table, [], world, bounces=0)
    free = transport.light_medium(medium, tables.build_tables(medium, directions, points=2), [], world, bounces=0)
    assert np.all(lit.direct < free.direct)  # every voxel has one of its two directions walled
    # The scattered fraction before the wall is the medium's, whatever is behind it: no more light appears.
    assert np.all(lit.direct <= free.direct + 1e-6)


def test_meshes_that_no_ray_meets_change_nothing_and_chunks_change_nothing(monkeypatch):
    medium = make_medium("cloud", np.random.default_rng(4).uniform(0.0, 2.0, (12, 10, 9)), TO_WORLD, extinction=3.0)
    directions = direction_set(12, rotate=True, seed=5)
    far = Occluders.from_meshes([quad(50.0, 51.0, 50.0, 51.0, 50.0)])
    plain = tables.build_tables(medium, directions, points=2, jitter_seed=3)
    monkeypatch.setattr(tables, "MESH_RAYS_PER_CHUNK", len(plain.voxels) * 5)  # three chunks of directions
    traced = tables.build_tables(medium, directions, points=2, jitter_seed=3, occluders=far)
    np.testing.assert_array_equal(traced.distance_codes, plain.distance_codes)
    np.testing.assert_array_equal(traced.escape_codes, plain.escape_codes)
    assert traced.sees_world.all()
    assert traced.nbytes == tables.table_bytes(len(plain.voxels), len(directions), 2, meshes=True)


def test_no_triangles_make_no_occluders():
    assert Occluders.from_meshes([]) is None
    assert Occluders.from_meshes([(np.zeros((0, 3)), np.zeros((0, 3), np.int32), True)]) is None


def test_a_mesh_hidden_from_volume_scattering_casts_shadows_but_ends_no_table_ray():
    medium = slab()
    positions, triangles, _ = quad(-1.0, 3.0, -1.0, 3.0, 2.0)
    hidden = Occluders.from_meshes([(positions, triangles, True, False)])
    assert hidden.scattered is None and hidden.shadows is not None
    up = np.array([[0.0, 0.0, 1.0]])
    table = tables.build_tables(medium, up, points=1, occluders=hidden)
    assert table.sees_world.all()
    seen = tables.build_tables(medium, up, points=1, occluders=Occluders.from_meshes([(positions, triangles, True)]))
    assert not seen.sees_world.any()
    lit = transport.light_medium(medium, table, [overhead_sun()], bounces=0, occluders=hidden)
    assert lit.direct.max() == 0.0


def floor(z, albedo=None, emission=None, flipped=False, side=20.0):
    """A large square floor at height ``z`` (two triangles), facing up (or down when ``flipped``)."""
    from core.volume.occluders import SurfaceMesh

    positions = np.array([[-side, -side, z], [side, -side, z], [side, side, z], [-side, side, z]])
    triangles = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    if flipped:
        triangles = triangles[:, ::-1].copy()
    return SurfaceMesh(positions, triangles, True, True,
                       None if albedo is None else np.full((2, 3), albedo, np.float32),
                       None if emission is None else np.full((2, 3), emission, np.float32))


@pytest.mark.parametrize("flipped", [False, True])
def test_a_lit_floor_under_a_cloud_sends_back_its_lamp_light_through_the_cloud_s_shadow(flipped):
    # A cloud over a grey floor, a sun straight down: every table ray that ends at the floor
    # brings its escaping fraction times albedo / pi times the sun's irradiance at the hit,
    # which the cloud shadows. The expected value marches that shadow with the independent
    # reference (benchmarks/volume_reference.py); only the table's own escaping fractions are
    # taken from the code under test.
    from benchmarks.volume_reference import segment_transmittance

    medium = make_medium("cloud", np.random.default_rng(2).uniform(0.5, 1.5, (10, 9, 8)), TO_WORLD, extinction=4.0)
    ground = Occluders.from_meshes([floor(-0.35, albedo=0.5, flipped=flipped)])
    directions = direction_set(24, rotate=True, seed=4)
    table = tables.build_tables(medium, directions, points=2, occluders=ground)
    sun = overhead_sun()
    # The meshes' light joins the first bounce (as Cycles counts it); the same tables bounce the
    # rest alike, so the difference is the floor's light alone.
    lit = transport.light_medium(medium, table, [sun], bounces=1, occluders=ground)
    alone = transport.light_medium(medium, table, [sun], bounces=1)
    np.testing.assert_array_equal(lit.direct, alone.direct)
    reflected = (lit.indirect - alone.indirect)[tuple(table.voxels.T)][:, 0]

    expected = np.zeros(len(table.voxels))
    origins = medium.world_positions(table.voxels)
    for d, direction in enumerate(directions):
        if direction[2] >= 0:
            assert table.sees_world[d].all()
            continue
        hits = origins + ((-0.35 - origins[:, 2]) / direction[2])[:, None] * direction
        starts = medium.to_index(hits)
        shadow = segment_transmittance(medium.density, medium.linear, medium.extinction, starts,
                                       starts + np.array([0.0, 0.0, 40.0]))
        expected += table.escape()[d] * 0.5 / np.pi * sun.strength * shadow
    expected /= len(directions)
    assert expected.max() > 0.01 and expected.min() < 0.5 * expected.max()  # the cloud's shadow shows
    np.testing.assert_allclose(reflected, expected, rtol=2e-3, atol=1e-4 * expected.max())


def test_an_emitting_floor_under_a_thin_medium_fills_the_lower_half_of_every_voxel_s_sky():
    # Nearly transparent medium, a floor of radiance 2 below it, no lamps: each voxel sees the
    # floor over the lower hemisphere, so its in-scattered radiance (the sphere's mean) is 1,
    # up to the direction set's sampling of the two halves (24 directions) and the transmittance.
    medium = make_medium("haze", np.ones((6, 6, 6)), TO_WORLD, extinction=1e-3)
    glow = Occluders.from_meshes([floor(-0.2, emission=2.0)])
    directions = direction_set(24, rotate=True, seed=4)
    table = tables.build_tables(medium, directions, points=1, occluders=glow)
    lit = transport.light_medium(medium, table, [], None, bounces=1, occluders=glow)
    downward = np.mean(directions[:, 2] < 0)
    np.testing.assert_allclose(lit.indirect[..., 0], 2.0 * downward, rtol=2e-3)
    assert not lit.direct.any()
    skipped = transport.light_medium(medium, table, [], None, bounces=0, occluders=glow)
    assert not skipped.indirect.any() and any("counts as a bounce" in w for w in skipped.warnings)
    assert abs(downward - 0.5) < 0.1
