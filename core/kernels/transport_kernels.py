"""Compiled (numba) kernels of the table lookups: the gather, its normalisation, and AO.

Imported only through :mod:`core.kernels`, which sets numba's cache folder and threading
layer first. Every kernel runs in parallel over blocks of samples and sums each sample's
directions in ascending order (the gather starting from what ``out`` already holds), so a
result is bitwise the same for any thread count and any split of the directions into calls.

The arithmetic follows the numpy twin (:mod:`core.transport.gather`): float32 weights and
bilinear lookups, as the GLSL gather computes them; only the per-sample sums are float64.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..visibility.table import BELOW_HORIZON, MISS, UV_CODE_SCALE
from . import KERNEL_OPTIONS
from .bits import entry_of, trailing_zeros

# Samples per parallel task: the block's float64 sums stay in the L1 cache while the
# block's slice of every direction's table row is read once, in order.
BLOCK = 256

_F32 = np.float32
# As core.visibility.table.decode_uv computes it (the GPU pass reads the decoded floats).
_UV_STEP = np.float32(1.0 / UV_CODE_SCALE)


@nb.njit(inline="always")
def _bilinear_add(acc, j, radiance, weight, offset, width, height, u, v, channels):
    """acc[j] += weight * bilinear lookup of the padded atlas at ``offset`` (float32 math);
    ``channels`` is radiance.shape[1], passed so that a caller can give it as a constant."""
    widthf = _F32(width)
    heightf = _F32(height)
    x = min(max(u * widthf - _F32(0.5), _F32(0.0)), widthf - _F32(1.0))
    y = min(max(v * heightf - _F32(0.5), _F32(0.0)), heightf - _F32(1.0))
    x0 = np.int64(x)
    y0 = np.int64(y)
    fx = x - _F32(x0)
    fy = y - _F32(y0)
    stride = width + 1
    base = offset + y0 * stride + x0
    for c in range(channels):
        c00 = radiance[base, c]
        c01 = radiance[base + 1, c]
        c10 = radiance[base + stride, c]
        c11 = radiance[base + stride + 1, c]
        bottom = c00 + (c01 - c00) * fx
        top = c10 + (c11 - c10) * fx
        acc[j, c] += np.float64((bottom + (top - bottom) * fy) * weight)


@nb.njit(inline="always")
def _vertex_add(acc, j, radiance, weight, corners, u, v, nearest):
    """acc[j] += weight * the hit triangle's samples ``corners`` (3,) mixed by barycentrics."""
    w0 = _F32(1.0) - u - v
    if nearest:
        pick = 0
        if u > w0:
            pick = 1
        if v > max(w0, u):
            pick = 2
        for c in range(radiance.shape[1]):
            acc[j, c] += np.float64(radiance[corners[pick], c] * weight)
        return
    for c in range(radiance.shape[1]):
        mixed = (radiance[corners[0], c] * w0 + radiance[corners[1], c] * u) + radiance[corners[2], c] * v
        acc[j, c] += np.float64(mixed * weight)


@nb.njit(inline="always")
def _whole_words(samples, start, size):
    """Whether samples[start:start + size] are consecutive from a multiple of 64: the block is
    whole words of the entry bits (its last perhaps cut short), whose stored entries can be walked."""
    if samples[start] % 64 != 0:
        return False
    for j in range(size):
        if samples[start + j] != samples[start] + j:
            return False
    return True


@nb.njit(inline="always")
def _block_word(above_words, i, first_word, w, size):
    """Word ``w`` of a block of ``size`` samples from word ``first_word``, in direction i, without
    the bits of samples past the block."""
    word = above_words[i, first_word + w]
    if (w + 1) * 64 > size:
        word &= (np.uint64(1) << np.uint64(size - w * 64)) - np.uint64(1)
    return word


@nb.njit(inline="always")
def _add_entry(acc, j, s, e, i, cosines, sample_scale, hit_object, hit_uv, has_world, world, has_exclude, exclude,
               lit_object, any_vertex, is_vertex, vertex_cells, corner_flat, corner_base, nearest_vertex, radiance,
               offsets, widths, heights):
    """Add stored entry ``e`` (direction i) to the block's sample j (sample s): :func:`gather`'s body."""
    channels = radiance.shape[1]
    obj = hit_object[e]
    if obj < 0 and not (obj == MISS and has_world):
        return
    if obj >= 0 and not lit_object[obj]:
        return  # its whole atlas is 0: no lookup (most of an emission gather's entries)
    cosine = cosines[j]
    if cosine <= _F32(0.0):
        return
    weight = cosine * sample_scale[j]
    if obj == MISS:
        for c in range(channels):
            acc[j, c] += np.float64(weight * world[i, c])
        return
    if has_exclude and exclude[s, obj]:
        return
    if any_vertex and is_vertex[obj]:
        cells = vertex_cells[obj]
        steps = 65536 // cells
        cu = np.int64(hit_uv[e, 0])
        cv = np.int64(hit_uv[e, 1])
        last = _F32(steps - 1)
        triangle = cu // steps + cells * (cv // steps)
        corners = corner_flat[corner_base[obj] + triangle]
        _vertex_add(acc, j, radiance, weight, corners, _F32(cu % steps) / last, _F32(cv % steps) / last,
                    nearest_vertex)
    else:
        u = _F32(hit_uv[e, 0]) * _UV_STEP
        v = _F32(hit_uv[e, 1]) * _UV_STEP
        # One light group's RGB is the common case: a constant channel count
        # lets the compiler unroll the lookup.
        if channels == 3:
            _bilinear_add(acc, j, radiance, weight, offsets[obj], widths[obj], heights[obj], u, v, 3)
        else:
            _bilinear_add(acc, j, radiance, weight, offsets[obj], widths[obj], heights[obj], u, v, channels)


