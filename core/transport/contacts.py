"""Contacts: direct light where a short ray lands, instead of the target's texels.

A ray that lands within a few of the target's texels (a sphere resting on a floor, a wall
standing on it, the inside of a corner) reads the target's light by a bilinear lookup in
its atlas, and texels a few centimetres wide blur what lies under the contact: a floor
texel half under a wall is half dark, and the rays of the wall's lowest row read it. For
those rays this module evaluates the lamps' direct light at the landing point itself, with
exact shadow rays, and corrects the first bounce by the difference: the light a short ray
carries is then as sharp as the direct light at its landing point, whatever the target's
texel size. Later bounces inherit the correction through the first.

The lamps' direct light is replaced, and only with exact shadows: the fractions have no
per-point shadow to evaluate. Emitters near a landing are evaluated there too
(core.pipeline.transport). The world's light is scaled by how open the sky is at the landing
against its texel (:func:`landing_openness`, :func:`world_contact_correction`): the ground under
a ball resting on it sees little sky, but its half-metre texel's mean saw mostly open sky, and
the ball's underside read that (balls 5-13% brighter than Cycles under a sky). What a short
hit is depends on geometry alone; the lamps' light at the hits is computed at every (re)light,
like the direct light of the samples.

The indirect light any ray carries is still read from its target's texels, and buried
texels darken that read at a contact. :func:`exposed_share` measures per texel how much
of its footprint is not inside other geometry, and the atlas the gathers look up
(core.pipeline.prepare.Prepared.lookup_atlas) is built from it:
- a texel half under a box standing on it is, as Cycles bakes it, the mean of its lit half
  and its dark buried half, but a ray can only land on the lit half: it is looked up as
  its value over its exposed share (:func:`lookup_scale`);
- a texel wholly under the box is never landed on, but bilinear filtering blends it, with
  up to half the weight, into every ray that lands at the box's foot: it is filled from
  its exposed neighbours, as the gutter is.
Without them the second bounce into a contact (the box's sunlit face, reflected by the
floor at its foot, back onto the face) is a third of Cycles' on the benchmark's sunlit
block. The texels' own outputs keep Cycles' mean.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..distributed.split import SplitTable
from ..geometry import mesh_triangle_areas
from ..lights.sampler import hash32, orthonormal_frame, sobol_points, square_to_disk
from ..visibility.table import BACKFACE, BELOW_HORIZON, DISTANCE_VALUES, ENTRY_BYTES, RELEASE_BYTES, WORD_BITS
from .contract import SampleSet

# A hit nearer than this many of its target's texels is evaluated at its landing point.
SHORT_HIT_TEXELS = 2.0
# A footprint point most of whose rays (this share) hit the back of a face lies inside
# other geometry. Inside a closed object every ray does; beside an open, one-sided mesh
# seen from behind only those towards it do, so that does not count as buried.
BURIED_POINT_SHARE = 0.9
# Lamp points per side (their square per lamp) where a short ray lands. A landing's light
# weighs one direction of its sample's gather, and a sample averages all its landings, so a
# lamp with an extent needs few points at each: each landing draws its own, and their mean
# over the landings converges as one sampler over more points. At the bake's own 8 per side,
# the soft lamps' penumbrae at contacts traced 94% of a room's bake (issue 52).
CONTACT_AREA_LIGHT_SAMPLES = 2
# Below this exposed share a texel is left as it is: dividing by a sliver's share would
# amplify its noise, and few rays land on a sliver.
MIN_EXPOSED_SHARE = 0.25


def exposed_share(table, slots: int, threads: int = 0) -> np.ndarray:
    """(K,) float64: the share of each sample's footprint points (``slots`` of them; the
    table's direction i starts from point i % slots) that are not buried inside other
    geometry, among the points with any ray above the horizon (1 where none has). Compiled
    on ``threads`` threads (0: all cores) where the kernels load, bitwise the numpy pass."""
    if isinstance(table, SplitTable):
        return table.exposed_share(slots)
    module = kernels.compiled()
    if module is None:
        return _exposed_share_numpy(table, slots)
    entries = table.entries
    share = np.empty(entries.samples)
    # A range of samples at a time (whole words of the entry bits), its entries' pages handed
    # back after it (a table in a scratch file, TableEntries.release): each range reads about
    # RELEASE_BYTES of hit_object.
    per_range = max(1, RELEASE_BYTES // max(2 * entries.directions * WORD_BITS, 1)) * WORD_BITS
    for first in range(0, entries.samples, per_range):
        kernels.run(module.exposed_share, threads, entries.above_words, entries.word_base, entries.hit_object,
                    max(int(slots), 1), BURIED_POINT_SHARE, first, share[first:first + per_range])
        entries.release()
    return share


def _exposed_share_numpy(table, slots: int) -> np.ndarray:
    """:func:`exposed_share` in numpy."""
    entries = table.entries
    samples = entries.samples
    slots = max(int(slots), 1)
    # 16-bit counts (a set has at most 65535 directions), and the shares taken a block of
    # samples at a time: this runs near the bake's memory peak, where whole (K, slots) float
    # temporaries cost a hundred megabytes at the demo's size.
    traced = np.zeros((samples, slots), np.uint16)
    backface = np.zeros((samples, slots), np.uint16)
    for direction in range(entries.directions):
        row = entries.dense("hit_object", direction, direction + 1)[0]
        traced[:, direction % slots] += row != BELOW_HORIZON
        backface[:, direction % slots] += row == BACKFACE
    share = np.ones(samples)
    block = 1 << 16
    for start in range(0, samples, block):
        rows = slice(start, start + block)
        with_rays = traced[rows] > 0
        buried = with_rays & (backface[rows] >= BURIED_POINT_SHARE * traced[rows])
        counted = with_rays.sum(axis=1)
        share[rows] = np.where(counted > 0, 1.0 - buried.sum(axis=1) / np.maximum(counted, 1), 1.0)
    return share


def lookup_scale(exposed: np.ndarray) -> np.ndarray:
    """(K,) float64 the factor from a texel's value to the radiance of its exposed part:
    1 / ``exposed`` (K,), or 1 where the share is under MIN_EXPOSED_SHARE."""
    return np.where(exposed >= MIN_EXPOSED_SHARE, 1.0 / np.maximum(exposed, MIN_EXPOSED_SHARE), 1.0)


@dataclass
class ShortHits:
    """The table entries whose ray lands close to its origin, with where it landed.

    sample : (m,) int64 the sample whose ray it is
    weight : (m,) float32 the entry's gather weight, max(0, n . d_i) times the sample's scale
    obj : (m,) int64 the object it landed on
    uv : (m, 2) float32 the atlas coordinate it landed at (the table's)
    points : SampleSet of the m landing points (position, normals facing the ray's origin,
        owner = the object), where the lamps' light is evaluated
    """

    sample: np.ndarray
    weight: np.ndarray
    obj: np.ndarray
    uv: np.ndarray
    points: SampleSet

    def __len__(self) -> int:
        return len(self.sample)


def texel_sizes(meshes, object_samples) -> np.ndarray:
    """(O,) float64 about how wide one atlas texel of each object is on its surface: the
    square root of its area over its covered texels (0 for objects without texels or in
    vertex mode: their light is not read from texels, so no hit on them counts as short)."""
    sizes = np.zeros(len(meshes))
    for index, (mesh, samples) in enumerate(zip(meshes, object_samples)):
        if mesh.mode != "atlas" or len(samples) == 0:
            continue
        sizes[index] = np.sqrt(np.nansum(mesh_triangle_areas(mesh)) / len(samples))
    return sizes


@dataclass
class CloseEntries:
    """Table entries whose ray lands close by, by direction, then sample (every array (m,)).

    sample, direction : int64; weight : float32 the gather weight, max(0, n . d_i) times the
    sample's scale; obj : int64 the object hit; uv : (m, 2) float32 the atlas coordinate it
    landed at (the table's); floor : float64 the least distance its code allows
    (VisibilityTable.entry_distance_floor)
    """

    sample: np.ndarray
    direction: np.ndarray
    weight: np.ndarray
    obj: np.ndarray
    uv: np.ndarray
    floor: np.ndarray


def table_close_entries(table, target_reach: np.ndarray, sample_reach: np.ndarray | None = None, threads: int = 0,
                        compiled: bool = True) -> tuple[np.ndarray, ...]:
    """The entries of ``table`` that hit an object o nearer than ``target_reach[o]`` (O,) and,
    if given, than their sample's ``sample_reach`` (K,): (sample, direction, obj) (m,) int64,
    uv (m, 2) float32 and floor (m,) float64 (as :class:`CloseEntries`), by direction, then
    sample. Reads the table alone, so a table of sample rows gives those rows' entries
    (core.distributed.split). Compiled where the kernels load (``compiled``), bitwise the numpy pass."""
    module = kernels.compiled() if compiled else None
    count = len(table.directions)
    if module is None:
        sample, direction, entry = _table_close_entries_numpy(table, target_reach, sample_reach)
    else:
        entries = table.entries
        arguments = [entries.hit_object, entries.hit_distance_code, DISTANCE_VALUES,
                     np.ascontiguousarray(target_reach, np.float32),
                     np.zeros(0) if sample_reach is None else np.ascontiguousarray(sample_reach, np.float64)]
        offsets = np.zeros(count + 1, np.int64)
        none = np.zeros(0, np.int64)
        # A range of directions (rows) at a time, each range's pages handed back after it (a
        # table in a scratch file): the directions' counts and lists are each range's own.
        rows = max(1, RELEASE_BYTES // max(4 * entries.stored // max(count, 1), 1))
        ranges = [(first, min(count, first + rows)) for first in range(0, count, rows)]
        for first, last in ranges:
            kernels.run(module.close_entries, threads, entries.above_words[first:last], entries.word_base[first:last],
                        *arguments, offsets[first:last + 1], none, none, False)
            entries.release()
        np.cumsum(offsets, out=offsets)
        sample = np.empty(offsets[-1], np.int64)
        entry = np.empty(offsets[-1], np.int64)
        for first, last in ranges:
            kernels.run(module.close_entries, threads, entries.above_words[first:last], entries.word_base[first:last],
                        *arguments, offsets[first:last + 1], sample, entry, True)
            entries.release()
        direction = np.repeat(np.arange(count, dtype=np.int64), np.diff(offsets))
    return (sample, direction, *_close_entry_values(table, entry))


def _close_entry_values(table, entry: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The objects (m,) int64, atlas coordinates (m, 2) float32 and distance floors (m,) float64
    of the stored entries ``entry`` (m,) int64, ascending: those of one span of RELEASE_BYTES of
    the table at a time, its pages handed back after each (a table in a scratch file; a few
    entries of every page would otherwise map the whole table)."""
    obj = np.empty(len(entry), np.int64)
    uv = np.empty((len(entry), 2), np.float32)
    floor = np.empty(len(entry), np.float64)
    span = max(1, RELEASE_BYTES // ENTRY_BYTES)
    cuts = np.searchsorted(entry, np.arange(span, table.entries.stored + span, span))
    start = 0
    for stop in cuts:
        if stop > start:
            part = entry[start:stop]
            obj[start:stop] = table.entries.hit_object[part]
            uv[start:stop] = table.entry_uv(part)
            floor[start:stop] = table.entry_distance_floor(part)
            table.entries.release()
        start = stop
    return obj, uv, floor


def _table_close_entries_numpy(table, target_reach: np.ndarray, sample_reach: np.ndarray | None):
    """(sample, direction, entry) of :func:`table_close_entries` in numpy."""
    target_reach = np.asarray(target_reach, np.float32)
    entries = table.entries
    samples, directions, found = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for i in range(len(table.directions)):
        span = entries.row_span(i, i + 1)
        stored = np.nonzero(entries.mask(i, i + 1)[0])[0]
        row = entries.hit_object[span]
        hit = np.nonzero(row >= 0)[0]
        if not len(hit):
            continue
        distance = table.entry_distance(span.start + hit)
        close = distance < target_reach[row[hit]]
        if sample_reach is not None:
            close &= distance < sample_reach[stored[hit]]
        samples.append(stored[hit[close]].astype(np.int64))
        directions.append(np.full(len(samples[-1]), i, np.int64))
        found.append(span.start + hit[close])
    return np.concatenate(samples), np.concatenate(directions), np.concatenate(found)


def close_entries(p, target_reach: np.ndarray, sample_reach: np.ndarray | None = None,
                  compiled: bool = True) -> CloseEntries | None:
    """The table entries of prepared scene ``p`` that hit an object o nearer than
    ``target_reach[o]`` (O,) and, if given, than their sample's ``sample_reach`` (K,), and
    have a gather weight (:func:`table_close_entries`, weighed); None when there are none.
    A table held by sample rows (core.distributed.split.SplitTable) finds each range's
    entries where it is kept; they are joined here in the same order."""
    if isinstance(p.table, SplitTable):
        sample, direction, obj, uv, floor = p.table.close_entries(target_reach, sample_reach)
    else:
        sample, direction, obj, uv, floor = table_close_entries(p.table, target_reach, sample_reach,
                                                                p.settings.threads, compiled)
    # The cosines are numpy's matrix products, one direction at a time: BLAS sums them its
    # own way (with fused multiply-adds where the CPU has them), which a kernel cannot
    # follow on every platform.
    normals = p.frame_normal.astype(np.float32)
    directions = np.asarray(p.table.directions, np.float32)
    cosine = np.empty(len(sample), np.float32)
    starts = np.searchsorted(direction, np.arange(len(directions) + 1))
    for i in np.nonzero(np.diff(starts))[0]:
        rows = slice(starts[i], starts[i + 1])
        cosine[rows] = normals[sample[rows]] @ directions[i]
    weight = np.maximum(cosine, 0.0) * p.gather_scale().astype(np.float32)[sample]
    del cosine, normals
    keep = weight > 0
    if not keep.any():
        return None
    # Each array is let go as soon as its kept part is taken: the whole ones and the kept ones
    # side by side were the demo's highest memory.
    sample = sample[keep]
    direction = direction[keep]
    weight = weight[keep]
    obj = obj[keep]
    uv = uv[keep]
    floor = floor[keep]
    return CloseEntries(sample, direction, weight, obj, uv, floor)


def _close_entries_numpy(p, target_reach: np.ndarray, sample_reach: np.ndarray | None = None) -> CloseEntries | None:
    """:func:`close_entries` in numpy."""
    return close_entries(p, target_reach, sample_reach, compiled=False)


# Landing points :func:`find_short_hits` works out at a time.
LANDING_CHUNK = 1 << 16


def find_short_hits(p, max_texels: float = SHORT_HIT_TEXELS) -> ShortHits | None:
    """The table entries of prepared scene ``p`` (core.pipeline.prepare.Prepared) that land
    within ``max_texels`` of their target's texel size; None when there are none.

    Nothing is traced: a landing point is the entry's ray origin plus its stored distance (the
    least the distance code allows, so that the point is never beyond the surface it lies on),
    and its normals are those of the sample owning the texel it landed in (a covered
    neighbour where that texel is outside the chart; an entry with none is left to the lookup).
    """
    entries = close_entries(p, max_texels * texel_sizes(p.meshes, p.object_samples))
    if entries is None:
        return None
    owner = _texel_owners(p, entries.obj, entries.uv)
    found = owner >= 0
    # One array at a time, each whole one let go once its kept part is taken: at the Production
    # preset the search is a bake's highest memory, and both copies at once were 190 MB more.
    kept = []
    for name in ("sample", "direction", "weight", "obj", "uv", "floor"):
        kept.append(getattr(entries, name)[found])
        setattr(entries, name, None)
    sample, direction, weight, obj, uv, floor = kept
    owner = owner[found]
    del entries, found, kept
    if not len(sample):
        return None
    position, shading, geometric, origins = _landings(p, sample, direction, owner, floor)
    return ShortHits(sample, weight, obj, uv, SampleSet(position, shading, geometric, origins, obj))


def _landings(p, sample: np.ndarray, direction: np.ndarray, owner: np.ndarray, floor: np.ndarray):
    """Where the entries (sample, direction, owner (m,) int64, floor (m,) float64) land, and
    how they are lit there: (position, shading, geometric) (m, 3) float64 and the shadow rays'
    origins (m, 3) (float32, or float64 where the ray scene is centred; RayScene.ray_origins).
    Compiled where the kernels load (bitwise :func:`_landings_numpy`): the numpy steps took
    most of the short-hit pass (0.2 of 0.5 s on the many_objects benchmark at N = 256)."""
    module = kernels.compiled()
    if module is None:
        return _landings_numpy(p, sample, direction, owner, floor)
    count = len(sample)
    centre = np.asarray(p.ray_scene.centre, np.float64)
    centred = bool(centre.any())
    footprint = _NO_FOOTPRINT if p.footprint is None else np.ascontiguousarray(p.footprint[0], np.float32)
    rotated = p.rotations is not None
    position, shading, geometric = (np.empty((count, 3)) for _ in range(3))
    origins = np.empty((count, 3), np.float64 if centred else np.float32)
    kernels.run(module.landings, p.settings.threads, np.asarray(sample, np.int64), np.asarray(direction, np.int64),
                np.asarray(owner, np.int64), np.ascontiguousarray(floor, np.float64),
                np.ascontiguousarray(p.position, np.float64), footprint,
                np.ascontiguousarray(p.rotations, np.float64) if rotated else _NO_ROTATIONS,
                np.ascontiguousarray(p.group, np.int64) if rotated else _NO_GROUPS,
                np.ascontiguousarray(p.directions, np.float64), np.ascontiguousarray(p.geometric, np.float64),
                np.ascontiguousarray(p.normal, np.float64), centre, centred, np.float32(tol.RAY_OFFSET_INT_SCALE),
                np.float32(tol.RAY_OFFSET_FLOAT_SCALE), np.float32(tol.RAY_OFFSET_ORIGIN), position, shading,
                geometric, origins)
    return position, shading, geometric, origins


# Stand-ins for the landing kernel's arrays where there are none (one signature for all calls).
_NO_FOOTPRINT = np.zeros((0, 0, 3), np.float32)
_NO_ROTATIONS = np.zeros((0, 3, 3))
_NO_GROUPS = np.zeros(0, np.int64)


def _landings_numpy(p, sample: np.ndarray, direction: np.ndarray, owner: np.ndarray, floor: np.ndarray):
    """:func:`_landings` in numpy."""
    count = len(sample)
    position, shading, geometric = (np.empty((count, 3)) for _ in range(3))
    origins = None
    # Chunk by chunk, the (m, 3) temporaries stay small: at the Production preset all 3.8 M
    # landings at once took 700 MB beyond the arrays kept, the bake's highest memory then.
    # Every step is per landing, so the chunks give the whole pass's bits.
    for first in range(0, count, LANDING_CHUNK):
        rows = slice(first, min(count, first + LANDING_CHUNK))
        chosen, way = sample[rows], direction[rows]
        start = p.position[chosen]
        if p.footprint is not None:
            points = p.footprint[0]
            start = start + points[chosen, way % points.shape[1]]
        unit = p.sample_directions(way, chosen)
        position[rows] = np.asarray(p.ray_scene.ray_origins(start, p.geometric[chosen]), np.float64) \
            + unit * floor[rows, None]
        geometric[rows], shading[rows] = p.geometric[owner[rows]], p.normal[owner[rows]]
        # The side the ray came from is the side that is lit (the table keeps front-face hits only).
        facing = np.where(np.einsum("kd,kd->k", geometric[rows], unit) > 0, -1.0, 1.0)[:, None]
        geometric[rows] *= facing
        shading[rows] *= facing
        landed = p.ray_scene.ray_origins(position[rows], geometric[rows])
        if origins is None:
            origins = np.empty((count, 3), landed.dtype)
        origins[rows] = landed
    return position, shading, geometric, origins


# The texels a landing point's owner is looked for in, in turn: its own, then its neighbours.
OWNER_SHIFTS = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1))


def _texel_owners(p, obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(m,) int64 the sample owning the texel each landing (object (m,) int64, atlas uv (m, 2)
    float32) lies in, else one owning a neighbouring texel; -1 where none does."""
    module = kernels.compiled()
    if module is None:
        return _texel_owners_numpy(p, obj, uv)
    widths = np.array([samples.width for samples in p.object_samples], np.int64)
    heights = np.array([samples.height for samples in p.object_samples], np.int64)
    # One grid of texel owners for the objects landed on, each at its offset.
    landed = np.nonzero(np.bincount(obj, minlength=len(widths)))[0]
    texels = widths[landed] * heights[landed]
    grid_offset = np.zeros(len(widths), np.int64)
    grid_offset[landed] = np.cumsum(texels) - texels
    grid = np.full(int(texels.sum()), -1, np.int64)
    for index in landed:
        samples = p.object_samples[index]
        grid[grid_offset[index] + samples.pixel] = p.sample_offset[index] + np.arange(len(samples))
    owner = np.empty(len(obj), np.int64)
    module.texel_owners(np.asarray(obj, np.int64), np.ascontiguousarray(uv, np.float32), widths, heights, grid_offset,
                        grid, np.array(OWNER_SHIFTS, np.int64), owner)
    return owner


def _texel_owners_numpy(p, obj: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """:func:`_texel_owners` in numpy."""
    owner = np.full(len(obj), -1, np.int64)
    for index in np.unique(obj):
        samples = p.object_samples[index]
        width, height = samples.width, samples.height
        texel_owner = np.full(width * height, -1, np.int64)
        texel_owner[samples.pixel] = p.sample_offset[index] + np.arange(len(samples))
        chosen = np.nonzero(obj == index)[0]
        x = np.clip(np.floor(uv[chosen, 0] * width).astype(np.int64), 0, width - 1)
        y = np.clip(np.floor(uv[chosen, 1] * height).astype(np.int64), 0, height - 1)
        found = np.full(len(chosen), -1, np.int64)
        for dx, dy in OWNER_SHIFTS:
            open_rows = found < 0
            if not open_rows.any():
                break
            xx, yy = np.clip(x + dx, 0, width - 1), np.clip(y + dy, 0, height - 1)
            found[open_rows] = texel_owner[(yy * width + xx)[open_rows]]
        owner[chosen] = found
    return owner


def contact_correction(short: ShortHits, layout, reflected_atlas: np.ndarray, at_hits: np.ndarray,
                       albedo_atlas: np.ndarray, samples: int) -> np.ndarray:
    """(samples, C) float64: what the first bounce gains when the short hits reflect the lamps'
    direct irradiance ``at_hits`` (m, C) at their landing points instead of what the gather
    looked up for them in ``reflected_atlas`` (layout.size, C) float32, the packed radiance
    albedo / pi * lamp irradiance.

    ``albedo_atlas`` (layout.size, 3) float32 is the packed albedo (C a multiple of 3, one
    RGB per light group). Each entry adds weight * (albedo / pi * at_hits - lookup).
    Compiled where the kernels load (one pass, bitwise the numpy code's below).
    """
    module = kernels.compiled()
    if module is not None and reflected_atlas.dtype == np.float32 and albedo_atlas.dtype == np.float32:
        total = np.zeros((samples, at_hits.shape[1]))
        module.contact_sums(reflected_atlas, albedo_atlas, layout.widths.astype(np.int32),
                            layout.heights.astype(np.int32), layout.offsets32,
                            np.asarray(short.obj, np.int32), np.ascontiguousarray(short.uv, np.float32),
                            np.asarray(short.weight, np.float32), np.ascontiguousarray(at_hits, np.float64),
                            np.asarray(short.sample, np.int64), total)
        return total
    looked_up = layout.bilinear(reflected_atlas, short.obj, short.uv).astype(np.float64)
    albedo = layout.bilinear(albedo_atlas, short.obj, short.uv).astype(np.float64)
    groups = at_hits.shape[1] // 3
    difference = (np.tile(albedo, groups) / np.pi * at_hits - looked_up) * short.weight[:, None]
    return sum_by_sample(short.sample, difference, samples)


def sum_by_sample(sample: np.ndarray, values: np.ndarray, count: int, rows: np.ndarray | None = None) -> np.ndarray:
    """(count, C) float64: the rows of ``values`` (m, C) summed per ``sample`` (m,) int, in the
    order given (bitwise ``np.add.at``'s sums, at a fraction of its cost: compiled, or one bincount a
    column). With ``rows`` (m,) int, the sums take ``values[rows]`` ((n, C) values), without
    making that copy where the kernels run."""
    values = np.asarray(values)
    module = kernels.compiled()
    if module is not None:
        total = np.zeros((count, values.shape[1]))
        module.sum_rows(_index_array(sample), np.ascontiguousarray(values, np.float64),
                        np.zeros(0, np.int64) if rows is None else _index_array(rows), total)
        return total
    if rows is not None:
        values = values[rows]
    total = np.empty((count, values.shape[1]))
    for column in range(values.shape[1]):
        total[:, column] = np.bincount(sample, weights=values[:, column], minlength=count)
    return total


def _index_array(indices) -> np.ndarray:
    """``indices`` as the compiled sums take them: int32 or int64 as they are (the filter's
    pairs are int32: no int64 copy of them), else as int64."""
    indices = np.asarray(indices)
    return indices if indices.dtype in (np.int32, np.int64) else indices.astype(np.int64)


# The sky's share at a landing point is measured once per cell of CONTACT_WORLD_CELLS^2 cells
# of its target's texel (and side a landing faces), with CONTACT_WORLD_RAYS cosine-distributed
# rays, and every landing in the cell takes it. A landing's light weighs one direction of its
# sample's gather, so a few rays each suffice, their noise averaging over the landings; cells
# much smaller than a texel, since the landings that matter (under a ball resting on a floor of
# half-metre texels) lie within a small part of one. Seed 1 of scenegen, sky only (64^2, 256
# directions, against Cycles): 13.1% per texel without; 4 x 4 cells and 16 rays 6.2%; 8 x 8 and
# 16 rays 4.0%; 32 x 32 and 4 rays 3.2% (blocks 1.8%); 64 x 64 and 4 rays 3.0% at 1.7x the rays.
CONTACT_WORLD_RAYS = 4
CONTACT_WORLD_CELLS = 32
# The most a landing's openness may exceed its target texel's: a landing on the open part of
# a texel half under an occluder is lit more than the texel's mean, but a texel almost wholly
# enclosed (few of its rays open) would otherwise amplify its noise.
MAX_OPENNESS_RATIO = 4.0


def landing_openness(short: ShortHits, object_samples, ray_scene, rays: int = CONTACT_WORLD_RAYS,
                     cells: int = CONTACT_WORLD_CELLS) -> np.ndarray:
    """(m,) float64: the cosine-weighted share of open directions above each short hit's landing
    point, as core.transport.gather.ambient_occlusion measures a texel's from the table: the
    landings of one cell (``cells``^2 cells a texel of the target, per side the landing faces)
    share one measurement of ``rays`` stratified cosine-distributed rays about the first
    landing's normal, each cell's set turned about the normal by an angle of its own."""
    points = short.points
    across = cells * np.array([[s.width, s.height] for s in object_samples], np.int64)
    counts = across[:, 0] * across[:, 1] * 8  # 8: the sides a landing's normal faces, one bit an axis
    base = np.cumsum(counts) - counts
    cell = np.clip(np.floor(short.uv * across[short.obj]).astype(np.int64), 0, across[short.obj] - 1)
    side = (points.normal > 0) @ np.array([1, 2, 4])
    key = base[short.obj] + (cell[:, 1] * across[short.obj, 0] + cell[:, 0]) * 8 + side
    keys, first, cell_of = np.unique(key, return_index=True, return_inverse=True)
    normal = np.asarray(points.normal[first], np.float64)
    tangent, bitangent = orthonormal_frame(normal)
    # A stratified square set (each point in the middle of its share), mapped to a cosine-weighted hemisphere.
    square = np.mod((sobol_points(rays)[:, :2] >> np.uint32(8)) * 2.0**-24 + 0.5 / rays, 1.0)
    disk = square_to_disk(square)  # (rays, 2)
    lift = np.sqrt(np.clip(1.0 - np.einsum("rk,rk->r", disk, disk), 0.0, 1.0))
    turn = (hash32(keys.astype(np.uint32) ^ hash32((keys >> 32).astype(np.uint32))) * (2.0 * np.pi / 2.0**32))
    cos, sin = np.cos(turn)[:, None], np.sin(turn)[:, None]
    x = cos * disk[None, :, 0] - sin * disk[None, :, 1]  # (cells, rays)
    y = sin * disk[None, :, 0] + cos * disk[None, :, 1]
    directions = (x[..., None] * tangent[:, None] + y[..., None] * bitangent[:, None]
                  + lift[None, :, None] * normal[:, None])
    origins = np.repeat(points.origins[first], rays, axis=0)
    blocked = ray_scene.occluded(origins, directions.reshape(-1, 3).astype(np.float32))
    openness = 1.0 - blocked.reshape(len(first), rays).mean(axis=1)
    return openness[cell_of.ravel()]


def world_contact_correction(short: ShortHits, openness: np.ndarray, layout, world_atlas: np.ndarray,
                             openness_atlas: np.ndarray, samples: int) -> np.ndarray:
    """(samples, C) float64: what every gather gains when the short hits reflect the world's light
    at their landing points instead of their target texel's mean. The texel's world light
    ``world_atlas`` (layout.size, C), packed albedo / pi * irradiance as the gathers look it up,
    is taken to scale with the sky's openness: at a landing it is the looked-up light times the
    landing's ``openness`` (m,) over the texel's, looked up in ``openness_atlas`` (layout.size, 1)
    (at most MAX_OPENNESS_RATIO times). Each entry adds weight * lookup * (ratio - 1)."""
    looked_up = layout.bilinear(world_atlas, short.obj, short.uv).astype(np.float64)
    texel_openness = layout.bilinear(openness_atlas, short.obj, short.uv).astype(np.float64)[:, 0]
    ratio = np.where(texel_openness > 0, openness / np.maximum(texel_openness, 1e-9), 1.0)
    ratio = np.minimum(ratio, MAX_OPENNESS_RATIO)
    return sum_by_sample(short.sample, looked_up * ((ratio - 1.0) * short.weight)[:, None], samples)
