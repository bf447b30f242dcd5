"""The direct-light sampler (core.lights.sampler) and the soft, linked and unshadowed lamps built on it."""
import numpy as np
import pytest

from core.lights.lamps import lamp_points, light_contributions
from core.lights.sampler import DirectSampler
from core.pipeline.prepare import prepare
from core.scene import Light, Material, Scene
from core.settings import BakeSettings
from core.transport import direct
from core.transport.direct import lamp_irradiance

from .core_scenes import quad_mesh

UP = np.array([0.0, 0.0, 1.0])


def _points(count, ids, seed=0, stream=0):
    sampler = DirectSampler(count, seed)
    return np.stack([sampler.uniforms(j, ids, stream) for j in range(count)], axis=1)  # (K, M, 4)


def test_points_are_jointly_stratified_for_every_sample():
    u = _points(16, np.arange(50), seed=3, stream=11)
    assert u.min() >= 0.0 and u.max() < 1.0
    for sample in u:
        for dimension in range(4):  # 16 1D strata per dimension
            assert sorted(np.floor(sample[:, dimension] * 16)) == list(range(16))
        for a, b in ((0, 1), (2, 3)):  # 4 x 4 over the lamp and over the footprint
            cells = np.floor(sample[:, a] * 4) * 4 + np.floor(sample[:, b] * 4)
            assert sorted(cells) == list(range(16))
        # and the 2^4 orthants of the whole 4D cube: lamp and footprint together
        cells = (np.floor(sample * 2) * np.array([8, 4, 2, 1])).sum(axis=1)
        assert sorted(cells) == list(range(16))


def test_points_are_deterministic_and_decorrelated():
    ids = np.arange(200)
    first = _points(8, ids, seed=5, stream=7)
    np.testing.assert_array_equal(first, _points(8, ids, seed=5, stream=7))
    assert not np.allclose(first, _points(8, ids, seed=6, stream=7))
    assert not np.allclose(first, _points(8, ids, seed=5, stream=8))
    # Different samples get different scrambles, and the scrambles are uniform.
    assert len({tuple(row) for row in first[:, 0, :2].round(6)}) == len(ids)
    assert abs(first[:, 0, 0].mean() - 0.5) < 0.05


def _estimate(light, position, normal, samples=8, **keywords):
    """(K, 3) sum of the sampler points' unshadowed irradiance."""
    return sum(part.irradiance for part in light_contributions(light, position, normal, samples, **keywords))


def _receivers(count, position=(0.0, 0.0, 0.0), normal=UP):
    return np.tile(position, (count, 1)).astype(np.float64), np.tile(normal, (count, 1)).astype(np.float64)


def test_sun_with_an_angle_is_unbiased_against_the_cone_average_of_the_cosine():
    angle = np.radians(10.0)
    tilt = np.radians(40.0)
    direction = -np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    sun = Light("Sun", "SUN", np.ones(3), 4.0, direction=direction, angle=angle)
    assert lamp_points(sun, 4) == 16
    position, normal = _receivers(400)
    estimate = _estimate(sun, position, normal, 4)[:, 0]
    # Uniform in the cone of half-angle a around the axis, cos to the normal averages
    # cos(tilt) (1 + cos a) / 2 while the cone stays above the horizon.
    exact = 4.0 * np.cos(tilt) * (1.0 + np.cos(angle / 2.0)) / 2.0
    assert estimate.mean() == pytest.approx(exact, rel=1e-4)
    assert np.abs(estimate / exact - 1.0).max() < 5e-3  # 16 stratified points per sample: within 0.5%
    hard = Light("Hard", "SUN", np.ones(3), 4.0, direction=direction)
    assert lamp_points(hard, 4) == 1
    np.testing.assert_allclose(_estimate(hard, position[:1], normal[:1])[0, 0], 4.0 * np.cos(tilt))


