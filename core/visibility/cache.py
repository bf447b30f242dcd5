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

A table file holds the table's stored entries as memory holds them (core.visibility.table.
TableEntries): only those above their sample's horizon (about half), a bit per entry saying
which are there (deflated), and the per-entry arrays listing those in row-major order (stored,
each starting on a 64-byte boundary of the file, so that a bake maps them in place rather than
reading them: see :func:`_mapped_arrays`). It reads back bitwise as it was traced.

The folder's total size can be capped (``VisibilityCache(limit_bytes=)``): before a table
is written, the least recently used slots of any scene are removed until it fits, and a
table larger than the cap is not written at all (the bake says so).
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import struct
import sys
import tempfile
import time
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .. import tolerances as tol

try:
    import fcntl
except ImportError:  # Windows: an open file cannot be removed, which serves as its lock
    fcntl = None
from ..scene import Mesh
from ..settings import BakeSettings
from .scratch import CAN_MAP_FILES, MappedFile
from .table import ENTRY_ARRAYS, TableEntries, entries_nbytes

# Bump whenever the meaning of a cached array changes (sampling, table codes, layout).
# 3: one checksum per array, backface counts stored; 4: rays from texel footprints, interleaved rotations;
# 5: a footprint point that finds no place on its triangle starts from the texel's centre;
# 6: compact entries (16-bit atlas coordinates, 16-bit logarithmic distances);
# 7: only the entries above the horizon, with a bit per entry saying which, and triangles only
#    of the entries that hit a vertex-mode object (then TablePacking);
# 8: a vertex-mode hit's triangle packed with its barycentrics in hit_uv_code (vertex_cells);
# 9: the entry bits as the table holds them in memory, 64-bit words per direction (TableEntries).
FORMAT_VERSION = 9
TABLE_FILE = "visibility.npz"
# A volume's scattering tables (core.volume.cache), one per slot of its own.
VOLUME_TABLE_FILE = "volume.npz"
LIGHTING_PREFIX = "lighting-"
# Transport results kept per slot (each is 48 bytes per texel): enough for a session
# of re-mixing a handful of light groups, small next to the table.
LIGHTING_ENTRIES_KEPT = 16
# A table's small arrays (a few bytes per sample) are read with its header; the large
# ones (per sample and direction) only when the table is used.
_SMALL_TABLE_ARRAYS = ("directions", "traced_per_sample", "backface_per_sample")
# Tables with vertex-mode objects also keep how those objects' hits are coded.
_OPTIONAL_SMALL_ARRAYS = ("vertex_cells",)
_LARGE_TABLE_ARRAYS = ("hit_object", "hit_uv_code", "hit_distance_code")
# The bits of the entries above the horizon (TableEntries.above_words).
ABOVE_WORDS = "above_words"
# Arrays stored deflated (zlib level 1): the entry bits, whose horizons repeat from sample to
# sample, shrink about 8 times (52 MB to 6 MB at the Production preset, 0.2 s each way), which
# keeps that table file under 1.7 GB. The per-entry arrays are stored as they are, to be mapped.
_DEFLATED_ARRAYS = (ABOVE_WORDS,)


def pack_entries(table) -> dict:
    """The arrays a table file stores of ``table``'s entries (:class:`TableEntries`, no copies):
    ``ABOVE_WORDS`` (N, W) uint64 and the per-entry arrays (A, ...)."""
    entries = table.entries
    return {ABOVE_WORDS: entries.above_words, **{name: getattr(entries, name) for name in ENTRY_ARRAYS}}


def packed_bytes(table) -> int:
    """Bytes :func:`pack_entries` stores of ``table``: what the file will hold, less a few
    kilobytes of header and per-sample arrays."""
    return sum(array.nbytes for array in pack_entries(table).values())


def unpack_entries(packed, samples: int) -> TableEntries:
    """The :class:`TableEntries` of a table of ``samples`` samples from :func:`pack_entries`'
    arrays (``packed``: a mapping, read one array at a time). Raises CorruptCache where the
    arrays do not fit together (a checksum guards against damage, this against a file made by
    hand)."""
    for name in (ABOVE_WORDS, *ENTRY_ARRAYS):
        if name not in packed:
            raise CorruptCache(f"it has no {name}")
    try:
        return TableEntries.from_stored(packed[ABOVE_WORDS], samples, {name: packed[name] for name in ENTRY_ARRAYS})
    except ValueError as error:
        raise CorruptCache(str(error)) from None


