"""Compiled (numba) kernels of the visibility bake: the rays' set-up, writing traced rays
into the table's stored entries (only those above the horizon), and finding them.

Imported only through :mod:`core.kernels`. They compute what ``TraceRequest.ray_origins`` /
``ray_directions`` and :func:`core.visibility.table._record_numpy` compute, in the same float32
and float64 operations, so both give bitwise the same rays and entries. Each ray owns its output
and its table entry.

The rays' set-up and their record run on one thread, over a span of rays: the trace runs them
on every thread at once, each thread setting up, tracing and recording a span of its own in
turn (core.visibility.table.SpanTracer), so that a span's arrays stay in its core's cache and
no thread waits for the others between the three steps. The rest run in parallel.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..visibility.table import (
    BACKFACE,
    DISTANCE_CODES_PER_OCTAVE,
    DISTANCE_LOWEST_OCTAVE,
    MISS,
    NO_HIT_DISTANCE_CODE,
    UV_CODE_SCALE,
)
from . import KERNEL_OPTIONS, SERIAL_OPTIONS
from .bits import bits_float32, entry_of, float32_bits, popcount, trailing_zeros

_F32 = np.float32


@nb.njit(inline="always")
def _uv_code(value):
    """encode_uv of one float32 coordinate: NaN -> 0, clamped to [0, 1], rounded half to even."""
    x = np.float64(value)
    if x != x:
        x = 0.0
    x = min(max(x, 0.0), 1.0)
    return np.uint16(np.rint(x * UV_CODE_SCALE))


# Where each of the 2048 steps of a float32's top 11 mantissa bits starts among its octave's
# distance codes (their middles' logarithms): a guess within a code or two of the answer,
# for the price of a lookup, where np.log2 took 9 of a record's 23 ns a ray.
_OCTAVE_GUESS = np.floor(DISTANCE_CODES_PER_OCTAVE * np.log2(1.0 + (np.arange(2048) + 0.5) / 2048) + 0.5
                         ).astype(np.int64)


@nb.njit(inline="always")
def _distance_code(d, splits):
    """encode_distance of one finite float32 distance: the number of ``splits`` below it
    (numpy's searchsorted), found from a guess (its exponent and top mantissa bits) and a step
    or two, not a 16-step binary search."""
    if d <= _F32(0.0):
        return np.uint16(0)
    bits = float32_bits(d)
    exponent = (bits >> 23) & 255
    code = np.int64(0)
    if exponent > 0:  # not subnormal (those lie far below the lowest code)
        code = ((np.int64(exponent) - 127 - DISTANCE_LOWEST_OCTAVE) * DISTANCE_CODES_PER_OCTAVE
                + _OCTAVE_GUESS[(bits >> 12) & 2047])
    code = min(max(code, 0), splits.shape[0])
    value = np.float64(d)
    while code > 0 and value <= splits[code - 1]:
        code -= 1
    while code < splits.shape[0] and value > splits[code]:
        code += 1
    return np.uint16(code)


@nb.njit(inline="always")
def _vertex_code(triangle, value, cells, axis):
    """encode_vertex_hit of one float32 barycentric along ``axis`` (0: u, 1: v)."""
    steps = 65536 // cells
    x = np.float64(value)
    if x != x:
        x = 0.0
    x = min(max(x, 0.0), 1.0)
    cell = triangle % cells if axis == 0 else triangle // cells
    return np.uint16(cell * steps + np.int64(np.rint(x * (steps - 1))))


@nb.njit(**SERIAL_OPTIONS)
def record(hit_object, hit_uv_code, hit_distance_code, entry, hit_geometry, triangle, bary,
           distance, ray_directions, triangle_offset, face_normals, corner_uv, vertex_cells, where,
           distance_splits, sample_index, first_sample, backfaces):
    """Write rays into their table entries ``entry[r]``: hits, backfaces and misses; count the
    backfaces per sample where asked.

    hit_object : (A,) int16; hit_uv_code : (A, 2) uint16; hit_distance_code : (A,) uint16, the
        table's stored entries (core.visibility.table.TableEntries)
    entry : (n,) int64 the rays' entries
    hit_geometry, triangle : (n,) int32 (embree's geomID, -1 for a miss, and primID)
    bary : (n, 2) float32; distance : (n,) float32; ray_directions : (n, 3) float32
    triangle_offset : (O,) int64; face_normals : (T, 3) float64; corner_uv : (T, 3, 2) float32
    vertex_cells : (O,) int64 core.visibility.table.vertex_cells (all 0 without vertex-mode objects)
    where : (n,) bool, or (0,) for every ray; with it only those rays are written, and misses never
    distance_splits : core.visibility.table.DISTANCE_SPLITS
    sample_index : (n,) int64 the rays' samples; backfaces : (m,) int32, in and out: each
        backface adds 1 at its sample minus ``first_sample`` (int64); (0,) to count nothing
        (and ``sample_index`` may then be (0,) too)
    """
    has_where = where.shape[0] > 0
    counting = backfaces.shape[0] > 0
    for r in range(entry.shape[0]):
        e = entry[r]
        geometry = hit_geometry[r]
        if has_where:
            if not where[r] or geometry < 0:
                continue
        elif geometry < 0:
            hit_object[e] = MISS
            hit_uv_code[e, 0] = 0
            hit_uv_code[e, 1] = 0
            hit_distance_code[e] = NO_HIT_DISTANCE_CODE
            continue
        t = triangle_offset[geometry] + triangle[r]
        facing = (face_normals[t, 0] * np.float64(ray_directions[r, 0])
                  + face_normals[t, 1] * np.float64(ray_directions[r, 1])) \
            + face_normals[t, 2] * np.float64(ray_directions[r, 2])
        back = facing > 0.0
        u = bary[r, 0]
        v = bary[r, 1]
        cells = vertex_cells[geometry]
        if back:
            hit_object[e] = BACKFACE
            hit_uv_code[e, 0] = 0
            hit_uv_code[e, 1] = 0
            if counting:
                backfaces[sample_index[r] - first_sample] += 1
        else:
            hit_object[e] = geometry
            if cells > 0:
                local = np.int64(triangle[r])
                hit_uv_code[e, 0] = _vertex_code(local, u, cells, 0)
                hit_uv_code[e, 1] = _vertex_code(local, v, cells, 1)
            else:
                w = (_F32(1.0) - u) - v
                for axis in range(2):
                    landing = (w * corner_uv[t, 0, axis] + u * corner_uv[t, 1, axis]) + v * corner_uv[t, 2, axis]
                    hit_uv_code[e, axis] = _uv_code(landing)
        d = distance[r]
        if d - d != _F32(0.0):  # inf or NaN
            hit_distance_code[e] = NO_HIT_DISTANCE_CODE
        else:
            hit_distance_code[e] = _distance_code(d, distance_splits)


@nb.njit(**SERIAL_OPTIONS)
def ray_setup(direction_index, sample_index, positions, footprint, point_of_direction, geometric, frame_directions,
              group, centre, int_scale, float_scale, origin_limit, origins, directions):
    """The rays (direction_index[r], sample_index[r]) as embree takes them, computed as
    ``TraceRequest.ray_origins`` and ``ray_directions`` followed by ``RayScene`` moving them
    into its frame compute them (core.visibility.rays.offset_ray_origins), bitwise: the origin
    stepped off the surface by whole float32 ULPs (its bits, as an int32), or by a distance
    near the world origin.

    positions, geometric : (K, 3) float64; footprint : (K, P, 3) float32, or (K, 0, 3) for none
    point_of_direction : (N,) int64, i % P: direction i's footprint point (a lookup, where the
        remainder was a 64-bit division per ray)
    frame_directions : (G, N, 3) float32 each rotation's directions (G = 1 without rotations);
    group : (K,) int64 each sample's rotation
    centre : (3,) float64 the ray scene's centre (the caller makes the round trip through world
        space that RayScene's queries make, where it is not zero)
    int_scale, float_scale, origin_limit : float32, core.tolerances' RAY_OFFSET_* constants
    origins : (n, 3) float32, out: in the ray scene's frame; directions : (n, 3) float32, out
    """
    points = footprint.shape[1]
    for r in range(direction_index.shape[0]):
        i = direction_index[r]
        s = sample_index[r]
        point = point_of_direction[i] if points > 0 else 0
        for axis in range(3):
            x = positions[s, axis]
            if points > 0:
                x = x + np.float64(footprint[s, point, axis])
            x = x - centre[axis]
            p = np.float32(x)
            n = np.float32(geometric[s, axis])
            if abs(p) < origin_limit:
                origins[r, axis] = p + float_scale * n
            else:
                offset = np.int32(int_scale * n)
                bits = float32_bits(p)
                origins[r, axis] = bits_float32(np.int32(bits - offset) if p < _F32(0.0) else np.int32(bits + offset))
            directions[r, axis] = frame_directions[group[s], i, axis]


@nb.njit(**KERNEL_OPTIONS)
def horizon_bits(directions, horizon, words, counts):
    """The table's entry bits: bit b of ``words[i, w]`` is set where direction i lies above
    sample 64 w + b's horizon, (d_x h_x + d_y h_y) + d_z h_z > 0 in float64, summed in that
    order as core.visibility.table.above_horizon sums it in numpy; ``counts[k]``: how many
    directions lie above sample k's. In parallel over words, each owning its samples.

    directions : (N, 3) float64; horizon : (K, 3) float64 (TraceRequest.horizon_normals);
    words : (N, W) uint64, out; counts : (K,) int32, out.
    """
    samples = horizon.shape[0]
    for w in nb.prange(words.shape[1]):
        start = w * 64
        stop = min(start + 64, samples)
        for k in range(start, stop):
            counts[k] = 0
        for i in range(directions.shape[0]):
            x, y, z = directions[i, 0], directions[i, 1], directions[i, 2]
            word = np.uint64(0)
            for k in range(start, stop):
                if (x * horizon[k, 0] + y * horizon[k, 1]) + z * horizon[k, 2] > 0.0:
                    word |= np.uint64(1) << np.uint64(k - start)
                    counts[k] += 1
            words[i, w] = word


@nb.njit(**KERNEL_OPTIONS)
def rays_where(mask, row_offset, start, direction_index, sample_index):
    """The (direction, sample + ``start``) of every True entry of ``mask``, in row-major order:
    ``np.nonzero(mask)`` with ``start`` added to the samples, written into the caller's arrays
    instead of two new strided ones; in parallel over rows.

    mask (N, k) bool; row_offset (N,) int64, the first index of each row's rays;
    direction_index, sample_index (n,) int64, out (n: the number of True in ``mask``).
    Branch-free like :func:`pack_rows`: every entry is written to the next free slot.
    """
    for row in nb.prange(mask.shape[0]):
        at = row_offset[row]
        end = row_offset[row + 1] if row + 1 < mask.shape[0] else direction_index.shape[0]
        for col in range(mask.shape[1]):
            if at < end:
                direction_index[at] = row
                sample_index[at] = col + start
            at += np.int64(mask[row, col])


@nb.njit(**SERIAL_OPTIONS)
def rays_of_span(above_words, word_base, first_word, last_word, row_offset, first, direction_index, sample_index,
                 entry):
    """Rays [first, first + n) of the list of the stored entries of words [first_word, last_word)
    of each row (core.visibility.table.rays_of_entries: (direction, sample, entry), row-major,
    each row from ``row_offset``), on one thread: a span of the list, made by the thread that
    traces it, with no list of the whole chunk in memory.

    above_words : (N, W) uint64; word_base : (N, W) int64; row_offset : (N,) int64;
    first : int64; direction_index, sample_index, entry : (n,) int64, out (n rays, all of
    which exist).
    """
    count = direction_index.shape[0]
    if count == 0:
        return
    # The last row starting at or before ``first``: rows without rays start where the next
    # one does, so this one holds ray ``first``.
    low, high = 0, row_offset.shape[0]
    while high - low > 1:
        middle = (low + high) // 2
        if row_offset[middle] <= first:
            low = middle
        else:
            high = middle
    row = low
    skip = first - row_offset[row]
    at = 0
    while at < count:
        e = word_base[row, first_word]
        w = first_word
        while skip > 0:
            bits = np.int64(popcount(above_words[row, w]))
            if bits > skip:
                break
            skip -= bits
            e += bits
            w += 1
        while w < last_word and at < count:
            word = above_words[row, w]
            while skip > 0:
                word &= word - np.uint64(1)
                skip -= 1
                e += 1
            while word != np.uint64(0) and at < count:
                direction_index[at] = row
                sample_index[at] = w * 64 + np.int64(trailing_zeros(word))
                entry[at] = e
                at += 1
                e += 1
                word &= word - np.uint64(1)
            w += 1
        row += 1


@nb.njit(**KERNEL_OPTIONS)
def entries_at(above_words, word_base, direction_index, sample_index, out):
    """out[r] = the stored entry of (direction_index[r], sample_index[r]), -1 where not stored
    (core.kernels.bits.entry_of); in parallel over r. Arrays (n,) int64."""
    for r in nb.prange(direction_index.shape[0]):
        out[r] = entry_of(above_words, word_base, direction_index[r], sample_index[r])


# Samples per task of count_per_sample: a whole number of 64-sample words.
COUNT_BLOCK = 1024


@nb.njit(**KERNEL_OPTIONS)
def count_per_sample(above_words, word_base, hit_object, code, counts):
    """counts[k] = how many of sample k's stored entries are ``code`` (core.visibility.table.
    TableEntries.per_sample); in parallel over blocks of samples, each walking its words of
    every direction. above_words (N, W) uint64; word_base (N, W) int64; hit_object (A,) int16;
    code int16; counts (K,) int32, out."""
    samples = counts.shape[0]
    for block in nb.prange((samples + COUNT_BLOCK - 1) // COUNT_BLOCK):
        start = block * COUNT_BLOCK
        stop = min(start + COUNT_BLOCK, samples)
        for k in range(start, stop):
            counts[k] = 0
        for i in range(above_words.shape[0]):
            e = word_base[i, start >> 6]
            for w in range(start >> 6, (stop + 63) >> 6):
                word = above_words[i, w]
                while word != np.uint64(0):
                    k = w * 64 + np.int64(trailing_zeros(word))
                    word &= word - np.uint64(1)
                    counts[k] += np.int32(hit_object[e] == code)
                    e += 1


@nb.njit(**KERNEL_OPTIONS)
def copy_runs(from_first, to_first, runs, source, target):
    """target[to_first[i] + j] = source[from_first[i] + j] for j < runs[i], every row i: the
    stored entries of a range of samples copied between two tables whose entry bits there
    agree (core.visibility.table.copy_columns); in parallel over rows. from_first, to_first,
    runs : (N,) int64; source, target : (A,) and (B,) of one dtype."""
    for row in nb.prange(runs.shape[0]):
        take = from_first[row]
        put = to_first[row]
        for j in range(runs[row]):
            target[put + j] = source[take + j]


@nb.njit(**KERNEL_OPTIONS)
def entry_columns(above_words, word_base, values, start, stop, out):
    """out[i, k - start] = values[entry (i, k)] for every stored entry of samples [start, stop)
    (core.visibility.table.dense_columns); entries not stored keep what ``out`` held. In
    parallel over rows. above_words (N, W) uint64; word_base (N, W) int64; values (A,);
    out (N, stop - start) of values' dtype."""
    if stop <= start:
        return
    first_word = start >> 6
    before_start = (np.uint64(1) << np.uint64(start & 63)) - np.uint64(1)
    for row in nb.prange(above_words.shape[0]):
        # The stored entries before ``start`` in its word come first: skip them.
        e = word_base[row, first_word] + np.int64(popcount(above_words[row, first_word] & before_start))
        for w in range(first_word, (stop + 63) >> 6):
            word = above_words[row, w]
            if w == first_word:
                word &= ~before_start
            while word != np.uint64(0):
                k = w * 64 + np.int64(trailing_zeros(word))
                if k >= stop:
                    break
                out[row, k - start] = values[e]
                e += 1
                word &= word - np.uint64(1)
