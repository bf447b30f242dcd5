"""Texel-centre rasterisation of UV triangles, and gutter dilation.

Conventions (shared with Blender's ``Image.pixels``): an image of ``width`` W and
``height`` H has texel (x, y), x in [0, W), y in [0, H), row y = 0 at the bottom
(v small); its centre is uv = ((x + 0.5) / W, (y + 0.5) / H) and its flat index is
``y * W + x``.

Which triangle owns a texel
---------------------------
A texel is sampled at its centre only. The rule has two tiers:

1. *Strict ownership* (a fill convention, so a watertight UV island is covered
   exactly once). A centre strictly inside a triangle belongs to it. A centre
   exactly on an edge belongs to the triangle whose interior lies *above* that
   edge, or to its *left* when the edge is vertical ("bottom-right rule"; the
   mirror image of the GPU top-left rule). This equals testing the point nudged by
   (-d*d, +d) for an infinitesimal d, so on a shared edge or a shared vertex of a
   watertight mesh exactly one triangle owns the centre. Each edge function is
   evaluated once per edge, from its endpoints in a canonical (lexicographic)
   order, so two triangles sharing an edge see exactly negated values and can
   never both (or neither) claim a centre through rounding.
2. *Boundary slack*. A centre that no triangle owns strictly is still claimed by a
   triangle when every barycentric weight is >= -``tolerances.RASTER_EDGE_EPSILON``.
   This covers centres lying exactly on the outer boundary of an island (which the
   fill rule gives to nobody when the island's interior is below/right of it), as
   Blender's bake does; the claimed weights are clipped to >= 0 and renormalised,
   so the sample lies on the triangle.

When several triangles claim a texel, the lowest tier wins, then the lowest
triangle index. ``overlap_count`` counts texels owned *strictly* by more than one
triangle: real UV overlaps, never shared edges or slack claims.

Degenerate triangles (doubled UV area below ``tolerances.DEGENERATE_TRIANGLE_RATIO``
times the square of the longest UV edge, or with a non-finite coordinate) get no
texels; so do triangles too small to contain any texel centre.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from .. import tolerances as tol

# Candidate (triangle, texel) pairs tested at once. Each pair costs ~300 bytes of
# temporaries, so this bounds the working set near 80 MB whatever the triangle
# sizes (a single triangle may span the whole image).
RASTER_CHUNK_PAIRS = 1 << 18
RASTER_CHUNK_ROWS = 1 << 16


@dataclass(frozen=True)
class TexelSamples:
    """Texels whose centre is covered by a UV triangle, one triangle per texel.

    Attributes
    ----------
    pixel : (k,) int64
        Flat pixel index ``y * W + x``, strictly increasing.
    triangle : (k,) int32
        Index of the owning triangle.
    barycentric : (k, 3) float32
        Weights of the owning triangle's three corners at the texel centre; each
        >= 0, summing to 1.
    coverage : (H, W) bool
        True for every texel in ``pixel``.
    overlap_count : int
        Texels strictly inside (or fill-rule owned by) more than one triangle.
    """

    pixel: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    coverage: np.ndarray
    overlap_count: int

    @property
    def width(self) -> int:
        return int(self.coverage.shape[1])

    @property
    def height(self) -> int:
        return int(self.coverage.shape[0])


def texel_centres(width: int, height: int) -> np.ndarray:
    """UV coordinates of every texel centre, indexed by flat pixel index.

    Returns
    -------
    uv : (H * W, 2) float64, row ``y * W + x`` is ((x + 0.5) / W, (y + 0.5) / H)
    """
    width, height = _check_size(width, height)
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    uu, vv = np.meshgrid(u, v, indexing="xy")
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


def degenerate_uv_triangles(corner_uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Triangles :func:`rasterize` skips: zero (relative) UV area or non-finite UVs.

    Parameters
    ----------
    corner_uv : (m, 3, 2) float
    width, height : image size in texels; areas are measured in texels

    Returns
    -------
    degenerate : (m,) bool
    """
    width, height = _check_size(width, height)
    corners = _texel_space(corner_uv, width, height)
    return _degenerate(corners)