def _member_layout(stream, archive: zipfile.ZipFile, name: str) -> tuple[int, np.dtype, tuple] | None:
    """Where array ``name``'s bytes lie in the open table file: (offset, dtype, shape), or None
    where they cannot be mapped in place (compressed, Fortran order, not aligned for its dtype:
    a file written before members were aligned)."""
    info = archive.getinfo(f"{name}.npy")
    if info.compress_type != zipfile.ZIP_STORED:
        return None
    stream.seek(info.header_offset)
    local = stream.read(30)
    if len(local) != 30 or local[:4] != b"PK\x03\x04":
        raise ValueError(f"the local header of {name} is damaged")
    name_length, extra_length = struct.unpack("<HH", local[26:30])
    start = info.header_offset + 30 + name_length + extra_length
    stream.seek(start)
    version = np.lib.format.read_magic(stream)
    reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = reader(stream)
    offset = stream.tell()
    nbytes = int(dtype.itemsize * np.prod(shape, dtype=np.int64))
    if fortran or dtype.hasobject or offset % max(dtype.alignment, 1) or offset - start + nbytes != info.file_size:
        return None
    return offset, dtype, tuple(shape)


# Bytes of a mapped array checksummed between handing its pages back.
CHECK_STEP_BYTES = 64 << 20


def _mapped_arrays(path: str, meta: dict, names) -> tuple[dict, MappedFile] | None:
    """The arrays ``names`` of a table file mapped in place, each checked against its digest a
    step at a time (the pages handed back after each), and the mapping; None where the file's
    members cannot be mapped (then they are read: :func:`_read_arrays`). Raises CorruptCache
    where an array does not match its checksum or the file cannot be read."""
    if not CAN_MAP_FILES:
        return None
    try:
        with open(path, "rb") as stream, zipfile.ZipFile(stream) as archive:
            layouts = {name: _member_layout(stream, archive, name) for name in names}
        if any(layout is None for layout in layouts.values()):
            return None
        mapped = MappedFile(path)
        arrays = {name: mapped.array(*layout) for name, layout in layouts.items()}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:
        raise CorruptCache(f"unreadable ({type(error).__name__}: {error})") from None
    digests = meta.get("digests") or {}
    for name, array in arrays.items():
        if _digest(name, array, CHECK_STEP_BYTES, lambda step: mapped.release()) != digests.get(name):
            raise CorruptCache(f"its {name} does not match its checksum")
    return arrays, mapped


def _read_entries(path: str, meta: dict, samples: int) -> TableEntries:
    """A table file's :class:`TableEntries`: mapped in place where the file allows
    (:func:`_mapped_arrays`; its pages are handed back as the passes read them, like a table
    traced into a scratch file), else read into memory one array at a time."""
    mapped = _mapped_arrays(path, meta, _LARGE_TABLE_ARRAYS)
    if mapped is None:
        return unpack_entries(_ArraysOnDemand(path, meta, _stored_entry_arrays(meta)), samples)
    arrays, mapping = mapped
    entries = unpack_entries({**arrays, **_read_arrays(path, meta, (ABOVE_WORDS,))}, samples)
    entries.scratch = mapping
    return entries


class _ArraysOnDemand(Mapping):
    """A table file's arrays, each read (and checked) when it is asked for and not kept."""

    def __init__(self, path: str, meta: dict, names):
        self.path, self.meta, self.names = path, meta, tuple(names)

    def __getitem__(self, name):
        if name not in self.names:
            raise KeyError(name)
        return _read_arrays(self.path, self.meta, (name,))[name]

    def __iter__(self):
        return iter(self.names)

    def __len__(self):
        return len(self.names)


def _stored_entry_arrays(meta: dict) -> tuple:
    """The names of a table file's per-entry arrays (:func:`pack_entries`)."""
    return (ABOVE_WORDS,) + _LARGE_TABLE_ARRAYS


def _small_arrays(meta: dict) -> tuple:
    """The names of a table file's small arrays (read with its header)."""
    return _SMALL_TABLE_ARRAYS + tuple(name for name in _OPTIONAL_SMALL_ARRAYS if name in meta.get("arrays", ()))


