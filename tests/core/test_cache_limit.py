"""The cache on disk: only entries above the horizon are stored, and the folder's size cap
removes the least recently used tables first."""
import fcntl
import os
import time

import numpy as np
import pytest

from core.pipeline.prepare import prepare
from core.scene import Light, Material, Scene
from core.settings import BakeSettings
from core.visibility.cache import (
    ABOVE_WORDS,
    CacheFull,
    CorruptCache,
    VisibilityCache,
    pack_entries,
    packed_bytes,
    unpack_entries,
)
from core.visibility.table import BELOW_HORIZON
from core_scenes import grid_mesh, quad_mesh

SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, 1.0]))
SETTINGS = BakeSettings(directions=32, bounces=1)
ENTRY_ARRAYS = ("hit_object", "hit_uv_code", "hit_distance_code", "vertex_cells")


def _scene(vertex: bool = False) -> Scene:
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.7)), resolution=12)
    roof = (grid_mesh("Roof", size=0.8, segments=4, z=0.6, flip=True) if vertex else
            quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, -0.4, 0.6)],
                      material=Material(base_color=np.full(3, 0.5)), resolution=6))
    return Scene([ground, roof], [SUN])


@pytest.mark.parametrize("vertex", [False, True], ids=["atlas", "vertex"])
def test_a_table_read_back_from_its_file_is_bitwise_the_traced_one(tmp_path, vertex):
    cache = VisibilityCache(str(tmp_path), "packed")
    traced = prepare(_scene(vertex), SETTINGS, cache=cache, table_needed=True)
    assert (traced.table.vertex_cells is not None) == vertex
    below = int(np.count_nonzero(traced.table.hit_object == BELOW_HORIZON))
    assert below > 0, "a scene with no entry below the horizon tests nothing here"
    read = prepare(_scene(vertex), SETTINGS, cache=cache, table_needed=True)
    assert read.cache_status.state == "hit"
    for name in ENTRY_ARRAYS:
        original, again = getattr(traced.table, name), getattr(read.table, name)
        if original is None:
            assert again is None
        else:
            np.testing.assert_array_equal(again, original, err_msg=name)
            assert again.dtype == original.dtype


def test_the_file_holds_the_entries_above_the_horizon_and_its_size_is_known_before_writing(tmp_path):
    cache = VisibilityCache(str(tmp_path), "size")
    prepared = prepare(_scene(), SETTINGS, cache=cache, table_needed=True)
    table, status = prepared.table, prepared.cache_status
    packed = pack_entries(table)
    above = int(np.count_nonzero(table.hit_object != BELOW_HORIZON))
    assert len(packed["hit_object"]) == above < table.hit_object.size
    assert BELOW_HORIZON not in packed["hit_object"]
    assert status.estimated_bytes == packed_bytes(table) == sum(a.nbytes for a in packed.values())
    # The file adds a header and the per-sample arrays to the estimate, a few kilobytes.
    assert 0 < status.bytes_on_disk - status.estimated_bytes < 16384
    dense_bytes = table.hit_object.size * (2 + 4 + 2)
    assert status.estimated_bytes < 0.75 * dense_bytes
    # Memory holds the same entries, and each word's first entry (8 bytes a word of 64 entries).
    assert table.nbytes == status.estimated_bytes + table.entries.word_base.nbytes


def test_entries_that_do_not_fit_their_bits_are_refused(tmp_path):
    table = prepare(_scene(), SETTINGS, table_needed=True).table
    samples = table.samples
    good = pack_entries(table)
    np.testing.assert_array_equal(unpack_entries(dict(good), samples).dense("hit_object"), table.hit_object)
    short = dict(good, hit_uv_code=good["hit_uv_code"][:-1])
    bits = dict(good, **{ABOVE_WORDS: good[ABOVE_WORDS][:, :-1]})
    # A bit past the last sample: an entry no sample owns.
    stray = good[ABOVE_WORDS].copy()
    stray[0, -1] |= np.uint64(1) << np.uint64(63)
    beyond = dict(good, **{ABOVE_WORDS: stray})
    retyped = dict(good, hit_object=good["hit_object"].astype(np.int32))
    assert samples % 64, "the scene's sample count must leave unused bits in the last word"
    for crafted, reason in ((short, "hit_uv_code"), (bits, "entry bits"), (retyped, "hit_object"),
                            (beyond, "samples the table does not have")):
        with pytest.raises(CorruptCache, match=reason):
            unpack_entries(crafted, samples)


def _slot(folder, name: str, sizes: dict, used: float) -> str:
    """A slot folder as a bake leaves it, its files of ``sizes`` bytes last used at ``used``."""
    slot = os.path.join(folder, name)
    os.makedirs(slot, exist_ok=True)
    for file, size in sizes.items():
        path = os.path.join(slot, file)
        with open(path, "wb") as stream:
            stream.write(b"\0" * size)
        os.utime(path, (used, used))
    return slot


