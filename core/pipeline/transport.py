"""Carrying a prepared scene's light groups through a transport backend: direct light
(lamps, then directly sampled emitters), then the emitted and world light and every
bounce in shared gathers, all groups side by side in one radiance atlas."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from ..distributed.split import SplitTable
from ..lights.emitters import (
    emissive_triangles,
    emitter_irradiance,
    find_emitters,
    near_triangles,
    sampled_directly,
    triangle_irradiance,
)
from ..lights.lamps import lamp_scale, lamp_shape_key, unit_lamp
from ..transport.contacts import (
    CONTACT_AREA_LIGHT_SAMPLES,
    ShortHits,
    contact_correction,
    texel_sizes,
    world_contact_correction,
)
from ..transport.contract import GatherSource, TransportBackend
from ..transport.direct import SHADOW_RAY_IN_LOOKUPS, shadow_rays_per_sample
from ..transport.groups import MAX_GROUPS_PER_GATHER, LightGroup, Transported
from ..transport.interleave import near_light, reconstruct_interleaved
from ..visibility.cache import arrays_key
from .prepare import Prepared
from .progress import Stages

# A kept preparation transports each lamp on its own (transport_lamp_parts) when the parts
# are at most this many: 3 channels a part, and a gather of 12 channels costs about 1.45x
# one of 3 on the demo (9: 1.34x), which the first relight that changes a power repays.
MAX_LAMP_PARTS = 4


def _direct_share(p, lamp_rays: float, emitter_rays: float) -> float:
    """The direct light's share of a transport's time, from its shadow rays and the
    gathers' lookups: the progress bar then moves at an even pace through both."""
    lamp_cost = lamp_rays * (SHADOW_RAY_IN_LOOKUPS if p.settings.shadows == "exact" else 0.2)
    shadow = lamp_cost + emitter_rays * SHADOW_RAY_IN_LOOKUPS
    lookups = (len(p.directions) * len(p.position) / 2 if p.table is not None else 0.0) * (p.bounces_needed() + 1)
    if shadow + lookups <= 0:
        return 0.5
    return float(np.clip(shadow / (shadow + lookups), 0.02, 0.98))


