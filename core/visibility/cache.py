"""The visibility cache on disk: tables that depend only on geometry and settings.

A table is valid exactly as long as its key is: a hash of every object's evaluated
world-space geometry, its bake UV map and atlas size (which place the samples), the
direction set (count, rotation, seed), every tolerance of the core and the format
version. Lighting, materials and the world are not in the key, so they can change
freely between bakes (relighting, the paper's section 8).

Each scene has a slot (a folder) named after its label (the .blend) and the
direction settings. The slot holds one table, whose per-object keys let the next
bake find which objects changed and update only what they can affect, and the
transport results of recent lightings, so an unchanged light group is not gathered
again.

Files are numpy ``.npz`` archives with a JSON header and a CRC-32 of every array (on
top of the zip's own); a file that is truncated, fails its check or has another
format version is reported and rebuilt, never trusted. Keys are BLAKE2 hashes.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import tempfile
import time
import zipfile
import zlib
from dataclasses import dataclass, field

import numpy as np

from .. import tolerances as tol

try:
    import fcntl
except ImportError:  # Windows: an open file cannot be removed, which serves as its lock
    fcntl = None
from ..scene import Mesh
from ..settings import BakeSettings

# Bump whenever the meaning of a cached array changes (sampling, table codes, layout).
# 3: one checksum per array, backface counts stored; 4: rays from texel footprints, interleaved rotations;
# 5: a footprint point that finds no place on its triangle starts from the texel's centre;
# 6: compact entries (16-bit atlas coordinates, 16-bit logarithmic distances).
FORMAT_VERSION = 6
TABLE_FILE = "visibility.npz"
LIGHTING_PREFIX = "lighting-"
# Transport results kept per slot (each is 48 bytes per texel): enough for a session
# of re-mixing a handful of light groups, small next to the table.
LIGHTING_ENTRIES_KEPT = 16
# A table's small arrays (a few bytes per sample) are read with its header; the large
# ones (per sample and direction) only when the table is used.
_SMALL_TABLE_ARRAYS = ("directions", "traced_per_sample", "backface_per_sample")
_LARGE_TABLE_ARRAYS = ("hit_object", "hit_uv_code", "hit_distance_code")
_TABLE_ARRAYS = _SMALL_TABLE_ARRAYS + _LARGE_TABLE_ARRAYS
_OPTIONAL_TABLE_ARRAYS = ("hit_triangle",)


def _hasher():
    return hashlib.blake2b(digest_size=16)


def _feed(hasher, array) -> None:
    array = np.ascontiguousarray(array)
    hasher.update(f"{array.dtype.str}{array.shape}".encode())
    hasher.update(array.data)


def object_key(mesh: Mesh) -> str:
    """Hash of what places an object's samples and what its rays can hit."""
    hasher = _hasher()
    _feed(hasher, np.asarray(mesh.positions, np.float64))
    _feed(hasher, np.asarray(mesh.triangles, np.int32))
    hasher.update(mesh.mode.encode())
    if mesh.mode == "vertex":
        # Vertex samples sit where the vertices are, with their shading normals.
        _feed(hasher, np.asarray(mesh.corner_normals, np.float32))
    else:
        _feed(hasher, np.asarray(mesh.uv_maps[mesh.bake_uv_map], np.float32))
        hasher.update(f"{tuple(int(r) for r in mesh.resolution)}".encode())
    return hasher.hexdigest()


def settings_key(settings: BakeSettings) -> str:
    """Hash of the settings and code constants every table entry depends on."""
    constants = {name: getattr(tol, name) for name in sorted(dir(tol)) if name.isupper()}
    text = json.dumps({"format": FORMAT_VERSION, "directions": settings.directions, "rotate": settings.rotate,
                       "seed": settings.seed if settings.rotate else 0,
                       "footprint_samples": settings.footprint_samples,
                       "interleave": settings.interleave,
                       "tolerances": constants}, sort_keys=True)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def table_key(object_keys: list[str], settings: BakeSettings) -> str:
    hasher = _hasher()
    hasher.update(settings_key(settings).encode())
    for key in object_keys:
        hasher.update(key.encode())
    return hasher.hexdigest()