@nb.njit(**KERNEL_OPTIONS)
def gather(above_words, word_base, hit_object, hit_uv, vertex_cells, directions, normals, scale, samples, first,
           stop, radiance, widths, heights, offsets, is_vertex, corner_flat, corner_base, nearest_vertex,
           world, exclude, lit_object, out):
    """out[j] += sum_{i in [first, stop)} w_i(s) L(S_i[s]) for s = samples[j].

    above_words : (N, W) uint64, word_base : (N, W) int64, hit_object : (A,) int16, hit_uv :
        (A, 2) uint16 codes (of triangle and barycentrics on vertex-mode objects): the table's
        stored entries (core.visibility.table.TableEntries)
    vertex_cells : (O,) int64 core.visibility.table.vertex_cells
    directions : (N, 3) float32; normals : (K, 3) float32 (the frame normals); scale : (K,) float32
    samples : (k,) int64 sample indices; first, stop : the direction range
    radiance : (size, C) float32 packed atlases; widths, heights, offsets : (O,) int64
    is_vertex : (O,) bool; corner_flat : (T, 3) int32; corner_base : (O,) int64 (dummies
        of length 1 when no object is in vertex mode); nearest_vertex : bool
    world : (N, C) float32 radiance of misses, or (0, C) for a black world
    exclude : (K, O) bool, or (0, 0) for no exclusion
    lit_object : (O,) bool, False where an object's atlas (and corners) hold only zeros: its
        entries add nothing and are skipped without a lookup
    out : (k, C) float64, added to
    """
    count = samples.shape[0]
    channels = radiance.shape[1]
    has_world = world.shape[0] > 0
    has_exclude = exclude.shape[0] > 0
    any_vertex = False
    for o in range(is_vertex.shape[0]):
        any_vertex = any_vertex or is_vertex[o]
    blocks = (count + BLOCK - 1) // BLOCK
    for block in nb.prange(blocks):
        start = block * BLOCK
        end = min(count, start + BLOCK)
        size = end - start
        acc = np.empty((size, channels), np.float64)
        # The block's normals and scales, contiguous: each direction's cosines are then one
        # vectorised pass, and the lookup loop reads no (K, 3) rows (with the unrolled lookup
        # below, 10-25% of the gather's time: docs/benchmarks.md, "Speed, part 6").
        nx = np.empty(size, np.float32)
        ny = np.empty(size, np.float32)
        nz = np.empty(size, np.float32)
        sample_scale = np.empty(size, np.float32)
        cosines = np.empty(size, np.float32)
        contiguous = _whole_words(samples, start, size)
        for j in range(size):
            s = samples[start + j]
            nx[j] = normals[s, 0]
            ny[j] = normals[s, 1]
            nz[j] = normals[s, 2]
            sample_scale[j] = scale[s]
            for c in range(channels):
                acc[j, c] = out[start + j, c]
        first_word = samples[start] >> 6
        words = (size + 63) // 64
        for i in range(first, stop):
            dx = directions[i, 0]
            dy = directions[i, 1]
            dz = directions[i, 2]
            for j in range(size):
                cosines[j] = nx[j] * dx + ny[j] * dy + nz[j] * dz
            if contiguous:
                # The block's samples are whole words of the entry bits: walk their stored
                # entries in order, never touching an entry below a sample's horizon.
                for w in range(words):
                    word = _block_word(above_words, i, first_word, w, size)
                    e = word_base[i, first_word + w]
                    while word != np.uint64(0):
                        j = w * 64 + np.int64(trailing_zeros(word))
                        word &= word - np.uint64(1)
                        _add_entry(acc, j, samples[start] + j, e, i, cosines, sample_scale, hit_object, hit_uv,
                                   has_world, world, has_exclude, exclude, lit_object, any_vertex, is_vertex,
                                   vertex_cells, corner_flat, corner_base, nearest_vertex, radiance, offsets, widths,
                                   heights)
                        e += 1
            else:
                for j in range(size):
                    s = samples[start + j]
                    e = entry_of(above_words, word_base, i, s)
                    if e >= 0:
                        _add_entry(acc, j, s, e, i, cosines, sample_scale, hit_object, hit_uv, has_world, world,
                                   has_exclude, exclude, lit_object, any_vertex, is_vertex, vertex_cells,
                                   corner_flat, corner_base, nearest_vertex, radiance, offsets, widths, heights)
        for j in range(size):
            for c in range(channels):
                out[start + j, c] = acc[j, c]


