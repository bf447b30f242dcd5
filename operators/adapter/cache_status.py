"""The visibility cache as the panel shows it, and the operator that clears it.

Whether the cached table is still valid is known for sure only by hashing the scene,
which a bake does. The panel tells from cheaper facts: after a bake this session, it
remembers a fingerprint of every mesh the table was made from (world matrix, evaluated
positions, triangles and bake UVs) and of the layout settings; a depsgraph handler
notes which meshes changed since, and only those are fingerprinted again. After a file
is opened, the state is unknown until the next bake.

The panel never computes any of this while it draws (folder listings, file sizes and
hashes would run on every redraw): it shows :func:`shown`, the status :func:`refresh`
last computed, which runs after a bake, after Clear Cache, on every depsgraph update
(the handler below; settings changes arrive there too), when a file is saved or
opened, and every few seconds for what other processes write to the folder.
"""
from __future__ import annotations

import hashlib
import os
import shutil

import bpy

import numpy as np

from ...core.visibility.cache import TABLE_FILE, folder_size
from . import extract, job
from .settings import bake_settings

# scene.session_uid -> what the last bake of this session left in the cache:
# {"table": path, "layout": layout settings, "uv_maps": {object: UV map}, "fingerprints": {object: hash},
#  "suspects": objects updated since they were last fingerprinted, "changed": those found changed}
_baked: dict[int, dict] = {}
# scene.session_uid -> the status the panel shows (:func:`status`'s dict, with the table path).
_shown: dict[int, dict] = {}
# Scenes whose panel found no status to show; a timer computes theirs.
_requested: set[int] = set()
# Seconds between two looks at the cache folders of the scenes the panel shows.
FOLDER_CHECK_SECONDS = 2.0
_FILE_FACTS = ("has_table", "table_bytes", "slots", "bytes")


def scene_slots(scene) -> list[str]:
    """The cache slot folders of ``scene`` (one per direction setting), existing ones only."""
    cache = job.visibility_cache(scene)
    if cache is None or not os.path.isdir(cache.folder):
        return []
    prefix = f"{cache.label}-"
    return sorted(os.path.join(cache.folder, name) for name in os.listdir(cache.folder)
                  if name.startswith(prefix) and os.path.isdir(os.path.join(cache.folder, name)))


def status(scene, depsgraph=None, known: dict | None = None) -> dict:
    """What the panel shows: whether the current settings have a cached table, whether it
    is still valid ('valid', 'stale' with the reasons, 'unknown', or 'none' without a
    table), and sizes.

    ``known``: an earlier status whose file facts (table, sizes, slots) are taken as they
    are, without reading the folder, if it was made for the same folder and table path.
    """
    cache = job.visibility_cache(scene)
    if cache is None:
        return {"enabled": False}
    settings = bake_settings(scene.visibake)
    table = cache.table_path(settings)
    if known is not None and known.get("enabled") and (known["folder"], known["table"]) == (cache.folder, table):
        files = {name: known[name] for name in _FILE_FACTS}
    else:
        slots = scene_slots(scene)
        has_table = os.path.exists(table)
        files = {"has_table": has_table, "table_bytes": os.path.getsize(table) if has_table else 0,
                 "slots": len(slots), "bytes": sum(folder_size(slot) for slot in slots)}
    validity, reasons = validity_of(scene, table, depsgraph) if files["has_table"] else ("none", [])
    return {"enabled": True, "folder": cache.folder, "table": table, **files, "validity": validity,
            "reasons": reasons}


def shown(scene) -> dict | None:
    """The status :func:`refresh` last computed for ``scene`` (None: none yet): all that
    draw code reads."""
    return _shown.get(scene.session_uid)


def refresh(scene, depsgraph=None, files: bool = True) -> dict:
    """Compute ``scene``'s :func:`status` and keep it for :func:`shown`.

    ``files`` False: read the folder only if the cache folder or table path changed
    since the last status (the depsgraph handler, which runs on every change).
    """
    known = None if files else _shown.get(scene.session_uid)
    _shown[scene.session_uid] = state = status(scene, depsgraph, known)
    return state


def request_refresh(scene) -> None:
    """For code that must not do the work itself (draw code, register): a timer computes
    the status right after it."""
    _requested.add(scene.session_uid)
    if not bpy.app.timers.is_registered(refresh_requested):
        bpy.app.timers.register(refresh_requested, first_interval=0.0)


