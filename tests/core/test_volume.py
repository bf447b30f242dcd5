"""Light in media (core.volume) against closed forms and an independent ray march.

The reference march (benchmarks/volume_reference.py) is plain numpy with its own trilinear
lookup of the same medium, in steps ten times finer than the tables'. Nothing in it comes
from core.volume or core.kernels.
"""
from __future__ import annotations

import numpy as np
import pytest

from benchmarks.volume_reference import segment_transmittance
from core import kernels
from core.errors import VolumeRefused
from core.scene import Light, World
from core.visibility.directions import direction_set, spherical_fibonacci
from core.volume import direct, tables, transport
from core.volume.medium import MAX_SIDE, check_grid_shape, make_medium

pytestmark = pytest.mark.skipif(kernels.compiled() is None,
                                reason=f"numba kernels unavailable here: {kernels.status().reason}")


def reference_transmittance(medium, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(K,) transmittance along index-space segments ``starts`` -> ``ends`` (K, 3), marched
    finely by the independent reference."""
    return segment_transmittance(medium.density, medium.linear, medium.extinction, starts, ends)


def exit_points(medium, starts: np.ndarray, direction_index: np.ndarray) -> np.ndarray:
    """Where index-space rays from ``starts`` along ``direction_index`` (3,) leave the padded
    box [-1, n] (beyond it the density is zero)."""
    upper = np.array(medium.shape, np.float64)
    with np.errstate(divide="ignore"):
        far = np.where(direction_index > 0, (upper - starts) / direction_index,
                       np.where(direction_index < 0, (-1.0 - starts) / direction_index, np.inf))
    return starts + far.min(axis=1, keepdims=True) * direction_index


def smooth_density(n: int, seed: int = 3) -> np.ndarray:
    """A cloud of a few Gaussian blobs in an n^3 grid."""
    rng = np.random.default_rng(seed)
    grid = np.indices((n, n, n)).reshape(3, -1).T.astype(np.float64)
    density = np.zeros(len(grid))
    for _ in range(5):
        centre = rng.uniform(0.25 * n, 0.75 * n, 3)
        width = rng.uniform(0.1, 0.2) * n
        density += rng.uniform(0.5, 1.5) * np.exp(-np.sum((grid - centre) ** 2, axis=1) / (2 * width * width))
    density[density < 0.05] = 0.0
    return density.reshape(n, n, n).astype(np.float32)


def sun(direction) -> Light:
    direction = np.asarray(direction, np.float64)
    return Light("sun", "SUN", np.ones(3), 3.0, direction=direction / np.linalg.norm(direction))


def test_a_sun_through_a_homogeneous_slab_is_the_closed_form():
    # Anisotropic voxels and an oblique sun: where the ray to the sun leaves through the top
    # face (z = n - 1/2), the transmittance is exp(-sigma * depth / cos). Near the side faces
    # the sweep's bilinear steps blur the edge where rays start entering through a side
    # (about sqrt(slices) / 2 voxels): the closed form holds from 6 voxels in.
    medium = make_medium("slab", np.ones((30, 26, 24)), np.diag([0.1, 0.12, 0.05, 1.0]), extinction=3.0)
    light = sun([0.25, -0.15, -1.0])
    result = direct.transmittance(medium, light)
    voxels = np.argwhere(np.ones(medium.shape, bool))
    towards = -light.direction / np.array([0.1, 0.12, 0.05])  # index units per world unit
    steps = (medium.shape[2] - 0.5 - voxels[:, 2]) / towards[2]
    leave = voxels + steps[:, None] * towards
    margin = 6.0
    sides = np.array(medium.shape[:2]) - 0.5
    inside = np.all((np.minimum(voxels[:, :2], leave[:, :2]) > -0.5 + margin)
                    & (np.maximum(voxels[:, :2], leave[:, :2]) < sides - margin), axis=1)
    assert inside.sum() > 200
    depth = (medium.shape[2] - 0.5 - voxels[inside, 2]) * 0.05 / -light.direction[2]
    got = result[tuple(voxels[inside].T)]
    np.testing.assert_allclose(got, np.exp(-3.0 * depth), rtol=2e-4)


# Measured mean and worst absolute errors in transmittance (this dense cloud has optical
# depths up to 1.5 per voxel): sun 0.0060 and 0.076; lamp inside 5e-7 and 3e-4; lamp
# outside 0.0100 and 0.167. The worst are at the edges of the blobs' shadows, which the
# sweep's bilinear reads blur by about a voxel; the limits are those plus a third.
@pytest.mark.parametrize("kind, mean_limit, worst_limit", [
    ("sun", 0.008, 0.10), ("point inside", 1e-4, 0.002), ("point outside", 0.0135, 0.22)])
def test_the_sweep_follows_a_fine_march_of_the_same_medium(kind, mean_limit, worst_limit):
    n = 24
    medium = make_medium("cloud", smooth_density(n), np.diag([0.05, 0.05, 0.05, 1.0]), extinction=30.0)
    voxels = np.argwhere(medium.density > 0)
    starts = voxels.astype(np.float64)
    if kind == "sun":
        light = sun([0.4, 0.7, -0.6])
        towards = medium.to_index(-light.direction[None]) - medium.to_index(np.zeros((1, 3)))
        ends = exit_points(medium, starts, towards[0] / np.linalg.norm(towards))
    else:
        position = np.array([0.6, 0.5, 0.55]) if kind == "point inside" else np.array([1.9, -0.4, 0.7])
        light = Light("lamp", "POINT", np.ones(3), 100.0, position=position)
        ends = np.broadcast_to(medium.to_index(position[None]), starts.shape)
    expected = reference_transmittance(medium, starts, ends)
    got = direct.transmittance(medium, light)[tuple(voxels.T)].astype(np.float64)
    assert expected.min() < 0.2  # the test has shadows to get right
    error = np.abs(got - expected)
    assert error.mean() < mean_limit, error.mean()
    assert error.max() < worst_limit, error.max()


def test_a_point_lamp_in_a_homogeneous_cube_falls_off_as_the_closed_form():
    n = 32
    medium = make_medium("cube", np.ones((n, n, n)), np.diag([0.1, 0.1, 0.1, 1.0]), extinction=2.0)
    position = np.array([1.23, 1.61, 1.4])
    light = Light("lamp", "POINT", np.ones(3), 100.0, position=position)
    result = direct.transmittance(medium, light)
    voxels = np.argwhere(np.ones(medium.shape, bool))
    distance = np.linalg.norm(medium.world_positions(voxels) - position, axis=1)
    got = result[tuple(voxels.T)]
    # The sweep carries the mean extinction along each ray, which is constant here, so the
    # radial falloff comes out exact (a carried transmittance erred by up to 4% in depth).
    np.testing.assert_allclose(-np.log(got), 2.0 * distance, rtol=1e-5, atol=1e-6)
    assert np.all(got <= 1.0) and np.all(got > 0)


def test_a_midpoint_table_stores_the_median_scattering_point_and_the_escaping_fraction():
    n = 20
    medium = make_medium("cube", np.ones((n, n, n)), np.diag([0.2, 0.2, 0.2, 1.0]), extinction=0.4)
    along = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    table = tables.build_tables(medium, along, points=1, step=1.0, jitter_seed=None)
    voxels = table.voxels.astype(np.float64)
    # Rays leave the medium at the face n - 1/2 (+x) and -1/2 (-y), in world units * 0.2.
    depth = np.stack([(n - 0.5 - voxels[:, 0]) * 0.2, (voxels[:, 1] + 0.5) * 0.2])
    escape = np.exp(-0.4 * depth)
    np.testing.assert_allclose(table.escape(), escape, atol=1.5 / tables.CODE_MAX)
    median = -np.log(1.0 - 0.5 * (1.0 - escape)) / 0.4 / 0.2  # index units
    # Within the last voxel before the face the density fades to zero, which the closed
    # form's hard face does not: leave out rays whose median falls there.
    clear = median < np.stack([n - 1.0 - voxels[:, 0], voxels[:, 1]])
    assert clear.mean() > 0.9
    np.testing.assert_allclose(table.distances()[:, :, 0][clear], median[clear],
                               atol=2 * table.distance_per_code + 1e-3)
    # What the refusal of too large tables estimates is what the tables take.
    assert table.nbytes == tables.table_bytes(len(table.voxels), len(along), 1)


def test_world_light_at_the_centre_of_a_cube_is_the_mean_transmittance_to_its_faces():
    n = 21
    size = 0.1
    medium = make_medium("cube", np.ones((n, n, n)), np.diag([size, size, size, 1.0]), extinction=4.0)
    directions = direction_set(64, rotate=True, seed=5)
    table = tables.build_tables(medium, directions)
    light = transport.light_medium(medium, table, world=World(color=np.array([2.0, 1.0, 0.5])), bounces=0)
    centre = light.direct[n // 2, n // 2, n // 2]

    def face_distance(dirs):
        half = n * size / 2
        with np.errstate(divide="ignore"):  # a direction along an axis never meets the other faces
            return (half / np.abs(dirs)).min(axis=1)

    # The same directions, marched finely through the same medium: what the table's escape
    # fractions must give, within their half-voxel trapezoid steps (measured 0.007 in
    # optical depth here, from the kinks where the density fades at the faces).
    starts = np.full((len(directions), 3), float(n // 2))
    index_directions = directions / size
    marched = reference_transmittance(medium, starts, exit_points(medium, starts, index_directions)).mean()
    np.testing.assert_allclose(centre, marched * np.array([2.0, 1.0, 0.5]), rtol=0.01)
    # A hard-faced cube (the zero-padded density differs only along its edges).
    np.testing.assert_allclose(marched, np.exp(-4.0 * face_distance(directions)).mean(), rtol=0.02)
    # The whole sphere: what 64 directions estimate (a few percent, the direction count's error).
    fine = np.exp(-4.0 * face_distance(spherical_fibonacci(200_000))).mean()
    np.testing.assert_allclose(centre, fine * np.array([2.0, 1.0, 0.5]), rtol=0.05)


def test_single_scattering_of_a_sun_is_its_irradiance_over_4_pi_times_the_transmittance():
    medium = make_medium("slab", np.ones((10, 10, 10)), np.diag([0.1, 0.1, 0.1, 1.0]), extinction=2.0,
                         albedo=(0.8, 0.5, 0.2))
    light = sun([0.0, 0.0, -1.0])
    table = tables.build_tables(medium, direction_set(16))
    result = transport.light_medium(medium, table, [light], bounces=0)
    expected = 3.0 / (4 * np.pi) * np.exp(-2.0 * (9.5 - np.arange(10)) * 0.1)
    np.testing.assert_allclose(result.direct[5, 5, :, 0], expected, rtol=1e-5)
    assert not result.indirect.any()


def test_a_furnace_rises_with_every_bounce_towards_the_world_and_never_above_it():
    # Albedo 1 inside a uniform world: the exact answer is the world's radiance everywhere.
    n = 16
    medium = make_medium("furnace", np.ones((n, n, n)), np.diag([1 / n, 1 / n, 1 / n, 1.0]), extinction=2.5)
    table = tables.build_tables(medium, direction_set(32, rotate=True, seed=2))
    world = World(color=np.full(3, 1.5))
    previous = None
    for bounces in (0, 1, 2, 4, 8, 40):
        total = transport.light_medium(medium, table, world=world, bounces=bounces).total[..., 0]
        assert total.max() <= 1.5 * (1 + 1e-5)
        if previous is not None:
            assert np.all(total >= previous - 1e-6)
        previous = total
    assert previous.min() > 1.5 * 0.99, previous.min()


def test_light_never_exceeds_the_world_with_any_albedo_and_the_bounces_shrink():
    n = 20
    rng = np.random.default_rng(4)
    medium = make_medium("cloud", smooth_density(n, 7), np.diag([0.05, 0.05, 0.05, 1.0]), extinction=40.0,
                         albedo=rng.uniform(0, 1, (n, n, n, 3)))
    table = tables.build_tables(medium, direction_set(24, rotate=True, seed=9), points=2)
    result = transport.light_medium(medium, table, world=World(color=np.ones(3)), bounces=6)
    assert result.total.max() <= 1.0 + 1e-5
    means = [float(m.mean()) for m in result.bounce_means]
    assert all(later <= earlier for earlier, later in zip(means, means[1:]))
    assert np.all(np.isfinite(result.total)) and result.total.min() >= 0


def test_emission_reaches_the_centre_as_the_closed_form():
    # A pure absorber that emits e per world unit: the radiance arriving along a ray is
    # e / sigma (1 - exp(-sigma d)), averaged over the table's directions.
    n = 21
    size = 0.1
    emission = np.array([1.0, 2.0, 3.0])
    medium = make_medium("glow", np.ones((n, n, n)), np.diag([size, size, size, 1.0]), extinction=3.0,
                         albedo=(0.0, 0.0, 0.0), emission=emission)
    directions = direction_set(48, rotate=True, seed=1)
    table = tables.build_tables(medium, directions, points=1)
    result = transport.light_medium(medium, table, bounces=2)
    half = n * size / 2
    distance = (half / np.abs(directions)).min(axis=1)
    expected = (emission / 3.0) * (1 - np.exp(-3.0 * distance)).mean()
    np.testing.assert_allclose(result.direct[n // 2, n // 2, n // 2], expected, rtol=2e-3)
    assert not result.indirect.any()  # albedo 0 scatters nothing


def test_results_do_not_depend_on_the_thread_count():
    n = 18
    medium = make_medium("cloud", smooth_density(n, 11), np.diag([0.05, 0.05, 0.05, 1.0]), extinction=25.0,
                         albedo=(0.9, 0.8, 0.7))
    directions = direction_set(20, rotate=True, seed=3)
    lamp = Light("lamp", "POINT", np.ones(3), 50.0, position=np.array([0.3, 0.6, 0.4]))
    results = []
    for threads in (1, 2):
        table = tables.build_tables(medium, directions, points=2, threads=threads)
        light = transport.light_medium(medium, table, [lamp], World(color=np.full(3, 0.2)), bounces=2,
                                       threads=threads)
        results.append((table.distance_codes, table.escape_codes, light.direct, light.indirect))
    for one, two in zip(*results):
        assert np.array_equal(one, two)


def test_jittered_tables_are_the_papers_random_points_and_reproducible():
    n = 12
    medium = make_medium("cube", np.ones((n, n, n)), np.diag([0.1, 0.1, 0.1, 1.0]), extinction=2.0)
    directions = direction_set(8)
    midpoint = tables.build_tables(medium, directions, jitter_seed=None)
    first = tables.build_tables(medium, directions, jitter_seed=7)
    again = tables.build_tables(medium, directions, jitter_seed=7)
    other = tables.build_tables(medium, directions, jitter_seed=8)
    assert np.array_equal(first.distance_codes, again.distance_codes)
    assert not np.array_equal(first.distance_codes, other.distance_codes)
    assert not np.array_equal(first.distance_codes, midpoint.distance_codes)
    assert np.array_equal(first.escape_codes, midpoint.escape_codes)


def test_an_empty_grid_lights_nothing_and_costs_nothing():
    medium = make_medium("empty", np.zeros((8, 8, 8)), np.eye(4))
    table = tables.build_tables(medium, direction_set(16))
    assert len(table.voxels) == 0 and table.nbytes == 0
    result = transport.light_medium(medium, table, [sun([0, 0, -1])], World(color=np.ones(3)), bounces=2)
    assert not result.total.any()


@pytest.mark.parametrize("density, message", [
    (np.full((4, 4, 4), np.nan), "NaN or infinite"),
    (np.full((4, 4, 4), -1.0), "negative"),
    (np.ones((4, 4)), "dimensions"),
])
def test_unusable_densities_are_refused_with_the_reason(density, message):
    with pytest.raises(VolumeRefused, match=message):
        make_medium("bad", density, np.eye(4))


def test_a_huge_grid_is_refused_before_anything_of_its_size_is_allocated():
    with pytest.raises(VolumeRefused, match="more than VisiBake"):
        check_grid_shape("huge", (10 ** 6, 10 ** 6, 10 ** 6))
    assert check_grid_shape("fine", (MAX_SIDE, 8, 8)) == (MAX_SIDE, 8, 8)


def test_a_singular_transform_and_bad_settings_are_refused():
    with pytest.raises(VolumeRefused, match="singular"):
        make_medium("flat", np.ones((4, 4, 4)), np.diag([1.0, 1.0, 0.0, 1.0]))
    with pytest.raises(VolumeRefused, match="density"):
        make_medium("x", np.ones((4, 4, 4)), np.eye(4), extinction=float("nan"))
    clamped = make_medium("bright", np.ones((4, 4, 4)), np.eye(4), albedo=(1.5, 0.5, -0.1))
    assert clamped.albedo.max() == 1.0 and clamped.albedo.min() == 0.0 and clamped.warnings


def test_tables_too_large_are_refused_with_their_size(monkeypatch):
    monkeypatch.setattr(tables, "MAX_TABLE_BYTES", 1000)
    medium = make_medium("cube", np.ones((8, 8, 8)), np.eye(4))
    with pytest.raises(VolumeRefused, match="GiB"):
        tables.build_tables(medium, direction_set(16))