def rasterize(corner_uv: np.ndarray, width: int, height: int, threads: int = 0,
              load_kernels: bool = True) -> TexelSamples:
    """Texels whose centre lies inside a UV triangle (see the module doc for the edge rule).

    Parameters
    ----------
    corner_uv : (m, 3, 2) float
        UV of each triangle corner; coordinates outside [0, 1] are clipped away,
        triangles with non-finite or zero-area UVs are skipped.
    width, height : int
        Image size in texels.
    threads : int
        The compiled kernels' thread count (0: all cores); the result does not depend on it,
        nor on whether the kernels or the numpy fallback run: both give the same bits.
    load_kernels : bool
        False: use the compiled kernels only if this process has loaded them already. The
        UV layout check runs on Blender's main thread before a bake starts, where a first
        load (seconds of compiling in a fresh kernel cache) would freeze the interface
        without progress; the bake loads them as a stage of its own.

    Returns
    -------
    TexelSamples
    """
    width, height = _check_size(width, height)
    module = kernels.compiled() if load_kernels or kernels.tried() else None
    if module is None:
        return _rasterize_numpy(corner_uv, width, height)
    return _rasterize_compiled(module, corner_uv, width, height, threads)


def _rasterize_compiled(module, corner_uv, width: int, height: int, threads: int) -> TexelSamples:
    """:func:`rasterize` by the compiled kernels (core.kernels.raster_kernels). Every claim
    is held at once: 21 bytes per claimed texel, about the size of the result."""
    uv = np.ascontiguousarray(_uv_corners(corner_uv))
    npix = width * height
    tolerances = (tol.RASTER_EDGE_EPSILON, tol.SPAN_MARGIN, tol.DEGENERATE_TRIANGLE_RATIO)
    offsets = np.zeros(uv.shape[0] + 1, np.int64)
    no_claims = np.empty(0, np.int32), np.empty(0, np.int32), np.empty(0, bool), np.empty((0, 3), np.float32)
    kernels.run(module.triangle_claims, threads, uv, width, height, *tolerances, offsets, *no_claims, False)
    np.cumsum(offsets, out=offsets)
    total = int(offsets[-1])
    if total == 0:
        return _empty(width, height)
    pixel = np.empty(total, np.int32)
    owner = np.empty(total, np.int32)
    strict = np.empty(total, bool)
    weight = np.empty((total, 3), np.float32)
    kernels.run(module.triangle_claims, threads, uv, width, height, *tolerances, offsets, pixel, owner, strict, weight,
                True)
    chosen = np.empty(npix, np.int64)
    totals = np.zeros(2, np.int64)
    kernels.run(module.resolve_claims, threads, pixel, strict, chosen, np.empty(npix, np.int8), totals)
    del pixel, strict  # before the result is allocated: the peak is the claims plus the result
    covered = int(totals[0])
    samples = TexelSamples(
        pixel=np.empty(covered, np.int64),
        triangle=np.empty(covered, np.int32),
        barycentric=np.empty((covered, 3), np.float32),
        coverage=np.empty((height, width), bool),
        overlap_count=int(totals[1]),
    )
    kernels.run(module.gather_claims, threads, chosen, owner, weight, samples.pixel, samples.triangle,
                samples.barycentric, samples.coverage.reshape(npix))
    return samples


