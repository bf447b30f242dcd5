"""Simulate BRDF and Simulate BTF: the active mesh object as a micro-geometry tile
(adapter.tile_io.BRDFJob, BTFJob)."""
import json
import os

import bpy

from ..core.appearance import gonio
from .adapter import tile_io
from .bake import _BakeOperator

EXTENSIONS = {"merl": ".binary", "table": ".npz", "bsdf": ".npz"}


def tile_object(context):
    """The active object when it is a mesh (the tile), else None."""
    obj = context.active_object
    return obj if obj is not None and obj.type == "MESH" else None


def output_path(context, obj, btf: bool = False) -> str:
    """``<Output Folder>/<object>.binary`` (or .npz; for a BTF the folder ``<object>_btf``),
    in the folder beside the saved .blend when none is set ('visibake_materials'); '' if neither."""
    folder = bpy.path.abspath(context.scene.visibake.output_dir)
    if not folder and bpy.data.filepath:
        folder = os.path.join(os.path.dirname(bpy.data.filepath), "visibake_materials")
    if not folder or obj is None:
        return ""
    name = bpy.path.clean_name(obj.name)
    return os.path.join(folder, name + ("_btf" if btf else EXTENSIONS[context.scene.visibake.appearance_format]))


def summary(report: dict) -> str:
    if report.get("command") == "btf":
        return (f"VisiBake: BTF of {report['images']} images of {report['image_size']} px -> "
                f"{os.path.basename(report['output'])} in {report['seconds']:.1f} s")
    passed = report.get("max_directional_transmittance", 0.0)
    return (f"VisiBake: BRDF of {report['settings']['lights']} x {report['settings']['views']} directions -> "
            f"{os.path.basename(report['output'])} in {report['seconds']:.1f} s (largest directional albedo "
            f"{report['max_directional_albedo']:.3f}" + (f", transmittance {passed:.3f})" if passed else ")"))


def _settings(props) -> gonio.GonioSettings:
    return gonio.GonioSettings(directions=props.appearance_directions, bounces=props.appearance_bounces,
                               resolution=props.appearance_resolution, seed=props.seed,
                               threads=tile_io.preferred_threads())


def _tile_reader(context, obj, path: str, what: str):
    """A callable reading the tile on the main thread, refusing first what cannot run."""
    scene = context.scene

    def read_tile():
        if obj is None:
            raise tile_io.AppearanceRefused("make a mesh object active: it is the tile")
        if not path:
            raise tile_io.OutputRefused(f"set an Output Folder (or save the file): the {what} is written there")
        return tile_io.read_tile(scene, obj.name)

    return read_tile


class VISIBAKE_OT_simulate_brdf(_BakeOperator, bpy.types.Operator):
    """Simulate the BRDF of the active mesh object as one period of a surface repeating in X and Y (its \
bounding box), and write it as a MERL or tabulated file in the Output Folder"""

    bl_idname = "visibake.simulate_brdf"
    bl_label = "Simulate BRDF"
    bl_options = {"REGISTER"}

    def _job(self, context, progress) -> tile_io.BRDFJob:
        props = context.scene.visibake
        obj = tile_object(context)
        self._tile_name = obj.name if obj is not None else ""
        path = output_path(context, obj)
        return tile_io.BRDFJob(_tile_reader(context, obj, path, "BRDF"),
                               path or os.path.join(os.getcwd(), "unset.binary"), props.appearance_format,
                               props.appearance_lights, props.appearance_views, _settings(props), False, progress,
                               make_folder=True)

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_brdf_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        fit = outcome.report.get("principled_fit")
        if fit is not None:
            material = tile_io.make_material(f"{self._tile_name} (VisiBake)", fit)
            self.report({"INFO"}, f"VisiBake: material {material.name!r} fitted to the BRDF (relative RMSE "
                                  f"{100 * fit['relative_rmse']:.1f}%)")
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


class VISIBAKE_OT_simulate_btf(_BakeOperator, bpy.types.Operator):
    """Simulate the BTF of the active mesh object (one period of a surface repeating in X and Y): \
81 x 81 images on Bonn's UBO2003 directions, in the UTIA folder layout, in the Output Folder"""

    bl_idname = "visibake.simulate_btf"
    bl_label = "Simulate BTF"
    bl_options = {"REGISTER"}

    def _job(self, context, progress) -> tile_io.BTFJob:
        props = context.scene.visibake
        obj = tile_object(context)
        path = output_path(context, obj, btf=True)
        return tile_io.BTFJob(_tile_reader(context, obj, path, "BTF"),
                              path or os.path.join(os.getcwd(), "unset_btf"), props.appearance_image_format,
                              props.appearance_image_size, _settings(props), progress=progress)

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_btf_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}


classes = (VISIBAKE_OT_simulate_brdf, VISIBAKE_OT_simulate_btf)
