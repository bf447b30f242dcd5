"""Preparation: samples, ray scene and the visibility table (traced, read from the
cache or updated for the objects that changed). Everything here depends on geometry
and settings alone, so a :class:`Prepared` serves every later relight."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace

import numpy as np

from .. import kernels
from ..errors import BakeRefused
from ..geometry import mesh_face_normals
from ..lights.environment import has_light
from ..sampling.samples import ObjectSamples, VertexSamples, build_samples, build_vertex_samples, dense_footprint
from ..scene import Scene
from ..settings import BakeSettings
from ..transport.contacts import MIN_EXPOSED_SHARE, exposed_share, find_short_hits, landing_openness, lookup_scale
from ..transport.contract import GatherGeometry, SampleSet, Shadowing
from ..transport.gather import AtlasLayout, ambient_occlusion, gather_normalisation, open_hemisphere_weight
from ..transport.groups import LightGroup, light_key_parts
from ..transport.interleave import filter_pairs, find_emitter_near_hits, find_near_hits
from ..visibility.cache import (
    CacheFull,
    CacheStatus,
    CorruptCache,
    VisibilityCache,
    arrays_key,
    object_key,
    table_key,
)
from ..visibility.directions import direction_set, interleaved_rotations
from ..visibility.rays import RayScene
from ..visibility.table import (
    MAX_VERTEX_TRIANGLES,
    DeferredTable,
    HitGeometry,
    TraceRequest,
    frame_vectors,
    table_from_arrays,
    trace_table,
    update_table,
)
from .budget import check_budget, release_free_heap
from .light_memo import LightMemo
from .progress import Stages

# Part of every lighting key: raised whenever the same table and lights give other light (a
# change of the transport's formulas), so that lighting cached by an older VisiBake is not
# reused. 2: the gathers' weights sum to pi (1 + n . n_g) / 2, not pi (speed part 18). 3: a soft
# lamp's points over a footprint are dimensions 2 and 3 of the sampler (issue 52), and cached
# lighting carries the bake's error estimate, and short rays reflect the world as open as the
# sky is at their landing points. 4: a rectangular area lamp's points near a receiver are
# uniform in its solid angle, its wholly lit texels take its closed form, and a wide lamp's
# probes include its first points (issue 52, part 3). 5: a lamp near a texel averages all its
# footprint points, a spot's cone edge takes a dense footprint, and the emitted light's near
# field reaches farther (issue 52, part 4).
TRANSPORT_REVISION = 5


@dataclass
class Prepared:
    """What a bake computes from geometry, materials and settings alone.

    Reused unchanged by every :func:`relight`: lights and world can change without
    tracing a single visibility ray again (the reason the method exists).
    """

    settings: BakeSettings
    meshes: list
    object_samples: list
    sample_offset: np.ndarray  # (objects + 1,) int64
    position: np.ndarray  # (K, 3) float64
    normal: np.ndarray  # (K, 3) float64 shading normals
    geometric: np.ndarray  # (K, 3) float64
    albedo: np.ndarray  # (K, 3) float64
    emission: np.ndarray  # (K, 3) float64
    layout: AtlasLayout
    directions: np.ndarray  # (N, 3) float64
    ray_scene: RayScene
    origins: np.ndarray  # (K, 3) float32, offset off the surface
    table: object  # VisibilityTable or None
    # ((K, P, 3) footprint points, (K, 4, 3) box corners, (K, P, 3) their normals or None)
    # float32 (ObjectSamples), or None
    footprint: tuple | None
    terminator: tuple | None  # ((K, 3) lifts, (K,) cutoffs) for smooth faces' shadow rays (SampleSet), or None
    rotations: np.ndarray | None  # (G, 3, 3) interleaved rotations of the direction set, or None (one set)
    group: np.ndarray | None  # (K,) int64 each sample's rotation, or None
    stage_seconds: dict
    skipped: list
    warnings: list
    table_key: str = ""  # the table's name in the cache; "" without a cache
    visibility_rays: int = 0  # rays this preparation traced for the table (0 on a cache hit)
    cache: VisibilityCache | None = None
    cache_status: CacheStatus | None = None
    _gather_scale: np.ndarray | None = None
    _sample_set: SampleSet | None = None
    _shadowing: Shadowing | None = None
    _frame_normal: np.ndarray | None = None
    _short_hits: object = False  # core.transport.contacts.ShortHits, None (none), False (not looked for)
    _landing_openness: np.ndarray | None = None  # (m,) the sky's openness at the short hits
    _openness: np.ndarray | None = None  # (K,) the samples' (the AO pass)
    _near_hits: object = False
    _emitter_near_hits: object = False
    _filter_pairs: tuple | None = None
    _exposed: np.ndarray | None = None
    # Light a later relight can reuse (core.pipeline.light_memo), bounded on its own.
    light_memo: LightMemo = field(default_factory=LightMemo)
    # Kept for later relights (core.pipeline.resident): its transport is split into parts they can reuse.
    resident: bool = False
    # Relit once by its caller (a bake whose preparation is not kept: operators.adapter.job):
    # the transport lets go of what only direct light reads as soon as the last of it is
    # computed (drop_direct_inputs).
    relit_once: bool = False
    _direct_inputs_dropped: bool = False
    _short_hits_dropped: bool = False
    _footprint_shading_dropped: bool = False

    def drop_footprint_shading(self) -> None:
        """Let go of the footprints' box corners and point normals (370 MiB at the Production
        preset), and of the sample set holding them, once the samples' direct light is computed:
        the short hits are found from the footprint points alone, and their search is the
        highest memory of a bake relit once. For a preparation relit once (:attr:`relit_once`);
        a later read of the sample set or the dense footprints is a bug and raises."""
        if self._footprint_shading_dropped:
            return
        self._sample_set = None
        if self.footprint is not None:
            self.footprint = (self.footprint[0], None, None)
        for samples in self.object_samples:
            for name in ("footprint_corners", "footprint_normals"):
                if getattr(samples, name, None) is not None:
                    setattr(samples, name, None)
        self._footprint_shading_dropped = True

    def drop_footprints(self) -> None:
        """Let go of every footprint (points, box corners and normals: 670 MiB at the Production
        preset) once the samples' direct light and the short hits are found: the short hits'
        own direct light and the gathers, whose working memory is the bake's highest, read none.
        For a preparation relit once (:attr:`relit_once`); a later read of them is a bug and raises."""
        if self._direct_inputs_dropped:
            return
        # The one pass after direct light that reads the footprints reads only their point
        # count, and runs after they are gone: it pages the table's entries in (the demo's
        # highest moment when the footprints were still alive).
        slots = 1 if self.footprint is None else self.footprint[0].shape[1]
        self.drop_footprint_shading()
        self.footprint = None
        for samples in self.object_samples:
            if getattr(samples, "footprint", None) is not None:
                samples.footprint = None
        self._direct_inputs_dropped = True
        self.exposed(slots)

    def drop_direct_inputs(self) -> None:
        """:meth:`drop_footprints`, and let go of the short hits' landing points (about 300 MiB at
        the Production preset) and the smooth faces' shadow-ray lifts once their direct light
        is computed too."""
        self.drop_footprints()
        if self._short_hits:
            self._short_hits = replace(self._short_hits, points=None)
        self.terminator = None  # read by the samples' shadow rays alone (sample_set, now gone)

    def drop_short_hits(self) -> None:
        """Let go of the short hits (22 MiB on the demo) once the contacts' correction is computed,
        for a preparation relit once (:attr:`relit_once`): every later gather adds that
        correction and reads no short hit. A later read of them is a bug and raises."""
        self._short_hits = self._landing_openness = None
        self._short_hits_dropped = True

    def _check_direct_inputs(self, what: str, shading: bool = False) -> None:
        """Raise where ``what`` is read after the preparation let it go: the footprints, or with
        ``shading`` their corners and normals (:meth:`drop_footprint_shading`)."""
        if self._direct_inputs_dropped or (shading and self._footprint_shading_dropped):
            raise RuntimeError(f"bug: {what} read after the preparation let go of its footprints "
                               "(Prepared.drop_direct_inputs)")

    def exposed(self, slots: int | None = None) -> np.ndarray:
        """(K,) float64 each sample's share of footprint points not buried inside other geometry
        (core.transport.contacts.exposed_share); ones without a table. Found once per
        preparation: it depends on geometry alone. ``slots``: the footprints' point count, where
        they are let go already (:meth:`drop_footprints`)."""
        if self._exposed is None:
            if self.table is None:
                self._exposed = np.ones(len(self.position))
            else:
                if slots is None:
                    self._check_direct_inputs("the footprints' point count")
                    slots = 1 if self.footprint is None else self.footprint[0].shape[1]
                self._exposed = exposed_share(self.table, slots, self.settings.threads)
        return self._exposed

    def dense_footprint(self, rows: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray | None]:
        """``count`` footprint points (r, count, 3) float32 of samples ``rows`` (r,), and their
        normals (r, count, 3) float32 or None (:func:`dense_footprint_of`)."""
        self._check_direct_inputs("footprint points", shading=True)
        return dense_footprint_of(self.meshes, self.object_samples.__getitem__, self.sample_offset,
                                  lambda chosen: self.normal[chosen], rows, count, self.settings.threads,
                                  self.settings.footprint_width)

    def lookup_atlas(self, values: np.ndarray, dilate) -> np.ndarray:
        """Per-sample reflected light (K, C) as the atlas rays look it up in: each texel's
        light over its exposed share, and texels wholly buried under other geometry filled
        from their exposed neighbours like the gutter (core.transport.contacts)."""
        exposed = self.exposed()
        buried = exposed < MIN_EXPOSED_SHARE
        return self.to_atlas(values * lookup_scale(exposed)[:, None], dilate, buried if buried.any() else None)

    def filter_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """The texel pairs the interleaving filter averages (core.transport.interleave.filter_pairs),
        found once per preparation: they depend on geometry alone."""
        if self._filter_pairs is None:
            self._filter_pairs = filter_pairs(self)
        return self._filter_pairs

    def near_hits(self):
        """The table entries that land near their sample (core.transport.interleave.find_near_hits),
        found once per preparation: they depend on geometry alone. None when there are none."""
        if self._near_hits is False:
            self._near_hits = find_near_hits(self)
        return self._near_hits

    def emitter_near_hits(self):
        """The near table entries of the emitted light's gather: :meth:`near_hits`, and those
        landing on an emissive object within core.transport.interleave.EMITTER_NEAR_FIELD_TILES
        windows; found once per preparation (geometry and materials alone). None when there are none."""
        if self._emitter_near_hits is False:
            emitting = np.array([bool(np.any(self.emission[a:b] > 0))
                                 for a, b in zip(self.sample_offset[:-1], self.sample_offset[1:])])
            self._emitter_near_hits = find_emitter_near_hits(self, self.near_hits(), emitting)
        return self._emitter_near_hits

    def short_hits(self):
        """The table entries whose rays land close by (core.transport.contacts), found once
        per preparation: they depend on geometry alone. None when there are none."""
        if self._short_hits_dropped:
            raise RuntimeError("bug: the short hits read after the preparation let go of them "
                               "(Prepared.drop_short_hits)")
        if self._short_hits is False:
            self._check_direct_inputs("the footprints the short hits are found from")
            self._short_hits = find_short_hits(self)
        return self._short_hits

    def landing_openness(self) -> np.ndarray:
        """(m,) float64 how open the sky is where each short hit lands
        (core.transport.contacts.landing_openness), traced once per preparation: it depends on
        geometry alone. Read before the short hits' landing points go (drop_direct_inputs)."""
        if self._landing_openness is None:
            self._landing_openness = landing_openness(self.short_hits(), self.object_samples, self.ray_scene)
        return self._landing_openness

    def openness(self) -> np.ndarray:
        """(K,) float64 each sample's cosine-weighted share of open directions
        (core.transport.gather.ambient_occlusion: the AO pass), once per preparation."""
        if self._openness is None:
            self._openness = ambient_occlusion(self.table, self.frame_normal, self.gather_scale(),
                                               self.settings.threads)
        return self._openness

    def sample_set(self) -> SampleSet:
        """All samples as the transport contract's :class:`SampleSet`."""
        self._check_direct_inputs("the sample set", shading=True)
        if self._sample_set is None:
            owner = np.repeat(np.arange(len(self.meshes)), np.diff(self.sample_offset))
            points, corners, normals = self.footprint or (None, None, None)
            self._sample_set = SampleSet(self.position, self.normal, self.geometric, self.origins, owner, points,
                                         corners, *(self.terminator or (None, None)), footprint_normals=normals,
                                         dense_footprint=None if points is None else self.dense_footprint)
        return self._sample_set

    def shadowing(self) -> Shadowing:
        """How direct light is shadowed, as the settings say; one object per preparation, so
        the distant lights' shadow fractions are computed once for every relight."""
        if self._shadowing is None:
            self._shadowing = shadowing_of(self, self.table, self.group)
        return self._shadowing

    def sample_rows(self, start: int, stop: int) -> SampleSet:
        """Samples [start, stop) (SampleSet.rows of :meth:`sample_set`: views, the bake's ids)."""
        return self.sample_set().rows(start, stop)

    def trace_request(self) -> TraceRequest:
        """The request this preparation's table is traced from (all samples; TraceRequest.rows
        narrows it to a range of them)."""
        self._check_direct_inputs("the trace request")
        return table_request(self.meshes, self.settings, self.directions, self.position, self.geometric,
                             self.footprint, self.rotations, self.group)

    def gather_geometry(self) -> GatherGeometry:
        """The light-independent half of every gather over this preparation. The normals are
        in each sample's frame of the direction set (its interleaved rotation), so a gather
        weighs direction i by max(0, d_i . n) whatever the rotation."""
        return GatherGeometry(self.table, self.frame_normal, self.gather_scale(), self.layout, self.settings.threads)

    @property
    def frame_normal(self) -> np.ndarray:
        """(K, 3) the shading normals in each sample's frame of the direction set."""
        if self._frame_normal is None:
            self._frame_normal = frame_vectors(self.normal, self.rotations, self.group)
        return self._frame_normal

    def world_directions(self) -> np.ndarray:
        """The directions rays travel: (N, 3), or (G, N, 3) per interleaved rotation."""
        if self.rotations is None:
            return self.directions
        return np.einsum("gab,nb->gna", self.rotations, self.directions)

    def sample_directions(self, direction_index: np.ndarray, sample_index: np.ndarray) -> np.ndarray:
        """(n, 3) float64 world direction of direction i of sample k for pairs (n,) each."""
        if self.rotations is None:
            return self.directions[direction_index]
        return np.einsum("nab,nb->na", self.rotations[self.group[sample_index]], self.directions[direction_index])

    def gather_scale(self) -> np.ndarray:
        """Per-sample gather normalisation (K,), computed once per preparation."""
        if self._gather_scale is None:
            self._gather_scale = gather_normalisation(self.table, self.frame_normal, self.open_weight(),
                                                      self.settings.threads)
        return self._gather_scale

    def open_weight(self) -> np.ndarray:
        """(K,) float64 what each sample's gather weights sum to: pi (1 + n . n_g) / 2
        (core.transport.gather.open_hemisphere_weight)."""
        return open_hemisphere_weight(self.normal, self.geometric)

    def bounces_needed(self) -> int:
        """The bounces to gather: none when no requested pass contains indirect light."""
        wants = set(self.settings.passes)
        return self.settings.bounces if wants & {"lighting", "indirect", "irradiance"} else 0

    def output_samples(self) -> np.ndarray | None:
        """(k,) int64 samples of the objects with outputs, or None if every object has outputs."""
        if all(m.output for m in self.meshes):
            return None
        return np.concatenate([np.arange(a, b) for m, a, b in zip(self.meshes, self.sample_offset[:-1],
                                                                  self.sample_offset[1:]) if m.output])

    def lighting_key(self, group: LightGroup) -> str:
        """Hash of everything one group's transport depends on besides the table's key."""
        s = self.settings
        emitting = np.repeat(group.emitting, np.diff(self.sample_offset))
        parts = [TRANSPORT_REVISION, self.table_key, self.bounces_needed(), s.shadows, s.shadow_regions,
                 s.area_light_samples, s.sharp_contacts, s.target_error,
                 s.emitter_samples, max(s.margin, 2), s.vertex_lookup, self.albedo, self.normal,
                 np.where(emitting[:, None], self.emission, 0.0), group.world, group.emitting,
                 np.array([m.output for m in self.meshes])]
        if group.lights:
            # Which meshes cast lamp shadows and which a linked lamp lights or is blocked by.
            parts += [s.seed, np.array([m.casts_shadow for m in self.meshes]), tuple(m.name for m in self.meshes)]
        for index in np.nonzero(group.emitting)[0]:
            parts += [np.asarray(m.emission, np.float64) for m in self.meshes[index].materials if m is not None]
        for light in group.lights:
            parts += light_key_parts(light)
        return arrays_key(*parts)

    def to_atlas(self, values: np.ndarray, dilate, empty: np.ndarray | None = None) -> np.ndarray:
        """Per-sample values (K, C) as the packed, gutter-dilated radiance atlas (size, C).

        ``dilate`` is a backend's dilation, (image, coverage, margin) -> (image, coverage).
        ``empty`` (K,) bool: texels of atlas-mode objects filled by the dilation like the gutter.
        """
        margin = max(self.settings.margin, 2)
        images = []
        for mesh, samples, a, b in zip(self.meshes, self.object_samples, self.sample_offset[:-1],
                                       self.sample_offset[1:]):
            image = np.zeros((samples.height * samples.width, values.shape[1]), np.float32)
            image[samples.pixel] = values[a:b]
            image = image.reshape(samples.height, samples.width, values.shape[1])
            coverage = samples.coverage
            if empty is not None and mesh.mode != "vertex" and empty[a:b].any():
                coverage = coverage.copy()
                coverage.reshape(-1)[samples.pixel[empty[a:b]]] = False
            # A vertex-mode object covers its whole one-row "atlas": nothing to dilate.
            if not coverage.all():
                image, _ = dilate(image, coverage, margin)
            images.append(image)
        return self.layout.pack(images)


