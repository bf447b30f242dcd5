"""Where in its texel a sample's light is measured: points spread over the texel's footprint.

A texel of a baked image stands for an area of surface, not its centre. Cycles' bake
(``init_from_bake.h`` with Blender's ``bake_differentials``) averages every texel over a box
around the centre, one texel wide in x and y since Blender 5.2.1 and half a texel before
(the differentials carried a factor 1/2; measured in tests/blender/test_cycles_bake.py),
keeping only the points that lie inside the texel's own triangle: a point outside is drawn
again, up to ten times, and otherwise the centre stands in. That is a box filter clipped
to the triangle, so a border texel is the mean of the part of its box on its own face and
never of the surface beyond the face's edge (another face of the mesh, or the gutter).

:func:`footprint_offsets` gives each sample ``count`` such points, as offsets from the
sample's position: a stratified 2D set (Sobol, Owen-scrambled per texel so neighbouring
texels do not share a pattern), each point drawn up to :data:`REDRAWS` times until it
lies inside the triangle, and otherwise the sample's own position (the texel's centre), as
Cycles does. On a mesh whose triangles are smaller than the box, that centre weighs a
large share of the texel (about 43% where the triangle covers 8% of the box), in Cycles
and here alike. Every slot holds a usable point, and consumers simply use slot
``j % count``. The visibility table starts direction i's ray from slot ``i % count``, so
the table itself averages the footprint; exact shadows average all slots, and direct
light is shaded with each point's own normal (:func:`footprint_normals`).
"""
from __future__ import annotations

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..lights.sampler import hash32, owen_scramble, sobol_point

# Width of the box each texel is averaged over, in texels, unless the caller names another:
# the area the texel stands for, as Cycles' bake averages it since Blender 5.2.1 (Blender
# 4.2 to 5.2.0 jitter over half of it; the Blender adapter passes the running Cycles' width,
# BakeSettings.footprint_width).
BOX_WIDTH = 1.0
# A point is drawn this many times before its slot gives up and takes the centre (Cycles'
# bake_jitter_barycentric tries ten jitters).
REDRAWS = 10


def _first_sobol_points(count: int) -> np.ndarray:
    """(count, 2) uint32: the first ``count`` points of the first two Sobol dimensions."""
    return np.array([sobol_point(index)[:2] for index in range(count)], np.uint32).reshape(count, 2)


