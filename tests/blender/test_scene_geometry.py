"""Geometry as Cycles sees it, base colour above 1 and precision far from the origin, in real bpy.

Each probe is a plane under a sun with a scene feature between them, baked by VisiBake and
by Cycles (tools/cycles_bake.py) on the same UV map. A probe asserts that the shadow is
there (or, for geometry Cycles does not render, that it is not) and that the two bakes
agree within the noise the test states. ``-s`` prints the measured numbers.
"""
import json
import math

import bpy

import numpy as np
import pytest

from bpy_scenes import (
    black_world,
    cube,
    grid,
    image_pixels,
    material,
    mesh_object,
    relative_rmse,
    select_only,
    sun,
)
from tools.blender_compat import compat
from tools.cycles_bake import bake_diffuse

RHO, SUN_STRENGTH, TILT = 0.8, 3.0, 20.0
RESOLUTION = 24
# Lit ground: rho * S * cos(tilt) / pi, plus the little light the feature bounces down.
LIT = RHO * SUN_STRENGTH * math.cos(math.radians(TILT)) / math.pi
# Cycles at 64 samples per texel under a zero-angle sun: direct light has no noise, the
# one bounce off the feature a few percent of a small term. What separates the bakes is
# texel-centre sampling along the shadow's edge (Cycles jitters over half a texel, or a whole one
# from Blender 5.2.1): the
# edge texels (about 4 per row of 24 for these shadows) differ by up to half the lit
# value, an RMSE of about 0.5 * sqrt(4/24) ~ 0.2 of the mean at worst. 0.15 bounds it for
# shadows of this size; a missing shadow (the bug) is an RMSE of 0.3 or more.
EDGE_RMSE = 0.15


def _ground():
    """A 1 x 1 ground (bmesh's grid size is half its width)."""
    return mesh_object("Ground", grid(0.5), material("White", (RHO, RHO, RHO)))


def _bake_both(ground):
    """VisiBake's and Cycles' lighting of ``ground``, and VisiBake's report."""
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.shadows, props.resolution = 64, 1, "exact", RESOLUTION
    props.passes = {"lighting"}
    props.bake_all = False
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    ours = image_pixels("VB_Ground_lighting")
    reference = bake_diffuse([ground], "UVMap", RESOLUTION, RESOLUTION, bounces=1, samples=64)["Ground"]
    return ours, reference, json.loads(bpy.context.scene["visibake_report"])


def _shadowed(image):
    """Fraction of the ground's texels that get less than half the lit value."""
    return float(np.mean(image[..., 0] < 0.5 * LIT))


def _collection(name, parent=None):
    collection = bpy.data.collections.new(name)
    (parent or bpy.context.scene.collection).children.link(collection)
    return collection


def _move_to(obj, collection):
    for old in list(obj.users_collection):
        old.objects.unlink(obj)
    collection.objects.link(obj)
    return obj


def _occluder(location=(0.0, 0.0, 0.5), size=0.4):
    return mesh_object("Occluder", cube(size), material("Grey", (0.5, 0.5, 0.5)), location=location, uv_map=None)