def _rasterize_numpy(corner_uv, width: int, height: int) -> TexelSamples:
    """:func:`rasterize` in numpy, in chunks of bounded memory (RASTER_CHUNK_PAIRS)."""
    corners = _texel_space(corner_uv, width, height)
    m = corners.shape[0]
    npix = width * height

    live = np.flatnonzero(~_degenerate(corners)) if m else np.zeros(0, np.int64)
    if live.size == 0:
        return _empty(width, height)
    c = corners[live]

    # Edge i is opposite corner i: it runs from corner i+1 to corner i+2.
    start = c[:, [1, 2, 0]]
    end = c[:, [2, 0, 1]]
    swap = (end[..., 0] < start[..., 0]) | ((end[..., 0] == start[..., 0]) & (end[..., 1] < start[..., 1]))
    origin = np.where(swap[..., None], end, start)
    direction = np.where(swap[..., None], start, end) - origin
    doubled_area = _cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    # side[t, i] = +1 when the triangle's interior lies on the left of the
    # canonical direction of edge i, i.e. where that edge's canonical function is > 0.
    side = np.where(swap, -1.0, 1.0) * np.sign(doubled_area)[:, None]
    # Slack is a barycentric bound: weight_i = side_i * E_i / |doubled_area|.
    slack = tol.RASTER_EDGE_EPSILON * np.abs(doubled_area)

    # The centres a triangle may claim lie in its slack region: where every weight
    # is >= -eps, i.e. the triangle scaled by 1 + 3 eps about its centroid.
    centroid = c.mean(axis=1, keepdims=True)
    grown = centroid + (1.0 + 3.0 * tol.RASTER_EDGE_EPSILON) * (c - centroid)
    y0 = np.clip(np.ceil(grown[..., 1].min(axis=1) - 0.5 - tol.SPAN_MARGIN), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(grown[..., 1].max(axis=1) - 0.5 + tol.SPAN_MARGIN), -1, height - 1).astype(np.int64)
    rows = np.maximum(y1 - y0 + 1, 0)

    # Work is split by (triangle, texel row) so a triangle spanning the whole
    # image is processed in bounded pieces like any other.
    row_tri = np.repeat(np.arange(live.size), rows)
    row_y = y0[row_tri] + (np.arange(row_tri.size) - np.repeat(np.cumsum(rows) - rows, rows))
    edge_data = (origin, direction, side, slack)

    pixels, owners, strict_flags, weights = [], [], [], []
    for lo in range(0, row_tri.size, RASTER_CHUNK_ROWS):
        tri_part = row_tri[lo:lo + RASTER_CHUNK_ROWS]
        y_part = row_y[lo:lo + RASTER_CHUNK_ROWS]
        x_first, count = _row_spans(grown[tri_part], y_part + 0.5, width)
        ends = np.cumsum(count)
        start = 0
        while start < tri_part.size:
            base = ends[start] - count[start]
            stop = max(int(np.searchsorted(ends, base + RASTER_CHUNK_PAIRS, side="right")), start + 1)
            got = _test_spans(tri_part[start:stop], y_part[start:stop], x_first[start:stop],
                              count[start:stop], width, edge_data)
            if got is not None:
                pixels.append(got[0])
                owners.append(got[1])
                strict_flags.append(got[2])
                weights.append(got[3])
            start = stop
    if not pixels:
        return _empty(width, height)

    pixel = np.concatenate(pixels)
    owner = np.concatenate(owners)
    strict = np.concatenate(strict_flags)
    weight = np.concatenate(weights)

    # Most texels have one claim; only contested ones need sorting: strict before
    # slack, then lowest triangle (keys are unique, so any sort will do).
    claims = np.bincount(pixel, minlength=npix)
    contested = claims[pixel] > 1
    chosen = np.flatnonzero(~contested)
    overlap_count = 0
    if contested.any():
        many = np.flatnonzero(contested)
        _, strict_claims = np.unique(pixel[many[strict[many]]], return_counts=True)
        overlap_count = int(np.count_nonzero(strict_claims > 1))
        key = (pixel[many].astype(np.int64) * 2 + (~strict[many])) * live.size + owner[many]
        order = many[np.argsort(key)]
        first = np.ones(order.size, bool)
        first[1:] = pixel[order[1:]] != pixel[order[:-1]]
        chosen = np.concatenate([chosen, order[first]])
    # Scatter through the image (reusing the count buffer: fresh large arrays
    # cost more in page faults than the arithmetic) to list claims in pixel order.
    slot = claims
    slot.fill(-1)
    slot[pixel[chosen]] = chosen
    covered = slot >= 0
    chosen = slot[covered]

    out_pixel = pixel[chosen]
    coverage = covered.reshape(height, width)
    return TexelSamples(
        pixel=out_pixel.astype(np.int64),
        triangle=live[owner[chosen]].astype(np.int32),
        barycentric=weight[chosen],
        coverage=coverage,
        overlap_count=overlap_count,
    )


