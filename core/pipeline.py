"""The bake: samples -> visibility table -> shadow fractions -> transport -> pass images.

:func:`bake` is the one entry point the operators, the command line, the tests and
the benchmarks share. It reports progress through a callback that may raise
:class:`Cancelled` to stop between batches.
"""
from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from .directions import ShadowRegions, direction_set
from .shadows import ShadowFractions, shadow_fractions
from .environment import has_light, world_radiance
from .lighting import (LIGHTING_PASSES, MAX_GROUPS_PER_GATHER, LightGroup, Transported, accumulate_passes,
                       lamp_irradiance, light_groups, light_key_parts, transport_groups)
from .raster import dilate
from .rays import RayScene, offset_ray_origins
from .tessellation import check_vertex_objects
from .samples import ObjectSamples, build_samples, build_vertex_samples, face_normals
from .scene import BakeSettings, Scene
from .images import sample_image
from .transport import AtlasLayout, ambient_occlusion, gather, gather_normalisation
from .visibility import DeferredTable, table_bytes, table_from_arrays, trace_table, update_table
from .cache import CacheStatus, CorruptCache, VisibilityCache, arrays_key, object_key, table_key
from . import tolerances as tol


class Cancelled(Exception):
    """Raised by a progress callback to stop a bake; nothing has been written."""


class BakeRefused(ValueError):
    """The bake cannot run with these inputs; the message says why and what to change."""


@dataclass
class ObjectResult:
    """Results of one output object, per pass name.

    Atlas mode: (H, W, 4) float32 images, bottom-up. Vertex mode (``domain`` set):
    (n, 4) float32 colours of the base mesh's points or face corners, alpha 0 where
    no valid triangle uses the element.
    """

    name: str
    width: int
    height: int
    samples: int
    images: dict[str, np.ndarray] = field(default_factory=dict)
    domain: str | None = None
    # Vertex mode: triangles whose light varies inside them (core.tessellation), to refine.
    coarse_triangles: np.ndarray | None = None


def element_colors(values: np.ndarray, element_sample: np.ndarray) -> np.ndarray:
    """Per-sample RGB (k, 3) as RGBA colours of mesh elements (n, 4) float32, finite."""
    colors = np.zeros((len(element_sample), 4), np.float32)
    has = element_sample >= 0
    colors[has, :3] = np.nan_to_num(values[element_sample[has]], nan=0.0, posinf=0.0, neginf=0.0)
    colors[has, 3] = 1.0
    return colors


@dataclass
class BakeResult:
    objects: list[ObjectResult]
    report: dict