@nb.njit(**KERNEL_OPTIONS)
def cosine_sum(above_words, word_base, hit_object, directions, normals, scale, code, counted, out):
    """out[k] = sum_i max(0, d_i . n_k) scale[k], summed in float64, over the directions i whose
    entry is ``code`` (``counted``) or is not (not ``counted``); the cosines in the dtype of
    ``normals`` and ``directions``.

    The gathers' normalisation: float32, scale 1, every entry not BELOW_HORIZON. AO: float64,
    the entries that MISS.

    above_words, word_base, hit_object : the stored entries, as in :func:`gather` (an entry not
    stored is BELOW_HORIZON); directions : (N, 3) and normals : (K, 3), float32 or float64;
    scale : (K,) the same dtype; code : int16; counted : bool; out : (K,) float64, overwritten
    """
    count = normals.shape[0]
    blocks = (count + BLOCK - 1) // BLOCK
    for block in nb.prange(blocks):
        start = block * BLOCK
        end = min(count, start + BLOCK)
        acc = np.zeros(end - start, np.float64)
        for i in range(directions.shape[0]):
            for j in range(end - start):
                s = start + j
                e = entry_of(above_words, word_base, i, s)
                # No stored entry is BELOW_HORIZON: asked for that code, the bits answer, and the
                # entries (a table in a scratch file: pages to map) are not read.
                if code == BELOW_HORIZON:
                    is_code = e < 0
                else:
                    is_code = (hit_object[e] if e >= 0 else np.int16(BELOW_HORIZON)) == code
                if is_code != counted:
                    continue
                cosine = normals[s, 0] * directions[i, 0] + normals[s, 1] * directions[i, 1] \
                    + normals[s, 2] * directions[i, 2]
                if cosine > 0.0:
                    acc[j] += np.float64(cosine * scale[s])
        for j in range(end - start):
            out[start + j] = acc[j]


@nb.njit(**KERNEL_OPTIONS)
def bare_lookup(above_words, word_base, hit_object, hit_uv, samples, first, stop, radiance, widths, heights, offsets,
                out):
    """The ceiling a gather is measured against: one nearest-texel read per hit entry, summed.

    The same table walk as :func:`gather` (the stored entries of whole words in order where
    the block's samples allow, else each sample's entry found from its bit) with the arithmetic
    taken out: what reading the table and the radiance costs on this machine. Arrays as in
    :func:`gather`.
    """
    count = samples.shape[0]
    channels = radiance.shape[1]
    blocks = (count + BLOCK - 1) // BLOCK
    for block in nb.prange(blocks):
        start = block * BLOCK
        end = min(count, start + BLOCK)
        size = end - start
        acc = np.zeros((size, channels), np.float64)
        contiguous = _whole_words(samples, start, size)
        first_word = samples[start] >> 6
        words = (size + 63) // 64
        for i in range(first, stop):
            if contiguous:
                for w in range(words):
                    word = _block_word(above_words, i, first_word, w, size)
                    e = word_base[i, first_word + w]
                    while word != np.uint64(0):
                        j = w * 64 + np.int64(trailing_zeros(word))
                        word &= word - np.uint64(1)
                        _bare_add(acc, j, e, hit_object, hit_uv, radiance, widths, heights, offsets)
                        e += 1
            else:
                for j in range(size):
                    e = entry_of(above_words, word_base, i, samples[start + j])
                    if e >= 0:
                        _bare_add(acc, j, e, hit_object, hit_uv, radiance, widths, heights, offsets)
        for j in range(size):
            for c in range(channels):
                out[start + j, c] = acc[j, c]


@nb.njit(inline="always")
def _bare_add(acc, j, e, hit_object, hit_uv, radiance, widths, heights, offsets):
    """:func:`bare_lookup`'s body: one nearest-texel read of stored entry ``e`` into sample j."""
    obj = hit_object[e]
    if obj < 0:
        return
    width = widths[obj]
    x = np.int64(_F32(hit_uv[e, 0]) * _UV_STEP * _F32(width))
    y = np.int64(_F32(hit_uv[e, 1]) * _UV_STEP * _F32(heights[obj]))
    base = offsets[obj] + y * (width + 1) + x
    for c in range(radiance.shape[1]):
        acc[j, c] += radiance[base, c]