@pytest.mark.parametrize("kind", ["POINT", "SPOT"])
@pytest.mark.parametrize("sphere", [True, False])
def test_point_with_a_radius_is_unbiased_against_the_closed_form(kind, sphere):
    r, d, power = 0.5, 2.0, 300.0
    lamp = Light("Lamp", kind, np.ones(3), power, position=np.array([0.0, 0.0, d]), radius=r, sphere=sphere,
                 spot_size=np.radians(170), spot_blend=0.0)
    position, normal = _receivers(3000)
    estimate = _estimate(lamp, position, normal, 6)[:, 0]
    # A sphere of radiance P / (4 pi^2 r^2) gives pi L sin^2 = P / (4 pi d^2) on axis; Cycles'
    # soft-falloff disk of that radiance facing the receiver gives pi L r^2 / (r^2 + d^2).
    exact = power / (4 * np.pi * d * d) if sphere else power / (4 * np.pi * (r * r + d * d))
    assert estimate.mean() == pytest.approx(exact, rel=2e-4)
    assert np.abs(estimate / exact - 1.0).max() < 1e-2


def test_area_disk_through_the_sampler_is_unbiased():
    r, d, power = 0.4, 1.0, 100.0
    area = Light("Area", "AREA", np.ones(3), power, position=np.array([0.0, 0.0, d]), area_shape="DISK",
                 size_x=2 * r, size_y=2 * r)
    position, normal = _receivers(300)
    estimate = _estimate(area, position, normal, 6)[:, 0]
    exact = power / (np.pi * np.pi * r * r) * np.pi * r * r / (r * r + d * d)  # L pi r^2 / (r^2 + d^2)
    assert estimate.mean() == pytest.approx(exact, rel=2e-4)


def _rectangle_irradiance(corners, position, normal, radiance):
    """Lambert's closed form for a polygon wholly above the receiver's horizon: L / 2 |sum of
    each edge's angle times n . its plane's unit normal|."""
    v = corners - position
    v = v / np.linalg.norm(v, axis=1)[:, None]
    total = 0.0
    for a, b in zip(v, np.roll(v, -1, axis=0)):
        cross = np.cross(a, b)
        total += np.arccos(np.clip(a @ b, -1, 1)) * (normal @ cross) / np.linalg.norm(cross)
    return radiance / 2.0 * abs(total)


