"""A mesh with a Principled Volume material (Cycles fills its inside with the medium) read as a
voxelised medium: recognised, filled, placed where the object is, refused when it encloses
nothing; the user's mesh and material untouched."""
import importlib

import bpy

import numpy as np
import pytest

from blender_support import extension_module_name

DENSITY = 3.0
COLOR = (0.8, 0.6, 0.4, 1.0)


@pytest.fixture
def volume_io(visibake):
    return importlib.import_module(extension_module_name() + ".operators.adapter.volume_io")


@pytest.fixture
def refused(visibake):
    return importlib.import_module(extension_module_name() + ".core.errors").VolumeRefused


def volume_material(name="Fog", surface=False):
    """A material whose output takes its Volume from a Principled Volume (and, with ``surface``,
    its Surface from a Principled BSDF)."""
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    material = bpy.data.materials.new(name)
    compat.ensure_node_tree(material)
    tree = material.node_tree
    tree.nodes.clear()
    principled = tree.nodes.new("ShaderNodeVolumePrincipled")
    principled.inputs["Density"].default_value = DENSITY
    principled.inputs["Color"].default_value = COLOR
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(principled.outputs[0], output.inputs["Volume"])
    if surface:
        bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
        tree.links.new(bsdf.outputs[0], output.inputs["Surface"])
    return material


def mesh_object(name, vertices, faces, material=None):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    if material is not None:
        mesh.materials.append(material)
    return obj


