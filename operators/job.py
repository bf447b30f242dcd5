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
import numpy as np

from ..core.pipeline import BakeResult, bake, peak_memory_bytes
from ..core.scene import Scene
from . import extract, layout, writeback


class BakeInputError(ValueError):
    """Bad input (objects, settings, names): the message is meant for the user."""


@dataclass
class JobResult:
    result: BakeResult
    report: dict
    files: list[str] = field(default_factory=list)


def _evaluated_geometry(obj, depsgraph):
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        count = len(mesh.loop_triangles)
        positions = np.empty(len(mesh.vertices) * 3, np.float64)
        mesh.vertices.foreach_get("co", positions)
        triangles = np.empty(count * 3, np.int32)
        loops = np.empty(count * 3, np.int64)
        mesh.loop_triangles.foreach_get("vertices", triangles)
        mesh.loop_triangles.foreach_get("loops", loops)
        uv = extract.mesh_corner_uv(mesh, loops.reshape(-1, 3))
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array([list(r) for r in obj.matrix_world], np.float64)
    positions = positions.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    return positions, triangles.reshape(-1, 3), uv


def output_objects(context, props) -> list[bpy.types.Object]:
    """The objects a bake writes results for: selected meshes, or all with ``bake_all``."""
    meshes = extract.scene_meshes(context.scene)
    if props.bake_all:
        return meshes
    return [o for o in meshes if o.select_get()]


def run_bake(context, objects, out_dir: str | None = None, previews: bool = False,
             progress=None) -> JobResult:
    """Bake ``objects`` (mesh objects) with the settings in ``context.scene.visibake``.

    Every other visible mesh of the scene occludes and reflects light but gets no
    output. Raises :class:`BakeInputError` for bad input, ``core.pipeline.Cancelled``
    if ``progress`` cancels; in both cases the scene is left unchanged.
    """
    scene = context.scene
    props = scene.visibake
    if props.mode == "vertex":
        raise BakeInputError("vertex mode is not implemented yet; use mode atlas or auto")
    if not objects:
        raise BakeInputError("no mesh objects to bake: select some, or enable All Objects")
    settings = props.to_bake_settings()
    try:
        settings.validate()
    except ValueError as error:
        raise BakeInputError(str(error)) from None
    try:
        writeback.check_image_names(writeback.image_name(o.name, p) for o in objects for p in settings.passes)
    except ValueError as error:
        raise BakeInputError(str(error)) from None

    times = {}
    started = time.perf_counter()
    outputs = set(o.name for o in objects)
    all_meshes = extract.scene_meshes(scene)
    warnings: list[str] = []
    created: list[tuple[bpy.types.Mesh, str]] = []
    try:
        depsgraph = context.evaluated_depsgraph_get()
        plans = {}
        for index, obj in enumerate(all_meshes):
            positions, triangles, uv = _evaluated_geometry(obj, depsgraph)
            if len(triangles) == 0:
                warnings.append(f"object {obj.name!r} has no faces and was skipped")
                continue
            try:
                plan = layout.plan_layout(obj, uv, positions, triangles, props, obj.name in outputs)
            except ValueError as error:
                raise BakeInputError(str(error)) from None
            if plan.created:
                created.append((obj.data, plan.uv_map))
            plans[obj.name] = plan
            if progress:
                progress("layout", (index + 1) / len(all_meshes))
        times["layout"] = time.perf_counter() - started

        t = time.perf_counter()
        depsgraph = context.evaluated_depsgraph_get()
        depsgraph.update()
        meshes = []
        for obj in all_meshes:
            plan = plans.get(obj.name)
            if plan is None:
                continue
            mesh = extract.read_mesh(obj, depsgraph, plan.uv_map, plan.resolution, obj.name in outputs, warnings)
            if plan.internal_uv is not None:
                mesh.uv_maps[plan.uv_map] = plan.internal_uv
            meshes.append(mesh)
        core_scene = Scene(meshes=meshes, lights=[extract.read_light(o) for o in extract.scene_lights(scene)],
                           world=extract.read_world(scene, warnings))
        times["extract"] = time.perf_counter() - t
        if not any(m.output for m in meshes):
            raise BakeInputError("none of the objects to bake has faces")
        try:
            result = bake(core_scene, settings, progress)
        except ValueError as error:
            raise BakeInputError(str(error)) from None
    except BaseException:
        layout.remove_created_uv_maps(created)
        raise

    t = time.perf_counter()
    files = writeback.write_outputs(result.objects, out_dir, previews)
    times["write"] = time.perf_counter() - t

    report = result.report
    report["stage_seconds"] = {**{k: round(v, 4) for k, v in times.items() if k != "write"},
                               **report["stage_seconds"], "write": round(times["write"], 4)}
    report["total_seconds"] = round(time.perf_counter() - started, 4)
    report["peak_memory_bytes"] = peak_memory_bytes()
    report["files"] = files
    report["warnings"] = warnings + report["warnings"]
    for entry in report["objects"]:
        plan = plans.get(entry["name"])
        if plan is not None:
            entry["uv_map_reason"] = plan.reason
            entry["uv_map_created"] = plan.created
    report["blender_version"] = bpy.app.version_string
    report["lights"] = [light.name for light in core_scene.lights]
    return JobResult(result=result, report=report, files=files)


def write_report(path: str, report: dict) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(report, handle, indent=2, default=float)
