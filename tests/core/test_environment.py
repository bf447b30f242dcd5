"""Equirectangular world light: cell means, energy, Cycles' orientation, robustness.

Cycles' own agreement (orientation, Mapping rotations, bilinear wrap) is tested with
real bakes in tests/blender/test_environment.py; these tests need no Blender.
"""
import numpy as np
import pytest

from core.lights.environment import (
    _box_downsample,
    _row_z_edges,
    constant_lookup,
    direction_to_equirectangular,
    equirectangular_to_direction,
    euler_xyz_matrix,
    mirror_ball_mean,
    split_sun,
    world_radiance,
)
from core.outputs.images import bilinear_wrap as bilinear_lookup
from core.pipeline.relight import bake
from core.scene import Material, Scene, World
from core.settings import BakeSettings
from core.visibility.directions import direction_set, random_rotation, spherical_fibonacci
from core_scenes import quad_mesh

# Largest deviation of a spherical Fibonacci cell's area from 4*pi/N, measured on a
# 2048 x 1024 grid for N = 16..1024, plain and rotated: 0.939..1.054. An image whose
# light lies in one or a few cells has its energy scaled by those cells' area ratio.
MAX_CELL_AREA_DEVIATION = 0.065


def _integral(image):
    """Integral over the sphere of a piecewise-constant equirect image: (3,)."""
    height, width = image.shape[:2]
    solid_angle = (2 * np.pi / width) * np.diff(_row_z_edges(height))
    return (np.asarray(image, np.float64) * solid_angle[:, None, None]).sum(axis=(0, 1))


def _energy(radiance):
    return radiance.sum(axis=0) * 4 * np.pi / len(radiance)


def _sky(height=128, width=256, patch_column=40):
    """A smooth sky gradient plus a warm patch at one azimuth (not mirror-symmetric)."""
    v = (np.arange(height) + 0.5) / height
    image = np.zeros((height, width, 3), np.float32)
    image[...] = (0.2 + 0.8 * v)[:, None, None] * np.array([0.4, 0.6, 1.0], np.float32)
    rows = slice(int(0.65 * height), int(0.75 * height))
    image[rows, patch_column:patch_column + width // 32] = (30.0, 15.0, 4.0)
    return image


def test_cycles_convention_round_trip():
    # u = 0.5 looks along +X, u = 0.25 along +Y, v = 1 is the zenith, row 0 the nadir
    # (kernel/camera/projection.h; orientation confirmed against Cycles bakes).
    u, v = direction_to_equirectangular(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0], [-1.0, 0, 0]]))
    np.testing.assert_allclose(u[:2], [0.5, 0.25], atol=1e-15)
    np.testing.assert_allclose(v, [0.5, 0.5, 1.0, 0.0, 0.5], atol=1e-15)
    assert u[4] in (0.0, 1.0)
    d = spherical_fibonacci(200)
    np.testing.assert_allclose(equirectangular_to_direction(*direction_to_equirectangular(d)), d, atol=1e-12)
    # The zero vector maps to (0, 0), as in Cycles.
    assert [float(x[0]) for x in direction_to_equirectangular(np.zeros((1, 3)))] == [0.0, 0.0]


@pytest.mark.parametrize("shape", [(4, 8), (64, 128), (600, 1100)])
@pytest.mark.parametrize("count", [1, 16, 300, 2048])
def test_uniform_image_gives_its_colour_everywhere(shape, count):
    # Every cell mean of a constant is that constant, through upsampling (small
    # images), as is (medium) and area-weighted downsampling (beyond 1024 x 512).
    color = np.array([0.3, 1.5, 4.0], np.float32)
    image = np.broadcast_to(color, shape + (3,)).copy()
    radiance = world_radiance(World(image=image), direction_set(count, rotate=True, seed=count))
    assert radiance.shape == (count, 3) and radiance.dtype == np.float64
    np.testing.assert_allclose(radiance, np.broadcast_to(color, radiance.shape), rtol=1e-6)