def _row_spans(grown: np.ndarray, yc: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """First texel column and column count whose centre may lie in each (triangle, row).

    Parameters
    ----------
    grown : (r, 3, 2) float64, slack-region corners of each row's triangle, in texels
    yc : (r,) float64, the row's centre height in texels

    Returns
    -------
    x_first : (r,) int64
    count : (r,) int64, 0 where the row misses the triangle
    """
    a = grown
    b = grown[:, [1, 2, 0]]
    dy = b[..., 1] - a[..., 1]
    below = yc[:, None] - a[..., 1]
    crosses = (below * (yc[:, None] - b[..., 1]) <= 0) & (dy != 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = a[..., 0] + below / dy * (b[..., 0] - a[..., 0])
    lo = np.where(crosses, x, np.inf).min(axis=1)
    hi = np.where(crosses, x, -np.inf).max(axis=1)
    hit = np.isfinite(lo) & np.isfinite(hi)
    lo = np.where(hit, lo, 0.0)
    hi = np.where(hit, hi, -1.0)
    x_first = np.clip(np.ceil(lo - 0.5 - tol.SPAN_MARGIN), 0, width).astype(np.int64)
    x_last = np.clip(np.floor(hi - 0.5 + tol.SPAN_MARGIN), -1, width - 1).astype(np.int64)
    count = np.where(hit, np.maximum(x_last - x_first + 1, 0), 0)
    return x_first, count


def _test_spans(tri, y, x_first, count, width, edge_data):
    """Edge-function test of every texel centre in the given row spans."""
    total = int(count.sum())
    if total == 0:
        return None
    origin, direction, side, slack = edge_data
    o = origin[tri]
    d = direction[tri]
    # The y part of each edge function is shared by the whole row; computing it
    # the same way for every triangle keeps shared edges bit-identical.
    row_term = d[..., 0] * ((y + 0.5)[:, None] - o[..., 1])
    rep = lambda a: np.repeat(a, count, axis=0)  # noqa: E731
    x = rep(x_first) + (np.arange(total) - rep(np.cumsum(count) - count))
    edge = rep(row_term) - rep(d[..., 1]) * ((x + 0.5)[:, None] - rep(o[..., 0]))
    s = rep(side[tri])
    inside = s * edge  # = barycentric weight * |doubled area|
    owned = np.where(s > 0, edge >= 0, edge < 0).all(axis=1)
    near = (inside >= -rep(slack[tri])[:, None]).all(axis=1)
    keep = owned | near
    if not keep.any():
        return None
    w = np.maximum(inside[keep], 0.0)
    total_w = w.sum(axis=1, keepdims=True)
    # A slack claim can clip every weight to zero only at a vanishing sliver; fall
    # back to the centroid there rather than dividing by zero.
    w = np.divide(w, total_w, out=np.full_like(w, 1.0 / 3.0), where=total_w > 0)
    pixel = (rep(y)[keep] * width + x[keep]).astype(np.int32)
    return pixel, rep(tri)[keep].astype(np.int32), owned[keep], w.astype(np.float32)


def _check_size(width, height) -> tuple[int, int]:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"image size must be positive integers, got {width!r} x {height!r}")
    if int(width) * int(height) >= 2 ** 31:
        raise ValueError(f"image of {width} x {height} texels is too large")
    return int(width), int(height)


def _texel_space(corner_uv, width: int, height: int) -> np.ndarray:
    return _uv_corners(corner_uv) * np.array([width, height], dtype=np.float64)


def _uv_corners(corner_uv) -> np.ndarray:
    corners = np.asarray(corner_uv, dtype=np.float64)
    if corners.ndim != 3 or corners.shape[1:] != (3, 2):
        raise ValueError(f"corner_uv must have shape (m, 3, 2), got {corners.shape}")
    return corners


def _degenerate(corners: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", over="ignore"):
        first = corners[:, 1] - corners[:, 0]
        doubled_area = np.abs(_cross(first, corners[:, 2] - corners[:, 0]))
        # The longest edge's squared length, edge by edge as (m, 2) rows: the same sums as
        # over the (m, 3, 2) edges at once, without its gather and its 2-wide reduction.
        longest = _squared_length(first)
        np.maximum(longest, _squared_length(corners[:, 2] - corners[:, 1]), out=longest)
        np.maximum(longest, _squared_length(corners[:, 0] - corners[:, 2]), out=longest)
        finite = np.isfinite(corners).all(axis=(1, 2)) & np.isfinite(doubled_area) & np.isfinite(longest)
        return ~finite | ~(doubled_area > tol.DEGENERATE_TRIANGLE_RATIO * longest)


def _squared_length(edge: np.ndarray) -> np.ndarray:
    """(m,) x^2 + y^2 of (m, 2) ``edge``."""
    return edge[:, 0] * edge[:, 0] + edge[:, 1] * edge[:, 1]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _empty(width: int, height: int) -> TexelSamples:
    return TexelSamples(
        pixel=np.zeros(0, np.int64),
        triangle=np.zeros(0, np.int32),
        barycentric=np.zeros((0, 3), np.float32),
        coverage=np.zeros((height, width), bool),
        overlap_count=0,
    )