def test_the_cap_removes_the_least_recently_used_tables_of_any_scene_first(tmp_path):
    now = time.time()
    oldest = _slot(tmp_path, "a-111111111111", {"visibility.npz": 4000, "lighting-1.npz": 500}, now - 300)
    middle = _slot(tmp_path, "b-222222222222", {"visibility.npz": 4000}, now - 200)
    newest = _slot(tmp_path, "c-333333333333", {"visibility.npz": 4000}, now - 100)
    (tmp_path / "notes.txt").write_bytes(b"\0" * 100)  # not VisiBake's: counted, never removed
    (tmp_path / "d-444444444444").mkdir()
    (tmp_path / "d-444444444444" / "mine.blend").write_bytes(b"\0" * 100)
    cache = VisibilityCache(str(tmp_path), "scene", limit_bytes=13000)
    settings = BakeSettings(directions=16)
    own = _slot(tmp_path, os.path.basename(cache.slot(settings)), {"visibility.npz": 3000}, now - 1000)
    # 15700 in the folder, 3000 of it replaced, 5000 coming: 4700 over the cap; the oldest slot frees 4500.
    cache.make_room(settings, 5000)
    assert not os.path.exists(oldest) and not os.path.exists(middle)
    assert os.path.exists(os.path.join(newest, "visibility.npz"))
    assert os.path.exists(os.path.join(own, "visibility.npz"))
    assert (tmp_path / "notes.txt").exists() and (tmp_path / "d-444444444444" / "mine.blend").exists()
    assert [os.path.basename(slot) for slot, _ in cache.evicted] == ["a-111111111111", "b-222222222222"]
    assert [size for _, size in cache.evicted] == [4500, 4000]


def test_a_table_larger_than_the_room_the_cap_can_make_is_not_written_and_nothing_is_removed(tmp_path):
    now = time.time()
    other = _slot(tmp_path, "a-111111111111", {"visibility.npz": 4000}, now - 100)
    cache = VisibilityCache(str(tmp_path), "scene", limit_bytes=10000)
    with pytest.raises(CacheFull, match="cap of 0 MiB"):
        cache.make_room(BakeSettings(directions=16), 10001)
    (tmp_path / "big.bin").write_bytes(b"\0" * 5000)  # not VisiBake's, so never made room from
    with pytest.raises(CacheFull):
        cache.make_room(BakeSettings(directions=16), 6000)
    assert os.path.exists(os.path.join(other, "visibility.npz")) and not cache.evicted


def test_a_slot_that_a_live_bake_is_writing_is_never_removed(tmp_path):
    now = time.time()
    busy = _slot(tmp_path, "a-111111111111", {"visibility.npz": 4000}, now - 300)
    idle = _slot(tmp_path, "b-222222222222", {"visibility.npz": 4000}, now - 200)
    writing = os.path.join(busy, ".writing-x.npz")
    with open(writing, "wb") as stream:
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        os.utime(writing, (now - 400, now - 400))
        cache = VisibilityCache(str(tmp_path), "scene", limit_bytes=9000)
        cache.make_room(BakeSettings(directions=16), 4000)
        assert os.path.exists(os.path.join(busy, "visibility.npz")) and not os.path.exists(idle)


def test_a_bake_whose_table_exceeds_the_cap_goes_on_uncached_and_says_why(tmp_path):
    cache = VisibilityCache(str(tmp_path), "small", limit_bytes=1024)
    prepared = prepare(_scene(), SETTINGS, cache=cache, table_needed=True)
    status = prepared.cache_status
    assert status.not_cached and "cap" in status.not_cached and status.bytes_on_disk == 0
    assert not os.path.exists(status.path)
    assert any("not cached" in warning and "Cache Limit" in warning for warning in prepared.warnings)
    assert status.estimated_bytes == packed_bytes(prepared.table)


def test_a_used_table_counts_as_recent(tmp_path):
    first = VisibilityCache(str(tmp_path), "first", limit_bytes=0)
    prepared = prepare(_scene(), SETTINGS, cache=first)
    path = prepared.cache_status.path
    os.utime(path, (1.0, 1.0))
    again = prepare(_scene(), SETTINGS, cache=VisibilityCache(str(tmp_path), "first"))
    assert again.cache_status.state == "hit" and os.path.getmtime(path) > 1.0


def test_lighting_results_respect_the_cap_too(tmp_path):
    now = time.time()
    other = _slot(tmp_path, "a-111111111111", {"visibility.npz": 4000}, now - 100)
    cache = VisibilityCache(str(tmp_path), "scene", limit_bytes=6000)
    settings = BakeSettings(directions=16)
    own = _slot(tmp_path, os.path.basename(cache.slot(settings)), {"visibility.npz": 1500}, now)
    # 5500 in the folder and 800 coming: 300 over the cap, so the other scene's table goes.
    cache.save_lighting(settings, "k" * 32, {"direct": np.zeros(100)})
    assert not os.path.exists(other) and os.path.exists(os.path.join(own, "visibility.npz"))
    assert cache.load_lighting(settings, "k" * 32) is not None
    cache.save_lighting(settings, "m" * 32, {"direct": np.zeros(1000)})  # 8 KB: never fits, skipped
    assert cache.load_lighting(settings, "m" * 32) is None
    assert os.path.exists(os.path.join(own, "visibility.npz"))


def test_the_progress_shows_the_table_s_size_before_it_is_written(tmp_path):
    from core.pipeline.progress import Progress

    cache = VisibilityCache(str(tmp_path), "noted")
    path = cache.table_path(SETTINGS)
    seen = []

    class Watching(Progress):
        def note(self, text):
            super().note(text)
            seen.append((self.stage, text, os.path.exists(path), self.status_text()))

    prepared = prepare(_scene(), SETTINGS, Watching(), cache=cache, table_needed=True)
    mib = f"{prepared.cache_status.estimated_bytes / 2**20:.0f} MiB"
    stage, text, written, status = seen[0]
    assert stage == "cache" and mib in text and not written and text in status
    assert seen[-1][1] == "" and os.path.exists(path)  # cleared once written
