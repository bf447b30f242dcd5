"""Render Light Field: the scene's camera at the centre of a grid of views of the baked
scene (adapter.lightfield_io.LightFieldJob), into the Output Folder."""
import json
import os

import bpy

from .adapter import device, lightfield_io
from .bake import _BakeOperator


def output_folder(context) -> str:
    """``<Output Folder>/lightfield``, or ``visibake_lightfield`` beside the saved .blend when no
    Output Folder is set; '' if neither."""
    folder = bpy.path.abspath(context.scene.visibake.output_dir)
    if folder:
        return os.path.join(folder, "lightfield")
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), "visibake_lightfield")
    return ""


def summary(report: dict) -> str:
    columns, rows = report["grid"]
    width, height = report["image_size"]
    return (f"VisiBake: light field of {columns}x{rows} views at {width}x{height} -> "
            f"{os.path.basename(report['output'])} in {report['seconds']:.1f} s (rendering {report['render_s']:.1f} s)")


class VISIBAKE_OT_render_lightfield(_BakeOperator, bpy.types.Operator):
    """Render the baked scene from a grid of parallel off-axis cameras around the scene's camera (the HCI \
light field benchmark's), with depth and disparity for the centre view, into the Output Folder"""

    bl_idname = "visibake.render_lightfield"
    bl_label = "Render Light Field"
    bl_options = {"REGISTER"}

    def _job(self, context, progress) -> lightfield_io.LightFieldJob:
        props = context.scene.visibake
        folder = output_folder(context)
        if not folder:
            raise lightfield_io.LightFieldRefused("set an Output Folder (or save the file): the light field is "
                                                  "written there")
        preferences = device.preferences(context)
        return lightfield_io.LightFieldJob(
            context.scene, None, folder, (props.lightfield_columns, props.lightfield_rows),
            props.lightfield_baseline_mm, props.lightfield_focus_m, (props.lightfield_width, props.lightfield_height),
            props.lightfield_format, preferences.device if preferences is not None else "auto", progress=progress,
            supersampling=props.lightfield_supersampling)

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_lightfield_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


classes = (VISIBAKE_OT_render_lightfield,)
