"""Bake Volume: run :class:`adapter.volume_job.VolumeJob` on the selected (or all) Volume objects."""
import json
import os

import bpy

from .adapter import volume_job
from .bake import _BakeOperator


def volume_targets(context) -> list:
    """The selected media VisiBake can bake (Volume objects, meshes with a Principled Volume), or every
    visible one when none is selected."""
    volumes = volume_job.scene_volumes(context.scene)
    selected = [o for o in volumes if o.select_get()]
    return selected or volumes


def output_folder(context) -> str:
    """The scene's output folder, else ``visibake_volumes`` beside the saved .blend; '' if neither."""
    folder = bpy.path.abspath(context.scene.visibake.output_dir)
    if folder:
        return folder
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), "visibake_volumes")
    return ""


def summary(report: dict) -> str:
    baked = [entry["name"] for entry in report["volumes"] if entry["output"]]
    return (f"VisiBake: {len(baked)} volume(s) baked ({', '.join(baked)}), {report['directions']} directions, "
            f"{report['bounces']} bounce(s), in {report['seconds']:.1f} s")


class VISIBAKE_OT_bake_volume(_BakeOperator, bpy.types.Operator):
    """Bake the light scattered in the selected volumes (Volume objects and meshes with a Principled Volume; all \
visible ones if none is selected) into \
VDB grids, and add a Volume object that renders them"""

    bl_idname = "visibake.bake_volume"
    bl_label = "Bake Volume"
    bl_options = {"REGISTER", "UNDO"}

    def _job(self, context, progress) -> volume_job.VolumeJob:
        props = context.scene.visibake
        return volume_job.VolumeJob(context.scene, volume_targets(context), output_folder(context),
                                    props.volume_resolution,
                                    props.volume_directions, props.volume_bounces, props.volume_points, props.seed,
                                    volume_job.preferred_threads(), progress)

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_volume_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


classes = (VISIBAKE_OT_bake_volume,)