def arrays_key(*parts) -> str:
    """Hash of arrays, numbers and strings (lighting keys)."""
    hasher = _hasher()
    for part in parts:
        if isinstance(part, np.ndarray):
            _feed(hasher, part)
        else:
            hasher.update(repr(part).encode())
    return hasher.hexdigest()


def _digest(name: str, array: np.ndarray) -> str:
    """CRC-32 over an array's name, dtype, shape and bytes: a check against damage, not
    tampering, at disk speed (a cryptographic hash of a 700 MB table costs a second more).
    One per array, so that each can be read and checked on its own."""
    array = np.ascontiguousarray(array)
    crc = zlib.crc32(f"{name}{array.dtype.str}{array.shape}".encode())
    return f"crc32:{zlib.crc32(array.data, crc):08x}"


class CorruptCache(Exception):
    """A cache file that cannot be trusted; the message says why."""


WRITING_PREFIX = ".writing-"


def _lock(stream) -> None:
    """Hold an exclusive lock on a file being written, so that another bake sharing the folder
    sees it is alive (the system drops the lock when the process dies, even by SIGKILL)."""
    if fcntl is not None:
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def _abandoned(path: str, before: float) -> bool:
    """Whether the half-written ``path`` was left by a writer that is gone: older than ``before``
    (the running bake's start) and not locked. Without flock (Windows) a file open for writing
    cannot be removed, which is the same test: the removal fails."""
    try:
        if os.path.getmtime(path) >= before:
            return False
        if fcntl is None:
            return True
        with open(path, "rb") as stream:
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(stream.fileno(), fcntl.LOCK_UN)
        return True
    except OSError:  # locked by a live writer, or gone already
        return False


def remove_abandoned_writes(folder: str, before: float) -> int:
    """Remove the ``.writing-*`` files of writers killed mid-write (see :func:`_abandoned`);
    returns how many were removed."""
    try:
        names = [n for n in os.listdir(folder) if n.startswith(WRITING_PREFIX)]
    except OSError:
        return 0
    removed = 0
    for name in names:
        path = os.path.join(folder, name)
        if _abandoned(path, before):
            try:
                os.remove(path)
                removed += 1
            except OSError:
                pass
    return removed


def _save_npz(stream, arrays: dict) -> None:
    """``np.savez`` with the archive closed on every exit: numpy leaves its ZipFile open when
    interrupted (Ctrl+C), and its finaliser then prints 'Exception ignored in ZipFile.__del__'."""
    with zipfile.ZipFile(stream, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def _write(path: str, meta: dict, arrays: dict) -> int:
    """Write atomically (a reader never sees half a file); returns the size in bytes."""
    meta = {**meta, "format": FORMAT_VERSION, "digests": {name: _digest(name, a) for name, a in arrays.items()}}
    header = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=WRITING_PREFIX, suffix=".npz", dir=folder)
    try:
        with os.fdopen(handle, "wb") as stream:
            _lock(stream)
            _save_npz(stream, {"meta": header, **arrays})
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise
    return os.path.getsize(path)


def _list_of(kind):
    return lambda value: isinstance(value, list) and all(_is(kind, v) for v in value)


def _is(kind, value) -> bool:
    """``value`` has type ``kind`` (JSON's: a bool is no int), or passes ``kind`` if it is a check."""
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if isinstance(kind, type):
        return isinstance(value, kind)
    return kind(value)


def _record_of(kind):
    return lambda value: isinstance(value, dict) and all(_is(kind, v) for v in value.values())


# The header of every cache file, field by field; a file whose header does not match is
# corrupt (a crafted or damaged header must never reach the code that trusts it).
_HEADER_SCHEMA = {
    "format": int, "kind": str, "key": str, "arrays": _list_of(str), "digests": _record_of(str),
}
_KIND_SCHEMA = {
    "table": {"object_names": _list_of(str), "object_keys": _list_of(str), "sample_offset": _list_of(int),
              "counters": lambda value: isinstance(value, dict) and all(
                  _is(int, value.get(name)) and value[name] >= 0
                  for name in ("rays_cast", "rays_below_horizon", "backface_hits")),
              "written": str},
    "lighting": {},
}


