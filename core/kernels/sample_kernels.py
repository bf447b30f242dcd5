"""Compiled (numba) kernels of sample placement: the texel footprints' jitter, first draw and offsets, and the
texel boxes' corners (core.sampling.footprint), in parallel over samples.

Imported only through :mod:`core.kernels`. The first draw computes what the numpy code
computes, in the same float64 operations and order, so the footprints (from which the
visibility table's rays start) are bitwise the same with either.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import KERNEL_OPTIONS


@nb.njit(**KERNEL_OPTIONS)
def footprint_first_draw(uv, centre, inverse, usable, jitter, tri_corners, box_width, inset, chosen, inside):
    """Every footprint slot's first draw: the jittered point of the texel's box, where it lies
    inside the texel's triangle, else NaN (``inside`` False).

    uv : (k, 3, 2) float64 the triangle's corners in texel units; centre : (k, 2) float64 the
    texel's centre; inverse : (k,) float64 1 / twice the triangle's signed area (0: degenerate);
    usable : (k,) bool; jitter : (k, P, 2) float64 in [0, 1); tri_corners : (k, 3, 3) float64
    world corners; box_width, inset : float. Outputs chosen (k, P, 3) float64, inside (k, P) bool.
    """
    for k in nb.prange(uv.shape[0]):
        a0, a1 = uv[k, 0, 0], uv[k, 0, 1]
        b0, b1 = uv[k, 1, 0], uv[k, 1, 1]
        c0, c1 = uv[k, 2, 0], uv[k, 2, 1]
        scale = inverse[k]
        for slot in range(jitter.shape[1]):
            x = (centre[k, 0] + (jitter[k, slot, 0] - 0.5) * box_width) - a0
            y = (centre[k, 1] + (jitter[k, slot, 1] - 0.5) * box_width) - a1
            w1 = (x * (c1 - a1) - (c0 - a0) * y) * scale
            w2 = ((b0 - a0) * y - x * (b1 - a1)) * scale
            w0 = 1.0 - w1 - w2
            ok = usable[k] and w0 >= inset and w1 >= inset and w2 >= inset
            inside[k, slot] = ok
            for axis in range(3):
                if ok:
                    chosen[k, slot, axis] = (w0 * tri_corners[k, 0, axis] + w1 * tri_corners[k, 1, axis]) \
                        + w2 * tri_corners[k, 2, axis]
                else:
                    chosen[k, slot, axis] = np.nan


@nb.njit(**KERNEL_OPTIONS)
def footprint_redraws(uv, centre, inverse, usable, jitter, tri_corners, box_width, inset, redraws, chosen, inside):
    """Every slot whose first draw fell outside its triangle (``inside`` False on a usable
    texel) draws again, up to ``redraws`` - 1 times, each draw hashed from the one before
    (core.sampling.footprint's redraw loop: the same integer and float64 operations in the
    same order, so the points are bitwise the same); a slot that finds a place gets its point
    in ``chosen`` (the others keep NaN). Arrays as :func:`footprint_first_draw`; ``inside``
    is read only.
    """
    step = 2.0 ** -24
    for k in nb.prange(uv.shape[0]):
        if not usable[k]:
            continue
        a0, a1 = uv[k, 0, 0], uv[k, 0, 1]
        b0, b1 = uv[k, 1, 0], uv[k, 1, 1]
        c0, c1 = uv[k, 2, 0], uv[k, 2, 1]
        scale = inverse[k]
        for slot in range(jitter.shape[1]):
            if inside[k, slot]:
                continue
            u0 = jitter[k, slot, 0]
            u1 = jitter[k, slot, 1]
            for attempt in range(1, redraws):
                bits0 = np.uint64(u0 * 16777216.0)
                bits1 = np.uint64(u1 * 16777216.0)
                salt = np.uint64((0x68E31DA4 * attempt) & 0xFFFFFFFF)
                h0 = _hash32(bits0 ^ _hash32((bits1 + np.uint64(attempt)) & _LOW32))
                h1 = _hash32(bits1 ^ _hash32((bits0 + salt) & _LOW32))
                u0 = np.float64(h0 >> np.uint64(8)) * step
                u1 = np.float64(h1 >> np.uint64(8)) * step
                x = (centre[k, 0] + (u0 - 0.5) * box_width) - a0
                y = (centre[k, 1] + (u1 - 0.5) * box_width) - a1
                w1 = (x * (c1 - a1) - (c0 - a0) * y) * scale
                w2 = ((b0 - a0) * y - x * (b1 - a1)) * scale
                w0 = 1.0 - w1 - w2
                if w0 >= inset and w1 >= inset and w2 >= inset:
                    for axis in range(3):
                        chosen[k, slot, axis] = (w0 * tri_corners[k, 0, axis] + w1 * tri_corners[k, 1, axis]) \
                            + w2 * tri_corners[k, 2, axis]
                    break


@nb.njit(inline="always")
def _nan_to_num(value):
    """numpy's nan_to_num of one float64: NaN -> 0, infinities -> the largest finite values."""
    if value != value:
        return 0.0
    if value == np.inf:
        return 1.7976931348623157e308
    if value == -np.inf:
        return -1.7976931348623157e308
    return value