def prepare(scene: Scene, settings: BakeSettings, progress=None, table_needed: bool | None = None,
            cache: VisibilityCache | None = None, require_cached_table: bool = False, split=None) -> Prepared:
    """Samples and the visibility table of ``scene``'s meshes.

    Parameters
    ----------
    table_needed : bool or None
        None: trace the table only if ``scene``'s own lights, world and materials
        need it. True: always (for relighting with lights not known yet).
    cache : VisibilityCache or None
        Where a valid table is read from, and a new or updated one written to.
    require_cached_table : bool
        Refuse (:class:`BakeRefused`) instead of tracing when the table is needed and
        the cache holds no valid one: a relight must not silently become a bake.
    split : an executor of core.distributed.split (in process, or a cluster's), or None
        Trace the table by ranges of sample rows, kept where the executor runs them: the
        preparation's table is then a core.distributed.split.SplitTable, never cached.
    """
    settings.validate()
    # A vertex-mode object has at most one sample per triangle corner.
    check_budget([m.resolution if m.mode == "atlas" else (3 * len(m.triangles), 1) for m in scene.meshes],
                 settings.directions)
    for mesh in scene.meshes:
        if mesh.mode == "vertex" and len(mesh.triangles) > MAX_VERTEX_TRIANGLES:
            raise BakeRefused(f"object {mesh.name!r} has {len(mesh.triangles)} triangles; vertex mode takes at most "
                              f"{MAX_VERTEX_TRIANGLES} per object: bake it as an atlas")
    stages = Stages(progress)
    skipped: list[str] = []
    warnings: list[str] = []

    if not kernels.tried():
        # The first bake of a session loads the compiled lookups: seconds when they must be
        # compiled (a fresh kernel cache), shown as a stage of its own.
        stages.start("kernels")
        kernels.status()
    stages.start("samples")
    meshes = meshes_with_faces(scene.meshes)
    warnings += [f"object {mesh.name!r} has no faces and was skipped" for mesh in scene.meshes
                 if len(mesh.triangles) == 0]
    if not any(m.output for m in meshes):
        raise BakeRefused("there is no mesh with faces to bake; select meshes that have faces")
    if settings.shadows == "fractions":
        # The table counts every hit, so the fractions cannot leave an object out of one
        # lamp's shadows; exact shadows can.
        for mesh in meshes:
            if not mesh.casts_shadow:
                warnings.append(f"object {mesh.name!r}: its shadow visibility is off, which shadow fractions cannot "
                                "honour: it still casts shadows; use exact shadows")
        for light in scene.lights:
            if light.blockers is not None and light.casts_shadows:
                warnings.append(f"light {light.name!r}: shadow linking is not honoured by shadow fractions: every "
                                "object shadows it; use exact shadows")
    centre, precision_warning = trace_frame(meshes)
    if precision_warning:
        warnings.append(precision_warning)
    object_samples: list[ObjectSamples] = []
    for index, mesh in enumerate(meshes):
        object_samples.append(build_vertex_samples(mesh, centre) if mesh.mode == "vertex"
                              else build_samples(mesh, settings.footprint_samples, settings.threads,
                                                  settings.footprint_width))
        stages.report((index + 1) / len(meshes))
    for mesh, samples in zip(meshes, object_samples):
        if len(samples) == 0 and mesh.output:
            warnings.append(f"object {mesh.name!r}: no texel centre falls inside its UV layout at "
                            f"{mesh.resolution[0]}x{mesh.resolution[1]}; raise the resolution")
        if samples.uv_overlap_texels:
            warnings.append(f"object {mesh.name!r}: {samples.uv_overlap_texels} texels are covered by "
                            "overlapping UV islands; each was given to one triangle")
    counts = np.array([len(s) for s in object_samples], np.int64)
    position = adopted(object_samples, "position", (3,), np.float64)
    geometric = adopted(object_samples, "geometric_normal", (3,), np.float64)
    normal = adopted(object_samples, "normal", (3,), np.float64)
    emission = np.concatenate([s.emission for s in object_samples]).astype(np.float64)
    footprint = concatenated_footprint(object_samples, settings.footprint_samples)
    terminator = concatenated_terminator(meshes, object_samples)
    rotations, group = interleaving(object_samples, settings.interleave, settings.seed)
    directions = direction_set(settings.directions, settings.rotate, settings.seed)
    if table_needed is None:
        table_needed = (settings.bounces > 0 or bool(np.any(emission > 0)) or "ao" in settings.passes
                        or has_light(scene.world)
                        or (settings.shadows == "fractions" and bool(scene.lights)))

    # embree's scene and BVH, shared by every pass that traces: a stage of its own, so that the
    # visibility stage times the trace alone (against embree's own rate in docs/benchmarks.md).
    stages.start("bvh")
    ray_scene = RayScene([(m.positions, m.triangles) for m in meshes], settings.threads, centre)
    stages.start("samples")
    sample_offset = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    # The keys name the table (and a lighting's light) in the cache; each hashes every mesh's
    # arrays (20-30 ms of a 200k-triangle mesh), so a bake without a cache makes none.
    object_keys = [object_key(m) for m in meshes] if cache is not None else []
    key = table_key(object_keys, settings) if cache is not None else ""
    table = None
    status = CacheStatus() if cache is None else None
    visibility_rays = 0
    if table_needed and split is not None:
        # Traced below, by rows, once the preparation exists.
        status = CacheStatus(state="unused", message="a table held by sample rows is not cached")
        skipped.append("visibility cache: the table is held by sample rows where they were traced")
    elif table_needed:
        stages.start("cache" if cache is not None else "visibility")
        request = replace(table_request(meshes, settings, directions, position, geometric, footprint, rotations,
                                        group), scratch_folder=scratch_folder(cache))
        table, status, visibility_rays = _cached_or_traced_table(TableJob(
            meshes, object_keys, key, settings, request, sample_offset, ray_scene, cache, require_cached_table,
            stages, skipped, warnings))
    else:
        stages.expect("visibility", 0.0)
        stages.expect("cache", 0.0)
        skipped.append("visibility table: no pass needs it (no bounces, emission, world, AO or shadow fractions)")
        status = status or CacheStatus(state="unused", message="no pass needs the visibility table")
    if cache is not None:
        status.abandoned_writes_removed = cache.abandoned_removed

    prepared = Prepared(
        settings=settings, meshes=meshes, object_samples=object_samples,
        sample_offset=np.concatenate([[0], np.cumsum(counts)]), position=position,
        normal=normal, geometric=geometric,
        albedo=np.concatenate([s.albedo for s in object_samples]).astype(np.float64), emission=emission,
        layout=AtlasLayout.from_sizes([(s.width, s.height) for s in object_samples],
                                      [getattr(s, "corner_sample", None) for s in object_samples],
                                      settings.vertex_lookup == "nearest"), directions=directions,
        ray_scene=ray_scene, origins=ray_scene.ray_origins(position, geometric), table=table, footprint=footprint,
        terminator=terminator, rotations=rotations, group=group,
        stage_seconds={}, skipped=skipped, warnings=warnings, table_key=key,
        visibility_rays=visibility_rays, cache=None if split is not None else cache, cache_status=status)
    if table_needed and split is not None:
        stages.start("visibility")
        prepared.table = split.start(prepared, stages.report)
        prepared.visibility_rays = prepared.table.rays_cast
    stages.stop()
    prepared.stage_seconds = dict(stages.times)
    return prepared


