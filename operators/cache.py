"""Clear Cache: the operator over :func:`adapter.cache_status.clear`."""
import bpy

from .adapter.cache_status import clear


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


classes = (VISIBAKE_OT_clear_cache,)
