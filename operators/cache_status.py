"""The visibility cache as the panel shows it, and the operator that clears it."""
from __future__ import annotations

import os
import shutil

import bpy

from ..core.cache import TABLE_FILE, folder_size
from . import job


def scene_slots(scene) -> list[str]:
    """The cache slot folders of ``scene`` (one per direction setting), existing ones only."""
    cache = job.visibility_cache(scene)
    if cache is None or not os.path.isdir(cache.folder):
        return []
    prefix = f"{cache.label}-"
    return sorted(os.path.join(cache.folder, name) for name in os.listdir(cache.folder)
                  if name.startswith(prefix) and os.path.isdir(os.path.join(cache.folder, name)))


def status(scene) -> dict:
    """What the panel shows: whether the current settings have a cached table, and sizes.

    The table's validity against the geometry is known only by hashing the scene, which
    a bake does; the panel shows the state the last bake reported.
    """
    cache = job.visibility_cache(scene)
    if cache is None:
        return {"enabled": False}
    settings = scene.visibake.to_bake_settings()
    table = cache.table_path(settings)
    slots = scene_slots(scene)
    return {"enabled": True, "folder": cache.folder, "has_table": os.path.exists(table),
            "table_bytes": os.path.getsize(table) if os.path.exists(table) else 0,
            "slots": len(slots), "bytes": sum(folder_size(slot) for slot in slots)}


class VISIBAKE_OT_clear_cache(bpy.types.Operator):
    """Delete this scene's cached visibility (every direction setting); the next bake traces it again"""

    bl_idname = "visibake.clear_cache"
    bl_label = "Clear Cache"
    bl_options = {"REGISTER"}

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event)

    def execute(self, context):
        slots = scene_slots(context.scene)
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
        self.report({"INFO"}, f"VisiBake: cleared {len(slots)} cached table(s), {freed / 2**20:.1f} MiB")
        return {"FINISHED"}


classes = (VISIBAKE_OT_clear_cache,)