def _hasher():
    return hashlib.blake2b(digest_size=16)


def _feed(hasher, array) -> None:
    array = np.ascontiguousarray(array)
    hasher.update(f"{array.dtype.str}{array.shape}".encode())
    hasher.update(array.data)


def object_key(mesh: Mesh) -> str:
    """Hash of what places an object's samples and what its rays can hit; kept on the mesh
    for as long as it holds the same arrays and layout (a bake asks twice: for the kept
    preparation's key and the table's, 35 ms each on a 200k-triangle mesh)."""
    inputs = (mesh.positions, mesh.triangles, mesh.mode, mesh.corner_normals, mesh.uv_maps.get(mesh.bake_uv_map),
              tuple(int(r) for r in mesh.resolution))
    kept = getattr(mesh, "_object_key", None)
    if kept is not None and all(a is b or not isinstance(a, np.ndarray) and not isinstance(b, np.ndarray) and a == b
                                for a, b in zip(kept[0], inputs)):
        return kept[1]
    key = _object_key(mesh)
    mesh._object_key = (inputs, key)
    return key


def _object_key(mesh: Mesh) -> str:
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
                       "footprint_width": settings.footprint_width,
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


def _digest(name: str, array: np.ndarray, step_bytes: int | None = None, each=None) -> str:
    """CRC-32 over an array's name, dtype, shape and bytes: a check against damage, not
    tampering, at disk speed (a cryptographic hash of a 700 MB table costs a second more).
    One per array, so that each can be read and checked on its own.

    With ``step_bytes``, the bytes are taken that many at a time and ``each(step)`` (if given)
    is called with each step's bytes (uint8) after it is summed: the table's writer writes
    them, and both it and the mapped reader hand the pages read back."""
    array = np.ascontiguousarray(array)
    crc = zlib.crc32(f"{name}{array.dtype.str}{array.shape}".encode())
    data = array.reshape(-1).view(np.uint8)
    step_bytes = step_bytes or max(len(data), 1)
    for start in range(0, len(data), step_bytes):
        step = data[start:start + step_bytes]
        crc = zlib.crc32(step, crc)
        if each is not None:
            each(step)
    return f"crc32:{crc:08x}"


class CorruptCache(Exception):
    """A cache file that cannot be trusted; the message says why."""


class CacheFull(Exception):
    """A table that the cache folder's cap leaves no room for; the message says why."""


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


# Bytes of an array written (and checksummed) between calls to _save_npz's ``release``.
WRITE_STEP_BYTES = 64 << 20


# The member's data starts at a multiple of this in the file (numpy pads its own header to 64
# bytes), so that a reader can map the arrays in place (_mapped_arrays).
MEMBER_ALIGN = 64
# The zip extra field that pads a member's local header (an id of our own: readers skip it).
_PADDING_EXTRA_ID = 0x5650


def _aligned_member(name: str, offset: int) -> zipfile.ZipInfo:
    """A stored member ``name`` whose local header, written at ``offset`` with a zip64 extra
    (20 bytes, ``force_zip64``), ends at a multiple of MEMBER_ALIGN: its extra field is padded."""
    info = zipfile.ZipInfo(name, date_time=time.localtime()[:6])
    info.compress_type = zipfile.ZIP_STORED
    fixed = offset + 30 + len(name.encode()) + 4 + 20
    pad = -fixed % MEMBER_ALIGN
    info.extra = struct.pack("<HH", _PADDING_EXTRA_ID, pad) + bytes(pad)
    return info


