"""The bake: samples -> visibility table -> shadow fractions -> transport -> pass images.

:func:`bake` is the one entry point the operators, the command line, the tests and
the benchmarks share. It reports progress through a callback that may raise
:class:`Cancelled` to stop between batches.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .directions import ShadowRegions, direction_set
from .environment import world_radiance
from .emitters import emitter_irradiance, find_emitters, sampled_directly
from .lights import light_contributions
from .raster import dilate
from .rays import RayScene, offset_ray_origins
from .samples import ObjectSamples, build_samples, face_normals
from .scene import BakeSettings, Scene
from .shadows import shadow_fractions
from .images import sample_image
from .transport import AtlasLayout, ambient_occlusion, gather, gather_normalisation
from .visibility import table_bytes, trace_table
from . import tolerances as tol


class Cancelled(Exception):
    """Raised by a progress callback to stop a bake; nothing has been written."""


class BakeRefused(ValueError):
    """The bake cannot run with these inputs; the message says why and what to change."""


@dataclass
class ObjectResult:
    """Pass images of one output object: pass name -> (H, W, 4) float32, bottom-up."""

    name: str
    width: int
    height: int
    samples: int
    images: dict[str, np.ndarray] = field(default_factory=dict)


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
            raise BakeRefused(f"light {light.name!r}: strength {strength:g} is not a usable number "
                              f"(at most {tol.MAX_LIGHT_STRENGTH:g})")
        color = np.asarray(light.color, np.float64)
        if not np.all(np.isfinite(color)):
            raise BakeRefused(f"light {light.name!r}: its colour is not finite")
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

    def start(self, name: str) -> None:
        self.stop()
        self._name = name
        self._start = time.perf_counter()
        self.report(0.0)

    def report(self, fraction: float) -> None:
        if self.progress is not None and self._name is not None:
            self.progress(self._name, float(fraction))

    def stop(self) -> None:
        if self._name is not None:
            self.times[self._name] = self.times.get(self._name, 0.0) + time.perf_counter() - self._start
            self._name = None


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

    def to_atlas(self, values: np.ndarray) -> np.ndarray:
        """Per-sample values (K, 3) as the packed, gutter-dilated radiance atlas."""
        margin = max(self.settings.margin, 2)
        images = []
        for samples, a, b in zip(self.object_samples, self.sample_offset[:-1], self.sample_offset[1:]):
            image = np.zeros((samples.height * samples.width, 3), np.float32)
            image[samples.pixel] = values[a:b]
            image = image.reshape(samples.height, samples.width, 3)
            image, _ = dilate(image, samples.coverage, margin)
            images.append(image)
        return self.layout.pack(images)




def prepare(scene: Scene, settings: BakeSettings, progress=None, table_needed: bool | None = None) -> Prepared:
    """Samples and the visibility table of ``scene``'s meshes.

    Parameters
    ----------
    table_needed : bool or None
        None: trace the table only if ``scene``'s own lights, world and materials
        need it. True: always (for relighting with lights not known yet).
    """
    settings.validate()
    check_budget([m.resolution for m in scene.meshes], settings.directions)
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
        raise BakeRefused("there is no mesh with faces to bake")
    object_samples: list[ObjectSamples] = []
    for index, mesh in enumerate(meshes):
        object_samples.append(build_samples(mesh))
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
                        or bool(np.any(world_radiance(scene.world, directions) > 0))
                        or (settings.shadows == "fractions" and bool(scene.lights)))

    ray_scene = RayScene([(m.positions, m.triangles) for m in meshes], settings.threads)
    table = None
    if table_needed:
        stages.start("visibility")
        triangle_counts = np.array([len(m.triangles) for m in meshes], np.int64)
        triangle_offset = np.concatenate([[0], np.cumsum(triangle_counts)[:-1]]).astype(np.int64)
        corner_uv = np.concatenate([m.uv_maps[m.bake_uv_map] for m in meshes]).astype(np.float32)
        all_face_normals = np.concatenate([face_normals(m.positions, m.triangles)[0] for m in meshes])
        table = trace_table(ray_scene, directions, position, geometric, corner_uv, triangle_offset,
                            all_face_normals, settings.chunk_rays, stages.report)
    else:
        skipped.append("visibility table: no pass needs it (no bounces, emission, world, AO or shadow fractions)")
    stages.stop()

    return Prepared(
        settings=settings, meshes=meshes, object_samples=object_samples,
        sample_offset=np.concatenate([[0], np.cumsum(counts)]), position=position,
        normal=np.concatenate([s.normal for s in object_samples]), geometric=geometric,
        albedo=np.concatenate([s.albedo for s in object_samples]).astype(np.float64), emission=emission,
        layout=AtlasLayout.from_sizes([(s.width, s.height) for s in object_samples]), directions=directions,
        ray_scene=ray_scene, origins=offset_ray_origins(position, geometric), table=table,
        stage_seconds=dict(stages.times), skipped=skipped, warnings=warnings)


def relight(prepared: Prepared, lights, world, progress=None) -> BakeResult:
    """Direct light, gathers and pass images for ``lights`` and ``world`` over a prepared scene.

    Traces only shadow rays (exact shadows, sampled emitters); never the table again.
    """
    p = prepared
    settings = p.settings
    stages = _Stages(progress)
    skipped = list(p.skipped)
    warnings = list(p.warnings)
    lights = usable_lights(lights, warnings)
    table = p.table
    world = world_radiance(world, p.directions)
    has_emission = bool(np.any(p.emission > 0))
    has_world = bool(np.any(world > 0))
    wants = set(settings.passes)
    needs_gather = settings.bounces > 0 or has_emission or has_world
    uses_fractions = bool(lights) and settings.shadows == "fractions"
    if table is None and (needs_gather or "ao" in wants or uses_fractions):
        raise BakeRefused("this scene was prepared without a visibility table, which these lights, world "
                          "or passes need; prepare it again with the table")

    stages.start("direct")
    regions = ShadowRegions(p.directions, settings.shadow_regions) if uses_fractions else None
    distant_fractions = None
    # E_d: everything that reaches a sample without a bounce (lamps, sampled emitters,
    # gathered emission and world). Bounces then only ever carry reflected light.
    direct_irradiance = np.zeros((len(p.position), 3))
    shadow_rays = 0
    for light_index, light in enumerate(lights):
        fractions = None
        if regions is not None:
            if light.kind == "SUN":
                if distant_fractions is None:
                    distant_fractions = shadow_fractions(table, regions)
                fractions = distant_fractions
            else:
                light_distance = np.linalg.norm(p.position - np.asarray(light.position, np.float64), axis=1)
                fractions = shadow_fractions(table, regions, light_distance)
        for part in light_contributions(light, p.position, p.normal, settings.area_light_samples):
            above = np.einsum("kd,kd->k", part.to_light, p.geometric) > 0.0
            lit = above & np.any(part.irradiance > 0, axis=1)
            if fractions is not None:
                visibility = np.where(lit, fractions.visibility(part.to_light), 0.0)
            else:
                visibility = lit.astype(np.float64)
                rays = np.nonzero(lit)[0]
                if len(rays):
                    distance = part.distance[rays]
                    limit = np.where(np.isfinite(distance), distance * (1.0 - tol.SHADOW_RAY_SHORTEN), np.inf)
                    blocked = p.ray_scene.occluded(p.origins[rays], part.to_light[rays], limit.astype(np.float32))
                    visibility[rays[blocked]] = 0.0
                    shadow_rays += len(rays)
            direct_irradiance += part.irradiance * visibility[:, None]
        stages.report((light_index + 1) / (len(lights) + 1))
    if settings.shadows == "exact":
        skipped.append("shadow fractions: shadows are exact")

    exclude = None
    emitters = find_emitters(p.meshes, settings.emitter_samples) if needs_gather else []
    emitter_rays = 0
    for emitter in emitters:
        direct = sampled_directly(emitter, p.position, settings.directions)
        if not np.any(direct):
            continue
        if exclude is None:
            exclude = np.zeros((len(p.position), len(p.meshes)), bool)
        exclude[:, emitter.object_index] = direct
        chosen = np.nonzero(direct)[0]
        irradiance, rays = emitter_irradiance(emitter, p.position[chosen], p.normal[chosen], p.geometric[chosen],
                                              p.origins[chosen], p.ray_scene)
        direct_irradiance[chosen] += irradiance
        emitter_rays += rays
    stages.report(1.0)

    gathered = np.zeros_like(direct_irradiance)
    gathers = 0
    scale = None
    if needs_gather:
        stages.start("transport")
        scale = gather_normalisation(table, p.normal)
        total = settings.bounces + 1

        def step_progress(step):
            return lambda fraction: stages.report((step + fraction) / total)

        if has_emission or has_world:
            direct_irradiance += gather(table, p.normal, scale, p.layout, p.to_atlas(p.emission), world,
                                        step_progress(0), exclude, settings.threads)
            gathers += 1
        else:
            skipped.append("gather of emitted light: the scene has no emission and no world light")
        for bounce in range(1, settings.bounces + 1):
            reflected = p.albedo / np.pi * (direct_irradiance + gathered)
            gathered = gather(table, p.normal, scale, p.layout, p.to_atlas(reflected), np.zeros(3),
                              step_progress(bounce), threads=settings.threads)
            gathers += 1
    else:
        skipped.append("indirect gathers: bounces = 0 and nothing emits")

    stages.start("outputs")
    per_pass: dict[str, np.ndarray] = {}
    irradiance = direct_irradiance + gathered
    if "lighting" in wants:
        per_pass["lighting"] = p.albedo / np.pi * irradiance
    if "direct" in wants:
        per_pass["direct"] = p.albedo / np.pi * direct_irradiance
    if "indirect" in wants:
        per_pass["indirect"] = p.albedo / np.pi * gathered
    if "irradiance" in wants:
        per_pass["irradiance"] = irradiance / np.pi
    if "ao" in wants:
        if scale is None:
            scale = gather_normalisation(table, p.normal)
        per_pass["ao"] = np.repeat(ambient_occlusion(table, p.normal, scale)[:, None], 3, axis=1)

    results = []
    output_meshes = [(i, m) for i, m in enumerate(p.meshes) if m.output]
    for done, (index, mesh) in enumerate(output_meshes):
        samples = p.object_samples[index]
        a, b = p.sample_offset[index], p.sample_offset[index + 1]
        result = ObjectResult(mesh.name, samples.width, samples.height, len(samples))
        for name in settings.passes:
            result.images[name] = sample_image(per_pass[name][a:b], samples.pixel, samples.coverage, settings.margin)
        results.append(result)
        stages.report((done + 1) / len(output_meshes))
    stages.stop()

    counts = np.diff(p.sample_offset)
    empty = sum(s.width * s.height for s in p.object_samples) - int(counts.sum())
    skipped.append(f"{empty} atlas texels outside every UV island: not sampled, filled by dilation only")
    if table is not None:
        skipped.append(f"{table.rays_below_horizon} directions below a texel's horizon: not traced")
    occluders = [m.name for m in p.meshes if not m.output]
    if occluders:
        skipped.append(f"outputs of {len(occluders)} objects that only occlude and reflect: {', '.join(occluders)}")
    report = {
        "settings": asdict(settings),
        "objects": [
            {"name": m.name, "output": m.output, "uv_map": m.bake_uv_map, "resolution": list(m.resolution),
             "texels": int(counts[i]), "triangles": int(len(m.triangles))}
            for i, m in enumerate(p.meshes)
        ],
        "stage_seconds": {k: round(v, 4) for k, v in {**p.stage_seconds, **stages.times}.items()},
        "rays": {
            "visibility_cast": int(table.rays_cast) if table else 0,
            "visibility_skipped_below_horizon": int(table.rays_below_horizon) if table else 0,
            "backface_hits": int(table.backface_hits) if table else 0,
            "shadow_rays": int(shadow_rays),
            "emitter_rays": int(emitter_rays),
        },
        "emitters_sampled": [p.meshes[e.object_index].name for e in emitters],
        "gathers": gathers,
        "table_bytes": int(table.nbytes) if table else 0,
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
    return BakeResult(objects=results, report=report)


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
