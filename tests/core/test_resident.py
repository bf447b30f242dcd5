"""The preparation kept in memory between bakes of a session (core.pipeline.resident)."""
import dataclasses
import gc
import weakref

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


def test_a_bake_that_keeps_nothing_hashes_nothing(monkeypatch):
    """Without a bound (a command's one bake) the key, which hashes every mesh's arrays, is
    never computed; and what was kept is let go all the same."""
    kept = resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY)
    keys = []
    real_key = resident.preparation_key
    monkeypatch.setattr(resident, "preparation_key", lambda *args: keys.append(real_key(*args)) or keys[-1])
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=0) is not kept and keys == []
    assert resident.prepare_or_reuse(_scene(), SETTINGS, keep_bytes=PLENTY) is not kept and len(keys) == 1


@pytest.fixture
def _no_automatic_collection():
    """The cyclic garbage collector held off, as during a bake that makes few Python objects."""
    gc.disable()
    yield
    gc.enable()


def test_a_preparation_let_go_is_freed_before_the_next_is_prepared(monkeypatch, _no_automatic_collection):
    """A kept preparation refers to itself once its sample set is made (its bound dense_footprint),
    so dropping it frees nothing until a collection: a second Bake held both (speed part 21)."""
    settings = dataclasses.replace(SETTINGS, footprint_samples=4)
    first = resident.prepare_or_reuse(_scene(), settings, keep_bytes=PLENTY)
    first.sample_set()
    assert first in gc.get_referents(*gc.get_referents(first.sample_set()))  # the cycle this guards
    old = weakref.ref(first)
    del first
    alive_when_preparing = []
    real_prepare = resident.prepare
    monkeypatch.setattr(resident, "prepare", lambda *a, **k: alive_when_preparing.append(old() is not None)
                        or real_prepare(*a, **k))
    second = resident.prepare_or_reuse(_scene(albedo=0.3), settings, keep_bytes=PLENTY)
    assert alive_when_preparing == [False]
    second.sample_set()
    gone = weakref.ref(second)
    del second
    resident.forget()
    assert gone() is None


POINT = Light("Bulb", "POINT", np.array([1.0, 0.9, 0.8]), 40.0, position=np.array([0.2, -0.3, 0.8]), radius=0.1)
MEMO_SETTINGS = dataclasses.replace(SETTINGS, footprint_samples=4, area_light_samples=2)


def _lit(p, lights, world=None):
    outcome = relight(p, lights, World() if world is None else world)
    return outcome.objects[0].images["lighting"], outcome.report


def test_the_lamp_key_ignores_power_colour_and_group_only():
    from core.lights.lamps import lamp_shape_key
    key = lamp_shape_key(POINT)
    assert lamp_shape_key(dataclasses.replace(POINT, strength=3.0, color=np.zeros(3), group="g")) == key
    for change in ({"position": np.array([0.2, -0.3, 0.9])}, {"radius": 0.2}, {"casts_shadows": False},
                   {"receivers": ("Floor",)}, {"name": "Other"}):
        assert lamp_shape_key(dataclasses.replace(POINT, **change)) != key, change
    hash(key)


def test_a_kept_preparation_relit_with_new_powers_and_colours_traces_and_gathers_nothing():
    kept = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=PLENTY, reuse=False)
    first, report = _lit(kept, [POINT, SUN])
    assert report["rays"]["shadow_rays"] > 0 and report["gathers"] == 1
    changed = [dataclasses.replace(POINT, strength=80.0, color=np.array([0.2, 1.0, 0.5])),
               dataclasses.replace(SUN, strength=0.5)]
    again = resident.prepare_or_reuse(_scene(sun=changed[0]), MEMO_SETTINGS, keep_bytes=PLENTY)
    assert again is kept
    reused, report = _lit(again, changed)
    assert report["rays"]["shadow_rays"] == 0 and report["gathers"] == 0
    assert any(s.startswith("transport of Bulb, Sun: only power or colour changed") for s in report["skipped"])
    assert not np.array_equal(first, reused)
    # The same light as a kept preparation transporting these lamps afresh, bitwise ...
    resident.forget()
    fresh = resident.prepare_or_reuse(_scene(sun=changed[0]), MEMO_SETTINGS, keep_bytes=PLENTY)
    assert fresh is not kept
    np.testing.assert_array_equal(reused, _lit(fresh, changed)[0])
    # ... and as a bake that transports the lamps together, to float32 rounding (the atlases).
    whole = resident.prepare_or_reuse(_scene(sun=changed[0]), MEMO_SETTINGS, keep_bytes=0)
    assert not whole.resident
    expected, report = _lit(whole, changed)
    assert not any(s.startswith("transport of") for s in report["skipped"])
    np.testing.assert_allclose(reused, expected, rtol=1e-5, atol=1e-6 * float(expected.max()))


