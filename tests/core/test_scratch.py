"""A large table held in a scratch file's mapping (core.visibility.scratch), its pages handed
back after each part of a pass: the same bits as a table in memory, and nothing left on disk."""
import os
from dataclasses import astuple
from types import SimpleNamespace

import numpy as np
import pytest

from core import kernels
from core.pipeline.prepare import prepare
from core.pipeline.relight import relight
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core.visibility import cache as cache_module
from core.visibility import scratch, shadows, table
from core.visibility.cache import VisibilityCache
from core.visibility.table import ENTRY_ARRAYS, TableEntries
from core_scenes import quad_mesh


def _wall_on_floor():
    floor = quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=24,
                      material=Material(base_color=np.full(3, 0.8)))
    wall = quad_mesh("Wall", [(-0.8, 0, 0), (0.8, 0, 0), (0.8, 0, 1), (-0.8, 0, 1)], resolution=16,
                     material=Material(base_color=np.full(3, 0.5)))
    lamp = Light("Lamp", "POINT", np.array([1.0, 0.9, 0.8]), 80.0, position=np.array([0.3, -0.6, 0.7]))
    return Scene([floor, wall], [lamp])


def _small_steps(monkeypatch):
    """Every pass over the table hands its pages back after a few hundred bytes: many parts."""
    from core.transport import contacts
    for module in (table, contacts, shadows):
        monkeypatch.setattr(module, "RELEASE_BYTES", 512)
    monkeypatch.setattr(cache_module, "WRITE_STEP_BYTES", 1000)


def test_scratch_arrays_keep_their_values_when_their_pages_are_handed_back(tmp_path):
    held = scratch.ScratchArrays(str(tmp_path), {"a": (np.int16, (5001,)), "b": (np.uint16, (3000, 2)),
                                                  "c": (np.uint64, (0,))})
    rng = np.random.default_rng(1)
    a, b = rng.integers(-3, 30000, 5001).astype(np.int16), rng.integers(0, 65535, (3000, 2)).astype(np.uint16)
    held.arrays["a"][:] = a
    held.arrays["b"][:] = b
    held.release()
    np.testing.assert_array_equal(held.arrays["a"], a)
    np.testing.assert_array_equal(held.arrays["b"], b)
    assert held.arrays["c"].shape == (0,)
    # Each array starts on a page of its own.
    base = held.arrays["a"].ctypes.data
    assert (held.arrays["b"].ctypes.data - base) % scratch.mmap.PAGESIZE == 0
    if os.name == "posix":
        assert os.listdir(tmp_path) == []  # nameless from the start: nothing can be left behind


def test_a_table_too_small_or_without_a_folder_stays_in_memory(tmp_path):
    words = np.full((3, 1), np.uint64(0b1011), np.uint64)
    assert TableEntries.empty(words, 4, str(tmp_path)).scratch is None  # under MIN_MAPPED_BYTES
    assert TableEntries.empty(words, 4).scratch is None


def test_a_scratch_file_that_cannot_be_made_leaves_the_table_in_memory_and_says_why(monkeypatch, tmp_path):
    monkeypatch.setattr(scratch, "MIN_MAPPED_BYTES", 0)
    words = np.full((3, 1), np.uint64(0b1011), np.uint64)
    entries = TableEntries.empty(words, 4, str(tmp_path / "missing"))
    assert entries.scratch is None and "missing" in entries.mapping_error
    assert entries.hit_uv_code.shape == (9, 2)
    mapped = TableEntries.empty(words, 4, str(tmp_path))
    assert mapped.scratch is not None and not mapped.mapping_error
    assert [getattr(mapped, name).dtype for name in ENTRY_ARRAYS] == [d for d, _, _ in ENTRY_ARRAYS.values()]


def test_without_a_space_reservation_a_disk_without_room_leaves_the_table_in_memory(monkeypatch, tmp_path):
    """Where the system cannot reserve the file's space (no posix_fallocate), a write through the
    mapping into a full disk would be a fault: the table stays in memory unless twice its size is free."""
    monkeypatch.setattr(scratch, "MIN_MAPPED_BYTES", 0)
    monkeypatch.delattr(scratch.os, "posix_fallocate", raising=False)
    words = np.full((3, 1), np.uint64(0b1011), np.uint64)
    monkeypatch.setattr(scratch.shutil, "disk_usage", lambda folder: SimpleNamespace(free=100))
    entries = TableEntries.empty(words, 4, str(tmp_path))
    assert entries.scratch is None and "free" in entries.mapping_error
    monkeypatch.setattr(scratch.shutil, "disk_usage", lambda folder: SimpleNamespace(free=1 << 40))
    entries = TableEntries.empty(words, 4, str(tmp_path))
    assert entries.scratch is not None
    entries.hit_object[:] = np.arange(9)
    entries.release()
    np.testing.assert_array_equal(entries.hit_object, np.arange(9))


