"""Interleaved rotations of the direction set, and the filter that puts them back together.

A fixed direction set sees a small bright patch (a sun spot on the floor, a lit window
reveal) through the same few directions from every texel nearby, so its light arrives as
streaks and blobs that no direction count removes quickly ("ray effects"). Interleaved
sampling (Keller and Heidrich, 2001) gives the texels of every tile x tile block of an
atlas their own rotation of the set (core.pipeline.prepare.interleaving): a block then
sees tile^2 times as many directions, and the structured error turns into a fine
per-texel pattern. :func:`reconstruct_interleaved` averages each texel's gathered light
over the window x window texels around it (:func:`filter_window`: at most FILTER_WINDOW,
however large the tile), where the neighbours lie on the same surface
(similar normal, close in space: never across a chart's border into another part of the
mesh, and in sight of each other: never across a wall standing between them), which
removes the pattern and keeps the light's shape at the window's scale. Texels
buried inside other geometry (core.visibility.table.VisibilityTable.buried: a floor
under a wall standing on it) neither give nor take light there: nobody sees them, and
their dark would bleed into the visible texels beside them.

Only the light that arrives from afar is filtered: the ray effects of small bright patches
come from there, while light from within a few texels (a wall standing on the floor, the
inside of a corner, what the contact correction and the footprint made sharp) changes
faster than the window and is kept as it was gathered (:func:`find_near_hits`,
:func:`near_light`), and so is an emitter's light from farther out
(:func:`find_emitter_near_hits`). The lamps' direct light, with its shadow edges, is never filtered;
texels buried inside other geometry (core.visibility.table.VisibilityTable.buried: a
floor under a wall standing on it) neither give nor take light (nobody sees them); vertex
samples keep the set itself and are not filtered.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..sampling.samples import VertexSamples
from .contacts import close_entries, sum_by_sample, texel_sizes

# Neighbours whose shading normals differ by more than this (cosine) are another surface.
SAME_SURFACE_COSINE = 0.995
# Neighbours farther than this many texels (of the object's mean texel size) apart in
# space are across a chart's border, on another part of the mesh.
SAME_SURFACE_TEXELS = 2.0
# Light arriving from hits within this many filter windows of the sample's texels is near
# light, which the filter keeps as gathered.
NEAR_FIELD_TILES = 2.0
# Light from an emitter within this many windows is near light too. An emitter's light falls as
# 1 / d^2 from its surface, so from a strip 10-30 cm above a column's 13 cm texels it changes by
# half from one texel to the next: averaged with neighbours that took the strip as near (and left
# it out of their far light) and with those that took it as far, the rows beside it were 40% too
# dark and 30% too bright (seeds 9 and 11 of ../shared/tools/scenegen.py). The gathered
# emitters' light is kept from that far out, the bounces' from NEAR_FIELD_TILES: a lit wall's
# light changes slowly, and filtering it is what removes the sun patches' ray effects.
EMITTER_NEAR_FIELD_TILES = 6.0
# The filter's window: a tile of more rotations than this squared is averaged over this many
# texels squared around each texel. Each window then averages 9 rotations, as a 3 x 3 tile's
# does, while neighbouring windows hold other rotations, so what the average leaves of the
# fixed set's error no longer repeats every 3 texels and falls away over larger areas too
# (a 4 x 4 tile: every 4 x 4 block of texels, the means a denoiser would leave, holds all 16
# rotations; docs/benchmarks.md, speed part 16). A window as large as a 5 x 5 tile blurred
# the direct-lit scenes' indirect light per texel.
FILTER_WINDOW = 3


def filter_window(p) -> int:
    """The filter's window (texels across) of prepared scene ``p``: its interleaving tile, at
    most FILTER_WINDOW (``p.rotations`` holds tile^2 rotations)."""
    return min(int(round(np.sqrt(len(p.rotations)))), FILTER_WINDOW)
# Texels per task of the compiled candidate search: thousands of tasks on a large atlas, to
# balance the threads, each long enough that its start costs nothing.
PAIR_TASK_TEXELS = 4096


@dataclass
class NearHits:
    """Table entries that land near their sample (within NEAR_FIELD_TILES windows of its texels,
    or EMITTER_NEAR_FIELD_TILES on an emitter) on an atlas object: sample (m,) int64, weight (m,)
    float32 (the gather's), obj (m,) int64, uv (m, 2) float32 (where it landed) and direction
    (m,) int64 (the table's)."""

    sample: np.ndarray
    weight: np.ndarray
    obj: np.ndarray
    uv: np.ndarray
    direction: np.ndarray


def find_near_hits(p) -> NearHits | None:
    """The near table entries of prepared scene ``p`` (geometry alone; None when there are none
    or the set is not interleaved)."""
    if p.rotations is None or p.table is None:
        return None
    reach = np.repeat(NEAR_FIELD_TILES * _window_widths(p), np.diff(p.sample_offset)).astype(np.float32)
    atlas = np.array([np.inf if m.mode == "atlas" else 0.0 for m in p.meshes])
    entries = close_entries(p, atlas, reach)
    if entries is None:
        return None
    return NearHits(entries.sample, entries.weight, entries.obj, entries.uv, entries.direction)


def find_emitter_near_hits(p, near: NearHits | None, emitting: np.ndarray) -> NearHits | None:
    """``near`` (:func:`find_near_hits` of prepared scene ``p``) and the table entries that land on
    the objects where ``emitting`` (O,) bool is set within EMITTER_NEAR_FIELD_TILES windows: the
    emitted light's near field (None when there are none or the set is not interleaved)."""
    if p.rotations is None or p.table is None or not np.any(emitting):
        return near
    reach = np.repeat(EMITTER_NEAR_FIELD_TILES * _window_widths(p), np.diff(p.sample_offset)).astype(np.float32)
    atlas = np.array([np.inf if m.mode == "atlas" and emits else 0.0 for m, emits in zip(p.meshes, emitting)])
    farther = close_entries(p, atlas, reach)
    if farther is None:
        return near
    if near is not None:
        # Those within the bounces' reach are in both.
        count = len(p.position)
        new = ~np.isin(farther.direction * count + farther.sample, near.direction * count + near.sample)
        farther = NearHits(farther.sample[new], farther.weight[new], farther.obj[new], farther.uv[new],
                           farther.direction[new])
        return NearHits(*(np.concatenate([getattr(near, f), getattr(farther, f)])
                          for f in ("sample", "weight", "obj", "uv", "direction")))
    return NearHits(farther.sample, farther.weight, farther.obj, farther.uv, farther.direction)


def _window_widths(p) -> np.ndarray:
    """(O,) float64 the filter window's width on each object's surface (its texel size times the
    window's texels across)."""
    return filter_window(p) * texel_sizes(p.meshes, p.object_samples)


def near_light(p, near: NearHits | None, atlas: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
    """(K, C) what the near entries contributed to a gather of the packed ``atlas`` (size, C)
    (``exclude`` (K, O) as the gather's)."""
    if near is None:
        return np.zeros((len(p.position), atlas.shape[1]))
    weight = near.weight.astype(np.float64)
    if exclude is not None:
        weight = np.where(exclude[near.sample, near.obj], 0.0, weight)
    return sum_by_sample(near.sample, p.layout.bilinear(atlas, near.obj, near.uv) * weight[:, None], len(p.position))


def filter_pairs(p) -> tuple[np.ndarray, np.ndarray]:
    """The (texel, neighbour) pairs the filter averages, global sample indices (n,) int32 each
    (int64 past 2^31 samples),
    every visible atlas texel paired with itself too: the neighbours within its window x
    window block (:func:`filter_window`) that lie on the same surface (normals within
    SAME_SURFACE_COSINE, closer than SAME_SURFACE_TEXELS windows), are not buried, and see
    each other (the segment between them, just off the surface, is clear: never across a wall
    standing between them).
    Listed by object, then by shift (dy, then dx, ascending), then by texel. Geometry alone,
    found once per preparation (p.filter_pairs()). The candidates are found by a compiled
    kernel where the kernels load, and each object's occlusion rays cast in one query;
    bitwise the numpy pass's pairs."""
    module = kernels.compiled()
    if module is None:
        return _filter_pairs_numpy(p)
    window = filter_window(p)
    steps = range(-(window // 2), window - window // 2)
    shifts = np.array([(dx, dy) for dy in steps for dx in steps], np.int64)
    centre = int(np.nonzero(~shifts.any(axis=1))[0][0])
    sizes = texel_sizes(p.meshes, p.object_samples)
    buried = p.table.buried() if p.table is not None else np.zeros(len(p.position), bool)
    geometry = (np.ascontiguousarray(p.position, np.float64), np.ascontiguousarray(p.normal, np.float64),
                np.ascontiguousarray(p.origins, np.float64))
    pair_dtype = _pair_dtype(p)
    texels, neighbours = [], []
    for index, samples, first, visible, owner in _atlas_texels(p, buried):
        count, width, height = len(samples), samples.width, samples.height
        reach = (SAME_SURFACE_TEXELS * window * sizes[index]) ** 2
        arguments = (np.asarray(samples.pixel, np.int64), visible, owner, first, int(width), int(height), shifts,
                     PAIR_TASK_TEXELS, *geometry, SAME_SURFACE_COSINE, float(reach))
        tasks = -(-count // PAIR_TASK_TEXELS)
        offsets = np.zeros(len(shifts) * tasks + 1, np.int64)
        none = np.zeros(0, np.int64)
        kernels.run(module.filter_candidates, p.settings.threads, *arguments, offsets, offsets, none, none,
                    np.zeros((0, 3), np.float32), np.zeros(0, np.float32), False)
        # The unshifted pairs (each texel with itself) cast no ray.
        ray_counts = offsets[1:].reshape(len(shifts), tasks).copy()
        ray_counts[centre] = 0
        ray_offsets = np.append(0, np.cumsum(ray_counts))
        np.cumsum(offsets, out=offsets)
        rows, other = np.empty(offsets[-1], np.int64), np.empty(offsets[-1], np.int64)
        direction, length = np.empty((ray_offsets[-1], 3), np.float32), np.empty(ray_offsets[-1], np.float32)
        kernels.run(module.filter_candidates, p.settings.threads, *arguments, offsets, ray_offsets, rows, other,
                    direction, length, True)
        # The rays, in pair order, are those of the pairs before and after the unshifted ones.
        a, b = offsets[centre * tasks], offsets[(centre + 1) * tasks]
        clear = np.ones(len(rows), bool)
        if len(length):
            blocked = p.ray_scene.occluded(p.origins[np.concatenate([rows[:a], rows[b:]])], direction, length)
            clear[:a], clear[b:] = ~blocked[:a], ~blocked[a:]
        texels.append(rows[clear].astype(pair_dtype))
        neighbours.append(other[clear].astype(pair_dtype))
    if not texels:
        return np.zeros(0, pair_dtype), np.zeros(0, pair_dtype)
    return np.concatenate(texels), np.concatenate(neighbours)


def _atlas_texels(p, buried: np.ndarray):
    """For each object with atlas texels: its index, samples, first global sample, which of its
    samples are visible ((n,) bool: not ``buried``), and the global sample owning each texel of
    its atlas if visible, else -1 ((width * height,) int64)."""
    for index, samples in enumerate(p.object_samples):
        if isinstance(samples, VertexSamples) or len(samples) == 0:
            continue
        first = int(p.sample_offset[index])
        owner = np.full(samples.width * samples.height, -1, np.int64)
        visible = ~buried[first:first + len(samples)]
        owner[samples.pixel[visible]] = first + np.nonzero(visible)[0]
        yield index, samples, first, visible, owner


def _filter_pairs_numpy(p) -> tuple[np.ndarray, np.ndarray]:
    """:func:`filter_pairs` in numpy."""
    window = filter_window(p)
    offsets = range(-(window // 2), window - window // 2)
    sizes = texel_sizes(p.meshes, p.object_samples)
    buried = p.table.buried() if p.table is not None else np.zeros(len(p.position), bool)
    origins = np.asarray(p.origins, np.float64)
    texels, neighbours = [], []
    for index, samples, first, visible, owner in _atlas_texels(p, buried):
        width, height = samples.width, samples.height
        x, y = samples.pixel % width, samples.pixel // width
        reach = (SAME_SURFACE_TEXELS * window * sizes[index]) ** 2
        for dy in offsets:
            for dx in offsets:
                xx, yy = x + dx, y + dy
                inside = (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
                neighbour = np.where(inside, owner[np.clip(yy, 0, height - 1) * width + np.clip(xx, 0, width - 1)], -1)
                rows = first + np.nonzero((neighbour >= 0) & visible)[0]
                other = neighbour[rows - first]
                if dx or dy:
                    gap = p.position[rows] - p.position[other]
                    same = ((np.einsum("kd,kd->k", p.normal[rows], p.normal[other]) > SAME_SURFACE_COSINE)
                            & (np.einsum("kd,kd->k", gap, gap) < reach))
                    rows, other = rows[same], other[same]
                    along = origins[other] - origins[rows]
                    length = np.linalg.norm(along, axis=1)
                    clear = length > 0
                    if clear.any():
                        clear[clear] = ~p.ray_scene.occluded(
                            p.origins[rows[clear]], (along[clear] / length[clear, None]).astype(np.float32),
                            length[clear].astype(np.float32))
                    rows, other = rows[clear], other[clear]
                texels.append(rows)
                neighbours.append(other)
    if not texels:
        return np.zeros(0, _pair_dtype(p)), np.zeros(0, _pair_dtype(p))
    return np.concatenate(texels).astype(_pair_dtype(p)), np.concatenate(neighbours).astype(_pair_dtype(p))


def _pair_dtype(p):
    """The filter pairs' index type: int32 where every sample index fits (half the memory: 100 MB
    of pairs at Production settings; the kernels read them as they are), else int64."""
    return np.int32 if len(p.position) < 2 ** 31 else np.int64


def reconstruct_interleaved(p, values: np.ndarray, near: np.ndarray | None = None, scratch: bool = False,
                            spread: list | None = None, hits: NearHits | None = None) -> np.ndarray:
    """(K, C) ``values`` (gathered light) with its far part averaged over each atlas texel's
    neighbours (:func:`filter_pairs`) and its ``near`` part (K, C) kept; unchanged without
    interleaving (``p.rotations`` None) and for texels without pairs (vertex samples, buried
    texels). ``p`` is a core.pipeline.prepare.Prepared. ``scratch``: ``values`` (float64) may be
    overwritten (the caller lets it go): its far part is then worked out in its array, not a new one.
    ``hits``: the near entries ``near`` came from (default: ``p.near_hits()``).

    ``spread``: a list, to which the average's standard error (K, C) float64 is appended (NaN
    where a texel has fewer than two usable pairs, or without interleaving). The neighbours of a
    window hold other rotations of the set, so their far radiance scatters by the fixed set's
    error (and by the light's own change across the window, which makes it an overestimate
    where the far light changes fast): the scatter over the square root of the pairs is the
    error of their mean (core.transport.estimate)."""
    if p.rotations is None:
        if spread is not None:
            spread.append(np.full(values.shape, np.nan))
        return values
    near = np.zeros_like(values) if near is None else near
    far = np.subtract(values, near, out=values if scratch and values.dtype == np.float64 else None)
    # What is averaged is the far light per unit of far weight (the mean radiance arriving
    # from afar), put back with the texel's own far weight: texels whose near and far shares
    # differ (one beside a wall, one in the open) then agree wherever the light is uniform,
    # and a white furnace stays exact.
    hits = p.near_hits() if hits is None else hits
    near_weight = np.zeros(len(far)) if hits is None else np.bincount(hits.sample, hits.weight, minlength=len(far))
    far_weight = np.where(p.gather_scale() > 0, p.open_weight(), 0.0) - near_weight
    usable = far_weight > 1e-6 * np.pi
    channels = far.shape[1]
    # Each texel's far radiance (0 where unusable), its square where the spread is asked for, and,
    # in the last column, whether it is usable. Written in place here and below: at the demo's
    # 403k texels each (K, C) array is 9 MiB, and numpy's expressions made seven of them at once.
    squares = channels if spread is not None else 0
    radiance = np.empty((len(far), channels + squares + 1))
    np.divide(far, np.where(usable, far_weight, 1.0)[:, None], out=radiance[:, :channels])
    radiance[~usable, :channels] = 0.0
    if squares:
        np.square(radiance[:, :channels], out=radiance[:, channels:channels + squares])
    radiance[:, -1] = usable
    texels, neighbours = p.filter_pairs()
    # Only pairs of two usable texels count. An unusable neighbour's radiance is 0 and its last
    # column (the count) 0, so summing every pair adds exactly what the usable pairs add, and an
    # unusable texel's count is zeroed below: no copy of the pairs (200 MB at Production settings).
    summed = sum_by_sample(texels, radiance, len(far), rows=neighbours)
    del radiance
    total, count = summed[:, :channels], np.where(usable, summed[:, -1], 0.0)
    if spread is not None:
        spread.append(mean_standard_error(total, summed[:, channels:channels + squares], count) * far_weight[:, None])
    # Where a texel has pairs, their mean radiance at its own far weight; else its own far light.
    np.divide(total, np.maximum(count, 1.0)[:, None], out=total)
    np.multiply(total, far_weight[:, None], out=total)
    np.copyto(total, far, where=~(count > 0)[:, None])
    # Into the far light's array where it is float64 (numpy's sum is float64 whatever the inputs).
    return np.add(total, near, out=far if far.dtype == np.float64 else None)


def mean_standard_error(total: np.ndarray, squares: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(K, C) float64 standard error of the mean of ``count`` (K,) values per row, from their sum
    ``total`` and sum of squares ``squares`` (K, C) each: the sample standard deviation over the
    square root of the count; NaN where the count is below 2."""
    with np.errstate(invalid="ignore", divide="ignore"):
        counted = np.maximum(count, 1.0)[:, None]
        mean = total / counted
        variance = np.maximum(squares / counted - mean * mean, 0.0) / np.maximum(count - 1.0, 1.0)[:, None]
        return np.where((count >= 2)[:, None], np.sqrt(variance), np.nan)
