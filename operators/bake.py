"""Bake and Relight: run :func:`job.run_bake` on the selected (or all) meshes."""
import json

import bpy

from ..core.pipeline import Cancelled
from . import job


def summary(report: dict) -> str:
    objects = [o for o in report["objects"] if o["output"]]
    texels = sum(o["texels"] for o in objects)
    verb = "relit" if report.get("relight_only") else "baked"
    cache = report.get("cache", {}).get("state", "off")
    visibility = {"hit": "visibility from the cache", "updated": "visibility updated for changed objects",
                  "unused": "no visibility needed"}.get(cache, f"{report['rays']['visibility_cast']} visibility rays")
    return (f"VisiBake: {verb} {len(objects)} object(s), {texels} texels, {visibility}, "
            f"in {report['total_seconds']:.1f} s")


class _BakeOperator:
    relight_only = False

    def execute(self, context):
        props = context.scene.visibake
        objects = job.output_objects(context, props)
        window_manager = context.window_manager
        window_manager.progress_begin(0, 100)
        stages = ("layout", "samples", "cache", "visibility", "transport", "outputs")

        def progress(stage, fraction):
            index = stages.index(stage) if stage in stages else 0
            window_manager.progress_update(int(100 * (index + fraction) / len(stages)))

        try:
            outcome = job.run_bake(context, objects, bpy.path.abspath(props.output_dir) or None, False, progress,
                                   relight_only=self.relight_only)
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except Cancelled:
            self.report({"WARNING"}, "VisiBake: bake cancelled; nothing was changed")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
        context.scene["visibake_last_report"] = summary(outcome.report)
        context.scene["visibake_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


class VISIBAKE_OT_bake(_BakeOperator, bpy.types.Operator):
    """Precompute visibility (or reuse the cached visibility) and bake lighting into textures for the selected meshes"""

    bl_idname = "visibake.bake"
    bl_label = "Bake"
    bl_options = {"REGISTER", "UNDO"}


class VISIBAKE_OT_relight(_BakeOperator, bpy.types.Operator):
    """Recompute only the lighting from the cached visibility, after lights, materials or the world changed. \
Refuses if the geometry changed since the last bake"""

    bl_idname = "visibake.relight"
    bl_label = "Relight"
    bl_options = {"REGISTER", "UNDO"}
    relight_only = True


classes = (VISIBAKE_OT_bake, VISIBAKE_OT_relight)
