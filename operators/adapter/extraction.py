"""A bake's scene read into core arrays, in the steps the modal bake runs apart: plan
(meshes read, layouts chosen; main thread), unwrap (no bpy: any thread or a child
process), complete (UV maps written, lamps and world read; main thread). What a step
creates is undone by :meth:`Extracted.undo` when a later one fails or is cancelled."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import bpy

import numpy as np

from ...core.errors import BakeRefused, Cancelled
from ...core.geometry import any_valid_triangle
from ...core.pipeline.budget import check_budget
from ...core.sampling import layout as layout_policy
from ...core.sampling.unwrap_child import UnwrapWorker
from ...core.scene import Scene
from . import extract, layout
from .settings import layout_settings


@dataclass
class Extracted:
    """The core scene of a bake, and what the Blender side did to produce it."""

    scene: Scene
    plans: dict  # object name -> layout.LayoutPlan
    created: list  # (mesh, UV map name) created for this bake
    warnings: list
    seconds: dict

    def undo(self) -> None:
        """Remove the UV maps this extraction created (a bake that did not finish)."""
        layout.remove_created_uv_maps(self.created)


@dataclass
class Planned:
    """The first step of an extraction: every mesh read and its layout chosen.

    Nothing in the scene has changed yet; the unwraps the plans need are still to run
    (:func:`run_unwraps`, anywhere), and :func:`complete_extraction` writes their UV maps.
    """

    objects: list  # the bpy objects that take part, in the order of ``meshes``
    meshes: list  # core.scene.Mesh as read, without their layout yet
    plans: dict  # object name -> layout.LayoutPlan
    budget: dict  # object name -> planned samples (width, height), for check_budget
    warnings: list
    seconds: dict
    geometry: list = field(default_factory=list)  # core meshes of instances and non-mesh objects (no outputs)

    @property
    def unwraps(self) -> list:
        # Linked duplicates share one unwrap (see _share_unwrap): each runs once.
        return list({id(p.pending): p.pending for p in self.plans.values() if p.pending is not None}.values())


def plan_extraction(context, objects, progress=None, view_densities: dict | None = None) -> Planned:
    """Read every visible mesh (``objects`` get outputs) and choose its layout (main thread).

    view_densities : {object name: texels per unit of surface the cameras need}, which lower
        those objects' atlas sizes (core.sampling.layout.object_resolution); None: none
    """
    scene = context.scene
    props = scene.visibake
    started = time.perf_counter()
    outputs = set(o.name for o in objects)
    all_meshes = extract.scene_meshes(scene)
    warnings: list[str] = []
    depsgraph = context.evaluated_depsgraph_get()
    planned = Planned([], [], {}, {}, warnings, {})
    for index, obj in enumerate(all_meshes):
        mesh = extract.read_mesh(obj, depsgraph, "", (0, 0), obj.name in outputs, warnings)
        if not any_valid_triangle(mesh.positions, mesh.triangles):
            # A scatter's points make instances (extract.scene_geometry) and no faces of their own.
            if mesh.output or not extract.makes_instances(obj):
                warnings.append(f"object {obj.name!r} has no face with a finite, non-zero area and was skipped")
            continue
        planned.plans[obj.name] = _plan(obj, mesh, layout_settings(props), planned.budget, props.directions,
                                        (view_densities or {}).get(obj.name, 0.0) if mesh.output else 0.0)
        _share_unwrap(planned, obj)
        planned.objects.append(obj)
        planned.meshes.append(mesh)
        if progress:
            progress("layout", (index + 1) / len(all_meshes))
    check_shared_vertex_meshes(planned)
    planned.geometry = extract.scene_geometry(depsgraph, scene, warnings).meshes
    for obj in getattr(context, "selected_objects", None) or []:
        reason = extract.why_not_a_target(obj) if obj.name not in outputs else None
        if reason:
            warnings.append(reason)
    planned.seconds["layout"] = time.perf_counter() - started
    return planned


def _share_unwrap(planned: Planned, obj) -> None:
    """Let ``obj`` share the unwrap of an earlier object with the same mesh (linked duplicates).

    The ``VisiBake`` UV map lives on the mesh, so they all bake on one map; unwrapping it once
    per object would write it over and over. It is packed at the smallest of their atlas sizes,
    so that its gutters are wide enough at every size (a larger atlas only widens them).
    """
    plan = planned.plans[obj.name]
    if plan.pending is None or plan.pending.loops is None:
        return
    for other in planned.objects:
        first = planned.plans[other.name].pending
        if other.data == obj.data and first is not None and first.loops is not None:
            first.resolution = min(first.resolution, plan.pending.resolution)
            plan.pending = first
            return


def check_shared_vertex_meshes(planned: Planned) -> None:
    """Refuse a vertex-mode output object whose mesh another object also uses (linked duplicates).

    Its result would be a colour attribute on that shared mesh, which every user of the mesh
    shows (through its materials, the viewport, exporters): a second baked user would overwrite
    it, and an unbaked one would show lighting that is not its own. Per-object attribute names
    would not help, since the duplicates share their materials too, and a material reads one
    name. Atlas mode gives each object its own image on the shared UV map.
    """
    vertex_outputs = [obj for obj, mesh in zip(planned.objects, planned.meshes)
                      if mesh.output and planned.plans[obj.name].mode == "vertex"]
    if not vertex_outputs:
        return
    users: dict = {}
    for other in bpy.data.objects:
        # Objects in no scene or collection (no users) show nothing and are purged on save.
        if other.type == "MESH" and other.users:
            users.setdefault(other.data, []).append(other.name)
    for obj in vertex_outputs:
        sharing = sorted(name for name in users.get(obj.data, []) if name != obj.name)
        if sharing:
            names = ", ".join(repr(n) for n in [obj.name, *sharing])
            raise BakeRefused(
                f"objects {names} share the mesh {obj.data.name!r}, and vertex mode writes {obj.name!r}'s result "
                "onto that mesh, where the others would show it too; make them single users (Object > Relations > "
                "Make Single User > Object & Data) or bake them with mode atlas")


def run_unwraps(planned: Planned, progress=None, in_child: bool = False) -> None:
    """Run the plans' unwraps (no bpy: any thread). ``in_child``: each in a child
    process, which a cancel through ``progress`` kills at once."""
    started = time.perf_counter()
    unwraps = planned.unwraps
    # Progress by expected time: one large mesh takes longer than many small ones.
    costs = np.cumsum([0.0] + [layout_policy.unwrap_seconds(len(p.triangles)) for p in unwraps])
    with UnwrapWorker() as worker:  # one child process for all the unwraps
        for index, pending in enumerate(unwraps):
            fraction = costs[index] / costs[-1]

            def cancelled() -> bool:
                try:
                    if progress:
                        progress("unwrap", fraction)
                except Cancelled:
                    return True
                return False

            if cancelled():
                raise Cancelled()
            pending.run(in_child, cancelled, worker)
            if in_child and cancelled():
                raise Cancelled()
    if unwraps and progress:
        progress("unwrap", 1.0)
    planned.seconds["unwrap"] = time.perf_counter() - started


def complete_extraction(context, planned: Planned) -> Extracted:
    """Write the unwrapped UV maps and read the scene as the core needs it (main thread).

    On an error the UV maps written here are removed again before this raises.
    """
    scene = context.scene
    props = scene.visibake
    warnings, times = planned.warnings, planned.seconds
    created: list[tuple[bpy.types.Mesh, str]] = []
    t = time.perf_counter()
    try:
        for obj, mesh in zip(planned.objects, planned.meshes):
            plan = planned.plans[obj.name]
            if plan.pending is None:
                continue
            plan = _complete_plan(obj, mesh, plan, planned.budget, props)
            planned.plans[obj.name] = plan
            if plan.created:
                created.append((obj.data, plan.uv_map))
        # Mode auto falls back to vertex tables where an unwrap failed: check those too.
        check_shared_vertex_meshes(planned)
        meshes = planned.meshes
        rewritten = [obj for obj in planned.objects if planned.plans[obj.name].written]
        if rewritten:
            # The new UV maps live on the base meshes; evaluate again so modifiers carry them.
            depsgraph = context.evaluated_depsgraph_get()
            depsgraph.update()
            outputs = {mesh.name for mesh in meshes if mesh.output}
            again = {obj.name: extract.read_mesh(obj, depsgraph, "", (0, 0), obj.name in outputs, [])
                     for obj in rewritten}
            meshes = [again.get(mesh.name, mesh) for mesh in meshes]
        for mesh in meshes:
            plan = planned.plans[mesh.name]
            mesh.bake_uv_map, mesh.resolution, mesh.mode = plan.uv_map, plan.resolution, plan.mode
            if plan.internal_uv is not None:
                mesh.uv_maps[plan.uv_map] = plan.internal_uv
        world = extract.read_world(scene, warnings)
        world.light_group = getattr(scene.world, "lightgroup", "") if scene.world else ""
        names = [m.name for m in meshes + planned.geometry]
        lights = [extract.read_light(o, warnings, names) for o in extract.scene_lights(scene)]
        extract.emitter_linking_warnings(scene, meshes + planned.geometry, warnings)
        core_scene = Scene(meshes=meshes + planned.geometry, lights=lights, world=world)
        times["extract"] = time.perf_counter() - t
        if not any(m.output for m in meshes):
            raise BakeRefused("none of the objects to bake has faces")
    except BaseException:
        layout.remove_created_uv_maps(created)
        raise
    return Extracted(core_scene, planned.plans, created, warnings, times)


def extract_scene(context, objects, progress=None) -> Extracted:
    """Lay out and read every visible mesh (``objects`` get outputs), lamps and world.

    Creates ``VisiBake`` UV maps where needed; on an error they are removed again
    before this raises. The three steps in one, on this thread.
    """
    planned = plan_extraction(context, objects, progress)
    run_unwraps(planned, progress)
    return complete_extraction(context, planned)


def _complete_plan(obj, mesh, plan, budget: dict, props) -> layout.LayoutPlan:
    """Apply a plan's unwrap; mode auto takes vertex tables where it failed."""
    try:
        return layout.complete_layout(obj, plan)
    except layout.UnwrapFailed as error:
        if obj.visibake.effective_mode(props) != "auto" or not _vertex_topology_kept(obj, mesh):
            raise
        budget[obj.name] = (3 * len(mesh.triangles), 1)
        check_budget(list(budget.values()), props.directions)
        return layout.vertex_plan(f"vertex tables: {error}")