@pytest.mark.parametrize("shadow_mode", ["exact", "fractions"])
def test_a_bake_whose_table_is_in_a_scratch_file_gives_the_bits_of_one_in_memory(monkeypatch, tmp_path, shadow_mode):
    """Trace, cache write, contacts, exposed shares, shadow fractions and gathers, each handing
    the table's pages back after a few hundred bytes, against the same bake with the table in
    memory: every image bitwise equal, and the cached table reads back as it was traced."""
    settings = BakeSettings(directions=64, bounces=2, footprint_samples=16, shadows=shadow_mode,
                            passes=("lighting", "direct", "indirect", "ao"))
    in_memory = prepare(_wall_on_floor(), settings)
    assert in_memory.table.entries.scratch is None
    expected = relight(in_memory, _wall_on_floor().lights, World())

    monkeypatch.setattr(scratch, "MIN_MAPPED_BYTES", 0)
    _small_steps(monkeypatch)
    cache = VisibilityCache(str(tmp_path / "cache"), "scene")
    mapped = prepare(_wall_on_floor(), settings, cache=cache)
    assert mapped.table.entries.scratch is not None
    assert not any("held in memory" in warning for warning in mapped.warnings)
    result = relight(mapped, _wall_on_floor().lights, World())
    for ours, theirs in zip(result.objects, expected.objects):
        assert ours.images.keys() == theirs.images.keys()
        for name in ours.images:
            np.testing.assert_array_equal(ours.images[name], theirs.images[name], err_msg=f"{ours.name} {name}")
    hit = prepare(_wall_on_floor(), settings, cache=cache)
    assert hit.cache_status.state == "hit"
    for name in ENTRY_ARRAYS:
        np.testing.assert_array_equal(getattr(hit.table.entries, name), getattr(in_memory.table.entries, name))
    # Only the cache's own files are in its folder: the scratch file had no name.
    if os.name == "posix":
        assert all(not name.startswith("visibake-table-") for _, _, names in os.walk(tmp_path) for name in names)


def test_contact_passes_in_parts_are_bitwise_those_of_numpy(monkeypatch):
    """Close entries by ranges of directions and exposed shares by ranges of samples, as a table
    in a scratch file runs them, give the one-pass numpy results."""
    if kernels.compiled() is None:
        pytest.skip(f"compiled kernels unavailable: {kernels.status().reason}")
    from core.transport import contacts
    p = prepare(_wall_on_floor(), BakeSettings(directions=64, bounces=1, footprint_samples=16))
    _small_steps(monkeypatch)
    sizes = contacts.texel_sizes(p.meshes, p.object_samples)
    target = contacts.SHORT_HIT_TEXELS * sizes
    ours, theirs = contacts.close_entries(p, target), contacts._close_entries_numpy(p, target, None)
    assert len(theirs.sample) > 100
    for a, b in zip(astuple(ours), astuple(theirs)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert p.table.samples > 3 * 64  # several ranges of samples
    for slots in (1, 16):
        np.testing.assert_array_equal(contacts.exposed_share(p.table, slots),
                                      contacts._exposed_share_numpy(p.table, slots))


def _traced_and_cached(tmp_path):
    cache = VisibilityCache(str(tmp_path / "cache"), "scene")
    settings = BakeSettings(directions=48, bounces=1, footprint_samples=4)
    traced = prepare(_wall_on_floor(), settings, cache=cache)
    return cache, settings, traced


def test_a_cached_table_is_read_in_place_and_checked(tmp_path):
    """A table file's members start on 64-byte boundaries, so a cache hit maps them (their pages
    handed back as passes read them) rather than reading 1.7 GB into memory at Production."""
    cache, settings, traced = _traced_and_cached(tmp_path)
    loaded = cache.load_table(settings, cache.read_table_meta(settings)).arrays["entries"]
    if not scratch.CAN_MAP_FILES:
        assert loaded.scratch is None
        return
    assert isinstance(loaded.scratch, scratch.MappedFile)
    for name in ("above_words", *ENTRY_ARRAYS):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(traced.table.entries, name))
        assert getattr(loaded, name).flags.writeable and getattr(loaded, name).flags.aligned
    loaded.release()
    np.testing.assert_array_equal(loaded.hit_uv_code, traced.table.entries.hit_uv_code)
    # The entry bits are stored deflated (they are not mapped), the entries as they are.
    with cache_module.zipfile.ZipFile(cache.table_path(settings)) as archive:
        assert archive.getinfo("above_words.npy").compress_type == cache_module.zipfile.ZIP_DEFLATED
        assert archive.getinfo("above_words.npy").compress_size < archive.getinfo("above_words.npy").file_size
        assert all(archive.getinfo(f"{name}.npy").compress_type == cache_module.zipfile.ZIP_STORED
                   for name in ENTRY_ARRAYS)


def test_a_cached_table_whose_members_are_not_aligned_is_read_into_memory(monkeypatch, tmp_path):
    """A file whose members do not start where their dtype can be mapped (written before the
    members were aligned) is read as before."""
    def odd_member(name, offset):
        info = cache_module.zipfile.ZipInfo(name, date_time=(2026, 1, 1, 0, 0, 0))
        pad = (1 - (offset + 30 + len(name) + 4 + 20)) % cache_module.MEMBER_ALIGN
        info.extra = cache_module.struct.pack("<HH", 0x5650, pad) + bytes(pad)
        return info

    monkeypatch.setattr(cache_module, "_aligned_member", odd_member)
    cache, settings, traced = _traced_and_cached(tmp_path)
    loaded = cache.load_table(settings, cache.read_table_meta(settings)).arrays["entries"]
    assert loaded.scratch is None
    for name in ENTRY_ARRAYS:
        np.testing.assert_array_equal(getattr(loaded, name), getattr(traced.table.entries, name))


def test_a_mapped_cached_table_that_does_not_match_its_checksum_is_refused(tmp_path):
    cache, settings, _ = _traced_and_cached(tmp_path)
    path = cache.table_path(settings)
    meta = cache.read_table_meta(settings)
    with open(path, "rb") as stream, cache_module.zipfile.ZipFile(stream) as archive:
        offset, _, _ = cache_module._member_layout(stream, archive, "hit_uv_code")
    with open(path, "r+b") as stream:
        stream.seek(offset + 5)
        byte = stream.read(1)
        stream.seek(offset + 5)
        stream.write(bytes([byte[0] ^ 0x40]))
    with pytest.raises(cache_module.CorruptCache, match="hit_uv_code does not match its checksum"):
        cache.load_table(settings, meta)