def _scrambled_points(count: int, seeds: np.ndarray) -> np.ndarray:
    """(k, count, 2) float64 in [0, 1): the first ``count`` 2D Sobol points, Owen-scrambled
    per sample by ``seeds`` (2, k) uint32."""
    samples = seeds.shape[1]
    sobol = _first_sobol_points(count)
    points = np.empty((samples, count, 2))
    # Every point of a block of samples in one pass of integer operations: a pass per point
    # costs ~40 numpy calls, which dominated for the few texels of a shadow edge (64 points
    # each); blocks of about 2^16 values stay in cache for the millions of a whole atlas.
    block = max(1, (1 << 15) // max(count, 1))
    for start in range(0, samples, block):
        part = seeds[:, start:start + block].T[:, None, :]  # (b, 1, 2)
        scrambled = owen_scramble(np.broadcast_to(sobol, (len(part), count, 2)),
                                  np.broadcast_to(part, (len(part), count, 2)))
        points[start:start + block] = (scrambled >> np.uint32(8)) * 2.0 ** -24
    return points


def footprint_offsets(pixel: np.ndarray, triangle: np.ndarray, width: int, height: int,
                      corner_uv: np.ndarray, corners: np.ndarray, position: np.ndarray, count: int,
                      threads: int = 0, seed_triangle: np.ndarray | None = None,
                      box_width: float = BOX_WIDTH) -> np.ndarray:
    """Offsets of each sample's footprint points from its position.

    Parameters
    ----------
    pixel : (k,) int64 flat texel index ``y * width + x``
    triangle : (k,) int32 the owning triangle of each texel
    corner_uv : (T, 3, 2) float the bake UVs of every triangle's corners
    corners : (T, 3, 3) float64 the world positions of every triangle's corners
    position : (k, 3) float64 each sample's own position (on its triangle)
    count : points per sample (1: the sample itself, offset 0)
    threads : the compiled kernels' thread count (0: all cores); the result does not depend on it
    seed_triangle : (k,) int32 the owning triangles where ``triangle`` only indexes ``corner_uv``
        and ``corners`` given per sample (``triangle`` then 0..k-1): the draws are seeded by
        the mesh's own triangle (None: ``triangle`` is it)
    box_width : the width of each texel's box, in texels

    Returns
    -------
    offsets : (k, count, 3) float32 world-space offsets; ``position + offsets[:, j]`` lies
        on the sample's triangle, within the texel's box (``box_width`` wide) around its centre
    """
    samples = len(pixel)
    if count <= 1 or samples == 0:
        return np.zeros((samples, max(count, 1), 3), np.float32)
    # Texel space: the triangle's corners in texel units, the texel's centre at (x + .5, y + .5).
    uv = np.asarray(corner_uv, np.float64)[triangle] * np.array([width, height], np.float64)
    centre = np.stack([pixel % width + 0.5, pixel // width + 0.5], axis=1).astype(np.float64)
    a, b, c = uv[:, 0], uv[:, 1], uv[:, 2]
    doubled = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    usable = np.abs(doubled) > 0
    inverse = np.divide(1.0, doubled, out=np.zeros_like(doubled), where=usable)

    def barycentric_of_slots(point):  # (k, count, 2) points of every texel, the same arithmetic
        pa, pb, pc, scale = a[:, None, :], b[:, None, :], c[:, None, :], inverse[:, None]
        x, y = point[..., 0] - pa[..., 0], point[..., 1] - pa[..., 1]
        w1 = (x * (pc[..., 1] - pa[..., 1]) - (pc[..., 0] - pa[..., 0]) * y) * scale
        w2 = ((pb[..., 0] - pa[..., 0]) * y - x * (pb[..., 1] - pa[..., 1])) * scale
        return np.stack([1.0 - w1 - w2, w1, w2], axis=2)

    module = kernels.compiled()
    jitter = footprint_jitter(pixel, triangle if seed_triangle is None else seed_triangle, count, module, threads)
    tri_corners = np.asarray(corners, np.float64)[triangle]  # (k, 3, 3)
    # The first draw of every slot at once: most land inside at once, and only the rest
    # (border texels, triangles smaller than the box) loop over their redraws.
    if module is not None:
        chosen = np.empty((samples, count, 3))
        inside = np.empty((samples, count), bool)
        kernels.run(module.footprint_first_draw, threads, np.ascontiguousarray(uv), centre, inverse, usable,
                    jitter, np.ascontiguousarray(tri_corners), box_width, tol.SAMPLE_BARYCENTRIC_INSET, chosen, inside)
    else:
        first = barycentric_of_slots(centre[:, None, :] + (jitter - 0.5) * box_width)  # (k, count, 3)
        inside = np.all(first >= tol.SAMPLE_BARYCENTRIC_INSET, axis=2) & usable[:, None]
        chosen = (first[..., 0:1] * tri_corners[:, None, 0] + first[..., 1:2] * tri_corners[:, None, 1]
                  + first[..., 2:3] * tri_corners[:, None, 2])
        del first
        chosen[~inside] = np.nan
    # Cycles redraws from a hash of the rejected point; so does this, per texel and slot.
    if module is not None:
        kernels.run(module.footprint_redraws, threads, np.ascontiguousarray(uv), centre, inverse, usable, jitter,
                    np.ascontiguousarray(tri_corners), box_width, tol.SAMPLE_BARYCENTRIC_INSET, REDRAWS, chosen,
                    inside)
    else:
        _redraw(uv, centre, inverse, usable, jitter, tri_corners, chosen, inside, box_width)
    # A slot that found no place inside takes the centre, as Cycles' sample does.
    if module is not None:
        offsets = np.empty((samples, count, 3), np.float32)
        kernels.run(module.footprint_offsets_of, threads, chosen, np.ascontiguousarray(position, np.float64), offsets)
        return offsets
    points = np.where(np.isnan(chosen), position[:, None, :], chosen)
    return (points - position[:, None, :]).astype(np.float32)


def _redraw(uv: np.ndarray, centre: np.ndarray, inverse: np.ndarray, usable: np.ndarray, jitter: np.ndarray,
            tri_corners: np.ndarray, chosen: np.ndarray, inside: np.ndarray, box_width: float) -> None:
    """The redraws of every slot whose first draw fell outside its triangle, in numpy (the
    compiled twin is core.kernels.sample_kernels.footprint_redraws): each draws again from a
    hash of its last draw, up to REDRAWS - 1 times; a slot that lands inside gets its point in
    ``chosen`` (k, P, 3) float64, the others keep NaN. uv (k, 3, 2), centre (k, 2), inverse
    (k,), tri_corners (k, 3, 3) float64; usable (k,) and inside (k, P) bool; jitter (k, P, 2);
    box_width in texels."""
    rows, slots = np.nonzero(~inside & usable[:, None])
    u = jitter[rows, slots]
    for attempt in range(1, REDRAWS):
        if not len(rows):
            break
        bits = (u * 2.0 ** 24).astype(np.uint32)
        salt = np.uint32((0x68E31DA4 * attempt) & 0xFFFFFFFF)
        u = np.stack([hash32(bits[:, 0] ^ hash32(bits[:, 1] + np.uint32(attempt))),
                      hash32(bits[:, 1] ^ hash32(bits[:, 0] + salt))], axis=1)
        u = (u >> np.uint32(8)) * 2.0 ** -24
        point = centre[rows] + (u - 0.5) * box_width
        pa, pb, pc, scale = uv[rows, 0], uv[rows, 1], uv[rows, 2], inverse[rows]
        x, y = point[:, 0] - pa[:, 0], point[:, 1] - pa[:, 1]
        w1 = (x * (pc[:, 1] - pa[:, 1]) - (pc[:, 0] - pa[:, 0]) * y) * scale
        w2 = ((pb[:, 0] - pa[:, 0]) * y - x * (pb[:, 1] - pa[:, 1])) * scale
        weights = np.stack([1.0 - w1 - w2, w1, w2], axis=1)
        found = np.all(weights >= tol.SAMPLE_BARYCENTRIC_INSET, axis=1)
        chosen[rows[found], slots[found]] = np.einsum("kc,kcd->kd", weights[found], tri_corners[rows[found]])
        rows, slots, u = rows[~found], slots[~found], u[~found]


def footprint_jitter(pixel: np.ndarray, triangle: np.ndarray, count: int, module=None, threads: int = 0
                     ) -> np.ndarray:
    """(k, count, 2) float64 in [0, 1): each texel's first draws in its box, the first
    ``count`` 2D Sobol points Owen-scrambled per texel.

    Seeded by the texel and its triangle only: an object's points do not depend on which
    other objects are in the bake, so an incremental table update reproduces them.
    pixel : (k,) int64; triangle : (k,) int32; module : the compiled kernels (bitwise the
    numpy code's integers), or None for numpy.
    """
    if module is not None:
        jitter = np.empty((len(pixel), count, 2))
        sobol = _first_sobol_points(count)
        kernels.run(module.footprint_jitter, threads, np.ascontiguousarray(pixel, np.int64),
                    np.ascontiguousarray(triangle, np.int32), sobol, jitter)
        return jitter
    base = hash32(np.asarray(pixel, np.uint64).astype(np.uint32) ^ hash32(np.asarray(triangle, np.uint32)
                                                                        + np.uint32(0x9E3779B9)))
    seeds = np.stack([hash32(base + np.uint32(0x85EBCA6B)), hash32(base + np.uint32(0xC2B2AE35))])
    return _scrambled_points(count, seeds)


def footprint_corners(pixel: np.ndarray, triangle: np.ndarray, width: int, height: int,
                      corner_uv: np.ndarray, corners: np.ndarray, position: np.ndarray,
                      offsets: np.ndarray, threads: int = 0, box_width: float = BOX_WIDTH) -> np.ndarray:
    """(k, 4, 3) float32 offsets from each sample's position to the four corners of its box
    (``box_width`` texels wide), or where a corner lies beyond the texel's own triangle, to the
    texel's footprint point (``offsets`` (k, P, 3), :func:`footprint_offsets`) nearest to it.

    A straight shadow edge that crosses the box separates at least one corner from the
    others, so rays from the corners tell a texel the edge crosses from one it misses, which
    a few of the (random) footprint points can fail to do. A corner beyond the triangle is
    never used itself: the plane's continuation runs into the ground or the air on a curved
    or finely tessellated surface, and onto the neighbouring face's edge on a flat one.
    Other arguments as :func:`footprint_offsets`.
    """
    if len(pixel) == 0:
        return np.zeros((0, 4, 3), np.float32)
    uv = np.asarray(corner_uv, np.float64)[triangle] * np.array([width, height], np.float64)
    centre = np.stack([pixel % width + 0.5, pixel // width + 0.5], axis=1).astype(np.float64)
    a, b, c = uv[:, 0], uv[:, 1], uv[:, 2]
    doubled = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    inverse = np.divide(1.0, doubled, out=np.zeros_like(doubled), where=np.abs(doubled) > 0)
    tri_corners = np.asarray(corners, np.float64)[triangle]
    result = np.empty((len(pixel), 4, 3), np.float32)
    half = box_width / 2
    module = kernels.compiled()
    if module is not None:
        kernels.run(module.footprint_corners, threads, np.ascontiguousarray(uv), centre, inverse, tri_corners,
                    np.ascontiguousarray(position, np.float64), np.ascontiguousarray(offsets, np.float32), half,
                    tol.SAMPLE_BARYCENTRIC_INSET, result)
        return result
    for index, (sx, sy) in enumerate(((-1, -1), (1, -1), (-1, 1), (1, 1))):
        point = centre + np.array([sx * half, sy * half])
        w1 = ((point[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (point[:, 1] - a[:, 1])) * inverse
        w2 = ((b[:, 0] - a[:, 0]) * (point[:, 1] - a[:, 1]) - (point[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) * inverse
        weights = np.stack([1.0 - w1 - w2, w1, w2], axis=1)
        moved = np.einsum("kc,kcd->kd", weights, tri_corners) - position
        inside = np.all(weights >= tol.SAMPLE_BARYCENTRIC_INSET, axis=1) & np.all(np.isfinite(moved), axis=1)
        gap = np.einsum("kpd,kpd->kp", offsets - np.nan_to_num(moved)[:, None, :],
                        offsets - np.nan_to_num(moved)[:, None, :])
        nearest = offsets[np.arange(len(pixel)), np.argmin(gap, axis=1)]
        result[:, index] = np.where(inside[:, None], moved, nearest)
    return result



def footprint_normals(offsets: np.ndarray, position: np.ndarray, triangle: np.ndarray, corners: np.ndarray,
                      corner_normals: np.ndarray, normal: np.ndarray, smooth: np.ndarray, threads: int = 0
                      ) -> np.ndarray:
    """The shading normal at each footprint point, as Cycles shades its jittered bake samples.

    On a smooth face the normal turns across a texel, and where a texel spans a large angle
    (a thin cylinder's few texels around) the light of its points differs from that of its
    centre; Cycles averages it, so the direct light does too.

    Parameters
    ----------
    offsets : (k, P, 3) float footprint points relative to ``position`` (k, 3) float64
    triangle : (k,) int the sample's triangle; corners, corner_normals : (T, 3, 3) float
        every triangle's corner positions and shading normals
    normal : (k, 3) float64 each sample's own unit shading normal (the points of a flat
        face, ``smooth`` (k,) bool False, all take it)
    threads : the compiled kernels' thread count (0: all cores); the result does not depend on it

    Returns
    -------
    (k, P, 3) float32 unit normals (a point's normal facing away from ``normal`` takes
    ``normal``, as the sample's own does its face's)
    """
    out = np.broadcast_to(np.asarray(normal, np.float32)[:, None, :], offsets.shape).copy()
    rows = np.flatnonzero(smooth)
    if not len(rows):
        return out
    module = kernels.compiled()
    if module is not None:
        # Compiled (bitwise the numpy code below): its (r, P, 3) float64 temporaries took most
        # of a bake's sample placement (0.6 s of the demo's 1.6 s).
        kernels.run(module.footprint_point_normals, threads, np.ascontiguousarray(offsets, np.float32),
                    np.ascontiguousarray(position, np.float64), rows.astype(np.int64), np.asarray(triangle, np.int64),
                    np.ascontiguousarray(corners, np.float64), np.ascontiguousarray(corner_normals, np.float32),
                    np.ascontiguousarray(normal, np.float64), out)
        return out
    a, b, c = (np.asarray(corners, np.float64)[triangle[rows], i] for i in range(3))
    points = np.asarray(position, np.float64)[rows, None, :] + np.asarray(offsets, np.float64)[rows]
    e1, e2 = (b - a)[:, None, :], (c - a)[:, None, :]
    d = points - a[:, None, :]
    d11, d12, d22 = (np.einsum("kpd,kpd->kp", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    d1, d2 = np.einsum("kpd,kpd->kp", d, e1), np.einsum("kpd,kpd->kp", d, e2)
    denominator = d11 * d22 - d12 * d12
    scale = np.divide(1.0, denominator, out=np.zeros_like(denominator), where=denominator > 0)
    w1 = (d22 * d1 - d12 * d2) * scale
    w2 = (d11 * d2 - d12 * d1) * scale
    weights = np.clip(np.stack([1.0 - w1 - w2, w1, w2], axis=-1), 0.0, None)  # (r, P, 3)
    weights /= np.maximum(weights.sum(axis=-1, keepdims=True), 1e-30)
    smooth_normals = np.einsum("kpc,kcd->kpd", weights, np.asarray(corner_normals, np.float64)[triangle[rows]])
    length = np.linalg.norm(smooth_normals, axis=-1, keepdims=True)
    unit = np.divide(smooth_normals, length, out=np.zeros_like(smooth_normals), where=length > 1e-12)
    own = np.asarray(normal, np.float64)[rows, None, :]
    usable = (length[..., 0] > 1e-12) & (np.einsum("kpd,kpd->kp", unit, own) > 0) & (denominator > 0)
    out[rows] = np.where(usable[..., None], unit, own).astype(np.float32)
    return out
