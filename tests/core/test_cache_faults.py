"""The visibility cache under faults: crafted headers, writers killed mid-write, interrupts."""
import fcntl
import gc
import json
import os
import sys
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.pipeline.prepare import prepare
from core.scene import Light, Material, Scene
from core.settings import BakeSettings
from core.visibility import cache as cache_module
from core.visibility.cache import CorruptCache, VisibilityCache, check_header
from core_scenes import quad_mesh

SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.1, -1.0]) / np.linalg.norm([0.3, 0.1, 1.0]))
SETTINGS = BakeSettings(directions=16, bounces=1)


def _meshes():
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.7)), resolution=8)
    roof = quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, -0.4, 0.6)],
                     material=Material(base_color=np.full(3, 0.5)), resolution=4)
    return [ground, roof]


def _bake(cache):
    return prepare(Scene(_meshes(), [SUN]), SETTINGS, cache=cache)


def _header(path) -> dict:
    with np.load(path) as data:
        return json.loads(bytes(data["meta"]).decode())


def _rewrite_header(path, header) -> None:
    """The file with its arrays as they are and ``header`` in place of its own."""
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files if name != "meta"}
    with open(path, "wb") as stream:
        np.savez(stream, meta=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)


@pytest.fixture(scope="module")
def table_header(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cache")
    return _header(_bake(VisibilityCache(str(folder))).cache_status.path)


# Each a header as an attacker or a damaged disk might leave it: a field missing, or of another type.
CRAFTED = [
    ("no key", lambda h: h.pop("key")),
    ("key a number", lambda h: h.update(key=7)),
    ("object names a string", lambda h: h.update(object_names="Ground")),
    ("object names of numbers", lambda h: h.update(object_names=[1, 2])),
    ("object keys missing", lambda h: h.pop("object_keys")),
    ("fewer keys than names", lambda h: h.update(object_keys=h["object_keys"][:1])),
    ("sample offset of strings", lambda h: h.update(sample_offset=["0", "64"])),
    ("sample offset a record", lambda h: h.update(sample_offset={"a": 1})),
    ("counters a list", lambda h: h.update(counters=[1, 2, 3])),
    ("a counter a string", lambda h: h["counters"].update(rays_cast="many")),
    ("a counter missing", lambda h: h["counters"].pop("backface_hits")),
    ("a counter negative", lambda h: h["counters"].update(rays_cast=-1)),
    ("arrays a string", lambda h: h.update(arrays="hit_object")),
    ("digests a list", lambda h: h.update(digests=["crc32:0"])),
    ("a digest a number", lambda h: h["digests"].update(hit_object=5)),
    ("format a string", lambda h: h.update(format="3")),
    ("format a float", lambda h: h.update(format=3.0)),
    ("format a bool", lambda h: h.update(format=True)),
    ("kind lighting", lambda h: h.update(kind="lighting")),
    ("kind missing", lambda h: h.pop("kind")),
    ("written a number", lambda h: h.update(written=2026)),
]


@pytest.mark.parametrize("craft", [c for _, c in CRAFTED], ids=[name for name, _ in CRAFTED])
def test_a_crafted_table_header_is_corrupt_and_rebuilt(tmp_path, craft):
    cache = VisibilityCache(str(tmp_path))
    good = _bake(cache)
    header = _header(good.cache_status.path)
    craft(header)
    _rewrite_header(good.cache_status.path, header)
    again = _bake(cache)
    assert again.cache_status.state == "corrupt"
    assert any("rebuilt" in w for w in again.warnings)
    np.testing.assert_array_equal(again.table.hit_object, good.table.hit_object)
    assert _bake(cache).cache_status.state == "hit"


_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=4),
                     lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                                  max_size=3), max_leaves=8)


@given(field=st.sampled_from(["format", "kind", "key", "arrays", "digests", "object_names", "object_keys",
                              "sample_offset", "counters", "written", None]), value=_JSON)
