"""Issue 14, class 2: results lost or clobbered without a word.

Vertex-mode results reach ``--out`` as PLY files; linked duplicates (one mesh, two
objects) get each their own result or a clear refusal; preview nodes never make an
object show lighting that is not its own. Through the command line and the operators.
"""
import json

import bpy

import numpy as np
import pytest

from bpy_scenes import (
    black_world,
    color_attribute,
    cube,
    grid,
    material,
    mesh_object,
    point,
    scene_report,
    select_only,
    small_bake_settings,
)


def _vertex_scene(tmp_path):
    """A dense floor that mode auto bakes with vertex tables, a flat-shaded box baked in
    vertex mode (face-corner results), mirrored to check the winding, and a lamp."""
    black_world()
    floor = mesh_object("Floor", grid(1.0, segments=80), material("White", (0.7, 0.7, 0.7)), uv_map=None)
    box = mesh_object("Box", cube(0.4), material("Grey", (0.5, 0.5, 0.5)), location=(0.3, 0.2, 0.2), uv_map=None)
    box.scale = (-1.0, 1.0, 1.0)
    box.visibake.mode = "vertex"
    point(150.0, (0.6, -0.5, 1.2), name="Lamp")
    path = tmp_path / "vertex.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return floor, box, path


def _open(path):
    bpy.ops.wm.open_mainfile(filepath=str(path))


def test_auto_mode_writes_vertex_results_under_out(visibake, clean_scene, tmp_path, capsys):
    from bl_ext.user_default.visibake.core.outputs.vertex_files import read_ply

    _, _, blend = _vertex_scene(tmp_path)
    out, saved, report_path = tmp_path / "out", tmp_path / "saved.blend", tmp_path / "report.json"
    status = visibake.cli.main(["bake", str(blend), "--mode", "auto", "--out", str(out), "--save", str(saved),
                                "--report", str(report_path), "--directions", "32", "--bounces", "1",
                                "--resolution", "32", "--passes", "lighting,ao", "--previews", "--no-progress"])
    assert status == 0
    report = json.loads(report_path.read_text())
    modes = {o["name"]: o["mode"] for o in report["objects"]}
    assert modes == {"Floor": "vertex", "Box": "vertex"}
    _open(saved)
    for name, domain in (("Floor", "POINT"), ("Box", "CORNER")):
        obj = bpy.data.objects[name]
        for pass_name in ("lighting", "ao"):
            path = out / name / f"{pass_name}.ply"
            assert str(path) in report["files"]
            positions, faces, colors = read_ply(str(path))
            attribute_domain, values = color_attribute(obj, f"VB_{pass_name}")
            assert attribute_domain == domain
            # The file holds the attribute's values exactly, one PLY vertex per element.
            np.testing.assert_array_equal(colors, values[:, :3])
            assert np.all(np.isfinite(positions)) and colors[:, 0].max() > 0
            corner_vertex = np.array([loop.vertex_index for loop in obj.data.loops])
            world = np.array([obj.matrix_world @ v.co for v in obj.data.vertices])
            expected = world if domain == "POINT" else world[corner_vertex]
            np.testing.assert_allclose(positions, expected, atol=1e-5)
            assert len(faces) == sum(len(p.vertices) - 2 for p in obj.data.polygons)
            # Faces turn counter-clockwise seen from the front (the mirrored box included):
            # their normals point away from the box's centre.
            if name == "Box":
                corners = positions[faces]
                normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
                outward = corners.mean(axis=1) - np.array(obj.matrix_world.translation)
                assert np.all(np.einsum("fd,fd->f", normals, outward) > 0)
            preview = out / name / f"{pass_name}.preview.ply"
            assert str(preview) in report["files"]
            _, _, display = read_ply(str(preview))
            assert display.max() <= 255 and display.max() > 0
    # No PNG for vertex data; the summary counts what was written.
    assert not list(out.rglob("*.png"))
    # ... and the folder's record of them (core.outputs.ownership).
    assert sorted(report["files"]) == sorted([str(p) for p in out.rglob("*.ply")]
                                             + [str(out / "visibake-bake.json"), str(saved)])
    assert len(report["files"]) == 10 and "files: 10 written" in capsys.readouterr().out


