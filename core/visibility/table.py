"""The visibility bake: the paper's scattering textures S_i for every sample.

For every sample p and every direction d_i above p's geometric horizon one ray is
traced; the table stores where it lands as a continuous coordinate in the hit
object's atlas (so later lookups filter bilinearly), or a code for why it holds no
landing point. Directions below the horizon are never traced.
"""
from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from .. import kernels
from .. import tolerances as tol
from .rays import RayScene, run_in_spans, run_together
from .scratch import ScratchArrays, mapped_layout

MISS = -1
BELOW_HORIZON = -2
BACKFACE = -3

# Table entries are stored compact, 8 bytes each (only those above the horizon: TableEntries):
# the object (int16), the landing point's atlas coordinate as two 16-bit fractions of the
# atlas (1/16 texel at 4096^2; a vertex-mode hit's triangle and barycentrics the same way) and the hit
# distance as a 16-bit logarithmic code. The code spans 2^-16 to 2^16 scene units with a
# relative step of 2^(1/2048) - 1 = 3.4e-4 at every scale, where a half float would lose
# precision below 6e-5 units and overflow above 65504 (millimetre tiles and kilometre
# terrains alike); the top code means "nothing hit".
UV_CODE_SCALE = 65535
_UV_STEP = np.float32(1.0 / UV_CODE_SCALE)
DISTANCE_CODES_PER_OCTAVE = 2048
DISTANCE_LOWEST_OCTAVE = -16
NO_HIT_DISTANCE_CODE = 65535
# Every code's distance: decoding is one lookup.
_DISTANCE_VALUES64 = np.exp2(np.arange(NO_HIT_DISTANCE_CODE, dtype=np.float64) / DISTANCE_CODES_PER_OCTAVE
                             + DISTANCE_LOWEST_OCTAVE)
DISTANCE_VALUES = np.append(_DISTANCE_VALUES64, np.inf).astype(np.float32)
# A distance's code is decided by comparisons against the geometric midpoints between
# neighbouring codes (a logarithm at most guesses where to start), so numpy and the compiled
# kernels encode bitwise alike on every platform.
DISTANCE_SPLITS = np.sqrt(_DISTANCE_VALUES64[:-1] * _DISTANCE_VALUES64[1:])


def encode_uv(uv: np.ndarray) -> np.ndarray:
    """(..., 2) float atlas coordinates (or barycentrics) in [0, 1] -> uint16 codes (clamped)."""
    with np.errstate(invalid="ignore"):
        return np.rint(np.clip(np.nan_to_num(np.asarray(uv, np.float64)), 0.0, 1.0) * UV_CODE_SCALE).astype(np.uint16)


def decode_uv(codes: np.ndarray) -> np.ndarray:
    """uint16 codes -> float32 coordinates, computed as the kernels compute them."""
    return np.asarray(codes).astype(np.float32) * _UV_STEP