def _save_npz(stream, arrays: dict, meta: dict, release=None) -> None:
    """``np.savez`` of ``arrays`` and then the header ``meta`` with every array's digest,
    the archive closed on every exit (numpy leaves its ZipFile open when interrupted, and its
    finaliser then prints 'Exception ignored in ZipFile.__del__'). An array given as a callable
    is made when its turn comes and dropped once written, so a table's large arrays are never
    all in memory at once; the header goes last because the digests are known only then.

    Each array is checksummed and written in steps of WRITE_STEP_BYTES, ``release()`` (if
    given) called after each: a table held in a scratch file hands back the pages read
    (TableEntries.release), so the write never holds the whole table resident. The arrays of
    _DEFLATED_ARRAYS (tens of megabytes) are deflated whole; the others are stored, each
    member's data aligned to MEMBER_ALIGN bytes in the file."""
    digests = {}
    with zipfile.ZipFile(stream, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, array in arrays.items():
            array = np.asanyarray(array() if callable(array) else array)
            if array.dtype.hasobject:
                raise ValueError(f"{name}: object arrays are not stored")
            if not array.flags.c_contiguous:
                array = np.array(array, order="C")
            if name in _DEFLATED_ARRAYS:
                member = io.BytesIO()
                np.lib.format.write_array_header_1_0(member, np.lib.format.header_data_from_array_1_0(array))
                member.write(array.reshape(-1).view(np.uint8))
                digests[name] = _digest(name, array)
                archive.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=time.localtime()[:6]), member.getbuffer(),
                                 compress_type=zipfile.ZIP_DEFLATED, compresslevel=1)
                del member, array
                continue
            with archive.open(_aligned_member(f"{name}.npy", stream.tell()), "w", force_zip64=True) as member:
                np.lib.format.write_array_header_1_0(member, np.lib.format.header_data_from_array_1_0(array))

                def write(step, member=member):
                    member.write(step)
                    if release is not None:
                        release()

                digests[name] = _digest(name, array, WRITE_STEP_BYTES, write)
            del array
        header = {**meta, "format": FORMAT_VERSION, "digests": digests}
        with archive.open("meta.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array(member, np.frombuffer(json.dumps(header).encode(), np.uint8),
                                      allow_pickle=False)


# Test hook (tests/blender/test_hostile_cache.py): with this variable naming a FIFO, a write
# stops once its half-written file exists and is locked, says so on stderr, and waits for the
# FIFO to be opened and closed, so that a signal sent then lands inside the write for certain.
HOLD_WRITE_VARIABLE = "VISIBAKE_TEST_HOLD_CACHE_WRITE"


def _hold_for_test(temporary: str) -> None:
    fifo = os.environ.get(HOLD_WRITE_VARIABLE)
    if fifo:
        print(f"visibake: test hook: holding the write of {os.path.basename(temporary)}", file=sys.stderr,
              flush=True)
        with open(fifo, "rb") as stream:
            stream.read()


