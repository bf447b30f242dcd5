"""Show Baked Lighting and Remove Preview: the operators over :mod:`adapter.preview_nodes`."""
from __future__ import annotations

import bpy

from ..core.errors import BakeRefused
from .adapter.job import output_objects
from .adapter.preview_nodes import add_preview, remove_preview


class VISIBAKE_OT_preview_add(bpy.types.Operator):
    """Show the baked lighting in the viewport and in renders: each baked object's materials get a node group \
emitting it, as their active output; your nodes stay as they are"""

    bl_idname = "visibake.preview_add"
    bl_label = "Show Baked Lighting"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        objects = output_objects(context, context.scene.visibake)
        try:
            wired, warnings = add_preview(objects)
        except BakeRefused as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for warning in warnings:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, f"VisiBake: baked lighting shown in {wired} material(s)")
        return {"FINISHED"}


class VISIBAKE_OT_preview_remove(bpy.types.Operator):
    """Remove the baked-lighting preview from every material and make their own outputs active again"""

    bl_idname = "visibake.preview_remove"
    bl_label = "Remove Preview"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        changed = remove_preview()
        self.report({"INFO"}, f"VisiBake: preview removed from {changed} material(s)")
        return {"FINISHED"}


classes = (VISIBAKE_OT_preview_add, VISIBAKE_OT_preview_remove)
