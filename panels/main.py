"""The VisiBake tab of the 3D viewport sidebar (N-panel)."""
import bpy

from ..operators import cache_status


class VIEW3D_PT_visibake(bpy.types.Panel):
    bl_label = "VisiBake"
    bl_idname = "VIEW3D_PT_visibake"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VisiBake"

    def draw(self, context):
        layout = self.layout
        props = context.scene.visibake
        layout.use_property_split = True
        layout.use_property_decorate = False
        column = layout.column()
        column.prop(props, "preset")
        column.prop(props, "directions")
        column.prop(props, "bounces")
        column.prop(props, "shadows")
        column.prop(props, "resolution")
        column.prop(props, "texel_density")
        column.prop(props, "mode")
        column.prop(props, "vertex_lookup")
        column.prop(props, "bake_all")
        column.prop(props, "output_dir")
        column.prop(props, "light_groups")
        column.prop(props, "use_cache")
        if props.use_cache:
            column.prop(props, "cache_dir")
        layout.label(text="Passes")
        layout.row().prop(props, "passes", expand=True)
        obj = context.object
        if obj is not None and obj.type == "MESH":
            layout.prop(obj.visibake, "resolution", text=f"{obj.name} Resolution")
            layout.prop(obj.visibake, "mode", text=f"{obj.name} Mode")
        row = layout.row(align=True)
        row.operator("visibake.bake", icon="RENDER_STILL")
        row.operator("visibake.relight", icon="LIGHT")
        if props.use_cache:
            box = layout.box()
            state = cache_status.status(context.scene)
            if state["has_table"]:
                box.label(text=f"Cache: table for these settings, {state['table_bytes'] / 2**20:.0f} MiB",
                          icon="CHECKMARK")
            else:
                box.label(text="Cache: no table for these settings yet", icon="INFO")
            box.label(text=f"{state['slots']} setting(s), {state['bytes'] / 2**20:.0f} MiB in {state['folder']}")
            box.operator("visibake.clear_cache", icon="TRASH")
        last = context.scene.get("visibake_last_report")
        if last:
            layout.label(text=last)


classes = (VIEW3D_PT_visibake,)