def _collection_instance():
    source = _collection("Rocks")
    _move_to(_occluder(location=(0.0, 0.0, 0.0)), source)
    # The usual set-up: the source collection is excluded, only its instance renders.
    bpy.context.view_layer.layer_collection.children["Rocks"].exclude = True
    empty = bpy.data.objects.new("RockInstance", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", source
    empty.location = (0.0, 0.0, 0.5)
    bpy.context.scene.collection.objects.link(empty)


def _geometry_nodes_instances():
    points = mesh_object("Points", lambda bm, uv: [bm.verts.new((x, y, 0.0)) for x in (-0.15, 0.15)
                                                   for y in (-0.15, 0.15)], location=(0.0, 0.0, 0.5), uv_map=None)
    tree = bpy.data.node_groups.new("Scatter", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in, group_out = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    on_points, box = tree.nodes.new("GeometryNodeInstanceOnPoints"), tree.nodes.new("GeometryNodeMeshCube")
    box.inputs["Size"].default_value = (0.2, 0.2, 0.2)
    tree.links.new(group_in.outputs[0], on_points.inputs["Points"])
    tree.links.new(box.outputs["Mesh"], on_points.inputs["Instance"])
    tree.links.new(on_points.outputs["Instances"], group_out.inputs[0])
    points.modifiers.new("Scatter", "NODES").node_group = tree


def _bevelled_curve():
    data = bpy.data.curves.new("Pipe", "CURVE")
    data.dimensions, data.bevel_depth, data.bevel_resolution = "3D", 0.12, 4
    spline = data.splines.new("POLY")
    spline.points.add(1)
    spline.points[0].co, spline.points[1].co = (-0.35, 0.0, 0.0, 1.0), (0.35, 0.0, 0.0, 1.0)
    obj = bpy.data.objects.new("Pipe", data)
    obj.location = (0.0, 0.0, 0.5)
    bpy.context.scene.collection.objects.link(obj)


def _text():
    data = bpy.data.curves.new("Label", "FONT")
    data.body, data.size, data.extrude, data.align_x, data.align_y = "W", 0.9, 0.02, "CENTER", "CENTER"
    obj = bpy.data.objects.new("Label", data)
    obj.location = (0.0, 0.0, 0.5)
    bpy.context.scene.collection.objects.link(obj)


def _metaball():
    data = bpy.data.metaballs.new("Blob")
    # The viewport and render resolutions agree, so the viewport's geometry is Cycles'.
    data.resolution = data.render_resolution = 0.05
    element = data.elements.new()
    element.radius = 0.3
    obj = bpy.data.objects.new("Blob", data)
    obj.location = (0.0, 0.0, 0.5)
    bpy.context.scene.collection.objects.link(obj)


def _render_disabled_collection():
    _move_to(_occluder(), _collection("Disabled")).users_collection[0].hide_render = True


def _excluded_collection():
    _move_to(_occluder(), _collection("Excluded"))
    bpy.context.view_layer.layer_collection.children["Excluded"].exclude = True


def _viewport_hidden_collection():
    _move_to(_occluder(), _collection("Hidden")).users_collection[0].hide_viewport = True


def _nested_disabled_collection():
    inner = _collection("Inner", _collection("Outer"))
    _move_to(_occluder(), inner)
    bpy.data.collections["Outer"].hide_render = True


def _mirrored_collection_instance():
    _collection_instance()
    bpy.data.objects["RockInstance"].scale = (-1.0, 1.0, 1.0)  # winding and normals turn back


def _hidden_curve():
    _bevelled_curve()
    bpy.data.objects["Pipe"].hide_set(True)  # hidden in the viewport (H), still rendered


CASTS = {"collection instance": _collection_instance, "geometry-nodes instances": _geometry_nodes_instances,
         "mirrored collection instance": _mirrored_collection_instance,
         "bevelled curve": _bevelled_curve, "curve hidden in the viewport": _hidden_curve, "text": _text,
         "metaball": _metaball,
         "collection hidden in the viewport only": _viewport_hidden_collection}
INVISIBLE = {"collection disabled in renders": _render_disabled_collection,
             "collection excluded from the view layer": _excluded_collection,
             "inside a collection disabled in renders": _nested_disabled_collection}


@pytest.mark.parametrize("feature", list(CASTS))
def test_feature_casts_its_shadow_as_in_cycles(visibake, clean_scene, feature):
    black_world()
    ground = _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    CASTS[feature]()
    ours, reference, report = _bake_both(ground)
    error = relative_rmse(ours, reference, reference[..., 3] > 0)
    print(f"\n{feature}: shadowed texels VisiBake {_shadowed(ours):.3f}, Cycles {_shadowed(reference):.3f}; "
          f"relative RMSE {error:.4f}")
    assert np.isfinite(ours).all()
    assert _shadowed(reference) > 0.03  # the probe has a shadow to find
    assert abs(_shadowed(ours) - _shadowed(reference)) < 0.25 * _shadowed(reference) + 2.0 / RESOLUTION ** 2
    assert error < EDGE_RMSE
    if feature != "collection hidden in the viewport only":
        assert any("occlude and reflect light but are not bake targets" in w for w in report["warnings"])
    assert not any("has no face" in w for w in report["warnings"])  # a scatter's points are not faulted


@pytest.mark.parametrize("feature", list(INVISIBLE))
def test_geometry_cycles_does_not_render_casts_no_shadow(visibake, clean_scene, feature):
    black_world()
    ground = _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    INVISIBLE[feature]()
    ours, reference, _ = _bake_both(ground)
    print(f"\n{feature}: shadowed texels VisiBake {_shadowed(ours):.3f}, Cycles {_shadowed(reference):.3f}")
    assert _shadowed(reference) == 0.0
    # Nothing at all between ground and sun: both are the exact lit value.
    np.testing.assert_allclose(reference[..., :3], LIT, rtol=1e-4)
    np.testing.assert_allclose(ours[..., :3], LIT, rtol=1e-4)


def test_instances_share_one_read_and_are_not_bake_targets(visibake, clean_scene):
    black_world()
    ground = _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    _collection_instance()
    second = bpy.data.objects.new("RockInstance2", None)
    second.instance_type, second.instance_collection = "COLLECTION", bpy.data.collections["Rocks"]
    second.location = (0.3, 0.3, 0.8)
    bpy.context.scene.collection.objects.link(second)
    _bevelled_curve()
    extract = visibake.operators.adapter.extract
    warnings = []
    geometry = extract.scene_geometry(bpy.context.evaluated_depsgraph_get(), bpy.context.scene, warnings)
    assert geometry.counts == {"instance": 2, "curve": 1}
    assert all(not mesh.output for mesh in geometry.meshes)
    # Each instancer's copies in world space: the cube's 8 corners moved by its instancer.
    rock = next(m for m in geometry.meshes if m.name.startswith("RockInstance2"))
    np.testing.assert_allclose(rock.positions.mean(axis=0), (0.3, 0.3, 0.8), atol=1e-9)
    # Selecting an instancer or a curve says why it gets no output.
    select_only([ground, second, bpy.data.objects["Pipe"]])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_report"])
    assert [o["name"] for o in report["objects"] if o["output"]] == ["Ground"]
    assert any("'RockInstance2' instances other objects" in w for w in report["warnings"])
    assert any("'Pipe' is a curve" in w for w in report["warnings"])


def test_instances_past_the_sample_budget_still_occlude(visibake, clean_scene, monkeypatch):
    black_world()
    ground = _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    _geometry_nodes_instances()
    monkeypatch.setattr(visibake.operators.adapter.extract, "REFLECTING_GEOMETRY_SAMPLES", 0)
    ours, reference, report = _bake_both(ground)
    error = relative_rmse(ours, reference, reference[..., 3] > 0)
    print(f"\ninstances that only occlude: shadowed texels VisiBake {_shadowed(ours):.3f}, Cycles "
          f"{_shadowed(reference):.3f}; relative RMSE {error:.4f}")
    assert any("only occlude light" in w for w in report["warnings"])
    assert abs(_shadowed(ours) - _shadowed(reference)) < 0.25 * _shadowed(reference)
    # What they no longer reflect is the one bounce off four small boxes: a few percent.
    assert error < EDGE_RMSE


def _base_colour_material(name, value, kind):
    mat = bpy.data.materials.new(name)
    tree = compat.ensure_node_tree(mat)
    if kind == "diffuse":
        principled = tree.nodes["Principled BSDF"]
        node = tree.nodes.new("ShaderNodeBsdfDiffuse")
        node.inputs["Color"].default_value = (value, value, value, 1.0)
        tree.links.new(node.outputs["BSDF"], principled.outputs["BSDF"].links[0].to_socket)
        tree.nodes.remove(principled)
    else:
        node = tree.nodes["Principled BSDF"]
        node.inputs["Base Color"].default_value = (value, value, value, 1.0)
        node.inputs["Roughness"].default_value = 1.0
        node.inputs["Specular IOR Level"].default_value = 0.0
    return mat


@pytest.mark.parametrize("kind", ["principled", "diffuse"])
def test_base_colour_above_one_is_kept_as_in_cycles(visibake, clean_scene, kind):
    black_world()
    bright = _base_colour_material("Bright", 1.5, kind)
    ground = mesh_object("Ground", grid(1.0), bright)
    # A wall of the same material beside the ground: its bounce is lit by 1.5 too.
    wall = mesh_object("Wall", grid(1.0), bright, location=(0.0, 0.5, 0.5), uv_map=None)
    wall.rotation_euler = (math.radians(90.0), 0.0, 0.0)
    sun(SUN_STRENGTH, tilt_degrees=40.0)
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.shadows, props.resolution = 128, 2, "exact", RESOLUTION
    props.passes = {"lighting"}
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    ours = image_pixels("VB_Ground_lighting")
    reference = bake_diffuse([ground], "UVMap", RESOLUTION, RESOLUTION, bounces=2, samples=256)["Ground"]
    report = json.loads(bpy.context.scene["visibake_report"])
    covered = reference[..., 3] > 0
    error = relative_rmse(ours, reference, covered)
    direct = 1.5 * SUN_STRENGTH * math.cos(math.radians(40.0)) / math.pi
    print(f"\nbase colour 1.5 ({kind}): VisiBake mean {ours[..., 0].mean():.4f}, Cycles "
          f"{reference[..., 0].mean():.4f}, direct alone {direct:.4f}; relative RMSE {error:.4f}")
    # Clamped to 1 the lit ground would be 1/1.5 of Cycles: a 33% error everywhere.
    assert abs(ours[..., 0].mean() / reference[..., 0].mean() - 1.0) < 0.03
    # The wall's shadow edge and the bounce's noise (256 spp, 2 bounces) stay under 10%.
    assert error < 0.10
    assert any("'Bright': base colour above 1" in w for w in report["warnings"])


def _offset_box_lighting(offset):
    """The ground-and-block probe moved by ``offset`` along (1, 1, 1); its lighting image."""
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    black_world()
    shift = np.array([offset, offset, offset], np.float64)
    ground = mesh_object("Ground", grid(1.0), material("White", (RHO, RHO, RHO)), location=tuple(shift))
    # Blender stores locations in float32 (steps of 1/16 at 1e6): the block sits on that grid,
    # so it is the same block at every offset and what is measured is VisiBake's precision.
    _occluder(location=tuple(shift + (0.125, 0.0, 0.375)), size=0.3)
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.shadows, props.resolution = 64, 1, "exact", RESOLUTION
    props.passes = {"lighting"}
    props.use_cache = False
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return image_pixels("VB_Ground_lighting"), json.loads(bpy.context.scene["visibake_report"])


def test_box_far_from_the_origin_is_lit_as_at_the_origin(visibake, clean_scene):
    at_origin, _ = _offset_box_lighting(0.0)
    covered = at_origin[..., 3] > 0
    for offset in (1e5, 1e6):
        far, report = _offset_box_lighting(offset)
        error = relative_rmse(far, at_origin, covered)
        mean_change = far[covered][:, 0].mean() / at_origin[covered][:, 0].mean() - 1.0
        print(f"\noffset {offset:.0e}: relative RMSE to the box at the origin {error:.5f}, mean {mean_change:+.5f}")
        assert error < 0.01
        assert not any(w.startswith("precision:") for w in report["warnings"])


def test_a_scene_too_large_for_float32_says_so(visibake, clean_scene):
    black_world()
    ground = mesh_object("Ground", grid(1e-3), material("White", (RHO, RHO, RHO)))
    # A distant object makes the traced frame large against the small ground.
    _occluder(location=(400.0, 0.0, 0.0), size=1.0)
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution = 16, 0, 8
    props.passes = {"lighting"}
    select_only([ground])
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    report = json.loads(bpy.context.scene["visibake_report"])
    assert any(w.startswith("precision:") for w in report["warnings"])


def test_cli_objects_naming_a_curve_says_why_it_is_no_target(visibake, clean_scene, tmp_path, capfd):
    black_world()
    _ground()
    _bevelled_curve()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    path = tmp_path / "curve.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    assert visibake.cli.main(["bake", str(path), "--objects", "Pipe", "--no-progress"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'Pipe' is a curve" in err[0] and "not a bake target" in err[0]


def test_baking_only_an_instancer_says_why_it_gets_no_output(visibake, clean_scene):
    black_world()
    _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    _collection_instance()
    select_only([bpy.data.objects["RockInstance"]])
    bpy.context.scene.visibake.bake_all = False
    with pytest.raises(RuntimeError, match="'RockInstance' instances other objects"):
        bpy.ops.visibake.bake()
    assert not any(image.name.startswith("VB_") for image in bpy.data.images)


def test_viewport_only_settings_are_named(visibake, clean_scene):
    black_world()
    ground = _ground()
    sun(SUN_STRENGTH, tilt_degrees=TILT)
    block = _occluder()
    modifier = block.modifiers.new("Smooth", "SUBSURF")
    modifier.levels, modifier.render_levels = 1, 2
    select_only([ground])
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution = 16, 0, 32
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    warnings = json.loads(bpy.context.scene["visibake_report"])["warnings"]
    assert any("'Occluder': modifier 'Smooth' has 1 viewport and 2 render levels" in w for w in warnings)


def test_hair_curves_cycles_renders_are_named_as_not_read(visibake, clean_scene):
    hair = bpy.data.hair_curves.new("Fur")
    hair.add_curves([3, 3])
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("Fur", hair))
    warnings = []
    geometry = visibake.operators.adapter.extract.scene_geometry(bpy.context.evaluated_depsgraph_get(),
                                                                 bpy.context.scene, warnings)
    assert geometry.meshes == []
    assert any("'Fur': its hair curves (which Cycles renders) are not read" in w for w in warnings)


@pytest.mark.parametrize("materials", [True, False], ids=["material-indices", "no-material-attribute"])
def test_triangles_read_from_attribute_arrays_are_blenders_loop_triangles(visibake, clean_scene, materials):
    """read_triangles takes the triangles' vertices and materials from the corner and face
    arrays: on quads, a concave n-gon and triangles, they are what Blender's per-triangle
    properties give (and the triangle's own material index, 0 without the attribute)."""
    import importlib
    extract = importlib.import_module(visibake.__name__ + ".operators.adapter.extract")
    mesh = bpy.data.meshes.new("Mixed")
    vertices = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0.2), (3, 0, 0), (3, 2, 0.1), (2.5, 0.5, 0),
                (2, 2, 0), (4, 0, 0), (4, 1, 0)]
    faces = [(0, 1, 2, 3), (4, 5, 6, 7, 8), (5, 9, 10), (1, 4, 8, 2)]
    mesh.from_pydata(vertices, [], faces)
    if materials:
        mesh.materials.append(bpy.data.materials.new("A"))
        mesh.materials.append(bpy.data.materials.new("B"))
        mesh.polygons.foreach_set("material_index", np.array([1, 0, 1, 1], np.int32))
    mesh.update()
    assert (mesh.attributes.get("material_index") is not None) == materials
    mesh.calc_loop_triangles()
    read = extract.read_triangles(mesh)
    count = len(mesh.loop_triangles)
    assert count == 2 + 3 + 1 + 2
    np.testing.assert_array_equal(read.triangles, [list(t.vertices) for t in mesh.loop_triangles])
    np.testing.assert_array_equal(read.loops, [list(t.loops) for t in mesh.loop_triangles])
    np.testing.assert_array_equal(read.material_index, [t.material_index for t in mesh.loop_triangles])
    np.testing.assert_array_equal(read.positions, [list(v.co) for v in mesh.vertices])
    assert read.triangles.dtype == np.int32 and read.loops.dtype == np.int64
    assert read.material_index.dtype == np.int32 and read.positions.dtype == np.float64
    assert read.material_index.any() == materials