# A vertex-mode hit keeps its triangle and barycentrics in the same two 16-bit codes: the
# object's triangles are laid out as cells of a square grid (``vertex_cells`` per row), each
# cell ``65536 // cells`` codes wide, and the barycentrics (u, v) are rounded to that cell's
# steps. A table with vertex-mode objects then costs 8 bytes an entry like any other, where a
# separate int32 triangle would add 4 bytes to every entry of the table (most of which never hit
# that object). A barycentric step is 1/1819 of the triangle at 1280 triangles, 1/64 at a million
# (a million-triangle object's triangle is as small as a texel of a 1024^2 atlas, whose code step
# is 1/64 texel), and never coarser than 1/15.
VERTEX_MIN_STEPS = 16
MAX_VERTEX_TRIANGLES = (65536 // VERTEX_MIN_STEPS) ** 2


def vertex_cells(triangle_counts: np.ndarray, vertex_object: np.ndarray | None) -> np.ndarray | None:
    """(O,) int64 cells per grid row of each vertex-mode object (0 for atlas objects), from the
    objects' triangle counts (O,); None when no object is in vertex mode.

    Raises ValueError for a vertex-mode object of more than MAX_VERTEX_TRIANGLES triangles."""
    if vertex_object is None or not np.any(vertex_object):
        return None
    counts = np.asarray(triangle_counts, np.int64)
    vertex_object = np.asarray(vertex_object, bool)
    too_many = vertex_object & (counts > MAX_VERTEX_TRIANGLES)
    if np.any(too_many):
        raise ValueError(f"a vertex-mode object has {int(counts[too_many].max())} triangles; vertex mode takes at "
                         f"most {MAX_VERTEX_TRIANGLES} per object (bake it as an atlas)")
    cells = np.ceil(np.sqrt(np.maximum(counts, 1))).astype(np.int64)
    cells = np.where(cells * cells < counts, cells + 1, cells)  # sqrt's rounding at perfect squares
    return np.where(vertex_object, cells, 0)


def encode_vertex_hit(triangle: np.ndarray, bary: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(n,) triangle indices within their object, (n, 2) float barycentrics (u, v) and (n,) the
    object's cells per row (:func:`vertex_cells`) -> (n, 2) uint16 codes."""
    cells = np.asarray(cells, np.int64)
    steps = 65536 // cells
    triangle = np.asarray(triangle, np.int64)
    with np.errstate(invalid="ignore"):
        rounded = np.rint(np.clip(np.nan_to_num(np.asarray(bary, np.float64)), 0.0, 1.0)
                          * (steps - 1)[:, None]).astype(np.int64)
    cell = np.stack([triangle % cells, triangle // cells], axis=1)
    return (cell * steps[:, None] + rounded).astype(np.uint16)


def decode_vertex_hit(codes: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) uint16 codes of vertex-mode hits and (n,) their objects' cells per row -> the
    triangles (n,) int64 and barycentrics (n, 2) float32, computed as the kernels compute them."""
    cells = np.asarray(cells, np.int64)
    steps = (65536 // cells)[:, None]
    codes = np.asarray(codes, np.int64)
    cell, rounded = codes // steps, codes % steps
    bary = rounded.astype(np.float32) / (steps - 1).astype(np.float32)
    return cell[:, 0] + cells * cell[:, 1], bary


def encode_distance(distance: np.ndarray) -> np.ndarray:
    """Hit distances (float, inf: nothing hit) -> uint16 codes of the nearest stored distance."""
    distance = np.asarray(distance, np.float64)
    codes = np.searchsorted(DISTANCE_SPLITS, distance)
    return np.where(np.isfinite(distance), codes, NO_HIT_DISTANCE_CODE).astype(np.uint16)


def decode_distance(codes: np.ndarray) -> np.ndarray:
    """uint16 codes -> float32 distances (inf where nothing was hit)."""
    return DISTANCE_VALUES[codes]


# The least distance each code stands for (float64): a point that far along the ray lies on the
# ray's side of the surface it hit, never behind it.
_DISTANCE_FLOORS = np.concatenate([[0.0], DISTANCE_SPLITS, [np.inf]])


def decode_distance_floor(codes: np.ndarray) -> np.ndarray:
    """uint16 codes -> the least float64 distance that has that code (inf where nothing was hit)."""
    return _DISTANCE_FLOORS[codes]


# The stored entries are those above their sample's horizon (about half of the table): a bit per
# (direction, sample) says which, in 64-bit words, and the entries themselves are listed row by
# row (direction-major, samples ascending). Entry (i, k) is found as its word's first entry plus
# the set bits below k's bit (core.kernels.bits.entry_of), so no reader needs the dense
# (directions, samples) arrays, whose unstored half cost 4 bytes an entry for nothing.
WORD_BITS = 64
# Popcounts of every byte, for the numpy side (numpy 1.26 has no bit count).
_BYTE_BITS = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.uint8)
# Each per-entry array's dtype, the shape of one entry, and what a dense view shows where no
# entry is stored.
ENTRY_ARRAYS = {"hit_object": (np.int16, (), BELOW_HORIZON), "hit_uv_code": (np.uint16, (2,), 0),
                "hit_distance_code": (np.uint16, (), NO_HIT_DISTANCE_CODE)}
ENTRY_BYTES = 8
# A pass over a table held in a scratch file hands its pages back after about this many bytes
# of entries (TableEntries.release): what it keeps resident, against one system call per step.
RELEASE_BYTES = 16 << 20


def words_of(mask: np.ndarray) -> np.ndarray:
    """(N, k) bool -> (N, ceil(k / 64)) uint64: bit b of word w is mask[:, 64 w + b]."""
    mask = np.asarray(mask, bool)
    width = -(-mask.shape[1] // WORD_BITS)
    packed = np.zeros((mask.shape[0], width * 8), np.uint8)
    packed[:, :-(-mask.shape[1] // 8)] = np.packbits(mask, axis=1, bitorder="little")
    return packed.view("<u8").astype(np.uint64, copy=False)


def mask_of(words: np.ndarray, samples: int) -> np.ndarray:
    """:func:`words_of` undone: (n, W) uint64 -> (n, samples) bool."""
    words = np.ascontiguousarray(words, "<u8")
    return np.unpackbits(words.view(np.uint8).reshape(words.shape[0], words.shape[1] * 8), axis=1, count=samples,
                         bitorder="little").view(bool)


def bit_counts(words: np.ndarray) -> np.ndarray:
    """(..., W) uint64 -> (..., W) int64 set bits of each word."""
    words = np.ascontiguousarray(words, "<u8")
    return _BYTE_BITS[words.view(np.uint8)].reshape(*words.shape, 8).sum(axis=-1, dtype=np.int64)


@dataclass
class TableEntries:
    """The stored entries of a visibility table: those above their sample's horizon.

    samples : K, the samples of a row
    above_words : (N, W) uint64, W = ceil(K / 64); bit b of word w is set where sample
        64 w + b's entry of that direction is stored
    word_base : (N, W) int64, the index of each word's first stored entry
    hit_object : (A,) int16, hit_uv_code : (A, 2) uint16, hit_distance_code : (A,) uint16, the
        A stored entries row by row, samples ascending (the codes of :class:`VisibilityTable`)
    scratch : the :class:`~core.visibility.scratch.ScratchArrays` holding the three per-entry
        arrays, or None where they are in memory; a pass that has read a part of the table calls
        :meth:`release` to hand its pages back
    """

    samples: int
    above_words: np.ndarray
    word_base: np.ndarray
    hit_object: np.ndarray
    hit_uv_code: np.ndarray
    hit_distance_code: np.ndarray
    scratch: ScratchArrays | None = None

    @classmethod
    def empty(cls, above_words: np.ndarray, samples: int, scratch_folder: str | None = None) -> "TableEntries":
        """Room for the entries ``above_words`` (N, W) uint64 marks, to be written by a trace (every
        marked entry is written: their values start undefined). With ``scratch_folder``, a table
        of at least MIN_MAPPED_BYTES is held in a scratch file there (core.visibility.scratch), or
        in memory where that file cannot be made (``mapping_error`` of the result says why)."""
        above_words = np.ascontiguousarray(above_words, np.uint64)
        word_base, stored = _word_base(above_words)
        layout = {name: (dtype, (stored, *tail)) for name, (dtype, tail, _) in ENTRY_ARRAYS.items()}
        error = ""
        if scratch_folder is not None and mapped_layout(layout):
            try:
                scratch = ScratchArrays(scratch_folder, layout)
            except OSError as failure:
                error = f"{type(failure).__name__}: {failure}"
            else:
                return cls(int(samples), above_words, word_base, **scratch.arrays, scratch=scratch)
        entries = cls(int(samples), above_words, word_base,
                      **{name: np.empty(shape, dtype) for name, (dtype, shape) in layout.items()})
        entries.mapping_error = error
        return entries

    mapping_error = ""  # why a table meant for a scratch file is in memory (see empty)

    def release(self) -> None:
        """Hand back the resident pages of a table held in a scratch file (nothing otherwise):
        called by each pass over the table once it is done with what it has read."""
        if self.scratch is not None:
            self.scratch.release()

    @classmethod
    def from_dense(cls, hit_object: np.ndarray, hit_uv_code: np.ndarray, hit_distance_code: np.ndarray
                   ) -> "TableEntries":
        """The entries of dense (N, K), (N, K, 2), (N, K) arrays: those not BELOW_HORIZON."""
        hit_object = np.asarray(hit_object, np.int16)
        stored = hit_object != BELOW_HORIZON
        above_words = words_of(stored)
        word_base, _ = _word_base(above_words)
        return cls(hit_object.shape[1], above_words, word_base, hit_object[stored],
                   np.asarray(hit_uv_code, np.uint16)[stored], np.asarray(hit_distance_code, np.uint16)[stored])

    @classmethod
    def from_stored(cls, above_words: np.ndarray, samples: int, arrays: dict) -> "TableEntries":
        """Entries from their stored arrays (``above_words`` and :data:`ENTRY_ARRAYS` in ``arrays``).
        Raises ValueError where they do not fit together."""
        above_words = np.ascontiguousarray(above_words)
        if above_words.dtype != np.uint64 or above_words.ndim != 2 or above_words.shape[1] != -(-samples // WORD_BITS):
            raise ValueError("its entry bits do not match its table's size")
        if samples % WORD_BITS and np.any(above_words[:, -1] >> np.uint64(samples % WORD_BITS)):
            raise ValueError("its entry bits mark samples the table does not have")
        word_base, stored = _word_base(above_words)
        for name, (dtype, tail, _) in ENTRY_ARRAYS.items():
            values = arrays.get(name)
            if values is None or values.dtype != dtype or values.shape != (stored, *tail):
                raise ValueError(f"its {name} does not match its entry bits")
        return cls(int(samples), above_words, word_base, *(arrays[name] for name in ENTRY_ARRAYS))

    @property
    def directions(self) -> int:
        return self.above_words.shape[0]

    @property
    def stored(self) -> int:
        return len(self.hit_object)

    @property
    def nbytes(self) -> int:
        return (self.above_words.nbytes + self.word_base.nbytes + self.hit_object.nbytes + self.hit_uv_code.nbytes
                + self.hit_distance_code.nbytes)

    def row_span(self, first: int, last: int) -> slice:
        """The stored entries of rows [first, last)."""
        if not self.above_words.shape[1]:
            return slice(0, 0)
        start = int(self.word_base[first, 0]) if first < self.directions else self.stored
        stop = int(self.word_base[last, 0]) if last < self.directions else self.stored
        return slice(start, stop)

    def mask(self, first: int = 0, last: int | None = None) -> np.ndarray:
        """(rows, K) bool of rows [first, last): which entries are stored."""
        return mask_of(self.above_words[first:last], self.samples)

    def dense(self, name: str, first: int = 0, last: int | None = None) -> np.ndarray:
        """Rows [first, last) of the per-entry array ``name`` as a dense (rows, K, ...) array, with
        the no-entry value (:data:`ENTRY_ARRAYS`) where nothing is stored. For tests, the numpy
        fallback and a direction batch's upload: a whole table's dense array is what this
        layout exists to avoid."""
        last = self.directions if last is None else min(last, self.directions)
        dtype, tail, fill = ENTRY_ARRAYS[name]
        mask = self.mask(first, last)
        out = np.full((*mask.shape, *tail), fill, dtype)
        out[mask] = getattr(self, name)[self.row_span(first, last)]
        return out

    def index(self, direction: np.ndarray, sample: np.ndarray) -> np.ndarray:
        """(n,) int64 indices of the entries (direction, sample) (n,) each; -1 where not stored."""
        direction = np.asarray(direction, np.int64)
        sample = np.asarray(sample, np.int64)
        word = self.above_words[direction, sample >> 6]
        bit = (sample & 63).astype(np.uint64)
        stored = ((word >> bit) & np.uint64(1)).astype(bool)
        below = word & ((np.uint64(1) << bit) - np.uint64(1))
        index = self.word_base[direction, sample >> 6] + bit_counts(below[:, None])[:, 0]
        return np.where(stored, index, -1)

    def per_sample(self, code: int) -> np.ndarray:
        """(K,) int32: for each sample, how many of its stored entries have hit_object ``code``;
        compiled where the kernels load, else a few rows at a time (a whole table's (N, K)
        mask would take a byte an entry)."""
        counts = np.zeros(self.samples, np.int32)
        module = kernels.compiled()
        if module is not None:
            if self.samples:
                kernels.run(module.count_per_sample, 0, self.above_words, self.word_base, self.hit_object,
                            np.int16(code), counts)
                self.release()
            return counts
        rows = max(1, (1 << 22) // max(self.samples, 1))
        for first in range(0, self.directions, rows):
            last = min(self.directions, first + rows)
            sample = np.nonzero(self.mask(first, last))[1]
            counts += np.bincount(sample[self.hit_object[self.row_span(first, last)] == code],
                                  minlength=self.samples).astype(np.int32)
        return counts


def _word_base(above_words: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, W) int64 index of each word's first entry (row-major running sum), and the total."""
    counts = bit_counts(above_words)
    base = np.zeros(counts.size, np.int64)
    if counts.size:
        np.cumsum(counts.reshape(-1)[:-1], out=base[1:])
    return base.reshape(counts.shape), int(counts.sum())


@dataclass
class VisibilityTable:
    """S_i[p] for all samples of all objects, one row per direction.

    directions : (N, 3) float64
    entries : :class:`TableEntries`, the entries above each sample's horizon. Per entry:
        hit_object, int16 object index, or MISS / BACKFACE (BELOW_HORIZON where none is stored);
        hit_uv_code, 2 uint16, atlas coordinate of the hit (:func:`encode_uv`; 0 where no hit);
        on a vertex-mode object, triangle and barycentrics (:func:`encode_vertex_hit`) instead;
        hit_distance_code, uint16 distance to the hit (:func:`encode_distance`;
        NO_HIT_DISTANCE_CODE where nothing was hit), so shadow fractions can ignore occluders
        beyond a local light
    vertex_cells : (O,) int64 per object, cells per row of a vertex-mode object's triangle
        grid (:func:`vertex_cells`; 0 for atlas objects); None when the scene has no
        vertex-mode object

    ``hit_object``, ``hit_uv_code`` and ``hit_distance_code`` are the dense (N, K), (N, K, 2),
    (N, K) arrays made on demand (:meth:`TableEntries.dense`): for tests and small tables only.
    """

    directions: np.ndarray
    entries: TableEntries
    vertex_cells: np.ndarray | None = None
    rays_cast: int = 0
    rays_below_horizon: int = 0
    backface_hits: int = 0
    backface_per_sample: np.ndarray | None = None  # (K,) int32
    traced_per_sample: np.ndarray | None = None  # (K,) int32

    @classmethod
    def from_dense(cls, directions, hit_object, hit_uv_code, hit_distance_code, vertex_cells=None,
                   **counters) -> "VisibilityTable":
        """A table from dense (N, K) / (N, K, 2) / (N, K) code arrays (entries BELOW_HORIZON are
        not stored)."""
        return cls(directions, TableEntries.from_dense(hit_object, hit_uv_code, hit_distance_code), vertex_cells,
                   **counters)

    def buried(self) -> np.ndarray:
        """(K,) bool: samples most of whose rays hit the back of a face.

        Such texels lie inside other geometry (a wall overlapping a floor slab);
        nobody sees them, and their backface hits say nothing about the scene.
        """
        return 2 * self.backface_per_sample > self.traced_per_sample

    @classmethod
    def from_values(cls, directions, hit_object, hit_uv, hit_distance, hit_triangle=None, vertex_cells=None,
                    **counters) -> "VisibilityTable":
        """A table from float coordinates (N, K, 2) and distances (N, K), encoded as stored; with
        ``vertex_cells`` (O,), the entries that hit a vertex-mode object take their triangle from
        ``hit_triangle`` (N, K) and their barycentrics from ``hit_uv``."""
        hit_object = np.asarray(hit_object, np.int16)
        codes = encode_uv(hit_uv)
        if vertex_cells is not None:
            vertex_cells = np.asarray(vertex_cells, np.int64)
            on_vertices = (hit_object >= 0) & (vertex_cells[np.maximum(hit_object, 0)] > 0)
            codes[on_vertices] = encode_vertex_hit(np.asarray(hit_triangle)[on_vertices],
                                                   np.asarray(hit_uv)[on_vertices],
                                                   vertex_cells[hit_object[on_vertices]])
        return cls.from_dense(directions, hit_object, codes, encode_distance(hit_distance), vertex_cells, **counters)

    @property
    def samples(self) -> int:
        return self.entries.samples

    @property
    def nbytes(self) -> int:
        return self.entries.nbytes

    @property
    def hit_object(self) -> np.ndarray:
        return self.entries.dense("hit_object")

    @property
    def hit_uv_code(self) -> np.ndarray:
        return self.entries.dense("hit_uv_code")

    @property
    def hit_distance_code(self) -> np.ndarray:
        return self.entries.dense("hit_distance_code")

    def entry_uv(self, entry: np.ndarray) -> np.ndarray:
        """The decoded atlas coordinates (n, 2) float32 of the stored entries ``entry`` (n,)."""
        return decode_uv(self.entries.hit_uv_code[entry])

    def entry_vertex(self, entry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The triangles (n,) int64 and barycentrics (n, 2) float32 of the stored entries
        ``entry`` (n,), every one of which must have hit a vertex-mode object."""
        objects = np.asarray(self.entries.hit_object[entry], np.int64).reshape(-1)
        return decode_vertex_hit(np.asarray(self.entries.hit_uv_code[entry]).reshape(-1, 2), self.vertex_cells[objects])

    def entry_distance(self, entry: np.ndarray) -> np.ndarray:
        """The decoded distances (float32, inf: nothing hit) of the stored entries ``entry``."""
        return decode_distance(self.entries.hit_distance_code[entry])

    def entry_distance_floor(self, entry: np.ndarray) -> np.ndarray:
        """The least distances (float64) the stored entries ``entry`` allow: where a point is
        placed on a surface from the stored distance (a code spans 3.4e-4 of it, and a point
        beyond the surface would be shadowed by it)."""
        return decode_distance_floor(self.entries.hit_distance_code[entry])


class DeferredTable:
    """A valid cached table whose entries (per sample and direction) are read from disk on
    first use, so a bake whose lighting comes from the cache never reads them.

    Has every field of :class:`VisibilityTable`; the small ones (directions, per-sample
    counts, counters) are there at once, ``buried`` and ``nbytes`` need no read.
    """

    LARGE = ("entries",)

    def __init__(self, small: dict, counters: dict, read_large, nbytes: int):
        self.directions = small["directions"]
        self.vertex_cells = small.get("vertex_cells")
        self.traced_per_sample = small["traced_per_sample"]
        self.backface_per_sample = small["backface_per_sample"]
        self.rays_cast = int(counters["rays_cast"])
        self.rays_below_horizon = int(counters["rays_below_horizon"])
        self.backface_hits = int(self.backface_per_sample.sum())
        self._read_large = read_large
        self._large = None
        self._nbytes = int(nbytes)
        self.read_seconds = 0.0

    @property
    def loaded(self) -> bool:
        return self._large is not None

    def load(self) -> None:
        if self._large is None:
            started = time.perf_counter()
            self._large = self._read_large()
            self.read_seconds = time.perf_counter() - started

    def __getattr__(self, name):
        if name in DeferredTable.LARGE:
            self.load()
            return self._large.get(name)
        raise AttributeError(name)

    def buried(self) -> np.ndarray:
        return 2 * self.backface_per_sample > self.traced_per_sample

    @property
    def samples(self) -> int:
        return len(self.traced_per_sample)

    hit_object = VisibilityTable.hit_object
    hit_uv_code = VisibilityTable.hit_uv_code
    hit_distance_code = VisibilityTable.hit_distance_code
    entry_uv = VisibilityTable.entry_uv
    entry_vertex = VisibilityTable.entry_vertex
    entry_distance = VisibilityTable.entry_distance
    entry_distance_floor = VisibilityTable.entry_distance_floor

    @property
    def nbytes(self) -> int:
        return self._nbytes


def entries_nbytes(directions: int, samples: int, stored: int) -> int:
    """Bytes of the :class:`TableEntries` of ``stored`` entries of a (directions, samples) table."""
    return directions * -(-samples // WORD_BITS) * 16 + stored * ENTRY_BYTES


def table_bytes(directions: int, samples: int) -> int:
    """Memory the table of ``samples`` samples can need, for refusing before allocating: every
    entry stored (a sample's horizon keeps about half), and the bits and word offsets."""
    return directions * samples * ENTRY_BYTES + directions * -(-samples // WORD_BITS) * 16


@dataclass(frozen=True)
class HitGeometry:
    """What turns a ray's hit into a table entry, for every object of the scene.

    corner_uv : (T, 3, 2) float32 bake-UV corners of all objects' triangles, concatenated
    triangle_offset : (objects,) int64 index of each object's first triangle in corner_uv
    face_normals : (T, 3) float64 unit face normals, concatenated like corner_uv
    vertex_object : (objects,) bool or None, objects whose hits keep triangle and
        barycentrics (:func:`encode_vertex_hit`) instead of an atlas coordinate
    """

    corner_uv: np.ndarray
    triangle_offset: np.ndarray
    face_normals: np.ndarray
    vertex_object: np.ndarray | None = None

    def vertex_cells(self) -> np.ndarray | None:
        """(objects,) int64 :func:`vertex_cells` of the objects (None without vertex-mode objects)."""
        counts = np.diff(np.append(self.triangle_offset, len(self.corner_uv)))
        return vertex_cells(counts, self.vertex_object)


def frame_vectors(vectors: np.ndarray, rotations: np.ndarray | None, group: np.ndarray | None) -> np.ndarray:
    """(K, 3) world ``vectors`` (K, 3) in each sample's frame of the direction set:
    ``rotations[group[k]]`` transposed times vector k (unchanged without rotations), so that
    d_i . frame_vector = (R d_i) . vector for the sample's rotated direction R d_i."""
    if rotations is None:
        return vectors
    # By chunks: each sample's rotation taken whole is (K, 3, 3) float64, 28 MiB at the demo's
    # 403k texels. Every row is its own product, so the chunks give the same bits.
    out = np.empty((len(vectors), 3), np.result_type(rotations, vectors))
    for first in range(0, len(vectors), FRAME_CHUNK):
        rows = slice(first, first + FRAME_CHUNK)
        out[rows] = np.einsum("kba,kb->ka", rotations[group[rows]], vectors[rows])
    return out


# Samples :func:`frame_vectors` turns at a time (about 5 MB of rotations).
FRAME_CHUNK = 1 << 16


@dataclass(frozen=True)
class TraceRequest:
    """One table to trace: the direction set, the samples, and where their hits land.

    directions : (N, 3) float64
    positions, geometric_normals : (K, 3) float64 of all samples, objects concatenated
    hits : HitGeometry of the scene's objects
    chunk_rays : rays per batch (bounds memory)
    footprint : (K, P, 3) float32 or None; direction i's ray of sample k starts from
        ``positions[k] + footprint[k, i % P]`` (a point of the texel's footprint), so the
        table averages the footprint; None: from the sample's position
    rotations : (G, 3, 3) float64 and group : (K,) int or None; sample k's direction i is
        ``rotations[group[k]] @ directions[i]`` (interleaved rotations of the set)
    scratch_folder : where a large table is held in a scratch file (TableEntries.empty), or
        None to hold it in memory
    """

    directions: np.ndarray
    positions: np.ndarray
    geometric_normals: np.ndarray
    hits: HitGeometry
    chunk_rays: int = 1 << 20
    footprint: np.ndarray | None = None
    rotations: np.ndarray | None = None
    group: np.ndarray | None = None
    scratch_folder: str | None = None

    def rows(self, start: int, stop: int) -> TraceRequest:
        """The request of samples [start, stop) only (0 <= start <= stop <= K): the per-sample
        arrays (positions, geometric_normals, footprint, group) sliced, everything else shared.

        Nothing a ray depends on is indexed by the sample's place in the whole set (a ray's
        footprint point is chosen by its direction, i % P; its rotation by ``group[k]``), so
        :func:`trace_table` of the rows equals columns [start, stop) of the whole table bitwise
        (:func:`concatenate_columns` joins them). The slices are views, not copies."""
        samples = len(self.positions)
        if not 0 <= start <= stop <= samples:
            raise ValueError(f"rows [{start}, {stop}) outside the request's {samples} samples")
        cut = slice(start, stop)
        return replace(self, positions=self.positions[cut], geometric_normals=self.geometric_normals[cut],
                       footprint=None if self.footprint is None else self.footprint[cut],
                       group=None if self.group is None else self.group[cut])

    def horizon_normals(self) -> np.ndarray:
        """(K, 3) the geometric normals in each sample's frame of the direction set: a
        direction d_i is above sample k's horizon where d_i . horizon_normals[k] > 0."""
        return frame_vectors(self.geometric_normals, self.rotations, self.group)

    def ray_directions(self, direction_index: np.ndarray, sample_index: np.ndarray) -> np.ndarray:
        """(n, 3) float32 world directions of the rays (direction_index, sample_index) (n,) each."""
        if self.rotations is None:
            return self.directions[direction_index].astype(np.float32)
        rotated = np.einsum("gab,nb->gna", self.rotations, self.directions)  # (G, N, 3)
        return rotated[self.group[sample_index], direction_index].astype(np.float32)

    def ray_origins(self, ray_scene: RayScene, direction_index: np.ndarray, sample_index: np.ndarray) -> np.ndarray:
        """(n, 3) origins of the rays (direction_index, sample_index) (n,) each, offset off the surface."""
        position = self.positions[sample_index]
        if self.footprint is not None:
            position = position + self.footprint[sample_index, direction_index % self.footprint.shape[1]]
        return ray_scene.ray_origins(position, self.geometric_normals[sample_index])

    def rays(self, ray_scene: RayScene, direction_index: np.ndarray, sample_index: np.ndarray,
             buffers: RayBuffers | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The rays (direction_index, sample_index) (n,) each as ``ray_scene`` traces them:
        origins (n, 3) float32 in its frame (:meth:`RayScene.intersect_local`) and directions
        (n, 3) float32; the same numbers as :meth:`ray_origins` and :meth:`ray_directions`.
        With ``buffers`` (holding at least n rays) the compiled set-up writes into them and
        returns views of them."""
        module = kernels.compiled()
        if module is None:
            origins = self.ray_origins(ray_scene, direction_index, sample_index)
            return (np.ascontiguousarray(ray_scene.local(origins), np.float32),
                    self.ray_directions(direction_index, sample_index))
        count = len(direction_index)
        if buffers is None:
            buffers = RayBuffers(count)
        origins, directions = buffers.origins[:count], buffers.directions[:count]
        direction_index = np.ascontiguousarray(direction_index, np.int64)
        sample_index = np.ascontiguousarray(sample_index, np.int64)
        set_up = self.ray_setup(ray_scene)
        run_in_spans(lambda a, b: set_up(direction_index[a:b], sample_index[a:b], origins[a:b], directions[a:b]),
                     count, ray_scene.threads)
        return origins, directions

    def ray_setup(self, ray_scene: RayScene):
        """The compiled set-up of this request's rays for ``ray_scene``, on the calling thread:
        ``set_up(direction_index, sample_index, origins, directions)`` writes the rays
        (direction_index, sample_index) (n,) int64 each into ``origins`` and ``directions``
        (n, 3) float32 as :meth:`rays` returns them. Releases the GIL: threads may run it on
        spans of their own at once. Needs the compiled kernels."""
        module = kernels.compiled()
        positions = np.ascontiguousarray(self.positions, np.float64)
        normals = np.ascontiguousarray(self.geometric_normals, np.float64)
        footprint = (np.zeros((len(self.positions), 0, 3), np.float32) if self.footprint is None
                     else np.ascontiguousarray(self.footprint, np.float32))
        point_of_direction = np.arange(len(self.directions), dtype=np.int64) % max(footprint.shape[1], 1)
        frame_directions, group, centre = self._frame_directions(), self._frame_group(), ray_scene.centre
        recentred = bool(centre.any())
        constants = (np.float32(tol.RAY_OFFSET_INT_SCALE), np.float32(tol.RAY_OFFSET_FLOAT_SCALE),
                     np.float32(tol.RAY_OFFSET_ORIGIN))

        def set_up(direction_index, sample_index, origins, directions):
            module.ray_setup(direction_index, sample_index, positions, footprint, point_of_direction, normals,
                             frame_directions, group, centre, *constants, origins, directions)
            if recentred:
                # RayScene.ray_origins returns world positions, which its queries move back: the same rounding.
                origins[:] = ((origins.astype(np.float64) + centre) - centre).astype(np.float32)

        return set_up

    def _frame_directions(self) -> np.ndarray:
        """(G, N, 3) float32 the directions of each rotation (G = 1 without rotations), as
        :meth:`ray_directions` rounds them."""
        if self.rotations is None:
            return np.ascontiguousarray(self.directions, np.float32)[None]
        # C order: the kernel is compiled for it (another layout would compile it again).
        return np.ascontiguousarray(np.einsum("gab,nb->gna", self.rotations, self.directions), np.float32)

    def _frame_group(self) -> np.ndarray:
        if self.group is None:
            return np.zeros(len(self.positions), np.int64)
        return np.ascontiguousarray(self.group, np.int64)

    def footprint_reach(self) -> float:
        """How far any ray starts from its sample's position (0 without a footprint)."""
        if self.footprint is None or not self.footprint.size:
            return 0.0
        return float(np.sqrt(np.max(np.einsum("kpd,kpd->kp", self.footprint, self.footprint))))


# Rays a thread of the trace sets up, traces and records at a time (SpanTracer): their arrays,
# embree's results among them, take about 1 MB, which stays in the core's cache.
SPAN_RAYS = 16384


class RayBuffers:
    """The arrays rays are listed, set up, traced and recorded in, for up to ``capacity`` rays:
    a span's, made once per thread of a trace (SpanTracer), or a chunk's, made once per update
    or numpy trace and reused by every chunk. Made per chunk, they met fresh pages every time,
    which on a virtual machine (about 1.6 microseconds a page) cost as long as the compiled ray
    set-up itself (docs/benchmarks.md, speed part 7). Pages are touched only as far as the
    largest chunk reaches, and only those arrays that are used.

    direction_index, sample_index, entry : (capacity,) int64; origins, directions : (capacity, 3)
    float32; hit_geometry, triangle : (capacity,) int32; bary : (capacity, 2) float32;
    distance : (capacity,) float32 (:meth:`RayScene.intersect_local`'s results).
    """

    def __init__(self, capacity: int):
        capacity = max(int(capacity), 1)
        self.capacity = capacity
        self.direction_index = np.empty(capacity, np.int64)
        self.sample_index = np.empty(capacity, np.int64)
        self.entry = np.empty(capacity, np.int64)
        self.origins = np.empty((capacity, 3), np.float32)
        self.directions = np.empty((capacity, 3), np.float32)
        self.hit_geometry = np.empty(capacity, np.int32)
        self.triangle = np.empty(capacity, np.int32)
        self.bary = np.empty((capacity, 2), np.float32)
        self.distance = np.empty(capacity, np.float32)

    def hits(self, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first ``count`` slots of the hit arrays, for RayScene.intersect_local's ``out``."""
        return self.hit_geometry[:count], self.triangle[:count], self.bary[:count], self.distance[:count]


def rays_where(mask: np.ndarray, start: int, buffers: RayBuffers | None = None, threads: int = 0
               ) -> tuple[np.ndarray, np.ndarray]:
    """The rays to trace of a chunk: ``np.nonzero(mask)`` of ``mask`` (N, k) bool (directions by
    the samples from ``start``: those above the horizon, or an update's rays to trace again),
    with ``start`` added to the samples. Returns (n,) int64 directions and samples in
    row-major order; compiled on ``threads`` (0: all cores), into ``buffers`` (views of them
    are returned) where given."""
    module = kernels.compiled()
    if module is None:
        direction_index, sample_index = np.nonzero(mask)
        return direction_index, sample_index + start
    per_row = np.count_nonzero(mask, axis=1)
    count = int(per_row.sum())
    if buffers is None or buffers.capacity < count:
        buffers = RayBuffers(count)
    row_offset = np.zeros(len(per_row), np.int64)
    np.cumsum(per_row[:-1], out=row_offset[1:])
    direction_index, sample_index = buffers.direction_index[:count], buffers.sample_index[:count]
    kernels.run(module.rays_where, threads, np.ascontiguousarray(mask), row_offset, np.int64(start),
                direction_index, sample_index)
    return direction_index, sample_index


def _record(entries: TableEntries, geometry: HitGeometry, ray_directions: np.ndarray, entry: np.ndarray,
            hit_geometry: np.ndarray, triangle: np.ndarray, bary: np.ndarray, distance: np.ndarray,
            where: np.ndarray | None = None, threads: int = 0) -> None:
    """Write traced rays into the table's stored entries ``entry`` (n,) int64: hits, backfaces,
    and (unless ``where``) misses.

    ``ray_directions`` (n, 3) are the rays' world directions, in the order of ``entry``.

    ``hit_geometry`` holds object indices (-1: miss). With ``where`` given, only
    those rays are written (an update that keeps the old entry elsewhere). ``threads``: the
    compiled kernel's (0: all cores).
    """
    if kernels.compiled() is None:
        _record_numpy(entries, geometry, ray_directions, entry, hit_geometry, triangle, bary, distance, where)
        return
    write = _recorder(entries, geometry)
    entry = np.ascontiguousarray(entry, np.int64)
    hit_geometry, triangle = np.ascontiguousarray(hit_geometry, np.int32), np.ascontiguousarray(triangle, np.int32)
    bary, distance = np.ascontiguousarray(bary, np.float32), np.ascontiguousarray(distance, np.float32)
    ray_directions = np.ascontiguousarray(ray_directions, np.float32)
    where = None if where is None else np.ascontiguousarray(where, bool)
    run_in_spans(lambda a, b: write(entry[a:b], hit_geometry[a:b], triangle[a:b], bary[a:b], distance[a:b],
                                    ray_directions[a:b], None if where is None else where[a:b]),
                 len(entry), threads)


def _recorder(entries: TableEntries, geometry: HitGeometry):
    """The compiled record of rays into ``entries``, on the calling thread:
    ``write(entry, hit_geometry, triangle, bary, distance, ray_directions, where, sample_index,
    first_sample, backfaces)`` takes :func:`_record`'s arrays, contiguous and of its dtypes,
    and where ``backfaces`` (m,) int32 is given adds each backface at its sample (n,) int64
    minus ``first_sample``. Releases the GIL: threads may run it at once on rays of their own
    (each ray owns its entry) with counts of their own."""
    module = kernels.compiled()
    cells = geometry.vertex_cells()
    cells = np.zeros(len(geometry.triangle_offset), np.int64) if cells is None else cells
    triangle_offset = np.ascontiguousarray(geometry.triangle_offset, np.int64)
    face_normals = np.ascontiguousarray(geometry.face_normals, np.float64)
    corner_uv = np.ascontiguousarray(geometry.corner_uv, np.float32)
    everywhere, uncounted, no_samples = np.zeros(0, bool), np.zeros(0, np.int32), np.zeros(0, np.int64)

    def write(entry, hit_geometry, triangle, bary, distance, ray_directions, where=None, sample_index=None,
              first_sample=0, backfaces=None):
        module.record(entries.hit_object, entries.hit_uv_code, entries.hit_distance_code, entry, hit_geometry,
                      triangle, bary, distance, ray_directions, triangle_offset, face_normals, corner_uv, cells,
                      everywhere if where is None else where, DISTANCE_SPLITS,
                      no_samples if sample_index is None else sample_index, np.int64(first_sample),
                      uncounted if backfaces is None else backfaces)

    return write


class SpanTracer:
    """Traces rays into a table's stored entries: each of ``ray_scene.threads`` threads takes
    spans of :data:`SPAN_RAYS` rays in turn and lists them (from the entry bits, for a range
    of samples), sets them up, traces them and records them before it takes the next.

    A span's arrays (about 1 MB) stay in its core's cache from one step to the next, no list
    of a whole chunk's rays is made, and no thread waits for the others until the last span.
    As four passes over a chunk of a million rays (its list, the set-up, embree, the record),
    each split between the threads, the same trace took 15-25% longer (docs/benchmarks.md,
    speed part 11): the rays' arrays went out to memory and back, and every pass waited for
    its slower thread. Where the compiled kernels do not load, the passes run one after the
    other, in numpy.

    Parameters
    ----------
    ray_scene : the scene to trace
    request : the table's request (its samples, directions, footprints and rotations)
    geometry : the hit geometry the entries are recorded against
    entries : the table's stored entries, written at the rays' entries
    """

    def __init__(self, ray_scene: RayScene, request: TraceRequest, geometry: HitGeometry, entries: TableEntries):
        self.ray_scene, self.request, self.geometry, self.entries = ray_scene, request, geometry, entries
        self.threads = ray_scene.threads
        self._module = kernels.compiled()
        if self._module is not None:
            self._set_up = request.ray_setup(ray_scene)
            self._write = _recorder(entries, geometry)
        self._buffers = [None] * self.threads

    def trace_samples(self, start: int, stop: int, backfaces: np.ndarray, buffers: RayBuffers | None = None) -> int:
        """Trace every stored entry of samples [start, stop) (``start`` a multiple of 64; ``stop``
        one too, or the last sample), adding each backface to ``backfaces`` (stop - start,) int32
        at its sample. ``buffers``: the numpy passes' arrays, for all the rays, where the compiled
        kernels do not load. Returns the number of rays traced."""
        entries = self.entries
        first_word, last_word = start // WORD_BITS, -(-stop // WORD_BITS)
        if self._module is None:
            direction_index, sample_index, entry = rays_of_entries(entries, first_word, last_word, buffers)
            self.trace(direction_index, sample_index, entry, buffers)
            back = entries.hit_object[entry] == BACKFACE
            backfaces += np.bincount(sample_index[back] - start, minlength=stop - start).astype(np.int32)
            return len(entry)
        row_offset, count = _row_offsets(entries, first_word, last_word)
        module, above, word_base = self._module, entries.above_words, entries.word_base

        def list_span(a, b, span):
            n = b - a
            direction_index, sample_index, entry = span.direction_index[:n], span.sample_index[:n], span.entry[:n]
            module.rays_of_span(above, word_base, first_word, last_word, row_offset, a, direction_index,
                                sample_index, entry)
            return direction_index, sample_index, entry

        counts = [np.zeros(stop - start, np.int32) for _ in range(self.threads)]
        self._run(count, list_span, counts, start)
        for thread_counts in counts:
            backfaces += thread_counts
        return count

    def trace(self, direction_index: np.ndarray, sample_index: np.ndarray, entry: np.ndarray,
              buffers: RayBuffers | None = None) -> None:
        """Trace the rays (direction_index, sample_index) (n,) int64 each into the stored entries
        ``entry`` (n,) int64; ``buffers`` (the numpy passes' arrays, for at least n rays) where
        the compiled kernels do not load."""
        count = len(entry)
        if not count:
            return
        if self._module is None:
            origins, ray_directions = self.request.rays(self.ray_scene, direction_index, sample_index, buffers)
            hit_geometry, triangle, bary, distance = self.ray_scene.intersect_local(
                origins, ray_directions, out=None if buffers is None else buffers.hits(count))
            _record_numpy(self.entries, self.geometry, ray_directions, entry, hit_geometry, triangle, bary, distance)
            return
        direction_index = np.ascontiguousarray(direction_index, np.int64)
        sample_index = np.ascontiguousarray(sample_index, np.int64)
        entry = np.ascontiguousarray(entry, np.int64)
        self._run(count, lambda a, b, span: (direction_index[a:b], sample_index[a:b], entry[a:b]))

    def _run(self, count: int, span_rays, backfaces: list | None = None, first_sample: int = 0) -> None:
        """Every span of rays [0, count) in turn on the threads: ``span_rays(a, b, buffers)`` gives
        rays [a, b)'s (direction_index, sample_index, entry), in the thread's buffers or not;
        ``backfaces``: one count per thread (:func:`_recorder`), or None."""
        spans = itertools.count()  # next() is atomic under the GIL: each span goes to one thread
        failed = threading.Event()

        def work(thread: int) -> None:
            if self._buffers[thread] is None:
                self._buffers[thread] = RayBuffers(SPAN_RAYS)
            span = self._buffers[thread]
            counts = None if backfaces is None else backfaces[thread]
            try:
                while not failed.is_set():
                    a = next(spans) * SPAN_RAYS
                    if a >= count:
                        return
                    b = min(count, a + SPAN_RAYS)
                    n = b - a
                    direction_index, sample_index, entry = span_rays(a, b, span)
                    origins, directions = span.origins[:n], span.directions[:n]
                    self._set_up(direction_index, sample_index, origins, directions)
                    found = self.ray_scene.intersect_here(origins, directions)
                    bary = span.bary[:n]
                    bary[:, 0] = found["u"]
                    bary[:, 1] = found["v"]
                    # A miss's distance is never read (its entry records the miss).
                    self._write(entry, found["geomID"], found["primID"], bary, found["tfar"], directions,
                                None, sample_index, first_sample, counts)
            except BaseException:
                failed.set()
                raise

        if self.threads == 1 or count <= SPAN_RAYS:
            work(0)
            return
        run_together([lambda thread=thread: work(thread) for thread in range(self.threads)])


def _record_numpy(entries: TableEntries, geometry: HitGeometry, ray_directions: np.ndarray, entry: np.ndarray,
                  hit_geometry: np.ndarray, triangle: np.ndarray, bary: np.ndarray, distance: np.ndarray,
                  where: np.ndarray | None = None) -> None:
    """:func:`_record` in numpy, where the compiled kernels cannot load."""
    if where is None:
        missed = entry[hit_geometry < 0]
        entries.hit_object[missed] = MISS
        entries.hit_uv_code[missed] = 0
        entries.hit_distance_code[missed] = NO_HIT_DISTANCE_CODE
        hit = hit_geometry >= 0
    else:
        hit = where & (hit_geometry >= 0)
    global_triangle = geometry.triangle_offset[hit_geometry[hit]] + triangle[hit]
    facing = np.einsum("kd,kd->k", geometry.face_normals[global_triangle], ray_directions[hit])
    back = facing > 0.0
    u = bary[hit, 0:1]
    v = bary[hit, 1:2]
    uv = geometry.corner_uv[global_triangle]
    landing = (1.0 - u - v) * uv[:, 0] + u * uv[:, 1] + v * uv[:, 2]
    codes = encode_uv(np.where(back[:, None], 0.0, landing))
    cells = geometry.vertex_cells()
    if cells is not None:
        # A vertex-mode object keeps where in the triangle the ray landed, not an atlas
        # coordinate: its light is the mix of the triangle's three samples.
        hit_cells = cells[hit_geometry[hit]]
        on_vertices = (hit_cells > 0) & ~back
        codes[on_vertices] = encode_vertex_hit(triangle[hit][on_vertices], bary[hit][on_vertices],
                                               hit_cells[on_vertices])
    written = entry[hit]
    entries.hit_object[written] = np.where(back, BACKFACE, hit_geometry[hit]).astype(np.int16)
    entries.hit_uv_code[written] = codes
    entries.hit_distance_code[written] = encode_distance(distance[hit])


def entries_at(entries: TableEntries, direction_index: np.ndarray, sample_index: np.ndarray,
               threads: int = 0) -> np.ndarray:
    """(n,) int64 the stored entries of (direction_index, sample_index) (n,) each, -1 where not
    stored; compiled where the kernels load (:meth:`TableEntries.index` otherwise)."""
    module = kernels.compiled()
    if module is None:
        return entries.index(direction_index, sample_index)
    out = np.empty(len(direction_index), np.int64)
    kernels.run(module.entries_at, threads, entries.above_words, entries.word_base,
                np.ascontiguousarray(direction_index, np.int64), np.ascontiguousarray(sample_index, np.int64), out)
    return out


def _finish(directions: np.ndarray, entries: TableEntries, traced_per_sample: np.ndarray, rays_cast: int,
            geometry: HitGeometry, backface_per_sample: np.ndarray | None = None) -> VisibilityTable:
    """The table of the traced ``entries``; ``backface_per_sample`` (K,) int32 where the trace
    counted it already, else counted here."""
    if backface_per_sample is None:
        backface_per_sample = entries.per_sample(BACKFACE)
    return VisibilityTable(directions=directions, entries=entries, vertex_cells=geometry.vertex_cells(),
                           rays_cast=rays_cast,
                           rays_below_horizon=entries.directions * entries.samples - int(traced_per_sample.sum()),
                           backface_hits=int(backface_per_sample.sum()), backface_per_sample=backface_per_sample,
                           traced_per_sample=traced_per_sample)


def table_from_arrays(arrays: dict, counters: dict) -> VisibilityTable:
    """A table from its stored arrays (see core.visibility.cache): its ``entries``
    (:class:`TableEntries`), directions, vertex_cells and the per-sample counts."""
    traced_per_sample = arrays["traced_per_sample"]
    entries = arrays["entries"]
    backface_per_sample = arrays.get("backface_per_sample")
    if backface_per_sample is None:
        backface_per_sample = entries.per_sample(BACKFACE)
    return VisibilityTable(directions=arrays["directions"], entries=entries, vertex_cells=arrays.get("vertex_cells"),
                           rays_cast=int(counters["rays_cast"]),
                           rays_below_horizon=int(counters["rays_below_horizon"]),
                           backface_hits=int(backface_per_sample.sum()), backface_per_sample=backface_per_sample,
                           traced_per_sample=traced_per_sample)


def _vertex_mask(vertex_object) -> np.ndarray | None:
    if vertex_object is None or not np.any(vertex_object):
        return None
    return np.asarray(vertex_object, bool)


def _word_chunk(count: int, chunk_rays: int) -> int:
    """Samples per batch of about ``chunk_rays`` entries of ``count`` directions: a whole number
    of 64-sample words, so that each batch owns its words of the entry bits."""
    return max(WORD_BITS, chunk_rays // max(count, 1) // WORD_BITS * WORD_BITS)


def above_horizon(directions: np.ndarray, horizon: np.ndarray, chunk_rays: int, threads: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Which entries lie above their sample's horizon: (N, W) uint64 entry bits (:class:`TableEntries`)
    and (K,) int32 how many per sample, for ``directions`` (N, 3) and ``horizon`` (K, 3)
    (TraceRequest.horizon_normals). Direction d lies above sample k's horizon where
    (d_x h_x + d_y h_y) + d_z h_z > 0 in float64, summed in that order by the compiled kernel
    and by numpy alike (a matrix product may sum in another order, or fuse, and decide a
    direction in the horizon's plane otherwise). numpy takes batches of about ``chunk_rays``
    entries (the whole (N, K) product would take 8 bytes an entry: gigabytes at Production
    settings). ``threads``: the compiled kernel's (0: all cores)."""
    directions = np.ascontiguousarray(directions, np.float64)
    horizon = np.ascontiguousarray(horizon, np.float64)
    samples = len(horizon)
    words = np.zeros((len(directions), -(-samples // WORD_BITS)), np.uint64)
    counts = np.zeros(samples, np.int32)
    module = kernels.compiled()
    if module is not None:
        kernels.run(module.horizon_bits, threads, directions, horizon, words, counts)
        return words, counts
    chunk = _word_chunk(len(directions), chunk_rays)
    for start in range(0, samples, chunk):
        stop = min(samples, start + chunk)
        part = horizon[start:stop]
        above = ((directions[:, 0:1] * part[:, 0] + directions[:, 1:2] * part[:, 1])
                 + directions[:, 2:3] * part[:, 2]) > 0.0
        counts[start:stop] = np.count_nonzero(above, axis=0)
        words[:, start // WORD_BITS:-(-stop // WORD_BITS)] = words_of(above)
    return words, counts


def _row_offsets(entries: TableEntries, first_word: int, last_word: int) -> tuple[np.ndarray, int]:
    """Where each row's rays start in the list of the stored entries of words [first_word,
    last_word) (row-major): (N,) int64, and how many there are."""
    start = entries.word_base[:, first_word]
    stop = (entries.word_base[:, last_word] if last_word < entries.above_words.shape[1]
            else np.append(entries.word_base[1:, 0], entries.stored))
    per_row = stop - start
    row_offset = np.zeros(len(per_row), np.int64)
    np.cumsum(per_row[:-1], out=row_offset[1:])
    return row_offset, int(per_row.sum())


def rays_of_entries(entries: TableEntries, first_word: int, last_word: int, buffers: RayBuffers | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays of the stored entries of samples [64 first_word, 64 last_word): (n,) int64
    directions, samples and entries, row-major (direction-major, samples ascending); compiled
    (one span of :func:`SpanTracer`'s list, the whole of it) into ``buffers`` where given (views
    of them are returned)."""
    above = entries.above_words
    row_offset, count = _row_offsets(entries, first_word, last_word)
    module = kernels.compiled()
    if module is None:
        mask = mask_of(above[:, first_word:last_word], min(entries.samples, last_word * WORD_BITS)
                       - first_word * WORD_BITS)
        direction_index, sample_index = np.nonzero(mask)
        entry = entries.word_base[direction_index, first_word] + np.arange(count) - row_offset[direction_index]
        return direction_index, sample_index + first_word * WORD_BITS, entry
    if buffers is None or buffers.capacity < count:
        buffers = RayBuffers(count)
    direction_index, sample_index = buffers.direction_index[:count], buffers.sample_index[:count]
    entry = buffers.entry[:count]
    module.rays_of_span(above, entries.word_base, first_word, last_word, row_offset, 0, direction_index,
                        sample_index, entry)
    return direction_index, sample_index, entry


def trace_table(ray_scene: RayScene, request: TraceRequest, progress=None) -> VisibilityTable:
    """Trace every (sample, direction) pair above the sample's horizon.

    Parameters
    ----------
    ray_scene : RayScene with one geometry per object, in object order
    request : the directions, the samples and the scene's hit geometry
    progress : callable(fraction) or None; may raise to cancel

    Returns
    -------
    VisibilityTable
    """
    directions, positions = request.directions, request.positions
    count = len(directions)
    samples = len(positions)
    hits = request.hits
    geometry = HitGeometry(hits.corner_uv, hits.triangle_offset, hits.face_normals, _vertex_mask(hits.vertex_object))
    above_words, traced_per_sample = above_horizon(directions, request.horizon_normals(), request.chunk_rays,
                                                   ray_scene.threads)
    entries = TableEntries.empty(above_words, samples, request.scratch_folder)
    chunk = _word_chunk(count, request.chunk_rays)
    rays_cast = 0
    written_since_release = 0
    backface_per_sample = np.zeros(samples, np.int32)
    # The numpy passes' arrays; the compiled trace lists and sets up its rays span by span.
    buffers = RayBuffers(min(chunk, samples) * count) if kernels.compiled() is None else None
    tracer = SpanTracer(ray_scene, request, geometry, entries)
    for start in range(0, samples, chunk):
        stop = min(samples, start + chunk)
        # Direction-major order: consecutive rays share a direction (coherent for embree) and
        # land in one row of the table (consecutive entries). Backfaces are counted as they
        # are recorded: over the whole table afterwards, this was a pass of 0.1 s on the demo.
        traced = tracer.trace_samples(start, stop, backface_per_sample[start:stop], buffers)
        rays_cast += traced
        written_since_release += traced
        if written_since_release * ENTRY_BYTES >= RELEASE_BYTES:
            entries.release()
            written_since_release = 0
        if progress is not None:
            progress(stop / samples)
    entries.release()
    return _finish(directions, entries, traced_per_sample, rays_cast, geometry, backface_per_sample)


def _ranks(entries: TableEntries, sample: int) -> np.ndarray:
    """(N,) int64: each row's index of its first stored entry at or after ``sample`` (0 <= sample <= K)."""
    if not entries.above_words.shape[1]:
        return np.zeros(entries.directions, np.int64)
    if sample >= entries.samples:
        return np.append(entries.word_base[1:, 0], entries.stored)
    word = entries.above_words[:, sample // WORD_BITS]
    below = word & np.uint64((1 << (sample % WORD_BITS)) - 1)
    return entries.word_base[:, sample // WORD_BITS] + bit_counts(below[:, None])[:, 0]


def _run_index(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The indices of the runs [starts[i], starts[i] + counts[i]) (N,) each, one after another."""
    total = int(counts.sum())
    ends = np.cumsum(counts)
    return np.arange(total, dtype=np.int64) + np.repeat(starts - (ends - counts), counts)


def copy_columns(source: TableEntries, source_start: int, target: TableEntries, target_start: int, count: int,
                 threads: int = 0) -> None:
    """Copy the stored entries of samples [source_start, +count) of ``source`` to samples
    [target_start, +count) of ``target``, whose entry bits there must be the same; compiled
    on ``threads`` (0: all cores) where the kernels load."""
    if count <= 0:
        return
    from_first, from_last = _ranks(source, source_start), _ranks(source, source_start + count)
    to_first = _ranks(target, target_start)
    runs = from_last - from_first
    if not np.array_equal(_ranks(target, target_start + count) - to_first, runs):
        raise ValueError("the columns' entry bits differ between the two tables")
    module = kernels.compiled()
    if module is not None:
        for name in ENTRY_ARRAYS:
            # The uv pairs as one uint32 each: every array copied is then one value an entry.
            to, of = getattr(target, name), getattr(source, name)
            if to.ndim == 2:
                to, of = to.view(np.uint32)[:, 0], of.view(np.uint32)[:, 0]
            kernels.run(module.copy_runs, threads, from_first, to_first, runs, of, to)
        return
    # One slice per row: a run of consecutive entries in both tables.
    for row in np.nonzero(runs)[0]:
        taken = slice(from_first[row], from_first[row] + runs[row])
        put = slice(to_first[row], to_first[row] + runs[row])
        for name in ENTRY_ARRAYS:
            getattr(target, name)[put] = getattr(source, name)[taken]


def column_mask(entries: TableEntries, start: int, stop: int) -> np.ndarray:
    """(N, stop - start) bool: which entries of samples [start, stop) are stored."""
    first_word = start // WORD_BITS
    mask = mask_of(entries.above_words[:, first_word:-(-stop // WORD_BITS)],
                   -(-stop // WORD_BITS) * WORD_BITS - first_word * WORD_BITS)
    return mask[:, start - first_word * WORD_BITS:stop - first_word * WORD_BITS]


def dense_columns(entries: TableEntries, name: str, start: int, stop: int, threads: int = 0) -> np.ndarray:
    """Samples [start, stop) of the per-entry array ``name`` as a dense (N, stop - start, ...)
    array (:meth:`TableEntries.dense`, by columns); compiled on ``threads`` (0: all cores) for
    one value an entry."""
    dtype, tail, fill = ENTRY_ARRAYS[name]
    module = kernels.compiled()
    if module is not None and not tail:
        out = np.full((entries.directions, stop - start), fill, dtype)
        kernels.run(module.entry_columns, threads, entries.above_words, entries.word_base, getattr(entries, name),
                    np.int64(start), np.int64(stop), out)
        return out
    mask = column_mask(entries, start, stop)
    out = np.full((*mask.shape, *tail), fill, dtype)
    first, last = _ranks(entries, start), _ranks(entries, stop)
    out[mask] = getattr(entries, name)[_run_index(first, last - first)]
    return out


def concatenate_columns(tables: list[VisibilityTable]) -> VisibilityTable:
    """One table from the tables of consecutive sample ranges of one request (traced from
    :meth:`TraceRequest.rows` in order): equal to the whole request's :func:`trace_table`.

    The entries are joined along the sample axis, row by row, and so are the (k,) int32
    per-sample counts; rays_cast, rays_below_horizon and backface_hits are summed; directions
    (N, 3) float64 and vertex_cells (O,) int64 (or None) are shared and must be equal in all.

    Raises ValueError for no table, or tables of different directions, vertex cells or
    counts of entries per sample."""
    tables = list(tables)
    if not tables:
        raise ValueError("no table to concatenate")
    first = tables[0]
    for table in tables[1:]:
        if not np.array_equal(table.directions, first.directions):
            raise ValueError("the tables were traced for different directions")
        if (table.vertex_cells is None) != (first.vertex_cells is None) or (
                first.vertex_cells is not None and not np.array_equal(table.vertex_cells, first.vertex_cells)):
            raise ValueError("the tables have different vertex-mode objects")
    for table in tables:
        if table.entries.directions != len(first.directions):
            raise ValueError(f"a table's entries do not have one row per direction: {table.entries.directions}")
        for name in ("traced_per_sample", "backface_per_sample"):
            per_sample = getattr(table, name)
            if per_sample is None or len(per_sample) != table.samples:
                raise ValueError(f"a table's {name} is missing or not one per sample")
    count = len(first.directions)
    samples = sum(table.samples for table in tables)
    words = np.zeros((count, -(-samples // WORD_BITS)), np.uint64)
    rows = max(1, (1 << 22) // max(samples, 1))
    for low in range(0, count, rows):
        high = min(count, low + rows)
        words[low:high] = words_of(np.concatenate([table.entries.mask(low, high) for table in tables], axis=1))
    joined = TableEntries.empty(words, samples)
    offset = 0
    for table in tables:
        copy_columns(table.entries, 0, joined, offset, table.samples)
        offset += table.samples

    def per_sample(name: str) -> np.ndarray:
        return np.concatenate([getattr(table, name) for table in tables])

    return VisibilityTable(directions=first.directions, entries=joined,
                           vertex_cells=first.vertex_cells, rays_cast=sum(int(t.rays_cast) for t in tables),
                           rays_below_horizon=sum(int(t.rays_below_horizon) for t in tables),
                           backface_hits=sum(int(t.backface_hits) for t in tables),
                           backface_per_sample=per_sample("backface_per_sample"),
                           traced_per_sample=per_sample("traced_per_sample"))


@dataclass
class UpdateCounts:
    """Rays an incremental update traced, for the bake report."""

    full: int = 0  # against the whole scene (changed objects' samples, entries that hit a changed object)
    changed_only: int = 0  # against the changed objects alone (could they now be in the way?)
    kept: int = 0  # entries of unchanged samples that no ray had to revisit


def _bounding_sphere(positions: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (3,) and radius of a sphere around the finite ``positions`` (n, 3), slightly enlarged."""
    finite = positions[np.all(np.isfinite(positions), axis=1)]
    if len(finite) == 0:
        return np.zeros(3), 0.0
    low, high = finite.min(axis=0), finite.max(axis=0)
    centre = (low + high) / 2
    radius = float(np.linalg.norm(high - low) / 2)
    return centre, radius * (1.0 + tol.CULL_SPHERE_MARGIN) + tol.CULL_SPHERE_MARGIN * float(np.abs(centre).max())


def _may_hit_spheres(origins: np.ndarray, directions: np.ndarray, spheres, request: TraceRequest | None = None,
                     cols: slice | None = None) -> np.ndarray:
    """(N, k) bool: whether the ray from origin k along direction i passes through any sphere.

    One matrix product per sphere: the squared distance from the centre to the ray's
    line is |v|^2 - (d . v)^2 with v = centre - origin; the sphere must not lie behind.
    With ``request``'s interleaved rotations, sample k's direction i is rotated: v is then
    taken into the sample's frame (d_i . R^T v = R d_i . v).
    """
    near = np.zeros((len(directions), len(origins)), bool)
    rotations = None if request is None else request.rotations
    group = None if rotations is None else request.group[cols]
    for centre, radius in spheres:
        v = centre - origins
        along = directions @ frame_vectors(v, rotations, group).T
        squared = np.einsum("kd,kd->k", v, v)
        near |= ((squared[None, :] - along * along) < radius * radius) & (along > -radius)
    return near


def update_table(old: VisibilityTable, old_offset: np.ndarray, sample_offset: np.ndarray, ray_scene: RayScene,
                 changed_scene: RayScene, changed: list[int], request: TraceRequest, progress=None):
    """The table after some objects changed, reusing every entry that cannot have changed.

    Unchanged objects' samples keep their positions and horizons, so an entry of theirs
    changes only if its ray used to hit a changed object (retraced against the whole
    scene), or if a changed object now lies nearer than the old hit (found by tracing
    against the changed objects alone, a far smaller BVH). Backface entries do not
    record their object and are always retraced. Samples of changed objects are traced
    from scratch. The result equals a fresh :func:`trace_table` of the new scene.

    Parameters
    ----------
    old : the table of the previous bake, same objects in the same order, same directions
    old_offset, sample_offset : (objects + 1,) int64 first sample of each object, old and new
    changed_scene : RayScene with the new geometry of the ``changed`` objects only, in that order
    changed : indices of the objects whose geometry, UVs or resolution changed
    request, progress : as :func:`trace_table`, for the new scene

    Returns
    -------
    table : VisibilityTable
    counts : UpdateCounts
    """
    directions, positions, geometric_normals = request.directions, request.positions, request.geometric_normals
    chunk_rays = request.chunk_rays
    count = len(directions)
    samples = len(positions)
    objects = len(sample_offset) - 1
    hits = request.hits
    geometry = HitGeometry(hits.corner_uv, hits.triangle_offset, hits.face_normals, _vertex_mask(hits.vertex_object))
    origins_all = ray_scene.ray_origins(positions, geometric_normals)
    horizon = request.horizon_normals()
    # The stored entries are those above the new horizons: a changed object's samples may store
    # others than before, so the entries are laid out anew and the unchanged samples' copied.
    above_words, traced_per_sample = above_horizon(directions, horizon, chunk_rays, ray_scene.threads)
    entries = TableEntries.empty(above_words, samples)
    is_changed = np.zeros(objects, bool)
    is_changed[list(changed)] = True
    retrace = is_changed.copy()
    for index in np.nonzero(~is_changed)[0]:
        try:
            copy_columns(old.entries, int(old_offset[index]), entries, int(sample_offset[index]),
                         int(sample_offset[index + 1] - sample_offset[index]), ray_scene.threads)
        except ValueError:
            retrace[index] = True  # its horizons moved after all: trace its samples afresh
    changed_map = np.asarray(changed, np.int32)
    # A ray starts up to the footprint's reach from its sample: widen the spheres by it.
    reach = request.footprint_reach()
    spheres = [(centre, radius + reach) for centre, radius in
               (_bounding_sphere(changed_scene.positions(i) + changed_scene.centre) for i in range(len(changed)))]
    counts = UpdateCounts()
    chunk = max(1, chunk_rays // max(count, 1))
    spans = []
    for index in range(objects):
        a, b = int(sample_offset[index]), int(sample_offset[index + 1])
        spans.extend((index, start, min(b, start + chunk)) for start in range(a, b, chunk))
    buffers = RayBuffers(min(chunk, samples) * count)
    threads = ray_scene.threads
    tracer = SpanTracer(ray_scene, request, geometry, entries)
    for done, (index, start, stop) in enumerate(spans):
        cols = slice(start, stop)
        if retrace[index]:
            redo = column_mask(entries, start, stop)
        else:
            code = dense_columns(entries, "hit_object", start, stop, threads)
            hit_changed = np.zeros(code.shape, bool)
            hits = code >= 0
            hit_changed[hits] = is_changed[code[hits]]
            redo = hit_changed | (code == BACKFACE)
            probe = (code == MISS) | (hits & ~hit_changed)
            probe &= _may_hit_spheres(origins_all[cols], directions, spheres, request, cols)
            counts.kept += int(np.count_nonzero((code == MISS) | (hits & ~hit_changed))) - int(np.count_nonzero(probe))
            direction_index, sample_index = rays_where(probe, start, buffers, threads)
            if len(sample_index):
                entry = entries_at(entries, direction_index, sample_index, threads)
                # The changed objects' scene shares the whole scene's frame (its centre).
                origins, ray_directions = request.rays(ray_scene, direction_index, sample_index, buffers)
                found, triangle, bary, distance = changed_scene.intersect_local(
                    origins, ray_directions, out=buffers.hits(len(sample_index)))
                new_code, old_code = encode_distance(distance), entries.hit_distance_code[entry]
                nearer = (found >= 0) & (new_code < old_code)
                mapped = np.where(found >= 0, changed_map[np.maximum(found, 0)], -1).astype(np.int32)
                _record(entries, geometry, ray_directions, entry, mapped, triangle, bary, distance, where=nearer,
                        threads=threads)
                counts.changed_only += len(sample_index)
                counts.kept += len(sample_index) - int(np.count_nonzero(nearer))
                # A changed object as far as the old hit, within one distance code: which is nearer
                # only the whole scene can tell, as a fresh trace would.
                tied = np.nonzero((found >= 0) & (new_code == old_code))[0]
                if len(tied):
                    hit_geometry, triangle, bary, distance = ray_scene.intersect_local(origins[tied],
                                                                                       ray_directions[tied])
                    _record(entries, geometry, ray_directions[tied], entry[tied], hit_geometry, triangle,
                            bary, distance, threads=threads)
                    counts.full += len(tied)
                    counts.kept -= len(tied)
        direction_index, sample_index = rays_where(redo, start, buffers, threads)
        if len(sample_index):
            entry = entries_at(entries, direction_index, sample_index, threads)
            tracer.trace(direction_index, sample_index, entry, buffers)
            counts.full += len(sample_index)
        if progress is not None:
            progress((done + 1) / len(spans))
    table = _finish(directions, entries, traced_per_sample, int(traced_per_sample.sum()), geometry)
    return table, counts
