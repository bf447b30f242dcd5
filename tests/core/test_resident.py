"""The preparation kept in memory between bakes of a session (core.pipeline.resident)."""
import dataclasses

import numpy as np
import pytest

from core.pipeline import resident
from core.pipeline.relight import relight
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core.visibility.cache import VisibilityCache
from core_scenes import quad_mesh

SETTINGS = BakeSettings(directions=32, bounces=1, passes=("lighting",), footprint_samples=1, interleave=1)
SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0))
PLENTY = 1 << 30


def _scene(albedo=0.8, sun=SUN):
    floor = quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=12,
                      material=Material(base_color=np.full(3, albedo)))
    wall = quad_mesh("Wall", [(-1, 0.5, 0), (-1, 0.5, 1), (1, 0.5, 1), (1, 0.5, 0)], resolution=12)
    return Scene([floor, wall], [sun], World())


@pytest.fixture(autouse=True)
def _nothing_kept():
    resident.forget()
    yield
    resident.forget()


def test_the_key_ignores_lights_world_and_threads_but_not_materials_or_settings():
    key = resident.preparation_key(_scene(), SETTINGS, None, None)
    moved_sun = dataclasses.replace(SUN, direction=np.array([0.0, 0.0, -1.0]), strength=9.0)
    assert resident.preparation_key(_scene(sun=moved_sun), SETTINGS, None, None) == key
    assert resident.preparation_key(_scene(), dataclasses.replace(SETTINGS, threads=1), None, None) == key
    assert resident.preparation_key(_scene(albedo=0.5), SETTINGS, None, None) != key
    assert resident.preparation_key(_scene(), dataclasses.replace(SETTINGS, directions=64), None, None) != key
    assert resident.preparation_key(_scene(), SETTINGS, True, None) != key


def test_a_relight_reuses_the_kept_preparation_and_gives_the_same_light(tmp_path):
    cache = VisibilityCache(str(tmp_path), "scene")
    first = resident.prepare_or_reuse(_scene(), SETTINGS, cache=cache, keep_bytes=PLENTY, reuse=False)
    assert first.cache_status.state == "miss" and first.visibility_rays > 0
    dimmer = dataclasses.replace(SUN, strength=1.5)
    again = resident.prepare_or_reuse(_scene(sun=dimmer), SETTINGS, cache=cache, keep_bytes=PLENTY)
    assert again is first
    assert again.cache_status.state == "resident" and again.visibility_rays == 0 and again.stage_seconds == {}
    assert sum(s.startswith("samples and visibility:") for s in again.skipped) == 1
    reused = relight(again, [dimmer], World()).objects[0].images["lighting"]
    resident.forget()
    cold = resident.prepare_or_reuse(_scene(sun=dimmer), SETTINGS, cache=cache, keep_bytes=PLENTY)
    assert cold is not first and cold.cache_status.state == "hit"
    np.testing.assert_array_equal(reused, relight(cold, [dimmer], World()).objects[0].images["lighting"])


def test_a_bake_prepares_anew_and_a_changed_material_is_never_reused():
    first = resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY)
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY, reuse=False) is not first
    kept = resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY)
    assert resident.prepare_or_reuse(_scene(albedo=0.3), SETTINGS, keep_bytes=PLENTY) is not kept


def test_the_memory_bound_is_kept_and_zero_lets_go():
    first = resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=1000)
    size = resident.prepared_bytes(first)
    assert size > 1000
    assert any("more than Resident Memory allows" in s for s in first.skipped)
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY) is not first
    kept = resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=size)
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=0) is not kept
    # Zero let it go: the next bake with room prepares anew.
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY) is not kept
