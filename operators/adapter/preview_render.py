"""A render of the scene lit only by its baked textures (the demo's visual check).

Each baked object is shown through an emission shader that reads its ``lighting``
image (or, in vertex mode, its ``VB_lighting`` colour attribute), lamps are switched
off, and Cycles renders with no bounces: what the camera sees is exactly what the bake
stored. Everything is restored afterwards.
"""
from __future__ import annotations

import bpy

from . import compat
from .writeback import find_image


def _emission_material(name: str, image: bpy.types.Image | None, uv_map: str | None,
                       attribute: str | None = None) -> bpy.types.Material:
    """Emission of the baked ``image`` (looked up with ``uv_map``) or colour ``attribute``."""
    material = bpy.data.materials.new(name)
    nodes = compat.ensure_node_tree(material).nodes
    links = material.node_tree.links
    nodes.clear()
    output = nodes.new("ShaderNodeOutputMaterial")
    emission = nodes.new("ShaderNodeEmission")
    if attribute is not None:
        source = nodes.new("ShaderNodeVertexColor")
        source.layer_name = attribute
    else:
        source = nodes.new("ShaderNodeTexImage")
        source.image = image
        uv = nodes.new("ShaderNodeUVMap")
        uv.uv_map = uv_map
        links.new(uv.outputs["UV"], source.inputs["Vector"])
    links.new(source.outputs["Color"], emission.inputs["Color"])
    links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def render_baked_preview(scene: bpy.types.Scene, object_names, path: str, uv_maps: dict[str, str],
                        width: int = 640, height: int = 400, samples: int = 16, file_format: str = "PNG") -> bool:
    """Render ``scene`` from its camera with baked lighting only, to ``path`` as ``file_format``
    (PNG: display-encoded; OPEN_EXR: the linear values, for measuring); False if it has no camera."""
    if scene.camera is None:
        return False
    render = scene.render
    saved_render = (render.engine, render.resolution_x, render.resolution_y, render.resolution_percentage,
                    render.filepath, render.image_settings.file_format, scene.view_settings.view_transform)
    saved_depth = render.image_settings.color_depth
    saved_cycles = (scene.cycles.samples, scene.cycles.max_bounces, scene.cycles.use_denoising,
                    scene.cycles.use_adaptive_sampling)
    saved_slots = []
    hidden_lights = []
    created = []
    try:
        for name in object_names:
            obj = bpy.data.objects[name]
            if uv_maps.get(name) is None:
                if "VB_lighting" not in obj.data.color_attributes:
                    continue
                material = _emission_material(f"__visibake_preview_{name}", None, None, attribute="VB_lighting")
            else:
                image = find_image(name, "lighting")
                if image is None:
                    continue
                material = _emission_material(f"__visibake_preview_{name}", image, uv_maps[name])
            created.append(material)
            if not obj.material_slots:
                obj.data.materials.append(None)
                saved_slots.append((obj, None, None, True))
            for slot in obj.material_slots:
                saved_slots.append((obj, slot, (slot.link, slot.material), False))
                slot.link = "OBJECT"
                slot.material = material
        for obj in scene.objects:
            if obj.type == "LIGHT" and not obj.hide_render:
                obj.hide_render = True
                hidden_lights.append(obj)
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y, render.resolution_percentage = width, height, 100
        scene.cycles.samples = samples
        scene.cycles.max_bounces = 0
        scene.cycles.use_denoising = False
        scene.cycles.use_adaptive_sampling = False
        scene.view_settings.view_transform = "Standard"
        render.image_settings.file_format = file_format
        if file_format == "OPEN_EXR":
            render.image_settings.color_depth = "32"  # full float: the values are measured
        render.filepath = path
        bpy.ops.render.render(write_still=True, scene=scene.name)
    finally:
        for obj, slot, state, appended in reversed(saved_slots):
            if appended:
                obj.data.materials.pop()
                continue
            slot.link, slot.material = state[0], state[1]
        for obj in hidden_lights:
            obj.hide_render = False
        for material in created:
            bpy.data.materials.remove(material)
        (render.engine, render.resolution_x, render.resolution_y, render.resolution_percentage,
         render.filepath, render.image_settings.file_format, scene.view_settings.view_transform) = saved_render
        try:
            render.image_settings.color_depth = saved_depth
        except TypeError:  # a depth the restored format does not offer: it keeps its own
            pass
        (scene.cycles.samples, scene.cycles.max_bounces, scene.cycles.use_denoising,
         scene.cycles.use_adaptive_sampling) = saved_cycles
    return True
