"""The baked-lighting preview: a node group wired into materials and taken out again."""
import bpy

import pytest

from bpy_scenes import black_world, cube, grid, material, mesh_object, point, select_only


def _tree_state(mat):
    tree = mat.node_tree
    nodes = sorted((n.name, n.bl_idname) for n in tree.nodes)
    links = sorted((l.from_node.name, l.from_socket.identifier, l.to_node.name, l.to_socket.identifier)
                   for l in tree.links)
    active = [n.name for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output]
    return nodes, links, active


@pytest.fixture
def baked(clean_scene):
    black_world()
    white = material("White", (0.8, 0.8, 0.8))
    ground = mesh_object("Ground", grid(1.0), white)
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    block.visibake.mode = "vertex"
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.use_cache = 32, 16, False
    select_only([ground, block])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return ground, block


def test_preview_is_added_beside_the_user_nodes_and_removed_without_a_trace(visibake, baked):
    ground, block = baked
    materials = [ground.material_slots[0].material, block.material_slots[0].material]
    before = {m.name: _tree_state(m) for m in materials}
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}
    for mat in materials:
        nodes, links, active = _tree_state(mat)
        old_nodes, old_links, old_active = before[mat.name]
        assert set(old_nodes) <= set(nodes) and set(old_links) <= set(links)  # nothing deleted or rewired
        assert active != old_active and len(nodes) == len(old_nodes) + 2
    tag = visibake.operators.adapter.preview_nodes.NODE_TAG
    for mat, obj in zip(materials, (ground, block)):
        tree = mat.node_tree
        group_node = next(n for n in tree.nodes if n.get(tag) and n.bl_idname == "ShaderNodeGroup")
        output = next(n for n in tree.nodes if n.get(tag) and n.bl_idname == "ShaderNodeOutputMaterial")
        # The object's own group feeds the new output's surface, which is the active one.
        assert group_node.node_tree.name == f"VisiBake Lighting {obj.name}"
        assert output.is_active_output and active == [output.name]
        new_links = set(_tree_state(mat)[1]) - set(before[mat.name][1])
        assert new_links == {(group_node.name, group_node.outputs[0].identifier, output.name, "Surface")}
    ground_group = bpy.data.node_groups["VisiBake Lighting Ground"]
    image_node = next(n for n in ground_group.nodes if n.bl_idname == "ShaderNodeTexImage")
    assert image_node.image.name == "VB_Ground_lighting"
    # Inside the group: the image, read through the bake UV map, is what it emits.
    inner = {(l.from_node.bl_idname, l.from_socket.identifier, l.to_node.bl_idname, l.to_socket.identifier)
             for l in ground_group.links}
    group_output = next(n for n in ground_group.nodes if n.bl_idname == "NodeGroupOutput")
    assert inner == {("ShaderNodeUVMap", "UV", "ShaderNodeTexImage", "Vector"),
                     ("ShaderNodeTexImage", "Color", "ShaderNodeEmission", "Color"),
                     ("ShaderNodeEmission", "Emission", "NodeGroupOutput", group_output.inputs[0].identifier)}
    assert next(n for n in ground_group.nodes if n.bl_idname == "ShaderNodeUVMap").uv_map == "UVMap"
    block_group = bpy.data.node_groups["VisiBake Lighting Block"]
    assert next(n for n in block_group.nodes if n.bl_idname == "ShaderNodeVertexColor").layer_name == "VB_lighting"
    # Adding again replaces, it does not stack.
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}
    assert len(_tree_state(materials[0])[0]) == len(before[materials[0].name][0]) + 2
    assert bpy.ops.visibake.preview_remove() == {"FINISHED"}
    for mat in materials:
        assert _tree_state(mat) == before[mat.name]
    assert not any(g.name.startswith("VisiBake Lighting") for g in bpy.data.node_groups)


def test_a_shared_material_is_left_alone_with_a_warning(visibake, clean_scene):
    black_world()
    shared = material("Shared", (0.8, 0.8, 0.8))
    a = mesh_object("A", grid(1.0), shared)
    b = mesh_object("B", grid(1.0), shared, location=(3, 0, 0))
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    bpy.context.scene.visibake.resolution = 16
    select_only([a, b])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    before = _tree_state(shared)
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}
    assert _tree_state(shared) == before
    # The warning the operator reports, once per material, naming its users and the remedy.
    wired, warnings = visibake.operators.adapter.preview_nodes.add_preview([a, b])
    assert wired == 0 and _tree_state(shared) == before
    assert len(warnings) == 1 and "material 'Shared' is used by 'A', 'B'" in warnings[0]
    assert "left as it is" in warnings[0] and "own copy of the material" in warnings[0]



def _undoable(operator, **options):
    """Run an operator as a click in the UI does: with an undo step (bpy.ops skips it by default)."""
    return operator("EXEC_DEFAULT", True, **options)


def test_undo_and_redo_of_adding_and_removing_the_preview(baked):
    names = ("White", "Red")
    before = {name: _tree_state(bpy.data.materials[name]) for name in names}
    bpy.ops.ed.undo_push(message="baked")
    assert _undoable(bpy.ops.visibake.preview_add) == {"FINISHED"}
    added = {name: _tree_state(bpy.data.materials[name]) for name in names}
    assert added != before

    assert bpy.ops.ed.undo() == {"FINISHED"}
    # Undo reloads the data: look everything up again by name.
    assert {name: _tree_state(bpy.data.materials[name]) for name in names} == before
    assert not any(g.name.startswith("VisiBake Lighting") for g in bpy.data.node_groups)
    assert bpy.ops.ed.redo() == {"FINISHED"}
    assert {name: _tree_state(bpy.data.materials[name]) for name in names} == added

    assert _undoable(bpy.ops.visibake.preview_remove) == {"FINISHED"}
    assert {name: _tree_state(bpy.data.materials[name]) for name in names} == before
    assert bpy.ops.ed.undo() == {"FINISHED"}
    assert {name: _tree_state(bpy.data.materials[name]) for name in names} == added
    assert "VisiBake Lighting Ground" in bpy.data.node_groups


def test_undo_of_a_bake_takes_its_images_uv_map_and_colours_away(clean_scene):
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    dome = mesh_object("Dome", cube(4.0), material("Grey", (0.5, 0.5, 0.5)), flip=True, uv_map=None)
    dome.visibake.mode = "vertex"
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.use_cache = 32, 32, False
    select_only([ground, block, dome])
    bpy.ops.ed.undo_push(message="scene built")
    assert _undoable(bpy.ops.visibake.bake) == {"FINISHED"}
    assert "VB_Ground_lighting" in bpy.data.images, list(bpy.data.images.keys())
    assert "VisiBake" in bpy.data.objects["Block"].data.uv_layers
    assert "VB_lighting" in bpy.data.objects["Dome"].data.color_attributes
    assert bpy.ops.ed.undo() == {"FINISHED"}
    assert "VB_Ground_lighting" not in bpy.data.images and "VB_Block_lighting" not in bpy.data.images
    assert "VisiBake" not in bpy.data.objects["Block"].data.uv_layers
    assert "VB_lighting" not in bpy.data.objects["Dome"].data.color_attributes
    assert bpy.ops.ed.redo() == {"FINISHED"}
    assert "VB_Ground_lighting" in bpy.data.images and "VB_lighting" in bpy.data.objects["Dome"].data.color_attributes
