"""Compiled (numba) kernels of the per-relight image work: bilinear atlas lookups at points
(contacts, near hits) and their sums per sample, the seam stitch's normal-equation product
and the gutter dilation.

Imported only through :mod:`core.kernels`. These are serial: each is a few milliseconds
on a relight's data, where a parallel loop would only add compile time (a parallel loop
compiles about three times slower) and thread start-up. The bilinear lookup is bitwise the
numpy code's (the same float32 operations in the same order), and so are the sums per sample
(bincount's order, row by row); the other two sum in a fixed
order that may round differently from numpy's einsum (within 1e-6 relative, tested).
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import SERIAL_OPTIONS


@nb.njit(**SERIAL_OPTIONS)
def _bilinear_site(widths, offsets, heights, o, u, v):
    """Where a bilinear lookup at atlas coordinate (u, v) float32 of object ``o`` reads, clamped
    to the texel centres at the atlas border: (base, stride, fx, fy), the lower-left texel's
    flat index, the row stride, and the blend weights (float64 of the float32 position)."""
    half = np.float32(0.5)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    width = np.float32(widths[o])
    height = np.float32(heights[o])
    x = min(max(u * width - half, zero), width - one)
    y = min(max(v * height - half, zero), height - one)
    x0 = np.int32(x)
    y0 = np.int32(y)
    stride = widths[o] + 1
    return offsets[o] + y0 * stride + x0, stride, np.float64(x) - np.float64(x0), np.float64(y) - np.float64(y0)


@nb.njit(**SERIAL_OPTIONS)
def _blend(flat, base, stride, c, fx, fy):
    """Channel ``c`` of the bilinear lookup at (base, stride, fx, fy) (:func:`_bilinear_site`): the
    neighbours' differences in float32, the blend in float64, as numpy promotes them."""
    c00 = flat[base, c]
    bottom = np.float64(c00) + np.float64(flat[base + 1, c] - c00) * fx
    c10 = flat[base + stride, c]
    top = np.float64(c10) + np.float64(flat[base + stride + 1, c] - c10) * fx
    return bottom + (top - bottom) * fy


@nb.njit(**SERIAL_OPTIONS)
def bilinear_points(flat, widths, heights, offsets, obj, uv, result):
    """Bilinear lookups at atlas coordinates, clamped to the texel centres at each atlas's
    border (core.transport.gather.AtlasLayout.bilinear): the texel position in float32, the
    neighbours' differences in float32 and the blend in float64, as numpy promotes them.

    flat : (size, C) float32 the padded atlases (AtlasLayout.pack); widths, heights,
    offsets : (objects,) int32; obj : (n,) int32; uv : (n, 2) float32.
    Output result (n, C) float64.
    """
    for i in range(obj.shape[0]):
        base, stride, fx, fy = _bilinear_site(widths, offsets, heights, obj[i], uv[i, 0], uv[i, 1])
        for c in range(flat.shape[1]):
            result[i, c] = _blend(flat, base, stride, c, fx, fy)


@nb.njit(**SERIAL_OPTIONS)
def contact_sums(reflected, albedo, widths, heights, offsets, obj, uv, weight, at_hits, sample, result):
    """What each short hit changes in the first bounce, summed per sample in the hits' order
    (core.transport.contacts.contact_correction): weight * (albedo / pi * at_hits - looked up),
    with both atlases read by :func:`bilinear_points`' lookup. One pass, with no (m, C)
    temporaries (four of 87 MiB each at the Production preset): bitwise the numpy code's.

    reflected : (size, C) float32 the packed reflected radiance; albedo : (size, 3) float32 the
    packed albedo (C a multiple of 3); widths, heights, offsets : (objects,) int32; obj : (m,) int32;
    uv : (m, 2) float32; weight : (m,) float32; at_hits : (m, C) float64; sample : (m,) int64.
    Output result (count, C) float64, zeroed by the caller.
    """
    for i in range(obj.shape[0]):
        base, stride, fx, fy = _bilinear_site(widths, offsets, heights, obj[i], uv[i, 0], uv[i, 1])
        w = np.float64(weight[i])
        target = sample[i]
        for c in range(reflected.shape[1]):
            lit = _blend(albedo, base, stride, c % 3, fx, fy) / np.pi * at_hits[i, c]
            result[target, c] += (lit - _blend(reflected, base, stride, c, fx, fy)) * w


@nb.njit(**SERIAL_OPTIONS)
def sum_rows(sample, values, rows, result):
    """Rows ``rows`` (m,) int64 or int32 of ``values`` (n, C) float64 (with ``rows`` of length 0: its m
    rows in order) added into ``result`` (count, C) float64 (zeroed by the caller) at rows
    ``sample`` (m,) int64 or int32, in the order given."""
    indexed = rows.shape[0] > 0
    for row in range(sample.shape[0]):
        target = sample[row]
        source = rows[row] if indexed else row
        for c in range(values.shape[1]):
            result[target, c] += values[source, c]


@nb.njit(**SERIAL_OPTIONS)
def seam_product(weight, index, keep, seam_weight, x, result):
    """The stitch's normal matrix times ``x``: keep * x + seam_weight * W^T W x, with W the
    seam points' signed bilinear weights (core.outputs.seams.Seams).

    weight : (s, 8) float64; index : (s, 8) int64; keep : (n,) float64; x : (n, C) float64.
    Output result (n, C) float64.
    """
    back = np.zeros_like(x)
    for s in range(weight.shape[0]):
        for c in range(x.shape[1]):
            residual = 0.0
            for k in range(8):
                residual += weight[s, k] * x[index[s, k], c]
            for k in range(8):
                back[index[s, k], c] += weight[s, k] * residual
    for i in range(x.shape[0]):
        for c in range(x.shape[1]):
            result[i, c] = keep[i] * x[i, c] + seam_weight * back[i, c]