# adopted() gives the heap's free pages back once this much is free (a trim takes about a
# millisecond; an object's footprint is a few MiB to a few hundred).
ADOPTED_TRIM_BYTES = 4 << 20


def concatenated_footprint(object_samples, count: int) -> tuple | None:
    """Every sample's footprint points (K, count, 3) and box corners (K, 4, 3) float32
    offsets, objects concatenated (zero for samples that stand for a point, such as vertex
    samples), and the points' shading normals (K, count, 3) float32 (each sample's own
    normal on flat faces: :func:`footprint_point_normals`), None where no face is smooth; or
    None when ``count`` is 1.

    Each object's own arrays become views into these (:func:`adopted`), so the footprints are
    in memory once, not twice (at the Production preset each copy is about 0.7 GB)."""
    if count <= 1:
        return None
    points = adopted(object_samples, "footprint", (count, 3), np.float32, lambda s: footprint_points(s, count))
    corners = adopted(object_samples, "footprint_corners", (4, 3), np.float32, footprint_box)
    point_normals = None
    if any(s.footprint_normals is not None for s in object_samples):
        point_normals = adopted(object_samples, "footprint_normals", (count, 3), np.float32,
                                lambda s: footprint_point_normals(s, count))
    return points, corners, point_normals


def adopted(object_samples, name: str, shape: tuple, dtype, values=None) -> np.ndarray:
    """(K, *shape) ``dtype``: every object's attribute ``name`` (or ``values(samples)``, for
    objects without it), objects concatenated; each object's own array, where it has one,
    becomes a view into it.

    Each object's array is let go as soon as it is copied, and the result's pages are only
    touched as they are filled, so the bake holds about one copy at any time, not the objects'
    and the whole's side by side (the demo's footprints: 166 MiB more at the samples stage's
    peak, given back object by object)."""
    out = np.empty((sum(len(s) for s in object_samples), *shape), dtype)
    start = released = 0
    for samples in object_samples:
        rows = slice(start, start + len(samples))
        own = getattr(samples, name)
        out[rows] = own if values is None else values(samples)
        if own is not None:
            setattr(samples, name, out[rows])
            released += own.nbytes
        del own
        start = rows.stop
        # The objects' arrays are small enough to have come from the heap, whose freed pages
        # glibc keeps until asked (a few milliseconds' work, not done for every small object).
        if released >= ADOPTED_TRIM_BYTES:
            release_free_heap(above=ADOPTED_TRIM_BYTES)
            released = 0
    return out