def test_any_value_in_any_header_field_is_accepted_or_corrupt_never_a_crash(table_header, field, value):
    header = json.loads(json.dumps(table_header))
    if field is None:
        header = value  # the whole header replaced
    else:
        header[field] = value
    try:
        check_header(header, "table")
    except CorruptCache as error:
        assert str(error) and "\n" not in str(error)
        return
    # Accepted: then every field is what the code that reads it expects.
    assert isinstance(header["object_names"], list) and all(isinstance(n, str) for n in header["object_names"])
    assert all(type(x) is int for x in header["sample_offset"])
    assert all(type(header["counters"][n]) is int for n in ("rays_cast", "rays_below_horizon", "backface_hits"))


def test_a_crafted_lighting_header_is_dropped_not_a_crash(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    cache.save_lighting(SETTINGS, "k1", {"direct": np.ones((4, 3), np.float32)})
    path = cache._lighting_path(SETTINGS, "k1")
    for craft in (lambda h: h.update(arrays=None), lambda h: h.update(key=["k1"]), lambda h: h.pop("digests")):
        cache.save_lighting(SETTINGS, "k1", {"direct": np.ones((4, 3), np.float32)})
        header = _header(path)
        craft(header)
        _rewrite_header(path, header)
        assert cache.load_lighting(SETTINGS, "k1") is None
        assert not os.path.exists(path)  # removed, so the next bake writes a good one


def _abandoned(slot, name, age_seconds):
    path = os.path.join(slot, f"{cache_module.WRITING_PREFIX}{name}.npz")
    with open(path, "wb") as stream:
        stream.write(b"PK\x03\x04 half a table")
    stamp = time.time() - age_seconds
    os.utime(path, (stamp, stamp))
    return path


def test_half_written_files_of_killed_bakes_are_removed_and_counted_live_ones_kept(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    slot = os.path.dirname(_bake(cache).cache_status.path)
    killed = [_abandoned(slot, f"killed{i}", 3600) for i in range(2)]
    live = _abandoned(slot, "live", 3600)
    recent = _abandoned(slot, "recent", -60)  # newer than this bake: another bake's, running now
    with open(live, "rb") as writer:
        # Another bake still writing holds the lock (a second open file description conflicts
        # with it, as another process's would).
        fcntl.flock(writer.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        again = VisibilityCache(str(tmp_path))
        status = _bake(again).cache_status
    assert status.state == "hit" and status.abandoned_writes_removed == 2
    assert not any(os.path.exists(p) for p in killed)
    assert os.path.exists(live) and os.path.exists(recent)


def test_a_read_only_cache_reads_but_never_writes_or_removes(tmp_path):
    first = _bake(VisibilityCache(str(tmp_path)))
    slot = os.path.dirname(first.cache_status.path)
    killed = _abandoned(slot, "killed", 3600)
    before = sorted(os.listdir(slot))
    reader = VisibilityCache(str(tmp_path), read_only=True)
    assert _bake(reader).cache_status.state == "hit"
    reader.save_lighting(SETTINGS, "k", {"direct": np.ones(3, np.float32)})
    assert sorted(os.listdir(slot)) == before and os.path.exists(killed)


def test_an_interrupted_cache_write_leaves_no_file_and_no_unclosed_archive(tmp_path, monkeypatch):
    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    write_header = np.lib.format.write_array_header_1_0
    written = []

    def interrupted_after_one(stream, header):
        # Ctrl+C in the middle of the archive: one member written, the next cut short.
        if written:
            stream.write(b"\x93NUMPY half")
            raise KeyboardInterrupt
        written.append(header)
        write_header(stream, header)

    monkeypatch.setattr(np.lib.format, "write_array_header_1_0", interrupted_after_one)
    path = str(tmp_path / "slot" / "visibility.npz")
    with pytest.raises(KeyboardInterrupt):
        cache_module._write(path, {"kind": "table"}, {"a": np.ones(1000), "b": np.zeros(1000)})
    gc.collect()
    assert written and unraisable == []  # 'Exception ignored in ZipFile.__del__' is an unraisable exception
    assert os.listdir(tmp_path / "slot") == []
