"""One bake, Blender side: plan layouts, extract, run the core, write results.

Shared by the operator, the command line and the tests, so all three run the same
code with the same settings (``scene.visibake``). Either the whole bake lands or
the scene is left as it was: UV maps created for a bake that fails or is cancelled
are removed again, and nothing is written before the core has finished.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import bpy

import numpy as np

from ...core import kernels
from ...core.errors import BakeRefused, OutputRefused
from ...core.outputs import names
from ...core.outputs.destinations import FOLDER, check_destinations, destination_problem
from ...core.outputs.ownership import StagedWrites, remove_leftovers
from ...core.outputs.report import DeviceReport, RefinedReport, Report, SetupReport
from ...core.pipeline.budget import peak_memory_bytes
from ...core.pipeline.prepare import prepare
from ...core.pipeline.relight import BakeResult, relight_many
from ...core.pipeline.resident import prepare_or_reuse
from ...core.pipeline.target import PILOT_DIRECTIONS, DirectionChoice, choose_directions
from ...core.sampling import layout as layout_policy
from ...core.transport.direct import SHADOW_RAY_IN_LOOKUPS, shadow_rays_per_sample
from ...core.visibility.cache import VisibilityCache
from ...core.visibility.table import table_bytes
from . import device, extract, refine, writeback
from .extraction import complete_extraction, plan_extraction, run_unwraps
from .settings import cache_folder, cache_limit_bytes, resolve


@dataclass
class JobResult:
    """A finished bake. ``rollback()`` undoes what it changed in the scene and the files it
    wrote, for a caller whose own later step (saving, a report) fails."""

    result: BakeResult
    report: dict
    files: list[str] = field(default_factory=list)
    rollback: Callable[[], None] = lambda: None
    # With run_bake's hold_replaced: drops the earlier files rollback() would have put back.
    keep: Callable[[], None] = lambda: None


class _WrittenResults:
    """What writing results changes in the scene, so that a failure can put it back.

    Taken before the write: for every image and colour attribute the results go to, whether it
    existed (it can only be VisiBake's own: writeback refuses any other) and, if so, a copy of
    its values. Restoring removes what the write created and puts the old values back into what
    it overwrote, so a failed re-bake leaves the previous bake's results, not a mix. The files
    go through :attr:`files` (core.outputs.ownership.StagedWrites): restoring removes only the
    files and folders this bake created and puts back the earlier bake's files it replaced
    (kept as hard links, no copy), never touching a file of the user's.
    """

    def __init__(self, results, out_dir: str | None):
        self.images, self.attributes = {}, {}
        self.files = StagedWrites(out_dir, keep_replaced=True)
        for result in results:
            if result.domain is None:
                for pass_name in result.images:
                    name = writeback.image_name(result.name, pass_name)
                    image = bpy.data.images.get(name)
                    self.images[name] = None if image is None else (
                        tuple(image.size), _values(image.pixels, len(image.pixels)))
            else:
                mesh = bpy.data.objects[result.name].data
                for pass_name in result.images:
                    name = writeback.attribute_name(pass_name)
                    attribute = mesh.attributes.get(name)
                    self.attributes[(mesh.name, name)] = None if attribute is None else (
                        attribute.domain, _values(attribute.data, 4 * len(attribute.data), "color"))
                self.attributes.setdefault((mesh.name, None), list(mesh.get(writeback.OWNED_ATTRIBUTES_KEY, [])))

    def restore(self) -> None:
        self.files.rollback()
        for name, old in self.images.items():
            image = bpy.data.images.get(name)
            if image is None:
                continue
            if old is None:
                bpy.data.images.remove(image)
                continue
            size, pixels = old
            if tuple(image.size) != size:
                image.scale(*size)
            image.pixels.foreach_set(pixels)
            image.update()
            image.pack()
        for (mesh_name, name), old in self.attributes.items():
            mesh = bpy.data.meshes.get(mesh_name)
            if mesh is None or name is None:
                continue
            attribute = mesh.attributes.get(name)
            if attribute is not None and (old is None or attribute.domain != old[0]):
                mesh.attributes.remove(attribute)
                attribute = None
            if old is not None:
                if attribute is None:
                    attribute = mesh.color_attributes.new(name, "FLOAT_COLOR", old[0])
                attribute.data.foreach_set("color", old[1])
            mesh[writeback.OWNED_ATTRIBUTES_KEY] = self.attributes[(mesh_name, None)]
            mesh.update()


def _values(collection, count: int, attribute: str | None = None) -> np.ndarray:
    """(count,) float32 copy of a bpy collection's values (image pixels, attribute colours)."""
    values = np.empty(count, np.float32)
    if attribute is None:
        collection.foreach_get(values)
    else:
        collection.foreach_get(attribute, values)
    return values


def cache_label(scene) -> str:
    """The cache slot's label: the .blend's and the scene's names, readable but cut short, and a
    hash of the file's full path and the scene's whole name, so that two files of one name in
    different folders (or two long names cut alike) never share a slot and evict each other."""
    path = os.path.normcase(os.path.realpath(bpy.data.filepath)) if bpy.data.filepath else ""
    base = os.path.splitext(os.path.basename(path))[0] if path else "untitled"
    digest = hashlib.blake2b(f"{path}\0{scene.name}".encode("utf-8", "surrogatepass"), digest_size=4).hexdigest()
    # VisibilityCache keeps 48 characters of a label: the hash must survive the cut.
    return f"{base[:20]}-{scene.name[:14]}-{digest}"


def visibility_cache(scene) -> VisibilityCache | None:
    """The cache of this scene (named after the .blend), or None when caching is off."""
    if not scene.visibake.use_cache:
        return None
    return VisibilityCache(cache_folder(scene), cache_label(scene), limit_bytes=cache_limit_bytes())


def preferred_cluster(context):
    """The local cluster the preference Cluster Workers asks the panel's Bake for
    (core.distributed.engine.ClusterOptions), or None: bake in this process."""
    prefs = device.preferences(context)
    workers = int(getattr(prefs, "cluster_workers", 0) or 0)
    if workers <= 0:
        return None
    from ...core.distributed.engine import ClusterOptions

    return ClusterOptions(workers=workers)


def output_objects(context, props) -> list[bpy.types.Object]:
    """The objects a bake writes results for: selected meshes, or all with ``bake_all``,
    except those whose role is Occlude Only."""
    meshes = [o for o in extract.scene_meshes(context.scene) if o.visibake.role != "OCCLUDE"]
    if props.bake_all:
        return meshes
    return [o for o in meshes if o.select_get()]


def _bake_refined(context, objects, coarse, out_dir, previews, progress, device_name, hold_replaced) -> JobResult:
    """Bake again with refined copies of the ``coarse`` [(object, triangles)] in their place.

    If that bake fails or is cancelled the copies are removed and the originals shown
    again (a copy refined again gets its previous mesh back), so the scene is as it was.
    """
    copies = {}
    # Before refining: a copy refined again (a re-bake) is refined in place.
    vertices_before = {obj.name: len(obj.data.vertices) for obj, _ in coarse}
    new_copies = {obj.name for obj, _ in coarse if not obj.get(refine.REFINED_FROM_KEY)}
    try:
        for obj, triangles in coarse:
            copies[obj.name] = refine.refined_copy(obj, triangles)
        replaced = [copies.get(obj.name, obj) for obj in objects]
        outcome = run_bake(context, replaced, out_dir, previews, progress, device_name=device_name, refine=False,
                           hold_replaced=hold_replaced)
    except BaseException:
        for copy in copies.values():
            refine.undo_refinement(copy)
        raise
    for copy in copies.values():
        refine.keep_refinement(copy)
    inner_rollback = outcome.rollback

    def rollback():
        # A copy refined in place keeps its finer mesh (the previous one is gone): it is still
        # VisiBake's own copy, and the user's original was never touched.
        inner_rollback()
        for name in new_copies:
            refine.undo_refinement(copies[name])

    outcome.rollback = rollback
    report = Report.from_dict(outcome.report)
    report.refined = [
        # The object is the original the copy stands for, also when a re-bake refined the copy again.
        RefinedReport(object=copy.get(refine.REFINED_FROM_KEY, name), copy=copy.name,
                      coarse_triangles=int(len(triangles)), vertices=[vertices_before[name], len(copy.data.vertices)])
        for (obj, triangles), (name, copy) in zip(coarse, copies.items())]
    outcome.result.report = outcome.report = report.to_dict()
    return outcome


def run_bake(context, objects, out_dir: str | None = None, previews: bool = False,
             progress=None, relight_only: bool = False, setups=None, device_name: str | None = None,
             refine: bool | None = None, threads: int | None = None, keep_preparation: bool = False,
             view_densities: dict | None = None, cluster=None, hold_replaced: bool = False,
             fixed_directions: bool = False) -> JobResult:
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
    keep_preparation : keep what this bake prepared in memory (within the preference Resident
        Memory) for the next Relight of this session, and let a Relight reuse the kept one
        (core.pipeline.resident); the panel's buttons do, a command (one bake a process) does not
    view_densities : {object name: texels per unit of surface} that the cameras which will see
        the bake need (core.lightfield.coverage): they lower those objects' atlas sizes
    cluster : core.distributed.engine.ClusterOptions (a Dask cluster) or
        core.distributed.farm.FarmOptions (one step of a farm job), or None: trace and read the
        table by ranges of sample rows there (the images are the same bits; no cache)
    hold_replaced : keep the earlier bake's files this one replaced (hidden hard links) until
        the outcome's ``keep()``, so that its ``rollback()`` puts them back (a caller with steps
        of its own after the bake); else they go when the bake has written all of its files
    fixed_directions : with a Target Error, keep the scene's Directions (the command line's
        --directions) instead of choosing them; the report still gives the estimate
    """
    return BakeJob(context, objects, out_dir, previews, progress, relight_only, setups, device_name, refine,
                   threads, keep_preparation, view_densities, cluster, hold_replaced, fixed_directions).run()


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
                 setups=None, device_name=None, refine=None, threads=None, keep_preparation=False,
                 view_densities=None, cluster=None, hold_replaced=False, fixed_directions=False):
        self.context, self.objects, self.out_dir, self.previews = context, objects, out_dir, previews
        self.progress, self.relight_only, self.setups = progress, relight_only, setups
        self.device_name, self.refine, self.threads = device_name, refine, threads
        self.keep_preparation = keep_preparation
        self.view_densities = view_densities
        self.cluster = cluster
        self.hold_replaced = hold_replaced
        self.fixed_directions = fixed_directions
        self.extracted = None
        self.results = None
        # A bake at a Target Error that chooses its directions: the pilot's (DirectionChoice) once made.
        self.choosing = False
        self.choice: DirectionChoice | None = None
        self.pilot_seconds = 0.0

    def run(self) -> JobResult:
        """Every step on this thread: the blocking bake."""
        with kernels.blas_on_one_thread():
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
            # A selected curve, text, metaball or instancer takes part in the light but has no output.
            selected = getattr(context, "selected_objects", None) or []
            reasons = [r for o in selected if (r := extract.why_not_a_target(o))]
            raise BakeRefused("no mesh objects to bake: select some, or enable All Objects"
                              + (f" ({'; '.join(reasons)})" if reasons else ""))
        if setups is not None and not self.out_dir:
            raise BakeRefused("lighting setups are written as files: give an output folder")
        # Before any work: a bake that cannot write its results would lose them at the end.
        check_destinations([(self.out_dir, FOLDER, "output folder")])
        self.resolved = resolve(context, self.threads, self.device_name, self.refine)
        self.settings = settings = self._directions_for_target(self.resolved.bake)
        if setups is None:
            writeback.check_image_names(writeback.image_name(o.name, p) for o in objects for p in settings.passes)
        if self.cluster is not None:
            if self.relight_only or setups is not None:
                raise BakeRefused("a bake on a cluster or a farm bakes one lighting without the cache: not with "
                                  "relight, --setups or --sun-sweep")
            if self.device_name == "gpu":
                raise BakeRefused("--device gpu: a bake on a cluster or a farm reads its table where the table is "
                                  "kept, with the CPU kernels; use --device cpu or auto")
            self.cluster.validate()
        # A table held by sample rows is read where it is kept, by the CPU kernels.
        self.chosen_device = device.choose(context, "cpu" if self.cluster is not None else self.resolved.device)
        self.started = time.perf_counter()
        self.shadow_rays_per_sample = sum(shadow_rays_per_sample(extract.read_light(lamp), settings)
                                          for lamp in extract.scene_lights(context.scene))
        self.planned = plan_extraction(context, objects, self.progress, self.view_densities)
        if self.out_dir:
            self._claim_output_folder()

    def _directions_for_target(self, settings):
        """``settings`` with the directions a Target Error bake starts from: the count the scene's
        last such bake chose, else PILOT_DIRECTIONS; a bake (not a relight) of one lighting in this
        process then chooses again from that pilot (:meth:`compute_chosen_visibility`)."""
        if settings.target_error <= 0 or self.fixed_directions:
            return settings
        if self.cluster is not None or self.setups is not None:
            # One lighting in this process only: the pilot's estimate is of that lighting.
            return settings
        remembered = int(self.context.scene.visibake.chosen_directions)
        self.choosing = not self.relight_only
        return replace(settings, directions=remembered if remembered > 0 else PILOT_DIRECTIONS)

    def _claim_output_folder(self) -> None:
        """Before any work, the one rule (core.outputs.ownership): refuse if a file the bake
        would write exists and no VisiBake record lists it (the files of the passes it knows
        now; a light group's, a refined copy's and a setup's are checked again before writing),
        then remove the temporaries a killed run left there."""
        if self.setups is None:
            planned = [SimpleNamespace(name=o.name, images=dict.fromkeys(self.settings.passes),
                                       domain="vertex" if self.planned.plans[o.name].mode == "vertex" else None)
                       for o in self.objects if o.name in self.planned.plans]
            writeback.refuse_foreign_outputs(planned, self.out_dir, self.previews)
        remove_leftovers(self.out_dir, depth=2 if self.setups is None else 3)

    def unwrap(self, in_child: bool = False) -> None:
        """The unwraps the layouts need (no bpy: any thread). ``in_child``: in child
        processes, so that a cancel stops them at once and the UI stays free."""
        run_unwraps(self.planned, self.progress, in_child)

    def extract(self) -> None:
        """Write the unwrapped UV maps and read the scene for the core (main thread)."""
        context, objects, setups, settings = self.context, self.objects, self.setups, self.settings
        self.extracted = extracted = complete_extraction(context, self.planned)
        self.cache = visibility_cache(context.scene)
        unusable = None if self.cache is None else destination_problem(self.cache.folder, FOLDER, "cache folder")
        if unusable is not None:
            # The cache only saves time: the result is the same without it. A folder that exists may
            # still hold a table to read (a shared, read-only cache).
            readable = os.path.isdir(self.cache.folder)
            extracted.warnings.append(f"{unusable}: the visibility cache is {'only read' if readable else 'off'} "
                                      "in this bake (choose another Cache Folder, or --cache-dir)")
            if readable:
                self.cache.read_only = True
            else:
                self.cache = None
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
            work["cache"] = 2 * table_bytes(1, int(rays))
        if self.planned.unwraps:
            # In seconds of the measured machine: xatlas grows faster than linearly.
            work["unwrap"] = sum(layout_policy.unwrap_seconds(len(p.triangles)) for p in self.planned.unwraps)
        return work

    def compute(self) -> None:
        """The visibility table and the transport (no bpy: any thread); on a cluster, both
        while its workers hold the table's rows."""
        if self.cluster is None:
            self.compute_visibility()
            self.compute_lighting()
            self.compute_chosen_visibility()
            self.compute_chosen_lighting()
            return
        from ...core.distributed.engine import cluster_rows
        from ...core.distributed.farm import FarmOptions, FarmRows, write_job_package
        from ...core.distributed.package import package_bytes

        if isinstance(self.cluster, FarmOptions):
            # One step of a farm job: stops (core.distributed.farm.PartsPending) where parts must run first.
            write_job_package(self.cluster.folder, self.extracted.scene, self.settings)
            self.prepared = prepare(self.extracted.scene, self.settings, self.progress,
                                    split=FarmRows(self.cluster.folder, self.cluster.parts))
            self.compute_lighting()
            return
        package = package_bytes(self.extracted.scene, self.settings)
        with cluster_rows(self.cluster, package, self.settings.threads) as rows:
            self.prepared = prepare(self.extracted.scene, self.settings, self.progress, split=rows)
            self.compute_lighting()

    def compute_visibility(self) -> None:
        """The visibility table, traced or from the cache (no bpy: any thread)."""
        # Relighting with a setup may need the table although the scene's own lights do not.
        # A user's error is a BakeRefused from the core; anything else is a bug and says so.
        keep_bytes = self.resolved.resident_bytes if self.keep_preparation else 0
        self.prepared = prepare_or_reuse(self.extracted.scene, self.settings, self.progress,
                                         table_needed=True if self.setups else None, cache=self.cache,
                                         require_cached_table=self.relight_only, keep_bytes=keep_bytes,
                                         reuse=self.relight_only)
        if not self.prepared.resident:
            # Not kept (a command's bake, or beyond Resident Memory): nothing relights it again,
            # so its footprints go before the gathers need their memory.
            self.prepared.relit_once = True

    def compute_chosen_visibility(self) -> None:
        """At a Target Error: choose the directions from the pilot's estimate (the bake so far), and
        where they are more, the table at the chosen count (no bpy: any thread); nothing otherwise."""
        if not self.choosing or self.choice is not None:
            return
        pilot = self.settings.directions
        estimate = self.results[0][1].report.get("estimated_error")
        self.choice = choose_directions(estimate, pilot, self.settings.target_error)
        if self.choice.directions == pilot:
            return
        self.pilot_seconds = time.perf_counter() - self.started
        # The pilot's preparation goes before the chosen one is made (its table is the bake's largest array).
        self.prepared = self.results = None
        self.settings = replace(self.settings, directions=self.choice.directions)
        self.compute_visibility()

    def compute_chosen_lighting(self) -> None:
        """The light at the chosen directions, where :meth:`compute_chosen_visibility` chose more."""
        if self.choice is not None and self.results is None:
            self.compute_lighting()

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
                                         self.progress, self.device_name, self.hold_replaced)
        except BaseException:
            self.abort()
            raise
        written = _WrittenResults([o for name, r in results if name is None for o in r.objects], self.out_dir)
        extracted = self.extracted
        try:
            outcome = self._write_and_report(written.files)
        except BaseException as error:
            written.restore()
            self.abort()
            if isinstance(error, OSError):
                # The disk (full, permissions changed during the bake): the user's to fix, not a bug.
                raise OutputRefused(f"the results could not be written ({error.strerror or error}: "
                                    f"{error.filename or self.out_dir}); nothing was changed") from error
            raise

        props = self.context.scene.visibake
        chosen_before = props.chosen_directions
        if self.choice is not None:
            # The next bake at this target starts from this count, and a relight reuses it.
            props.chosen_directions = self.choice.directions

        def rollback():
            written.restore()
            extracted.undo()
            props.chosen_directions = chosen_before

        outcome.rollback = rollback
        if self.hold_replaced:
            outcome.keep = written.files.keep
        else:
            written.files.keep()
        return outcome

    def _write_and_report(self, staged: StagedWrites) -> JobResult:
        extracted, results, lightings, setups = self.extracted, self.results, self.lightings, self.setups
        times, warnings, plans = extracted.seconds, extracted.warnings, extracted.plans
        t = time.perf_counter()
        files, renamed = [], []
        setup_folders = names.unique_components([n for n, _ in results if n is not None],
                                                reserved=writeback.OUT_FOLDER_RESERVED)
        for name, result in results:
            # Every destination of every setup before the first file is written.
            if name is not None:
                writeback.refuse_foreign_outputs(result.objects, names.inside_folder(self.out_dir, setup_folders[name]),
                                                 self.previews)
            elif self.out_dir:
                writeback.refuse_foreign_outputs(result.objects, self.out_dir, self.previews)
        for name, result in results:
            if name is None:
                files += writeback.write_outputs(result.objects, self.out_dir, self.previews, renamed=renamed,
                                                 staged=staged)
            else:
                folder = names.inside_folder(self.out_dir, setup_folders[name])
                if setup_folders[name] != name:
                    renamed.append({"name": name, "kind": "setup", "path": folder})
                files += writeback.write_outputs(result.objects, folder, self.previews, store_images=False,
                                                 renamed=renamed, staged=staged)
        times["write"] = time.perf_counter() - t

        result = results[-1][1]
        reports = [Report.from_dict(r.report) for _, r in results]
        report = reports[-1]
        report.stage_seconds = {**{k: round(v, 4) for k, v in times.items() if k != "write"},
                                **report.stage_seconds, "write": round(times["write"], 4)}
        report.total_seconds = round(time.perf_counter() - self.started, 4)
        report.peak_memory_bytes = peak_memory_bytes()
        report.files = files
        report.renamed_outputs = renamed
        report.warnings = warnings + report.warnings + names.renamed_warnings(renamed)
        for entry in report.objects:
            plan = plans.get(entry.name)
            if plan is not None:
                entry.mode, entry.layout_reason, entry.uv_map_created = plan.mode, plan.reason, plan.created
        report.blender_version = bpy.app.version_string
        report.lights = [light.name for light in lightings[-1][1]]
        report.relight_only = self.relight_only
        report.device = DeviceReport.from_dict(self.chosen_device.report)
        if self.settings.target_error > 0:
            report.target = self._target_record(report)
        if self.cluster is not None:
            report.split = {**(report.split or {}), "cluster": self.cluster.describe()}
        if setups is not None:
            # The last setup's times are the whole bake's, as in the report itself.
            report.setups = [SetupReport(name=name, lights=[light.name for light in lights],
                                         stage_seconds=r.stage_seconds, gathers=r.gathers,
                                         shadow_rays=r.rays.shadow_rays,
                                         lighting_reused=r.cache.lighting_reused if r.cache is not None else [])
                             for (name, lights, _), r in zip(lightings, reports)]
        result.report = report.to_dict()
        return JobResult(result=result, report=result.report, files=files)

    def _target_record(self, report: Report) -> dict:
        """The report's ``target``: the target, what was chosen and why, and whether the bake's
        own estimate meets it."""
        target = self.settings.target_error
        if self.choice is not None:
            record = {**self.choice.as_dict(), "pilot_seconds": round(self.pilot_seconds, 4)}
        else:
            why = ("--directions was given" if self.fixed_directions else
                   "a relight reuses the directions the last bake chose" if self.relight_only else
                   "a bake of several lightings, or on a cluster, keeps its directions")
            record = {"target_error": target, "directions": self.settings.directions, "reason": why}
        estimated = (report.estimated_error or {}).get("total")
        record["estimated_error"] = estimated
        record["met"] = None if estimated is None else bool(estimated <= target)
        return record


def write_report(path: str, report: dict) -> None:
    """Write the report as JSON, whole or not at all (a full disk leaves no half report)."""
    path = os.path.abspath(path)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if os.path.isdir(path):  # made by the bake itself (an object's folder): the check before could not know
        raise IsADirectoryError(errno.EISDIR, "is a folder", path)
    text = json.dumps(report, indent=2, default=float)
    temporary = f"{path}.writing-{os.getpid()}"
    try:
        with open(temporary, "w", encoding="utf-8") as handle:
            handle.write(text)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)