@pytest.mark.parametrize("count", [64, 256, 1024])
def test_energy_is_the_image_integral(count):
    directions = direction_set(count, rotate=True, seed=7)
    sky = _sky()
    ratio = _energy(world_radiance(World(image=sky), directions)) / _integral(sky)
    print(f"\nN={count}: energy / integral, sky with patch: {np.round(ratio, 5)}")
    # Most of this image's light is the patch, spread over a few cells; their areas
    # differ from 4*pi/N by at most MAX_CELL_AREA_DEVIATION.
    np.testing.assert_allclose(ratio, 1.0, atol=MAX_CELL_AREA_DEVIATION)
    # A patch far smaller than a cell (2 x 2 pixels of 512 x 256, ~1/300 of a cell at
    # N = 64) is neither missed nor blown up, as point sampling would do.
    dot = np.zeros((256, 512, 3), np.float32)
    dot[180:182, 301:303] = 1000.0
    radiance = world_radiance(World(image=dot), directions)
    ratio = _energy(radiance) / _integral(dot)
    cells = np.count_nonzero(radiance[:, 0])
    print(f"N={count}: energy / integral, 2 x 2 pixel patch: {ratio[0]:.5f} in {cells} cell(s)")
    np.testing.assert_allclose(ratio, 1.0, atol=MAX_CELL_AREA_DEVIATION)
    # Light spread over every cell averages the deviations out (measured < 1e-4).
    noise = np.random.default_rng(count).random((300, 600, 3)).astype(np.float32)
    ratio = _energy(world_radiance(World(image=noise), directions)) / _integral(noise)
    np.testing.assert_allclose(ratio, 1.0, atol=1e-3)


def test_large_image_is_downsampled_keeping_its_integral():
    image = np.random.default_rng(3).random((1100, 2300, 3)).astype(np.float32) ** 4
    image[900:905, 100:104] = 5000.0
    small = _box_downsample(image, 1024, 512)
    assert small.shape == (512, 1024, 3)
    np.testing.assert_allclose(_integral(small), _integral(image), rtol=1e-9)


def test_half_bright_sky_lights_an_open_plane_with_pi_l():
    # Upper hemisphere radiance L, lower 0: an upward plane with nothing above it
    # receives E = pi * L, so the irradiance pass (E / pi) is L and lighting rho * L.
    radiance_l = np.array([2.0, 1.0, 0.5])
    image = np.zeros((64, 128, 3), np.float32)
    image[32:] = radiance_l
    rho = 0.6
    plane = quad_mesh("Plane", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                      material=Material(base_color=np.full(3, rho)), resolution=8)
    for count in (64, 256):
        settings = BakeSettings(directions=count, bounces=0, rotate=True, seed=2, passes=("lighting", "irradiance"))
        result = bake(Scene([plane], [], World(image=image)), settings).objects[0].images
        irradiance = result["irradiance"][..., :3].reshape(-1, 3)
        error = np.abs(irradiance / radiance_l - 1).max()
        print(f"\nN={count}: E / (pi L) - 1 = {error:.4f}")
        # The only error is the ring of cells straddling the horizon (mean L/2 each):
        # they sit within a cell radius ~ sqrt(4pi/N)/2 of cos = 0, so carry a share
        # ~ (4pi/N)/4 of the cosine weight: ~1.2% at N = 64, 0.3% at 256.
        assert error < 3.0 / count
        np.testing.assert_allclose(result["lighting"][..., :3], rho * result["irradiance"][..., :3], rtol=1e-5)


def test_rotated_world_equals_rotated_directions():
    sky = _sky()
    rotation = euler_xyz_matrix((0.3, -0.5, 1.1))
    directions = direction_set(300, rotate=True, seed=5)
    rotated = world_radiance(World(image=sky, rotation=rotation), directions)
    np.testing.assert_array_equal(rotated, world_radiance(World(image=sky), directions @ rotation.T))
    # The texture-space direction R d is what is looked up: the patch moves with R.
    rotation = random_rotation(11)
    bright = directions[np.argmax(world_radiance(World(image=sky, rotation=rotation), directions)[:, 0])]
    u, v = direction_to_equirectangular((rotation @ bright)[None])
    assert 40 / 256 - 0.05 < u[0] < 48 / 256 + 0.05 and 0.6 < v[0] < 0.8