@pytest.mark.parametrize("height", [0.01, 0.05, 0.3])
def test_a_rectangle_lamp_near_a_receiver_is_unbiased_and_quiet(height):
    # A 0.6 x 0.4 m lamp a centimetre to 30 cm above the receiver, seen off-centre by a tilted
    # receiver: its points uniform in solid angle (core.lights.sampler.spherical_rectangle) give
    # the closed form, and every sample's 16 points land within a few percent of it, where points
    # uniform on the area (cos / r^2 blowing up under the lamp) spread far wider.
    power, size_x, size_y = 50.0, 0.6, 0.4
    area = Light("Area", "AREA", np.ones(3), power, position=np.array([0.1, 0.05, height]),
                 direction=np.array([0.0, 0.0, -1.0]), area_shape="RECTANGLE", size_x=size_x, size_y=size_y)
    normal = np.array([0.03, 0.02, 1.0]) / np.linalg.norm([0.03, 0.02, 1.0])
    position, normals = _receivers(400, normal=normal)
    corners = np.array([[0.1 + sx * size_x / 2, 0.05 + sy * size_y / 2, height]
                        for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    # The part of the lamp below the tilted receiver's horizon would need clipping: the receiver
    # sees the whole lamp at these heights only if every corner is above it.
    assert np.all((corners - position[0]) @ normal > 0)
    exact = _rectangle_irradiance(corners, position[0], normal, power / (np.pi * size_x * size_y))
    estimate = _estimate(area, position, normals, 4)[:, 0]
    assert estimate.mean() == pytest.approx(exact, rel=5e-3)
    assert np.std(estimate) / exact < 0.05
    # Points uniform on its area, the estimator this replaced, at the same receivers.
    sampler = DirectSampler(16, 0)
    scrambles = sampler.scrambles(np.arange(400))
    uniform = np.zeros(400)
    for j in range(16):
        u = sampler.uniforms(j, scrambles=scrambles)[:, :2]
        points = corners[0] + u[:, :1] * (corners[1] - corners[0]) + u[:, 1:] * (corners[3] - corners[0])
        offset = points - position
        r = np.linalg.norm(offset, axis=1)
        cosines = np.clip(offset @ normal / r, 0, None) * (height / r)
        uniform += power / (np.pi * size_x * size_y) * cosines / r ** 2 * size_x * size_y / 16
    assert np.std(estimate) < 0.5 * np.std(uniform)


def test_a_rectangles_closed_form_is_what_its_points_average_to():
    # Receivers all around a panel, tilted every way: some see it whole, some clipped by their
    # horizon, some from behind (nothing). core.lights.lamps.rectangle_irradiance against the mean
    # of 4000 scrambled sets of its 64 points each.
    from core.lights.lamps import rectangle_irradiance

    panel = Light("Panel", "AREA", np.array([1.0, 0.8, 0.6]), 50.0, position=np.array([0.1, 0.05, 0.3]),
                  direction=np.array([0.0, 0.0, -1.0]), area_shape="RECTANGLE", size_x=0.6, size_y=0.4)
    rng = np.random.default_rng(0)
    position = rng.uniform(-1, 1, (12, 3))
    position[:, 2] = rng.uniform(-0.5, 0.6, 12)
    normal = rng.normal(size=(12, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    many = 4000
    points = _estimate(panel, np.repeat(position, many, axis=0), np.repeat(normal, many, axis=0), 8)
    mean = points.reshape(12, many, 3).mean(axis=1)
    exact = rectangle_irradiance(panel, position, normal)
    assert np.count_nonzero(exact[:, 0] > 0) >= 4 and np.count_nonzero(exact[:, 0] == 0) >= 4
    np.testing.assert_allclose(exact, mean, rtol=2e-3, atol=1e-9)


def test_a_rectangle_seen_from_its_plane_or_behind_it_gives_nothing():
    area = Light("Area", "AREA", np.ones(3), 50.0, position=np.array([0.0, 0.0, 1.0]),
                 direction=np.array([0.0, 0.0, -1.0]), area_shape="SQUARE", size_x=0.5, size_y=0.5)
    beside = _estimate(area, *_receivers(16, position=(1.0, 0.0, 1.0), normal=np.array([-1.0, 0.0, 0.0])), 4)
    behind = _estimate(area, *_receivers(16, position=(0.1, 0.0, 1.2), normal=np.array([0.0, 0.0, -1.0])), 4)
    assert np.all(np.isfinite(beside)) and np.all(beside == 0.0)
    assert np.all(behind == 0.0)


def test_footprint_offsets_move_the_receiving_points():
    point = Light("Point", "POINT", np.ones(3), 100.0, position=np.array([0.0, 0.0, 1.0]))
    position, normal = _receivers(5)
    grid = (np.stack(np.meshgrid(np.arange(4), np.arange(4)), axis=-1).reshape(16, 2) + 0.5) / 4 - 0.5
    offsets = np.tile(np.concatenate([0.2 * grid, np.zeros((16, 1))], axis=1), (5, 1, 1))  # (5, 16, 3)
    parts = list(light_contributions(point, position, normal, 4, footprint=offsets, points=16))
    assert len(parts) == 16
    moved = np.stack([p.position for p in parts], axis=1)  # (K, 16, 3)
    assert np.all(np.abs(moved[..., :2]) <= 0.1) and np.all(moved[..., 2] == 0.0)
    assert np.ptp(moved[..., 0], axis=1).min() > 0.15  # spread over the texel
    # The average over a small footprint is near the centre's value (the field is smooth there).
    mean = sum(p.irradiance for p in parts)[:, 0]
    np.testing.assert_allclose(mean, 100 / (4 * np.pi), rtol=0.03)


def _blocked_plane(**light_keywords):
    """A ground plane under a floating blocker, prepared for exact shadows."""
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=24)
    blocker = quad_mesh("Blocker", [(-0.3, -0.3, 0.5), (-0.3, 0.3, 0.5), (0.3, 0.3, 0.5), (0.3, -0.3, 0.5)],
                        resolution=8)
    return ground, blocker


def _ground_irradiance(meshes, light, shadows="exact", samples=4):
    """The ground's irradiance at its texel centres (footprints are tested on their own)."""
    settings = BakeSettings(directions=64, bounces=0, shadows=shadows, area_light_samples=samples,
                            footprint_samples=1)
    p = prepare(Scene(meshes, []), settings, table_needed=shadows == "fractions")
    irradiance, rays = lamp_irradiance(p.sample_set(), p.shadowing(), [light])
    ground = slice(p.sample_offset[0], p.sample_offset[1])
    return irradiance[ground, 0], p.position[ground], rays


def test_a_soft_sun_has_a_penumbra_and_a_hard_one_does_not():
    meshes = _blocked_plane()
    hard = Light("Sun", "SUN", np.ones(3), 1.0)
    soft = Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(30))
    for shadows in ("exact", "fractions"):
        e_hard, _, _ = _ground_irradiance(meshes, hard, shadows)
        e_soft, _, _ = _ground_irradiance(meshes, soft, shadows)
        between = lambda e: np.count_nonzero((e > 0.05) & (e < 0.95))  # noqa: E731
        assert between(e_soft) > between(e_hard) + 10, shadows
    e_hard, position, rays_hard = _ground_irradiance(meshes, hard)
    e_soft, _, rays_soft = _ground_irradiance(meshes, soft)
    # A 30 degree sun is wide (core.transport.direct.WIDE_LAMP_RADIUS) and has too few points
    # (16) for probes to save any: every point is traced.
    assert rays_soft == 16 * rays_hard
    # A 1 degree sun is not: nine probe rays everywhere, all sixteen points only where the
    # probes disagree (the penumbra).
    narrow = Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(1.0))
    _, _, rays_narrow = _ground_irradiance(meshes, narrow)
    assert 9 * rays_hard <= rays_narrow < 16 * rays_hard
    centre = np.linalg.norm(position[:, :2], axis=1) < 0.1  # umbra: dark either way
    assert np.all(e_soft[centre] < 0.05) and np.all(e_hard[centre] == 0.0)


def test_linking_use_shadow_and_shadow_visibility():
    ground, blocker = _blocked_plane()
    sun = Light("Sun", "SUN", np.ones(3), 1.0)
    shaded, position, _ = _ground_irradiance([ground, blocker], sun)
    under = np.all(np.abs(position[:, :2]) < 0.25, axis=1)
    assert np.all(shaded[under] == 0.0) and np.all(shaded[~under & (np.abs(position[:, 0]) > 0.35)] == 1.0)

    no_shadow = Light("Sun", "SUN", np.ones(3), 1.0, casts_shadows=False)
    e, _, rays = _ground_irradiance([ground, blocker], no_shadow)
    assert rays == 0 and np.all(e == 1.0)
    e, _, _ = _ground_irradiance([ground, blocker], no_shadow, "fractions")
    assert np.all(e == 1.0)

    blocker.casts_shadow = False
    e, _, _ = _ground_irradiance([ground, blocker], sun)
    assert np.all(e == 1.0)
    blocker.casts_shadow = True

    other_blockers = Light("Sun", "SUN", np.ones(3), 1.0, blockers=("Ground",))
    e, _, _ = _ground_irradiance([ground, blocker], other_blockers)
    assert np.all(e == 1.0)
    own_blocker = Light("Sun", "SUN", np.ones(3), 1.0, blockers=("Blocker",))
    np.testing.assert_array_equal(_ground_irradiance([ground, blocker], own_blocker)[0], shaded)

    elsewhere = Light("Sun", "SUN", np.ones(3), 1.0, receivers=("Blocker",))
    e, _, rays = _ground_irradiance([ground, blocker], elsewhere)
    assert rays == 0 and np.all(e == 0.0)
    here = Light("Sun", "SUN", np.ones(3), 1.0, receivers=("Ground",))
    np.testing.assert_array_equal(_ground_irradiance([ground, blocker], here)[0], shaded)


@pytest.mark.parametrize("box_width", [0.5, 1.0])
def test_direct_light_over_a_footprint_traces_its_points_from_each_position(box_width):
    meshes = _blocked_plane()
    sun = Light("Sun", "SUN", np.ones(3), 1.0)
    centres = prepare(Scene(list(meshes), []), BakeSettings(directions=16, bounces=0, shadows="exact",
                                                            footprint_samples=1), table_needed=False)
    point_sampled, rays = lamp_irradiance(centres.sample_set(), centres.shadowing(), [sun])
    p = prepare(Scene(list(meshes), []), BakeSettings(directions=16, bounces=0, shadows="exact",
                                                      footprint_samples=16, footprint_width=box_width),
                table_needed=False)
    averaged, footprint_rays = lamp_irradiance(p.sample_set(), p.shadowing(), [sun])
    ground = slice(p.sample_offset[0], p.sample_offset[1])
    # Lit and shadowed texels stay so; texels the shadow edge crosses get fractions.
    partial = (averaged[ground, 0] > 0.02) & (averaged[ground, 0] < 0.98)
    # Four probes a texel, and the dense footprint's points only where they disagree (the
    # edge: the partial texels, and a few whose box the edge only grazes).
    from core.transport.direct import EDGE_FOOTPRINT_POINTS
    assert 4 * rays + EDGE_FOOTPRINT_POINTS * np.count_nonzero(partial) <= footprint_rays
    assert footprint_rays <= 4 * rays + EDGE_FOOTPRINT_POINTS * 1.5 * np.count_nonzero(partial)
    hard = point_sampled[ground, 0]
    assert np.count_nonzero(partial) >= 20 and not np.any((hard > 0) & (hard < 1))
    # Each texel is the lit share of its box (box_width x 2 m / 24 wide) as in Cycles' bake,
    # under the overhead sun's shadow of the 0.6 m square: texel centres alias it.
    half = box_width / 2 * 2.0 / 24
    centre = p.position[ground]
    covered = np.prod([np.clip(np.minimum(centre[:, a] + half, 0.3) - np.maximum(centre[:, a] - half, -0.3), 0, None)
                       for a in (0, 1)], axis=0) / (2 * half) ** 2
    exact = 1.0 - covered
    error, aliased = averaged[ground, 0] - exact, point_sampled[ground, 0] - exact
    assert np.abs(error).max() < 0.13 and np.sqrt(np.mean(error ** 2)) < 0.02
    assert np.sqrt(np.mean(error ** 2)) < 0.25 * np.sqrt(np.mean(aliased ** 2))


@pytest.mark.parametrize("light", [
    Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(2.0), direction=np.array([0.6, 0.0, -0.8])),
    Light("Sun", "SUN", np.ones(3), 1.0, angle=np.radians(30.0)),
    Light("Lamp", "POINT", np.ones(3), 40.0, position=np.array([0.3, 0.2, 1.5]), radius=0.2),
    Light("Panel", "AREA", np.ones(3), 40.0, position=np.array([0.0, 0.0, 1.2]), direction=np.array([0, 0, -1.0]),
          size_x=0.6, size_y=0.6),
])
def test_skipping_the_rays_that_agree_keeps_the_estimate(monkeypatch, light):
    """The probes decide lit and shadowed samples; the penumbra still gets every point."""
    meshes = _blocked_plane()
    adaptive, _, rays_adaptive = _ground_irradiance(meshes, light, samples=8)
    monkeypatch.setattr(direct, "ADAPTIVE_MIN_POINTS", 10**6)
    full, _, rays_full = _ground_irradiance(meshes, light, samples=8)
    # This small plane is mostly penumbra under the panel, and the panel is wide, so its samples
    # also probe along its first 16 points (a slat may pass between its corners).
    assert rays_adaptive < 0.85 * rays_full
    lit = full > 0.02 * full.max()
    assert np.mean(np.abs(adaptive[lit] / full[lit] - 1.0)) < 0.005
    assert np.max(np.abs(adaptive - full)) < 0.03 * full.max()