def _write(path: str, meta: dict, arrays: dict, release=None) -> int:
    """Write atomically (a reader never sees half a file); returns the size in bytes.
    ``arrays``: name -> array, or a callable making it; ``release``: see :func:`_save_npz`."""
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=WRITING_PREFIX, suffix=".npz", dir=folder)
    try:
        with os.fdopen(handle, "wb") as stream:
            _lock(stream)
            _hold_for_test(temporary)
            _save_npz(stream, arrays, meta, release)
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
    "volume_table": {"volume": str, "written": str},
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
    estimated_bytes: int = 0  # the table's size on disk, known before it is written
    not_cached: str = ""  # why the table was not written, where the folder's cap left no room
    evicted: list = field(default_factory=list)  # [{"slot", "bytes"}] removed by the cap to make room


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

    def __init__(self, folder: str, label: str = "untitled", read_only: bool = False, limit_bytes: int = 0):
        self.folder = os.path.abspath(folder)
        self.label = _safe_label(label)
        # The folder's total size may not exceed this (0: no cap); see make_room.
        self.limit_bytes = max(int(limit_bytes), 0)
        # Slots removed by the cap in this bake: [(slot folder, bytes)], for the report.
        self.evicted: list[tuple[str, int]] = []
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
        small = _read_arrays(path, meta, _small_arrays(meta))
        samples = len(small["traced_per_sample"])

        def read_large():
            try:
                return {"entries": _read_entries(path, meta, samples)}
            except CorruptCache as error:
                if damaged is None:
                    raise
                return damaged(error)

        self._touch(path)
        stored = int(np.sum(small["traced_per_sample"], dtype=np.int64))
        nbytes = entries_nbytes(len(small["directions"]), samples, stored)
        return DeferredTable(small, meta["counters"], read_large, nbytes)

    def load_table(self, settings: BakeSettings, meta: dict) -> CachedTable:
        path = self.table_path(settings)
        arrays = _read_arrays(path, meta, _small_arrays(meta))
        entries = _read_entries(path, meta, len(arrays["traced_per_sample"]))
        self._touch(path)
        return CachedTable(arrays={**arrays, "entries": entries}, object_names=list(meta["object_names"]),
                           object_keys=list(meta["object_keys"]),
                           sample_offset=np.asarray(meta["sample_offset"], np.int64), counters=meta["counters"])

    def _touch(self, path: str) -> None:
        """Mark a file as just used: the folder's cap removes the least recently used slots first."""
        if not self.read_only:
            try:
                os.utime(path)
            except OSError:
                pass

    def save_table(self, settings: BakeSettings, key: str, object_names: list, object_keys: list,
                   sample_offset: np.ndarray, table, announce=None) -> int:
        """Write the slot's table; returns its size in bytes, 0 where nothing was written (a
        read-only cache). ``announce(bytes)``, if given, is told the stored arrays' size before
        anything is written. Raises :class:`CacheFull` where the folder's cap leaves it no room."""
        if self.read_only:
            return 0
        self._remove_abandoned(settings)
        stored = pack_entries(table)
        size = sum(array.nbytes for array in stored.values())
        if announce is not None:
            announce(size)
        self.make_room(settings, size)
        meta = {"kind": "table", "key": key, "object_names": list(object_names), "object_keys": list(object_keys),
                "sample_offset": [int(x) for x in sample_offset],
                "counters": {"rays_cast": int(table.rays_cast), "rays_below_horizon": int(table.rays_below_horizon),
                             "backface_hits": int(table.backface_hits)},
                "written": time.strftime("%Y-%m-%dT%H:%M:%S")}
        arrays = {name: getattr(table, name) for name in _SMALL_TABLE_ARRAYS}
        if table.vertex_cells is not None:
            arrays["vertex_cells"] = np.asarray(table.vertex_cells, np.int64)
        arrays.update(stored)
        meta["arrays"] = sorted(arrays)
        size = _write(self.table_path(settings), meta, arrays, table.entries.release)
        self.clear_lighting(settings)  # results of the old table are of no use any more
        return size

    def make_room(self, settings: BakeSettings, incoming: int, replacing: bool = True) -> None:
        """Remove the least recently used slots (of any scene in the folder) until a file of
        ``incoming`` bytes fits under the cap; raise :class:`CacheFull`, removing nothing, where
        it cannot fit. This bake's own slot is never removed: with ``replacing`` (a new table)
        its old files are about to be replaced, and count as free.

        Only VisiBake's own files are removed (tables and lighting results in slot folders),
        never a slot that a live bake is writing into, and never anything else in the folder.
        """
        self._make_room(self.slot(settings), incoming, replacing)

    def _make_room(self, own: str, incoming: int, replacing: bool) -> None:
        """:meth:`make_room` for the slot folder ``own``."""
        if self.limit_bytes <= 0:
            return
        replaced = sum(_size(path) for path in _slot_files(own)) if replacing else 0
        total = folder_size(self.folder)
        excess = total - replaced + incoming - self.limit_bytes
        if excess <= 0:
            return
        candidates = []
        for slot in _slot_folders(self.folder):
            if slot == own or _being_written(slot, self.opened):
                continue
            files = _slot_files(slot)
            if files:
                candidates.append((max(_mtime(path) for path in files), slot, sum(_size(path) for path in files)))
        candidates.sort()
        chosen, freed = [], 0
        for _, slot, size in candidates:
            if freed >= excess:
                break
            chosen.append((slot, size))
            freed += size
        if freed < excess:
            raise CacheFull(f"the table's {incoming / 2**20:.0f} MiB do not fit under the cache folder's cap of "
                            f"{self.limit_bytes / 2**20:.0f} MiB (the folder holds {total / 2**20:.0f} MiB, "
                            f"{(total - replaced - freed) / 2**20:.0f} MiB of it not removable: this table's "
                            "other files, bakes being written, or files that are not VisiBake's)")
        for slot, size in chosen:
            for path in _slot_files(slot):
                try:
                    os.remove(path)
                except OSError:
                    pass
            try:
                os.rmdir(slot)  # only if nothing else is left in it
            except OSError:
                pass
            self.evicted.append((slot, size))

    def volume_slot(self, slot_key: str) -> str:
        """The slot folder of one volume's tables (``slot_key``: hex, core.volume.cache.slot_key)."""
        return os.path.join(self.folder, f"{self.label}-{slot_key[:12]}")

    def load_volume_tables(self, slot: str, key: str) -> tuple[dict, dict] | None:
        """(header, arrays) of the volume tables in ``slot`` if they were stored under ``key``,
        else None; raises CorruptCache for a file that cannot be trusted (which it removes)."""
        return self._load_keyed(os.path.join(slot, VOLUME_TABLE_FILE), "volume_table", key)

    def _load_keyed(self, path: str, kind: str, key: str) -> tuple[dict, dict] | None:
        """(header, arrays) of the ``kind`` file at ``path`` if it was stored under ``key``, else
        None, marked as just used; raises CorruptCache for a file that cannot be trusted, which
        it removes (unless read-only)."""
        if not os.path.exists(path):
            return None
        try:
            meta = _read_meta(path, kind)
            if meta["key"] != key:
                return None
            arrays = _read_arrays(path, meta, meta["arrays"])
        except CorruptCache:
            if not self.read_only:
                os.remove(path)
            raise
        self._touch(path)
        return meta, arrays

    def save_volume_tables(self, slot: str, key: str, volume: str, arrays: dict) -> int:
        """Write a volume's tables into ``slot``, replacing what it held; returns the bytes
        written (0: a read-only cache). Raises CacheFull where the cap leaves no room."""
        if self.read_only:
            return 0
        self.abandoned_removed += remove_abandoned_writes(slot, self.opened)
        self._make_room(slot, sum(np.asarray(a).nbytes for a in arrays.values()), replacing=True)
        meta = {"kind": "volume_table", "key": key, "volume": volume, "arrays": sorted(arrays),
                "written": time.strftime("%Y-%m-%dT%H:%M:%S")}
        return _write(os.path.join(slot, VOLUME_TABLE_FILE), meta, arrays)

    def discard_table(self, settings: BakeSettings) -> None:
        path = self.table_path(settings)
        if not self.read_only and os.path.exists(path):
            os.remove(path)

    def _lighting_path(self, settings: BakeSettings, key: str) -> str:
        return os.path.join(self.slot(settings), f"{LIGHTING_PREFIX}{key}.npz")

    def load_lighting(self, settings: BakeSettings, key: str) -> dict | None:
        """Transport arrays stored under ``key``; None if absent or not trustworthy."""
        try:
            found = self._load_keyed(self._lighting_path(settings, key), "lighting", key)
        except CorruptCache:
            return None
        return None if found is None else found[1]

    def save_lighting(self, settings: BakeSettings, key: str, arrays: dict) -> None:
        if self.read_only:
            return
        self._remove_abandoned(settings)
        try:
            self.make_room(settings, sum(np.asarray(a).nbytes for a in arrays.values()), replacing=False)
        except CacheFull:
            return  # a lighting result only saves a later bake some transport: skip it, as without a cache
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