def check_header(meta, kind: str) -> None:
    """Raise CorruptCache unless ``meta`` is a header of a ``kind`` ('table' or 'lighting') file
    of this format version, every field present with its type."""
    if not isinstance(meta, dict):
        raise CorruptCache("its header is not a record")
    if meta.get("format") != FORMAT_VERSION or not _is(int, meta.get("format")):
        raise CorruptCache(f"format {meta.get('format')!r} is not this version's {FORMAT_VERSION}")
    for name, field_kind in {**_HEADER_SCHEMA, **_KIND_SCHEMA[kind]}.items():
        if name not in meta:
            raise CorruptCache(f"its header has no {name!r}")
        if not _is(field_kind, meta[name]):
            raise CorruptCache(f"its header's {name!r} is malformed")
    if meta["kind"] != kind:
        raise CorruptCache(f"it holds a {meta['kind']!r}, not a {kind!r}")
    if kind == "table" and len(meta["object_names"]) != len(meta["object_keys"]):
        raise CorruptCache("its header's object names and keys differ in number")


def _read_meta(path: str, kind: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, UnicodeDecodeError,
            RecursionError) as error:
        raise CorruptCache(f"unreadable ({type(error).__name__}: {error})") from None
    check_header(meta, kind)
    return meta


def _read_arrays(path: str, meta: dict, names) -> dict:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in names}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise CorruptCache(f"unreadable ({type(error).__name__}: {error})") from None
    digests = meta.get("digests") or {}
    for name, array in arrays.items():
        if _digest(name, array) != digests.get(name):
            raise CorruptCache(f"its {name} does not match its checksum")
    return arrays


@dataclass
class CacheStatus:
    """What the cache did in one bake, for the report.

    state : 'off' | 'hit' | 'miss' | 'stale' | 'corrupt' | 'updated'
    """

    state: str = "off"
    path: str = ""
    message: str = ""
    changed_objects: list = field(default_factory=list)
    bytes_on_disk: int = 0
    load_seconds: float = 0.0
    save_seconds: float = 0.0
    lighting_reused: list = field(default_factory=list)
    abandoned_writes_removed: int = 0  # half-written files of killed bakes removed


@dataclass
class CachedTable:
    """A table read back from disk, with the layout it was made for."""

    arrays: dict
    object_names: list
    object_keys: list
    sample_offset: np.ndarray
    counters: dict


def _safe_label(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label).strip("._")[:48] or "untitled"