def test_a_rectangle_lamps_wholly_lit_texels_get_its_closed_form(monkeypatch):
    """A panel 15 cm over the ground: the texels the probes find wholly lit get the closed form
    (core.lights.lamps.rectangle_irradiance), without its points' noise; the penumbra keeps them."""
    from core.lights.lamps import rectangle_irradiance

    panel = Light("Panel", "AREA", np.ones(3), 40.0, position=np.array([0.2, 0.1, 0.15]),
                  direction=np.array([0, 0, -1.0]), size_x=0.8, size_y=0.5)
    meshes = _blocked_plane()
    closed, position, _ = _ground_irradiance(meshes, panel, samples=8)
    monkeypatch.setattr(direct, "ADAPTIVE_MIN_POINTS", 10**6)
    sampled, _, _ = _ground_irradiance(meshes, panel, samples=8)
    exact = rectangle_irradiance(panel, position, np.tile([0.0, 0.0, 1.0], (len(position), 1)))[:, 0]
    matches = np.isclose(closed, exact, rtol=1e-9, atol=0.0) & (exact > 0)
    assert matches.mean() > 0.5  # the blocker's shadow (under 0.6 x 0.6 m of 4 m^2) aside
    # The points scatter about the closed form there (8 x 8 of them near the lamp); in the mean they agree.
    noise = sampled[matches] / exact[matches] - 1.0
    assert abs(noise.mean()) < 0.01 and noise.std() > 1e-4


