"""Direct light from lamps: unshadowed irradiance per sampler point, then shadows
from the paper's shadow fractions or from exact shadow rays."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..lights.lamps import (
    KERNEL_KINDS,
    RECTANGLE_CHUNK,
    LampPoints,
    LightContribution,
    angular_radius,
    centre_probe,
    is_rectangle,
    lamp_points,
    outline_probes,
    rectangle_irradiance,
    spot_cone,
)
from ..sampling.terminator import lift_amount
from .contract import SampleSet, Shadowing

# Samples one exact-shadow direct-light pass evaluates at a time: its working arrays (about a
# dozen of (n, 3) float64) stay near 100 MB however many samples there are, where the 3.8 M
# short hits of the demo at the Production preset took 700 MB in one pass, the bake's highest.
DIRECT_LIGHT_CHUNK = 1 << 18


def lamp_irradiance(samples: SampleSet, shadowing: Shadowing, lights, report=None, spread: list | None = None
                    ) -> tuple[np.ndarray, int]:
    """(K, 3) float64 irradiance of ``lights`` at ``samples``, and the shadow rays traced
    (:func:`_lamp_irradiance`), by chunks of DIRECT_LIGHT_CHUNK samples where shadows are exact.
    A sample's light depends on its own id alone (SampleSet.rows), so the chunks' light is
    bitwise the whole set's; the fractions' lookups read the whole table's rows, so they run whole.
    ``spread``: a list, to which the light's standard error (K, 3) float64 is appended
    (:func:`_lamp_irradiance`)."""
    count = len(samples.position)
    if shadowing.mode == "fractions" or count <= DIRECT_LIGHT_CHUNK:
        return _lamp_irradiance(samples, shadowing, lights, report, spread)
    irradiance = np.empty((count, 3))
    error = np.empty((count, 3)) if spread is not None else None
    shadow_rays = 0
    curved = samples.derived.get("curved_footprints")
    curved_parts = []
    for start in range(0, count, DIRECT_LIGHT_CHUNK):
        stop = min(count, start + DIRECT_LIGHT_CHUNK)
        chunk = samples.rows(start, stop)
        if curved is not None:
            chunk.derived["curved_footprints"] = curved[start:stop]
        part_report = None if report is None else (lambda f, a=start, b=stop: report((a + f * (b - a)) / count))
        part_spread = [] if spread is not None else None
        irradiance[start:stop], rays = _lamp_irradiance(chunk, shadowing, lights, part_report, part_spread)
        if error is not None:
            error[start:stop] = part_spread[0]
        shadow_rays += rays
        curved_parts.append(chunk.derived.get("curved_footprints"))
    if curved is None and all(part is not None for part in curved_parts):
        # What the chunks derived is kept with the whole set, for the next relight.
        samples.derived["curved_footprints"] = np.concatenate(curved_parts)
    if spread is not None:
        spread.append(error)
    return irradiance, shadow_rays


def _lamp_irradiance(samples: SampleSet, shadowing: Shadowing, lights, report=None, spread: list | None = None
                     ) -> tuple[np.ndarray, int]:
    """(K, 3) float64 irradiance of ``lights`` at ``samples``, and the shadow rays traced.

    Each lamp is integrated over its extent with the direct-light sampler
    (:func:`core.lights.lamps.light_contributions`; one point for a hard lamp) and, with
    exact shadows and a footprint in ``samples`` (:attr:`SampleSet.footprint`, P points a
    texel), over each texel's footprint too: at least P points a lamp, point j seen from
    footprint point j % P, also for a hard lamp, so a shadow edge crossing a texel leaves
    the share of it that is lit. Shadows as ``shadowing`` says: exact rays against the
    lamp's blockers (:meth:`Shadowing.blocker_scene`), one per point where the probes of
    :func:`_penumbra_probes` disagree and none elsewhere, or the paper's fractions looked up
    in each point's direction, so a soft lamp averages the fractions over its extent (the
    fractions are per texel, so they ignore the footprint). Light linking: a lamp lights
    only its receivers. ``report(fraction)`` is called after each lamp. The CPU backend's
    direct-light pass.

    ``spread``: a list, to which the standard error (K, 3) float64 of the returned light is
    appended. Only the samples whose every point is traced (a penumbra, a shadow edge across the
    footprint) have one: half the difference between the light of the first and of the second
    half of their points (each half of a scrambled Sobol set is itself stratified, so the two
    are two estimates of the same light), summed over the lamps in quadrature. It is 0 where the
    probes decided a sample wholly lit or wholly shadowed (core.transport.estimate).
    """
    fractions_mode = bool(lights) and shadowing.mode == "fractions"
    footprint = None if fractions_mode else samples.footprint
    irradiance = np.zeros((len(samples.position), 3))
    variance = np.zeros(len(samples.position)) if spread is not None else None
    shadow_rays = 0
    # Each sample's index in the whole bake, not in this set: a set of some rows of the bake
    # (SampleSet.rows) then draws the same points and gets bitwise the same light.
    sample_ids = samples.sample_ids()
    points = [lamp_points(light, shadowing.area_light_samples) for light in lights]
    if footprint is not None:
        points = [max(count, footprint.shape[1]) for count in points]
    # Progress by expected shadow rays, not by lamps: a soft lamp traces several per sample.
    costs = np.cumsum([shadow_rays_per_sample(light, shadowing) for light in lights])
    for light_index, light in enumerate(lights):
        fractions = None
        if fractions_mode and light.casts_shadows:
            if light.kind == "SUN":
                fractions = shadowing.distant_fractions()
            else:
                light_distance = np.linalg.norm(samples.position - np.asarray(light.position, np.float64), axis=1)
                fractions = shadowing.local_fractions(light_distance)
        blockers = shadowing.blocker_scene(light) if not fractions_mode else None
        receives = shadowing.receivers(light, samples)
        lamp = LampPoints(light, samples.position, samples.normal, shadowing.area_light_samples, sample_ids,
                          shadowing.seed, footprint, points[light_index], samples.footprint_normals,
                          _threads(shadowing))
        # Skip what a sample does not need. Rays to the lamp's centre and outline tell each
        # sample whether it is in a penumbra; a sample wholly lit or wholly shadowed traces no
        # more rays, and where the lamp looks small from it (its unshadowed light is nearly
        # constant over the lamp) the first few points stand for all. Only penumbrae trace
        # every point. Without this, Blender's default sun (0.5 degrees) would trace
        # points[i] rays in every texel.
        adaptive = blockers is not None and lamp.count >= ADAPTIVE_MIN_POINTS
        decided = np.zeros(len(sample_ids), bool)
        shadowed = np.zeros(len(sample_ids), bool)
        edge_light = edges = edge_half = None
        if adaptive:
            decided, shadowed, mixed, probe_rays = _penumbra_probes(light, lamp, samples, blockers, receives)
            shadow_rays += probe_rays
            # A spot's cone edge across a texel is a step in its light as sharp as a shadow's.
            cone = spot_edge_samples(light, samples) & ~(decided & shadowed)
            mixed |= cone
            if footprint is not None and samples.dense_footprint is not None and mixed.any():
                # A shadow edge crossing a texel is where 16 points leave visible noise: such
                # texels take EDGE_FOOTPRINT_POINTS, a spot's cone edge SPOT_EDGE_POINTS, and the
                # loop below leaves them alone.
                edges = np.nonzero(mixed)[0]
                edge_light, edge_half = np.zeros((len(edges), 3)), np.zeros((len(edges), 3))
                for part, count in ((~cone[edges], EDGE_FOOTPRINT_POINTS), (cone[edges], SPOT_EDGE_POINTS)):
                    if part.any():
                        edge_light[part], part_rays, edge_half[part] = _edge_irradiance(
                            light, samples, edges[part], shadowing, blockers, receives, points[light_index], count)
                        shadow_rays += part_rays
                decided[edges] = shadowed[edges] = True
        lamp_light = np.zeros_like(irradiance)
        # The light of the first half of the points, where every point is traced (the spread).
        traced_everywhere = ~decided
        first_half = np.zeros_like(irradiance) if variance is not None else None
        slots = footprint.shape[1] if footprint is not None else lamp.count
        rows = None  # every sample; after the first points only those still needing more
        small = _small_lamp_samples(light, lamp, samples, decided, _threads(shadowing)) if adaptive else None
        pending = None
        if adaptive:
            visible = ~shadowed if receives is None else receives & ~shadowed
            pending = lamp.add_untraced(~_mask(edges, len(decided)), decided, visible, small, SMALL_LAMP_POINTS,
                                        lamp_light)
        if pending is not None:
            # Summed in one pass where no ray is needed: the loop below traces the rest.
            rows = np.nonzero(pending)[0]
            lamp = lamp.subset(rows)
            adaptive = False
        whole_lamp, closed = lamp, np.zeros(len(decided), bool)
        if adaptive and is_rectangle(light):
            # Wholly lit, a rectangle's light over the footprint is known in closed form: its
            # points' noise (cos / r^2 near the lamp) goes, and so do their evaluations.
            closed = decided & ~shadowed & ~small
            if closed.any():
                lamp_light[closed] = _closed_rectangle_light(light, lamp, np.nonzero(closed)[0], receives)
                rows = np.nonzero(~closed)[0]
                small &= ~closed
                lamp = lamp.subset(rows)
        for index in range(lamp.count):
            if rows is not None and not len(rows):
                break
            if adaptive and index == SMALL_LAMP_POINTS:
                lamp_light[small] *= lamp.count / SMALL_LAMP_POINTS
                rows = np.nonzero(~small & ~closed)[0]
                if not len(rows):
                    break
                lamp = whole_lamp.subset(rows)
            part = lamp.contribution(index)
            # Above the shading normal's horizon, as Cycles lights a smooth face (its shadow rays
            # then start lifted towards the smooth surface: trace_shadow_rays).
            lit = part.lit if part.lit is not None else _lit(part, lamp.point_normal(index))
            if receives is not None:
                lit &= receives if rows is None else receives[rows]
            visibility = lit.astype(np.float64)
            if fractions is not None:
                visibility = np.where(lit, fractions.visibility(part.to_light), 0.0)
            elif blockers is not None:
                known = decided if rows is None else decided[rows]
                visibility[shadowed if rows is None else shadowed[rows]] = 0.0
                local = np.nonzero(lit & ~known)[0]
                if len(local):
                    blocked = trace_shadow_rays(blockers, samples, part, local,
                                                local if rows is None else rows[local])
                    visibility[local[blocked]] = 0.0
                    shadow_rays += len(local)
            if rows is None:
                lamp_light += part.irradiance * visibility[:, None]
            else:
                lamp_light[rows] += part.irradiance * visibility[:, None]
            if first_half is not None and _in_first_half(index, slots):
                if rows is None:
                    first_half += part.irradiance * visibility[:, None]
                else:
                    first_half[rows] += part.irradiance * visibility[:, None]
        if edges is not None:
            lamp_light[edges] = edge_light
        if variance is not None and lamp.count > 1:
            variance += _half_difference_variance(lamp_light, first_half, traced_everywhere)
            if edges is not None:
                variance[edges] += _half_difference_variance(edge_light, edge_half)
        irradiance += lamp_light
        if report is not None:
            report(costs[light_index] / costs[-1])
    if spread is not None:
        # Per unit of light in each channel: the lamps' spread, as their light, shared by the channels.
        brightness = irradiance.sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(brightness[:, None] > 0, 3.0 * irradiance / brightness[:, None], 1.0)
        spread.append(np.sqrt(variance)[:, None] * share)
    return irradiance, shadow_rays


def spot_edge_samples(light, samples: SampleSet) -> np.ndarray:
    """(K,) bool: samples whose footprint box reaches into a spot's cone edge: some corner (or the
    centre) is not wholly outside the cone and some is not wholly inside its blend band, each
    widened by the lamp's angular radius there (Cycles weighs each point of a spot of some radius
    by the cone factor of its own direction, which blurs the edge by that much). All False for
    other lamps and without a footprint. Sixteen footprint points left such texels 5% off Cycles,
    as a shadow edge's would (a column beside a spot, seed 11 of ../shared/tools/scenegen.py)."""
    count = len(samples.position)
    if light.kind != "SPOT" or samples.footprint_corners is None or not count:
        return np.zeros(count, bool)
    cos_half, band = spot_cone(light)
    half = np.arccos(np.clip(cos_half, -1.0, 1.0))
    inside = np.arccos(np.clip(cos_half + max(band, 0.0), -1.0, 1.0))  # the band's inner edge
    alpha = angular_radius(light, samples.position)
    some_lit = np.zeros(count, bool)
    some_short = np.zeros(count, bool)
    corners = samples.footprint_corners.astype(np.float64)
    axis = np.asarray(light.direction, np.float64)
    for offset in [np.zeros((count, 3))] + [corners[:, corner] for corner in range(corners.shape[1])]:
        from_light = samples.position + offset - np.asarray(light.position, np.float64)
        from_light /= np.maximum(np.linalg.norm(from_light, axis=1), 1e-300)[:, None]
        angle = np.arccos(np.clip(from_light @ axis, -1.0, 1.0))
        some_lit |= angle - alpha < half
        some_short |= angle + alpha > inside
    return some_lit & some_short


