"""The Bake operator: runs :func:`job.run_bake` on the selected (or all) meshes."""
import bpy

from ..core.pipeline import Cancelled
from . import job


def summary(report: dict) -> str:
    objects = [o for o in report["objects"] if o["output"]]
    texels = sum(o["texels"] for o in objects)
    return (f"VisiBake: baked {len(objects)} object(s), {texels} texels, "
            f"{report['rays']['visibility_cast']} rays in {report['total_seconds']:.1f} s")


class VISIBAKE_OT_bake(bpy.types.Operator):
    """Precompute visibility and bake lighting into textures for the selected meshes"""

    bl_idname = "visibake.bake"
    bl_label = "Bake"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        props = context.scene.visibake
        objects = job.output_objects(context, props)
        window_manager = context.window_manager
        window_manager.progress_begin(0, 100)
        stages = ("layout", "samples", "visibility", "direct", "transport", "outputs")

        def progress(stage, fraction):
            index = stages.index(stage) if stage in stages else 0
            window_manager.progress_update(int(100 * (index + fraction) / len(stages)))

        try:
            outcome = job.run_bake(context, objects, bpy.path.abspath(props.output_dir) or None, False, progress)
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except Cancelled:
            self.report({"WARNING"}, "VisiBake: bake cancelled; nothing was changed")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
        context.scene["visibake_last_report"] = summary(outcome.report)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


classes = (VISIBAKE_OT_bake,)
