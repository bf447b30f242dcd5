"""Refinement of coarse vertex-mode objects: a subdivided copy, never the user's mesh.

Where a vertex-mode object's triangles are too large for its light (a shadow edge
inside them, see core.outputs.diagnostics), VisiBake can bake a copy instead: the faces of
those triangles are subdivided in a new mesh, a new object shows it in the original's
place, and the original is hidden from renders and the viewport. Both are marked as
VisiBake's; :func:`undo_refinement` puts everything back (a bake that failed after
refining, or the user's choice).
"""
from __future__ import annotations

import bpy

import bmesh
import numpy as np

REFINED_FROM_KEY = "visibake_refined_from"  # on the copy: the original object's name


def refined_copy(original: bpy.types.Object, triangles: np.ndarray) -> bpy.types.Object:
    """A copy of ``original`` with the faces of its loop ``triangles`` subdivided once.

    The copy takes the original's place: same transform, materials and collections;
    the original is hidden (render and viewport) so it neither shows nor occludes twice.
    """
    mesh = original.data
    mesh.calc_loop_triangles()
    polygon_of = np.empty(len(mesh.loop_triangles), np.int64)
    mesh.loop_triangles.foreach_get("polygon_index", polygon_of)
    faces = set(int(p) for p in polygon_of[np.asarray(triangles, np.int64)])
    bm = bmesh.new()
    try:
        bm.from_mesh(mesh)
        bm.faces.ensure_lookup_table()
        edges = {edge for index in faces for edge in bm.faces[index].edges}
        bmesh.ops.subdivide_edges(bm, edges=list(edges), cuts=1, use_grid_fill=True)
        refined = bpy.data.meshes.new(f"{mesh.name} (VisiBake refined)")
        bm.to_mesh(refined)
    finally:
        bm.free()
    for material in mesh.materials:
        refined.materials.append(material)
    # The original's VisiBake results do not fit the new vertices: the bake writes anew.
    for name in list(mesh.get("visibake_color_attributes", [])):
        if name in refined.attributes:
            refined.attributes.remove(refined.attributes[name])
    if "visibake_color_attributes" in refined:
        del refined["visibake_color_attributes"]
    copy = original.copy()
    copy.data = refined
    copy.name = f"{original.name} (VisiBake refined)"
    copy[REFINED_FROM_KEY] = original.name
    copy.visibake.mode = "vertex"
    for collection in original.users_collection:
        collection.objects.link(copy)
    original.hide_render = True
    original.hide_set(True)
    return copy


def undo_refinement(copy: bpy.types.Object) -> None:
    """Remove a refined copy and show its original again."""
    original = bpy.data.objects.get(copy.get(REFINED_FROM_KEY, ""))
    mesh = copy.data
    bpy.data.objects.remove(copy)
    if mesh is not None and mesh.users == 0:
        bpy.data.meshes.remove(mesh)
    if original is not None:
        original.hide_render = False
        original.hide_set(False)