@nb.njit(**SERIAL_OPTIONS)
def seam_solve(weight, index, keep, seam_weight, diagonal, rhs, limit, max_iterations, x):
    """The stitch's Jacobi-preconditioned conjugate gradients (core.outputs.seams.stitch), each
    channel its own solve, all stepped together until every channel's residual norm is at most
    its ``limit``: the numpy loop's steps, with its sums taken in index order.

    weight : (s, 8) float64; index : (s, 8) int64; keep, diagonal : (n,) float64; rhs : (n, C)
    float64; limit : (C,) float64. ``x`` (n, C) float64 holds the start and is updated.
    Returns the iterations taken.
    """
    n, channels = x.shape
    q = np.empty_like(x)
    seam_product(weight, index, keep, seam_weight, x, q)
    r = rhs - q
    z = np.empty_like(x)
    rz = np.zeros(channels)
    for i in range(n):
        for c in range(channels):
            z[i, c] = r[i, c] / diagonal[i]
            rz[c] += r[i, c] * z[i, c]
    d = z.copy()
    alpha = np.zeros(channels)
    beta = np.zeros(channels)
    dq = np.zeros(channels)
    rz_next = np.zeros(channels)
    norm = np.zeros(channels)
    iterations = 0
    while iterations < max_iterations:
        norm[:] = 0.0
        for i in range(n):
            for c in range(channels):
                norm[c] += r[i, c] * r[i, c]
        open_channel = False
        for c in range(channels):
            if np.sqrt(norm[c]) > limit[c]:
                open_channel = True
        if not open_channel:
            break
        seam_product(weight, index, keep, seam_weight, d, q)
        dq[:] = 0.0
        for i in range(n):
            for c in range(channels):
                dq[c] += d[i, c] * q[i, c]
        for c in range(channels):
            alpha[c] = rz[c] / dq[c] if dq[c] > 0 else 0.0
        rz_next[:] = 0.0
        for i in range(n):
            for c in range(channels):
                x[i, c] += alpha[c] * d[i, c]
                r[i, c] -= alpha[c] * q[i, c]
                z[i, c] = r[i, c] / diagonal[i]
                rz_next[c] += r[i, c] * z[i, c]
        for c in range(channels):
            beta[c] = rz_next[c] / rz[c] if rz[c] > 0 else 0.0
            rz[c] = rz_next[c]
        for i in range(n):
            for c in range(channels):
                d[i, c] = z[i, c] + beta[c] * d[i, c]
        iterations += 1
    return iterations


@nb.njit(**SERIAL_OPTIONS)
def dilate_rings(values, known, frontier, width, height, margin):
    """``margin`` passes of the gutter dilation (core.outputs.dilation.dilate): every
    still-empty texel with a filled 8-neighbour takes those neighbours' mean, as filled at
    the start of the pass, then counts as filled.

    values : (H * W, C) float32, filled where ``known``; known : (H * W,) bool, updated;
    frontier : (f,) int64 the first pass's empty texels next to filled ones.
    """
    channels = values.shape[1]
    terms = np.zeros((8, channels), np.float32)
    queued = np.zeros(known.shape[0], np.bool_)
    for _ in range(margin):
        if frontier.shape[0] == 0:
            break
        fresh = np.empty((frontier.shape[0], channels), np.float32)
        for f in range(frontier.shape[0]):
            texel = frontier[f]
            tx = texel % width
            ty = texel // width
            count = 0
            # Bit for bit what numpy's einsum("fn,fnc->fc") gives (the GPU twin matches it
            # too): all 8 neighbours in _neighbours8's order, outside ones clamped into the
            # image with weight 0 (so 0 * inf stays NaN), each term weight * value.
            n = 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    if dx == 0 and dy == 0:
                        continue
                    x = tx + dx
                    y = ty + dy
                    inside = x >= 0 and x < width and y >= 0 and y < height
                    neighbour = min(max(y, 0), height - 1) * width + min(max(x, 0), width - 1)
                    weight = np.float32(0.0)
                    if inside and known[neighbour]:
                        weight = np.float32(1.0)
                        count += 1
                    for c in range(channels):
                        terms[n, c] = weight * values[neighbour, c]
                    n += 1
            for c in range(channels):
                if channels == 1:
                    # One channel: einsum's reduced axis is contiguous and it sums 4-wide
                    # SIMD lanes (n, n + 4), then the lanes pairwise.
                    total = ((terms[0, c] + terms[4, c]) + (terms[1, c] + terms[5, c])) + \
                            ((terms[2, c] + terms[6, c]) + (terms[3, c] + terms[7, c]))
                else:
                    total = np.float32(0.0)
                    for k in range(8):
                        total += terms[k, c]
                # numpy divides in float64 and rounds to float32: for a division that
                # equals the correctly rounded float32 quotient.
                fresh[f, c] = np.float32(np.float64(total) / np.float64(count))
        for f in range(frontier.shape[0]):
            known[frontier[f]] = True
            for c in range(channels):
                values[frontier[f], c] = fresh[f, c]
        # The next ring: empty neighbours of this one, each once (a queued texel is filled by
        # the next pass, so its flag never needs clearing), in texel order.
        following = np.empty(frontier.shape[0] * 8, np.int64)
        size = 0
        for f in range(frontier.shape[0]):
            texel = frontier[f]
            tx = texel % width
            ty = texel // width
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    x = tx + dx
                    y = ty + dy
                    if x < 0 or x >= width or y < 0 or y >= height:
                        continue
                    neighbour = y * width + x
                    if not known[neighbour] and not queued[neighbour]:
                        queued[neighbour] = True
                        following[size] = neighbour
                        size += 1
        frontier = np.sort(following[:size])
