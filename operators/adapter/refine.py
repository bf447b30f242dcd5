"""Refinement of coarse vertex-mode objects: a subdivided copy, never the user's mesh.

Where a vertex-mode object's triangles are too large for its light (a shadow edge
inside them, see core.outputs.diagnostics), VisiBake can bake a copy instead: the faces of
those triangles are subdivided in a new mesh, a new object shows it in the original's
place, and the original is hidden from renders and the viewport. Both are marked as
VisiBake's; :func:`undo_refinement` puts everything back (a bake that failed after
refining, or the user's choice).

Refining VisiBake's own copy again (a re-bake of a refined file) makes no copy of the copy:
the copy gets the finer mesh in place, the original stays hidden and stays the source its
name and :data:`REFINED_FROM_KEY` point to. :func:`keep_refinement` drops the copy's
previous mesh once the bake succeeded; :func:`undo_refinement` puts it back otherwise.
"""
from __future__ import annotations

import bpy

import bmesh
import numpy as np

from ...core.outputs import names
from . import compat
from .extract import read_values

REFINED_FROM_KEY = "visibake_refined_from"  # on the copy: the original object's name
PREVIOUS_MESH_KEY = "visibake_refined_previous_mesh"  # on a copy refined again, until the bake is kept
SUFFIX = " (VisiBake refined)"


def refined_name(source_name: str) -> str:
    """``<source> (VisiBake refined)``, hashed rather than cut by Blender when too long."""
    return names.datablock_name("", [source_name], compat.MAX_NAME_BYTES, suffix=SUFFIX)


def refined_copy(original: bpy.types.Object, triangles: np.ndarray) -> bpy.types.Object:
    """A copy of ``original`` with the faces of its loop ``triangles`` subdivided once.

    The copy takes the original's place: same transform, materials and collections;
    the original is hidden (render and viewport) so it neither shows nor occludes twice.
    """
    if original.get(REFINED_FROM_KEY):
        return _refine_in_place(original, triangles)
    mesh = original.data
    refined = _refined_mesh(mesh, triangles, refined_name(mesh.name))
    copy = original.copy()
    copy.data = refined
    copy.name = refined_name(original.name)
    copy[REFINED_FROM_KEY] = original.name
    copy.visibake.mode = "vertex"
    for collection in original.users_collection:
        collection.objects.link(copy)
    original.hide_render = True
    original.hide_set(True)
    return copy


def _refine_in_place(copy: bpy.types.Object, triangles: np.ndarray) -> bpy.types.Object:
    """VisiBake's refined ``copy`` with the faces of its loop ``triangles`` subdivided once more.

    Its mesh is swapped, not the object: the result stays one copy named after the original.
    """
    previous = copy.data
    source = bpy.data.objects.get(copy[REFINED_FROM_KEY])
    source_mesh_name = source.data.name if source is not None and source.data is not None else previous.name
    copy.data = _refined_mesh(previous, triangles, refined_name(source_mesh_name))
    copy[PREVIOUS_MESH_KEY] = previous.name
    return copy


def _refined_mesh(mesh: bpy.types.Mesh, triangles: np.ndarray, name: str) -> bpy.types.Mesh:
    """A new mesh ``name``: ``mesh`` with the faces of its loop ``triangles`` subdivided once."""
    mesh.calc_loop_triangles()
    polygon_of = read_values(mesh.loop_triangles, "polygon_index", len(mesh.loop_triangles), 1, np.int32)
    faces = set(int(p) for p in polygon_of[np.asarray(triangles, np.int64)])
    bm = bmesh.new()
    try:
        bm.from_mesh(mesh)
        bm.faces.ensure_lookup_table()
        edges = {edge for index in faces for edge in bm.faces[index].edges}
        bmesh.ops.subdivide_edges(bm, edges=list(edges), cuts=1, use_grid_fill=True)
        refined = bpy.data.meshes.new(name)
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
    return refined


def keep_refinement(copy: bpy.types.Object) -> None:
    """The bake of ``copy`` succeeded: drop the mesh it had before it was refined again."""
    previous_name = copy.pop(PREVIOUS_MESH_KEY, None)
    previous = bpy.data.meshes.get(previous_name) if previous_name else None
    if previous is not None and previous.users == 0:
        intended = previous.name
        bpy.data.meshes.remove(previous)
        # The new mesh was made while the previous one held its name (and got a ``.001``).
        copy.data.name = intended


def undo_refinement(copy: bpy.types.Object) -> None:
    """Remove a refined copy and show its original again; a copy refined again gets its previous mesh back."""
    previous_name = copy.pop(PREVIOUS_MESH_KEY, None)
    if previous_name is not None:
        refined, previous = copy.data, bpy.data.meshes.get(previous_name)
        if previous is not None:
            copy.data = previous
            if refined.users == 0:
                bpy.data.meshes.remove(refined)
        return
    original = bpy.data.objects.get(copy.get(REFINED_FROM_KEY, ""))
    mesh = copy.data
    bpy.data.objects.remove(copy)
    if mesh is not None and mesh.users == 0:
        bpy.data.meshes.remove(mesh)
    if original is not None:
        original.hide_render = False
        original.hide_set(False)
