"""The GPU direct-light pass against core.transport.direct.lamp_irradiance on the same prepared scenes.

Tolerance: both evaluate the same formulas per sample and virtual point; the GPU in
float32 (positions relative to the samples' centre, offsets, normalisation, pow() of
the region weights, sums over up to 81 points), numpy in float64. Float32 rounding
of these steps stays near 1e-6 relative; the spot's smoothstep divides a cosine
difference by a narrow band, which amplifies it tenfold or so. 1e-4 relative plus
1e-5 of the largest value bounds that with room, and still catches any wrong
formula, epsilon, region, bit or texel (errors of order one).
"""
import importlib
import importlib.util
from pathlib import Path

import numpy as np
import pytest

RTOL, ATOL_OF_MAX = 1e-4, 1e-5
CORE_SCENES = Path(__file__).resolve().parents[1] / "core" / "core_scenes.py"
KINDS = ("sun", "point", "spot", "area_square", "area_rectangle", "area_disk", "area_ellipse")


def _scene_builders(core):
    """tests/core/core_scenes.py building meshes of the installed extension's core."""
    spec = importlib.util.spec_from_file_location("direct_twin_core_scenes", CORE_SCENES)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.Mesh, module.Material = core.scene.Mesh, core.scene.Material
    return module


def _rotation(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                     [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                     [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]])


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _light(core, kind, height, area_scale=1.0, spot_aim=(-0.35, 0.25, 0.0)):
    """One lamp of ``kind`` at ``height`` over the origin, tilted so nothing is axis-aligned."""
    Light = core.scene.Light
    position = np.array([0.15, -0.1, height])
    if kind == "sun":
        return Light("Sun", "SUN", np.array([1.0, 0.9, 0.7]), 3.0, direction=_unit([0.3, 0.2, -1.0]))
    if kind == "point":
        return Light("Point", "POINT", np.array([1.0, 0.8, 0.6]), 150.0, position=position)
    if kind == "spot":
        # Aimed off-centre with a soft edge: the smoothstep band crosses the receivers.
        return Light("Spot", "SPOT", np.array([0.7, 0.9, 1.0]), 300.0, position=position,
                     direction=_unit(np.asarray(spot_aim) - position),
                     spot_size=1.0, spot_blend=0.3)
    shape = kind.split("_")[1].upper()
    sizes = area_scale * np.array({"SQUARE": (0.6, 0.6), "RECTANGLE": (0.8, 0.3), "DISK": (0.5, 0.5),
                                   "ELLIPSE": (0.9, 0.35)}[shape])
    rotation = _rotation([0.3, -0.5, 1.0], 0.7) @ _rotation([1.0, 0.2, 0.0], 0.35)
    return Light(f"Area {shape}", "AREA", np.array([0.9, 1.0, 0.8]), 80.0, position=position,
                 direction=-rotation[:, 2], area_shape=shape, size_x=sizes[0], size_y=sizes[1],
                 axis_x=rotation[:, 0], axis_y=rotation[:, 1])


SCENES = {
    # Ground under a roof that faces down: lamps above cast the roof's shadow, and
    # the default 8 x 8 area points and 32 regions.
    "open": dict(height=1.2, area_scale=1.0, spot_aim=(-0.35, 0.25, 0.0),
                 area_light_samples=8, shadow_regions=32),
    # Lamps inside a closed box above a floating tile: local fractions must ignore the
    # walls beyond the lamp; 9 x 9 area points (two bit layers) and a region count that
    # is not a multiple of 4.
    "box": dict(height=0.25, area_scale=0.5, spot_aim=(-0.1, 0.05, -0.5),
                area_light_samples=9, shadow_regions=13),
}


def prepare_scene(core, scene, shadows):
    """One of SCENES prepared with its table (benchmarks/gpu_direct_twin.py measures the same)."""
    builders = _scene_builders(core)
    spec = SCENES[scene]
    if scene == "open":
        Material = core.scene.Material
        meshes = [builders.quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                                     material=Material(base_color=np.full(3, 0.7)), resolution=40),
                  builders.quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6),
                                              (0.4, -0.4, 0.6)], resolution=12)]
    else:
        meshes = [builders.box_interior(size=1.0, resolution=36),
                  builders.quad_mesh("Tile", [(-0.15, -0.15, -0.2), (0.15, -0.15, -0.2), (0.15, 0.15, -0.2),
                                              (-0.15, 0.15, -0.2)], resolution=8)]
    # Texel centres: the GLSL pass evaluates them (over footprints it hands every lamp to numpy).
    settings = core.settings.BakeSettings(directions=64, bounces=0, shadows=shadows,
                                          shadow_regions=spec["shadow_regions"],
                                          area_light_samples=spec["area_light_samples"], footprint_samples=1)
    return core.pipeline.prepare.prepare(core.scene.Scene(meshes, []), settings, table_needed=True)


@pytest.fixture(scope="module")
def prepared(visibake):
    made = {}

    def get(scene, shadows):
        if (scene, shadows) not in made:
            made[scene, shadows] = prepare_scene(visibake.core, scene, shadows)
        return made[scene, shadows]

    return get


@pytest.fixture(scope="module")
def direct(gpu_shaders, visibake):
    return importlib.import_module(f"{visibake.__name__}.gpu_shaders.direct")


def evaluate(visibake, direct, p, lights, **keywords):
    """(GPU irradiance, its shadow rays, numpy irradiance, its shadow rays) of ``lights`` over ``p``."""
    ours, our_rays = direct.lamp_irradiance(p.sample_set(), p.shadowing(), lights, lambda f: None, **keywords)
    twin, twin_rays = visibake.core.transport.direct.lamp_irradiance(p.sample_set(), p.shadowing(), lights,
                                                                     lambda f: None)
    return ours, our_rays, twin, twin_rays


