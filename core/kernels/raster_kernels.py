"""Compiled (numba) kernels of texel-centre rasterisation (core.sampling.raster): the
claims of every triangle, in parallel over triangles, and their resolution to one owner
per texel.

Imported only through :mod:`core.kernels`. A triangle's claims are computed in the float64
operations, and order, of the numpy code (its degenerate test, canonical edges, slack
region, row spans and edge functions), so they, and the texel samples chosen from them,
are bitwise the numpy code's. Claims are counted first and then written at each
triangle's offset, so their order (by triangle, then row, then column) does not depend on
the thread count.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import KERNEL_OPTIONS, SERIAL_OPTIONS


@nb.njit(inline="always")
def _finite(value):
    return value - value == 0.0


@nb.njit(inline="always")
def _canonical(ax, ay, bx, by):
    """Origin, direction and orientation (+1.0, or -1.0 where it runs from b to a) of the
    edge from corner a to corner b, taken from its lexicographically first endpoint."""
    if bx < ax or (bx == ax and by < ay):
        return bx, by, ax - bx, ay - by, -1.0
    return ax, ay, bx - ax, by - ay, 1.0


@nb.njit(inline="always")
def _crossing(ax, ay, bx, by, yc, lo, hi):
    """Widen the row span [lo, hi] by where the row at height yc crosses segment a-b."""
    dy = by - ay
    below = yc - ay
    if below * (yc - by) <= 0 and dy != 0:
        x = ax + below / dy * (bx - ax)
        lo = min(lo, x)
        hi = max(hi, x)
    return lo, hi


@nb.njit(inline="always")
def _clip(value, low, high):
    return min(max(value, low), high)


@nb.njit(inline="always")
def _live_area(c0x, c0y, c1x, c1y, c2x, c2y, ratio):
    """Twice the signed area of the triangle with corners c0, c1, c2 (texel units), and
    whether it is live: finite corners, and an area above ``ratio`` times its longest squared
    edge (core.sampling.raster.degenerate_uv_triangles' test, in its float64 operations)."""
    if not (_finite(c0x) and _finite(c0y) and _finite(c1x) and _finite(c1y) and _finite(c2x) and _finite(c2y)):
        return 0.0, False
    area = (c1x - c0x) * (c2y - c0y) - (c1y - c0y) * (c2x - c0x)
    e0x, e0y = c1x - c0x, c1y - c0y
    e1x, e1y = c2x - c1x, c2y - c1y
    e2x, e2y = c0x - c2x, c0y - c2y
    longest = max(e0x * e0x + e0y * e0y, e1x * e1x + e1y * e1y, e2x * e2x + e2y * e2y)
    return area, _finite(area) and _finite(longest) and abs(area) > ratio * longest


@nb.njit
def _triangle_claims(uv, t, width, height, eps, margin, ratio, at, pixel, owner, strict, weight, write):
    """Count triangle ``t``'s claims, and with ``write`` store them from index ``at`` on."""
    w, h = np.float64(width), np.float64(height)
    c0x, c0y = uv[t, 0, 0] * w, uv[t, 0, 1] * h
    c1x, c1y = uv[t, 1, 0] * w, uv[t, 1, 1] * h
    c2x, c2y = uv[t, 2, 0] * w, uv[t, 2, 1] * h
    area, live = _live_area(c0x, c0y, c1x, c1y, c2x, c2y, ratio)
    if not live:
        return 0

    # The grown corners and row spans are finite: a live triangle's corners differ by less than
    # 1.4e154 (its squared edges are finite), so none lies near the float64 limit, where floats
    # are further apart than that. So min, max and clip need not propagate NaN as numpy's do.
    grow = 1.0 + 3.0 * eps
    mx = (c0x + c1x + c2x) / 3
    my = (c0y + c1y + c2y) / 3
    g0x, g0y = mx + grow * (c0x - mx), my + grow * (c0y - my)
    g1x, g1y = mx + grow * (c1x - mx), my + grow * (c1y - my)
    g2x, g2y = mx + grow * (c2x - mx), my + grow * (c2y - my)
    y0 = np.int64(_clip(np.ceil(min(g0y, g1y, g2y) - 0.5 - margin), 0.0, h))
    y1 = np.int64(_clip(np.floor(max(g0y, g1y, g2y) - 0.5 + margin), -1.0, h - 1.0))
    if y1 < y0:
        return 0  # most triangles of a dense mesh on a small image: skip their edge setup

    # Edge i is opposite corner i. Live triangles have a non-zero area, so side is +-1.
    sign = 1.0 if area > 0 else -1.0
    o0x, o0y, d0x, d0y, s0 = _canonical(c1x, c1y, c2x, c2y)
    o1x, o1y, d1x, d1y, s1 = _canonical(c2x, c2y, c0x, c0y)
    o2x, o2y, d2x, d2y, s2 = _canonical(c0x, c0y, c1x, c1y)
    s0, s1, s2 = s0 * sign, s1 * sign, s2 * sign
    below = -(eps * abs(area))

    count = 0
    for y in range(y0, y1 + 1):
        yc = y + 0.5
        lo, hi = np.inf, -np.inf
        lo, hi = _crossing(g0x, g0y, g1x, g1y, yc, lo, hi)
        lo, hi = _crossing(g1x, g1y, g2x, g2y, yc, lo, hi)
        lo, hi = _crossing(g2x, g2y, g0x, g0y, yc, lo, hi)
        if not (_finite(lo) and _finite(hi)):
            continue
        x_first = np.int64(_clip(np.ceil(lo - 0.5 - margin), 0.0, w))
        x_last = np.int64(_clip(np.floor(hi - 0.5 + margin), -1.0, w - 1.0))
        r0 = d0x * (yc - o0y)
        r1 = d1x * (yc - o1y)
        r2 = d2x * (yc - o2y)
        for x in range(x_first, x_last + 1):
            xc = x + 0.5
            edge0 = r0 - d0y * (xc - o0x)
            edge1 = r1 - d1y * (xc - o1x)
            edge2 = r2 - d2y * (xc - o2x)
            owned = ((edge0 >= 0) if s0 > 0 else (edge0 < 0)) and ((edge1 >= 0) if s1 > 0 else (edge1 < 0)) \
                and ((edge2 >= 0) if s2 > 0 else (edge2 < 0))
            inside0 = s0 * edge0
            inside1 = s1 * edge1
            inside2 = s2 * edge2
            if not (owned or (inside0 >= below and inside1 >= below and inside2 >= below)):
                continue
            if write:
                # As np.maximum(inside, 0.0): +0.0 for -0.0 too.
                w0 = 0.0 if inside0 <= 0 else inside0
                w1 = 0.0 if inside1 <= 0 else inside1
                w2 = 0.0 if inside2 <= 0 else inside2
                total = w0 + w1 + w2
                k = at + count
                pixel[k] = np.int32(y * width + x)
                owner[k] = np.int32(t)
                strict[k] = owned
                if total > 0:
                    weight[k, 0] = np.float32(w0 / total)
                    weight[k, 1] = np.float32(w1 / total)
                    weight[k, 2] = np.float32(w2 / total)
                else:
                    weight[k, 0] = weight[k, 1] = weight[k, 2] = np.float32(1.0 / 3.0)
            count += 1
    return count


@nb.njit(**KERNEL_OPTIONS)
def triangle_claims(uv, width, height, eps, margin, ratio, offsets, pixel, owner, strict, weight, write):
    """Count the texel centres each triangle claims (strictly or within the slack), or with
    ``write`` list them at each triangle's offset: by triangle, then row, then column. One
    kernel for both, so that they agree and compile once.

    uv : (m, 3, 2) float64 UV corners; width, height : int the image size in texels;
    eps, margin, ratio : float tolerances.RASTER_EDGE_EPSILON, SPAN_MARGIN and
    DEGENERATE_TRIANGLE_RATIO; offsets : (m + 1,) int64, without ``write`` an output whose
    entry t + 1 is triangle t's count (entry 0 untouched), with it their running sum from 0.
    Outputs with ``write``, each of offsets[-1] rows (otherwise of none): pixel int32 the flat
    pixel index, owner int32 the triangle, strict bool whether the fill rule gives it the
    centre, weight (n, 3) float32 its clipped, normalised barycentric weights.
    """
    for t in nb.prange(uv.shape[0]):
        if write and offsets[t + 1] == offsets[t]:
            continue
        # One call site: two made LLVM inline and optimise the helper twice (twice the compile time).
        count = _triangle_claims(uv, t, width, height, eps, margin, ratio, offsets[t], pixel, owner, strict, weight,
                                 write)
        if not write:
            offsets[t + 1] = count


@nb.njit(**SERIAL_OPTIONS)
def resolve_claims(pixel, strict, chosen, state, totals):
    """Each texel's winning claim: the first strict one, else the first slack one (claims
    come by triangle, so the first is the lowest triangle's).

    pixel : (n,) int32; strict : (n,) bool, both as :func:`triangle_claims` writes them.
    Outputs chosen (H * W,) int64 the winning claim of each texel or -1, state (H * W,) int8
    scratch, totals (2,) int64 the texels claimed, and those claimed strictly more than once.
    """
    chosen[:] = -1
    state[:] = 0  # 0: unclaimed, 1: slack claim, 2: one strict claim, 3: several
    covered = 0
    overlaps = 0
    for i in range(pixel.shape[0]):
        p = pixel[i]
        if strict[i]:
            if state[p] == 2:
                state[p] = 3
                overlaps += 1
            elif state[p] < 2:
                covered += state[p] == 0
                chosen[p] = i
                state[p] = 2
        elif state[p] == 0:
            covered += 1
            chosen[p] = i
            state[p] = 1
    totals[0] = covered
    totals[1] = overlaps


@nb.njit(**SERIAL_OPTIONS)
def gather_claims(chosen, owner, weight, pixel, triangle, barycentric, coverage):
    """The winning claims in pixel order.

    chosen : (H * W,) int64 as :func:`resolve_claims` writes it; owner, weight : as
    :func:`triangle_claims` writes them. Outputs, one row per claimed texel: pixel (k,) int64,
    triangle (k,) int32, barycentric (k, 3) float32; and coverage (H * W,) bool.
    """
    k = 0
    for p in range(chosen.shape[0]):
        i = chosen[p]
        coverage[p] = i >= 0
        if i >= 0:
            pixel[k] = p
            triangle[k] = owner[i]
            barycentric[k, 0] = weight[i, 0]
            barycentric[k, 1] = weight[i, 1]
            barycentric[k, 2] = weight[i, 2]
            k += 1


@nb.njit(**KERNEL_OPTIONS)
def uv_checks(uv, width, height, slack, ratio, degenerate, non_finite, outside):
    """What core.sampling.atlas.uv_layout_stats counts, per triangle, in parallel: whether it
    is degenerate at ``width`` x ``height`` texels (:func:`_live_area`, the test
    :func:`_triangle_claims` starts with), how many of its
    corners are not finite, and how many finite ones lie outside [-slack, 1 + slack].

    uv : (m, 3, 2) float64; slack : tolerances' UV_RANGE_SLACK; ratio : DEGENERATE_TRIANGLE_RATIO.
    Outputs degenerate (m,) bool, non_finite (m,) int8, outside (m,) int8.
    """
    w, h = np.float64(width), np.float64(height)
    low, high = -slack, 1.0 + slack
    for t in nb.prange(uv.shape[0]):
        bad, away = 0, 0
        for corner in range(3):
            u, v = uv[t, corner, 0], uv[t, corner, 1]
            if _finite(u) and _finite(v):
                if u < low or u > high or v < low or v > high:
                    away += 1
            else:
                bad += 1
        non_finite[t] = bad
        outside[t] = away
        c0x, c0y = uv[t, 0, 0] * w, uv[t, 0, 1] * h
        c1x, c1y = uv[t, 1, 0] * w, uv[t, 1, 1] * h
        c2x, c2y = uv[t, 2, 0] * w, uv[t, 2, 1] * h
        degenerate[t] = not _live_area(c0x, c0y, c1x, c1y, c2x, c2y, ratio)[1]
