"""Seam stitching: the two sides of a UV seam made to agree under bilinear filtering.

A mesh edge whose two faces lie in different places of the atlas (a UV seam) is drawn
twice, once from each side's texels. The sides are baked as separate texels, and a
bilinear lookup on the edge reads texels of which half lie in the gutter, so a renderer
shows a line along the seam. Stitching moves the texels those lookups read, as little as
it can, until the lookups on both sides agree: the least-squares stitch of Unity's,
Godot's and Bakery's lightmappers,

    minimise  sum_i keep_i (x_i - x0_i)^2  +  SEAM_WEIGHT * sum_s (a_s . x - b_s . x)^2

with x0 the baked (dilated) image and a_s, b_s the bilinear weights of seam point s on
either side. Gutter texels keep little weight: they exist only to be filtered.

Only seams between smooth faces are stitched. Where the shading normals across an edge
differ (a box's corner, a flat-shaded facet) the light really changes at the edge.

Cycles does not stitch, so stitching is judged by how far the two sides' lookups
disagree before and after (:attr:`StitchResult.before` / ``after``), not by texel error
against Cycles. Images are (H, W, C) float32, row 0 at v = 0 (core.outputs.images).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels

__all__ = ["Seams", "StitchResult", "find_seams", "stitch"]

# Weight of one seam point's disagreement against keeping one covered texel's value.
# Three points per texel of edge length: 8 makes a seam's lookups agree to well under a
# percent of their difference while interior texels move by little more than half of it.
SEAM_WEIGHT = 8.0
# Keep weight of a texel outside the UV islands (dilated or empty): the lower, the more of a
# stitch the gutter takes and the less the covered texels move from their baked light.
# 0.01 against 0.1 (docs/benchmarks.md, speed part 19): a render's seam pixels 6.35% from the
# truth against 6.72% (benchmarks/seams.py at 64², unstitched 8.95%), and many_objects'
# texels closer to Cycles' bake (4 x 4 blocks 0.56% against 0.64% at N = 256, unstitched
# 0.56%); the sides' disagreement after is 0.4-1.8% against 0.2-0.8%. 0.003 and 0.001 take
# the seam pixels back to 6.46% and 6.67%.
GUTTER_KEEP = 0.01
POINTS_PER_TEXEL = 3.0
# Shading normals across an edge closer than this cosine: the light is continuous there.
SMOOTH_COSINE = 0.995
# A shared corner whose two UVs differ by more than this many texels is split (a seam).
SPLIT_TEXELS = 0.05
WELD_FRACTION = 1e-6  # positions closer than this share of the mesh's extent are one vertex
MAX_ITERATIONS = 400
# Conjugate gradients stop at this residual relative to the right-hand side: 30-60
# iterations; 1e-7 takes 250-400 for the same disagreement to four digits.
TOLERANCE = 1e-4


@dataclass(frozen=True)
class Seams:
    """The stitching system of one atlas.

    texels : (n,) int64 flat texel indices (y * width + x) that the seam lookups read
    keep : (n,) float64 weight of each texel's baked value (1 covered, GUTTER_KEEP not)
    index : (s, 8) int64 into ``texels``: side a's four lookup texels, then side b's
    weight : (s, 8) float64 their bilinear weights, side b's negated, so that
        ``(weight * x[index]).sum(1)`` is seam point s's disagreement
    edges : seam edges stitched
    """

    texels: np.ndarray
    keep: np.ndarray
    index: np.ndarray
    weight: np.ndarray
    edges: int

    def disagreement(self, values: np.ndarray) -> np.ndarray:
        """(s, C) float64 side a's lookup minus side b's, of ``values`` (n, C) on ``texels``."""
        return np.einsum("sk,skc->sc", self.weight, values[self.index])


@dataclass(frozen=True)
class StitchResult:
    """image : (H, W, C) float32 stitched, finite, non-negative; before / after : RMS
    disagreement of the seam lookups (all channels) relative to the mean covered value
    (0 when that mean is 0); iterations : conjugate-gradient steps taken."""

    image: np.ndarray
    before: float
    after: float
    iterations: int


def find_seams(positions: np.ndarray, triangles: np.ndarray, corner_uvs: np.ndarray, corner_normals: np.ndarray,
               width: int, height: int, coverage: np.ndarray) -> Seams | None:
    """The seams between smooth faces of one mesh in its ``width`` x ``height`` atlas;
    None when it has none.

    Parameters
    ----------
    positions : (v, 3) float vertex positions (vertices closer than WELD_FRACTION of the
        extent count as one, so meshes split at their seams are stitched too)
    triangles : (m, 3) int vertex indices
    corner_uvs : (m, 3, 2) float the atlas UVs of each triangle corner
    corner_normals : (m, 3, 3) float shading normals of each corner
    coverage : (height, width) bool texels inside the UV islands
    """
    positions = np.asarray(positions, np.float64)
    triangles = np.asarray(triangles, np.int64)
    if not len(triangles) or width < 1 or height < 1:
        return None
    corners = _welded(positions)[triangles]  # (m, 3)
    uvs = np.asarray(corner_uvs, np.float64)
    scale = np.array([width, height], np.float64)
    split_vertex = _split_vertices(corners, uvs, scale)
    if not split_vertex.any():  # no corner leaves its vertex's UV: one island, no edge to pair
        return None

    # Edge e of triangle e // 3 runs from its corner e % 3 to the next one.
    start, end = corners.reshape(-1), corners[:, [1, 2, 0]].reshape(-1)
    low, high = np.minimum(start, end), np.maximum(start, end)
    # One int64 key per edge sorts as (low, high) would; stable, so shared edges stay in triangle order.
    key = low * (int(corners.max()) + 1) + high
    # An edge with no split vertex at either end joins its faces in the atlas. Leaving those
    # out keeps or drops every copy of an edge together (they share their ends), so the
    # pairs found below, and their order, are those of all edges that can be split.
    edge = np.flatnonzero((low != high) & (split_vertex[low] | split_vertex[high]))
    edge = edge[np.argsort(key[edge], kind="stable")]
    same_as_next = key[edge[1:]] == key[edge[:-1]]
    # Manifold edges only: exactly two faces (an edge shared by three has no two sides).
    pair = np.zeros(len(edge), bool)
    pair[:-1] = same_as_next  # i and i + 1 share an edge ...
    pair[:-2] &= ~same_as_next[1:]  # ... that i + 2 does not share ...
    pair[1:] &= ~same_as_next  # ... nor i - 1
    edge_a = edge[np.flatnonzero(pair)]
    edge_b = edge[np.flatnonzero(pair) + 1]
    distinct = edge_a // 3 != edge_b // 3
    edge_a, edge_b = edge_a[distinct], edge_b[distinct]
    if not len(edge_a):
        return None

    def side(edges):
        """Each edge's triangle, and its corners at the edge's lower and higher vertex."""
        first = edges % 3
        second = (first + 1) % 3
        forward = start[edges] == low[edges]
        return edges // 3, np.where(forward, first, second), np.where(forward, second, first)

    (tri_a, a_low_corner, a_high_corner), (tri_b, b_low_corner, b_high_corner) = side(edge_a), side(edge_b)
    a_low, a_high = uvs[tri_a, a_low_corner], uvs[tri_a, a_high_corner]
    b_low, b_high = uvs[tri_b, b_low_corner], uvs[tri_b, b_high_corner]
    split = np.maximum(np.abs((a_low - b_low) * scale).max(1), np.abs((a_high - b_high) * scale).max(1)) > SPLIT_TEXELS
    if not split.any():  # one island, or islands meeting only where their UVs agree
        return None
    normals = np.asarray(corner_normals)

    def cosine(corner_a, corner_b):
        """Cosine between the two sides' unit shading normals at one end of each split edge."""
        normal_a = normals[tri_a[split], corner_a[split]].astype(np.float64)
        normal_b = normals[tri_b[split], corner_b[split]].astype(np.float64)
        normal_a /= np.maximum(np.linalg.norm(normal_a, axis=-1, keepdims=True), 1e-30)
        normal_b /= np.maximum(np.linalg.norm(normal_b, axis=-1, keepdims=True), 1e-30)
        return np.einsum("kd,kd->k", normal_a, normal_b)

    smooth = (cosine(a_low_corner, b_low_corner) > SMOOTH_COSINE) & (cosine(a_high_corner, b_high_corner)
                                                                     > SMOOTH_COSINE)
    a_low, a_high, b_low, b_high = (x[split] for x in (a_low, a_high, b_low, b_high))
    length = np.maximum(np.linalg.norm((a_high - a_low) * scale, axis=1), np.linalg.norm((b_high - b_low) * scale,
                                                                                         axis=1))
    seam = smooth & np.isfinite(length) & (length > 0)
    if not seam.any():
        return None
    a_low, a_high, b_low, b_high, length = (x[seam] for x in (a_low, a_high, b_low, b_high, length))

    points = np.maximum(2, np.ceil(POINTS_PER_TEXEL * length)).astype(np.int64)
    edge = np.repeat(np.arange(len(points)), points)
    step = np.arange(len(edge)) - np.repeat(np.cumsum(points) - points, points)
    t = ((step + 0.5) / points[edge])[:, None]
    a_texels, a_weights = _bilinear_taps(a_low[edge] + t * (a_high - a_low)[edge], width, height)
    b_texels, b_weights = _bilinear_taps(b_low[edge] + t * (b_high - b_low)[edge], width, height)
    taps = np.concatenate([a_texels, b_texels], axis=1)
    texels, index = np.unique(taps, return_inverse=True)
    keep = np.where(np.asarray(coverage, bool).reshape(-1)[texels], 1.0, GUTTER_KEEP)
    return Seams(texels=texels, keep=keep, index=index.reshape(taps.shape),
                 weight=np.concatenate([a_weights, -b_weights], axis=1), edges=int(len(points)))