def _plan(obj, mesh, props, budget: dict, directions: int, view_density: float = 0.0) -> layout.LayoutPlan:
    """The layout of one object: an atlas (its UV map, or one to unwrap) or vertex tables.

    Mode vertex always takes vertex tables; mode auto takes them where the mesh is too
    dense or too big to unwrap (or, later, where unwrapping fails); mode atlas never does.
    """
    mode = obj.visibake.effective_mode(props)
    if mode == "vertex":
        _check_vertex_topology(obj, mesh)
        budget[obj.name] = (3 * len(mesh.triangles), 1)
        check_budget(list(budget.values()), directions)
        return layout.vertex_plan("vertex mode was asked for")
    # Checked before any work at the planned size: validating a UV map rasterises it
    # at the bake resolution.
    budget[obj.name] = layout.planned_resolution(obj, props, mesh.positions, mesh.triangles, view_density)
    check_budget(list(budget.values()), directions)
    existing = None
    if mode == "auto":
        # A valid UV map of the user's is a request for textures; only a mesh that would
        # have to be unwrapped is considered for vertex tables.
        existing = layout.existing_layout(obj, mesh.uv_maps, mesh.positions, mesh.triangles, props, view_density)
        reason = None if existing is not None else layout.auto_vertex_reason(
            obj, mesh.positions, mesh.triangles, mesh.loop_count, props)
        if reason is not None:
            budget[obj.name] = (3 * len(mesh.triangles), 1)
            check_budget(list(budget.values()), directions)
            return layout.vertex_plan(f"vertex tables: {reason}")
    plan = existing or layout.plan_layout(obj, mesh.uv_maps, mesh.positions, mesh.triangles, props, mesh.output,
                                          view_density)
    budget[obj.name] = plan.resolution
    check_budget(list(budget.values()), directions)
    return plan


def _vertex_topology_kept(obj, mesh) -> bool:
    return mesh.vertex_count == len(obj.data.vertices) and mesh.loop_count == len(obj.data.loops)


def _check_vertex_topology(obj, mesh) -> None:
    if mesh.output and not _vertex_topology_kept(obj, mesh):
        raise BakeRefused(
            f"object {obj.name!r}: vertex mode writes colour attributes on the mesh, but its modifiers change "
            f"its vertices ({len(obj.data.vertices)} -> {mesh.vertex_count}) or corners; apply the modifiers "
            "or use mode atlas")