class VisibilityCache:
    """The cache folder of one scene; see the module docstring for what it holds."""

    def __init__(self, folder: str, label: str = "untitled", read_only: bool = False):
        self.folder = os.path.abspath(folder)
        self.label = _safe_label(label)
        # Nothing is written or removed (a folder this process cannot write; the bake says so).
        self.read_only = read_only
        # A half-written file older than this cache's first use is no live bake's own.
        self.opened = time.time()
        # Half-written files of killed bakes removed so far (in the report).
        self.abandoned_removed = 0

    def _remove_abandoned(self, settings: BakeSettings) -> None:
        if not self.read_only:
            self.abandoned_removed += remove_abandoned_writes(self.slot(settings), self.opened)

    def slot(self, settings: BakeSettings) -> str:
        return os.path.join(self.folder, f"{self.label}-{settings_key(settings)[:12]}")

    def table_path(self, settings: BakeSettings) -> str:
        return os.path.join(self.slot(settings), TABLE_FILE)

    def read_table_meta(self, settings: BakeSettings) -> dict | None:
        """The header of the slot's table, None if there is none; raises CorruptCache."""
        self._remove_abandoned(settings)
        path = self.table_path(settings)
        if not os.path.exists(path):
            return None
        return _read_meta(path, "table")

    def deferred_table(self, settings: BakeSettings, meta: dict, damaged=None):
        """The slot's table with only its small arrays read (and checked) now; the large
        ones are read on first use. ``damaged(error)`` -> dict of large arrays is called
        if they turn out not to match their checksums then (and may raise)."""
        from .table import DeferredTable

        path = self.table_path(settings)
        small = _read_arrays(path, meta, _SMALL_TABLE_ARRAYS)
        large = _LARGE_TABLE_ARRAYS + tuple(n for n in _OPTIONAL_TABLE_ARRAYS if n in meta.get("arrays", ()))

        def read_large():
            try:
                return _read_arrays(path, meta, large)
            except CorruptCache as error:
                if damaged is None:
                    raise
                return damaged(error)

        return DeferredTable(small, meta["counters"], "hit_triangle" in large, read_large)

    def load_table(self, settings: BakeSettings, meta: dict) -> CachedTable:
        names = _TABLE_ARRAYS + tuple(n for n in _OPTIONAL_TABLE_ARRAYS if n in meta.get("arrays", ()))
        arrays = _read_arrays(self.table_path(settings), meta, names)
        return CachedTable(arrays=arrays, object_names=list(meta["object_names"]),
                           object_keys=list(meta["object_keys"]),
                           sample_offset=np.asarray(meta["sample_offset"], np.int64), counters=meta["counters"])

    def save_table(self, settings: BakeSettings, key: str, object_names: list, object_keys: list,
                   sample_offset: np.ndarray, table) -> int:
        if self.read_only:
            return 0
        self._remove_abandoned(settings)
        meta = {"kind": "table", "key": key, "object_names": list(object_names), "object_keys": list(object_keys),
                "sample_offset": [int(x) for x in sample_offset],
                "counters": {"rays_cast": int(table.rays_cast), "rays_below_horizon": int(table.rays_below_horizon),
                             "backface_hits": int(table.backface_hits)},
                "written": time.strftime("%Y-%m-%dT%H:%M:%S")}
        arrays = {name: getattr(table, name) for name in _TABLE_ARRAYS}
        arrays.update({name: getattr(table, name) for name in _OPTIONAL_TABLE_ARRAYS
                       if getattr(table, name) is not None})
        meta["arrays"] = sorted(arrays)
        size = _write(self.table_path(settings), meta, arrays)
        self.clear_lighting(settings)  # results of the old table are of no use any more
        return size

    def discard_table(self, settings: BakeSettings) -> None:
        path = self.table_path(settings)
        if not self.read_only and os.path.exists(path):
            os.remove(path)

    def _lighting_path(self, settings: BakeSettings, key: str) -> str:
        return os.path.join(self.slot(settings), f"{LIGHTING_PREFIX}{key}.npz")

    def load_lighting(self, settings: BakeSettings, key: str) -> dict | None:
        """Transport arrays stored under ``key``; None if absent or not trustworthy."""
        path = self._lighting_path(settings, key)
        if not os.path.exists(path):
            return None
        try:
            meta = _read_meta(path, "lighting")
            if meta["key"] != key:
                return None
            arrays = _read_arrays(path, meta, meta["arrays"])
        except CorruptCache:
            if not self.read_only:
                os.remove(path)
            return None
        if not self.read_only:
            os.utime(path)  # most recently used, kept longest
        return arrays

    def save_lighting(self, settings: BakeSettings, key: str, arrays: dict) -> None:
        if self.read_only:
            return
        self._remove_abandoned(settings)
        _write(self._lighting_path(settings, key), {"kind": "lighting", "key": key, "arrays": sorted(arrays)}, arrays)
        entries = self._lighting_files(settings)
        entries.sort(key=os.path.getmtime)
        for path in entries[:-LIGHTING_ENTRIES_KEPT]:
            os.remove(path)

    def _lighting_files(self, settings: BakeSettings) -> list[str]:
        slot = self.slot(settings)
        if not os.path.isdir(slot):
            return []
        return [os.path.join(slot, name) for name in os.listdir(slot)
                if name.startswith(LIGHTING_PREFIX) and name.endswith(".npz")]

    def clear_lighting(self, settings: BakeSettings) -> None:
        for path in self._lighting_files(settings):
            os.remove(path)


def folder_size(folder: str) -> int:
    """Bytes under ``folder`` (0 if it does not exist)."""
    total = 0
    for root, _, files in os.walk(folder):
        for name in files:
            try:
                total += os.path.getsize(os.path.join(root, name))
            except OSError:
                pass
    return total
