"""Vertex-table mode against Cycles' colour-attribute bake, both lookups (run by ``benchmarks/run.py``).

The scene: a finely tessellated floor and wall meeting at a corner, a smooth sphere on
the floor, a sun and a point light, every object in vertex mode. Cycles bakes the same
DIFFUSE pass into a point-domain colour attribute (``tools.cycles_bake.
bake_diffuse_vertex_colors``); its converged bake (the profile's reference samples) is
the reference, its sample sweep gives the time it needs for VisiBake's error.
"""
from __future__ import annotations

import time

import bpy

import bmesh
import numpy as np

from tools.blender_compat import compat

SEGMENTS = {"smoke": 8, "full": 48}


def build(size: str) -> list:
    """The vertex scene in the current (empty) scene; returns its mesh objects."""
    def material(name, color):
        mat = bpy.data.materials.new(name)
        bsdf = compat.ensure_node_tree(mat).nodes["Principled BSDF"]
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        bsdf.inputs["Roughness"].default_value = 1.0
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
        return mat

    def obj(name, fill, mat, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), smooth=False):
        bm = bmesh.new()
        fill(bm)
        for face in bm.faces:
            face.smooth = smooth
        mesh = bpy.data.meshes.new(name)
        bm.to_mesh(mesh)
        bm.free()
        mesh.materials.append(mat)
        made = bpy.data.objects.new(name, mesh)
        made.location, made.rotation_euler = location, rotation
        bpy.context.scene.collection.objects.link(made)
        made.visibake.mode = "vertex"
        return made

    segments = SEGMENTS[size]
    world = bpy.data.worlds.new("Black")
    compat.ensure_node_tree(world).nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.context.scene.world = world
    objects = [
        obj("Floor", lambda bm: bmesh.ops.create_grid(bm, x_segments=segments, y_segments=segments, size=1.0),
            material("White", (0.8, 0.8, 0.8))),
        obj("Wall", lambda bm: bmesh.ops.create_grid(bm, x_segments=segments, y_segments=segments, size=1.0),
            material("Red", (0.8, 0.2, 0.1)), location=(1.0, 0.0, 1.0), rotation=(0.0, -np.pi / 2, 0.0)),
        obj("Ball", lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=2 * segments, v_segments=segments,
                                                         radius=0.3),
            material("Ivory", (0.7, 0.7, 0.6)), location=(0.2, -0.3, 0.3), smooth=True),
    ]
    point = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
    point.data.energy, point.data.shadow_soft_size = 150.0, 0.0
    point.location = (-0.3, 0.4, 1.2)
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy, sun.data.angle = 2.0, 0.0
    sun.rotation_euler = (np.radians(40), 0.0, np.radians(200))
    for light in (point, sun):
        bpy.context.scene.collection.objects.link(light)
    bpy.context.view_layer.update()
    return objects


def _stacked(colors: dict, names) -> np.ndarray:
    return np.concatenate([colors[name][:, :3] for name in names])


def _errors(ours: np.ndarray, reference: np.ndarray) -> dict:
    scale = float(np.sqrt(np.mean(reference ** 2)))
    return {"relative_rmse": float(np.sqrt(np.mean((ours - reference) ** 2)) / scale),
            "bias": float(ours.mean() / reference.mean() - 1.0)}


def run(job, profile: dict, bake_vertex_colors) -> list[dict]:
    """Rows of VisiBake (per direction count and lookup) and Cycles (per sample count)."""
    objects = build(profile["size"])
    names = [o.name for o in objects]
    props = bpy.context.scene.visibake
    props.passes, props.bounces, props.use_cache, props.bake_all = {"lighting"}, 2, False, True
    started = time.perf_counter()
    reference = _stacked(bake_vertex_colors(objects, bounces=2, samples=profile["reference_samples"]), names)
    reference_seconds = time.perf_counter() - started
    rows = []
    for samples in profile["cycles_samples"]:
        started = time.perf_counter()
        colors = bake_vertex_colors(objects, bounces=2, samples=samples, seed=1)
        rows.append({"method": "cycles", "samples": samples, "seconds": time.perf_counter() - started,
                     **_errors(_stacked(colors, names), reference)})
    for directions in profile["directions"]:
        for lookup in ("interpolate", "nearest"):
            props.directions, props.vertex_lookup = directions, lookup
            outcome = job.run_bake(bpy.context, objects)
            colors = {r.name: r.images["lighting"] for r in outcome.result.objects}
            rows.append({"method": "visibake", "lookup": lookup, "directions": directions,
                         "seconds": outcome.report["total_seconds"], "samples": int(sum(
                             entry["texels"] for entry in outcome.report["objects"])),
                         **_errors(_stacked(colors, names), reference)})
    for row in rows:
        row["reference_samples"] = profile["reference_samples"]
        row["reference_seconds"] = reference_seconds
    return rows