def transport_groups(p: Prepared, backend: TransportBackend, groups: list[LightGroup], stages: Stages,
                     skipped: list, dilate, share=(0.0, 1.0), last_direct: bool = False
                     ) -> tuple[list[Transported], int]:
    """Direct light of every group, then all groups' gathers at once, on ``backend``.

    ``stages`` times the direct part as "direct" inside the running stage; ``dilate``
    is the (timed) dilation radiance atlases are made with; ``share`` is this call's
    slice of the stage's progress bar. ``last_direct``: no direct light of this preparation
    follows, so what only direct light reads is let go before the gathers
    (Prepared.drop_direct_inputs). Returns the groups' irradiance and the gathers run.
    """
    low, high = share

    def report(fraction):
        stages.report(low + (high - low) * fraction)

    direct_started = time.perf_counter()
    count = len(groups)
    emitting_any = np.zeros(len(p.meshes), bool)
    for group in groups:
        emitting_any |= group.emitting

    # Small emitters are integrated directly where the fixed directions would alias,
    # and left out of the gather there. Whether a sample samples an emitter depends on
    # the emitter alone, so one exclusion mask serves every group: an emitter's light
    # is only in its own group's atlas.
    exclude = None
    sampled = []  # (owning group, emitter, samples that sample it directly)
    if bool(np.any(emitting_any)) and bool(np.any(p.emission > 0)):
        for emitter in find_emitters(p.meshes, p.settings.emitter_samples):
            owner = next((i for i, g in enumerate(groups) if g.emitting[emitter.object_index]), None)
            if owner is None:
                continue
            direct = sampled_directly(emitter, p.position, p.settings.directions)
            if not np.any(direct):
                continue
            if exclude is None:
                exclude = np.zeros((len(p.position), len(p.meshes)), bool)
            exclude[:, emitter.object_index] = direct
            sampled.append((owner, emitter, np.nonzero(direct)[0]))

    lamp_rays = len(p.position) * sum(shadow_rays_per_sample(light, p.settings)
                                      for group in groups for light in group.lights)
    emitter_rays = sum(len(chosen) for _, _, chosen in sampled) * p.settings.emitter_samples
    direct_share = _direct_share(p, lamp_rays, emitter_rays)
    lamp_share = direct_share * lamp_rays / max(lamp_rays + emitter_rays, 1)
    results = []
    reused = set()  # names of lamps and emitters whose light was kept from an earlier relight
    for index, group in enumerate(groups):
        variance = np.zeros((len(p.position), 3))
        irradiance, rays = lamp_light(p, backend, "samples", p.sample_set(), group.lights, reused,
                                      lambda f, i=index: report(lamp_share * (i + f) / count), variance)
        # The gathered light is set once the gathers are done (a (K, 3) array kept until then).
        results.append(Transported(irradiance, None, shadow_rays=rays, direct_variance=variance))
    contacts = _contact_light(p, backend, groups, results, stages, skipped, reused, last_direct)
    # (K, 3 * count) float64: what each sample reflects of a unit of light, per group.
    reflectance = np.tile(p.albedo, count) / np.pi
    # Every gather looks the lamps' direct light up again (bounce b gathers direct plus b - 1
    # bounces), so every one gets the same correction of its short hits. It reads no gathered
    # light, so it is made before the gathers and the short hits go before the first one.
    correction = None if contacts is None else _contacts_corrected(p, contacts, reflectance, dilate, last_direct)
    emitter_contacts = None if contacts is None else contacts.emitters
    world_contacts = None if contacts is None or contacts.openness is None else contacts
    del contacts
    if last_direct:
        p.drop_direct_inputs()  # the emitters' light below reads neither footprints nor short hits
    for number, (owner, emitter, chosen) in enumerate(sampled):
        name = p.meshes[emitter.object_index].name
        key = ("emitter", emitter.object_index)
        kept = p.light_memo.get(key)
        if kept is None:
            irradiance, rays = emitter_irradiance(emitter, p.position[chosen], p.normal[chosen],
                                                  p.geometric[chosen], p.origins[chosen], p.ray_scene)
            p.light_memo.put(key, irradiance)
        else:
            irradiance, rays = kept, 0
            reused.add(name)
        results[owner].direct[chosen] += irradiance
        del irradiance
        results[owner].emitter_rays += rays
        results[owner].emitters_sampled += (name,)
        report(lamp_share + (direct_share - lamp_share) * (number + 1) / len(sampled))
    if reused:
        skipped.append(f"direct light of {', '.join(sorted(reused))}: only power or colour changed since an "
                       "earlier relight of this preparation; its kept light was scaled, no shadow ray traced")
    stages.book("direct", time.perf_counter() - direct_started)
    stages.record_pass(f"direct light ({count} groups)", backend.name, time.perf_counter() - direct_started)
    if last_direct:
        # No later relight of this preparation: what the memo kept of its direct light is never read again.
        p.light_memo.clear()

    per_sample_emitting = np.stack([np.repeat(g.emitting, np.diff(p.sample_offset)) for g in groups])
    emissions = [np.where(per_sample_emitting[i][:, None], p.emission, 0.0) for i in range(count)]
    worlds = [g.world for g in groups]
    gathers_emission = any(np.any(e > 0) for e in emissions) or any(np.any(w > 0) for w in worlds)
    bounces = p.bounces_needed()
    if not (bounces > 0 or gathers_emission):
        for result in results:
            result.gathered = np.zeros_like(result.direct)
            result.gathered_variance = np.zeros_like(result.direct)
        return results, 0
    geometry = p.gather_geometry()
    # Only objects with outputs need the last gather's result; the others' radiance
    # would only feed a bounce that is never gathered.
    outputs = p.output_samples()
    steps = bounces + 1

    def step_progress(step):
        return lambda fraction: report(direct_share + (1.0 - direct_share) * (step + fraction) / steps)

    def wide(arrays):  # one group's array as it is (no copy: nothing writes into it)
        return arrays[0] if len(arrays) == 1 else np.concatenate(arrays, axis=1)

    def narrow(array):
        return [array[:, 3 * i:3 * i + 3] for i in range(count)]

    gathers = 0
    def timed_gather(name, source, progress, samples):
        started = time.perf_counter()
        result = backend.gather(geometry, source, progress, samples=samples)
        stages.record_pass(f"{name} ({3 * count} channels)", backend.name, time.perf_counter() - started)
        return result

    if gathers_emission:
        # Emission is fixed with the preparation's materials: only the groups' emitters and worlds vary.
        key = ("emitted", backend.name, arrays_key(np.stack([g.emitting for g in groups]),
                                                   *[np.asarray(w, np.float64) for w in worlds]))
        kept = p.light_memo.get(key)
        if kept is None:
            emitting_atlas = p.to_atlas(wide(emissions), dilate)
            emitted = _gather_emission(p, timed_gather, emitting_atlas, np.concatenate(worlds, axis=-1), exclude,
                                       step_progress(0), outputs if bounces == 0 else None)
            spread = []
            hits = p.emitter_near_hits()
            emitted = reconstruct_interleaved(p, emitted, near_light(p, hits, emitting_atlas, exclude),
                                              scratch=True, spread=spread, hits=hits)
            del emitting_atlas
            np.maximum(emitted, 0.0, out=emitted)  # the filter's subtraction may leave -1e-10
            emitted_variance = np.square(spread[0])
            if not last_direct:
                p.light_memo.put(key, (emitted, emitted_variance))
            gathers += 1
        else:
            emitted, emitted_variance = kept
            skipped.append("gather of emitted and world light: emitters and world unchanged since an earlier "
                           "relight of this preparation; its result was kept")
        for result, part, part_variance in zip(results, narrow(emitted), narrow(emitted_variance)):
            result.direct += part
            # The world's and emitters' light comes through the table: its error is the gathers' kind
            # (it falls with more directions), not the lamps'.
            result.gathered_variance = part_variance
        del emitted, emitted_variance
    del emissions
    if emitter_contacts is not None:
        # The emitters' light is known now (sampled directly and gathered): correct the short hits
        # near an emitter by its exact light at their landing points, as the lamps' above.
        near_correction = _emitter_contacts_corrected(p, emitter_contacts, results, groups, reflectance, dilate)
        correction = near_correction if correction is None else correction + near_correction
        del emitter_contacts, near_correction
    if world_contacts is not None:
        # So is the world's: the short hits reflect it as open as the sky is at their landing points.
        sky_correction = _world_contacts_corrected(p, world_contacts, results, groups, reflectance, dilate)
        correction = sky_correction if correction is None else correction + sky_correction
        del world_contacts, sky_correction
    gathered = np.zeros((len(p.position), 3 * count))
    direct = wide([r.direct for r in results])
    shares = BounceShares(p.settings.target_error, direct, outputs)
    for bounce in range(1, bounces + 1):
        # In place, each (K, 3 * count) array made once: at the demo's 403k texels each one is
        # 9 MiB, and the gathers are where a bake holds the most beside its table.
        if bounce > 1 and shares.remaining_below_target(gathered):
            skipped.append(f"bounce {bounce} and later: {shares.describe(bounce)}")
            break
        reflected = direct + gathered
        if not np.any(reflected > 0):
            skipped.append(f"bounce {bounce} and later: no light left to reflect")
            break
        del gathered
        # Rays land only on what is not buried under other geometry (core.transport.contacts).
        reflected_atlas = p.lookup_atlas(np.multiply(reflectance, reflected, out=reflected), dilate)
        del reflected
        gathered = timed_gather(f"gather of bounce {bounce}", GatherSource(reflected_atlas, np.zeros(3 * count)),
                                step_progress(bounce), outputs if bounce == bounces else None)
        gathers += 1
        if correction is not None:
            gathered += correction
    del direct, reflectance
    gathered_variance = np.zeros_like(gathered)
    if bounces and p.rotations is not None and np.any(gathered):
        # The last gather's near part (its near entries' lookups, and the contacts' correction) stays sharp.
        near = near_light(p, p.near_hits(), reflected_atlas)
        if correction is not None:
            near += correction
        del correction
        spread = []
        gathered = reconstruct_interleaved(p, gathered, near, scratch=True, spread=spread)
        gathered_variance = np.square(spread[0])
    elif bounces and p.rotations is None:
        gathered_variance[:] = np.nan  # without interleaving, the gathered light's error has no estimate
    # A contact correction takes light away where a lookup overestimated it; rounding there
    # (and in the filter's subtraction) must never leave negative light.
    np.maximum(gathered, 0.0, out=gathered)
    for result, part, part_variance in zip(results, narrow(gathered), narrow(gathered_variance)):
        result.gathered = part
        result.gathered_variance = (part_variance if result.gathered_variance is None
                                    else result.gathered_variance + part_variance)
    return results, gathers


