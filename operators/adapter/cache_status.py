"""The visibility cache as the panel shows it, and the operator that clears it.

Whether the cached table is still valid is known for sure only by hashing the scene,
which a bake does. The panel tells from cheaper facts: after a bake this session, it
remembers a fingerprint of every mesh the table was made from (world matrix, evaluated
positions, triangles and bake UVs) and of the layout settings; a depsgraph handler
notes which meshes changed since, and only those are fingerprinted again. After a file
is opened, the state is unknown until the next bake.
"""
from __future__ import annotations

import hashlib
import os
import shutil

import bpy
import numpy as np

from ...core.visibility.cache import TABLE_FILE, folder_size
from . import extract, job

# scene.session_uid -> what the last bake of this session left in the cache:
# {"table": path, "layout": layout settings, "fingerprints": {object: hash}, "suspects": set}
_baked: dict[int, dict] = {}


def scene_slots(scene) -> list[str]:
    """The cache slot folders of ``scene`` (one per direction setting), existing ones only."""
    cache = job.visibility_cache(scene)
    if cache is None or not os.path.isdir(cache.folder):
        return []
    prefix = f"{cache.label}-"
    return sorted(os.path.join(cache.folder, name) for name in os.listdir(cache.folder)
                  if name.startswith(prefix) and os.path.isdir(os.path.join(cache.folder, name)))


def status(scene, depsgraph=None) -> dict:
    """What the panel shows: whether the current settings have a cached table, whether it
    is still valid ('valid', 'stale' with the reasons, or 'unknown'), and sizes."""
    cache = job.visibility_cache(scene)
    if cache is None:
        return {"enabled": False}
    settings = scene.visibake.to_bake_settings()
    table = cache.table_path(settings)
    slots = scene_slots(scene)
    has_table = os.path.exists(table)
    validity, reasons = validity_of(scene, table, depsgraph) if has_table else ("none", [])
    return {"enabled": True, "folder": cache.folder, "has_table": has_table,
            "table_bytes": os.path.getsize(table) if has_table else 0, "validity": validity, "reasons": reasons,
            "slots": len(slots), "bytes": sum(folder_size(slot) for slot in slots)}


def _layout_settings(scene) -> tuple:
    """The settings besides the direction set that decide where samples lie."""
    props = scene.visibake
    per_object = {o.name: (o.visibake.resolution, o.visibake.texel_density, o.visibake.mode)
                  for o in extract.scene_meshes(scene)}
    return (props.resolution, props.texel_density, props.mode), per_object


