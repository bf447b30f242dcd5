import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.transport.contract import GatherGeometry, GatherSource, direction_chunks
from core.transport.gather import (
    AtlasLayout,
    ambient_occlusion,
    gather,
    gather_normalisation,
    open_hemisphere_weight,
)
from core.visibility.directions import ShadowRegions, spherical_fibonacci
from core.visibility.shadows import shadow_fractions
from core.visibility.table import BELOW_HORIZON, MISS, VisibilityTable


def _table(directions, normals, hit_object, hit_uv, hit_distance=None):
    if hit_distance is None:
        hit_distance = np.where(hit_object >= 0, 1.0, np.inf).astype(np.float32)
    return VisibilityTable.from_values(directions, hit_object, hit_uv, hit_distance)


def _open_table(count, normals, code=MISS):
    d = spherical_fibonacci(count)
    above = (normals @ d.T).T > 0
    hit = np.where(above, code, BELOW_HORIZON).astype(np.int16)
    return _table(d, normals, hit, np.zeros((count, len(normals), 2), np.float32))


@pytest.mark.parametrize("count", [1, 7, 32, 128, 513])
def test_white_furnace_is_exact_for_any_direction_count(count):
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    table = _open_table(count, normals)
    scale = gather_normalisation(table, normals, np.pi)
    layout = AtlasLayout.from_sizes([(2, 2)])
    radiance = np.zeros((layout.size, 3), np.float32)
    irradiance = gather(GatherGeometry(table, normals, scale, layout), GatherSource(radiance, np.ones(3)))
    open_samples = scale > 0
    # Exact up to the gather's float32 sums (a few ULPs of pi).
    np.testing.assert_allclose(irradiance[open_samples], np.pi, rtol=1e-6)
    np.testing.assert_allclose(ambient_occlusion(table, normals, scale)[open_samples], 1.0)


@pytest.mark.parametrize("lean_degrees", [0.0, 5.0, 22.5, 60.0, 120.0, 180.0])
def test_the_open_hemisphere_weight_is_the_integral_over_the_directions_above_the_face(lean_degrees):
    """pi (1 + cos theta) / 2 against a sum over 200k evenly spread directions of the cosine
    about the shading normal, over those above the face only."""
    lean = np.radians(lean_degrees)
    geometric = np.array([[0.0, 0.0, 1.0]])
    shading = np.array([[np.sin(lean), 0.0, np.cos(lean)]])
    d = spherical_fibonacci(200_000)
    above_face = d @ geometric[0] > 0
    numeric = np.sum(np.maximum(d @ shading[0], 0.0) * above_face) * 4.0 * np.pi / len(d)
    weight = open_hemisphere_weight(shading, geometric)
    assert weight.shape == (1,) and weight.dtype == np.float64
    assert weight[0] == pytest.approx(numeric, abs=2e-4)
    # Unnormalised normals give the same weight.
    assert open_hemisphere_weight(3.0 * shading, 0.5 * geometric)[0] == pytest.approx(weight[0], rel=1e-12)


def test_the_open_hemisphere_weight_of_rows_is_bitwise_the_rows_of_the_whole():
    """The scale-out's workers compute it for their rows alone."""
    rng = np.random.default_rng(5)
    shading, geometric = rng.normal(size=(2, 1000, 3))
    whole = open_hemisphere_weight(shading, geometric)
    assert np.array_equal(open_hemisphere_weight(shading[317:640], geometric[317:640]), whole[317:640])
    assert np.all((whole >= 0) & (whole <= np.pi))


