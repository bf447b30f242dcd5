import numpy as np
import pytest

from core.errors import BakeRefused
from core.pipeline.prepare import prepare
from core.pipeline.relight import bake, relight
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core_scenes import box_interior, quad_mesh


def _scene(lights):
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.7)), resolution=24)
    roof = quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, -0.4, 0.6)],
                     material=Material(base_color=np.full(3, 0.5)), resolution=12)
    return Scene([ground, roof], lights)


SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0))
LAMP = Light("Lamp", "POINT", np.array([1.0, 0.8, 0.6]), 150.0, position=np.array([0.5, 0.2, 1.2]))


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_relight_equals_a_fresh_bake_exactly(shadows):
    settings = BakeSettings(directions=48, bounces=2, shadows=shadows, passes=("lighting", "direct", "indirect"))
    prepared = prepare(_scene([]), settings, table_needed=True)
    table, traced = prepared.table, prepared.visibility_rays
    assert table is not None and traced > 0
    for lights in ([SUN], [LAMP], [SUN, LAMP]):
        fresh = bake(_scene(lights), settings)
        stages = []
        again = relight(prepared, lights, World(), progress=lambda stage, fraction: stages.append(stage))
        for a, b in zip(fresh.objects, again.objects):
            for name in settings.passes:
                np.testing.assert_array_equal(a.images[name], b.images[name])
        # Relighting never traces the table: no visibility stage ran, the prepared table
        # is the one it read, and the report carries the preparation's rays and time.
        assert "transport" in stages and "visibility" not in stages and "samples" not in stages
        assert prepared.table is table and prepared.visibility_rays == traced
        assert again.report["rays"]["visibility_cast"] == traced == fresh.report["rays"]["visibility_cast"]
        assert again.report["stage_seconds"]["visibility"] == round(prepared.stage_seconds["visibility"], 4)


def test_relight_without_a_table_says_what_to_do():
    settings = BakeSettings(directions=16, bounces=0)
    prepared = prepare(_scene([SUN]), settings)
    assert prepared.table is None
    # Exact shadows, no bounces: no table needed, and the result is a fresh bake's.
    lit = relight(prepared, [SUN], World())
    fresh = bake(_scene([SUN]), settings)
    for a, b in zip(fresh.objects, lit.objects):
        np.testing.assert_array_equal(a.images["lighting"], b.images["lighting"])
    assert lit.report["rays"]["visibility_cast"] == 0 and lit.report["table_bytes"] == 0
    assert lit.report["rays"]["shadow_rays"] > 0
    # The ground outside the roof's shadow: rho * S * cos(theta) / pi, theta the sun's angle.
    ground = lit.objects[0].images["lighting"]
    open_sky = 0.7 * 3.0 * (1.0 / np.hypot(0.3, 1.0)) / np.pi
    covered = ground[..., 3] > 0
    np.testing.assert_allclose(ground[..., :3][covered].max(axis=0), open_sky, rtol=1e-6)
    assert ground[..., 0][covered].min() < 0.5 * open_sky  # and the roof's shadow is on it
    with pytest.raises(BakeRefused, match="prepare it again"):
        relight(prepared, [SUN], World(np.full(3, 0.5)))


def test_uniform_world_in_a_closed_box_adds_nothing():
    # Every ray from inside a closed box hits a wall: the world never shows.
    box = box_interior(material=Material(base_color=np.full(3, 0.5)), resolution=16)
    lit = bake(Scene([box], [], World(np.full(3, 2.0))), BakeSettings(directions=32, bounces=1))
    np.testing.assert_array_equal(lit.objects[0].images["lighting"][..., :3], 0.0)


def test_skipped_work_changes_no_requested_output():
    settings = BakeSettings(directions=48, bounces=2, passes=("lighting", "direct", "indirect"))
    lights = [SUN, LAMP]
    world = World(np.full(3, 0.2))
    full = bake(Scene(_scene([]).meshes, lights, world), settings)
    # The roof only occludes and reflects: its last gather is skipped, the ground's
    # images are the same to the last bit.
    meshes = _scene([]).meshes
    meshes[1].output = False
    partial = bake(Scene(meshes, lights, world), settings)
    assert [o.name for o in partial.objects] == ["Ground"]
    for name in settings.passes:
        np.testing.assert_array_equal(partial.objects[0].images[name], full.objects[0].images[name])
    assert any("last gather of" in line for line in partial.report["skipped"])
    # Only the direct pass: no bounce is gathered, and it equals the full bake's.
    direct_only = bake(Scene(_scene([]).meshes, lights, world), BakeSettings(directions=48, bounces=2,
                                                                             passes=("direct",)))
    assert direct_only.report["gathers"] == 1  # the world's, which is direct light
    assert any("no requested pass contains indirect light" in line for line in direct_only.report["skipped"])
    for a, b in zip(direct_only.objects, full.objects):
        np.testing.assert_array_equal(a.images["direct"], b.images["direct"])


def test_the_objects_samples_and_footprints_are_views_of_the_bake_s_arrays():
    """prepare holds each object's samples once: its positions, normals and footprints are
    views into the bake's concatenated arrays (prepare.adopted), with the values it built,
    and an object without footprint normals (a flat one) reads its own normal at every point."""
    from core.pipeline.prepare import adopted
    from core.sampling.samples import build_samples
    floor = quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=16)
    wall = quad_mesh("Wall", [(-1, 0, 0), (1, 0, 0), (1, 0, 1), (-1, 0, 1)], resolution=8)
    p = prepare(Scene([floor, wall], [Light("Sun", "SUN", np.ones(3), 1.0, direction=np.array([0.0, 0.3, -1.0]))]),
                BakeSettings(directions=16, bounces=0, footprint_samples=4))
    points, corners, _ = p.footprint
    for index, (samples, start) in enumerate(zip(p.object_samples, p.sample_offset[:-1])):
        rows = slice(int(start), int(start) + len(samples))
        fresh = build_samples(p.meshes[index], 4)
        for own, whole, built in ((samples.position, p.position, fresh.position),
                                  (samples.normal, p.normal, fresh.normal),
                                  (samples.footprint, points, fresh.footprint),
                                  (samples.footprint_corners, corners, fresh.footprint_corners)):
            assert np.shares_memory(own, whole)
            np.testing.assert_array_equal(whole[rows], built)

    class Flat:
        def __init__(self, normal):
            self.normal, self.footprint_normals = normal, None

        def __len__(self):
            return len(self.normal)

    flat = [Flat(np.array([[0.0, 0.0, 1.0]] * 3)), Flat(np.array([[0.0, 1.0, 0.0]] * 2))]
    normals = adopted(flat, "footprint_normals", (4, 3), np.float32,
                      lambda s: np.broadcast_to(s.normal.astype(np.float32)[:, None], (len(s), 4, 3)))
    assert normals.shape == (5, 4, 3) and all(s.footprint_normals is None for s in flat)
    np.testing.assert_array_equal(normals[3:, 2], [[0.0, 1.0, 0.0]] * 2)
