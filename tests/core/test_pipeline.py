import numpy as np
import pytest

from core.errors import BakeRefused
from core.pipeline.relight import bake, relight
from core.pipeline.prepare import prepare
from core.settings import BakeSettings
from core.scene import Light, Material, Scene, World
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
    for lights in ([SUN], [LAMP], [SUN, LAMP]):
        fresh = bake(_scene(lights), settings)
        again = relight(prepared, lights, World())
        for a, b in zip(fresh.objects, again.objects):
            for name in settings.passes:
                np.testing.assert_array_equal(a.images[name], b.images[name])
        # Relighting traced no visibility ray of its own: it reports the prepared table.
        assert again.report["rays"]["visibility_cast"] == fresh.report["rays"]["visibility_cast"]
        assert "visibility" not in {k for k in again.report["stage_seconds"] if k not in prepared.stage_seconds}


def test_relight_without_a_table_says_what_to_do():
    settings = BakeSettings(directions=16, bounces=0)
    prepared = prepare(_scene([SUN]), settings)
    assert prepared.table is None
    relight(prepared, [SUN], World())  # exact shadows, no bounces: no table needed
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