def fingerprint(obj, depsgraph, uv_map: str) -> str:
    """Hash of what a mesh contributes to the table's key, read from the evaluated mesh:
    world matrix, positions, corners and the UV map it is baked on ('' for none)."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.data
    hasher = hashlib.blake2b(digest_size=16)
    hasher.update(np.array(obj.matrix_world, np.float64).tobytes())
    positions = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", positions)
    hasher.update(positions.tobytes())
    corners = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", corners)
    hasher.update(corners.tobytes())
    layer = mesh.uv_layers.get(uv_map) if uv_map else None
    if layer is not None:
        uv = np.empty(len(mesh.loops) * 2, np.float32)
        layer.uv.foreach_get("vector", uv)
        hasher.update(uv.tobytes())
    return hasher.hexdigest()


def remember_bake(scene, depsgraph, report: dict) -> None:
    """After a bake that left a valid table in the cache: remember what it was made from."""
    cache_state = report.get("cache", {})
    # Every state but these left the table for the scene as it is (read, traced, updated or
    # rebuilt); bytes_on_disk is 0 where writing it failed.
    if cache_state.get("state") in ("off", "unused", None) or not cache_state.get("bytes_on_disk"):
        _baked.pop(scene.session_uid, None)
        return
    uv_maps = {entry["name"]: entry.get("uv_map", "") for entry in report["objects"]}
    try:
        fingerprints = {name: fingerprint(bpy.data.objects[name], depsgraph, uv_map)
                        for name, uv_map in uv_maps.items()}
    except (KeyError, ReferenceError):  # an object renamed or removed since: the state is unknown
        _baked.pop(scene.session_uid, None)
        return
    _baked[scene.session_uid] = {"table": cache_state["path"], "layout": _layout_settings(scene), "uv_maps": uv_maps,
                                 "fingerprints": fingerprints, "suspects": set()}


def note_changes(scene, depsgraph) -> None:
    """depsgraph_update_post: note the meshes that may have changed since the last bake."""
    baked = _baked.get(scene.session_uid)
    if baked is None:
        return
    for update in depsgraph.updates:
        if isinstance(update.id, bpy.types.Object) and update.id.type == "MESH" and (
                update.is_updated_geometry or update.is_updated_transform):
            baked["suspects"].add(update.id.original.name)


def validity_of(scene, table: str, depsgraph=None) -> tuple[str, list[str]]:
    """('valid' | 'stale' | 'unknown', reasons) of the cached ``table`` for the scene as it is."""
    baked = _baked.get(scene.session_uid)
    if baked is None or baked["table"] != table:
        return "unknown", []
    reasons = []
    (scene_layout, per_object), (baked_scene_layout, baked_per_object) = _layout_settings(scene), baked["layout"]
    if scene_layout != baked_scene_layout or any(
            per_object[name] != baked_per_object[name] for name in set(per_object) & set(baked_per_object)):
        reasons.append("resolution or mode changed")
    names = {o.name for o in extract.scene_meshes(scene)}
    known = baked["fingerprints"]
    added, removed = sorted(names - set(known)), sorted(set(known) - names)
    if added:
        reasons.append(f"added: {', '.join(added)}")
    if removed:
        reasons.append(f"removed or hidden: {', '.join(removed)}")
    suspects = sorted(baked["suspects"] & names & set(known))
    if suspects:
        depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
        changed = [name for name in suspects
                   if fingerprint(bpy.data.objects[name], depsgraph, baked["uv_maps"][name]) != known[name]]
        baked["suspects"] -= set(suspects) - set(changed)  # checked: unchanged after all
        if changed:
            reasons.append(f"changed: {', '.join(changed)}")
    return ("stale" if reasons else "valid"), reasons


@bpy.app.handlers.persistent
def _on_depsgraph_update(scene, depsgraph) -> None:
    note_changes(scene, depsgraph)


def register_handlers() -> None:
    bpy.app.handlers.depsgraph_update_post.append(_on_depsgraph_update)


def unregister_handlers() -> None:
    if _on_depsgraph_update in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(_on_depsgraph_update)
    _baked.clear()


class VISIBAKE_OT_clear_cache(bpy.types.Operator):
    """Delete this scene's cached visibility (every direction setting); the next bake traces it again"""

    bl_idname = "visibake.clear_cache"
    bl_label = "Clear Cache"
    bl_options = {"REGISTER"}

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        slots, freed = clear(context.scene)
        self.report({"INFO"}, f"VisiBake: cleared {slots} cached table(s), {freed / 2**20:.1f} MiB")
        return {"FINISHED"}


def clear(scene) -> tuple[int, int]:
    """Delete ``scene``'s cached visibility, every direction setting; returns (slots, bytes freed)."""
    slots = scene_slots(scene)
    freed = 0
    for slot in slots:
        # Only what VisiBake writes: its table and lighting files (and nothing else
        # that might have been put in the folder).
        for name in os.listdir(slot):
            path = os.path.join(slot, name)
            if os.path.isfile(path) and (name == TABLE_FILE or name.endswith(".npz")):
                freed += os.path.getsize(path)
                os.remove(path)
        if not os.listdir(slot):
            shutil.rmtree(slot, ignore_errors=True)
    _baked.pop(scene.session_uid, None)
    return len(slots), freed


classes = (VISIBAKE_OT_clear_cache,)
