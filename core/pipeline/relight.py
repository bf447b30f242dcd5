"""The bake: samples -> visibility table -> shadow fractions -> transport -> pass images.

:func:`bake` is the one entry point the operators, the command line, the tests and
the benchmarks share. It reports progress through a callback that may raise
:class:`Cancelled` to stop between batches.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import BakeRefused
from ..lights.lamps import usable_lights
from .prepare import Prepared, prepare, read_deferred_table
from .progress import Stages

from ..lights.environment import world_radiance
from ..settings import LIGHTING_PASSES
from ..transport.groups import (MAX_GROUPS_PER_GATHER, Transported, light_groups, transport_groups)
from ..outputs.diagnostics import check_vertex_objects
from ..settings import BakeSettings
from ..scene import Scene
from ..outputs.images import sample_image
from ..transport.gather import ambient_occlusion


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
    # Vertex mode: triangles whose light varies inside them (core.outputs.diagnostics), to refine.
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
    stages = Stages(progress)
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
    read_deferred_table(p, stages, needed=bool(pending) or "ao" in wants)
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
