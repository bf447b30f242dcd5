"""The visibility cache: hits, misses, invalidation, incremental updates, corruption."""
import dataclasses
import os

import numpy as np
import pytest

from core.errors import BakeRefused
from core.pipeline.prepare import prepare
from core.pipeline.relight import bake, relight
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core.visibility.cache import VisibilityCache
from core.visibility.table import DeferredTable
from core_scenes import quad_mesh

SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, 1.0]))
LAMP = Light("Lamp", "POINT", np.array([1.0, 0.8, 0.6]), 150.0, position=np.array([0.5, 0.2, 1.2]))
TABLE_FIELDS = ("hit_object", "hit_uv_code", "hit_distance_code", "traced_per_sample", "backface_per_sample")


def _meshes(roof_height=0.6, roof_shift=0.0):
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.7)), resolution=20)
    h = roof_height
    roof = quad_mesh("Roof", [(-0.4 + roof_shift, -0.4, h), (-0.4 + roof_shift, 0.4, h),
                              (0.4 + roof_shift, 0.4, h), (0.4 + roof_shift, -0.4, h)],
                     material=Material(base_color=np.full(3, 0.5)), resolution=10)
    wall = quad_mesh("Wall", [(0.9, -1, 0), (0.9, 1, 0), (0.9, 1, 1), (0.9, -1, 1)],
                     material=Material(base_color=np.array([0.6, 0.3, 0.2])), resolution=12)
    return [ground, roof, wall]


def _settings(**changes):
    return BakeSettings(**{**dict(directions=48, bounces=2, passes=("lighting", "direct", "indirect")), **changes})


def _images(result):
    return {(o.name, name): image for o in result.objects for name, image in o.images.items()}


def _assert_same_images(a, b):
    images_a, images_b = _images(a), _images(b)
    assert images_a.keys() == images_b.keys()
    for key in images_a:
        np.testing.assert_array_equal(images_a[key], images_b[key], err_msg=str(key))


def _assert_same_table(a, b):
    for name in TABLE_FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_miss_then_hit_gives_the_same_bake(tmp_path):
    cache = VisibilityCache(str(tmp_path), "scene")
    settings = _settings()
    first = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    assert first.cache_status.state == "miss"
    assert first.visibility_rays > 0 and os.path.exists(first.cache_status.path)
    second = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    assert second.cache_status.state == "hit"
    assert second.visibility_rays == 0
    _assert_same_table(first.table, second.table)
    result = relight(second, [SUN], World())
    assert result.report["cache"]["state"] == "hit"
    assert any("cached table is valid" in line for line in result.report["skipped"])
    _assert_same_images(bake(Scene(_meshes(), [SUN]), settings), result)


