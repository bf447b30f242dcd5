"""A micro-geometry tile whose material holds NaN or infinite numbers (issue 51, item 5): refused
up front, naming the object and the material, by `visibake brdf`, `visibake btf` and the panel's
operators, before any simulation and without writing anything."""
import importlib
import math

import bpy

import pytest

from blender_support import extension_module_name


def tile_scene(path, socket: str, value: float):
    """A .blend with a V-groove tile "Groove" whose Principled BSDF "Cloth" has ``socket`` set to
    ``value``; returns the path. Blender keeps a NaN set by a script (an infinity it clamps)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    mesh = bpy.data.meshes.new("Groove")
    mesh.from_pydata([(0, 0, 0.5), (0.5, 0, 0), (1, 0, 0.5), (0, 1, 0.5), (0.5, 1, 0), (1, 1, 0.5)], [],
                     [(0, 1, 4, 3), (1, 2, 5, 4)])
    obj = bpy.data.objects.new("Groove", mesh)
    bpy.context.scene.collection.objects.link(obj)
    made = bpy.data.materials.new("Cloth")
    importlib.import_module(extension_module_name() + ".operators.adapter.compat").ensure_node_tree(made)
    tree = made.node_tree
    tree.nodes.clear()
    shader = tree.nodes.new("ShaderNodeBsdfPrincipled")
    if socket == "Base Color":
        shader.inputs[socket].default_value = (value, 0.5, 0.5, 1.0)
        assert math.isnan(shader.inputs[socket].default_value[0])
    else:
        shader.inputs[socket].default_value = value
        assert math.isnan(shader.inputs[socket].default_value)
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(shader.outputs[0], output.inputs["Surface"])
    mesh.materials.append(made)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


CASES = [("Base Color", math.nan, "base colour"), ("Roughness", math.nan, "roughness"),
         ("Transmission Weight", math.nan, "transmission")]


@pytest.mark.parametrize("command", ["brdf", "btf"])
@pytest.mark.parametrize("socket, value, named", CASES)
def test_a_non_finite_tile_material_exits_2_naming_object_and_material(visibake, tmp_path, capfd, command, socket,
                                                                       value, named):
    blend = tile_scene(tmp_path / "tile.blend", socket, value)
    out = tmp_path / ("tile.binary" if command == "brdf" else "tile_btf")
    arguments = [command, str(blend), "--tile", "Groove", "--out", str(out), "--directions", "16", "--resolution",
                 "4", "--no-progress"]
    if command == "brdf":
        arguments += ["--lights", "6", "--views", "6"]
    else:
        arguments += ["--image-size", "8"]
    assert visibake.cli.main(arguments) == 2
    said = capfd.readouterr().err.strip().splitlines()
    assert said and "tile object 'Groove', material 'Cloth'" in said[-1] and named in said[-1], said
    assert "not a finite number" in said[-1]
    assert not out.exists()


@pytest.mark.parametrize("operator", ["simulate_brdf", "simulate_btf"])
def test_the_panel_refuses_a_nan_base_colour_and_writes_nothing(visibake, tmp_path, operator):
    blend = tile_scene(tmp_path / "tile.blend", "Base Color", math.nan)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    props = scene.visibake
    props.output_dir = str(tmp_path / "materials")
    props.appearance_lights, props.appearance_views = 5, 5
    props.appearance_directions, props.appearance_resolution = 16, 4
    props.appearance_image_size = 8
    bpy.context.view_layer.objects.active = scene.objects["Groove"]
    materials = set(bpy.data.materials.keys())
    with pytest.raises(RuntimeError, match="tile object 'Groove', material 'Cloth': its base colour"):
        getattr(bpy.ops.visibake, operator)()  # an error report raises in scripts
    assert not (tmp_path / "materials").exists() or not any((tmp_path / "materials").iterdir())
    assert set(bpy.data.materials.keys()) == materials
