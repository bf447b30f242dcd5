"""Periodic micro-geometry tiles for BRDF simulation (pure numpy, no bpy).

A tile is ``(positions (P, 3) float64, triangles (T, 3) int32, period (2,) float64)``:
the surface of one period of a doubly periodic micro-geometry, lying in the column
``[0, px] x [0, py]`` of the XY plane, z up (the macro surface is a plane z = const,
normal +z). Copies translated by ``(i * px, j * py, 0)`` join without gaps or overlaps:
the border of the tile at x = 0 is the border at x = px translated by ``-px`` (same for
y), vertex for vertex. Triangles are wound counter-clockwise seen from outside (the
geometric normal points out of the material, up for height fields).

Units are free (metres in Blender); a BRDF does not depend on the scale, only on shape.

Builders
--------
``flat_tile(size)``                  one quad: the Lambert sanity check (f = albedo / pi).
``v_groove_tile(depth, period, grooves)``  V-grooves along Y (profile in X), rims at z = depth,
                                     bottoms at z = 0.
``woven_tile(...)``                  plain weave: two warp threads (along Y) and two weft
                                     threads (along X) per period, tubes of elliptical
                                     vertical section on sinusoidal centre lines, going over
                                     and under alternately with a guaranteed vertical gap.
``heightfield_tile(heights, period)`` a periodic height field on a wrapped grid.

``v_groove_direct_brdf`` is the closed-form single-scattering (direct light only) BRDF of
``v_groove_tile`` (shadowing and masking of a V-cavity), the analytic check of the
Cycles harness (benchmarks/brdf_reference.py) with diffuse bounces = 0.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["flat_tile", "v_groove_tile", "woven_tile", "heightfield_tile", "tile_height",
           "v_groove_direct_brdf", "woven_min_gap", "vertical_intervals"]


def _tile(positions, triangles, period):
    return (np.ascontiguousarray(positions, np.float64), np.ascontiguousarray(triangles, np.int32),
            np.asarray(period, np.float64).reshape(2))


def _grid_triangles(n_u: int, n_v: int, stride: int) -> np.ndarray:
    """Two triangles per cell of a (n_u + 1) x (n_v + 1) vertex grid (index u * stride + v),
    wound (u, v) -> (u + 1, v) -> (u + 1, v + 1): counter-clockwise when u, v, out form a
    right-handed frame."""
    u, v = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a = (u * stride + v).ravel()
    b = ((u + 1) * stride + v).ravel()
    c = ((u + 1) * stride + v + 1).ravel()
    d = (u * stride + v + 1).ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)


def tile_height(positions: np.ndarray) -> float:
    """Vertical extent (max z - min z) of a tile: how far its neighbours can shadow."""
    z = np.asarray(positions)[:, 2]
    return float(z.max() - z.min())


def flat_tile(size: float = 1.0):
    """One square quad [0, size]^2 at z = 0 (2 triangles, normal +z)."""
    s = float(size)
    positions = [(0.0, 0.0, 0.0), (s, 0.0, 0.0), (s, s, 0.0), (0.0, s, 0.0)]
    return _tile(positions, [(0, 1, 2), (0, 2, 3)], (s, s))


def v_groove_tile(depth: float, period: float = 1.0, grooves: int = 1):
    """V-grooves parallel to Y: ``grooves`` symmetric Vs across [0, period] in X, rims at
    z = depth (x = k * period / grooves), bottoms at z = 0, extruded over [0, period] in Y.
    Facet slope: tan(alpha) = 2 * depth * grooves / period."""
    if grooves < 1:
        raise ValueError("grooves must be >= 1")
    n = 2 * grooves  # facets
    x = np.linspace(0.0, float(period), n + 1)
    z = np.where(np.arange(n + 1) % 2 == 0, float(depth), 0.0)
    # vertex (k, j): profile point k at y = j * period, index k * 2 + j
    positions = np.zeros((n + 1, 2, 3))
    positions[:, :, 0] = x[:, None]
    positions[:, 1, 1] = period
    positions[:, :, 2] = z[:, None]
    # u = profile index (+x), v = y: (x, y, z-up) frame -> normals up
    return _tile(positions.reshape(-1, 3), _grid_triangles(n, 1, 2), (period, period))


def heightfield_tile(heights, period=(1.0, 1.0)):
    """A periodic height field: ``heights[j, i]`` is z at (x, y) = (i * px / nx, j * py / ny),
    shape (ny, nx); the grid is wrapped (row/column nx, ny repeat row/column 0), so the
    tile has (nx + 1) * (ny + 1) vertices and 2 * nx * ny triangles (each cell split along
    the same diagonal)."""
    h = np.asarray(heights, np.float64)
    if h.ndim != 2 or min(h.shape) < 1:
        raise ValueError("heights must be a 2-D array")
    ny, nx = h.shape
    px, py = np.broadcast_to(np.asarray(period, np.float64), (2,))
    i = np.arange(nx + 1)
    j = np.arange(ny + 1)
    ii, jj = np.meshgrid(i, j, indexing="ij")  # vertex (i, j) at index i * (ny + 1) + j
    positions = np.stack([ii * px / nx, jj * py / ny, h[jj % ny, ii % nx]], -1).reshape(-1, 3)
    return _tile(positions, _grid_triangles(nx, ny, ny + 1), (px, py))


# ----------------------------------------------------------------------------- weave


def _weave_profile(t, half_width, half_thickness, amplitude, spacing):
    """Vertical gap contribution h(t) of one thread at a crossing (see woven_min_gap)."""
    c = np.sqrt(np.clip(1.0 - (t / half_width) ** 2, 0.0, None))
    return amplitude * np.cos(np.pi * t / spacing) - half_thickness * c


def woven_min_gap(amplitude: float, half_width: float, half_thickness: float, spacing: float) -> float:
    """Smallest vertical gap between a warp and a weft thread of ``woven_tile`` (exact
    centre lines and ellipses, before meshing).

    At a crossing (local coordinates u across the warp, t across the weft) the upper
    thread's bottom minus the lower thread's top is h(t) + h(u) with
    h(t) = a cos(pi t / s) - r_z sqrt(1 - t^2 / r_w^2) on |t| <= r_w, so the minimum is
    2 min h.
    """
    t = np.linspace(0.0, half_width, 4001)
    return float(2.0 * _weave_profile(t, half_width, half_thickness, amplitude, spacing).min())


def woven_tile(period: float = 1.0, width: float = 0.8, thickness: float = 0.12, gap: float = 0.02,
               amplitude: float | None = None, n_along: int = 24, n_around: int = 12):
    """A plain weave: two warp threads (along Y, at x = period/4, 3 period/4) and two weft
    threads (along X, at y = period/4, 3 period/4) per period, each going over and under
    the crossing threads alternately.

    Each thread is a tube whose *vertical* cross-section is an ellipse of half width
    ``width * s / 2`` (s = period / 2, the thread spacing) and half height
    ``thickness / 2``, centred on the sinusoid z = +-amplitude cos(pi (t - s/2) / s) along
    the thread. Warp j is up (+amplitude) over weft i where i + j is even; the weft is
    then down. Vertical sections make each tube occupy one z-interval per (x, y) column,
    so the threads do not interpenetrate iff their column intervals are disjoint; the
    smallest vertical gap is ``woven_min_gap(...)``. ``amplitude=None`` picks the
    amplitude whose gap is ``gap`` before meshing (the meshed default tile's smallest gap,
measured by vertical rays: 0.0203 for 0.02; its height is 0.293 for a period of 1).

    The tube of each thread spans exactly one period along its axis: its end rings at
    0 and ``period`` match the next tile's, so the repeated threads are closed tubes.
    There is nothing underneath: light through the pores between threads escapes.
    4 * n_along * n_around * 2 triangles (2304 by default).
    """
    s = period / 2.0
    r_w = width * s / 2.0
    r_z = thickness / 2.0
    if not 0.0 < width < 1.0:
        raise ValueError("width must be in (0, 1): a fraction of the thread spacing")
    if amplitude is None:
        # the gap is linear and increasing in the amplitude: bisect
        lo, hi = 0.0, 10.0 * (r_z + gap + period)
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if woven_min_gap(mid, r_w, r_z, s) < gap else (lo, mid)
        amplitude = hi
    a = float(amplitude)
    t = np.linspace(0.0, period, n_along + 1)  # along the thread, both end rings
    phi = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    positions, triangles = [], []
    offset = 0
    for axis in ("warp", "weft"):
        for k in range(2):
            centre = (k + 0.5) * s
            # warp k at weft i (t = (i + 0.5) s): a (-1)^k cos(pi i) = a (-1)^(i+k); the weft
            # is the opposite: -a (-1)^(i+k)
            sign = (-1.0) ** k * (1.0 if axis == "warp" else -1.0)
            zc = sign * a * np.cos(np.pi * (t - s / 2.0) / s)
            across = centre + r_w * np.cos(phi)  # (n_around,)
            z = zc[:, None] + r_z * np.sin(phi)[None, :]  # (n_along + 1, n_around)
            along = np.broadcast_to(t[:, None], z.shape)
            across = np.broadcast_to(across[None, :], z.shape)
            if axis == "warp":  # along +Y, section in XZ
                verts = np.stack([across, along, z], -1).reshape(-1, 3)
            else:  # along +X, section in YZ
                verts = np.stack([along, across, z], -1).reshape(-1, 3)
            tri = _wrap_seam(n_along, n_around)
            # _wrap_seam winds (along, around): its normal is d_along x d_around, outward for
            # the warp (y x (-sin, 0, cos) = (cos, 0, sin)) and inward for the weft
            # (x x (0, -sin, cos) = (0, -cos, -sin)): reverse the weft's triangles.
            if axis == "weft":
                tri = tri[:, ::-1]
            positions.append(verts)
            triangles.append(tri + offset)
            offset += len(verts)
    positions = np.concatenate(positions)
    triangles = np.concatenate(triangles)
    return _tile(positions, triangles, (period, period))


def _wrap_seam(n_along: int, n_around: int) -> np.ndarray:
    """Triangles of a tube: rings u = 0..n_along of n_around vertices (index u * n_around + v),
    the section closed (v = n_around is v = 0)."""
    u, v = np.meshgrid(np.arange(n_along), np.arange(n_around), indexing="ij")
    v1 = (v + 1) % n_around
    a = (u * n_around + v).ravel()
    b = ((u + 1) * n_around + v).ravel()
    c = ((u + 1) * n_around + v1).ravel()
    d = (u * n_around + v1).ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)


# ----------------------------------------------------------------------------- checks


def vertical_intervals(positions, triangles, xy):
    """z of every crossing of the vertical lines through ``xy`` (N, 2) with the triangles:
    a list of N sorted arrays (pure numpy; for tests of tiles, e.g. that the threads of
    ``woven_tile`` do not overlap)."""
    p = np.asarray(positions, np.float64)
    tri = p[np.asarray(triangles)]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    out = []
    for x, y in np.asarray(xy, np.float64):
        # barycentric coordinates of (x, y) in each triangle's XY projection
        v0 = b[:, :2] - a[:, :2]
        v1 = c[:, :2] - a[:, :2]
        v2 = np.array([x, y]) - a[:, :2]
        den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
        ok = np.abs(den) > 1e-15
        den = np.where(ok, den, 1.0)
        beta = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
        gamma = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
        inside = ok & (beta >= 0) & (gamma >= 0) & (beta + gamma <= 1)
        z = (a[:, 2] + beta * (b[:, 2] - a[:, 2]) + gamma * (c[:, 2] - a[:, 2]))[inside]
        out.append(np.sort(z))
    return out


def v_groove_direct_brdf(depth: float, albedo, l, v, period: float = 1.0, grooves: int = 1):
    """Closed-form BRDF of ``v_groove_tile(depth, period, grooves)`` with direct light only
    (a Lambert material of ``albedo``, a collimated light along ``l``, seen along ``v``;
    unit vectors, z up). Light and view may have any azimuth: the grooves run along Y, so
    shadowing and masking depend on the projections of l and v on the XZ plane.

    Each facet (outward normal n, slope alpha) is lit over a top part of fraction
    g(l) and seen over a top part of fraction g(v), where g(w) = 1 if w leans away from
    the rim that faces it (or lies along the grooves) and else
    min(1, 2 / (1 + tan(alpha) |w_x| / w_z)); both parts start at the facet's rim, so the
    part both lit and seen is min(g(l), g(v)). With facet area A_f per cell of area A:

        f = albedo / pi * sum_f (n.l)+ (n.v)+ min(g_l, g_v) A_f / (A cos(theta_l) cos(theta_v))
    """
    l = np.asarray(l, np.float64)
    v = np.asarray(v, np.float64)
    w = period / grooves
    alpha = math.atan2(depth, w / 2.0)
    facet = (w / 2.0) / math.cos(alpha)  # facet length across the groove
    total = 0.0
    for sx in (1.0, -1.0):  # +1: facet descending from its rim at smaller x, faces +x
        n = np.array([sx * math.sin(alpha), 0.0, math.cos(alpha)])
        nl, nv = float(n @ l), float(n @ v)
        if nl <= 0.0 or nv <= 0.0:
            continue

        def g(d, sx=sx):
            if d[0] * sx <= 0.0:  # leans towards the facet's own rim: nothing in the way
                return 1.0
            return min(1.0, 2.0 / (1.0 + math.tan(alpha) * abs(d[0]) / d[2]))

        total += nl * nv * min(g(l), g(v)) * facet
    # per groove: two facets over a width w (areas per unit length in y)
    return np.asarray(albedo, np.float64) / math.pi * total / (w * l[2] * v[2])