def shadowing_of(bake, table, group: np.ndarray | None) -> Shadowing:
    """The Shadowing of a bake (a Prepared, or a worker's core.distributed.rows.PackagedBake:
    its settings, meshes, ray_scene, directions and rotations) over ``table`` (its whole table,
    or a range of rows' with those rows' ``group`` (k,) int64 rotations, or None)."""
    s = bake.settings
    return Shadowing(s.shadows, bake.ray_scene, s.area_light_samples, table, bake.directions, s.shadow_regions,
                     tuple(m.name for m in bake.meshes), np.array([m.casts_shadow for m in bake.meshes], bool),
                     s.seed, s.footprint_samples, bake.rotations, group)


def dense_footprint_of(meshes, object_samples, sample_offset: np.ndarray, normal_of, rows: np.ndarray, count: int,
                       threads: int, footprint_width: float) -> tuple[np.ndarray, np.ndarray | None]:
    """``count`` footprint points (r, count, 3) float32 of the bake's samples ``rows`` (r,) int64,
    and their normals (r, count, 3) float32 or None (core.sampling.samples.dense_footprint);
    vertex samples stand for their position (zero offsets).

    object_samples : callable(object index) -> its ObjectSamples; sample_offset : (objects + 1,)
    where each object's samples start; normal_of : callable(rows) -> their (r, 3) shading normals;
    footprint_width : the texels' box width (BakeSettings.footprint_width).
    """
    rows = np.asarray(rows, np.int64)
    offsets = np.zeros((len(rows), count, 3), np.float32)
    normals = None
    owner = np.searchsorted(sample_offset, rows, side="right") - 1
    for index in np.unique(owner):
        mesh, samples = meshes[index], object_samples(index)
        chosen = np.nonzero(owner == index)[0]
        if mesh.mode == "vertex":  # its samples stand for their position
            continue
        local = rows[chosen] - sample_offset[index]
        offsets[chosen], point_normals = dense_footprint(mesh, samples, local, count, threads, footprint_width)
        if point_normals is not None:
            if normals is None:
                normals = np.broadcast_to(normal_of(rows).astype(np.float32)[:, None, :], offsets.shape).copy()
            normals[chosen] = point_normals
    return offsets, normals