def test_vertex_files_without_save_are_the_only_copy(visibake, clean_scene, tmp_path):
    from bl_ext.user_default.visibake.core.outputs.vertex_files import read_ply

    _, _, blend = _vertex_scene(tmp_path)
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(blend), "--mode", "auto", "--out", str(out),
                              "--directions", "32", "--resolution", "32", "--no-progress"]) == 0
    for name in ("Floor", "Box"):
        _, _, colors = read_ply(str(out / name / "lighting.ply"))
        assert np.all(np.isfinite(colors)) and colors.max() > 0


def test_blender_reads_the_vertex_files_back(visibake, clean_scene, tmp_path):
    floor, box, _ = _vertex_scene(tmp_path)
    # The operator, with the panel's output folder: the same files as the command line.
    props = small_bake_settings(mode="auto")
    out = tmp_path / "out"
    props.output_dir = str(out)
    select_only([floor, box])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert {str(out / n / "lighting.ply") for n in ("Floor", "Box")} <= set(scene_report()["files"])
    for obj in (floor, box):
        _, values = color_attribute(obj)
        bpy.ops.wm.ply_import(filepath=str(out / obj.name / "lighting.ply"), import_colors="LINEAR")
        imported = bpy.context.selected_objects[0]
        assert imported is not obj and len(imported.data.vertices) == len(values)
        _, colors = color_attribute(imported, imported.data.color_attributes[0].name)
        np.testing.assert_allclose(colors[:, :3], values[:, :3], rtol=1e-6, atol=1e-7)