def test_a_moved_lamp_is_transported_again_and_the_others_are_kept():
    kept = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=PLENTY, reuse=False)
    _lit(kept, [POINT, SUN])
    moved = dataclasses.replace(POINT, position=np.array([0.4, -0.2, 0.7]))
    images, report = _lit(kept, [moved, SUN])
    assert report["rays"]["shadow_rays"] > 0 and report["gathers"] == 1
    assert any(s.startswith("transport of Sun: only power") for s in report["skipped"])
    resident.forget()
    fresh = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=PLENTY, reuse=False)
    np.testing.assert_array_equal(images, _lit(fresh, [moved, SUN])[0])


def test_many_lamps_are_transported_together_and_only_their_direct_light_is_kept():
    lamps = [dataclasses.replace(POINT, name=f"Bulb{i}", position=np.array([0.2 * i - 0.4, -0.3, 0.8]))
             for i in range(5)]
    kept = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=PLENTY, reuse=False)
    _lit(kept, lamps)
    dimmer = [dataclasses.replace(lamp, strength=10.0) for lamp in lamps]
    images, report = _lit(kept, dimmer)
    assert report["rays"]["shadow_rays"] == 0 and report["gathers"] == 1
    assert not any(s.startswith("transport of") for s in report["skipped"])
    assert any(s.startswith("direct light of Bulb0, Bulb1, Bulb2, Bulb3, Bulb4: only power") for s in report["skipped"])
    fresh = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=0)
    np.testing.assert_array_equal(images, _lit(fresh, dimmer)[0])


def test_the_memo_keeps_to_its_bound_dropping_the_least_recently_used():
    from core.pipeline.light_memo import LightMemo
    memo = LightMemo(limit_bytes=3 * 800)
    for name in "abc":
        memo.put(name, np.zeros(100))
    assert memo.get("a") is not None  # a is now the most recent
    memo.put("d", np.zeros(100))
    assert memo.get("b") is None and memo.get("a") is not None and memo.get("d") is not None
    assert memo.nbytes() <= 3 * 800
    memo.put("huge", np.zeros(1000))
    assert memo.get("huge") is None and len(memo) == 3


def test_emitters_and_the_emitted_gather_are_kept_until_the_world_changes():
    glow = quad_mesh("Glow", [(-0.1, -0.1, 0.6), (-0.1, 0.1, 0.6), (0.1, 0.1, 0.6), (0.1, -0.1, 0.6)], resolution=4,
                     material=Material(base_color=np.full(3, 0.5), emission=np.array([30.0, 20.0, 10.0])))
    base = _scene()
    scene = Scene(base.meshes + [glow], [SUN], World())
    sky = World(color=np.array([0.1, 0.2, 0.4]))
    kept = resident.prepare_or_reuse(scene, MEMO_SETTINGS, keep_bytes=0)  # lamps and emitters transported together
    _, report = _lit(kept, [SUN], sky)
    assert "Glow" in report["emitters_sampled"] and report["rays"]["emitter_rays"] > 0
    brighter = dataclasses.replace(SUN, strength=6.0)
    images, report = _lit(kept, [brighter], sky)
    assert report["rays"]["emitter_rays"] == 0 and report["gathers"] == 1
    assert any(s.startswith("gather of emitted and world light: emitters and world unchanged")
               for s in report["skipped"])
    assert any(s.startswith("direct light of Glow, Sun:") for s in report["skipped"])
    fresh = resident.prepare_or_reuse(scene, MEMO_SETTINGS, keep_bytes=0)
    np.testing.assert_array_equal(images, _lit(fresh, [brighter], sky)[0])
    _, report = _lit(kept, [brighter], World(color=np.array([0.3, 0.2, 0.1])))
    assert report["gathers"] == 2
    assert not any(s.startswith("gather of emitted and world light: emitters") for s in report["skipped"])


def test_what_relights_keep_stays_within_resident_memory():
    first = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=PLENTY)
    size = resident.prepared_bytes(first)
    resident.forget()
    tight = resident.prepare_or_reuse(_scene(sun=POINT), MEMO_SETTINGS, keep_bytes=size + 1000)
    assert tight.resident and tight.light_memo.limit_bytes == 1000
    _lit(tight, [POINT])
    assert tight.light_memo.nbytes() <= 1000
    # Nothing fits, so a relight that changes only the power transports again, with the same light.
    images, report = _lit(tight, [dataclasses.replace(POINT, strength=7.0)])
    assert report["gathers"] == 1 and report["rays"]["shadow_rays"] > 0
    np.testing.assert_array_equal(images, _lit(first, [dataclasses.replace(POINT, strength=7.0)])[0])