# At a Target Error, the bounces not gathered may take away at most this share of the target, as
# a share of the mean light. A bias adds to the estimate's noise in quadrature: with the
# estimate aiming at 0.85 of the target (core.pipeline.target.AIM), the two stay within 0.94 of it.
BOUNCE_SHARE_OF_TARGET = 0.4


class BounceShares:
    """At a Target Error (BakeSettings.target_error), whether the bounces left would add less
    than BOUNCE_SHARE_OF_TARGET of the target to the mean light: each bounce's light is the one
    before it times about the same ratio (the scene's mean reflectance, as the light sees it), so
    after a bounce that added a share s of the light at ratio q the rest add s q / (1 - q).

    ``direct`` (K, C) the light the bounces reflect first; ``outputs`` (k,) int64 the samples
    with outputs (None: all), the only ones the means are taken over. Off (never below) without
    a target."""

    def __init__(self, target: float, direct: np.ndarray, outputs: np.ndarray | None):
        self.target, self.outputs = target, outputs
        self.direct_mean = self._mean(direct) if target > 0 else 0.0
        self.added = []  # the mean light each bounce added
        self.previous = 0.0

    def _mean(self, values: np.ndarray) -> float:
        return float(np.mean(values if self.outputs is None else values[self.outputs]))

    def remaining_below_target(self, gathered: np.ndarray) -> bool:
        """Whether the bounces after those in ``gathered`` (K, C: the light of every bounce so
        far) may be left out."""
        if self.target <= 0:
            return False
        total = self._mean(gathered)
        self.added.append(total - self.previous)
        self.previous = total
        if len(self.added) < 2 or self.added[-2] <= 0 or self.direct_mean + total <= 0:
            return False
        ratio = self.added[-1] / self.added[-2]
        if not 0.0 <= ratio < 1.0:
            return False
        self.rest = self.added[-1] * ratio / (1.0 - ratio) / (self.direct_mean + total)
        return self.rest < BOUNCE_SHARE_OF_TARGET * self.target

    def describe(self, bounce: int) -> str:
        return (f"they would add about {self.rest:.2%} of the light, below the Target Error's "
                f"{BOUNCE_SHARE_OF_TARGET * self.target:.2%} for them (bounce {bounce - 1} added "
                f"{self.added[-1] / (self.direct_mean + self.previous):.2%})")


