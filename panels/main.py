"""The VisiBake tab of the 3D viewport sidebar (N-panel)."""
import json

import bpy

from ..operators.adapter import cache_status, device
from . import properties
from .preferences import apply_default_preset_to_new_scenes


class VIEW3D_PT_visibake(bpy.types.Panel):
    bl_label = "VisiBake"
    bl_idname = "VIEW3D_PT_visibake"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VisiBake"

    def draw(self, context):
        layout = self.layout
        props = context.scene.visibake
        _offer_default_preset(props)
        layout.use_property_split = True
        layout.use_property_decorate = False
        column = layout.column()
        column.prop(props, "preset")
        column.prop(props, "directions")
        column.prop(props, "bounces")
        column.prop(props, "shadows")
        column.prop(props, "rotate")
        seed = column.row()
        seed.active = props.rotate
        seed.prop(props, "seed")
        column.separator()
        column.prop(props, "resolution")
        column.prop(props, "texel_density")
        column.prop(props, "margin")
        column.prop(props, "mode")
        column.prop(props, "vertex_lookup")
        column.prop(props, "refine_vertex_objects")
        column.separator()
        column.prop(props, "bake_all")
        prefs = device.preferences()
        if prefs is not None:
            column.prop(prefs, "device", text="Device (Preference)")
        column.prop(props, "output_dir")
        column.prop(props, "light_groups")
        column.prop(props, "use_cache")
        if props.use_cache:
            column.prop(props, "cache_dir")
        layout.label(text="Passes")
        layout.row().prop(props, "passes", expand=True)
        obj = context.object
        if obj is not None and obj.type == "MESH":
            layout.prop(obj.visibake, "role", text=f"{obj.name} Role")
            layout.prop(obj.visibake, "resolution", text=f"{obj.name} Resolution")
            layout.prop(obj.visibake, "mode", text=f"{obj.name} Mode")
            layout.prop(obj.visibake, "texel_density", text=f"{obj.name} Texels per Unit")
        row = layout.row(align=True)
        row.operator("visibake.bake", icon="RENDER_STILL")
        row.operator("visibake.relight", icon="LIGHT")
        row = layout.row(align=True)
        row.operator("visibake.preview_add", icon="SHADING_RENDERED")
        row.operator("visibake.preview_remove", icon="X")
        if props.use_cache:
            box = layout.box()
            state = cache_status.status(context.scene)
            size = f"{state['table_bytes'] / 2**20:.0f} MiB"
            if not state["has_table"]:
                box.label(text="Cache: no table for these settings yet", icon="INFO")
            elif state["validity"] == "valid":
                box.label(text=f"Cache: valid for the scene as it is, {size}", icon="CHECKMARK")
            elif state["validity"] == "stale":
                box.label(text=f"Cache: stale, {size}; the next bake re-traces what changed", icon="ERROR")
                for reason in state["reasons"]:
                    box.label(text=reason, icon="BLANK1")
            else:
                box.label(text=f"Cache: table for these settings, {size} (checked at the next bake)", icon="FILE_CACHE")
            box.label(text=f"{state['slots']} setting(s), {state['bytes'] / 2**20:.0f} MiB in {state['folder']}")
            box.operator("visibake.clear_cache", icon="TRASH")
        last = context.scene.get("visibake_last_report")
        if last:
            layout.label(text=last)


def _offer_default_preset(props) -> None:
    """A scene added during the session has no settings yet: give it the preferred preset.

    Draw code may not write to the scene, so a timer does it right after this draw.
    """
    prefs = device.preferences()
    if prefs is None or prefs.default_preset == "NONE" or not properties.settings_untouched(props):
        return
    if not bpy.app.timers.is_registered(apply_default_preset_to_new_scenes):
        bpy.app.timers.register(apply_default_preset_to_new_scenes, first_interval=0.0)


def report_lines(report: dict) -> list[tuple[str, str]]:
    """(text, icon) lines of a bake report for the panel: stage times, rays, skips, warnings."""
    lines = [(f"{report.get('total_seconds', 0):.1f} s in total", "TIME")]
    for stage, seconds in report.get("stage_seconds", {}).items():
        lines.append((f"{stage}: {seconds:.2f} s", "BLANK1"))
    rays = report.get("rays", {})
    lines.append((f"rays: {rays.get('visibility_cast', 0):,} traced, "
                  f"{rays.get('visibility_skipped_below_horizon', 0):,} below the horizon skipped", "LIGHT_SUN"))
    cache = report.get("cache", {})
    if cache.get("state", "off") != "off":
        lines.append((f"cache: {cache['state']}" + (f" ({cache['message']})" if cache.get("message") else ""),
                      "FILE_CACHE"))
    device = report.get("device", {})
    if device:
        lines.append((f"device: {device.get('used')} ({device.get('renderer', 'numpy')})", "MEMORY"))
    lines += [(f"skipped: {item}", "FORWARD") for item in report.get("skipped", [])]
    lines += [(item, "ERROR") for item in report.get("warnings", [])]
    return lines


class VISIBAKE_UL_objects(bpy.types.UIList):
    """The scene's meshes with their VisiBake role, mode and resolution."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_property, index=0, flt_flag=0):
        row = layout.row(align=True)
        row.label(text=item.name, icon="MESH_DATA")
        row.prop(item.visibake, "role", text="")
        row.prop(item.visibake, "mode", text="")
        row.prop(item.visibake, "resolution", text="")
        row.prop(item.visibake, "texel_density", text="")

    def filter_items(self, context, data, property):
        objects = getattr(data, property)
        flags = [self.bitflag_filter_item if obj.type == "MESH" else 0 for obj in objects]
        return flags, []


class VIEW3D_PT_visibake_objects(bpy.types.Panel):
    bl_label = "Objects"
    bl_idname = "VIEW3D_PT_visibake_objects"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VisiBake"
    bl_parent_id = "VIEW3D_PT_visibake"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        self.layout.template_list("VISIBAKE_UL_objects", "", context.scene, "objects", context.scene.visibake,
                                  "active_object_index", rows=4)


class VIEW3D_PT_visibake_report(bpy.types.Panel):
    bl_label = "Last Bake"
    bl_idname = "VIEW3D_PT_visibake_report"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VisiBake"
    bl_parent_id = "VIEW3D_PT_visibake"
    bl_options = {"DEFAULT_CLOSED"}

    @classmethod
    def poll(cls, context):
        return "visibake_report" in context.scene

    def draw(self, context):
        column = self.layout.column(align=True)
        try:
            report = json.loads(context.scene["visibake_report"])
        except (TypeError, ValueError):
            column.label(text="The last report cannot be read")
            return
        for text, icon in report_lines(report):
            column.label(text=text, icon=icon)


classes = (VIEW3D_PT_visibake, VISIBAKE_UL_objects, VIEW3D_PT_visibake_objects, VIEW3D_PT_visibake_report)