def _compare(visibake, direct, p, lights, label, **keywords):
    ours, our_rays, twin, twin_rays = evaluate(visibake, direct, p, lights, **keywords)
    assert ours.shape == twin.shape == (len(p.position), 3)
    assert ours.dtype == np.float64
    assert our_rays == twin_rays
    peak = np.abs(twin).max()
    assert peak > 1e-3  # the case is not trivially zero
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL_OF_MAX * peak, err_msg=label)
    return ours, twin


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
@pytest.mark.parametrize("kind,scene", [(kind, scene) for scene in SCENES for kind in KINDS
                                        if (kind, scene) != ("sun", "box")])  # no sunlight in a closed box
def test_each_lamp_kind_matches_numpy(visibake, direct, prepared, kind, scene, shadows):
    p = prepared(scene, shadows)
    spec = SCENES[scene]
    light = _light(visibake.core, kind, spec["height"], spec["area_scale"], spec["spot_aim"])
    ours, twin = _compare(visibake, direct, p, [light], f"{kind} {scene} {shadows}")
    # Shadowing took part: some samples facing the lamp are dark or dimmed.
    unshadowed = sum(part.irradiance for part in visibake.core.lights.lamps.light_contributions(
        light, p.position, p.normal, p.settings.area_light_samples))
    assert np.any(twin.sum(axis=1) < 0.99 * unshadowed.sum(axis=1))


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_many_lamps_in_chunks_match_numpy_and_report_each_lamp(visibake, direct, prepared, shadows):
    p = prepared("open", shadows)
    lights = [_light(visibake.core, kind, 1.2) for kind in KINDS]
    lights.append(_light(visibake.core, "sun", 1.2))
    lights[-1].direction = _unit([-0.4, 0.1, -1.0])  # a second sun shares the distant fractions
    reported = []
    whole, rays = direct.lamp_irradiance(p.sample_set(), p.shadowing(), lights, reported.append)
    # One report per lamp, weighted by its expected shadow rays: the sampled (soft or area)
    # lamps run first on numpy, then the hard ones on the GPU.
    cost = visibake.core.transport.direct.shadow_rays_per_sample
    shadowing = p.shadowing()
    points = visibake.core.lights.lamps.lamp_points
    sampled = [light.kind == "AREA" or points(light, shadowing.area_light_samples) > 1 for light in lights]
    weights = ([cost(light, shadowing) for light, s in zip(lights, sampled) if s]
               + [cost(light, shadowing) for light, s in zip(lights, sampled) if not s])
    assert reported == pytest.approx(np.cumsum(weights) / np.sum(weights))
    # A budget holding about 700 samples: three chunks, nothing resident between lamps.
    per_sample = 16 * (4 + (4 * 8 if shadows == "fractions" else 1))
    budget = 16 * (4 * 64 + 32) + 700 * per_sample
    assert direct.chunk_samples(len(p.position), per_sample, 16 * (4 * 64 + 32), budget) * 2 < len(p.position)
    chunked, _ = _compare(visibake, direct, p, lights, f"all lamps {shadows}, chunked", budget_bytes=budget)
    np.testing.assert_allclose(chunked, whole, rtol=1e-6, atol=1e-9 * np.abs(whole).max())


def test_a_budget_too_small_for_one_sample_is_refused(visibake, direct, prepared):
    p = prepared("open", "fractions")
    with pytest.raises(MemoryError, match="GPU budget"):
        direct.lamp_irradiance(p.sample_set(), p.shadowing(), [_light(visibake.core, "point", 1.2)], budget_bytes=600)


def test_no_lamps_and_bad_lamps_behave_as_numpy(visibake, direct, prepared):
    p = prepared("open", "exact")
    irradiance, rays = direct.lamp_irradiance(p.sample_set(), p.shadowing(), [])
    assert irradiance.shape == (len(p.position), 3) and not np.any(irradiance) and rays == 0
    bad = _light(visibake.core, "point", 1.2)
    bad.strength = float("inf")
    with pytest.raises(ValueError, match="non-finite"):
        direct.lamp_irradiance(p.sample_set(), p.shadowing(), [bad])


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_linked_and_unshadowed_hard_lamps_match_numpy(visibake, direct, prepared, shadows):
    p = prepared("open", shadows)
    point = _light(visibake.core, "point", 1.2)
    sun = _light(visibake.core, "sun", 1.2)
    only_ground = _light(visibake.core, "spot", 1.2)
    only_ground.receivers = ("Ground",)
    no_shadow = _light(visibake.core, "point", 1.2)
    no_shadow.casts_shadows = False
    lights = [point, sun, only_ground, no_shadow]
    if shadows == "exact":
        unblocked = _light(visibake.core, "point", 1.2)
        unblocked.blockers = ("Ground",)  # the roof casts none of its shadows
        lights.append(unblocked)
    ours, twin = _compare(visibake, direct, p, lights, f"linked lamps {shadows}")
    roof = slice(p.sample_offset[1], p.sample_offset[2])
    alone, _ = visibake.core.transport.direct.lamp_irradiance(p.sample_set(), p.shadowing(), [only_ground])
    assert np.all(alone[roof] == 0.0) and np.any(alone[: p.sample_offset[1]] > 0)
    open_sky, _ = visibake.core.transport.direct.lamp_irradiance(p.sample_set(), p.shadowing(), [no_shadow])
    unshadowed = sum(part.irradiance for part in visibake.core.lights.lamps.light_contributions(
        no_shadow, p.position, p.normal, p.settings.area_light_samples))
    above = np.einsum("kd,kd->k", p.geometric, np.asarray(no_shadow.position) - p.position) > 0
    np.testing.assert_allclose(open_sky[above], unshadowed[above])