def cube_object(name="Fog", material=None, half=1.0):
    vertices = [(x * half, y * half, z * half) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return mesh_object(name, vertices, faces, material if material is not None else volume_material(name))


def plane_object(name="Sheet", material=None):
    return mesh_object(name, [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [(0, 1, 2, 3)],
                       material if material is not None else volume_material(name))


def snapshot(obj) -> dict:
    """What reading must leave as it was: the object, its mesh, its material and the datablocks."""
    mesh, material = obj.data, obj.active_material
    positions = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", positions)
    tree = material.node_tree
    return {
        "matrix": np.array(obj.matrix_world).tolist(), "modifiers": [m.name for m in obj.modifiers],
        "mesh": mesh.name, "vertices": positions.tolist(), "polygons": len(mesh.polygons),
        "loop_triangles": len(mesh.loop_triangles), "material": material.name,
        "nodes": sorted(n.bl_idname for n in tree.nodes), "links": len(tree.links),
        "density": tree.nodes["Principled Volume"].inputs["Density"].default_value,
        "color": tuple(tree.nodes["Principled Volume"].inputs["Color"].default_value),
        "counts": (len(bpy.data.meshes), len(bpy.data.materials), len(bpy.data.objects), len(bpy.data.volumes)),
        "users": (mesh.users, material.users), "owned": obj.get("visibake_volume_of"),
    }


def world_points(medium, voxels):
    return medium.world_positions(np.asarray(voxels, np.int32))


def test_a_cube_with_a_volume_material_is_filled_where_the_object_is(volume_io, clean_scene):
    cube = cube_object()
    cube.location = (3.0, -1.0, 2.0)
    cube.scale = (2.0, 0.5, 1.0)
    cube.rotation_euler = (0.0, 0.0, 0.3)
    bpy.context.view_layer.update()
    assert volume_io.is_mesh_volume(cube)
    before = snapshot(cube)
    warnings = []
    medium, index_to_local = volume_io.read_mesh_medium(cube, 16, warnings)
    assert snapshot(cube) == before   # nothing of the user's changed, no mesh left behind
    assert warnings == []

    # A grid of 16 fitted to the local cube: 14 voxels across it, one empty margin voxel each side.
    assert medium.shape == (16, 16, 16) and medium.name == "Fog"
    assert np.all(medium.density[1:-1, 1:-1, 1:-1] == 1.0)
    assert medium.density.sum() == 14 ** 3
    # The material's Density is the extinction (a mesh has no density grid: 1 x Density inside,
    # as in Cycles; a black Absorption Color absorbs what the colour does not scatter); the
    # colour is the albedo.
    assert medium.extinction == pytest.approx(DENSITY)
    np.testing.assert_allclose(medium.albedo[8, 8, 8], COLOR[:3], rtol=1e-6)
    assert medium.emission is None

    # Object space: the grid's outer faces one voxel (2 / 14) outside the cube's [-1, 1], so
    # voxel 0's centre is half a voxel outside it.
    voxel = 2.0 / 14
    np.testing.assert_allclose(index_to_local[:3, :3], np.eye(3) * voxel, rtol=1e-6)
    np.testing.assert_allclose(index_to_local[:3, 3], [-1.0 - 0.5 * voxel] * 3, rtol=1e-6)
    # World: the medium's transform is the object's matrix after index_to_local.
    world = np.array(cube.matrix_world)
    np.testing.assert_allclose(medium.index_to_world, world @ index_to_local)
    # Every filled voxel's centre lies inside the moved, scaled, rotated cube; the margin's outside.
    to_local = np.linalg.inv(world)
    filled = world_points(medium, medium.active())
    local = filled @ to_local[:3, :3].T + to_local[:3, 3]
    assert np.all(np.abs(local) < 1.0)
    low, high = filled.min(axis=0), filled.max(axis=0)
    corners = np.array([(x, y, z, 1.0) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) @ world.T
    assert np.all(low > corners[:, :3].min(axis=0)) and np.all(high < corners[:, :3].max(axis=0))
    centre = world_points(medium, [(8, 8, 8)])[0]
    assert np.linalg.norm(centre - np.array(cube.location)) < 2 * voxel * 2.0
    margin = world_points(medium, [(0, 8, 8), (15, 8, 8)])
    local_points = margin @ to_local[:3, :3].T + to_local[:3, 3]
    assert np.all(np.abs(local_points[:, 0]) > 1.0)


def test_the_mesh_is_read_with_its_modifiers(volume_io, clean_scene):
    """A plane encloses nothing, but a Solidify modifier makes it a closed slab."""
    sheet = plane_object()
    solidify = sheet.modifiers.new("Thicken", "SOLIDIFY")
    solidify.thickness = 4.0 / 9.0
    solidify.offset = 0.0
    bpy.context.view_layer.update()
    medium, index_to_local = volume_io.read_mesh_medium(sheet, 20, [])
    # The slab is 2 x 2 x 4/9: 18 voxels of 1/9 across, 4 through; its faces lie on voxel faces,
    # so the voxelised volume is exact.
    assert medium.shape == (20, 20, 4 + 2)
    volume = medium.density.sum() * abs(np.linalg.det(index_to_local[:3, :3]))
    assert volume == pytest.approx(2.0 * 2.0 * 4.0 / 9.0, rel=1e-5)
    assert len(sheet.data.polygons) == 1 and [m.name for m in sheet.modifiers] == ["Thicken"]


def test_a_plane_and_a_mesh_without_faces_are_refused_with_the_reason(volume_io, refused, clean_scene):
    sheet = plane_object()
    assert volume_io.is_mesh_volume(sheet)  # it has a volume material: the reading refuses it
    before = snapshot(sheet)
    with pytest.raises(refused, match="encloses nothing.*must be closed"):
        volume_io.read_mesh_medium(sheet, 16, [])
    assert snapshot(sheet) == before
    points = mesh_object("Points", [(0, 0, 0), (1, 0, 0), (0, 1, 1)], [], volume_material("Dust"))
    with pytest.raises(refused, match="no faces"):
        volume_io.read_mesh_medium(points, 16, [])


def test_which_meshes_are_mesh_volumes(volume_io, clean_scene):
    plain = cube_object("Plain", material=bpy.data.materials.new("Plain"))
    assert not volume_io.is_mesh_volume(plain)
    bare = mesh_object("Bare", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    assert not volume_io.is_mesh_volume(bare)
    scatter = bpy.data.materials.new("Scatter")
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    compat.ensure_node_tree(scatter)
    tree = scatter.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(tree.nodes.new("ShaderNodeVolumeScatter").outputs[0], output.inputs["Volume"])
    assert not volume_io.is_mesh_volume(cube_object("Scattering", material=scatter))
    made = cube_object("Made")
    made["visibake_volume_of"] = "Something"
    assert not volume_io.is_mesh_volume(made)
    assert volume_io.is_mesh_volume(cube_object("Fog"))
    # A Volume object is not a mesh volume (read_medium reads it).
    volume = bpy.data.objects.new("Cloud", bpy.data.volumes.new("Cloud"))
    bpy.context.scene.collection.objects.link(volume)
    assert not volume_io.is_mesh_volume(volume) and volume_io.is_volume_target(volume)


def test_a_surface_shader_and_emission_are_reported_and_baked_inside(volume_io, clean_scene):
    material = volume_material("Glow", surface=True)
    principled = material.node_tree.nodes["Principled Volume"]
    principled.inputs["Emission Strength"].default_value = 2.0
    principled.inputs["Emission Color"].default_value = (1.0, 0.5, 0.25, 1.0)
    cube = cube_object("Glow", material=material)
    bpy.context.view_layer.update()
    warnings = []
    medium, _ = volume_io.read_mesh_medium(cube, 12, warnings)
    assert any("Surface shader" in line for line in warnings), warnings
    # Emission is Cycles' throughout the inside: full in whole voxels, nothing in the margin.
    np.testing.assert_allclose(medium.emission[6, 6, 6], [2.0, 1.0, 0.5], rtol=1e-6)
    assert not medium.emission[0].any()


def test_the_baked_object_of_a_mesh_volume_sits_where_the_mesh_is(volume_io, visibake, clean_scene, tmp_path):
    compat = importlib.import_module(extension_module_name() + ".operators.adapter.compat")
    try:
        vdb = compat.openvdb()
    except compat.FeatureMissing as missing:
        pytest.skip(f"volumes need Blender's openvdb module: {missing}")
    cube = cube_object(half=0.7)
    cube.location = (1.0, 2.0, 3.0)
    cube.scale = (1.5, 1.5, 1.5)
    bpy.context.view_layer.update()
    before = snapshot(cube)
    medium, index_to_local = volume_io.read_mesh_medium(cube, 16, [])
    path = tmp_path / "Fog.vdb"
    volume_io.write_grids(vdb, str(path), {"density": medium.density,
                                           "emission": np.zeros((*medium.shape, 3), np.float32)}, index_to_local)
    baked = volume_io.make_baked_object(cube, str(path), medium.extinction)
    assert baked.type == "VOLUME" and baked.get("visibake_volume_of") == "Fog"
    np.testing.assert_allclose(np.array(baked.matrix_world), np.array(cube.matrix_world))
    assert baked.users_collection[0] == cube.users_collection[0]
    bpy.context.view_layer.update()
    baked.data.grids.load()
    assert {g.name for g in baked.data.grids} == {"density", "emission"}
    # The baked volume's bounds (its active voxels, in object space) are the mesh's, +-0.7, to
    # within a voxel (1.4 / 14).
    corners = np.array([tuple(c) for c in baked.evaluated_get(bpy.context.evaluated_depsgraph_get()).bound_box])
    np.testing.assert_allclose(corners.min(axis=0), [-0.7] * 3, atol=0.1 + 1e-6)
    np.testing.assert_allclose(corners.max(axis=0), [0.7] * 3, atol=0.1 + 1e-6)
    volume_io.remove_baked_object(baked)
    assert snapshot(cube) == before


def test_a_density_attribute_and_other_materials_are_reported(volume_io, clean_scene):
    cube = cube_object()
    cube.data.attributes.new("density", "FLOAT", "POINT")
    cube.data.materials.append(bpy.data.materials.new("Paint"))
    bpy.context.view_layer.update()
    warnings = []
    medium, _ = volume_io.read_mesh_medium(cube, 8, warnings)
    assert any("'density' attribute" in line for line in warnings), warnings
    assert any("only its active material 'Fog'" in line and "'Paint'" in line for line in warnings), warnings
    assert medium.density.max() == 1.0


def test_visibake_volume_bakes_a_fog_cube_beside_a_solid_mesh_that_shadows_part_of_it(visibake, clean_scene, tmp_path):
    """The command finds the fog cube among the scene's meshes, voxelises it, and takes the solid
    mesh above half of it as an occluder (never the fog cube itself)."""
    import json
    import math

    from bpy_scenes import black_world, sun

    try:
        importlib.import_module(extension_module_name() + ".operators.adapter.compat").openvdb()
    except Exception as missing:  # noqa: BLE001 - compat.FeatureMissing where Blender lacks openvdb
        pytest.skip(f"volumes need Blender's openvdb module: {missing}")
    black_world()
    sun(3.0)  # straight down
    cube_object("Fog", half=0.5)  # 1 m cube of density 3 at the origin
    mesh_object("Roof", [(-2, -2, 2), (0, -2, 2), (0, 2, 2), (-2, 2, 2)], [(0, 1, 2, 3)])
    blend = tmp_path / "fog.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    out, report_path = tmp_path / "out", tmp_path / "report.json"
    status = visibake.cli.main(["volume", str(blend), "--out", str(out), "--resolution", "22", "--directions", "16",
                                "--bounces", "0", "--report", str(report_path), "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    [entry] = report["volumes"]
    assert entry["name"] == "Fog" and entry["output"] == "Fog (VisiBake)" and entry["grid"] == [22, 22, 22]
    assert report["occluders"] == {"meshes": 1, "triangles": 2}
    assert "Roof" in bpy.data.objects
    vdb = importlib.import_module(extension_module_name() + ".operators.adapter.compat").openvdb()
    grid = vdb.read(str(out / "Fog" / "direct.vdb"), "direct")
    direct = np.zeros((22, 22, 22, 3), np.float32)
    grid.copyToArray(direct, ijk=(0, 0, 0))
    # Grid: 22 voxels over the cube's 1 m plus a voxel of margin each side (1/20 m voxels,
    # centres from -0.525 m): x index 10 is at -0.025 m (under the roof), 11 at +0.025 m.
    column = direct[15, 11, :, 0]  # x = +0.225 m, y = +0.025 m: in the sun
    assert direct[:10, 1:-1, 1:-1].max() == 0.0  # x < 0: under the roof
    top, lower = 20, 10  # z = +0.475 m (fully inside) and -0.025 m
    expected = 3.0 / (4 * math.pi) * math.exp(-DENSITY * (0.5 - 0.475))
    assert column[top] == pytest.approx(expected, rel=0.1)
    assert column[lower] == pytest.approx(3.0 / (4 * math.pi) * math.exp(-DENSITY * 0.525), rel=0.1)
