"""Relighting: lights -> direct light and gathers on a backend -> pass images.

:func:`relight_many` carries any number of lightings over one :class:`Prepared` scene
(their light groups share the gathers); :func:`bake` is prepare then relight, the one
entry point the tests and the benchmarks share. Progress goes through a callback that
may raise :class:`core.errors.Cancelled` to stop between batches.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..distributed.split import SplitTable
from ..errors import BakeRefused
from ..lights.environment import world_radiance
from ..lights.lamps import usable_lights
from ..outputs.images import sample_image
from ..outputs.report import lighting_report, report_seams, report_tessellation
from ..outputs.seams import find_seams, stitch
from ..scene import Scene
from ..settings import LIGHTING_PASSES, BakeSettings
from ..transport.contract import TransportBackend
from ..transport.cpu import CPU_BACKEND
from ..transport.groups import Transported, light_groups
from ..visibility.rays import default_threads
from .prepare import Prepared, prepare, read_deferred_table
from .progress import Stages
from .transport import transport_pending


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


class TimedDilation:
    """A backend's dilation with its calls and time counted, for the report's passes."""

    def __init__(self, backend: TransportBackend):
        self.backend = backend
        self.calls = 0
        self.seconds = 0.0

    def __call__(self, image, coverage, margin):
        started = time.perf_counter()
        result = self.backend.dilate(image, coverage, margin)
        self.seconds += time.perf_counter() - started
        self.calls += 1
        return result


@dataclass
class BakeResult:
    objects: list[ObjectResult]
    report: dict


def relight(prepared: Prepared, lights, world, progress=None, backend: TransportBackend = CPU_BACKEND) -> BakeResult:
    """Direct light, gathers and pass images for ``lights`` and ``world`` over a prepared scene.

    Traces only shadow rays (exact shadows, sampled emitters); never the table again.
    """
    return relight_many(prepared, [(lights, world)], progress, backend)[0]


def relight_many(prepared: Prepared, lightings, progress=None,
                 backend: TransportBackend = CPU_BACKEND) -> list[BakeResult]:
    """:func:`relight` for several lightings at once: their light groups share the gathers.

    Parameters
    ----------
    lightings : list of (lights, World)

    With a cache, a light group whose lighting, materials and settings are unchanged
    since an earlier single relight is read back instead of transported again.
    """
    p = prepared
    settings = p.settings
    if isinstance(p.table, SplitTable) and backend.name != "cpu":
        raise BakeRefused(f"a table held by sample rows is read by the CPU kernels where it is kept, not by the "
                          f"{backend.name} passes: bake on the CPU device")
    stages = Stages(progress)
    wants = set(settings.passes)
    has_emission = bool(np.any(p.emission > 0))
    lighting_wanted = bool(wants & set(LIGHTING_PASSES))
    plans = []  # per lighting: warnings, skipped, groups
    for lights, world in lightings:
        warnings = list(p.warnings)
        skipped = list(p.skipped)
        world_group = getattr(world, "light_group", "")
        # The world's sun discs are lamps of the world's light group.
        suns = [replace(sun, group=world_group or "world") for sun in getattr(world, "suns", ())]
        lights = usable_lights(list(lights) + suns, warnings)
        # Per interleaved rotation (G, N, 3) where the set is rotated per texel.
        directions = p.world_directions()
        radiance = world_radiance(world, directions.reshape(-1, 3)).reshape(directions.shape)
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
        groups = light_groups(p.meshes, p.emission, p.sample_offset, lights, radiance, world_group,
                              settings.light_groups) if lighting_wanted else []
        if not lighting_wanted:
            skipped.append("direct light and gathers: no lighting pass was asked for")
        plans.append({"lights": lights, "warnings": warnings, "skipped": skipped, "groups": groups})

    dilation = TimedDilation(backend)
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
                transported[index, group.name] = Transported(cached["direct"], cached["gathered"],
                                                             direct_variance=cached.get("direct_variance"),
                                                             gathered_variance=cached.get("gathered_variance"))
                plan["reused"].append(group.name)
            else:
                pending.append((index, group, key))
    total_groups = sum(len(plan["groups"]) for plan in plans)
    if total_groups:
        stages.expect("transport", len(pending) / total_groups)
    read_deferred_table(p, stages, needed=bool(pending) or "ao" in wants)
    shared_skips: list[str] = []
    results, gathers = transport_pending(p, backend, [group for _, group, _ in pending], stages, shared_skips,
                                         dilation)
    for (index, group, key), result in zip(pending, results):
        transported[index, group.name] = result
        # Interactive relighting revisits its lightings; a batch of setups rarely
        # does, and would fill the cache with results nobody reads again.
        if key and len(lightings) == 1:
            try:
                arrays = {"direct": result.direct, "gathered": result.gathered}
                if result.direct_variance is not None and result.gathered_variance is not None:
                    arrays.update(direct_variance=result.direct_variance, gathered_variance=result.gathered_variance)
                p.cache.save_lighting(settings, key, arrays)
            except OSError as error:
                plans[index]["warnings"].append(f"lighting cache in {p.cache.folder} could not be written "
                                                f"({error.strerror or error}); nothing else is affected")

    stages.start("outputs")
    per_lighting = []
    for index, plan in enumerate(plans):
        parts = {name: transported[i, name] for i, name in transported if i == index}
        started = time.perf_counter()
        per_pass = backend.accumulate_passes(p.albedo, wants, parts, settings.light_groups)
        if parts:
            stages.record_pass(f"accumulation of passes ({len(parts)} groups)", backend.name,
                               time.perf_counter() - started)
        if "ao" in wants:
            per_pass["ao"] = np.repeat(p.openness()[:, None], 3, axis=1)
        per_lighting.append((per_pass, parts))

    images = []
    output_meshes = [(i, m) for i, m in enumerate(p.meshes) if m.output]
    started = time.perf_counter()
    seams = _seams(p, output_meshes) if settings.stitch_seams else {}
    stitch_seconds = time.perf_counter() - started
    # Per lighting: mesh index -> (seam edges, before, after), of its lighting pass (else its first).
    stitched_per_lighting: list[dict[int, tuple]] = []
    for per_pass, _ in per_lighting:
        objects = []
        to_stitch = []  # (mesh index, pass name, image), stitched below, all at once
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
                    image = sample_image(values[a:b], samples.pixel, samples.coverage, settings.margin, dilation)
                    if seams.get(index) is not None:
                        to_stitch.append((index, name, image))
                    result.images[name] = image
            objects.append(result)
        started = time.perf_counter()
        stitched: dict[int, tuple] = {}
        for (index, name, image), done in zip(to_stitch, _stitched(to_stitch, seams, settings.threads)):
            image[..., :3] = done.image
            if index not in stitched or name == "lighting":
                stitched[index] = (seams[index].edges, done.before, done.after)
        stitch_seconds += time.perf_counter() - started
        images.append(objects)
        stitched_per_lighting.append(stitched)
        stages.report(len(images) / len(per_lighting))
    stages.stop()
    if stitched_per_lighting and stitched_per_lighting[0]:
        stages.record_pass(f"seam stitching ({len(stitched_per_lighting[0])} objects)", "cpu", stitch_seconds)

    if dilation.calls:
        stages.record_pass(f"gutter dilation ({dilation.calls} images)", backend.name, dilation.seconds)
    results = []
    for objects, plan, (_, parts), stitched in zip(images, plans, per_lighting, stitched_per_lighting):
        report = lighting_report(p, plan, parts, stages.times, list(stages.passes), gathers, shared_skips,
                                 len(lightings))
        report_tessellation(p, plan["lights"], objects, report)
        report_seams(report, settings.stitch_seams, seams, stitched)
        results.append(BakeResult(objects=objects, report=report.to_dict()))
    return results


def _stitched(to_stitch: list, seams: dict, threads: int) -> list:
    """core.outputs.seams.stitch of each (mesh index, pass name, (h, w, C) image) of
    ``to_stitch`` with its mesh's seams, in order, several at once: each solve is serial (a
    conjugate gradient's steps follow one another) and an object's own, so objects share the
    cores (``threads``: the Threads preference, 0 all), with the same bits as one by one."""
    if len(to_stitch) <= 1:
        return [stitch(image[..., :3], seams[index]) for index, _, image in to_stitch]
    with ThreadPoolExecutor(min(threads or default_threads(), len(to_stitch))) as pool:
        return list(pool.map(lambda job: stitch(job[2][..., :3], seams[job[0]]), to_stitch))


def _seams(p: Prepared, output_meshes) -> dict:
    """Mesh index -> core.outputs.seams.Seams (or None) of each atlas-mode output mesh."""
    found = {}
    for index, mesh in output_meshes:
        if mesh.mode != "atlas":
            continue
        samples = p.object_samples[index]
        found[index] = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps[mesh.bake_uv_map], mesh.corner_normals,
                                  samples.width, samples.height, samples.coverage)
    return found


def bake(scene: Scene, settings: BakeSettings, progress=None, backend: TransportBackend = CPU_BACKEND,
         split=None) -> BakeResult:
    """Bake every output object of ``scene``: :func:`prepare`, then :func:`relight`.

    Parameters
    ----------
    scene : Scene
        Meshes with a valid bake UV map each, lights and world.
    settings : BakeSettings
    progress : callable(stage: str, fraction: float) or None
        Called often; raise :class:`Cancelled` in it to stop.
    split : an executor of core.distributed.split, or None: the table is then traced and
        read by ranges of sample rows where the executor keeps them (the result is the same)
    """
    return relight(prepare(scene, settings, progress, split=split), scene.lights, scene.world, progress, backend)