@pytest.mark.parametrize("count", [16, 128, 1024])
def test_a_smooth_shaded_sample_in_a_white_world_gets_what_cycles_diffuse_lobe_gets(count):
    """A shading normal leaning from its face: the world light of the directions above the face
    only, pi (1 + cos theta) / 2 (what Cycles bakes on a smooth low-poly face), exact for any
    N; its ambient occlusion in the open (1 + cos theta) / 2, as Cycles' AO rays below the face
    count as occluded. The old normalisation gave pi and 1."""
    geometric = np.array([[0.0, 0.0, 1.0]] * 3)
    lean = np.radians([0.0, 15.0, 40.0])
    shading = np.stack([np.sin(lean), np.zeros(3), np.cos(lean)], axis=1)
    d = spherical_fibonacci(count)
    hit = np.where((geometric @ d.T).T > 0, MISS, BELOW_HORIZON).astype(np.int16)
    table = _table(d, geometric, hit, np.zeros((count, 3, 2), np.float32))
    scale = gather_normalisation(table, shading, open_hemisphere_weight(shading, geometric))
    layout = AtlasLayout.from_sizes([(1, 1)])
    irradiance = gather(GatherGeometry(table, shading, scale, layout),
                        GatherSource(np.zeros((layout.size, 3), np.float32), np.ones(3)))
    expected = np.pi * (1.0 + np.cos(lean)) / 2.0
    np.testing.assert_allclose(irradiance, np.repeat(expected[:, None], 3, axis=1), rtol=1e-6)
    np.testing.assert_allclose(ambient_occlusion(table, shading, scale), (1.0 + np.cos(lean)) / 2.0, rtol=1e-6)


def test_gather_of_uniform_atlas_equals_pi_times_radiance():
    normals = np.array([[0.0, 0.0, 1.0]] * 4)
    d = spherical_fibonacci(64)
    hit = np.where((normals @ d.T).T > 0, 0, BELOW_HORIZON).astype(np.int16)
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 1, size=(64, 4, 2)).astype(np.float32)
    table = _table(d, normals, hit, uv)
    layout = AtlasLayout.from_sizes([(8, 4)])
    flat = layout.pack([np.full((4, 8, 3), 0.25, np.float32)])
    irradiance = gather(GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi), layout),
                        GatherSource(flat, np.zeros(3)))
    np.testing.assert_allclose(irradiance, np.pi * 0.25, rtol=1e-6)


@given(st.floats(0, 1), st.floats(0, 1), st.integers(1, 9), st.integers(1, 9))
@settings(max_examples=100, deadline=None)
def test_bilinear_reproduces_a_linear_ramp(u, v, width, height):
    # A ramp in x is reproduced exactly between texel centres and clamped outside.
    layout = AtlasLayout.from_sizes([(3, 2), (width, height)])
    x = (np.arange(width) + 0.5) / width
    ramp = np.repeat(np.repeat(x[None, :, None], height, 0), 3, 2).astype(np.float32)
    flat = layout.pack([np.zeros((2, 3, 3), np.float32), ramp])
    value = layout.bilinear(flat, np.array([1]), np.array([[u, v]], np.float32))[0, 0]
    expected = np.clip(u, x[0], x[-1])
    assert value == pytest.approx(expected, abs=1e-5)


def test_shadow_fractions_count_only_traced_directions():
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d = spherical_fibonacci(256)
    above = (normals @ d.T).T > 0
    hit = np.where(above, MISS, BELOW_HORIZON).astype(np.int16)
    # Sample 1 is covered by a roof: every direction steeper than 45 degrees hits.
    roof = above[:, 1] & (d[:, 2] > np.cos(np.radians(45)))
    hit[roof, 1] = 0
    table = _table(d, normals, hit, np.zeros((256, 2, 2), np.float32))
    fractions = shadow_fractions(table, ShadowRegions(d, 32))
    overhead = np.array([[0.0, 0.0, 1.0]] * 2)
    grazing = np.array([[np.cos(np.radians(10)), 0.0, np.sin(np.radians(10))]] * 2)
    v_overhead = fractions.visibility(overhead)
    v_grazing = fractions.visibility(grazing)
    assert v_overhead[0] == pytest.approx(1.0)
    assert v_grazing[0] == pytest.approx(1.0)  # below-horizon directions do not darken grazing light
    assert v_overhead[1] < 0.1
    assert v_grazing[1] > 0.9
    f = fractions.fractions()
    assert np.all((f >= 0) & (f <= 1))