def _gather_emission(p: Prepared, timed_gather, atlas: np.ndarray, world: np.ndarray, exclude, progress, samples):
    """The gather of emitted and world light. A world seen per interleaved rotation (G, N, C)
    is gathered once per rotation, over that rotation's samples."""
    name = "gather of emitted and world light"
    if world.ndim < 3 or not np.any(world):
        return timed_gather(name, GatherSource(atlas, world[0] if world.ndim == 3 else world, exclude), progress,
                            samples)
    total = np.zeros((len(p.position), atlas.shape[1]))
    wanted = np.ones(len(p.position), bool) if samples is None else np.isin(np.arange(len(p.position)), samples)
    for rotation in range(len(world)):
        chosen = np.nonzero(wanted & (p.group == rotation))[0]
        if len(chosen):
            total += timed_gather(f"{name}, rotation {rotation}", GatherSource(atlas, world[rotation], exclude),
                                  lambda f, r=rotation: progress((r + f) / len(world)), chosen)
    return total


def lamp_light(p: Prepared, backend: TransportBackend, where: str, samples, lights, reused: set,
               report=None, variance: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """(K, 3) float64 direct light of ``lights`` at ``samples`` (a SampleSet, ``where`` naming
    which of the preparation's: "samples" or "short hits"), and the shadow rays traced.
    ``variance`` (K, 3) float64: the light's squared standard error is added to it (NaN where
    the lamps' pass has none: a table held by sample rows).

    Each lamp's light is its unit lamp's (core.lights.lamps.unit_lamp) times its power and
    colour. The unit light is kept in the preparation's memo, so a later relight in which a
    lamp changed only power or colour takes it from there (and adds the lamp's name to
    ``reused``). A first bake computes it the same way, so both give bitwise the same light.
    """
    total = np.zeros((len(samples.position), 3))
    rays = 0
    for number, light in enumerate(lights):
        key = ("lamp", backend.name, where, lamp_shape_key(light))
        kept = p.light_memo.get(key)
        if kept is None:
            part = None if report is None else (lambda f, n=number: report((n + f) / len(lights)))
            spread = [] if variance is not None else None
            if where == "samples" and isinstance(p.table, SplitTable):
                # A table held by row ranges: the samples' direct light runs where they are.
                irradiance, traced = p.table.lamp_irradiance([unit_lamp(light)], part)
                if spread is not None:
                    spread.append(np.full((len(samples.position), 3), np.nan))
            else:
                irradiance, traced = backend.lamp_irradiance(samples, _shadowing_at(p, where), [unit_lamp(light)],
                                                             part, spread)
            unit = np.ascontiguousarray(irradiance[:, 0], dtype=np.float64)
            del irradiance  # (K, 3): not held while the next lamp's is made
            # The unit lamp is white: one channel's spread is each one's.
            unit_spread = None if spread is None else np.ascontiguousarray(spread[0][:, 0], dtype=np.float64)
            rays += traced
            p.light_memo.put(key, (unit, unit_spread))
        else:
            unit, unit_spread = kept
            reused.add(light.name)
        total += unit[:, None] * lamp_scale(light)
        if variance is not None:
            if unit_spread is None:  # kept by a relight that asked for no estimate
                variance[:] = np.nan
            else:
                variance += np.square(unit_spread)[:, None] * np.square(lamp_scale(light))
        if report is not None:
            report((number + 1) / len(lights))
    return total, rays


def _shadowing_at(p: Prepared, where: str):
    """The preparation's Shadowing for the samples (``where`` "samples"), or for the short hits:
    lamps with an extent integrated with CONTACT_AREA_LIGHT_SAMPLES per side at most."""
    shadowing = p.shadowing()
    if where == "short hits" and shadowing.area_light_samples > CONTACT_AREA_LIGHT_SAMPLES:
        # A copy that shares the preparation's blocker scenes and fractions.
        return replace(shadowing, area_light_samples=CONTACT_AREA_LIGHT_SAMPLES)
    return shadowing


def _contact_light(p: Prepared, backend: TransportBackend, groups: list[LightGroup], results: list[Transported],
                   stages: Stages, skipped: list, reused: set, last_direct: bool = False):
    """The lamps' direct light where short rays land (core.transport.contacts), per group, for
    every bounce's correction: (short hits, (K, 3G) the samples' lamp light, (m, 3G) the
    hits' lamp light), or None when the bake needs none (say why in ``skipped``). The pass
    record names the short hits; their shadow rays count with each group's. ``last_direct``
    (transport_groups): the footprints go once the short hits are found, and the short hits
    come back without their landing points."""
    if not p.settings.sharp_contacts or p.bounces_needed() == 0 or p.table is None:
        return None
    emitting_any = np.zeros(len(p.meshes), bool)
    for group in groups:
        emitting_any |= group.emitting
    triangles = emissive_triangles([mesh for mesh, emitting in zip(p.meshes, emitting_any) if emitting])
    # Back to the bake's mesh indices.
    triangles.object_index = np.nonzero(emitting_any)[0][triangles.object_index]
    # The world's light at the landings: groups lit by the world and no emitter (whose gather
    # would mix the emitters' light into the world's).
    sky_groups = [bool(np.any(np.asarray(g.world) > 0)) and not bool(np.any(g.emitting)) for g in groups]
    if not any(group.lights for group in groups) and not len(triangles) and not any(sky_groups):
        return None
    if p.settings.shadows != "exact":
        skipped.append("sharp contacts: shadow fractions have no shadow to evaluate where short rays land")
        return None
    started = time.perf_counter()
    if last_direct:
        p.drop_footprint_shading()
    short = p.short_hits()
    if last_direct:
        p.drop_footprints()
    if short is None:
        skipped.append("sharp contacts: no ray of the table lands within two texels of its target")
        return None
    at_hits = None
    if any(group.lights for group in groups):
        at_hits = []
        for group, result in zip(groups, results):
            irradiance, rays = lamp_light(p, backend, "short hits", short.points, group.lights, reused)
            at_hits.append(irradiance)
            result.shadow_rays += rays
        at_hits = at_hits[0] if len(at_hits) == 1 else np.concatenate(at_hits, axis=1)
    emitters = _emitter_contact_light(p, short, groups, triangles)
    openness = p.landing_openness() if any(sky_groups) else None
    stages.record_pass(f"direct light at {len(short)} short hits", backend.name, time.perf_counter() - started)
    if last_direct:
        short = replace(short, points=None)
    # A copy: the emitters' and the emitted light are added to the groups' direct light later.
    return ContactLight(short, np.concatenate([r.direct for r in results], axis=1), at_hits, emitters, openness,
                        sky_groups)


# Short hits within this many of their target's texels of an emissive mesh's bounding box take
# that mesh's exact light at their landing point (beyond, its light changes slowly over a texel).
EMITTER_CONTACT_TEXELS = 1.0
# Cells across a texel in which the landings near an emitter share one evaluation of its light.
EMITTER_CONTACT_CELLS = 8


@dataclass
class ContactLight:
    """What the contacts' corrections read (:func:`_contact_light`): the short hits, (K, 3G) the
    samples' lamp light, (m, 3G) the lamps' light at the hits (None without lamps), the
    emitters' (:class:`EmitterContacts`, None where no hit lands near an emitter) and the sky's
    openness at the hits."""

    short: ShortHits
    lamp_direct: np.ndarray
    at_hits: np.ndarray | None
    emitters: "EmitterContacts | None"
    # (m,) how open the sky is at each landing (core.transport.contacts.landing_openness), and
    # per group whether its world light is corrected there; None where no group is lit by a world alone.
    openness: np.ndarray | None = None
    sky_groups: list | None = None


@dataclass
class EmitterContacts:
    """The short hits that land near an emissive mesh (their landing points let go) and each
    group's emitters' exact irradiance there, (n, 3G) float64 (:func:`_emitter_contact_light`);
    ``lamp_direct`` (K, 3G) the samples' lamp light, which the emitters' correction leaves out."""

    short: ShortHits
    at_hits: np.ndarray
    lamp_direct: np.ndarray | None = None


def _emitter_contact_light(p, short: ShortHits, groups: list[LightGroup], triangles) -> EmitterContacts | None:
    """The emissive meshes' light at the short hits that land within EMITTER_CONTACT_TEXELS of
    their target's texels of one (core.lights.emitters.triangle_irradiance, per group its own
    emitters), or None where none does. A group lit by the world as well is left out (zero
    columns and no correction): its gather mixes the world's light into the emitters'."""
    if not len(triangles):
        return None
    reach = EMITTER_CONTACT_TEXELS * texel_sizes(p.meshes, p.object_samples)[short.obj]
    # A landing on an emitter keeps the lookup: an emitter does not light itself, and rays from
    # all around a glowing object land on it (most of the demo's landings near its ball).
    on_emitter = np.zeros(len(p.meshes), bool)
    on_emitter[triangles.object_index] = True
    near = np.nonzero(~on_emitter[short.obj] & near_triangles(triangles, short.points.position, reach))[0]
    if not len(near):
        return None
    # One landing per cell of EMITTER_CONTACT_CELLS^2 per texel (and side) is evaluated, and every
    # landing in the cell takes its light: hundreds of rays of a texel land in each texel nearby
    # (195,000 landings by the demo's glowing ball, 12 s per 20,000 of them one by one).
    across = EMITTER_CONTACT_CELLS * np.array([[s.width, s.height] for s in p.object_samples], np.int64)
    cells = across[:, 0] * across[:, 1] * 8  # 8: the sides a landing's normal faces, one bit an axis
    base = np.cumsum(cells) - cells
    obj = short.obj[near]
    cell = np.clip(np.floor(short.uv[near] * across[obj]).astype(np.int64), 0, across[obj] - 1)
    side = (short.points.normal[near] > 0) @ np.array([1, 2, 4])
    key = base[obj] + (cell[:, 1] * across[obj, 0] + cell[:, 0]) * 8 + side
    _, first, cell_of = np.unique(key, return_index=True, return_inverse=True)
    evaluated = near[first]
    at_hits = np.zeros((len(evaluated), 3 * len(groups)))
    for index, group in enumerate(groups):
        own = triangles.of_objects(group.emitting)
        if len(own) and not np.any(np.asarray(group.world) > 0):
            at_hits[:, 3 * index:3 * index + 3] = triangle_irradiance(
                own, short.points.position[evaluated], short.points.normal[evaluated],
                short.points.origins[evaluated], p.ray_scene)
    at_hits = at_hits[cell_of.ravel()]
    chosen = ShortHits(short.sample[near], short.weight[near], short.obj[near], short.uv[near], None)
    return EmitterContacts(chosen, at_hits)


def _contacts_corrected(p: Prepared, contacts, reflectance: np.ndarray, dilate, last_direct: bool) -> np.ndarray:
    """(K, 3G) float64: what every bounce's gather gains at the short hits of ``contacts``
    (:func:`_contact_light`'s triple) when they reflect the lamps' light at their landing points
    (core.transport.contacts.contact_correction); ``reflectance`` (K, 3G) is albedo / pi per group.
    The correction is all the gathers need of the short hits: with ``last_direct`` they go now."""
    short, lamp_direct, at_hits = contacts.short, contacts.lamp_direct, contacts.at_hits
    if contacts.emitters is not None:
        contacts.emitters.lamp_direct = lamp_direct
    correction = None
    if at_hits is not None:
        correction = contact_correction(short, p.layout, p.lookup_atlas(reflectance * lamp_direct, dilate),
                                        at_hits, p.to_atlas(p.albedo, dilate), len(p.position))
    if last_direct:
        p.drop_short_hits()
    return correction


def _emitter_contacts_corrected(p: Prepared, contacts: EmitterContacts, results: list[Transported],
                                groups: list[LightGroup], reflectance: np.ndarray, dilate) -> np.ndarray:
    """(K, 3G) float64: what every bounce's gather gains where the short hits near an emitter
    reflect its exact light at their landing points instead of what the gather looked up in the
    atlas of the emitters' light (every group's direct light but its lamps', once the emitted
    gather is added to it). Groups lit by the world as well look up nothing here (zero columns)."""
    emitted = np.concatenate([r.direct for r in results], axis=1) - contacts.lamp_direct
    for index, group in enumerate(groups):
        if np.any(np.asarray(group.world) > 0):
            emitted[:, 3 * index:3 * index + 3] = 0.0
    return contact_correction(contacts.short, p.layout, p.lookup_atlas(reflectance * emitted, dilate),
                              contacts.at_hits, p.to_atlas(p.albedo, dilate), len(p.position))


def _world_contacts_corrected(p: Prepared, contacts: ContactLight, results: list[Transported],
                              groups: list[LightGroup], reflectance: np.ndarray, dilate) -> np.ndarray:
    """(K, 3G) float64: what every bounce's gather gains where the short hits reflect the world's
    light as open as the sky is at their landing points, instead of their target texel's mean
    (core.transport.contacts.world_contact_correction). The world's light is each group's direct
    light but its lamps', once the emitted gather is added to it; groups with emitters, or
    without a world, look up nothing here (zero columns). A texel's openness is the table's
    (core.transport.gather.ambient_occlusion), looked up as its light is."""
    world = np.concatenate([r.direct for r in results], axis=1) - contacts.lamp_direct
    for index, corrected in enumerate(contacts.sky_groups):
        if not corrected:
            world[:, 3 * index:3 * index + 3] = 0.0
    return world_contact_correction(contacts.short, contacts.openness, p.layout,
                                    p.lookup_atlas(reflectance * world, dilate),
                                    p.lookup_atlas(p.openness()[:, None], dilate), len(p.position))


def transport_lamp_parts(p: Prepared, backend: TransportBackend, groups: list[LightGroup], stages: Stages,
                         skipped: list, dilate, share=(0.0, 1.0)) -> tuple[list[Transported], int] | None:
    """:func:`transport_groups` for a kept preparation, by parts that a later relight can reuse;
    None where the parts would be more than MAX_LAMP_PARTS (then transport the groups whole).

    Transport is linear in the emitted light, so a group's light is the sum of each lamp's
    unit transport (direct light and every bounce of core.lights.lamps.unit_lamp) times its
    power and colour, plus the transport of its emitters and world. Each part is kept in the
    preparation's memo (core.pipeline.light_memo) and only the parts not kept are transported:
    a relight that changes powers and colours gathers nothing. Returns the groups' light and
    the gathers run.
    """
    parts: dict = {}
    recipes = []  # per group: [(part key, (3,) scale or None for the emitters and world)]
    for group in groups:
        recipe = []
        for light in group.lights:
            key = ("part", backend.name, lamp_shape_key(light))
            parts.setdefault(key, (light.name, LightGroup(f"lamp {light.name}", [unit_lamp(light)],
                                                          np.zeros_like(group.world),
                                                          np.zeros_like(group.emitting))))
            recipe.append((key, lamp_scale(light)))
        if np.any(group.emitting) or np.any(np.asarray(group.world) > 0):
            key = ("part", backend.name, arrays_key(np.asarray(group.emitting), np.asarray(group.world, np.float64)))
            parts.setdefault(key, ("emitted and world light", LightGroup("emitted and world light", [], group.world,
                                                                         group.emitting)))
            recipe.append((key, None))
        recipes.append(recipe)
    if len(parts) > MAX_LAMP_PARTS:
        return None
    available = {key: p.light_memo.get(key) for key in parts}
    missing = [key for key, kept in available.items() if kept is None]
    reused = sorted(parts[key][0] for key in parts if key not in missing)
    if reused:
        skipped.append(f"transport of {', '.join(reused)}: only power or colour changed since an earlier relight "
                       "of this preparation; its kept light (direct and every bounce) was scaled")
    gathers = 0
    rays = {}
    if missing:
        results, gathers = transport_groups(p, backend, [parts[key][1] for key in missing], stages, skipped, dilate,
                                            share)
        for key, result in zip(missing, results):
            kept = (result.direct, result.gathered, result.emitters_sampled, result.direct_variance,
                    result.gathered_variance)
            p.light_memo.put(key, kept)
            available[key] = kept
            rays[key] = (result.shadow_rays, result.emitter_rays)
    transported = []
    for recipe in recipes:
        direct = np.zeros((len(p.position), 3))
        gathered = np.zeros((len(p.position), 3))
        # The parts' errors summed as independent ones (each lamp's light is its own bright patches).
        result = Transported(direct, gathered, direct_variance=np.zeros_like(direct),
                             gathered_variance=np.zeros_like(gathered))
        for key, scale in recipe:
            part_direct, part_gathered, emitters, direct_variance, gathered_variance = available[key]
            weight = np.ones(3) if scale is None else scale
            direct += part_direct * weight
            gathered += part_gathered * weight
            result.direct_variance += direct_variance * np.square(weight)
            result.gathered_variance += gathered_variance * np.square(weight)
            shadow, emitter = rays.pop(key, (0, 0))  # a part shared by two groups was traced once
            result.shadow_rays += shadow
            result.emitter_rays += emitter
            result.emitters_sampled += tuple(emitters)
        transported.append(result)
    return transported, gathers


def transport_pending(p: Prepared, backend: TransportBackend, groups: list[LightGroup], stages: Stages,
                      skipped: list, dilate) -> tuple[list[Transported], int]:
    """Every group's light: by lamp parts where the preparation is kept for relights and the
    parts are few (:func:`transport_lamp_parts`), else in batches of MAX_GROUPS_PER_GATHER
    groups gathered together (:func:`transport_groups`). Returns the groups' light and the gathers run."""
    if p.resident and groups:
        by_parts = transport_lamp_parts(p, backend, groups, stages, skipped, dilate)
        if by_parts is not None:
            return by_parts
    results, gathers = [], 0
    batches = [groups[i:i + MAX_GROUPS_PER_GATHER] for i in range(0, len(groups), MAX_GROUPS_PER_GATHER)]
    for number, batch in enumerate(batches):
        batch_results, count = transport_groups(p, backend, batch, stages, skipped, dilate,
                                                (number / len(batches), (number + 1) / len(batches)),
                                                last_direct=p.relit_once and number == len(batches) - 1)
        results += batch_results
        gathers += count
    return results, gathers