def refresh_requested() -> None:
    """The timer of :func:`request_refresh`: the statuses asked for, then a redraw."""
    requested = set(_requested)
    _requested.clear()
    for scene in bpy.data.scenes:
        if scene.session_uid in requested:
            refresh(scene)
    _redraw_panels()
    return None


def _refresh_shown_folders() -> float:
    """Timer: read the folders of the statuses shown again (another process may bake or clear)."""
    changed = False
    for scene in bpy.data.scenes:
        before = _shown.get(scene.session_uid)
        if before is not None:
            changed |= refresh(scene) != before
    if changed:
        _redraw_panels()
    return FOLDER_CHECK_SECONDS


def _redraw_panels() -> None:
    window_manager = getattr(bpy.context, "window_manager", None)
    for window in window_manager.windows if window_manager is not None else []:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


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
        refresh(scene, depsgraph)
        return
    # Instances and curves, text or metaballs also take part (extract.scene_geometry); only
    # mesh objects are fingerprinted, the others' changes reach the cache through its key.
    uv_maps = {entry["name"]: entry.get("uv_map", "") for entry in report["objects"]
               if getattr(bpy.data.objects.get(entry["name"]), "type", None) == "MESH"}
    try:
        fingerprints = {name: fingerprint(bpy.data.objects[name], depsgraph, uv_map)
                        for name, uv_map in uv_maps.items()}
    except (KeyError, ReferenceError):  # an object renamed or removed since: the state is unknown
        _baked.pop(scene.session_uid, None)
        refresh(scene, depsgraph)
        return
    _baked[scene.session_uid] = {"table": cache_state["path"], "layout": _layout_settings(scene), "uv_maps": uv_maps,
                                 "fingerprints": fingerprints, "suspects": set(), "changed": set()}
    refresh(scene, depsgraph)


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
        for name in suspects:
            if fingerprint(bpy.data.objects[name], depsgraph, baked["uv_maps"][name]) == known[name]:
                baked["changed"].discard(name)  # as it was baked (moved back, or not changed after all)
            else:
                baked["changed"].add(name)
        # Hashed once per update: the next update of an object makes it a suspect again.
        baked["suspects"] -= set(suspects)
    changed = sorted(baked["changed"] & names)
    if changed:
        reasons.append(f"changed: {', '.join(changed)}")
    return ("stale" if reasons else "valid"), reasons


@bpy.app.handlers.persistent
def _on_depsgraph_update(scene, depsgraph) -> None:
    note_changes(scene, depsgraph)
    refresh(scene, depsgraph, files=False)


@bpy.app.handlers.persistent
def _on_save(*_args) -> None:
    # Saving names the cache after the file (and may move it beside the file).
    for scene in bpy.data.scenes:
        if scene.session_uid in _shown:
            refresh(scene)


@bpy.app.handlers.persistent
def _on_load(*_args) -> None:
    _shown.clear()
    _requested.clear()
    if bpy.context.scene is not None:
        refresh(bpy.context.scene)


_HANDLERS = (("depsgraph_update_post", _on_depsgraph_update), ("save_post", _on_save), ("load_post", _on_load))


def register_handlers() -> None:
    for name, handler in _HANDLERS:
        getattr(bpy.app.handlers, name).append(handler)
    if not bpy.app.timers.is_registered(_refresh_shown_folders):
        bpy.app.timers.register(_refresh_shown_folders, first_interval=FOLDER_CHECK_SECONDS, persistent=True)
    try:
        scenes = list(bpy.data.scenes)
    except AttributeError:  # Blender starting up: data is not readable yet; the handlers see the file load
        scenes = []
    # Not in register itself (folder listings, maybe mesh hashes): a timer right after it.
    for scene in scenes:
        request_refresh(scene)


def unregister_handlers() -> None:
    for name, handler in _HANDLERS:
        if handler in getattr(bpy.app.handlers, name):
            getattr(bpy.app.handlers, name).remove(handler)
    for timer in (_refresh_shown_folders, refresh_requested):
        if bpy.app.timers.is_registered(timer):
            bpy.app.timers.unregister(timer)
    _baked.clear()
    _shown.clear()
    _requested.clear()


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
    refresh(scene)
    return len(slots), freed