def test_slats_narrower_than_a_panel_are_not_missed_by_its_probes(monkeypatch):
    """Slats 3 cm wide under a 0.6 m panel can pass between its centre and corners, leaving every
    probe open over texels they shade in part: the panel's first points, probed too where it
    looks wide, find them, and the light matches tracing every point."""
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=24)
    slats = [quad_mesh(f"Slat{k}", [(-0.8, y - 0.015, 0.6), (-0.8, y + 0.015, 0.6), (0.8, y + 0.015, 0.6),
                                    (0.8, y - 0.015, 0.6)], resolution=2)
             for k, y in enumerate(np.arange(-0.75, 0.8, 0.25))]
    panel = Light("Panel", "AREA", np.ones(3), 80.0, position=np.array([0.05, 0.02, 1.6]),
                  direction=np.array([0, 0, -1.0]), size_x=0.6, size_y=0.6)
    meshes = [ground, *slats]
    probed, _, _ = _ground_irradiance(meshes, panel, samples=8)
    monkeypatch.setattr(direct, "WIDE_LAMP_RADIUS", np.inf)
    outline_only, _, _ = _ground_irradiance(meshes, panel, samples=8)
    monkeypatch.setattr(direct, "ADAPTIVE_MIN_POINTS", 10**6)
    full, _, _ = _ground_irradiance(meshes, panel, samples=8)
    lit = full > 0.05 * full.max()
    bias = lambda e: np.mean(e[lit]) / np.mean(full[lit]) - 1.0  # noqa: E731
    assert bias(outline_only) > 0.05  # the centre and corners alone miss the slats' shadows (+9.9%)
    assert abs(bias(probed)) < 0.003
    assert np.mean(np.abs(probed[lit] / full[lit] - 1.0)) < 0.01