def test_relight_from_the_cache_equals_a_fresh_bake_exactly(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings(shadows="fractions")
    prepare(Scene(_meshes(), []), settings, table_needed=True, cache=cache)
    for lights, world in (([SUN], World()), ([LAMP], World(np.full(3, 0.3))), ([SUN, LAMP], World())):
        cached = prepare(Scene(_meshes(), lights, world), settings, cache=cache, require_cached_table=True)
        assert cached.cache_status.state == "hit"
        _assert_same_images(bake(Scene(_meshes(), lights, world), settings), relight(cached, lights, world))


@pytest.mark.parametrize("change", ["move", "reshape"])
def test_changing_one_object_updates_only_what_it_affects_and_equals_a_fresh_trace(tmp_path, change):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings()
    prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    # "move" keeps the roof's sample count (a transform); "reshape" changes its layout
    # (a modifier that adds geometry), so samples of later objects shift in the table.
    meshes = _meshes(roof_shift=0.25) if change == "move" else _meshes(roof_height=0.45)
    if change == "reshape":
        meshes[1].resolution = (14, 14)
    updated = prepare(Scene(meshes, [SUN]), settings, cache=cache)
    assert updated.cache_status.state == "updated"
    assert updated.cache_status.changed_objects == ["Roof"]
    fresh = prepare(Scene(meshes, [SUN]), settings)
    _assert_same_table(updated.table, fresh.table)
    assert updated.table.rays_cast == fresh.table.rays_cast
    _assert_same_images(relight(updated, [SUN], World()), relight(fresh, [SUN], World()))
    assert any("visibility of unchanged objects" in line for line in relight(updated, [SUN], World()).report["skipped"])
    # The updated table was saved: the next bake of the same scene is a hit.
    assert prepare(Scene(meshes, [SUN]), settings, cache=cache).cache_status.state == "hit"


def test_changing_the_direction_count_never_uses_the_old_table(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    prepare(Scene(_meshes(), [SUN]), _settings(directions=48), cache=cache)
    other = prepare(Scene(_meshes(), [SUN]), _settings(directions=64), cache=cache)
    assert other.cache_status.state == "miss"
    assert other.table.hit_object.shape[0] == 64
    # Lighting-only settings share the table.
    assert prepare(Scene(_meshes(), [SUN]), _settings(directions=48, bounces=5, shadows="fractions"),
                   cache=cache).cache_status.state == "hit"


def test_a_stale_cache_refuses_to_relight(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    prepare(Scene(_meshes(), [SUN]), _settings(), cache=cache)
    with pytest.raises(BakeRefused, match="Roof"):
        prepare(Scene(_meshes(roof_shift=0.1), [SUN]), _settings(), cache=cache, require_cached_table=True)
    with pytest.raises(BakeRefused, match="bake first"):
        prepare(Scene(_meshes(), [SUN]), _settings(directions=40), cache=cache, require_cached_table=True)


def _corrupt_truncate(path):
    size = os.path.getsize(path)
    with open(path, "r+b") as handle:
        handle.truncate(size // 2)


def _corrupt_flip_bit(path):
    # A bit in the middle of the payload (an array, not the zip directory).
    with open(path, "r+b") as handle:
        handle.seek(os.path.getsize(path) // 2)
        byte = handle.read(1)
        handle.seek(-1, os.SEEK_CUR)
        handle.write(bytes([byte[0] ^ 0x10]))


def _corrupt_empty(path):
    open(path, "wb").close()


@pytest.mark.parametrize("corrupt", [_corrupt_truncate, _corrupt_flip_bit, _corrupt_empty])
def test_a_corrupted_cache_is_detected_and_rebuilt(tmp_path, corrupt):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings()
    good = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    corrupt(good.cache_status.path)
    again = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    # A damaged header is found at once, a damaged array when a pass first reads it.
    again.table.hit_object
    assert again.cache_status.state == "corrupt"
    assert any("rebuilt" in w for w in again.warnings)
    _assert_same_table(good.table, again.table)
    assert prepare(Scene(_meshes(), [SUN]), settings, cache=cache).cache_status.state == "hit"


def test_light_groups_sum_to_the_combined_passes_and_unchanged_groups_are_reused(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings(light_groups=True)
    world = World(np.array([0.2, 0.3, 0.4]))
    lights = [SUN, LAMP]
    first = relight(prepare(Scene(_meshes(), lights, world), settings, cache=cache), lights, world)
    images = _images(first)
    assert set(first.report["light_groups"]) == {"Sun", "Lamp", "world"}
    for obj in ("Ground", "Roof", "Wall"):
        for name in ("lighting", "direct", "indirect"):
            total = sum(images[(obj, f"{name}_{g}")][..., :3] for g in ("Sun", "Lamp", "world"))
            np.testing.assert_allclose(total, images[(obj, name)][..., :3], rtol=1e-5, atol=1e-7)
    # Only the lamp changes: the sun's and the world's transport are read back.
    brighter = dataclasses.replace(LAMP, strength=300.0)
    prepared = prepare(Scene(_meshes(), [SUN, brighter], world), settings, cache=cache)
    second = relight(prepared, [SUN, brighter], world)
    assert sorted(second.report["cache"]["lighting_reused"]) == ["Sun", "world"]
    assert any("transport of 'Sun', 'world'" in line for line in second.report["skipped"])
    _assert_same_images(bake(Scene(_meshes(), [SUN, brighter], world), settings), second)


def test_unchanged_lighting_skips_the_transport(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings()
    relight(prepare(Scene(_meshes(), [SUN]), settings, cache=cache), [SUN], World())
    again = relight(prepare(Scene(_meshes(), [SUN]), settings, cache=cache), [SUN], World())
    assert again.report["cache"]["lighting_reused"] == ["all"]
    assert again.report["gathers"] == 0
    # A material change is not "unchanged lighting".
    meshes = _meshes()
    meshes[0].materials[0].base_color = np.full(3, 0.2)
    changed = relight(prepare(Scene(meshes, [SUN]), settings, cache=cache), [SUN], World())
    assert changed.report["cache"]["lighting_reused"] == []
    assert changed.report["gathers"] == 2


def test_an_unwritable_cache_folder_warns_and_the_bake_goes_on(tmp_path):
    blocker = tmp_path / "not a folder"
    blocker.write_text("a file where the cache folder should be")
    cache = VisibilityCache(str(blocker))
    prepared = prepare(Scene(_meshes(), [SUN]), _settings(), cache=cache)
    assert any("could not be written" in w for w in prepared.warnings)
    _assert_same_images(relight(prepared, [SUN], World()), bake(Scene(_meshes(), [SUN]), _settings()))


def test_a_bake_whose_lighting_is_cached_never_reads_the_table(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings()
    first = relight(prepare(Scene(_meshes(), [SUN]), settings, cache=cache), [SUN], World())
    again = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    assert isinstance(again.table, DeferredTable) and not again.table.loaded
    second = relight(again, [SUN], World())
    assert not again.table.loaded and second.report["cache"]["lighting_reused"] == ["all"]
    assert second.report["rays"]["visibility_in_table"] == first.report["rays"]["visibility_in_table"]
    assert second.report["table_bytes"] == first.report["table_bytes"]
    for a, b in zip(first.objects, second.objects):
        for name in a.images:
            np.testing.assert_array_equal(a.images[name], b.images[name])
    third = relight(again, [dataclasses.replace(SUN, strength=SUN.strength * 2)], World())
    assert again.table.loaded and third.report["cache"]["lighting_reused"] == []


def test_a_damaged_table_found_when_read_refuses_a_relight_and_is_rebuilt_by_a_bake(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    settings = _settings()
    good = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    _corrupt_flip_bit(good.cache_status.path)
    for_relight = prepare(Scene(_meshes(), [SUN]), settings, cache=cache, require_cached_table=True)
    with pytest.raises(BakeRefused, match="damaged"):
        for_relight.table.hit_object
    rebuilt = prepare(Scene(_meshes(), [SUN]), settings, cache=cache)
    result = relight(rebuilt, [SUN], World())
    assert result.report["cache"]["state"] == "corrupt"
    assert any("rebuilt" in w for w in result.report["warnings"])
    _assert_same_table(good.table, rebuilt.table)
    assert prepare(Scene(_meshes(), [SUN]), settings, cache=cache).cache_status.state == "hit"



def test_an_object_key_kept_on_its_mesh_follows_every_array_and_setting_it_hashes():
    """object_key is kept on the mesh between the two times a bake asks for it; replacing
    any array it hashes, or the layout's resolution or mode, gives the key computed afresh."""
    from core.visibility import cache as module

    mesh = quad_mesh("Q", [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    mesh.uv_maps["Other"] = mesh.uv_maps[mesh.bake_uv_map][:, ::-1].copy()
    first = module.object_key(mesh)
    assert module.object_key(mesh) == first == module._object_key(mesh)
    changes = [
        ("positions", lambda m: setattr(m, "positions", m.positions + 1.0)),
        ("triangles", lambda m: setattr(m, "triangles", m.triangles[:, [0, 2, 1]].copy())),
        ("uv map", lambda m: m.uv_maps.__setitem__(m.bake_uv_map, m.uv_maps[m.bake_uv_map] * 0.5)),
        ("resolution", lambda m: setattr(m, "resolution", (m.resolution[0] * 2, m.resolution[1]))),
        ("mode", lambda m: setattr(m, "mode", "vertex")),
        ("a bake UV map where there was none", lambda m: setattr(m, "bake_uv_map", "Other")),
    ]
    for name, change in changes:
        changed = dataclasses.replace(mesh, uv_maps=dict(mesh.uv_maps))
        changed._object_key = mesh._object_key
        change(changed)
        assert module.object_key(changed) == module._object_key(changed) != first, name
    # A vertex-mode mesh without its bake UV map, then with one (which vertex keys do not
    # hash): the kept key's None is compared with an array without asking numpy for a truth.
    vertex = dataclasses.replace(mesh, mode="vertex", bake_uv_map="None yet", uv_maps=dict(mesh.uv_maps))
    before = module.object_key(vertex)
    vertex.uv_maps["None yet"] = mesh.uv_maps[mesh.bake_uv_map]
    assert module.object_key(vertex) == module._object_key(vertex) == before
