"""Baked lighting wired into materials for preview, and taken out again.

For each baked object, a node group "VisiBake Lighting <object>" emits its
``lighting`` result (the image through its bake UV map, or the ``VB_lighting``
colour attribute in vertex mode). Each of the object's materials gets that group and
a Material Output of its own, made the active output: the user's nodes are neither
deleted nor reconnected, and their output is made active again on removal.
"""
from __future__ import annotations

import bpy

from ...core.errors import OutputRefused
from . import layout, writeback

NODE_TAG = "visibake_preview"  # on every node VisiBake adds to a material
PREVIOUS_OUTPUT_KEY = "visibake_preview_output"  # on the material: the output active before
GROUP_PREFIX = "VisiBake Lighting "


def _bake_uv_map(obj) -> str | None:
    mesh = obj.data
    if layout.owns_uv_map(mesh, layout.UV_MAP_NAME):
        return layout.UV_MAP_NAME
    return next((uv.name for uv in mesh.uv_layers if uv.active_render), None)


def _lighting_group(obj) -> bpy.types.ShaderNodeTree | None:
    """The node group emitting ``obj``'s baked lighting, made or refreshed; None if nothing is baked."""
    image = bpy.data.images.get(writeback.image_name(obj.name, "lighting"))
    attribute = writeback.attribute_name("lighting") if obj.type == "MESH" and \
        writeback.attribute_name("lighting") in obj.data.color_attributes else None
    if image is None and attribute is None:
        return None
    name = f"{GROUP_PREFIX}{obj.name}"
    group = bpy.data.node_groups.get(name)
    if group is not None and not group.get(NODE_TAG):
        raise OutputRefused(f"a node group named {name!r} exists that VisiBake did not create; rename it")
    if group is None:
        group = bpy.data.node_groups.new(name, "ShaderNodeTree")
        group[NODE_TAG] = True
        group.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    group.nodes.clear()
    output = group.nodes.new("NodeGroupOutput")
    emission = group.nodes.new("ShaderNodeEmission")
    if attribute is not None:
        source = group.nodes.new("ShaderNodeVertexColor")
        source.layer_name = attribute
    else:
        source = group.nodes.new("ShaderNodeTexImage")
        source.image = image
        uv_map = _bake_uv_map(obj)
        if uv_map:
            uv = group.nodes.new("ShaderNodeUVMap")
            uv.uv_map = uv_map
            group.links.new(uv.outputs["UV"], source.inputs["Vector"])
    group.links.new(source.outputs["Color"], emission.inputs["Color"])
    group.links.new(emission.outputs["Emission"], output.inputs[0])
    return group


def _active_output(tree):
    return next((n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output), None)


def add_preview(objects) -> tuple[int, list[str]]:
    """Wire each object's baked lighting into its materials; returns (materials wired, warnings)."""
    users: dict = {}
    for obj in objects:
        for slot in obj.material_slots:
            if slot.material is not None:
                users.setdefault(slot.material, set()).add(obj.name)
    wired, warnings = 0, []
    for obj in objects:
        group = _lighting_group(obj)
        if group is None:
            warnings.append(f"object {obj.name!r} has no baked lighting to preview; bake it first")
            continue
        for slot in obj.material_slots:
            material = slot.material
            if material is None or material.node_tree is None:
                continue
            if len(users[material]) > 1:
                warnings.append(f"material {material.name!r} is shared by {', '.join(sorted(users[material]))}, "
                                "whose baked lighting differs; it was left as it is")
                continue
            tree = material.node_tree
            remove_from_material(material)
            previous = _active_output(tree)
            material[PREVIOUS_OUTPUT_KEY] = previous.name if previous is not None else ""
            node = tree.nodes.new("ShaderNodeGroup")
            node.node_tree = group
            node.label = "VisiBake baked lighting"
            output = tree.nodes.new("ShaderNodeOutputMaterial")
            output.label = "VisiBake preview"
            for made in (node, output):
                made[NODE_TAG] = True
            if previous is not None:
                node.location = (previous.location.x, previous.location.y - 300)
                output.location = (previous.location.x + 250, previous.location.y - 300)
            tree.links.new(node.outputs[0], output.inputs["Surface"])
            output.is_active_output = True
            wired += 1
    return wired, warnings


def remove_from_material(material) -> bool:
    """Take VisiBake's preview nodes out of ``material`` and reactivate its own output."""
    tree = material.node_tree
    if tree is None:
        return False
    ours = [n for n in tree.nodes if n.get(NODE_TAG)]
    for node in ours:
        tree.nodes.remove(node)
    previous = tree.nodes.get(material.get(PREVIOUS_OUTPUT_KEY, ""))
    if previous is not None:
        previous.is_active_output = True
    if PREVIOUS_OUTPUT_KEY in material:
        del material[PREVIOUS_OUTPUT_KEY]
    return bool(ours)


def remove_preview() -> int:
    """Remove every VisiBake preview from every material, and the unused groups; returns materials changed."""
    changed = sum(remove_from_material(material) for material in bpy.data.materials)
    for group in list(bpy.data.node_groups):
        if group.get(NODE_TAG) and group.users == 0:
            bpy.data.node_groups.remove(group)
    return changed