def _closed_rectangle_light(light, lamp: LampPoints, rows: np.ndarray, receives: np.ndarray | None) -> np.ndarray:
    """(len(rows), 3) float64: a rectangular lamp's unshadowed light at samples ``rows`` of
    ``lamp`` (its LampPoints over all samples) averaged over each one's footprint points, as its
    points would average it (core.lights.lamps.rectangle_irradiance); 0 where the lamp does not
    light the sample (``receives`` (K,) bool, light linking, or None: everywhere)."""
    if lamp.footprint is None:
        light_sum = rectangle_irradiance(light, lamp.position[rows], lamp.normal[rows])
    else:
        slots = lamp.footprint.shape[1]
        light_sum = np.empty((len(rows), 3))
        # By parts of RECTANGLE_CHUNK footprint points: the pass's own chunk of samples times
        # its 16 slots would hold some 300 MB of receivers at once.
        step = max(1, RECTANGLE_CHUNK // slots)
        for first in range(0, len(rows), step):
            part = rows[first:first + step]
            receivers = (lamp.position[part][:, None, :] + lamp.footprint[part].astype(np.float64)).reshape(-1, 3)
            normals = (np.repeat(lamp.normal[part][:, None, :], slots, axis=1) if lamp.footprint_normals is None
                       else lamp.footprint_normals[part].astype(np.float64)).reshape(-1, 3)
            light_sum[first:first + step] = rectangle_irradiance(light, receivers, normals).reshape(
                len(part), slots, 3).mean(axis=1)
    if receives is not None:
        light_sum *= receives[rows, None]
    return light_sum


def _half_difference_variance(light: np.ndarray, first_half: np.ndarray, where: np.ndarray | None = None
                              ) -> np.ndarray:
    """(k,) float64: the squared standard error of ``light`` (k, 3), the sum of a set of points'
    light whose first half summed to ``first_half`` (k, 3): the two halves' means are 2 * first
    and 2 * (light - first), and half their difference, squared, is the variance of the whole
    set's mean (were the halves independent; a stratified set's complementary halves make it an
    overestimate by about 2^(1/2) for a shadow edge's step). Summed over the channels' light;
    0 outside ``where`` (k,) bool."""
    difference = (2.0 * first_half - light).sum(axis=1)
    squared = difference * difference / 9.0  # per channel of a white light, as the channels share it
    return squared if where is None else np.where(where, squared, 0.0)


def _in_first_half(point: int, slots: int) -> bool:
    """Whether lamp point ``point``, seen from footprint slot ``point % slots``, belongs to the
    first half of the spread's split: the half whose footprint slots are the first half of the
    footprint's Sobol set. Split by slot, not by point: a soft lamp's P x 4 points see each slot
    four times, and halves of the points that held every slot would agree however few the
    slots are (a texel's footprint, not its lamp, is most of a small lamp's penumbra noise)."""
    return point % slots < slots // 2 if slots > 1 else point < 1


def _small_lamp_samples(light, lamp: LampPoints, samples: SampleSet, decided: np.ndarray, threads: int = 0
                        ) -> np.ndarray:
    """(K,) bool: decided samples whose first SMALL_LAMP_POINTS points stand for all of the
    lamp's: it looks small from them and their footprint is flat (``threads``: the kernels'
    thread count, 0: all cores)."""
    small = decided & (unshadowed_variation(light, samples) < SMALL_LAMP_VARIATION) \
        & (footprint_variation(light, samples) < SMALL_FOOTPRINT_VARIATION)
    if lamp.footprint_normals is not None:
        # A curved footprint's light changes across it: it needs every point's cosine (no ray:
        # it is decided).
        curved = samples.derived.get("curved_footprints")
        if curved is None:
            curved = curved_footprints(lamp.footprint_normals, samples.normal, threads)
            samples.derived["curved_footprints"] = curved
        small &= ~curved
    return small


def _mask(indices: np.ndarray | None, count: int) -> np.ndarray:
    """(count,) bool True at ``indices`` (None: nowhere)."""
    mask = np.zeros(count, bool)
    if indices is not None:
        mask[indices] = True
    return mask


def _lit(part: LightContribution, shading: np.ndarray) -> np.ndarray:
    """(K,) bool: the point is above the horizon of ``shading`` (K, 3) and gives some light."""
    return (np.einsum("kd,kd->k", part.to_light, shading) > 0.0) & np.any(part.irradiance > 0, axis=1)


def _edge_irradiance(light, samples: SampleSet, edges: np.ndarray, shadowing, blockers, receives, points: int,
                     count: int = 0):
    """(len(edges), 3) the lamp's irradiance at samples ``edges`` (rows of ``samples``) over their
    dense footprints (SampleSet.dense_footprint, ``count`` points each, EDGE_FOOTPRINT_POINTS where
    0), every point traced; the rays; and (len(edges), 3) the light of the first half of the points."""
    count = count or EDGE_FOOTPRINT_POINTS
    # The dense footprint and the scramble belong to the samples' indices in the whole bake.
    ids = samples.sample_ids()[edges]
    offsets, normals = samples.dense_footprint(ids, count)
    lamp = LampPoints(light, samples.position[edges], samples.normal[edges], shadowing.area_light_samples, ids,
                      shadowing.seed, offsets, max(points, count), normals, _threads(shadowing))
    module = kernels.compiled()
    if module is not None and lamp.point_lamp:
        return _hard_edge_irradiance(module, lamp, samples, edges, blockers, receives, count)
    light_sum = np.zeros((len(edges), 3))
    first_half = np.zeros((len(edges), 3))
    rays = 0
    # Several points' rays in one query; their light still added point by point, in order.
    points_at_once = max(1, EDGE_BATCH_ROWS // max(len(edges), 1))
    for first in range(0, lamp.count, points_at_once):
        evaluated = []
        for index in range(first, min(first + points_at_once, lamp.count)):
            part = lamp.contribution(index)
            lit = part.lit if part.lit is not None else _lit(part, lamp.point_normal(index))
            if receives is not None:
                lit &= receives[edges]
            evaluated.append((part, lit, np.nonzero(lit)[0]))
        answers = iter(trace_shadow_rays_together(
            blockers, samples, [(part, local, edges[local]) for part, _, local in evaluated if len(local)]))
        for offset, (part, lit, local) in enumerate(evaluated):
            if len(local):
                lit[local[next(answers)]] = False
                rays += len(local)
            light_sum += part.irradiance * lit[:, None]
            if _in_first_half(first + offset, count):
                first_half += part.irradiance * lit[:, None]
    return light_sum, rays, first_half


def _hard_edge_irradiance(module, lamp: LampPoints, samples: SampleSet, edges: np.ndarray, blockers, receives,
                          footprint_points: int) -> tuple[np.ndarray, int, np.ndarray]:
    """:func:`_edge_irradiance` of a lamp without extent (``lamp``: its points over the edge
    samples' dense footprints) through the compiled kernels, bitwise the loop there: each
    batch of points and every one of their shadow rays made in one pass
    (core.kernels.light_kernels.hard_lamp_edge_rays), traced in one query, and added up point
    by point. The loop's Python and its two kernel calls a point were most of an edge's cost
    (a few hundred edge samples a lamp on the benchmark scenes: some 40 ms for 25k rays)."""
    count = len(edges)
    smooth = samples.terminator is not None
    terminator = np.ascontiguousarray(samples.terminator[edges], np.float64) if smooth else _NOWHERE
    cutoff = np.ascontiguousarray(samples.terminator_cutoff[edges], np.float64) if smooth else _NO_CUTOFF
    receiving = np.ones(count, bool) if receives is None else np.ascontiguousarray(receives[edges], bool)
    point_normals = (np.zeros((count, 0, 3), np.float32) if lamp.footprint_normals is None
                     else np.ascontiguousarray(lamp.footprint_normals, np.float32))
    light = lamp.light
    origin_type = samples.origins.dtype
    geometric = np.ascontiguousarray(samples.geometric[edges], np.float64)
    light_sum = np.zeros((count, 3))
    first_half = np.zeros((count, 3))
    rays = 0
    points_at_once = max(1, EDGE_BATCH_ROWS // max(count, 1))
    for first in range(0, lamp.count, points_at_once):
        batch = min(points_at_once, lamp.count - first)
        irradiance = np.empty((batch, count, 3))
        lit = np.empty((batch, count), bool)
        origins = np.empty((batch, count, 3), origin_type)
        directions = np.empty((batch, count, 3))
        limits = np.empty((batch, count), np.float32)
        kernels.run(module.hard_lamp_edge_rays, lamp.threads, KERNEL_KINDS[light.kind],
                    np.asarray(light.position, np.float64), np.asarray(light.direction, np.float64),
                    *spot_cone(light), np.ascontiguousarray(lamp.position, np.float64),
                    np.ascontiguousarray(lamp.normal, np.float64), geometric, terminator, cutoff,
                    np.ascontiguousarray(lamp.footprint, np.float32), point_normals, first, receiving,
                    lamp.scale / lamp.count, *_ray_constants(blockers), irradiance, lit, origins, directions, limits)
        flat = lit.reshape(-1)
        traced = np.flatnonzero(flat)
        if len(traced):
            blocked = blockers.occluded(origins.reshape(-1, 3)[traced], directions.reshape(-1, 3)[traced],
                                        limits.reshape(-1)[traced])
            flat[traced[blocked]] = False
            rays += len(traced)
        kernels.run(module.edge_light_add, lamp.threads, irradiance, lit, light_sum)
        halves = np.array([_in_first_half(first + offset, footprint_points) for offset in range(batch)])
        if halves.any():
            first_half += np.einsum("bkc,bk->kc", irradiance[halves], lit[halves])
    return light_sum, rays, first_half


def _ray_constants(blockers) -> tuple:
    """What the edge and corner-probe kernels take to make shadow rays in ``blockers``' frame
    (core.kernels.light_kernels._shadow_ray): the share of a ray's length kept, the ray scene's
    centre (3,) float64 and whether it is off the origin, and core.tolerances' RAY_OFFSET_*
    steps as float32."""
    centre = np.asarray(blockers.centre, np.float64)
    return (1.0 - tol.SHADOW_RAY_SHORTEN, centre, bool(centre.any()), np.float32(tol.RAY_OFFSET_INT_SCALE),
            np.float32(tol.RAY_OFFSET_FLOAT_SCALE), np.float32(tol.RAY_OFFSET_ORIGIN))


def _threads(shadowing) -> int:
    """The Threads preference as the preparation's ray scene holds it (0: all cores)."""
    return getattr(shadowing.ray_scene, "threads", 0) or 0


def curved_footprints(footprint_normals: np.ndarray, normal: np.ndarray, threads: int = 0) -> np.ndarray:
    """(K,) bool: samples whose footprint points' normals (K, P, 3) float32 turn away from
    their own ``normal`` (K, 3) float64 by more than about a degree. Compiled where the kernels
    load (core.kernels.light_kernels.footprint_curvature), bitwise this einsum, which widens
    every cosine to a (K, P) float64 temporary first (8 bytes a footprint point: 49 MiB on the demo);
    ``threads``: the kernel's thread count (0: all cores)."""
    module = kernels.compiled()
    if module is not None and footprint_normals.dtype == np.float32:
        curved = np.empty(len(normal), bool)
        kernels.run(module.footprint_curvature, threads, np.ascontiguousarray(footprint_normals),
                    np.ascontiguousarray(normal, np.float64), CURVED_COSINE, curved)
        return curved
    return np.einsum("kpd,kd->kp", footprint_normals, normal).min(axis=1) < CURVED_COSINE


# A footprint whose normals stay within this cosine of its centre's (about 1.8 degrees) shades
# like its centre to within 0.05 of a cosine's slope: the first points stand for all.
CURVED_COSINE = 0.9995


def _penumbra_probes(light, lamp: LampPoints, samples: SampleSet, blockers, receives):
    """Shadow rays that tell a penumbra from full light or full shadow: from the sample to
    the lamp's centre and outline (:func:`core.lights.lamps.outline_probes`; the centre only
    for a lamp without extent) and, over a footprint, from the four corners of the texel's
    box (:attr:`SampleSet.footprint_corners`) to the lamp's centre: a straight shadow edge
    that crosses the box separates two of them.

    Returns (decided, shadowed, mixed, rays): (K,) bool each, a sample whose probes all agree
    (and whether they all were blocked), one whose probes disagree (a penumbra or a shadow
    edge), and the rays traced. A sample none of whose probes is above its horizon is
    neither decided nor mixed.
    """
    count = len(samples.position)
    seen_open, seen_blocked = np.zeros(count, bool), np.zeros(count, bool)
    # Each sample turns its round outline by its own scramble, so missed caps do not align.
    rotation = (lamp.scrambles[0] >> np.uint32(8)) * (2.0 * np.pi * 2.0 ** -24)
    footprint = lamp.footprint
    # Where the lamp looks wide, an occluder narrower than it (a pergola's slat under a panel)
    # can pass between the centre and the outline and leave every probe open: those samples also
    # probe along the lamp's first WIDE_LAMP_CHECK_POINTS stratified points, which such a slat
    # crosses. Without them, seed 7 of ../shared/tools/scenegen.py lit only by its area lamp was
    # 10% too bright on 4x4 blocks. A wide lamp of fewer points than twice that traces them all.
    wide = (np.nonzero(angular_radius(light, samples.position) > WIDE_LAMP_RADIUS)[0]
            if not lamp.point_lamp else np.zeros(0, np.int64))
    if len(wide) and lamp.count < 2 * WIDE_LAMP_CHECK_POINTS:
        # Probes would cost about as many rays as the points: those samples trace every point.
        unprobed = np.zeros(count, bool)
        unprobed[wide] = True
        receives = ~unprobed if receives is None else receives & ~unprobed
        wide = wide[:0]

    module = kernels.compiled()
    corners_compiled = module is not None and footprint is not None and samples.footprint_corners is not None

    def probes():
        # One probe's arrays at a time (each (K, 3) float64, 9 MiB at the demo's 403k
        # texels): made as they are traced, not all thirteen kept side by side. Each with the
        # rows it is for (None: all).
        if not lamp.point_lamp:
            yield from ((to_light, distance, None, None)
                        for to_light, distance in outline_probes(light, samples.position, rotation))
        elif footprint is None:
            # A lamp without extent has no outline: its centre, from the sample or from the corners.
            yield (*centre_probe(light, samples.position), None, None)
        if footprint is not None and samples.footprint_corners is not None and not corners_compiled:
            for corner in range(FOOTPRINT_PROBES):
                moved = samples.position + samples.footprint_corners[:, corner]
                yield (*centre_probe(light, moved), moved, None)
        if len(wide):
            points = lamp.subset(wide)
            for index in range(min(WIDE_LAMP_CHECK_POINTS, lamp.count)):
                part = points.contribution(index)
                yield part.to_light, part.distance, part.position, wide

    def requests():
        for to_light, distance, moved, rows in probes():
            normal = samples.normal if rows is None else samples.normal[rows]
            aimed = np.einsum("kd,kd->k", to_light, normal) > 0.0
            if receives is not None:
                aimed &= receives if rows is None else receives[rows]
            local = np.nonzero(aimed)[0]
            if len(local):
                # A probe carries no light: only its rays are traced.
                yield (LightContribution(None, to_light, distance, moved), local,
                       local if rows is None else rows[local])

    rays = 0
    for (_, _, rows), blocked in trace_shadow_rays_streamed(blockers, samples, requests()):
        seen_blocked[rows[blocked]] = True
        seen_open[rows[~blocked]] = True
        rays += len(rows)
    if corners_compiled:
        for local, blocked in _corner_probes(module, light, samples, blockers, receives):
            seen_blocked[local[blocked]] = True
            seen_open[local[~blocked]] = True
            rays += len(local)
    decided = seen_open != seen_blocked
    return decided, decided & seen_blocked, seen_open & seen_blocked, rays


def _corner_probes(module, light, samples: SampleSet, blockers, receives) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The footprint box's corner probes of :func:`_penumbra_probes` through the compiled
    kernels, one corner at a time: yields (the samples whose probe was traced (n,) int64,
    whether each ray was blocked (n,) bool), bitwise the numpy probes' answers. Each corner's
    rays are made in one pass (core.kernels.light_kernels.corner_probe_rays), where the numpy
    probe took some ten passes over (K, 3) arrays and a set-up kernel (the demo's point lamp:
    0.40 s to 0.30 s of direct light; docs/benchmarks.md, speed part 16)."""
    count = len(samples.position)
    smooth = samples.terminator is not None
    receiving = np.ones(count, bool) if receives is None else np.ascontiguousarray(receives, bool)
    arguments = (light.kind == "SUN", np.asarray(light.position, np.float64),
                 np.asarray(light.direction, np.float64), np.ascontiguousarray(samples.position, np.float64),
                 np.ascontiguousarray(samples.normal, np.float64), np.ascontiguousarray(samples.geometric, np.float64),
                 np.ascontiguousarray(samples.terminator, np.float64) if smooth else _NOWHERE,
                 np.ascontiguousarray(samples.terminator_cutoff, np.float64) if smooth else _NO_CUTOFF,
                 np.ascontiguousarray(samples.footprint_corners, np.float32))
    for corner in range(FOOTPRINT_PROBES):
        aimed = np.empty(count, bool)
        origins = np.empty((count, 3), samples.origins.dtype)
        directions = np.empty((count, 3))
        limits = np.empty(count, np.float32)
        kernels.run(module.corner_probe_rays, blockers.threads, *arguments, corner, receiving,
                    *_ray_constants(blockers), aimed, origins, directions, limits)
        local = np.flatnonzero(aimed)
        if len(local):
            yield local, blockers.occluded(origins[local], directions[local], limits[local])


def trace_shadow_rays(blockers, samples: SampleSet, part, rays: np.ndarray,
                      sample_rows: np.ndarray | None = None) -> np.ndarray:
    """(len(rays),) bool: whether the shadow rays of rows ``rays`` of one sampler point
    (a :class:`core.lights.lamps.LightContribution`) are blocked in ``blockers`` (a
    RayScene). ``sample_rows``: those rows' samples, where the point was evaluated for a
    subset of the samples (default: the same indices). A point moved within its footprint
    starts from its own origin; one on a smooth face towards a light near or below the flat
    face's horizon starts lifted towards the smooth surface (core.sampling.terminator)."""
    return blockers.occluded(*shadow_rays(blockers, samples, part, rays, sample_rows))


def shadow_rays(blockers, samples: SampleSet, part, rays: np.ndarray, sample_rows: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays :func:`trace_shadow_rays` traces: origins (n, 3) (as ``blockers.ray_origins``
    gives them), unit directions (n, 3) float64 and lengths (n,) float32 (inf: unbounded).
    One compiled pass (core.kernels.light_kernels.shadow_ray_setup) where the kernels load,
    bitwise what the numpy code below makes: some ten numpy passes over the rays, which took
    most of the direct light's time (docs/benchmarks.md, "Speed, part 12")."""
    sample_rows = rays if sample_rows is None else sample_rows
    module = kernels.compiled()
    if module is not None:
        return _shadow_rays_compiled(module, blockers, samples, part, rays, sample_rows)
    distance = part.distance[rays]
    limit = np.where(np.isfinite(distance), distance * (1.0 - tol.SHADOW_RAY_SHORTEN), np.inf)
    to_light = part.to_light[rays]
    lift = None
    if samples.terminator is not None:
        amount = lift_amount(np.einsum("kd,kd->k", samples.normal[sample_rows], to_light),
                             np.einsum("kd,kd->k", samples.geometric[sample_rows], to_light),
                             samples.terminator_cutoff[sample_rows])
        lift = samples.terminator[sample_rows] * amount[:, None]
        if not np.any(lift):
            lift = None
    if part.position is None and lift is None:
        origins = samples.origins[sample_rows]
    else:
        start = samples.position[sample_rows] if part.position is None else part.position[rays]
        origins = blockers.ray_origins(start if lift is None else start + lift, samples.geometric[sample_rows])
    return origins, to_light, limit.astype(np.float32)


def _shadow_rays_compiled(module, blockers, samples: SampleSet, part, rays: np.ndarray, sample_rows: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`shadow_rays` through the compiled kernel (arguments as there)."""
    count = len(rays)
    smooth = samples.terminator is not None
    origins = np.empty((count, 3), samples.origins.dtype)
    directions = np.empty((count, 3))
    limits = np.empty(count, np.float32)
    centre = np.asarray(blockers.centre, np.float64)
    kernels.run(module.shadow_ray_setup, blockers.threads, np.asarray(rays, np.int64),
                np.asarray(sample_rows, np.int64), np.ascontiguousarray(part.distance, np.float64),
                np.ascontiguousarray(part.to_light, np.float64),
                _NOWHERE if part.position is None else np.ascontiguousarray(part.position, np.float64),
                np.ascontiguousarray(samples.position, np.float64), np.ascontiguousarray(samples.normal, np.float64),
                np.ascontiguousarray(samples.geometric, np.float64),
                np.ascontiguousarray(samples.terminator, np.float64) if smooth else _NOWHERE,
                np.ascontiguousarray(samples.terminator_cutoff, np.float64) if smooth else _NO_CUTOFF,
                np.ascontiguousarray(samples.origins), centre, bool(centre.any()), 1.0 - tol.SHADOW_RAY_SHORTEN,
                np.float32(tol.RAY_OFFSET_INT_SCALE), np.float32(tol.RAY_OFFSET_FLOAT_SCALE),
                np.float32(tol.RAY_OFFSET_ORIGIN), origins, directions, limits,
                np.empty((count if smooth else 0, 3)))
    return origins, directions, limits


# Stand-ins for the kernel's arrays where there are none (one signature for all calls).
_NOWHERE = np.zeros((0, 3))
_NO_CUTOFF = np.zeros(0)


def trace_shadow_rays_together(blockers, samples: SampleSet, requests: list) -> list[np.ndarray]:
    """:func:`trace_shadow_rays` of each request (part, rays, sample_rows), the rays of
    several requests traced in one query (up to SHADOW_BATCH_RAYS at a time): each query
    starts a pool of threads and slices its arrays, which cost more than embree's work
    where a request has a few hundred rays (a shadow edge's 64 points each trace only the
    texels the edge crosses). A ray's answer does not depend on the rays beside it, so the
    answers are those of one query per request. Returns (len(rays),) bool per request."""
    return [blocked for _, blocked in trace_shadow_rays_streamed(blockers, samples, requests)]


def trace_shadow_rays_streamed(blockers, samples: SampleSet, requests) -> Iterator[tuple[tuple, np.ndarray]]:
    """:func:`trace_shadow_rays_together` of an iterable of requests, taken one at a time:
    yields (request, (len(rays),) bool) in their order as each batch is traced, so a request
    and its rays are let go once answered, not all kept until the last is made."""
    batch: list[tuple] = []
    taken: list[tuple] = []
    queued = 0

    def trace_batch():
        if len(batch) == 1:
            answers = [blockers.occluded(*batch[0])]
        elif batch:
            blocked = blockers.occluded(*(np.concatenate([rays[i] for rays in batch]) for i in range(3)))
            answers = np.split(blocked, np.cumsum([len(rays[0]) for rays in batch])[:-1])
        else:
            answers = []
        done = list(zip(taken, answers))
        batch.clear()
        taken.clear()
        return done

    for request in requests:
        part, rays, sample_rows = request
        if queued and queued + len(rays) > SHADOW_BATCH_RAYS:
            yield from trace_batch()
            queued = 0
        batch.append(shadow_rays(blockers, samples, part, rays, sample_rows))
        taken.append(request)
        queued += len(rays)
    yield from trace_batch()


# The most shadow rays :func:`trace_shadow_rays_together` traces in one query (about 14 MB
# of rays), and the most sample rows whose sampler points a shadow edge evaluates at once
# (about 5 MB of sampler points).
SHADOW_BATCH_RAYS = 1 << 18
EDGE_BATCH_ROWS = 1 << 16


# A soft lamp with at least this many points probes for penumbrae first (_penumbra_probes),
# and so does any lamp over a footprint of at least this many points.
ADAPTIVE_MIN_POINTS = 16
# The corners of a texel's box, whose view of the lamp's centre is probed.
FOOTPRINT_PROBES = 4
# Seen under a larger angular radius (radians) than this a lamp is wide: occluders narrower
# than it are common (a 4 cm slat 4 m away is as wide as 0.57 degrees), and its probes add its
# first WIDE_LAMP_CHECK_POINTS points (_penumbra_probes). Blender's default sun (0.26 degrees)
# is not wide.
WIDE_LAMP_RADIUS = 0.01
WIDE_LAMP_CHECK_POINTS = 16
# Footprint points of a texel that a shadow edge crosses (its probes disagree). 16 points
# leave a few percent of noise on such texels; 64 cut the error on the sun patch's edges of
# benchmarks/scenes.py interior_opening by 3x, at 64 shadow rays for the few texels an edge crosses.
EDGE_FOOTPRINT_POINTS = 64
# Footprint points of a texel that a spot's cone edge crosses (spot_edge_samples): its brightest
# texels, where the footprint is all of the error. On test_estimate's spot over a floor, the
# edge texels' light was 25% of the room's mean off at 64 points and 6% at 256 (3% at 1024), the
# estimate 25%, 7% and 3%. Choosing 256 only where 64 points' halves disagreed left 16%, and
# estimated 9%: on a step, the halves of a stratified set can agree and both be wrong.
SPOT_EDGE_POINTS = 256
# Points of a soft lamp that every sample evaluates: outside penumbrae, where the lamp is
# small (SMALL_LAMP_VARIATION), they stand for all of them.
SMALL_LAMP_POINTS = 4
# Where a lamp's unshadowed irradiance varies this little across it (see
# unshadowed_variation), four stratified points give within about 0.3% (1% at most) of
# what 64 give, measured for suns, spheres and area lamps.
SMALL_LAMP_VARIATION = 0.1
# Where a lamp's unshadowed irradiance changes this little across a texel's footprint (see
# footprint_variation), its first four points stand for all sixteen: the variation is near
# linear there and each point stands for a quarter of the box, so they scatter by about 0.5% of
# the light and 3% at most (at 0.3, by up to 7%: tests/core/test_direct_sampler.py).
SMALL_FOOTPRINT_VARIATION = 0.1


def unshadowed_variation(light, samples: SampleSet) -> np.ndarray:
    """(K,) float64: about how much (relative) a lamp's unshadowed irradiance changes across
    the lamp at each sample: its angular radius alpha times (1 + tan of the incidence angle),
    from the cosine's slope and the distance's; inf where the lamp is at or below the horizon."""
    alpha = angular_radius(light, samples.position)
    if light.kind == "SUN":
        towards = np.broadcast_to(-np.asarray(light.direction, np.float64), samples.normal.shape)
    else:
        towards = np.asarray(light.position, np.float64) - samples.position
        towards = towards / np.maximum(np.linalg.norm(towards, axis=1), 1e-300)[:, None]
    cosine = np.einsum("kd,kd->k", samples.normal, towards)
    lit = cosine > 0
    tangent = np.sqrt(np.clip(1.0 - cosine * cosine, 0.0, None)) / np.where(lit, cosine, 1.0)
    return np.where(lit, alpha * (1.0 + tangent), np.inf)


def footprint_variation(light, samples: SampleSet) -> np.ndarray:
    """(K,) float64: about how much (relative) a lamp's unshadowed irradiance changes across each
    sample's footprint: 4 h / d for a footprint of half-diagonal h at distance d from the lamp
    (over the box, about 1.4 h: twice that through 1 / d^2 and once through the cosine, whose
    relative change across a flat footprint is at most the distance's); 0 for a sun, and where
    the samples have no footprint. A lamp 20 cm from a 10 cm texel changes by half and more
    across it, which four points of sixteen left 20% off Cycles (a column's top beside a point
    lamp, issue 52)."""
    if light.kind == "SUN" or samples.footprint_corners is None:
        return np.zeros(len(samples.position))
    half_diagonal = np.linalg.norm(samples.footprint_corners.astype(np.float64), axis=2).max(axis=1)
    distance = np.linalg.norm(samples.position - np.asarray(light.position, np.float64), axis=1)
    return 4.0 * half_diagonal / np.maximum(distance, 1e-300)


# An exact shadow ray costs about as much as this many table lookups of a gather
# (embree ~5 M rays/s, the numpy gather ~15 M lookups/s on 2 cores).
SHADOW_RAY_IN_LOOKUPS = 3.0


# For estimates only: the share of samples in a soft lamp's penumbrae, which trace every point.
TYPICAL_PENUMBRA_SHARE = 0.1


def shadow_rays_per_sample(light, settings) -> float:
    """About how many shadow rays a lamp (a core.scene.Light) traces per sample with exact
    shadows (``settings``: anything with ``area_light_samples``, such as BakeSettings or a
    Shadowing): its points, or for a soft lamp that probes, the probes plus its points in
    the typical share of penumbra samples. For progress and time-left estimates."""
    footprint = getattr(settings, "footprint_samples", 1)
    points = max(lamp_points(light, settings.area_light_samples), footprint)
    if points < ADAPTIVE_MIN_POINTS:
        return float(points)
    if lamp_points(light, settings.area_light_samples) == 1 and light.kind != "AREA":
        probes = 0  # a lamp without extent is probed from the footprint only
    else:
        probes = 5 if light.kind == "AREA" and light.area_shape not in ("DISK", "ELLIPSE") else 9
    if footprint > 1:
        probes += FOOTPRINT_PROBES
    return probes + TYPICAL_PENUMBRA_SHARE * points
