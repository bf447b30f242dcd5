"""The VisiBake tab of the 3D viewport sidebar (N-panel).

Draw code reads state computed elsewhere and never touches the disk or hashes a mesh:
the cache's status comes from ``cache_status.shown`` (computed after bakes, changes and
on a timer), the last report from the scene, where the bake stored it.
"""
import json

import bpy

from ..core.outputs import summary as report_texts
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
        column.prop(props, "target_error")
        # With a target, the bake chooses the directions: the count it chose is where the next
        # pilot starts (0 starts afresh), and Directions rests.
        chosen = column.row()
        chosen.active = props.target_error > 0
        chosen.prop(props, "chosen_directions")
        directions = column.row()
        directions.active = props.target_error <= 0
        directions.prop(props, "directions")
        column.prop(props, "bounces")
        column.prop(props, "shadows")
        column.prop(props, "rotate")
        seed = column.row()
        seed.active = props.rotate
        seed.prop(props, "seed")
        column.prop(props, "interleave")
        column.separator()
        column.prop(props, "resolution")
        column.prop(props, "texel_density")
        column.prop(props, "margin")
        column.prop(props, "footprint_samples")
        column.prop(props, "sharp_contacts")
        column.prop(props, "stitch_seams")
        column.prop(props, "mode")
        column.prop(props, "vertex_lookup")
        column.prop(props, "refine_vertex_objects")
        column.separator()
        column.prop(props, "bake_all")
        prefs = device.preferences()
        if prefs is not None:
            column.prop(prefs, "device", text="Device (Preference)")
            column.prop(prefs, "cluster_workers", text="Cluster Workers (Preference)")
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
            _draw_cache(layout.box(), context.scene)
        last = context.scene.get("visibake_last_report")
        if last:
            layout.label(text=last)


def _draw_cache(box, scene) -> None:
    """The cache's status as last computed (cache_status.shown), and Clear Cache."""
    state = cache_status.shown(scene)
    if state is None or not state["enabled"]:
        # Not computed yet (a scene new to this session): a timer does it right after this draw.
        cache_status.request_refresh(scene)
        box.label(text="Cache: looking at the cache folder...", icon="TIME")
        box.operator("visibake.clear_cache", icon="TRASH")
        return
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
    """(text, icon) lines of a bake report for the panel (core.outputs.summary.panel_lines)."""
    return report_texts.panel_lines(report)


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
            lines = report_lines(json.loads(context.scene["visibake_report"]))
        except (TypeError, ValueError, KeyError, AttributeError):  # not JSON, or not a report of this version
            column.label(text="The last report cannot be read")
            return
        for text, icon in lines:
            column.label(text=text, icon=icon)


NO_VOLUMES = "No volumes (Volume objects, meshes with a Principled Volume)"


class _Section:
    """A closed-by-default section under VisiBake's main panel."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "VisiBake"
    bl_parent_id = "VIEW3D_PT_visibake"
    bl_options = {"DEFAULT_CLOSED"}


class VIEW3D_PT_visibake_volumes(_Section, bpy.types.Panel):
    bl_label = "Volumes"
    bl_idname = "VIEW3D_PT_visibake_volumes"

    def draw(self, context):
        from ..operators import volume

        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.visibake
        targets = volume.volume_targets(context)
        selected = any(o.select_get() for o in targets)
        names = ", ".join(o.name for o in targets[:3]) + (", ..." if len(targets) > 3 else "")
        layout.label(text=(f"{'Selected' if selected else 'All'}: {names}" if targets else NO_VOLUMES),
                     icon="VOLUME_DATA")
        column = layout.column()
        for name in ("volume_resolution", "volume_directions", "volume_bounces", "volume_points"):
            column.prop(props, name)
        folder = volume.output_folder(context)
        layout.label(text=f"Grids into {folder}" if folder else "Set an Output Folder (or save the file)")
        row = layout.row()
        row.enabled = bool(targets) and bool(folder)
        row.operator("visibake.bake_volume", icon="RENDER_STILL")
        report = context.scene.get("visibake_volume_report")
        if report:
            try:
                layout.label(text=volume.summary(json.loads(report)).removeprefix("VisiBake: "))
            except (TypeError, ValueError, KeyError):
                layout.label(text="The last volume report cannot be read")


class VIEW3D_PT_visibake_appearance(_Section, bpy.types.Panel):
    bl_label = "Materials from Micro-Geometry"
    bl_idname = "VIEW3D_PT_visibake_appearance"

    def draw(self, context):
        from ..operators import appearance

        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.visibake
        tile = appearance.tile_object(context)
        layout.label(text=f"Tile: {tile.name} (one period, repeating in X and Y)" if tile
                     else "Make the tile's mesh object active", icon="MOD_ARRAY")
        column = layout.column()
        for name in ("appearance_directions", "appearance_bounces", "appearance_resolution"):
            column.prop(props, name)
        column.separator()
        for name in ("appearance_lights", "appearance_views", "appearance_format"):
            column.prop(props, name)
        path = appearance.output_path(context, tile)
        layout.label(text=f"Into {path}" if path else "Set an Output Folder (or save the file)")
        row = layout.row()
        row.enabled = tile is not None and bool(path)
        row.operator("visibake.simulate_brdf", icon="MATERIAL")
        column = layout.column()
        for name in ("appearance_image_size", "appearance_image_format"):
            column.prop(props, name)
        row = layout.row()
        row.enabled = tile is not None and bool(path)
        row.operator("visibake.simulate_btf", icon="TEXTURE")
        for key, what in (("visibake_brdf_report", "BRDF"), ("visibake_btf_report", "BTF")):
            report = context.scene.get(key)
            if report:
                try:
                    layout.label(text=appearance.summary(json.loads(report)).removeprefix("VisiBake: "))
                except (TypeError, ValueError, KeyError):
                    layout.label(text=f"The last {what} report cannot be read")


class VIEW3D_PT_visibake_lightfield(_Section, bpy.types.Panel):
    bl_label = "Light Field"
    bl_idname = "VIEW3D_PT_visibake_lightfield"

    def draw(self, context):
        from ..operators import lightfield

        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.visibake
        camera = context.scene.camera
        layout.label(text=f"Around camera {camera.name} (bake the scene first)" if camera
                     else "Set the scene's camera: the grid is centred on it", icon="CAMERA_DATA")
        column = layout.column()
        for name in ("lightfield_columns", "lightfield_rows", "lightfield_baseline_mm", "lightfield_focus_m",
                     "lightfield_width", "lightfield_height", "lightfield_supersampling", "lightfield_format"):
            column.prop(props, name)
        folder = lightfield.output_folder(context)
        layout.label(text=f"Into {folder}" if folder else "Set an Output Folder (or save the file)")
        row = layout.row()
        row.enabled = camera is not None and bool(folder)
        row.operator("visibake.render_lightfield", icon="RENDER_STILL")
        report = context.scene.get("visibake_lightfield_report")
        if report:
            try:
                layout.label(text=lightfield.summary(json.loads(report)).removeprefix("VisiBake: "))
            except (TypeError, ValueError, KeyError):
                layout.label(text="The last light field report cannot be read")


classes = (VIEW3D_PT_visibake, VISIBAKE_UL_objects, VIEW3D_PT_visibake_objects, VIEW3D_PT_visibake_report,
           VIEW3D_PT_visibake_volumes, VIEW3D_PT_visibake_appearance, VIEW3D_PT_visibake_lightfield)