def test_fractions_ignore_occluders_beyond_a_local_light():
    # A sample under a roof at distance 2: a light at distance 1 (below the roof)
    # is unshadowed, the same direction at distance 3 (above it) is shadowed.
    normals = np.array([[0.0, 0.0, 1.0]])
    d = spherical_fibonacci(256)
    hit = np.where((normals @ d.T).T > 0, 0, BELOW_HORIZON).astype(np.int16)
    distance = np.where(hit >= 0, 2.0, np.inf).astype(np.float32)
    table = _table(d, normals, hit, np.zeros((256, 1, 2), np.float32), distance)
    regions = ShadowRegions(d, 32)
    up = np.array([[0.0, 0.0, 1.0]])
    assert shadow_fractions(table, regions, np.array([1.0])).visibility(up)[0] == pytest.approx(1.0)
    assert shadow_fractions(table, regions, np.array([3.0])).visibility(up)[0] == 0.0
    assert shadow_fractions(table, regions).visibility(up)[0] == 0.0


@given(st.integers(1, 300), st.integers(0, 2**32 - 1), st.floats(0.0, 5.0))
@settings(max_examples=40, deadline=None)
def test_gather_of_uniform_radiance_is_pi_times_it_for_any_table(count, seed, level):
    """Whatever each ray hits (any object, any atlas coordinate, a miss into a world of
    the same radiance), a uniform scene returns E = pi * L for every open texel."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(6, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = spherical_fibonacci(count)
    above = (normals @ d.T).T > 0
    hit = np.where(above, rng.integers(-1, 3, size=above.shape), BELOW_HORIZON).astype(np.int16)
    uv = rng.uniform(-0.2, 1.2, size=(count, 6, 2)).astype(np.float32)
    table = _table(d, normals, hit, uv)
    layout = AtlasLayout.from_sizes([(5, 3), (1, 1), (7, 9)])
    flat = layout.pack([np.full((h, w, 3), level, np.float32) for w, h in [(5, 3), (1, 1), (7, 9)]])
    scale = gather_normalisation(table, normals, np.pi)
    irradiance = gather(GatherGeometry(table, normals, scale, layout, threads=2), GatherSource(flat, np.full(3, level)))
    open_samples = scale > 0
    np.testing.assert_allclose(irradiance[open_samples], np.pi * level, rtol=2e-6, atol=1e-12)
    assert np.all(irradiance[~open_samples] == 0)


@pytest.mark.parametrize("parts", [1, 2, 3, 7])
def test_gathers_over_direction_subsets_add_up_to_the_whole(parts):
    """The scale-out contract: disjoint direction ranges covering the set sum to the full gather."""
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = spherical_fibonacci(61)
    above = (normals @ d.T).T > 0
    hit = np.where(above, rng.integers(-1, 2, size=above.shape), BELOW_HORIZON).astype(np.int16)
    table = _table(d, normals, hit, rng.uniform(0, 1, size=(61, 40, 2)).astype(np.float32))
    layout = AtlasLayout.from_sizes([(4, 4), (3, 5)])
    flat = layout.pack([rng.uniform(0, 2, (4, 4, 6)).astype(np.float32),
                        rng.uniform(0, 2, (5, 3, 6)).astype(np.float32)])
    geometry = GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi), layout, threads=1)
    source = GatherSource(flat, rng.uniform(0, 1, (61, 6)))
    whole = gather(geometry, source)
    chunks = direction_chunks(len(d), parts)
    assert [i for chunk in chunks for i in chunk] == list(range(len(d)))
    summed = sum(gather(geometry, source, directions=chunk) for chunk in chunks)
    np.testing.assert_allclose(summed, whole, rtol=1e-5, atol=1e-9)
    assert np.any(whole > 0)


def test_a_direction_range_outside_the_set_is_refused():
    normals = np.array([[0.0, 0.0, 1.0]])
    table = _open_table(8, normals)
    geometry = GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi),
                              AtlasLayout.from_sizes([(1, 1)]))
    with pytest.raises(ValueError, match="contiguous range"):
        gather(geometry, GatherSource(np.zeros((4, 3), np.float32), np.ones(3)), directions=range(4, 9))