def _linked_duplicates(uv_map=None):
    """Objects A and B sharing one mesh, a lamp close above A only: clearly different light."""
    black_world()
    a = mesh_object("A", grid(1.0, segments=4), material("White", (0.7, 0.7, 0.7)), uv_map=uv_map)
    b = bpy.data.objects.new("B", a.data)
    b.location = (4.0, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(b)
    point(200.0, (0.2, 0.1, 0.8), name="Lamp")
    bpy.context.view_layer.update()
    return a, b


def test_linked_duplicates_in_vertex_mode_are_refused_before_any_work(visibake, clean_scene, tmp_path, capfd):
    a, b = _linked_duplicates()
    small_bake_settings(mode="vertex")
    select_only([a])
    # Even one of them baked: its result would land on the mesh B shows too.
    with pytest.raises(RuntimeError, match="share the mesh .*Make Single User.*mode atlas"):
        bpy.ops.visibake.bake()
    assert "VB_lighting" not in a.data.color_attributes and "visibake_report" not in bpy.context.scene
    blend = tmp_path / "shared.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(blend), "--mode", "vertex", "--out", str(out), "--directions", "32",
                              "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'A', 'B'" in err[0] and "Make Single User" in err[0]
    assert not out.exists()


def test_made_single_user_they_bake_in_vertex_mode(visibake, clean_scene):
    a, b = _linked_duplicates()
    b.data = a.data.copy()
    small_bake_settings(mode="vertex")
    select_only([a, b])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    # The lamp is above A: A's vertices are far brighter than B's.
    assert color_attribute(a)[1][:, 0].mean() > 10 * color_attribute(b)[1][:, 0].mean() > 0


def _atlas_image(name):
    from bpy_scenes import image_pixels

    return image_pixels(name).copy()


@pytest.mark.parametrize("uv_map", ["UVMap", None])
def test_linked_duplicates_in_atlas_mode_get_each_their_own_image(visibake, clean_scene, uv_map):
    """Baked together, each object's image equals its image baked alone (the other then only
    occludes), though the mesh and its UV map are one; with different resolutions too."""
    a, b = _linked_duplicates(uv_map)
    b.visibake.resolution = 48  # A keeps the scene's 32
    small_bake_settings(mode="atlas")
    select_only([a, b])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    together = {name: _atlas_image(f"VB_{name}_lighting") for name in ("A", "B")}
    entries = {o["name"]: o for o in scene_report()["objects"]}
    assert entries["A"]["uv_map"] == entries["B"]["uv_map"] == (uv_map or "VisiBake")
    alone = {}
    for obj in (a, b):
        select_only([obj])
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        alone[obj.name] = _atlas_image(f"VB_{obj.name}_lighting")
    assert together["A"].shape[:2] == (32, 32) and together["B"].shape[:2] == (48, 48)
    for name in ("A", "B"):
        np.testing.assert_allclose(together[name], alone[name], rtol=1e-5, atol=1e-7)
    # And the lighting is each one's own: the lamp is above A.
    assert together["A"][..., 0].mean() > 10 * together["B"][..., 0].mean() > 0
    assert [layer.name for layer in a.data.uv_layers].count("VisiBake") == (0 if uv_map else 1)


def _tree_state(mat):
    tree = mat.node_tree
    nodes = sorted((n.name, n.bl_idname) for n in tree.nodes)
    links = sorted((link.from_node.name, link.from_socket.identifier, link.to_node.name, link.to_socket.identifier)
                   for link in tree.links)
    active = [n.name for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output]
    return nodes, links, active


def _boxes_sharing_a_material():
    """Box and Box2 (own meshes) share the material 'Shared'; the floor has its own."""
    black_world()
    shared = material("Shared", (0.6, 0.6, 0.6))
    floor = mesh_object("Floor", grid(2.0), material("White", (0.8, 0.8, 0.8)))
    box = mesh_object("Box", cube(0.4), shared, location=(-0.8, 0.0, 0.2), uv_map=None)
    box2 = mesh_object("Box2", cube(0.4), shared, location=(0.8, 0.0, 0.2), uv_map=None)
    point(120.0, (-0.8, -0.6, 1.0), name="Lamp")
    return floor, box, box2, shared


def test_preview_nodes_leave_a_material_an_unbaked_object_uses(visibake, clean_scene, tmp_path, capfd):
    _, _, _, shared = _boxes_sharing_a_material()
    before = _tree_state(shared)
    blend, saved, report_path = tmp_path / "boxes.blend", tmp_path / "saved.blend", tmp_path / "report.json"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    assert visibake.cli.main(["bake", str(blend), "--objects", "Box", "--preview-nodes", "--save", str(saved),
                              "--report", str(report_path), "--directions", "32", "--resolution", "32",
                              "--mode", "atlas", "--no-progress"]) == 0
    report = json.loads(report_path.read_text())
    warnings = report["warnings"]
    assert {o["name"]: o["mode"] for o in report["objects"] if o["output"]} == {"Box": "atlas"}
    assert any("material 'Shared' is used by 'Box', 'Box2'" in w and "own copy" in w for w in warnings)
    _open(saved)
    assert "VB_Box_lighting" in bpy.data.images
    assert _tree_state(bpy.data.materials["Shared"]) == before
    # The preview command on the baked file: the same refusal, as a warning on stderr.
    shown = tmp_path / "shown.blend"
    capfd.readouterr()
    assert visibake.cli.main(["preview", str(saved), "--objects", "Box", "--save", str(shown)]) == 0
    captured = capfd.readouterr()
    assert "warning: material 'Shared' is used by 'Box', 'Box2'" in captured.err
    assert "shown in 0 material(s)" in captured.out
    _open(shown)
    assert _tree_state(bpy.data.materials["Shared"]) == before


def test_preview_operator_never_shows_one_object_another_s_lighting(visibake, clean_scene):
    floor, box, box2, shared = _boxes_sharing_a_material()
    small_bake_settings(mode="atlas")
    select_only([box, floor])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    before = _tree_state(shared)
    floor_before = _tree_state(floor.active_material)
    assert bpy.ops.visibake.preview_add() == {"FINISHED"}
    assert _tree_state(shared) == before  # Box2 would show Box's image
    assert _tree_state(floor.active_material) != floor_before  # the floor's own material is wired
    # A material wired while one object used it is taken out again once another uses it too.
    box2.data.materials.clear()
    box2.data.materials.append(floor.active_material)
    wired, warnings = visibake.operators.adapter.preview_nodes.add_preview([floor])
    assert wired == 0 and _tree_state(floor.active_material) == floor_before
    assert len(warnings) == 1 and "'Box2', 'Floor'" in warnings[0]


def test_a_material_shared_by_vertex_mode_objects_shows_each_its_own_attribute(visibake, clean_scene):
    floor, box, box2, shared = _boxes_sharing_a_material()
    small_bake_settings(mode="vertex")
    select_only([box, box2])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    # The lamp is nearer Box: their attributes differ, and each lives on its own mesh.
    assert color_attribute(box)[1][:, 0].mean() > 1.5 * color_attribute(box2)[1][:, 0].mean() > 0
    wired, warnings = visibake.operators.adapter.preview_nodes.add_preview([box, box2])
    assert wired == 1 and warnings == []
    group = next(n for n in shared.node_tree.nodes if n.bl_idname == "ShaderNodeGroup").node_tree
    attribute_nodes = [n for n in group.nodes if n.bl_idname == "ShaderNodeVertexColor"]
    assert [n.layer_name for n in attribute_nodes] == ["VB_lighting"]
    # Box2 unbaked (its attribute gone) or sharing Box's mesh: then it would not show its own light.
    box2.data = box.data
    wired, warnings = visibake.operators.adapter.preview_nodes.add_preview([box])
    assert wired == 0 and len(warnings) == 1
    assert not any(n.get("visibake_preview") for n in shared.node_tree.nodes)


def test_a_mirrored_flat_shaded_box_gets_each_corner_its_own_light(visibake, clean_scene):
    """Negative scale turns the triangles' winding around; the corners' results must turn with
    it. A cube is its own mirror image, so mirrored it must be lit as it is unmirrored."""
    black_world()
    box = mesh_object("Box", cube(1.0), material("Grey", (0.5, 0.5, 0.5)), uv_map=None)
    point(200.0, (1.5, -1.0, 2.0), name="Lamp")
    small_bake_settings(mode="vertex")
    select_only([box])
    lit = []
    for scale_x in (1.0, -1.0):
        box.scale = (scale_x, 1.0, 1.0)
        bpy.context.view_layer.update()
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        domain, values = color_attribute(box)
        assert domain == "CORNER"
        matrix, normal_matrix = box.matrix_world, box.matrix_world.to_3x3().inverted().transposed()
        by_corner = {}
        for polygon in box.data.polygons:
            normal = tuple(np.round(normal_matrix @ polygon.normal, 3))
            for loop in polygon.loop_indices:
                where = tuple(np.round(matrix @ box.data.vertices[box.data.loops[loop].vertex_index].co, 4))
                by_corner[where, normal] = values[loop, 0]
        lit.append(by_corner)
    assert lit[0].keys() == lit[1].keys()
    plain, mirrored = (np.array([light[k] for k in sorted(lit[0])]) for light in lit)
    assert plain.max() > 0
    np.testing.assert_allclose(mirrored, plain, rtol=1e-4, atol=1e-6)


def test_linked_duplicates_share_one_unwrap_at_the_smaller_size(visibake, clean_scene):
    from bl_ext.user_default.visibake.operators.adapter.extraction import plan_extraction

    a, b = _linked_duplicates(None)
    b.visibake.resolution = 48
    small_bake_settings(mode="atlas")
    planned = plan_extraction(bpy.context, [a, b])
    assert len(planned.unwraps) == 1 and planned.unwraps[0].resolution == 32
    assert planned.plans["A"].resolution == (32, 32) and planned.plans["B"].resolution == (48, 48)


def test_lighting_setups_write_vertex_results_per_setup(visibake, clean_scene, tmp_path):
    from bl_ext.user_default.visibake.core.outputs.vertex_files import read_ply

    _, _, blend = _vertex_scene(tmp_path)
    out = tmp_path / "out"
    assert visibake.cli.main(["bake", str(blend), "--mode", "vertex", "--out", str(out), "--sun-sweep", "8:16:2",
                              "--directions", "32", "--no-progress"]) == 0
    files = sorted(out.rglob("*.ply"))
    assert len(files) == 4 and {f.parent.name for f in files} == {"Floor", "Box"}
    # Each setup's own light: the sun moved between them.
    by_setup = {}
    for path in files:
        by_setup.setdefault(path.parent.parent.name, {})[path.parent.name] = read_ply(str(path))[2]
    first, second = by_setup.values()
    assert not np.allclose(first["Floor"], second["Floor"])


def test_mode_auto_refuses_vertex_tables_on_a_shared_mesh(visibake, clean_scene, tmp_path, capfd):
    """Mode auto takes vertex tables for a dense mesh; shared, it is refused the same way, before
    anything is unwrapped or written."""
    black_world()
    dense = mesh_object("Dense", grid(1.0, segments=80), material("White", (0.7, 0.7, 0.7)), uv_map=None)
    twin = bpy.data.objects.new("Twin", dense.data)
    twin.location = (3.0, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(twin)
    point(100.0, (0.0, 0.0, 1.0), name="Lamp")
    blend = tmp_path / "dense.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    out, saved = tmp_path / "out", tmp_path / "saved.blend"
    assert visibake.cli.main(["bake", str(blend), "--mode", "auto", "--objects", "Dense", "--resolution", "32",
                              "--out", str(out), "--save", str(saved), "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'Dense', 'Twin' share the mesh" in err[0]
    assert not out.exists() and not saved.exists()
