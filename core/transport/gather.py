"""Light transport by table lookups (the Method of Dependent Tests) on the CPU.

All objects' radiance atlases live in one flat array so a gather over the table
needs no per-object loop. Each atlas is stored with one extra replicated column and
row, so a bilinear lookup always finds its four texels without bounds checks.

The lookups run in the compiled kernels of :mod:`core.kernels` where numba loads, and
in the numpy functions here (``*_numpy``) where it does not; both compute the same sums.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..distributed.split import SplitTable
from ..visibility.table import BELOW_HORIZON, MISS, VisibilityTable, decode_uv, decode_vertex_hit
from .contract import GatherGeometry, GatherSource


@dataclass
class AtlasLayout:
    """Where each object's padded atlas starts in the flat radiance array.

    widths, heights : (O,) int64 atlas sizes in texels (unpadded)
    offsets : (O,) int64 first flat index of each padded atlas
    """

    widths: np.ndarray
    heights: np.ndarray
    offsets: np.ndarray
    # Vertex-mode objects are one-row atlases of their samples; a ray landing on one
    # mixes the three samples of the hit triangle instead of filtering texels.
    is_vertex: np.ndarray | None = None  # (O,) bool
    corner_flat: np.ndarray | None = None  # (T_vertex, 3) int32 flat index of each corner's sample
    corner_base: np.ndarray | None = None  # (O,) int64 first row of each vertex object in corner_flat
    nearest_vertex: bool = False  # the paper's variant: the corner with the largest weight only

    @classmethod
    def from_sizes(cls, sizes, corner_samples=None, nearest_vertex: bool = False) -> "AtlasLayout":
        """Layout of atlases ``sizes`` [(width, height)]; ``corner_samples`` per object:
        None for an atlas, the (m, 3) corner-to-sample table of a vertex-mode object."""
        widths = np.array([w for w, _ in sizes], np.int64)
        heights = np.array([h for _, h in sizes], np.int64)
        padded = (widths + 1) * (heights + 1)
        offsets = np.concatenate([[0], np.cumsum(padded)[:-1]]).astype(np.int64)
        layout = cls(widths, heights, offsets, nearest_vertex=nearest_vertex)
        if corner_samples is not None and any(c is not None for c in corner_samples):
            layout.is_vertex = np.array([c is not None for c in corner_samples], bool)
            blocks, bases, total = [], [], 0
            for index, corners in enumerate(corner_samples):
                bases.append(total if corners is not None else -1)
                if corners is not None:
                    # Corners of degenerate triangles (-1) are never hit; point them anywhere valid.
                    blocks.append(offsets[index] + np.maximum(np.asarray(corners, np.int64), 0))
                    total += len(corners)
            layout.corner_flat = np.concatenate(blocks).astype(np.int32)
            layout.corner_base = np.array(bases, np.int64)
        return layout

    def lit_objects(self, flat: np.ndarray) -> np.ndarray:
        """(O,) bool: whether any value of each object's padded atlas in ``flat`` (size, C) is not
        0 (a vertex-mode object's corners point into its own atlas, so the same region holds them)."""
        if not len(self.offsets):
            return np.zeros(0, bool)
        return np.logical_or.reduceat(np.any(flat != 0, axis=1), self.offsets)

    def vertex_lookup(self, flat: np.ndarray, obj: np.ndarray, triangle: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Radiance where rays landed on vertex-mode objects: the hit triangle's samples mixed
        by the barycentrics ``uv`` (n, 2) (embree's: w0 = 1 - u - v), or the nearest one."""
        corners = self.corner_flat[self.corner_base[obj] + triangle]  # (n, 3)
        u = uv[:, 0:1]
        v = uv[:, 1:2]
        weights = np.concatenate([np.float32(1.0) - u - v, u, v], axis=1)
        if self.nearest_vertex:
            chosen = np.argmax(weights, axis=1)
            return np.take(flat, corners[np.arange(len(corners)), chosen], axis=0)
        return (np.take(flat, corners[:, 0], axis=0) * weights[:, 0:1]
                + np.take(flat, corners[:, 1], axis=0) * weights[:, 1:2]
                + np.take(flat, corners[:, 2], axis=0) * weights[:, 2:3])

    @property
    def size(self) -> int:
        return int(np.sum((self.widths + 1) * (self.heights + 1)))

    def pack(self, images) -> np.ndarray:
        """Flatten per-object images (H, W, C) into the padded flat array (size, C)."""
        channels = images[0].shape[2]
        flat = np.zeros((self.size, channels), np.float32)
        for image, offset in zip(images, self.offsets):
            padded = np.pad(image, ((0, 1), (0, 1), (0, 0)), mode="edge")
            flat[offset:offset + padded.size // channels] = padded.reshape(-1, channels)
        return flat

    def bilinear(self, flat: np.ndarray, obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Bilinear lookup at atlas coordinates ``uv`` (n, 2) of objects ``obj`` (n,).

        Clamped to the texel centres at the atlas border. Returns (n, C) float64 (the
        texel position is float32, the blend float64 as numpy promotes it). Compiled
        (bitwise the same) where the kernels load.
        """
        module = kernels.compiled()
        if module is not None and flat.ndim == 2 and flat.dtype == np.float32:
            result = np.empty((len(obj), flat.shape[1]))
            module.bilinear_points(flat, self.widths.astype(np.int32), self.heights.astype(np.int32),
                                   self.offsets32, np.asarray(obj, np.int32),
                                   np.ascontiguousarray(uv, np.float32), result)
            return result
        width = self.widths.astype(np.float32)[obj]
        height = self.heights.astype(np.float32)[obj]
        x = np.minimum(np.maximum(uv[:, 0] * width - np.float32(0.5), np.float32(0.0)), width - 1)
        y = np.minimum(np.maximum(uv[:, 1] * height - np.float32(0.5), np.float32(0.0)), height - 1)
        x0 = x.astype(np.int32)  # x >= 0, so truncation is floor
        y0 = y.astype(np.int32)
        fx = (x - x0)[:, None]
        fy = (y - y0)[:, None]
        stride = self.widths.astype(np.int32)[obj] + 1
        base = self.offsets32[obj] + y0 * stride + x0
        c00 = np.take(flat, base, axis=0)
        c01 = np.take(flat, base + 1, axis=0)
        bottom = c00 + (c01 - c00) * fx
        c10 = np.take(flat, base + stride, axis=0)
        c11 = np.take(flat, base + stride + 1, axis=0)
        top = c10 + (c11 - c10) * fx
        return bottom + (top - bottom) * fy

    @property
    def offsets32(self) -> np.ndarray:
        """(objects,) int32 :attr:`offsets`, as the compiled lookups take them."""
        if self.size >= 2 ** 31:
            raise ValueError("atlases beyond 2^31 texels in total are not supported")
        return self.offsets.astype(np.int32)


# Table entries one compiled gather call walks: the progress bar moves, and a cancel is
# seen, between calls (about a quarter of a second each on one core).
LOOKUPS_PER_CALL = 1 << 23


def open_hemisphere_weight(normals: np.ndarray, geometric: np.ndarray) -> np.ndarray:
    """(K,) float64: the integral of max(0, d . n) over the directions d above the geometric
    horizon (d . n_g > 0), pi (1 + n . n_g) / 2 for unit shading normals ``normals`` and
    geometric normals ``geometric`` (K, 3) each (any common frame; both are normalised here).

    Cycles' diffuse lobe drops the directions below the face (its sampled directions there
    carry nothing, and so do its AO rays), so a smooth-shaded texel whose shading normal leans
    by theta from its face receives pi (1 + cos theta) / 2 from a uniform world, not pi: 2%
    less on a coarse sphere of 8 x 4 faces (docs/benchmarks.md, speed part 18). Projected onto
    the plane normal to n, the lost directions are half the unit disc less half an ellipse of
    semi-axes 1 and cos theta: pi (1 - cos theta) / 2. Each row is computed on its own, with
    no sum across rows, so a slice of the rows gives bitwise the slice of the whole.
    """
    normals = np.asarray(normals, np.float64)
    geometric = np.asarray(geometric, np.float64)
    dot = normals[:, 0] * geometric[:, 0] + normals[:, 1] * geometric[:, 1] + normals[:, 2] * geometric[:, 2]
    squares = (normals[:, 0] * normals[:, 0] + normals[:, 1] * normals[:, 1] + normals[:, 2] * normals[:, 2]) \
        * (geometric[:, 0] * geometric[:, 0] + geometric[:, 1] * geometric[:, 1] + geometric[:, 2] * geometric[:, 2])
    lengths = np.sqrt(squares)
    cosine = np.divide(dot, lengths, out=np.ones_like(dot), where=lengths > 0)
    return 0.5 * np.pi * (1.0 + np.clip(cosine, -1.0, 1.0))


def gather_normalisation(table: VisibilityTable, normals: np.ndarray, open_weight, threads: int = 0) -> np.ndarray:
    """Per-sample factor that makes the weights max(0, d_i . n) of one sample's directions
    above its horizon sum to ``open_weight``, what they integrate to over the sphere.

    With a finite direction set the raw sum only nears that integral; normalising makes a
    white furnace exact for any N (DESIGN.md). Samples with no open direction get 0.

    normals : (K, 3) float in the table's frame; open_weight : (K,) float64 from
    :func:`open_hemisphere_weight`, or pi where each shading normal is its geometric normal;
    threads : the kernels' threads (0: all cores)

    Returns
    -------
    scale : (K,) float64
    """
    if isinstance(table, SplitTable):
        return table.gather_normalisation()
    # The cosines in float32, as the gathers weigh with them: at a grazing direction the
    # float32 dot product differs from the float64 one by up to 1e-4 of itself, and the
    # weights must sum to their target as the gathers compute them.
    normals32 = np.ascontiguousarray(normals, np.float32)
    directions32 = np.ascontiguousarray(table.directions, np.float32)
    module = kernels.compiled()
    if module is not None:
        total = np.zeros(len(normals))
        if len(normals):
            kernels.run(module.cosine_sum, threads, *_stored_entries(table), directions32, normals32,
                        np.ones(len(normals32), np.float32), np.int16(BELOW_HORIZON), False, total)
    else:
        total = _open_cosine_sum_numpy(table, directions32, normals32)
    target = np.broadcast_to(np.asarray(open_weight, np.float64), total.shape)
    return np.divide(target, total, out=np.zeros_like(total), where=total > tol.MIN_WEIGHT_SUM)


def _open_cosine_sum_numpy(table, directions32: np.ndarray, normals32: np.ndarray) -> np.ndarray:
    total = np.zeros(len(normals32))
    for i, direction in enumerate(directions32):
        cosine = np.maximum(normals32 @ direction, np.float32(0.0)).astype(np.float64)
        total += np.where(table.entries.mask(i, i + 1)[0], cosine, 0.0)
    return total


def _stored_entries(table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' view of the table's stored entries: above_words (N, W) uint64, word_base
    (N, W) int64 and hit_object (A,) int16 (core.visibility.table.TableEntries)."""
    entries = table.entries
    return entries.above_words, entries.word_base, entries.hit_object


def gather(geometry: GatherGeometry, source: GatherSource, progress=None, samples: np.ndarray | None = None,
           directions: range | None = None) -> np.ndarray:
    """E(p) = sum_i w_i(p) L(S_i[p]): irradiance from the radiance atlases and the world.

    Parameters
    ----------
    geometry : the table, shading normals (K, 3), normalisation (K,) from
        :func:`gather_normalisation`, atlas layout and worker threads (0: all cores;
        each sums its own share of directions)
    source : radiance (layout.size, C) float32 packed outgoing radiance of every object
        (C is 3 per light group gathered together); world (N, C) or (C,) radiance of rays
        that leave the scene (:func:`core.lights.environment.world_radiance`); exclude
        (K, O) bool or None, True where sample k must not gather object o
    progress : callable(fraction) or None, called from the calling thread only
    samples : (k,) int64 or None; gather only these samples (the others get 0), e.g.
        the last bounce, which only objects with outputs need
    directions : a contiguous range of direction indices, or None for all; gathers over
        disjoint ranges covering the set add up to the whole gather

    Returns
    -------
    irradiance : (K, C) float64
    """
    if isinstance(geometry.table, SplitTable):
        if directions is not None:
            raise ValueError("a table held by sample rows is gathered over all its directions")
        return geometry.table.gather(source.radiance, source.world, source.exclude, samples, progress)
    chosen_directions = _direction_range(len(geometry.table.directions), directions)
    module = kernels.compiled()
    if module is None:
        return gather_numpy(geometry, source, progress, samples, directions)
    return _gather_compiled(module, geometry, source, progress, samples, chosen_directions)


def vertex_cells_of(table, layout) -> np.ndarray:
    """(O,) int64 the table's vertex_cells, checked against the layout's vertex-mode objects
    (``layout.is_vertex`` not None): a table traced for other objects would be misread."""
    cells = table.vertex_cells
    if cells is None or not np.array_equal(np.asarray(cells) > 0, np.asarray(layout.is_vertex, bool)):
        raise ValueError("the table's vertex-mode objects differ from the layout's")
    return np.ascontiguousarray(cells, np.int64)


def _direction_range(count: int, directions: range | None) -> range:
    """The gather's directions: all ``count`` for None, else ``directions`` checked to be a
    contiguous range within the set."""
    chosen = range(count) if directions is None else directions
    if chosen.step != 1 or chosen.start < 0 or chosen.stop > count:
        raise ValueError(f"gather: directions must be a contiguous range within 0..{count}, got {directions!r}")
    return chosen


def _gather_compiled(module, geometry: GatherGeometry, source: GatherSource, progress, samples, directions: range
                     ) -> np.ndarray:
    """:func:`gather` in the compiled kernel, a slice of the directions per call."""
    sample_count = len(geometry.normals)
    chosen = np.arange(sample_count, dtype=np.int64) if samples is None else np.asarray(samples, np.int64)
    arguments, atlases = gather_kernel_arguments(geometry, source, chosen)
    out, channels = atlases[-1], atlases[-1].shape[1]
    step = max(1, LOOKUPS_PER_CALL // max(len(chosen), 1))
    first, stop = directions.start, directions.stop
    for start in range(first, stop, step):
        if len(chosen):
            kernels.run(module.gather, geometry.threads, *arguments, start, min(stop, start + step), *atlases)
            geometry.table.entries.release()
        if progress is not None:
            progress((min(stop, start + step) - first) / max(stop - first, 1))
    if samples is None:
        return out
    full = np.zeros((sample_count, channels))
    full[chosen] = out
    return full


def gather_kernel_arguments(geometry: GatherGeometry, source: GatherSource, chosen: np.ndarray
                            ) -> tuple[tuple, tuple]:
    """The compiled gather's arguments for samples ``chosen`` (k,) int64: those before its
    direction range (first, stop) and those after it, the last being ``out`` (k, C) float64,
    zeroed. ``kernels.compiled().gather(*before, first, stop, *after)`` adds those directions."""
    table, layout = geometry.table, geometry.layout
    radiance = np.ascontiguousarray(source.radiance, np.float32)
    channels = radiance.shape[1]
    out = np.zeros((len(chosen), channels))
    world = np.broadcast_to(np.asarray(source.world, np.float64), (len(table.directions), channels))
    world32 = np.ascontiguousarray(world, np.float32) if np.any(world != 0) else np.zeros((0, channels), np.float32)
    exclude = (np.zeros((0, 0), bool) if source.exclude is None
               else np.ascontiguousarray(source.exclude, bool))
    if layout.is_vertex is None:
        cells, is_vertex = np.zeros(len(layout.widths), np.int64), np.zeros(len(layout.widths), bool)
        corner_flat, corner_base = np.zeros((1, 3), np.int32), np.zeros(len(layout.widths), np.int64)
    else:
        cells, is_vertex = vertex_cells_of(table, layout), layout.is_vertex
        corner_flat, corner_base = layout.corner_flat, np.maximum(layout.corner_base, 0)
    arguments = (*_stored_entries(table), table.entries.hit_uv_code, cells,
                 np.ascontiguousarray(table.directions, np.float32),
                 np.ascontiguousarray(geometry.normals, np.float32), np.ascontiguousarray(geometry.scale, np.float32),
                 chosen)
    atlases = (radiance, layout.widths.astype(np.int64), layout.heights.astype(np.int64),
               layout.offsets.astype(np.int64), np.ascontiguousarray(is_vertex, bool),
               np.ascontiguousarray(corner_flat, np.int32), np.ascontiguousarray(corner_base, np.int64),
               bool(layout.nearest_vertex), world32, exclude, np.ascontiguousarray(layout.lit_objects(radiance), bool),
               out)
    return arguments, atlases


def gather_numpy(geometry: GatherGeometry, source: GatherSource, progress=None, samples: np.ndarray | None = None,
                 directions: range | None = None) -> np.ndarray:
    """:func:`gather` in numpy: the fallback where the compiled kernels cannot load."""
    table, normals, scale, layout = geometry.table, geometry.normals, geometry.scale, geometry.layout
    radiance, world, exclude = source.radiance, source.world, source.exclude
    threads = geometry.threads
    chosen_directions = _direction_range(len(table.directions), directions)
    count = len(table.directions)
    channels = radiance.shape[1]
    world = np.broadcast_to(np.asarray(world, np.float64), (count, channels))
    has_world = bool(np.any(world != 0))
    workers = max(1, threads or os.cpu_count() or 1)
    chosen = slice(None) if samples is None else samples
    # float32 inside the loop: the looked-up radiance is float32 already, and a worker
    # sums at most a few hundred directions (relative error ~1e-5); halving the bytes
    # moved halves the time of this memory-bound loop. Workers' sums meet in float64.
    chosen_normals = np.asarray(normals[chosen], np.float32)
    chosen_scale = np.asarray(scale[chosen], np.float32)
    directions = np.asarray(table.directions, np.float32)
    world32 = world.astype(np.float32)
    chosen_exclude = None if exclude is None else exclude[chosen]
    cells = None if layout.is_vertex is None else vertex_cells_of(table, layout)
    sums = [np.zeros((len(chosen_normals), channels), np.float32) for _ in range(workers)]

    def accumulate(worker, indices):
        irradiance = sums[worker]
        for i in indices:
            weight = np.maximum(chosen_normals @ directions[i], np.float32(0.0))
            weight *= chosen_scale
            dense_object = table.entries.dense("hit_object", i, i + 1)[0]
            row = dense_object[chosen]
            hit = np.nonzero(row >= 0)[0]
            if chosen_exclude is not None and len(hit):
                hit = hit[~chosen_exclude[hit, row[hit]]]
            if len(hit):
                codes = table.entries.dense("hit_uv_code", i, i + 1)[0][chosen][hit]
                objects = row[hit].astype(np.int64)
                if layout.is_vertex is None:
                    looked_up = layout.bilinear(radiance, objects, decode_uv(codes))
                else:
                    on_vertices = layout.is_vertex[objects]
                    looked_up = np.empty((len(hit), channels), np.float32)
                    atlas = ~on_vertices
                    looked_up[atlas] = layout.bilinear(radiance, objects[atlas], decode_uv(codes[atlas]))
                    triangles, bary = decode_vertex_hit(codes[on_vertices], cells[objects[on_vertices]])
                    looked_up[on_vertices] = layout.vertex_lookup(radiance, objects[on_vertices], triangles, bary)
                looked_up *= weight[hit, None]
                irradiance[hit] += looked_up
            if has_world and np.any(world[i] != 0):
                irradiance += (weight * (row == MISS))[:, None] * world32[i]

    first, stop = chosen_directions.start, chosen_directions.stop
    block = 8 * workers
    with ThreadPoolExecutor(workers) as pool:
        for start in range(first, stop, block):
            shares = [range(start + w, min(stop, start + block), workers) for w in range(workers)]
            list(pool.map(accumulate, range(workers), shares))
            if progress is not None:
                progress((min(stop, start + block) - first) / max(stop - first, 1))
    total = np.zeros((len(chosen_normals), channels))
    for part in sums:
        total += part
    if samples is None:
        return total
    full = np.zeros((len(normals), channels))
    full[samples] = total
    return full


def ambient_occlusion(table: VisibilityTable, normals: np.ndarray, scale: np.ndarray, threads: int = 0
                      ) -> np.ndarray:
    """Cosine-weighted fraction of open directions, (K,) float64 in [0, 1]: pi is the whole
    sphere's weight, so on a smooth-shaded face the directions below the face count as
    occluded, as Cycles' AO rays there count (:func:`open_hemisphere_weight`).

    normals : (K, 3) float; scale : (K,) float from :func:`gather_normalisation`
    """
    if isinstance(table, SplitTable):
        return table.ambient_occlusion()
    module = kernels.compiled()
    open_weight = np.zeros(len(normals))
    if module is not None:
        if len(normals):
            kernels.run(module.cosine_sum, threads, *_stored_entries(table),
                        np.ascontiguousarray(table.directions, np.float64), np.ascontiguousarray(normals, np.float64),
                        np.ascontiguousarray(scale, np.float64), np.int16(MISS), True, open_weight)
            table.entries.release()
    else:
        for i, direction in enumerate(table.directions):
            weight = np.clip(normals @ direction, 0.0, None) * scale
            open_weight += weight * (table.entries.dense("hit_object", i, i + 1)[0] == MISS)
    return np.clip(open_weight / np.pi, 0.0, 1.0)