def test_shadow_rays_traced_together_answer_as_one_query_each_and_keep_the_light_bitwise(monkeypatch):
    """Several sampler points' shadow rays in one embree query (the probes, a shadow edge's
    dense footprint): each ray's answer, and so the light, does not depend on the batching."""
    meshes = _blocked_plane()
    sun = Light("Sun", "SUN", np.ones(3), 1.0, direction=np.array([0.3, 0.1, -0.9]) / np.linalg.norm([0.3, 0.1, -0.9]))
    p = prepare(Scene(list(meshes), []), BakeSettings(directions=16, bounces=0, shadows="exact",
                                                      footprint_samples=16), table_needed=False)
    samples, shadowing = p.sample_set(), p.shadowing()
    blockers = shadowing.blocker_scene(sun)
    from core.lights.lamps import LampPoints
    lamp = LampPoints(sun, samples.position, samples.normal, footprint=samples.footprint, points=16)
    count = len(samples.position)
    requests = [(lamp.contribution(j), np.arange(j, count, 3), None) for j in range(12)]
    alone = [direct.trace_shadow_rays(blockers, samples, *request) for request in requests]
    assert 0 < np.mean(np.concatenate(alone)) < 1  # some rays blocked, some not
    for batch_rays in (1, 500, 10**9):  # every request alone, a few at a time, all at once
        monkeypatch.setattr(direct, "SHADOW_BATCH_RAYS", batch_rays)
        together = direct.trace_shadow_rays_together(blockers, samples, requests)
        assert len(together) == len(alone)
        for ours, theirs in zip(together, alone):
            np.testing.assert_array_equal(ours, theirs)
    monkeypatch.setattr(direct, "SHADOW_BATCH_RAYS", 10**9)
    batched, batched_rays = lamp_irradiance(samples, shadowing, [sun])
    # One point's rays per query, as before batching.
    monkeypatch.setattr(direct, "SHADOW_BATCH_RAYS", 1)
    monkeypatch.setattr(direct, "EDGE_BATCH_ROWS", 1)
    single, single_rays = lamp_irradiance(samples, shadowing, [sun])
    assert batched_rays == single_rays and np.count_nonzero((single[:, 0] > 0.02) & (single[:, 0] < 0.98)) >= 10
    np.testing.assert_array_equal(batched.view(np.uint64), single.view(np.uint64))


