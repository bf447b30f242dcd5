"""Compiled (numba) kernels of the passes a preparation runs once over the whole table:
the table entries that land close by, the texels' exposed shares, the texels owning
landing points and the landing points themselves (core.transport.contacts: close_entries,
exposed_share, _texel_owners, _landings), and the interleaving filter's candidate pairs
(core.transport.interleave.filter_pairs).

Imported only through :mod:`core.kernels`. Each computes what the numpy code computes, in
the same float32 and float64 operations and order, so their results are bitwise the numpy
code's. Where a pass lists entries, it counts them first and then writes them at each
task's offset (the callers take the running sum in between), so their order is the numpy
code's, whatever the thread count.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from ..visibility.table import BACKFACE
from . import KERNEL_OPTIONS, SERIAL_OPTIONS
from .bits import trailing_zeros
from .light_kernels import _dot, _origin_axis

# Samples per task of exposed_share: its counts (slots x block, int32) stay in the core's cache
# while every direction's row of the block is read. A multiple of 64: the blocks' words are their own.
EXPOSED_BLOCK = 1024


@nb.njit(**KERNEL_OPTIONS)
def close_entries(above_words, word_base, hit_object, hit_distance_code, distance_values, target_reach, sample_reach,
                  offsets, sample, entry, write):
    """Count the hits of each direction nearer than their target's ``target_reach`` and (where
    given) their sample's ``sample_reach``, or with ``write`` list their samples, ascending, and
    their entries at each direction's offset; in parallel over directions.

    above_words : (N, W) uint64, word_base : (N, W) int64, hit_object : (A,) int16,
    hit_distance_code : (A,) uint16: the table's stored entries (core.visibility.table.
    TableEntries); distance_values : (65536,) float32 core.visibility.table.DISTANCE_VALUES;
    target_reach : (O,) float32; sample_reach : (K,) float64, or (0,) for none (float32 reaches
    widen exactly, and a comparison of float32 distances with float32 or float64 reaches is exact
    in float64). offsets : (N + 1,) int64, without ``write`` an output whose entry i + 1 is
    direction i's count (entry 0 untouched), with it their running sum from 0. Output with
    ``write``: sample, entry (offsets[-1],) int64.
    """
    by_sample = sample_reach.shape[0] > 0
    for i in nb.prange(above_words.shape[0]):
        if write and offsets[i + 1] == offsets[i]:
            continue
        at = offsets[i]
        count = 0
        e = word_base[i, 0]
        for w in range(above_words.shape[1]):
            word = above_words[i, w]
            while word != np.uint64(0):
                k = w * 64 + np.int64(trailing_zeros(word))
                word &= word - np.uint64(1)
                this = e
                e += 1
                target = hit_object[this]
                if target < 0:
                    continue
                distance = distance_values[hit_distance_code[this]]
                if not distance < target_reach[target]:
                    continue
                if by_sample and not np.float64(distance) < sample_reach[k]:
                    continue
                if write:
                    sample[at + count] = k
                    entry[at + count] = this
                count += 1
        if not write:
            offsets[i + 1] = count


@nb.njit(**KERNEL_OPTIONS)
def exposed_share(above_words, word_base, hit_object, slots, buried_share, first, share):
    """The share of footprint points that are not buried (core.transport.contacts.exposed_share)
    of samples [first, first + k), in parallel over blocks of samples.

    above_words, word_base, hit_object : the table's stored entries, as in :func:`close_entries`,
    direction i starting from footprint point i % ``slots``; buried_share : float,
    core.transport.contacts.BURIED_POINT_SHARE (an argument, as a constant imported from there
    would outlive a change in the cached kernel); first : int, a multiple of 64. Output share
    (k,) float64, the samples' shares.
    """
    end = first + share.shape[0]
    for block in nb.prange((share.shape[0] + EXPOSED_BLOCK - 1) // EXPOSED_BLOCK):
        start = first + block * EXPOSED_BLOCK
        stop = min(start + EXPOSED_BLOCK, end)
        traced = np.zeros((slots, stop - start), np.int32)
        backface = np.zeros((slots, stop - start), np.int32)
        for i in range(above_words.shape[0]):
            slot = i % slots
            # EXPOSED_BLOCK is a whole number of words: the block's words are its own.
            e = word_base[i, start >> 6]
            for w in range(start >> 6, (stop + 63) >> 6):
                word = above_words[i, w]
                while word != np.uint64(0):
                    k = w * 64 + np.int64(trailing_zeros(word))
                    word &= word - np.uint64(1)
                    traced[slot, k - start] += np.int32(1)
                    backface[slot, k - start] += np.int32(hit_object[e] == BACKFACE)
                    e += 1
        for k in range(start, stop):
            counted = 0
            buried = 0
            for slot in range(slots):
                rays = traced[slot, k - start]
                if rays > 0:
                    counted += 1
                    # As numpy: the 16-bit counts against the share times the count in float64.
                    if np.float64(backface[slot, k - start]) >= buried_share * np.float64(rays):
                        buried += 1
            share[k - first] = 1.0 - buried / counted if counted > 0 else 1.0


@nb.njit(**SERIAL_OPTIONS)
def texel_owners(obj, uv, widths, heights, grid_offset, grid, shifts, owner):
    """The sample owning the texel each landing lies in, else the first of its neighbours in
    ``shifts`` order that has one, else -1 (core.transport.contacts._texel_owners).

    obj : (m,) int64; uv : (m, 2) float32; widths, heights, grid_offset : (O,) int64 each
    object's atlas size and the start of its texels in ``grid`` (G,) int64, the sample owning
    each texel or -1; shifts : (S, 2) int64 (dx, dy), the first (0, 0). Output owner (m,) int64.
    """
    for i in range(obj.shape[0]):
        o = obj[i]
        width = widths[o]
        height = heights[o]
        # float32 texel coordinates, as numpy multiplies float32 by a Python int.
        x = min(max(np.int64(np.floor(uv[i, 0] * np.float32(width))), 0), width - 1)
        y = min(max(np.int64(np.floor(uv[i, 1] * np.float32(height))), 0), height - 1)
        found = -1
        for s in range(shifts.shape[0]):
            xx = min(max(x + shifts[s, 0], 0), width - 1)
            yy = min(max(y + shifts[s, 1], 0), height - 1)
            found = grid[grid_offset[o] + yy * width + xx]
            if found >= 0:
                break
        owner[i] = found


@nb.njit(**KERNEL_OPTIONS)
def landings(sample, direction, owner, floor, position, footprint, rotations, group, directions, geometric, normal,
             centre, centred, int_scale, float_scale, origin_limit, landed, landed_normal, landed_geometric,
             landed_origins):
    """Where each short entry's ray lands, lit from the side it came from
    (core.transport.contacts._landings_numpy, bitwise). In parallel over entries.

    sample, direction, owner : (m,) int64 the entry's sample, direction and the sample owning
    the texel it landed in; floor : (m,) float64 its distance (the least its code allows).
    position, geometric, normal : (K, 3) float64; footprint : (K, P, 3) float32 the points the
    directions leave from (direction i from point i mod P), or (K, 0, 3): from the samples.
    rotations : (G, 3, 3) float64 and group (K,) int64 each sample's rotation, or (0, 3, 3):
    none; directions : (N, 3) float64. centre : (3,) float64 the ray scene's, ``centred``
    where it is not the origin; int_scale, float_scale, origin_limit : float32, the
    RAY_OFFSET_* tolerances (as light_kernels.shadow_ray_setup).

    Outputs (m, 3): landed (float64) the point, landed_normal and landed_geometric (float64)
    its owner's normals turned towards the ray's origin, landed_origins (float32, or float64
    where centred) its shadow rays' origin.
    """
    points = footprint.shape[1]
    rotated = rotations.shape[0] > 0
    for r in nb.prange(sample.shape[0]):
        s = sample[r]
        w = direction[r]
        d0, d1, d2 = directions[w, 0], directions[w, 1], directions[w, 2]
        if rotated:
            g = group[s]
            # As numpy's einsum("nab,nb->na") sums each row.
            u0 = _dot(rotations[g, 0, 0], rotations[g, 0, 1], rotations[g, 0, 2], d0, d1, d2)
            u1 = _dot(rotations[g, 1, 0], rotations[g, 1, 1], rotations[g, 1, 2], d0, d1, d2)
            u2 = _dot(rotations[g, 2, 0], rotations[g, 2, 1], rotations[g, 2, 2], d0, d1, d2)
        else:
            u0, u1, u2 = d0, d1, d2
        o = owner[r]
        facing = -1.0 if _dot(geometric[o, 0], geometric[o, 1], geometric[o, 2], u0, u1, u2) > 0.0 else 1.0
        for axis in range(3):
            start = position[s, axis]
            if points > 0:
                start = start + np.float64(footprint[s, w % points, axis])
            origin = _origin_axis(start, geometric[s, axis], centre[axis], centred, int_scale, float_scale,
                                  origin_limit)
            unit = u0 if axis == 0 else (u1 if axis == 1 else u2)
            landed[r, axis] = origin + unit * floor[r]
            landed_geometric[r, axis] = geometric[o, axis] * facing
            landed_normal[r, axis] = normal[o, axis] * facing
        for axis in range(3):
            landed_origins[r, axis] = _origin_axis(landed[r, axis], landed_geometric[r, axis], centre[axis], centred,
                                                   int_scale, float_scale, origin_limit)


@nb.njit(inline="always")
def _same_surface(row, neighbour, position, normal, origins, cosine, reach):
    """Whether texel ``row`` and its neighbour lie on the same surface (normals' dot product
    over ``cosine``, squared distance under ``reach``) with distinct origins, and if so the ray
    between those: its float64 offset and length (else zeros). numpy's einsum sums three
    products as (0 + 2) + 1 (its two SIMD lanes), its norm as (0 + 1) + 2."""
    facing = (normal[row, 0] * normal[neighbour, 0] + normal[row, 2] * normal[neighbour, 2]) \
        + normal[row, 1] * normal[neighbour, 1]
    g0 = position[row, 0] - position[neighbour, 0]
    g1 = position[row, 1] - position[neighbour, 1]
    g2 = position[row, 2] - position[neighbour, 2]
    if not (facing > cosine and (g0 * g0 + g2 * g2) + g1 * g1 < reach):
        return False, 0.0, 0.0, 0.0, 0.0
    a0 = origins[neighbour, 0] - origins[row, 0]
    a1 = origins[neighbour, 1] - origins[row, 1]
    a2 = origins[neighbour, 2] - origins[row, 2]
    length = np.sqrt((a0 * a0 + a1 * a1) + a2 * a2)
    return length > 0.0, a0, a1, a2, length


@nb.njit(**KERNEL_OPTIONS)
def filter_candidates(pixel, visible, grid, first, width, height, shifts, chunk, position, normal, origins, cosine,
                      reach, offsets, ray_offsets, rows, other, direction, length, write):
    """One object's candidate pairs of the interleaving filter (core.transport.interleave.
    filter_pairs) before their occlusion test: for each shift (dx, dy) of ``shifts`` in turn,
    each visible texel whose shifted texel holds a visible sample on the same surface (shift
    (0, 0): the texel itself), texels in ascending order. Counted, or with ``write`` listed,
    in parallel over tasks: shift s and the ``chunk`` texels from c * chunk, task s * chunks + c.

    pixel : (n,) int64 the object's texels; visible : (n,) bool; grid : (width * height,)
    int64 the global sample owning each texel if visible, else -1; first : int the object's
    first sample; shifts : (S, 2) int64; position, normal, origins : (K, 3) float64 (origins:
    p.origins); cosine, reach : float the bounds (exclusive) of the same surface's normals' dot
    product and squared distance. offsets, ray_offsets : (T + 1,) int64, T the task count;
    without ``write`` offsets is an output whose entry t + 1 is task t's count (entry 0
    untouched), with it both are running sums from 0: of every task's count, and of those of
    shifted tasks (shift (0, 0) casts no ray). Outputs with ``write``: rows, other (offsets[-1],)
    int64 the texel and its neighbour; direction (r, 3) float32 and length (r,) float32 the
    rays from texel to neighbour of the shifted pairs (r = ray_offsets[-1]), in pair order.
    """
    count = pixel.shape[0]
    chunks = (count + chunk - 1) // chunk
    for task in nb.prange(shifts.shape[0] * chunks):
        if write and offsets[task + 1] == offsets[task]:
            continue
        dx = shifts[task // chunks, 0]
        dy = shifts[task // chunks, 1]
        shifted = dx != 0 or dy != 0
        start = (task % chunks) * chunk
        at = offsets[task]
        ray_at = ray_offsets[task]
        found = 0
        for j in range(start, min(start + chunk, count)):
            if not visible[j]:
                continue
            x = pixel[j] % width + dx
            y = pixel[j] // width + dy
            if x < 0 or x >= width or y < 0 or y >= height:
                continue
            neighbour = grid[y * width + x]
            if neighbour < 0:
                continue
            row = first + j
            if shifted:
                same, a0, a1, a2, far = _same_surface(row, neighbour, position, normal, origins, cosine, reach)
                if not same:
                    continue
                if write:
                    direction[ray_at + found, 0] = np.float32(a0 / far)
                    direction[ray_at + found, 1] = np.float32(a1 / far)
                    direction[ray_at + found, 2] = np.float32(a2 / far)
                    length[ray_at + found] = np.float32(far)
            if write:
                rows[at + found] = row
                other[at + found] = neighbour
            found += 1
        if not write:
            offsets[task + 1] = found