def test_a_mesh_of_triangles_only_reads_its_corners_in_order_as_blender_s_loop_triangles_give_them(visibake,
                                                                                                  clean_scene):
    """Where every face is a triangle, read_triangles and read_mesh make no per-triangle read:
    the loop triangles are the faces, corners in order. The triangles, corners, per-corner UVs
    and normals are bitwise those gathered through Blender's own loop triangles, also after
    the faces were reordered and on a mirrored object; a mesh with one quad is read the
    general way."""
    import importlib
    extract = importlib.import_module(visibake.__name__ + ".operators.adapter.extract")
    bpy.ops.mesh.primitive_uv_sphere_add(segments=12, ring_count=7, location=(0.3, -0.2, 0.5))
    sphere = bpy.context.active_object
    bpy.ops.object.modifier_add(type="TRIANGULATE")
    bpy.ops.object.modifier_apply(modifier=sphere.modifiers[-1].name)
    bpy.ops.object.shade_smooth()
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.sort_elements(type="RANDOMIZE", elements={"FACE"}, seed=7)
    bpy.ops.object.mode_set(mode="OBJECT")
    sphere.scale = (1.0, -1.5, 0.8)  # mirrored: the corners turn around
    mesh = sphere.data
    assert len(mesh.loops) == 3 * len(mesh.polygons)
    mesh.calc_loop_triangles()
    read = extract.read_triangles(mesh)
    assert read.corners_in_order
    blender_loops = np.array([list(t.loops) for t in mesh.loop_triangles], np.int64)
    np.testing.assert_array_equal(read.loops, blender_loops)
    np.testing.assert_array_equal(read.triangles, [list(t.vertices) for t in mesh.loop_triangles])
    uv = np.array([list(d.uv) for d in mesh.uv_layers.active.data], np.float32)
    np.testing.assert_array_equal(extract.mesh_corner_uv(mesh, read)[mesh.uv_layers.active.name], uv[blender_loops])

    depsgraph = bpy.context.evaluated_depsgraph_get()
    baked = extract.read_mesh(sphere, depsgraph, mesh.uv_layers.active.name, (16, 16), True, [])
    normals = np.array([list(n.vector) for n in mesh.corner_normals], np.float64)
    matrix = np.array(sphere.matrix_world, np.float64)[:3, :3]
    expected = (normals[blender_loops].reshape(-1, 3) @ np.linalg.inv(matrix)).astype(np.float32).reshape(-1, 3, 3)
    np.testing.assert_array_equal(baked.corner_normals, expected[:, [0, 2, 1]])
    np.testing.assert_array_equal(baked.corner_loops, blender_loops[:, [0, 2, 1]])
    np.testing.assert_array_equal(baked.uv_maps[mesh.uv_layers.active.name], uv[blender_loops][:, [0, 2, 1]])

    bpy.ops.mesh.primitive_plane_add()
    quad = bpy.context.active_object.data
    quad.calc_loop_triangles()
    general = extract.read_triangles(quad)
    assert not general.corners_in_order
    np.testing.assert_array_equal(general.loops, [list(t.loops) for t in quad.loop_triangles])