def test_euler_matrix_is_rz_ry_rx():
    x, y, z = 0.3, -0.5, 1.1

    def axis(angle, i, j):
        m = np.eye(3)
        m[i, i] = m[j, j] = np.cos(angle)
        m[i, j], m[j, i] = -np.sin(angle), np.sin(angle)
        return m

    np.testing.assert_allclose(euler_xyz_matrix((x, y, z)), axis(z, 0, 1) @ axis(y, 2, 0) @ axis(x, 1, 2), atol=1e-15)


def test_nan_inf_and_negative_pixels_give_finite_non_negative_radiance():
    image = _sky()
    image[10:20, 10:20] = np.nan
    image[50, :] = np.inf
    image[60, 5] = -np.inf
    image[70:72, 100:110] = -3.0
    for count in (7, 128, 1500):
        radiance = world_radiance(World(image=image), direction_set(count, rotate=True, seed=1))
        assert np.isfinite(radiance).all() and (radiance >= 0).all()
    # Only the bad pixels are dropped: the rest of the light is still there.
    clean = np.where(np.isfinite(image) & (image > 0), image, 0.0)
    ratio = _energy(world_radiance(World(image=image), direction_set(256))) / _integral(clean)
    np.testing.assert_allclose(ratio, 1.0, atol=MAX_CELL_AREA_DEVIATION)


def test_tiny_image_with_many_directions():
    # 4 x 2 pixels, 1024 cells: Cycles shows such an image bilinearly interpolated
    # with wrapping in u and v (measured: a plane facing down under a top-row-only
    # image gets 0.27 of it), so every cell gets that interpolation's mean.
    image = np.zeros((2, 4, 3), np.float32)
    image[1] = 1.0
    image[1, 1] = (3.0, 0.5, 0.0)
    directions = direction_set(1024, rotate=True, seed=4)
    radiance = world_radiance(World(image=image), directions)
    assert radiance.shape == (1024, 3) and np.isfinite(radiance).all() and (radiance >= 0).all()
    # Matches a point lookup of the interpolated image up to its variation within a
    # cell (~0.11 rad across): small on average, largest at the zenith, where one cell
    # spans every u and so the whole top row (values 1 to 3).
    point = bilinear_lookup(image, *direction_to_equirectangular(directions))
    difference = np.abs(radiance - point)
    print(f"\n4 x 2 image, N=1024: |cell mean - point lookup| mean {difference.mean():.4f} max {difference.max():.4f}")
    assert difference.mean() < 0.01 and difference.max() < 0.3
    # The irradiance of a downward plane: what Cycles baked (0.2724, 0.1590, 0.1363).
    weights = np.clip(-directions[:, 2], 0, None)
    e_over_pi = (radiance * weights[:, None]).sum(0) / weights.sum()
    np.testing.assert_allclose(e_over_pi, [0.2724, 0.1590, 0.1363], atol=0.004)


def test_empty_or_degenerate_images():
    directions = direction_set(32)
    for image in (np.zeros((0, 4, 3), np.float32), np.zeros((4, 0, 3), np.float32)):
        np.testing.assert_array_equal(world_radiance(World(image=image), directions), 0.0)
    grey = np.full((8, 16), 0.5, np.float32)  # one channel
    np.testing.assert_allclose(world_radiance(World(image=grey), directions), 0.5)
    assert world_radiance(World(image=_sky()), np.zeros((0, 3))).shape == (0, 3)


def test_constant_lookup_and_mirror_ball_mean():
    image = _sky()
    # The zero vector reads (u, v) = (0, 0): the four corner pixels, wrapped.
    corners = image[[0, 0, -1, -1], [0, -1, 0, -1]].mean(axis=0)
    np.testing.assert_allclose(constant_lookup(image, (0.0, 0.0, 0.0)), corners, rtol=1e-6)
    # Any other vector is normalised and mapped like a direction: +Z is (u, v) = (0.5, 1).
    np.testing.assert_allclose(constant_lookup(image, (0.0, 0.0, 5.0)), bilinear_lookup(image, [0.5], [1.0])[0],
                               rtol=1e-6)
    ball = np.zeros((64, 64, 3), np.float32)
    ball[...] = 9.0  # outside the disc: ignored
    y, x = np.mgrid[0:64, 0:64]
    inside = ((x + 0.5) / 32 - 1) ** 2 + ((y + 0.5) / 32 - 1) ** 2 <= 1
    ball[inside] = (1.0, 2.0, 3.0)
    np.testing.assert_allclose(mirror_ball_mean(ball), [1.0, 2.0, 3.0])