def _split_vertices(corners: np.ndarray, uvs: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(v,) bool for each welded vertex whether its corners may lie apart in the atlas: some
    corner's UV is not finite or lies more than a quarter of SPLIT_TEXELS from the one UV
    chosen for the vertex (one of its corners'). Any two corners of a vertex not marked
    lie within half SPLIT_TEXELS of each other, so no edge is split there.

    corners : (m, 3) int64 welded vertex of each triangle corner; uvs : (m, 3, 2) float64;
    scale : (2,) the atlas's width and height in texels
    """
    # Each UV as one complex number, so that scattering and gathering them moves one 16-byte
    # item per corner: numpy's row-wise fancy indexing of (m * 3, 2) is several times slower.
    corner_uv = np.ascontiguousarray(uvs, np.float64).reshape(-1, 2).view(np.complex128).reshape(-1)
    vertex = corners.reshape(-1)
    chosen = np.zeros(int(vertex.max()) + 1, np.complex128)
    chosen[vertex] = corner_uv
    offset = corner_uv - chosen[vertex]
    reach = SPLIT_TEXELS / 4
    with np.errstate(invalid="ignore"):
        near = (np.abs(offset.real) * scale[0] <= reach) & (np.abs(offset.imag) * scale[1] <= reach)
    marked = np.zeros(len(chosen), bool)
    marked[vertex[~near]] = True
    return marked


def _welded(positions: np.ndarray) -> np.ndarray:
    """(v,) int64 one label per vertex, equal for vertices within WELD_FRACTION of the mesh's
    extent of each other (on the same grid cell) and ordered as their cells are, x first. A
    vertex that is not finite welds to nothing (and does not spoil the others' extent)."""
    if not np.isfinite(positions).all():
        finite = np.isfinite(positions).all(axis=1)
        labels = np.empty(len(positions), np.int64)
        labels[finite] = _welded(positions[finite])
        labels[~finite] = np.count_nonzero(finite) + np.arange(np.count_nonzero(~finite))
        return labels
    if not len(positions):
        return np.zeros(0, np.int64)
    # Column by column: numpy reduces a (v, 3) array along its first axis 20x slower than
    # three contiguous rows (5.7 ms of a 100k-vertex mesh's extent; docs/benchmarks.md, part 20).
    columns = np.ascontiguousarray(np.asarray(positions, np.float64).T)
    extent = float((columns.max(axis=1) - columns.min(axis=1)).max())
    quantum = max(extent * WELD_FRACTION, np.finfo(np.float64).tiny)
    cells = np.round(columns / quantum).astype(np.int64)
    cells -= cells.min(axis=1, keepdims=True)
    # The cells span about 1 / WELD_FRACTION (1e6) a side: three fit one int64 key, sorted as
    # a plain array, 5-10x faster than rows (np.unique's axis=0) on a dense mesh.
    if int(cells.max()) < 1 << 21:
        return _ranks((cells[0] << 42) | (cells[1] << 21) | cells[2])
    _, welded = np.unique(cells.T, axis=0, return_inverse=True)
    return welded.reshape(-1)


def _ranks(keys: np.ndarray) -> np.ndarray:
    """(v,) int64 each key's rank among the distinct ``keys`` (v,) int64: np.unique's inverse,
    through a stable sort, which runs through a mesh's vertices (often in nearly sorted cells,
    row after row) about 9x sooner than np.unique's quicksort."""
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    new = np.empty(len(keys), np.int64)
    new[0] = 0
    np.not_equal(ordered[1:], ordered[:-1], out=new[1:], casting="unsafe")
    ranks = np.empty(len(keys), np.int64)
    ranks[order] = np.cumsum(new)
    return ranks


def _bilinear_taps(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The four texels (s, 4) int64 flat and weights (s, 4) float64 of a bilinear lookup at
    ``uv`` (s, 2), with texel centres at (i + 1/2) / size and clamped at the atlas border,
    as core.transport.gather.AtlasLayout.bilinear and the GPU's linear filter read it."""
    x = np.clip(uv[:, 0] * width - 0.5, 0.0, width - 1)
    y = np.clip(uv[:, 1] * height - 0.5, 0.0, height - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    texels = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], axis=1)
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=1)
    return texels, weights


def stitch(image: np.ndarray, seams: Seams) -> StitchResult:
    """``image`` (H, W, C) float with its seam texels moved by the least-squares stitch.

    Solved by Jacobi-preconditioned conjugate gradients, each channel on its own; the
    system is symmetric positive definite (keep > 0), so it converges. Texels no seam
    reads are returned unchanged.
    """
    height, width = image.shape[:2]
    channels = image.shape[2] if image.ndim == 3 else 1
    flat = np.asarray(image, np.float32).reshape(height * width, channels)
    baked = np.nan_to_num(flat[seams.texels].astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    n = len(seams.texels)
    keep = seams.keep[:, None]
    rows = seams.index.reshape(-1)

    module = kernels.compiled()

    def normal_matrix(x):
        residual = seams.disagreement(x)  # (s, C)
        spread = seams.weight[:, :, None] * residual[:, None, :]
        back = np.stack([np.bincount(rows, spread[..., c].reshape(-1), n) for c in range(channels)], axis=1)
        return keep * x + SEAM_WEIGHT * back

    diagonal = (seams.keep + SEAM_WEIGHT * np.bincount(rows, (seams.weight ** 2).reshape(-1), n))[:, None]
    rhs = keep * baked
    x = baked.copy()
    limit = TOLERANCE * np.maximum(np.linalg.norm(rhs, axis=0), 1e-30)
    if module is not None:
        # The whole solve compiled: the numpy loop's calls cost more than its arithmetic.
        iterations = module.seam_solve(seams.weight, seams.index, seams.keep, SEAM_WEIGHT,
                                       np.ascontiguousarray(diagonal[:, 0]), rhs, limit, MAX_ITERATIONS, x)
    else:
        x, iterations = _solve_numpy(normal_matrix, diagonal, rhs, limit, x)
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    out = flat.copy()
    out[seams.texels] = x
    covered = seams.keep == 1.0
    mean = float(np.abs(baked[covered]).mean()) if covered.any() else 0.0

    def relative(values):
        return float(np.sqrt(np.mean(seams.disagreement(values) ** 2)) / mean) if mean > 0 else 0.0

    return StitchResult(image=out.reshape(image.shape), before=relative(baked), after=relative(x),
                        iterations=iterations)


def _solve_numpy(normal_matrix, diagonal: np.ndarray, rhs: np.ndarray, limit: np.ndarray, x: np.ndarray):
    """:func:`stitch`'s conjugate gradients in numpy, from ``x`` (n, C) float64: (x, iterations).
    normal_matrix : callable (n, C) -> (n, C); diagonal : (n, 1) its diagonal; limit : (C,)."""
    r = rhs - normal_matrix(x)
    z = r / diagonal
    d = z.copy()
    rz = (r * z).sum(0)
    iterations = 0
    while iterations < MAX_ITERATIONS and (np.linalg.norm(r, axis=0) > limit).any():
        q = normal_matrix(d)
        dq = (d * q).sum(0)
        alpha = np.divide(rz, dq, out=np.zeros_like(rz), where=dq > 0)
        x += alpha * d
        r -= alpha * q
        z = r / diagonal
        rz_next = (r * z).sum(0)
        beta = np.divide(rz_next, rz, out=np.zeros_like(rz), where=rz > 0)
        d = z + beta * d
        rz = rz_next
        iterations += 1
    return x, iterations
