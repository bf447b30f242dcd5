"""One bake, Blender side: plan layouts, extract, run the core, write results.

Shared by the operator, the command line and the tests, so all three run the same
code with the same settings (``scene.visibake``). Either the whole bake lands or
the scene is left as it was: UV maps created for a bake that fails or is cancelled
are removed again, and nothing is written before the core has finished.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import bpy

from ...core.errors import BakeRefused
from ...core.outputs.report import DeviceReport, RefinedReport, Report, SetupReport
from ...core.pipeline.budget import peak_memory_bytes
from ...core.pipeline.prepare import prepare
from ...core.pipeline.relight import BakeResult, relight_many
from ...core.sampling import layout as layout_policy
from ...core.transport.direct import SHADOW_RAY_IN_LOOKUPS, shadow_rays_per_sample
from ...core.visibility.cache import VisibilityCache
from ...core.visibility.table import table_bytes
from . import device, extract, refine, writeback
from .extraction import complete_extraction, plan_extraction, run_unwraps
from .settings import cache_folder, resolve


@dataclass
class JobResult:
    result: BakeResult
    report: dict
    files: list[str] = field(default_factory=list)


def visibility_cache(scene) -> VisibilityCache | None:
    """The cache of this scene (named after the .blend), or None when caching is off."""
    if not scene.visibake.use_cache:
        return None
    label = os.path.splitext(os.path.basename(bpy.data.filepath))[0] if bpy.data.filepath else "untitled"
    return VisibilityCache(cache_folder(scene), f"{label}-{scene.name}")


def output_objects(context, props) -> list[bpy.types.Object]:
    """The objects a bake writes results for: selected meshes, or all with ``bake_all``,
    except those whose role is Occlude Only."""
    meshes = [o for o in extract.scene_meshes(context.scene) if o.visibake.role != "OCCLUDE"]
    if props.bake_all:
        return meshes
    return [o for o in meshes if o.select_get()]


def _bake_refined(context, objects, coarse, out_dir, previews, progress, device_name) -> JobResult:
    """Bake again with refined copies of the ``coarse`` [(object, triangles)] in their place.

    If that bake fails or is cancelled the copies are removed and the originals shown
    again, so the scene is as it was.
    """
    copies = {}
    try:
        for obj, triangles in coarse:
            copies[obj.name] = refine.refined_copy(obj, triangles)
        replaced = [copies.get(obj.name, obj) for obj in objects]
        outcome = run_bake(context, replaced, out_dir, previews, progress, device_name=device_name, refine=False)
    except BaseException:
        for copy in copies.values():
            refine.undo_refinement(copy)
        raise
    report = Report.from_dict(outcome.report)
    report.refined = [
        RefinedReport(object=name, copy=copy.name, coarse_triangles=int(len(triangles)),
                      vertices=[len(bpy.data.objects[name].data.vertices), len(copy.data.vertices)])
        for (obj, triangles), (name, copy) in zip(coarse, copies.items())]
    outcome.result.report = outcome.report = report.to_dict()
    return outcome


def run_bake(context, objects, out_dir: str | None = None, previews: bool = False,
             progress=None, relight_only: bool = False, setups=None, device_name: str | None = None,
             refine: bool | None = None, threads: int | None = None) -> JobResult:
    """Bake ``objects`` (mesh objects) with the settings in ``context.scene.visibake``.

    Every other visible mesh of the scene occludes and reflects light but gets no
    output. Raises :class:`BakeRefused` for bad input, ``core.errors.Cancelled``
    if ``progress`` cancels; in both cases the scene is left unchanged.

    Parameters
    ----------
    relight_only : refuse unless the visibility cache holds a valid table for the
        scene's current geometry (the table is never traced again)
    setups : callable(lights, world) -> list of core.lights.setups.Setup, or None. Each setup
        is relit from the one prepared table and written to ``out_dir/<setup>/``
        (files only; the scene's images keep the scene's own lighting).
    device_name : 'auto', 'gpu' or 'cpu' for the transport passes; None: the preference
    refine : bake refined copies of vertex-mode objects whose triangles are too coarse for
        their light (operators.adapter.refine); None: the scene's setting
    threads : worker threads for ray tracing and gathers (0: all cores); None: the preference
    """
    return BakeJob(context, objects, out_dir, previews, progress, relight_only, setups, device_name, refine,
                   threads).run()


class BakeJob:
    """:func:`run_bake` in steps, so the long ones can run on worker threads.

    :meth:`plan`, :meth:`extract` and :meth:`finish` use bpy and run on the main
    thread; :meth:`unwrap`, :meth:`compute_visibility` and :meth:`compute_lighting` are
    the core's work (no bpy) and may run anywhere, except that the lighting needs the
    main thread when :attr:`needs_main_thread` (the GPU passes need Blender's GL
    context). Only :meth:`extract` changes the scene before :meth:`finish`; after it,
    either ``finish`` or :meth:`abort` must follow.
    """

    def __init__(self, context, objects, out_dir=None, previews=False, progress=None, relight_only=False,
                 setups=None, device_name=None, refine=None, threads=None):
        self.context, self.objects, self.out_dir, self.previews = context, objects, out_dir, previews
        self.progress, self.relight_only, self.setups = progress, relight_only, setups
        self.device_name, self.refine, self.threads = device_name, refine, threads
        self.extracted = None
        self.results = None

    def run(self) -> JobResult:
        """Every step on this thread: the blocking bake."""
        self.start()
        return self.compute_and_finish()

    def compute_and_finish(self) -> JobResult:
        try:
            self.compute()
        except BaseException:
            self.abort()
            raise
        return self.finish()

    @property
    def needs_main_thread(self) -> bool:
        return self.chosen_device.name == "gpu"

    def start(self) -> None:
        """Everything before the core's work, on this (the main) thread: :meth:`plan`,
        :meth:`unwrap`, :meth:`extract`."""
        self.plan()
        self.unwrap()
        self.extract()

    def plan(self) -> None:
        """Check the inputs, choose the device, read the meshes and choose their layouts.

        Changes nothing in the scene (main thread).
        """
        context, objects, setups = self.context, self.objects, self.setups
        if not objects:
            raise BakeRefused("no mesh objects to bake: select some, or enable All Objects")
        if setups is not None and not self.out_dir:
            raise BakeRefused("lighting setups are written as files: give an output folder")
        self.resolved = resolve(context, self.threads, self.device_name, self.refine)
        self.settings = settings = self.resolved.bake
        if setups is None:
            writeback.check_image_names(writeback.image_name(o.name, p) for o in objects for p in settings.passes)
        self.chosen_device = device.choose(context, self.resolved.device)
        self.started = time.perf_counter()
        self.shadow_rays_per_sample = sum(shadow_rays_per_sample(lamp.data.type, settings)
                                          for lamp in extract.scene_lights(context.scene))
        self.planned = plan_extraction(context, objects, self.progress)

    def unwrap(self, in_child: bool = False) -> None:
        """The unwraps the layouts need (no bpy: any thread). ``in_child``: in child
        processes, so that a cancel stops them at once and the UI stays free."""
        run_unwraps(self.planned, self.progress, in_child)

    def extract(self) -> None:
        """Write the unwrapped UV maps and read the scene for the core (main thread)."""
        context, objects, setups, settings = self.context, self.objects, self.setups, self.settings
        self.extracted = extracted = complete_extraction(context, self.planned)
        self.cache = visibility_cache(context.scene)
        try:
            if setups is None:
                writeback.check_attribute_names(
                    [o for o in objects if o.name in extracted.plans and extracted.plans[o.name].mode == "vertex"],
                    settings.passes)
            self.lightings = [(None, extracted.scene.lights, extracted.scene.world)]
            if setups is not None:
                self.lightings = [(s.name, s.lights, s.world)
                                  for s in setups(extracted.scene.lights, extracted.scene.world)]
        except BaseException:
            extracted.undo()
            self.extracted = None
            raise

    def expected_work(self) -> dict:
        """The bake's work, known once it is planned: unwraps (in seconds of the measured
        machine), samples to place and write out, rays to trace, cache bytes, and table
        lookups (plus exact shadow rays, in lookups) to transport.

        Atlas texels count at the share a packed UV layout typically covers; a vertex-mode
        object has about one sample per vertex. Half the directions lie above a sample's
        horizon. For the time-left estimate in the UI, not for any decision.
        """
        samples = 0.0
        for mesh in self.planned.meshes:
            plan = self.planned.plans[mesh.name]
            if plan.mode == "vertex":
                samples += mesh.vertex_count or len(mesh.positions)
            else:
                samples += layout_policy.TYPICAL_PACKED_UV_AREA * plan.resolution[0] * plan.resolution[1]
        rays = samples * self.settings.directions / 2
        gathers = self.settings.bounces + 1
        shadow_rays = samples * self.shadow_rays_per_sample if self.settings.shadows == "exact" else 0.0
        work = {"samples": samples, "visibility": rays,
                "transport": rays * gathers + SHADOW_RAY_IN_LOOKUPS * shadow_rays, "outputs": samples}
        if self.context.scene.visibake.use_cache:
            # The table is written after a trace or read on a hit: one pass over its bytes.
            vertex = any(self.planned.plans[m.name].mode == "vertex" for m in self.planned.meshes)
            work["cache"] = 2 * table_bytes(1, int(rays), vertex_objects=vertex)
        if self.planned.unwraps:
            # In seconds of the measured machine: xatlas grows faster than linearly.
            work["unwrap"] = sum(layout_policy.unwrap_seconds(len(p.triangles)) for p in self.planned.unwraps)
        return work

    def compute(self) -> None:
        """The visibility table and the transport (no bpy: any thread)."""
        self.compute_visibility()
        self.compute_lighting()

    def compute_visibility(self) -> None:
        """The visibility table, traced or from the cache (no bpy: any thread)."""
        # Relighting with a setup may need the table although the scene's own lights do not.
        # A user's error is a BakeRefused from the core; anything else is a bug and says so.
        self.prepared = prepare(self.extracted.scene, self.settings, self.progress,
                                table_needed=True if self.setups else None, cache=self.cache,
                                require_cached_table=self.relight_only)

    def compute_lighting(self) -> None:
        """Direct and indirect light from the table (any thread for numpy; the main
        thread when :attr:`needs_main_thread`)."""
        # All setups' light groups share the gathers: one table walk serves them all.
        relit = relight_many(self.prepared, [(lights, world) for _, lights, world in self.lightings],
                             self.progress, self.chosen_device.backend)
        self.results = [(name, result) for (name, _, _), result in zip(self.lightings, relit)]

    def abort(self) -> None:
        """Undo what the main-thread steps did to the scene (the bake failed or was cancelled)."""
        if self.extracted is not None:
            self.extracted.undo()
            self.extracted = None

    def finish(self) -> JobResult:
        """Write the results into the scene and files, and assemble the report (main thread)."""
        results, setups = self.results, self.setups
        try:
            if setups is None:
                first = results[0][1].objects
                writeback.check_image_names(writeback.image_name(o.name, p)
                                            for o in first if o.domain is None for p in o.images)
                writeback.check_attribute_names(
                    [bpy.data.objects[o.name] for o in first if o.domain is not None],
                    {p for o in first if o.domain is not None for p in o.images})
            if self.resolved.refine and setups is None and not self.relight_only:
                coarse = [(bpy.data.objects[r.name], r.coarse_triangles) for r in results[0][1].objects
                          if r.domain is not None and r.coarse_triangles is not None and len(r.coarse_triangles)]
                if coarse:
                    return _bake_refined(self.context, self.objects, coarse, self.out_dir, self.previews,
                                         self.progress, self.device_name)
        except BaseException:
            self.abort()
            raise
        return self._write_and_report()

    def _write_and_report(self) -> JobResult:
        extracted, results, lightings, setups = self.extracted, self.results, self.lightings, self.setups
        times, warnings, plans = extracted.seconds, extracted.warnings, extracted.plans
        t = time.perf_counter()
        files = []
        for name, result in results:
            if name is None:
                files += writeback.write_outputs(result.objects, self.out_dir, self.previews)
            else:
                files += writeback.write_outputs(result.objects,
                                                 os.path.join(self.out_dir, writeback.safe_file_name(name)),
                                                 self.previews, store_images=False)
        times["write"] = time.perf_counter() - t

        result = results[-1][1]
        reports = [Report.from_dict(r.report) for _, r in results]
        report = reports[-1]
        report.stage_seconds = {**{k: round(v, 4) for k, v in times.items() if k != "write"},
                                **report.stage_seconds, "write": round(times["write"], 4)}
        report.total_seconds = round(time.perf_counter() - self.started, 4)
        report.peak_memory_bytes = peak_memory_bytes()
        report.files = files
        report.warnings = warnings + report.warnings
        for entry in report.objects:
            plan = plans.get(entry.name)
            if plan is not None:
                entry.mode, entry.layout_reason, entry.uv_map_created = plan.mode, plan.reason, plan.created
        report.blender_version = bpy.app.version_string
        report.lights = [light.name for light in lightings[-1][1]]
        report.relight_only = self.relight_only
        report.device = DeviceReport.from_dict(self.chosen_device.report)
        if setups is not None:
            # The last setup's times are the whole bake's, as in the report itself.
            report.setups = [SetupReport(name=name, lights=[light.name for light in lights],
                                         stage_seconds=r.stage_seconds, gathers=r.gathers,
                                         shadow_rays=r.rays.shadow_rays,
                                         lighting_reused=r.cache.lighting_reused if r.cache is not None else [])
                             for (name, lights, _), r in zip(lightings, reports)]
        result.report = report.to_dict()
        return JobResult(result=result, report=result.report, files=files)


def write_report(path: str, report: dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(report, handle, indent=2, default=float)