_SLOT_NAME = re.compile(r"^[A-Za-z0-9._-]+-[0-9a-f]{12}$")


def _listed(folder: str, keep) -> list[str]:
    """The paths of the entries of ``folder`` whose name passes ``keep(folder, name)`` ([] if unreadable)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return [os.path.join(folder, name) for name in names if keep(folder, name)]


def _slot_folders(folder: str) -> list[str]:
    """The slot folders (VisibilityCache.slot's names) directly in ``folder``."""
    return _listed(folder, lambda where, name: bool(_SLOT_NAME.match(name))
                   and os.path.isdir(os.path.join(where, name)))


def _slot_files(slot: str) -> list[str]:
    """The files VisiBake keeps in a slot folder (its table and lighting results), existing ones only."""
    return _listed(slot, lambda _, name: name in (TABLE_FILE, VOLUME_TABLE_FILE)
                   or (name.startswith(LIGHTING_PREFIX) and name.endswith(".npz")))


def _being_written(slot: str, before: float) -> bool:
    """Whether a live bake is writing into ``slot`` (a half-written file that is not abandoned)."""
    return any(not _abandoned(path, before)
               for path in _listed(slot, lambda _, name: name.startswith(WRITING_PREFIX)))


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _mtime(path: str) -> float:
    try:
        return os.path.getmtime(path)
    except OSError:
        return 0.0


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
