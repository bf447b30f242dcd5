"""Baked lighting wired into materials for preview, and taken out again.

For each baked object, a node group "VisiBake Lighting <object>" emits its
``lighting`` result (the image through its bake UV map, or the ``VB_lighting``
colour attribute in vertex mode). Each of the object's materials gets that group and
a Material Output of its own, made the active output: the user's nodes are neither
deleted nor reconnected, and their output is made active again on removal. A material
that other objects use too is wired only where each of them would show its own lighting
(see :func:`add_preview`).
"""
from __future__ import annotations

import bpy

from ...core.errors import OutputRefused
from ...core.outputs import names
from . import compat, layout, writeback

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
    image = writeback.find_image(obj.name, "lighting")
    attribute = writeback.attribute_name("lighting") if obj.type == "MESH" and \
        writeback.attribute_name("lighting") in obj.data.color_attributes else None
    if image is None and attribute is None:
        return None
    # Never cut by Blender: a cut name would no longer be found, and a new group made on every preview.
    name = names.datablock_name(GROUP_PREFIX, [obj.name], compat.MAX_NAME_BYTES)
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


def _reads_own_attribute(obj, mesh_users: dict) -> bool:
    """Whether ``obj``'s preview reads its own vertex-mode result: VisiBake's ``VB_lighting`` on a
    mesh no other object uses. A group reads a colour attribute by name, from the mesh of the
    object being drawn, so one material can show several such objects each its own light.
    ``mesh_users``: mesh -> number of objects using it."""
    mesh = obj.data
    name = writeback.attribute_name("lighting")
    return (obj.type == "MESH" and name in mesh.color_attributes
            and name in list(mesh.get(writeback.OWNED_ATTRIBUTES_KEY, []))
            and mesh_users.get(mesh, 0) == 1)


def _material_users() -> dict:
    """material -> every object in the file that uses it (any scene, previewed or not; not
    objects in no scene or collection, which show nothing and are purged on save)."""
    users: dict = {}
    for obj in bpy.data.objects:
        if not obj.users:
            continue
        for slot in obj.material_slots:
            if slot.material is not None:
                users.setdefault(slot.material, set()).add(obj)
    return users


def add_preview(objects) -> tuple[int, list[str]]:
    """Wire each object's baked lighting into its materials; returns (materials wired, warnings).

    A material is wired only where every object that uses it would then show its own lighting:
    used by that object alone, or by objects that each read their own vertex-mode attribute.
    Any other shared material is left showing its own nodes (an earlier preview in it is taken
    out), with a warning naming its users and the remedy.
    """
    users = _material_users()
    mesh_users: dict = {}
    for other in bpy.data.objects:
        if other.type == "MESH" and other.users:
            mesh_users[other.data] = mesh_users.get(other.data, 0) + 1
    wired, warnings = 0, []
    done, refused = set(), set()
    for obj in objects:
        group = _lighting_group(obj)
        if group is None:
            warnings.append(f"object {obj.name!r} has no baked lighting to preview; bake it first")
            continue
        for slot in obj.material_slots:
            material = slot.material
            if material is None or material.node_tree is None or material in done:
                continue
            others = users[material] - {obj}
            if others and not all(_reads_own_attribute(o, mesh_users) for o in (obj, *others)):
                if material not in refused:
                    refused.add(material)
                    remove_from_material(material)
                    users_text = ", ".join(repr(o.name) for o in sorted(users[material], key=lambda o: o.name))
                    warnings.append(
                        f"material {material.name!r} is used by {users_text}; wired to the baked lighting of "
                        f"{obj.name!r}, it would show that (or none) on the others, so it was left as it is; give "
                        f"{obj.name!r} its own copy of the material (the user count beside its name in the "
                        "Material tab) and preview again")
                continue
            done.add(material)
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