def test_a_hard_lamp_a_texel_away_averages_every_footprint_point(monkeypatch):
    """A point lamp 12 cm over a floor of 8 cm texels: its light changes by half and more
    across a texel, so the four footprint points that stand for sixteen where a lamp looks small
    (core.transport.direct.SMALL_LAMP_POINTS) are not enough there; a column's top beside such
    a lamp was 20% off Cycles (issue 52). Far from the lamp the four still stand for all."""
    ground = quad_mesh("Ground", [(-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0)], resolution=72)
    lamp = Light("Lamp", "POINT", np.ones(3), 40.0, position=np.array([0.05, -0.02, 0.12]))

    def floor_light():
        p = prepare(Scene([ground], []), BakeSettings(directions=16, bounces=0, shadows="exact",
                                                      footprint_samples=16), table_needed=False)
        light, _ = lamp_irradiance(p.sample_set(), p.shadowing(), [lamp])
        return light[:, 0], p.position

    adaptive, position = floor_light()
    monkeypatch.setattr(direct, "SMALL_LAMP_VARIATION", -1.0)  # every point everywhere
    every_point, _ = floor_light()
    near = np.linalg.norm(position[:, :2] - lamp.position[:2], axis=1) < 0.25
    np.testing.assert_array_equal(adaptive[near], every_point[near])
    # Beyond 4 half-diagonals / SMALL_FOOTPRINT_VARIATION (about 2.4 m) the first four points
    # stand for all sixteen: 0.7% apart in the mean, 3% at most (over some 3000 texels).
    half_diagonal = np.sqrt(2) * (6.0 / 72) / 2
    far = np.linalg.norm(position - lamp.position, axis=1) > 4.0 * half_diagonal / direct.SMALL_FOOTPRINT_VARIATION
    assert far.sum() > 50 and not np.array_equal(adaptive[far], every_point[far])
    apart = np.abs(adaptive[far] / every_point[far] - 1.0)
    assert apart.mean() < 0.005 and apart.max() < 0.03


def test_a_spot_s_cone_edge_across_texels_takes_a_dense_footprint(monkeypatch):
    """A hard 12 degree spot 0.9 m over a floor of 4 cm texels: the texels its cone's edge crosses
    are its brightest and their light a step across them. Against 4096 points each, the light of
    those texels was 25% of the floor's mean off with the footprint's 16 points; with
    SPOT_EDGE_POINTS it is a quarter of that, and the estimate says so."""
    from core_scenes import box_interior

    box = box_interior(size=2.0, material=Material(base_color=np.full(3, 0.6)), resolution=48)
    spot = Light("Spot", "SPOT", np.ones(3), 2000.0, position=np.array([0.0, 0.0, 0.9]),
                 direction=np.array([0.0, 0.0, -1.0]), spot_size=np.radians(12.0), spot_blend=0.0)
    p = prepare(Scene([box], [spot]), BakeSettings(directions=16, bounces=0), table_needed=False)

    def floor_light():
        spread = []
        light, rays = lamp_irradiance(p.sample_set(), p.shadowing(), [spot], None, spread)
        return light[:, 0], spread[0][:, 0], rays

    edges = direct.spot_edge_samples(spot, p.sample_set())
    assert 8 <= edges.sum() <= 40
    light, estimate, rays = floor_light()
    points = direct.SPOT_EDGE_POINTS
    monkeypatch.setattr(direct, "SPOT_EDGE_POINTS", 4096)
    truth, _, _ = floor_light()
    monkeypatch.setattr(direct, "spot_edge_samples", lambda light, samples: np.zeros(len(samples.position), bool))
    plain, _, plain_rays = floor_light()
    mean = truth.mean()

    def rms(values):
        return float(np.sqrt(np.mean(np.square(values)))) / mean

    assert rms(plain - truth) > 3.0 * rms(light - truth)
    assert np.all(light[~edges] == plain[~edges])
    assert rms(light - truth) / 1.5 < rms(estimate) < 1.5 * rms(light - truth)
    # Rays for the edge texels' points inside the cone alone (a spot's floor has nothing to shadow it
    # but the probes still ask).
    assert 0 < rays - plain_rays <= points * edges.sum()