@nb.njit(**KERNEL_OPTIONS)
def footprint_corners(uv, centre, inverse, tri_corners, position, offsets, half, inset, result):
    """The four corners of each texel's box as offsets from its position, or where a corner
    is not inside the triangle, the footprint point nearest to it (core.sampling.footprint).

    uv, centre, inverse, tri_corners : as :func:`footprint_first_draw`; position : (k, 3)
    float64; offsets : (k, P, 3) float32 the footprint; half : half the box's width;
    inset : float. Output result (k, 4, 3) float32.
    """
    for k in nb.prange(uv.shape[0]):
        a0, a1 = uv[k, 0, 0], uv[k, 0, 1]
        b0, b1 = uv[k, 1, 0], uv[k, 1, 1]
        c0, c1 = uv[k, 2, 0], uv[k, 2, 1]
        scale = inverse[k]
        for corner in range(4):
            p0 = centre[k, 0] + (half if corner & 1 else -half)
            p1 = centre[k, 1] + (half if corner & 2 else -half)
            w1 = ((p0 - a0) * (c1 - a1) - (c0 - a0) * (p1 - a1)) * scale
            w2 = ((b0 - a0) * (p1 - a1) - (p0 - a0) * (b1 - a1)) * scale
            w0 = 1.0 - w1 - w2
            m0 = (w0 * tri_corners[k, 0, 0] + w1 * tri_corners[k, 1, 0] + w2 * tri_corners[k, 2, 0]) - position[k, 0]
            m1 = (w0 * tri_corners[k, 0, 1] + w1 * tri_corners[k, 1, 1] + w2 * tri_corners[k, 2, 1]) - position[k, 1]
            m2 = (w0 * tri_corners[k, 0, 2] + w1 * tri_corners[k, 1, 2] + w2 * tri_corners[k, 2, 2]) - position[k, 2]
            finite = (m0 - m0 == 0.0) and (m1 - m1 == 0.0) and (m2 - m2 == 0.0)
            if finite and w0 >= inset and w1 >= inset and w2 >= inset:
                result[k, corner, 0] = np.float32(m0)
                result[k, corner, 1] = np.float32(m1)
                result[k, corner, 2] = np.float32(m2)
                continue
            m0, m1, m2 = _nan_to_num(m0), _nan_to_num(m1), _nan_to_num(m2)
            best, nearest = np.inf, 0
            for slot in range(offsets.shape[1]):
                gap = 0.0
                step = np.float64(offsets[k, slot, 0]) - m0
                gap += step * step
                step = np.float64(offsets[k, slot, 1]) - m1
                gap += step * step
                step = np.float64(offsets[k, slot, 2]) - m2
                gap += step * step
                if gap < best:
                    best, nearest = gap, slot
            for axis in range(3):
                result[k, corner, axis] = offsets[k, nearest, axis]


_LOW32 = np.uint64(0xFFFFFFFF)


@nb.njit(inline="always")
def _hash32(x):
    """core.lights.sampler.hash32 of one value held in a uint64 (< 2^32), kept to 32 bits."""
    x = x ^ (x >> np.uint64(16))
    x = (x * np.uint64(0x7FEB352D)) & _LOW32
    x = x ^ (x >> np.uint64(15))
    x = (x * np.uint64(0x846CA68B)) & _LOW32
    return x ^ (x >> np.uint64(16))


@nb.njit(inline="always")
def _reverse32(x):
    """The 32 bits of ``x`` (a uint64 < 2^32) in reverse order."""
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << np.uint64(1))
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | ((x & np.uint64(0x33333333)) << np.uint64(2))
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | ((x & np.uint64(0x0F0F0F0F)) << np.uint64(4))
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | ((x & np.uint64(0x00FF00FF)) << np.uint64(8))
    return ((x >> np.uint64(16)) | (x << np.uint64(16))) & _LOW32