def meshes_with_faces(meshes: list) -> list:
    """The meshes a bake samples and traces, in order: those with faces."""
    return [mesh for mesh in meshes if len(mesh.triangles)]


def direction_rotations(tile: int, seed: int) -> np.ndarray | None:
    """The interleaved rotations (tile², 3, 3) float64 of the direction set, or None for one set."""
    return None if tile <= 1 else interleaved_rotations(tile * tile, seed)


def footprint_points(samples: ObjectSamples, count: int) -> np.ndarray:
    """(k, count, 3) float32 one object's footprint offsets; zeros where its samples stand
    for a point (vertex samples)."""
    if samples.footprint is not None:
        return samples.footprint
    return np.zeros((len(samples), count, 3), np.float32)


def footprint_box(samples: ObjectSamples) -> np.ndarray:
    """(k, 4, 3) float32 one object's footprint box corners; zeros where it has none."""
    if samples.footprint_corners is not None:
        return samples.footprint_corners
    return np.zeros((len(samples), 4, 3), np.float32)


def footprint_point_normals(samples: ObjectSamples, count: int) -> np.ndarray:
    """(k, count, 3) float32 the shading normal at one object's footprint points: its own where
    it has them, else each sample's normal at every point."""
    if samples.footprint_normals is not None:
        return samples.footprint_normals
    return np.broadcast_to(np.asarray(samples.normal, np.float32)[:, None, :], (len(samples), count, 3))