def _sky_with_sun(height=256, width=512, sun=(0.3, -0.5, 0.6), radius_degrees=0.6, radiance=2.0e5):
    """A smooth sky and a disc of ``radiance`` around ``sun``: (image, disc direction, disc irradiance (3,))."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    uu, vv = np.meshgrid(u, v)
    directions = equirectangular_to_direction(uu.ravel(), vv.ravel()).reshape(height, width, 3)
    sky = (0.5 + 0.5 * directions[..., 2:3]) * np.array([0.3, 0.5, 1.0]) + 0.05
    axis = np.asarray(sun, np.float64) / np.linalg.norm(sun)
    inside = directions @ axis > np.cos(np.radians(radius_degrees))
    image = np.where(inside[..., None], radiance, sky).astype(np.float32)
    solid_angle = np.broadcast_to(((2 * np.pi / width) * np.diff(_row_z_edges(height)))[:, None], inside.shape)
    excess = ((radiance - sky[inside]) * solid_angle[inside][:, None]).sum(axis=0)
    return image, axis, excess


def test_split_sun_gives_a_small_bright_disc_to_a_lamp():
    image, axis, excess = _sky_with_sun()
    residual, sun = split_sun(image)
    assert sun is not None and sun.kind == "SUN" and sun.strength == 1.0
    # Direction within a fraction of a pixel (0.7 degrees), the disc's light within 2%.
    assert np.degrees(np.arccos(np.clip(-sun.direction @ axis, -1, 1))) < 0.3
    np.testing.assert_allclose(sun.color, excess, rtol=0.02)
    assert 0.5 * np.radians(1.2) < sun.angle < 2.0 * np.radians(1.2)
    # Nothing is lost or counted twice: the residual plus the lamp is the image's light.
    np.testing.assert_allclose(_integral(residual) + sun.color, _integral(image), rtol=1e-3)
    assert residual.max() < 2.0 and np.isfinite(residual).all()


def test_split_sun_leaves_skies_without_a_compact_disc_alone():
    image, _, _ = _sky_with_sun(radiance=1.0)  # a faint disc is part of the sky
    residual, sun = split_sun(image)
    assert sun is None and np.array_equal(residual, image)
    # Two suns far apart are no single disc: the image stands as it is.
    first, _, _ = _sky_with_sun(sun=(0.3, -0.5, 0.6))
    second, _, _ = _sky_with_sun(sun=(-0.6, 0.2, 0.4))
    both = np.maximum(first, second)
    residual, sun = split_sun(both)
    assert sun is None and np.array_equal(residual, both)
    assert split_sun(np.zeros((8, 16, 3), np.float32))[1] is None


def test_a_split_sun_lights_as_the_disc_does():
    # An upward plane under a sky with a sun: irradiance / pi against the image's own
    # integral of L cos. In a cell the disc's light is scaled by that cell's area ratio
    # (and lit from the cell's direction); as a lamp it is exact.
    image, axis, excess = _sky_with_sun(sun=(0.3, -0.5, 0.6))
    height, width = image.shape[:2]
    z_edges = _row_z_edges(height)
    z = 0.5 * (z_edges[1:] + z_edges[:-1])
    weight = (2 * np.pi / width) * np.diff(z_edges) * np.clip(z, 0, None)
    expected = (np.asarray(image, np.float64) * weight[:, None, None]).sum(axis=(0, 1)) / np.pi
    residual, sun = split_sun(image)
    plane = quad_mesh("Plane", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=4)
    settings = BakeSettings(directions=256, bounces=0, rotate=True, seed=3, passes=("irradiance",))
    errors = {}
    for label, world in (("cells", World(image=image)), ("lamp", World(image=residual, suns=[sun]))):
        irradiance = bake(Scene([plane], [], world), settings).objects[0].images["irradiance"][..., :3]
        errors[label] = float(np.abs(irradiance.reshape(-1, 3) / expected - 1).max())
    print(f"\nsun in a cell: {errors['cells']:.4f}, as a lamp: {errors['lamp']:.4f}")
    assert errors["lamp"] < 0.01
    assert errors["lamp"] < errors["cells"]