@nb.njit(inline="always")
def _owen_scramble(x, seed):
    """core.lights.sampler.owen_scramble of one 32-bit fraction (uint64 < 2^32)."""
    x = (_reverse32(x) + seed) & _LOW32
    x = x ^ ((x * np.uint64(0x6C50B47C)) & _LOW32)
    x = x ^ ((x * np.uint64(0xB82F1E52)) & _LOW32)
    x = x ^ ((x * np.uint64(0xC7AFE638)) & _LOW32)
    x = x ^ ((x * np.uint64(0x8D22F6E6)) & _LOW32)
    return _reverse32(x)


@nb.njit(**KERNEL_OPTIONS)
def footprint_jitter(pixel, triangle, sobol, jitter):
    """Every texel's footprint points in [0, 1)^2: the Sobol points Owen-scrambled by seeds
    hashed from the texel and its triangle, as core.sampling.footprint's numpy code computes
    them (integer operations, so bitwise the same).

    pixel : (k,) int64; triangle : (k,) int32; sobol : (P, 2) uint32 the first P Sobol points;
    jitter : (k, P, 2) float64, out
    """
    step = 2.0 ** -24
    for k in nb.prange(pixel.shape[0]):
        texel = np.uint64(pixel[k]) & _LOW32
        owner = np.uint64(np.uint32(triangle[k]))
        base = _hash32(texel ^ _hash32((owner + np.uint64(0x9E3779B9)) & _LOW32))
        seed_x = _hash32((base + np.uint64(0x85EBCA6B)) & _LOW32)
        seed_y = _hash32((base + np.uint64(0xC2B2AE35)) & _LOW32)
        for slot in range(sobol.shape[0]):
            jitter[k, slot, 0] = np.float64(_owen_scramble(np.uint64(sobol[slot, 0]), seed_x) >> np.uint64(8)) * step
            jitter[k, slot, 1] = np.float64(_owen_scramble(np.uint64(sobol[slot, 1]), seed_y) >> np.uint64(8)) * step


@nb.njit(**KERNEL_OPTIONS)
def footprint_offsets_of(chosen, position, offsets):
    """offsets = chosen - position, where a NaN slot of ``chosen`` (no draw inside the
    triangle) takes the position itself: chosen (k, P, 3) float64; position (k, 3) float64;
    offsets (k, P, 3) float32, out."""
    for k in nb.prange(chosen.shape[0]):
        for slot in range(chosen.shape[1]):
            for axis in range(3):
                point = chosen[k, slot, axis]
                if point != point:
                    point = position[k, axis]
                offsets[k, slot, axis] = np.float32(point - position[k, axis])