def rotation_group(samples: ObjectSamples, tile: int) -> np.ndarray:
    """(k,) int64 the interleaved rotation of each of one object's samples (:func:`interleaving`)."""
    if isinstance(samples, VertexSamples):
        return np.zeros(len(samples), np.int64)
    x, y = samples.pixel % samples.width, samples.pixel // samples.width
    return (x % tile + tile * (y % tile)).astype(np.int64)


def interleaving(object_samples, tile: int, seed: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The interleaved rotations (G, 3, 3) of the direction set and each sample's (K,) int64, or
    (None, None) for one set. A texel at (x, y) of an atlas takes rotation
    (x % tile) + tile * (y % tile), so every tile x tile block holds each rotation once; vertex
    samples, which no filter averages, keep the set itself (rotation 0)."""
    if tile <= 1:
        return None, None
    return direction_rotations(tile, seed), np.concatenate([rotation_group(s, tile) for s in object_samples])


def concatenated_terminator(meshes, object_samples) -> tuple[np.ndarray, np.ndarray] | None:
    """Every sample's shadow-ray lift (K, 3) float64 and its object's cutoff (K,) float64
    (core.sampling.terminator), objects concatenated; None when no sample has a lift."""
    if all(s.terminator is None for s in object_samples):
        return None
    lifts = np.concatenate([terminator_lifts(s) for s in object_samples])
    cutoffs = np.concatenate([terminator_cutoffs(m, s) for m, s in zip(meshes, object_samples)])
    return lifts, cutoffs


def terminator_lifts(samples: ObjectSamples) -> np.ndarray:
    """(k, 3) float64 one object's shadow-ray lifts; zeros where it has none."""
    return samples.terminator if samples.terminator is not None else np.zeros((len(samples), 3))


def terminator_cutoffs(mesh, samples: ObjectSamples) -> np.ndarray:
    """(k,) float64 one object's terminator cutoff, per sample."""
    return np.full(len(samples), mesh.terminator_offset)


# Float32 resolves about 1 part in 1.7e7; ray origins step a few hundred ULPs off the
# surface. Past this ratio of the traced frame's extent to an output object's size, the
# steps reach about 1% of the object and contact shadows start to move.
PRECISION_EXTENT_RATIO = 1e5


def trace_frame(meshes) -> tuple[np.ndarray, str | None]:
    """The centre the ray scene is traced around, and a warning if float32 still limits precision.

    The centre is the middle of the finite geometry's bounds, rounded to a power of two
    at least the scene's size: a scene near the world origin keeps centre 0 (and traces
    exactly as before), a scene far from it is traced as if it were at the origin. The
    table holds distances and atlas coordinates only, so it does not depend on the
    centre, and the cache key (which hashes world-space geometry) needs no part of it.

    Returns
    -------
    centre : (3,) float64
    warning : str or None, when the scene's own extent against its smallest output
        object leaves float32 too coarse (the frame cannot remove that)
    """
    bounds = [(m, _finite_bounds(m.positions)) for m in meshes]
    bounds = [(m, b) for m, b in bounds if b is not None]
    if not bounds:
        return np.zeros(3), None
    low = np.min([b[0] for _, b in bounds], axis=0)
    high = np.max([b[1] for _, b in bounds], axis=0)
    extent = float(np.max(high - low))
    step = 2.0 ** np.ceil(np.log2(max(extent, 1e-30)))
    centre = np.round((low + high) / 2 / step) * step
    reach = float(np.max(np.maximum(np.abs(high - centre), np.abs(low - centre))))
    sizes = [float(np.max(b[1] - b[0])) for m, b in bounds if m.output]
    smallest = min((s for s in sizes if s > 0), default=0.0)
    if smallest > 0 and reach / smallest > PRECISION_EXTENT_RATIO:
        return centre, (f"precision: the scene reaches {reach:.3g} units from its centre but the smallest baked object "
                        f"is {smallest:.3g} across (ratio {reach / smallest:.2g} > {PRECISION_EXTENT_RATIO:.0e}); "
                        "rays are traced in float32, so its shadows and contacts may be off by about 1%; bake it "
                        "with fewer distant objects")
    return centre, None


def _finite_bounds(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(low, high) (3,) each, the bounds of the rows of ``positions`` (n, 3) that are finite;
    None where none is. Reduced column by column: numpy reduces an (n, 3) array along its first
    axis about 20x slower (12 ms of a 100k-vertex mesh's four reductions; docs/benchmarks.md,
    speed part 20)."""
    positions = np.asarray(positions)
    if not np.isfinite(positions).all():
        positions = positions[np.all(np.isfinite(positions), axis=1)]
    if not len(positions):
        return None
    columns = np.ascontiguousarray(positions.T)
    return columns.min(axis=1), columns.max(axis=1)


def table_request(meshes, settings: BakeSettings, directions, position, geometric, footprint, rotations,
                  group) -> TraceRequest:
    """The visibility table's TraceRequest of a preparation's samples (the Prepared fields of
    the same names; ``footprint`` the (points, corners, normals) tuple or None)."""
    return TraceRequest(directions, position, geometric, scene_hit_geometry(meshes), settings.chunk_rays,
                        None if footprint is None else footprint[0], rotations, group)


def scratch_folder(cache: VisibilityCache | None) -> str | None:
    """Where a large table is held while a bake runs (core.visibility.scratch): the cache folder,
    which the user chose for tables, made if need be; None (in memory) where caching is off or
    the folder cannot be written. Not the system's temporary folder: it may be a tmpfs, whose
    pages are memory however the process hands them back, and the user did not choose it."""
    if cache is None or cache.read_only:
        return None
    try:
        os.makedirs(cache.folder, exist_ok=True)
    except OSError:
        return None
    return cache.folder


def scene_hit_geometry(meshes) -> HitGeometry:
    """Where a ray's hit on any of ``meshes`` lands in the table: bake-UV corners (zeros
    for vertex-mode objects, whose hits keep barycentrics instead), face normals and
    which objects are in vertex mode."""
    triangle_counts = np.array([len(m.triangles) for m in meshes], np.int64)
    triangle_offset = np.concatenate([[0], np.cumsum(triangle_counts)[:-1]]).astype(np.int64)
    corner_uv = np.concatenate([m.uv_maps[m.bake_uv_map] if m.mode == "atlas" else np.zeros((len(m.triangles), 3, 2))
                                for m in meshes]).astype(np.float32)
    vertex_object = np.array([m.mode == "vertex" for m in meshes], bool)
    all_face_normals = np.concatenate([mesh_face_normals(m)[0] for m in meshes])
    return HitGeometry(corner_uv, triangle_offset, all_face_normals, vertex_object)


@dataclass
class TableJob:
    """What finding a preparation's table needs: the scene's keys, what to trace, the
    cache, and where to report (stages, skipped work, warnings)."""

    meshes: list
    object_keys: list[str]
    key: str
    settings: BakeSettings
    request: TraceRequest
    sample_offset: np.ndarray  # (objects + 1,) int64
    ray_scene: RayScene
    cache: VisibilityCache | None
    require_cached_table: bool
    stages: Stages
    skipped: list
    warnings: list


def _cached_or_traced_table(job: TableJob):
    """The table from the cache if it is valid, updated if only some objects changed, else traced.

    Returns (table, CacheStatus, rays traced against the scene).
    """
    meshes, object_keys, key, settings, cache = job.meshes, job.object_keys, job.key, job.settings, job.cache
    sample_offset, ray_scene, stages, skipped, warnings = (job.sample_offset, job.ray_scene, job.stages, job.skipped,
                                                           job.warnings)
    require_cached_table = job.require_cached_table
    names = [m.name for m in meshes]
    status = CacheStatus()
    meta = None

    def trace(report):
        table = trace_table(ray_scene, job.request, report)
        if table.entries.mapping_error:
            warnings.append(f"the visibility table is held in memory: its scratch file in "
                            f"{job.request.scratch_folder} could not be made ({table.entries.mapping_error})")
        return table

    def announce(size):
        status.estimated_bytes = size
        stages.note(f"writing about {size / 2**20:.0f} MiB to the visibility cache")

    def save(table):
        try:
            status.bytes_on_disk = cache.save_table(settings, key, names, object_keys, sample_offset, table, announce)
        except CacheFull as error:
            status.not_cached = str(error)
            warnings.append(f"visibility table not cached: {error}; raise the Cache Limit preference, or the next "
                            "bake traces the table again")
        except OSError as error:
            warnings.append(f"visibility cache {status.path} could not be written ({error}); the next bake "
                            "traces the table again")
        finally:
            stages.note("")
        status.evicted = [{"slot": slot, "bytes": size} for slot, size in cache.evicted]

    def damaged(error):
        """The deferred table's large arrays are damaged: trace them again (never for a relight)."""
        if require_cached_table:
            raise BakeRefused(f"the cached visibility is damaged ({error}); bake first")
        status.state, status.message = "corrupt", f"the cache file cannot be trusted: {error}"
        warnings.append(f"visibility cache {status.path}: {error}; it was rebuilt")
        fresh = trace(None)
        save(fresh)
        return {name: getattr(fresh, name) for name in DeferredTable.LARGE}  # its entries

    if cache is not None:
        status.path = cache.table_path(settings)
        started = time.perf_counter()
        try:
            meta = cache.read_table_meta(settings)
            if meta is None:
                status.state, status.message = "miss", "no cached visibility for this scene and these settings"
            elif meta.get("key") == key:
                stages.expect("visibility", 0.0)
                if meta.get("sample_offset") != [int(x) for x in sample_offset]:
                    raise CorruptCache("its layout does not match its key")
                # Read when a pass needs it: a bake whose lighting is cached never does.
                table = cache.deferred_table(settings, meta, damaged)
                if not np.array_equal(table.directions, job.request.directions):
                    raise CorruptCache("its directions do not match its key")
                _check_vertex_cells(table, job.request)
                status.state, status.message = "hit", "the cached visibility is valid"
                status.bytes_on_disk = os.path.getsize(status.path)
                status.load_seconds = time.perf_counter() - started
                skipped.append(f"visibility stage: the cached table is valid ({status.path})")
                return table, status, 0
            else:
                status.state = "stale"
                old_names, old_keys = meta.get("object_names", []), meta.get("object_keys", [])
                if old_names == names:
                    status.changed_objects = [n for n, a, b in zip(names, object_keys, old_keys) if a != b]
                    status.message = f"changed since the cached bake: {', '.join(status.changed_objects)}"
                else:
                    added = sorted(set(names) - set(old_names))
                    removed = sorted(set(old_names) - set(names))
                    status.changed_objects = added + removed
                    status.message = ("the scene's objects changed since the cached bake"
                                      + (f" (added: {', '.join(added)})" if added else "")
                                      + (f" (removed: {', '.join(removed)})" if removed else ""))
        except CorruptCache as error:
            status.state, status.message = "corrupt", f"the cache file cannot be trusted: {error}"
            warnings.append(f"visibility cache {status.path}: {error}; it was rebuilt")
            meta = None
        status.load_seconds = time.perf_counter() - started
    if require_cached_table:
        detail = status.message or "the cache is off"
        raise BakeRefused(f"no valid cached visibility for relighting ({detail}); bake first")

    table = None
    rays = 0
    stages.start("visibility")
    changed = [i for i, n in enumerate(names) if n in status.changed_objects]
    if status.state == "stale" and meta is not None and meta.get("object_names") == names and len(changed) < len(names):
        try:
            stages.start("cache")
            old = cache.load_table(settings, meta)
            old_table = table_from_arrays(old.arrays, old.counters)
            _check_vertex_cells(old_table, job.request, changed)
            stages.report(0.5)  # read; writing the updated table is the other half
            stages.start("visibility")
            changed_scene = RayScene([(meshes[i].positions, meshes[i].triangles) for i in changed], settings.threads,
                                     ray_scene.centre)
            table, counts = update_table(old_table, old.sample_offset, sample_offset, ray_scene, changed_scene,
                                         changed, job.request, stages.report)
            del old, old_table
            rays = counts.full + counts.changed_only
            status.state = "updated"
            skipped.append(f"visibility of unchanged objects: {counts.kept} of {table.rays_cast} table entries kept; "
                           f"{counts.changed_only} rays traced against the changed objects only, {counts.full} "
                           f"against the whole scene (changed: {', '.join(status.changed_objects)})")
        except CorruptCache as error:
            status.state, status.message = "corrupt", f"the cache file cannot be trusted: {error}"
            warnings.append(f"visibility cache {status.path}: {error}; it was rebuilt")
    if table is None:
        table = trace(stages.report)
        rays = table.rays_cast
    if cache is not None:
        stages.start("cache")
        started = time.perf_counter()
        save(table)
        status.save_seconds = time.perf_counter() - started
        stages.report(1.0)
    return table, status, rays


def _check_vertex_cells(table, request: TraceRequest, changed=()) -> None:
    """Raise CorruptCache where a cached table codes the vertex-mode hits of an object (other than
    the ``changed`` ones, which are traced again) otherwise than this scene does."""
    objects = len(request.hits.triangle_offset)
    expected, stored = request.hits.vertex_cells(), table.vertex_cells
    expected = np.zeros(objects, np.int64) if expected is None else expected
    stored = np.zeros(objects, np.int64) if stored is None else np.asarray(stored)
    kept = np.ones(objects, bool)
    kept[list(changed)] = False
    if stored.shape != expected.shape or not np.array_equal(stored[kept], expected[kept]):
        raise CorruptCache("its vertex-mode hits are coded for other meshes")


def read_deferred_table(p: Prepared, stages: Stages, needed: bool) -> None:
    """Read a cached table's large arrays now if the transport or AO needs them, as the
    cache stage inside the transport; otherwise tell the progress there is nothing left
    to read."""
    table = p.table
    if not isinstance(table, DeferredTable) or table.loaded:
        return
    if not needed:
        stages.expect("cache", 0.0)
        return
    stages.start("cache")
    table.load()
    if p.cache_status is not None:
        p.cache_status.load_seconds += table.read_seconds
    stages.report(1.0)
    stages.start("transport")