def physical_memory_bytes() -> int:
    """Installed memory, or 0 where it cannot be read."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def peak_memory_bytes() -> int:
    """Peak resident memory of this process so far, or 0 where it cannot be read."""
    try:
        import resource
    except ImportError:
        return 0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def memory_budget_bytes() -> int:
    """How much the table may take: half the installed memory (the rest is Blender's)."""
    physical = physical_memory_bytes()
    return physical // 2 if physical else 8 << 30


def _human_bytes(count: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if count < 1024 or unit == "TiB":
            return f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} TiB"


def check_budget(sizes, directions: int, budget: int | None = None) -> None:
    """Refuse, before anything is allocated, atlases or a table that cannot fit in memory.

    Parameters
    ----------
    sizes : iterable of (width, height), the atlas of every object
    directions : size of the direction set

    The bound counts every texel of every atlas (covered ones are fewer), so a bake
    that passes here cannot run out of memory in the table.
    """
    budget = memory_budget_bytes() if budget is None else budget
    sizes = [(int(w), int(h)) for w, h in sizes]
    for width, height in sizes:
        if width < 1 or height < 1:
            raise BakeRefused(f"atlas resolution must be at least 1x1, got {width}x{height}")
    texels = sum(w * h for w, h in sizes)
    # Per texel: coverage, per-sample geometry and colours, radiance atlases and outputs.
    per_texel = 200
    need_atlas = texels * per_texel
    if need_atlas > budget:
        raise BakeRefused(f"the atlases ({texels} texels) would need about {_human_bytes(need_atlas)}, "
                          f"more than the {_human_bytes(budget)} available; lower the resolution")
    need_table = table_bytes(directions, texels)
    if need_table + need_atlas > budget:
        raise BakeRefused(f"the visibility table ({directions} directions x up to {texels} texels) "
                          f"could need {_human_bytes(need_table)}, more than the {_human_bytes(budget - need_atlas)} "
                          f"available; lower the directions or the resolution")


def usable_lights(lights, warnings: list[str]):
    """The lamps that can be baked; refuse the bake for strengths no output could hold."""
    usable = []
    for light in lights:
        strength = float(light.strength)
        if not np.isfinite(strength) or abs(strength) > tol.MAX_LIGHT_STRENGTH:
            raise BakeRefused(f"light {light.name!r}: strength {strength:g} is not a usable number; set it to a "
                              f"finite value of at most {tol.MAX_LIGHT_STRENGTH:g}")
        color = np.asarray(light.color, np.float64)
        if not np.all(np.isfinite(color)):
            raise BakeRefused(f"light {light.name!r}: its colour is not finite; set its colour again")
        if strength < 0 or np.any(color < 0):
            warnings.append(f"light {light.name!r}: negative light is not supported (Cycles subtracts it); "
                            "it was left out")
            continue
        if strength == 0 or not np.any(color > 0):
            continue
        usable.append(light)
    return usable


class _Stages:
    """Wall time per stage and the progress callback, in one place."""

    def __init__(self, progress):
        self.progress = progress
        self.times: dict[str, float] = {}
        self._name = None
        self._start = 0.0
        self._moved = 0.0
        self.passes: list[dict] = []

    def start(self, name: str) -> None:
        self.stop()
        self._name = name
        self._start = time.perf_counter()
        self.report(0.0)

    def record_pass(self, name: str, device: str, seconds: float) -> None:
        """One transport pass (a direct-light pass, a gather) for the report."""
        self.passes.append({"pass": name, "device": device, "seconds": round(seconds, 4)})

    def book(self, name: str, seconds: float) -> None:
        """Count ``seconds`` of the running stage as ``name`` (one progress bar, two timings)."""
        self.times[name] = self.times.get(name, 0.0) + seconds
        self._moved += seconds

    def expect(self, name: str, share: float) -> None:
        """Tell the progress callback, if it has an ``expect`` method, that stage ``name``
        will do ``share`` of the work it was planned with (0: none, e.g. a valid cache)."""
        expect = getattr(self.progress, "expect", None)
        if expect is not None:
            expect(name, float(share))

    def report(self, fraction: float) -> None:
        if self.progress is not None and self._name is not None:
            self.progress(self._name, float(fraction))

    def stop(self) -> None:
        if self._name is not None:
            elapsed = time.perf_counter() - self._start - self._moved
            self.times[self._name] = self.times.get(self._name, 0.0) + elapsed
            self._name = None
            self._moved = 0.0


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
    stage_seconds: dict
    skipped: list
    warnings: list
    table_key: str = ""
    visibility_rays: int = 0  # rays this preparation traced for the table (0 on a cache hit)
    cache: VisibilityCache | None = None
    cache_status: CacheStatus | None = None
    # The gather implementation: core.transport.gather, or a twin with the same
    # contract (gpu_shaders.gather.gather) chosen by the Blender side.
    gather: Callable = gather
    gather_device: str = "cpu"
    lamp_irradiance: Callable = lamp_irradiance  # core.lighting.lamp_irradiance or a twin
    direct_device: str = "cpu"
    accumulate_passes: Callable = accumulate_passes  # core.lighting.accumulate_passes or a twin
    accumulate_device: str = "cpu"
    dilate: Callable = dilate  # core.raster.dilate or a twin
    dilate_device: str = "cpu"
    dilation_seconds: float = 0.0
    dilation_calls: int = 0
    _gather_scale: np.ndarray | None = None
    _shadow_regions: ShadowRegions | None = None
    _distant_fractions: ShadowFractions | None = None

    def shadow_regions(self) -> ShadowRegions:
        if self._shadow_regions is None:
            self._shadow_regions = ShadowRegions(self.directions, self.settings.shadow_regions)
        return self._shadow_regions

    def distant_fractions(self) -> ShadowFractions:
        """The paper's shadow fractions for distant lights: computed once, shared by every sun."""
        if self._distant_fractions is None:
            self._distant_fractions = shadow_fractions(self.table, self.shadow_regions())
        return self._distant_fractions

    def gather_scale(self) -> np.ndarray:
        """Per-sample gather normalisation (K,), computed once per preparation."""
        if self._gather_scale is None:
            self._gather_scale = gather_normalisation(self.table, self.normal)
        return self._gather_scale

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
        parts = [self.table_key, self.bounces_needed(), s.shadows, s.shadow_regions, s.area_light_samples,
                 s.emitter_samples, max(s.margin, 2), s.vertex_lookup, self.albedo, self.normal,
                 np.where(emitting[:, None], self.emission, 0.0), group.world, group.emitting,
                 np.array([m.output for m in self.meshes])]
        for index in np.nonzero(group.emitting)[0]:
            parts += [np.asarray(m.emission, np.float64) for m in self.meshes[index].materials if m is not None]
        for light in group.lights:
            parts += light_key_parts(light)
        return arrays_key(*parts)

    def to_atlas(self, values: np.ndarray) -> np.ndarray:
        """Per-sample values (K, C) as the packed, gutter-dilated radiance atlas (size, C)."""
        margin = max(self.settings.margin, 2)
        images = []
        for samples, a, b in zip(self.object_samples, self.sample_offset[:-1], self.sample_offset[1:]):
            image = np.zeros((samples.height * samples.width, values.shape[1]), np.float32)
            image[samples.pixel] = values[a:b]
            image = image.reshape(samples.height, samples.width, values.shape[1])
            if not samples.coverage.all():  # a vertex-mode object covers its whole one-row "atlas"
                image, _ = self.timed_dilate(image, samples.coverage, margin)
            images.append(image)
        return self.layout.pack(images)

    def timed_dilate(self, image, coverage, margin):
        """``self.dilate`` with its calls and time counted for the report's passes."""
        started = time.perf_counter()
        result = self.dilate(image, coverage, margin)
        self.dilation_seconds += time.perf_counter() - started
        self.dilation_calls += 1
        return result



def prepare(scene: Scene, settings: BakeSettings, progress=None, table_needed: bool | None = None,
            cache: VisibilityCache | None = None, require_cached_table: bool = False) -> Prepared:
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
    """
    settings.validate()
    # A vertex-mode object has at most one sample per triangle corner.
    check_budget([m.resolution if m.mode == "atlas" else (3 * len(m.triangles), 1) for m in scene.meshes],
                 settings.directions)
    stages = _Stages(progress)
    skipped: list[str] = []
    warnings: list[str] = []

    stages.start("samples")
    meshes = []
    for mesh in scene.meshes:
        if len(mesh.triangles) == 0:
            warnings.append(f"object {mesh.name!r} has no faces and was skipped")
            continue
        meshes.append(mesh)
    if not any(m.output for m in meshes):
        raise BakeRefused("there is no mesh with faces to bake; select meshes that have faces")
    object_samples: list[ObjectSamples] = []
    for index, mesh in enumerate(meshes):
        object_samples.append(build_vertex_samples(mesh) if mesh.mode == "vertex" else build_samples(mesh))
        stages.report((index + 1) / len(meshes))
    for mesh, samples in zip(meshes, object_samples):
        if len(samples) == 0:
            warnings.append(f"object {mesh.name!r}: no texel centre falls inside its UV layout at "
                            f"{mesh.resolution[0]}x{mesh.resolution[1]}; raise the resolution")
        if samples.uv_overlap_texels:
            warnings.append(f"object {mesh.name!r}: {samples.uv_overlap_texels} texels are covered by "
                            "overlapping UV islands; each was given to one triangle")
    counts = np.array([len(s) for s in object_samples], np.int64)
    position = np.concatenate([s.position for s in object_samples])
    geometric = np.concatenate([s.geometric_normal for s in object_samples])
    emission = np.concatenate([s.emission for s in object_samples]).astype(np.float64)
    directions = direction_set(settings.directions, settings.rotate, settings.seed)
    if table_needed is None:
        table_needed = (settings.bounces > 0 or bool(np.any(emission > 0)) or "ao" in settings.passes
                        or has_light(scene.world)
                        or (settings.shadows == "fractions" and bool(scene.lights)))

    ray_scene = RayScene([(m.positions, m.triangles) for m in meshes], settings.threads)
    sample_offset = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    object_keys = [object_key(m) for m in meshes]
    key = table_key(object_keys, settings)
    table = None
    status = CacheStatus() if cache is None else None
    visibility_rays = 0
    if table_needed:
        stages.start("cache" if cache is not None else "visibility")
        table, status, visibility_rays = _cached_or_traced_table(
            meshes, object_keys, key, settings, directions, position, geometric, sample_offset, ray_scene, cache,
            require_cached_table, stages, skipped, warnings)
    else:
        stages.expect("visibility", 0.0)
        stages.expect("cache", 0.0)
        skipped.append("visibility table: no pass needs it (no bounces, emission, world, AO or shadow fractions)")
        status = status or CacheStatus(state="unused", message="no pass needs the visibility table")
    stages.stop()

    return Prepared(
        settings=settings, meshes=meshes, object_samples=object_samples,
        sample_offset=np.concatenate([[0], np.cumsum(counts)]), position=position,
        normal=np.concatenate([s.normal for s in object_samples]), geometric=geometric,
        albedo=np.concatenate([s.albedo for s in object_samples]).astype(np.float64), emission=emission,
        layout=AtlasLayout.from_sizes([(s.width, s.height) for s in object_samples],
                                      [getattr(s, "corner_sample", None) for s in object_samples],
                                      settings.vertex_lookup == "nearest"), directions=directions,
        ray_scene=ray_scene, origins=offset_ray_origins(position, geometric), table=table,
        stage_seconds=dict(stages.times), skipped=skipped, warnings=warnings, table_key=key,
        visibility_rays=visibility_rays, cache=cache, cache_status=status)


def _cached_or_traced_table(meshes, object_keys, key, settings, directions, position, geometric, sample_offset,
                            ray_scene, cache, require_cached_table, stages, skipped, warnings):
    """The table from the cache if it is valid, updated if only some objects changed, else traced.

    Returns (table, CacheStatus, rays traced against the scene).
    """
    names = [m.name for m in meshes]
    status = CacheStatus()
    meta = None
    triangle_counts = np.array([len(m.triangles) for m in meshes], np.int64)
    triangle_offset = np.concatenate([[0], np.cumsum(triangle_counts)[:-1]]).astype(np.int64)
    # Vertex-mode objects have no bake UV map: their hits keep barycentrics instead.
    corner_uv = np.concatenate([m.uv_maps[m.bake_uv_map] if m.mode == "atlas" else np.zeros((len(m.triangles), 3, 2))
                                for m in meshes]).astype(np.float32)
    vertex_object = np.array([m.mode == "vertex" for m in meshes], bool)
    all_face_normals = np.concatenate([face_normals(m.positions, m.triangles)[0] for m in meshes])

    def trace(report):
        return trace_table(ray_scene, directions, position, geometric, corner_uv, triangle_offset,
                           all_face_normals, settings.chunk_rays, report, vertex_object)

    def save(table):
        try:
            status.bytes_on_disk = cache.save_table(settings, key, names, object_keys, sample_offset, table)
        except OSError as error:
            warnings.append(f"visibility cache {status.path} could not be written ({error}); the next bake "
                            "traces the table again")

    def damaged(error):
        """The deferred table's large arrays are damaged: trace them again (never for a relight)."""
        if require_cached_table:
            raise BakeRefused(f"the cached visibility is damaged ({error}); bake first")
        status.state, status.message = "corrupt", f"the cache file cannot be trusted: {error}"
        warnings.append(f"visibility cache {status.path}: {error}; it was rebuilt")
        fresh = trace(None)
        save(fresh)
        return {name: getattr(fresh, name) for name in ("hit_object", "hit_uv", "hit_distance", "hit_triangle")}

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
                if not np.array_equal(table.directions, directions):
                    raise CorruptCache("its directions do not match its key")
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
            stages.report(0.5)  # read; writing the updated table is the other half
            stages.start("visibility")
            changed_scene = RayScene([(meshes[i].positions, meshes[i].triangles) for i in changed], settings.threads)
            table, counts = update_table(old_table, old.sample_offset, ray_scene, changed_scene, changed, directions,
                                         position, geometric, sample_offset, corner_uv, triangle_offset,
                                         all_face_normals, settings.chunk_rays, stages.report, vertex_object)
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


def _read_deferred_table(p: Prepared, stages: _Stages, needed: bool) -> None:
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


def relight(prepared: Prepared, lights, world, progress=None) -> BakeResult:
    """Direct light, gathers and pass images for ``lights`` and ``world`` over a prepared scene.

    Traces only shadow rays (exact shadows, sampled emitters); never the table again.
    """
    return relight_many(prepared, [(lights, world)], progress)[0]


def relight_many(prepared: Prepared, lightings, progress=None) -> list[BakeResult]:
    """:func:`relight` for several lightings at once: their light groups share the gathers.

    Parameters
    ----------
    lightings : list of (lights, World)

    With a cache, a light group whose lighting, materials and settings are unchanged
    since an earlier single relight is read back instead of transported again.
    """
    p = prepared
    settings = p.settings
    stages = _Stages(progress)
    wants = set(settings.passes)
    has_emission = bool(np.any(p.emission > 0))
    lighting_wanted = bool(wants & set(LIGHTING_PASSES))
    plans = []  # per lighting: warnings, skipped, groups
    for lights, world in lightings:
        warnings = list(p.warnings)
        skipped = list(p.skipped)
        lights = usable_lights(lights, warnings)
        world_group = getattr(world, "light_group", "")
        radiance = world_radiance(world, p.directions)
        needs_table = (settings.bounces > 0 or has_emission or bool(np.any(radiance > 0)) or "ao" in wants
                       or (bool(lights) and settings.shadows == "fractions"))
        if p.table is None and needs_table:
            raise BakeRefused("this scene was prepared without a visibility table, which these lights, world "
                              "or passes need; prepare it again with the table")
        if settings.shadows == "exact":
            skipped.append("shadow fractions: shadows are exact")
        if settings.bounces == 0:
            skipped.append("bounce gathers: bounces = 0")
        elif p.bounces_needed() == 0:
            skipped.append(f"{settings.bounces} bounce gathers: no requested pass contains indirect light")
        if not has_emission and not np.any(radiance > 0):
            skipped.append("gather of emitted light: the scene has no emission and no world light")
        if p.output_samples() is not None and (p.bounces_needed() > 0 or has_emission or np.any(radiance > 0)):
            occluder_samples = len(p.position) - len(p.output_samples())
            skipped.append(f"last gather of {occluder_samples} texels of objects that only occlude and reflect: "
                           "nothing reads it")
        groups = light_groups(p, lights, radiance, world_group, settings.light_groups) if lighting_wanted else []
        if not lighting_wanted:
            skipped.append("direct light and gathers: no lighting pass was asked for")
        plans.append({"lights": lights, "warnings": warnings, "skipped": skipped, "groups": groups})

    stages.start("transport")
    # Every group of every lighting: read back if cached, else transported in batches.
    transported: dict[tuple[int, str], Transported] = {}
    pending = []
    for index, plan in enumerate(plans):
        plan["reused"] = []
        for group in plan["groups"]:
            key = p.lighting_key(group) if p.cache is not None else None
            cached = p.cache.load_lighting(settings, key) if key else None
            if cached is not None:
                transported[index, group.name] = Transported(cached["direct"], cached["gathered"])
                plan["reused"].append(group.name)
            else:
                pending.append((index, group, key))
    total_groups = sum(len(plan["groups"]) for plan in plans)
    if total_groups:
        stages.expect("transport", len(pending) / total_groups)
    _read_deferred_table(p, stages, needed=bool(pending) or "ao" in wants)
    gathers = 0
    batches = [pending[i:i + MAX_GROUPS_PER_GATHER] for i in range(0, len(pending), MAX_GROUPS_PER_GATHER)]
    shared_skips: list[str] = []
    for number, batch in enumerate(batches):
        results, count = transport_groups(p, [group for _, group, _ in batch], stages, shared_skips,
                                          (number / len(batches), (number + 1) / len(batches)))
        gathers += count
        for (index, group, key), result in zip(batch, results):
            transported[index, group.name] = result
            # Interactive relighting revisits its lightings; a batch of setups rarely
            # does, and would fill the cache with results nobody reads again.
            if key and len(lightings) == 1:
                try:
                    p.cache.save_lighting(settings, key, {"direct": result.direct, "gathered": result.gathered})
                except OSError as error:
                    plans[index]["warnings"].append(f"lighting cache in {p.cache.folder} could not be written "
                                                    f"({error.strerror or error}); nothing else is affected")

    stages.start("outputs")
    per_lighting = []
    for index, plan in enumerate(plans):
        parts = {name: transported[i, name] for i, name in transported if i == index}
        started = time.perf_counter()
        per_pass = p.accumulate_passes(p.albedo, wants, parts, settings.light_groups)
        if parts:
            stages.record_pass(f"accumulation of passes ({len(parts)} groups)", p.accumulate_device,
                               time.perf_counter() - started)
        if "ao" in wants:
            per_pass["ao"] = np.repeat(ambient_occlusion(p.table, p.normal, p.gather_scale())[:, None], 3, axis=1)
        per_lighting.append((per_pass, parts))

    images = []
    output_meshes = [(i, m) for i, m in enumerate(p.meshes) if m.output]
    for per_pass, _ in per_lighting:
        objects = []
        for index, mesh in output_meshes:
            samples = p.object_samples[index]
            a, b = p.sample_offset[index], p.sample_offset[index + 1]
            result = ObjectResult(mesh.name, samples.width, samples.height, len(samples))
            if mesh.mode == "vertex":
                result.domain = samples.domain
                for name, values in per_pass.items():
                    result.images[name] = element_colors(values[a:b], samples.element_sample)
            else:
                for name, values in per_pass.items():
                    result.images[name] = sample_image(values[a:b], samples.pixel, samples.coverage,
                                                       settings.margin, p.timed_dilate)
            objects.append(result)
        images.append(objects)
        stages.report(len(images) / len(per_lighting))
    stages.stop()

    if p.dilation_calls:
        stages.record_pass(f"gutter dilation ({p.dilation_calls} images)", p.dilate_device, p.dilation_seconds)
        p.dilation_seconds, p.dilation_calls = 0.0, 0
    results = [BakeResult(objects=objects, report=_report(p, plan, parts, stages.times, gathers, shared_skips,
                                                          len(lightings)))
               for objects, plan, (_, parts) in zip(images, plans, per_lighting)]
    for result, plan in zip(results, plans):
        result.report["passes"] = list(stages.passes)
        _report_tessellation(p, plan["lights"], result)
    return results


def _report_tessellation(p: Prepared, lights, result: BakeResult) -> None:
    """Per vertex-mode object: triangles whose light varies inside them (a warning if any)."""
    report = result.report
    by_name = {o.name: o for o in result.objects}
    for index, check in check_vertex_objects(p, lights).items():
        entry = report["objects"][index]
        if entry["name"] in by_name:
            by_name[entry["name"]].coarse_triangles = check.flagged_triangles
        entry["under_tessellated_triangles"] = check.flagged
        entry["under_tessellated_area_share"] = round(check.area_share, 4)
        if check.flagged:
            report["warnings"].append(
                f"object {entry['name']!r}: {check.flagged} of {check.triangles} triangles "
                f"({check.area_share:.0%} of its area) have direct light varying inside them by up to "
                f"{check.worst:.0%}, which its vertices cannot show; subdivide it or bake it as an atlas")


def _report(p: Prepared, plan: dict, parts: dict, times: dict, gathers: int, shared_skips: list,
            lightings: int) -> dict:
    """The bake report of one lighting (times and gathers are those of the whole call)."""
    table = p.table
    skipped, warnings = plan["skipped"] + shared_skips, plan["warnings"]
    # A cached table found damaged when it was read (after the plan was made).
    warnings += [w for w in p.warnings if w not in warnings]
    if plan["reused"]:
        names = "all lights" if plan["reused"] == ["all"] else ", ".join(repr(n) for n in plan["reused"])
        skipped.append(f"transport of {names}: lighting, materials and settings unchanged since a cached bake")
    counts = np.diff(p.sample_offset)
    empty = sum(s.width * s.height for s in p.object_samples) - int(counts.sum())
    skipped.append(f"{empty} atlas texels outside every UV island: not sampled, filled by dilation only")
    if table is not None:
        skipped.append(f"{table.rays_below_horizon} directions below a texel's horizon: not traced")
    occluders = [m.name for m in p.meshes if not m.output]
    if occluders:
        skipped.append(f"outputs of {len(occluders)} objects that only occlude and reflect: {', '.join(occluders)}")
    cache = asdict(p.cache_status) if p.cache_status is not None else {"state": "off"}
    cache["lighting_reused"] = list(plan["reused"])
    report = {
        "settings": asdict(p.settings),
        "objects": [
            {"name": m.name, "output": m.output, "uv_map": m.bake_uv_map, "resolution": list(m.resolution),
             "texels": int(counts[i]), "triangles": int(len(m.triangles))}
            for i, m in enumerate(p.meshes)
        ],
        "stage_seconds": {k: round(v, 4) for k, v in {**p.stage_seconds, **times}.items()},
        "lightings_transported_together": lightings,
        "rays": {
            "visibility_cast": int(p.visibility_rays),
            "visibility_in_table": int(table.rays_cast) if table else 0,
            "visibility_skipped_below_horizon": int(table.rays_below_horizon) if table else 0,
            "backface_hits": int(table.backface_hits) if table else 0,
            "shadow_rays": int(sum(t.shadow_rays for t in parts.values())),
            "emitter_rays": int(sum(t.emitter_rays for t in parts.values())),
        },
        "light_groups": [g.name for g in plan["groups"]] if p.settings.light_groups else [],
        "emitters_sampled": sorted({n for t in parts.values() for n in t.emitters_sampled}),
        "gathers": int(gathers),
        "table_bytes": int(table.nbytes) if table else 0,
        "cache": cache,
        "skipped": skipped,
        "warnings": warnings,
    }
    if table is not None and table.backface_hits:
        buried = table.buried()
        for entry, a, b in zip(report["objects"], p.sample_offset[:-1], p.sample_offset[1:]):
            entry["buried_texels"] = int(np.count_nonzero(buried[a:b]))
        visible = ~buried
        share = table.backface_per_sample[visible].sum() / max(int(table.traced_per_sample[visible].sum()), 1)
        if share > 0.01:
            warnings.append(f"{share:.1%} of the rays from visible texels hit the back of a face; backs reflect "
                            "no light (single-sided geometry or flipped normals)")
    return report


def bake(scene: Scene, settings: BakeSettings, progress=None) -> BakeResult:
    """Bake every output object of ``scene``: :func:`prepare`, then :func:`relight`.

    Parameters
    ----------
    scene : Scene
        Meshes with a valid bake UV map each, lights and world.
    settings : BakeSettings
    progress : callable(stage: str, fraction: float) or None
        Called often; raise :class:`Cancelled` in it to stop.
    """
    return relight(prepare(scene, settings, progress), scene.lights, scene.world, progress)