@nb.njit(**KERNEL_OPTIONS)
def footprint_point_normals(offsets, position, rows, triangle, corners, corner_normals, normal, out):
    """The shading normal at each footprint point of samples ``rows`` (core.sampling.footprint.
    footprint_normals): the point's barycentric weights on its triangle (clamped at 0, summing
    to 1) blend the corners' normals; a point whose blend is degenerate or faces away from the
    sample's own normal takes that. The numpy code's float64 operations in its order, so the
    normals are bitwise the same.

    offsets : (k, P, 3) float32; position, normal : (k, 3) float64; rows : (r,) int64;
    triangle : (k,) int; corners : (T, 3, 3) float64; corner_normals : (T, 3, 3) float32.
    Output out (k, P, 3) float32, written at ``rows`` only.
    """
    points = offsets.shape[1]
    for task in nb.prange(rows.shape[0]):
        k = rows[task]
        t = triangle[k]
        e1 = np.empty(3)
        e2 = np.empty(3)
        for i in range(3):
            e1[i] = corners[t, 1, i] - corners[t, 0, i]
            e2[i] = corners[t, 2, i] - corners[t, 0, i]
        d11 = 0.0
        d12 = 0.0
        d22 = 0.0
        for i in range(3):
            d11 += e1[i] * e1[i]
            d12 += e1[i] * e2[i]
            d22 += e2[i] * e2[i]
        denominator = d11 * d22 - d12 * d12
        scale = 1.0 / denominator if denominator > 0 else 0.0
        for p in range(points):
            d1 = 0.0
            d2 = 0.0
            for i in range(3):
                d = (position[k, i] + np.float64(offsets[k, p, i])) - corners[t, 0, i]
                d1 += d * e1[i]
                d2 += d * e2[i]
            w1 = (d22 * d1 - d12 * d2) * scale
            w2 = (d11 * d2 - d12 * d1) * scale
            w0 = 1.0 - w1 - w2
            # np.clip(w, 0, None): NaN and -0.0 kept as they are.
            w0 = 0.0 if w0 < 0.0 else w0
            w1 = 0.0 if w1 < 0.0 else w1
            w2 = 0.0 if w2 < 0.0 else w2
            total = max(w0 + w1 + w2, 1e-30)
            w0 /= total
            w1 /= total
            w2 /= total
            n0 = 0.0
            n1 = 0.0
            n2 = 0.0
            n0 += w0 * np.float64(corner_normals[t, 0, 0])
            n0 += w1 * np.float64(corner_normals[t, 1, 0])
            n0 += w2 * np.float64(corner_normals[t, 2, 0])
            n1 += w0 * np.float64(corner_normals[t, 0, 1])
            n1 += w1 * np.float64(corner_normals[t, 1, 1])
            n1 += w2 * np.float64(corner_normals[t, 2, 1])
            n2 += w0 * np.float64(corner_normals[t, 0, 2])
            n2 += w1 * np.float64(corner_normals[t, 1, 2])
            n2 += w2 * np.float64(corner_normals[t, 2, 2])
            length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if length > 1e-12:
                u0 = n0 / length
                u1 = n1 / length
                u2 = n2 / length
            else:
                u0 = 0.0
                u1 = 0.0
                u2 = 0.0
            facing = 0.0
            facing += u0 * normal[k, 0]
            facing += u1 * normal[k, 1]
            facing += u2 * normal[k, 2]
            if length > 1e-12 and facing > 0 and denominator > 0:
                out[k, p, 0] = np.float32(u0)
                out[k, p, 1] = np.float32(u1)
                out[k, p, 2] = np.float32(u2)
            else:
                out[k, p, 0] = np.float32(normal[k, 0])
                out[k, p, 1] = np.float32(normal[k, 1])
                out[k, p, 2] = np.float32(normal[k, 2])


@nb.njit(inline="always")
def _edge_length(ax, ay, az):
    return np.sqrt((ax * ax + ay * ay) + az * az)


@nb.njit(**KERNEL_OPTIONS)
def face_frames(positions, triangles, ratio, normals, valid, areas):
    """Every triangle's unit normal, whether it has one, and its area (core.geometry._face_frames:
    np.cross's products and differences, np.linalg.norm's sums, in their order, so the bits
    are numpy's).

    positions : (n, 3) float64; triangles : (m, 3) int32; ratio : tolerances'
    DEGENERATE_TRIANGLE_RATIO. Outputs normals (m, 3) float64 (zero where not valid),
    valid (m,) bool, areas (m,) float64 (NaN where a corner is not finite).
    """
    for t in nb.prange(triangles.shape[0]):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        ax = positions[i1, 0] - positions[i0, 0]
        ay = positions[i1, 1] - positions[i0, 1]
        az = positions[i1, 2] - positions[i0, 2]
        bx = positions[i2, 0] - positions[i0, 0]
        by = positions[i2, 1] - positions[i0, 1]
        bz = positions[i2, 2] - positions[i0, 2]
        cx = ay * bz - az * by
        cy = az * bx - ax * bz
        cz = ax * by - ay * bx
        length = _edge_length(cx, cy, cz)
        # A plain max, not np.maximum's NaN rules: a non-finite edge makes the cross product
        # non-finite too (inf times anything is inf or NaN), so such a triangle fails the
        # finiteness test below whatever its longest edge is.
        longest = max(_edge_length(ax, ay, az),
                      _edge_length(positions[i2, 0] - positions[i1, 0], positions[i2, 1] - positions[i1, 1],
                                   positions[i2, 2] - positions[i1, 2]),
                      _edge_length(positions[i0, 0] - positions[i2, 0], positions[i0, 1] - positions[i2, 1],
                                   positions[i0, 2] - positions[i2, 2]))
        ok = np.isfinite(length) and length > ratio * longest * longest and length > 0
        valid[t] = ok
        if ok:
            normals[t, 0] = cx / length
            normals[t, 1] = cy / length
            normals[t, 2] = cz / length
        else:
            normals[t, 0] = 0.0
            normals[t, 1] = 0.0
            normals[t, 2] = 0.0
        areas[t] = 0.5 * length
