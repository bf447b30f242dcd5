"""The Cycles reference bake (tools/cycles_bake.py) and the demo scene, in real bpy.

The light-unit tests pin down the formulas VisiBake relies on (see DESIGN.md, "Units
and conventions"); each tolerance is derived next to its assertion.
"""
import importlib
import importlib.util
import math
import sys
from pathlib import Path

import bpy

import bmesh  # importable only once bpy is
import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from bpy_scenes import black_world, cube, grid, material, mesh_object, point, sun  # noqa: E402
from tools.blender_compat import compat  # noqa: E402
from tools.cycles_bake import bake_diffuse, bake_diffuse_vertex_colors  # noqa: E402


def _demo_scene(visibake):
    """The installed extension's demo scene builder (the module the demo bakes)."""
    return importlib.import_module(f"{visibake.__name__}.operators.adapter.demo_scene")


def _lambert_material(name, rho):
    mat = bpy.data.materials.new(name)
    bsdf = compat.ensure_node_tree(mat).nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (rho, rho, rho, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    # The default specular layer would take ~1.4% off the diffuse weight.
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    return mat


def _plane(name, size, mat=None, location=(0.0, 0.0, 0.0), extra_uv=None):
    """A size x size quad facing +z with "UVMap" = [0, 1]^2 (u along +x, v along +y)."""
    bm = bmesh.new()
    bm.loops.layers.uv.new("UVMap")
    bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=size / 2.0, calc_uvs=True)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if extra_uv:
        mesh.uv_layers.new(name=extra_uv)
        mesh.uv_layers.active = mesh.uv_layers[extra_uv]
    if mat is not None:
        mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _light(kind, name, energy, location=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0), **props):
    light = bpy.data.lights.new(name, kind)
    light.energy = energy
    for key, value in props.items():
        setattr(light, key, value)
    obj = bpy.data.objects.new(name, light)
    obj.location = location
    obj.rotation_euler = rotation
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _texel_centres(resolution, size):
    """World x, y of texel centres in Blender pixel order (row 0 = v 0 = -y edge)."""
    c = ((np.arange(resolution) + 0.5) / resolution - 0.5) * size
    x, y = np.meshgrid(c, c)  # rows follow y
    return x, y


@pytest.mark.parametrize("theta_degrees", [0.0, 60.0])
def test_sun_on_plane_is_rho_s_cos_over_pi(clean_scene, theta_degrees):
    rho, strength = 0.7, 3.0
    plane = _plane("Plane", 1.0, _lambert_material("Lambert", rho))
    _light("SUN", "Sun", strength, rotation=(math.radians(theta_degrees), 0.0, 0.0), angle=0.0)
    result = bake_diffuse([plane], "UVMap", 32, 32, bounces=0, samples=4)["Plane"]
    assert result.shape == (32, 32, 4) and result.dtype == np.float32
    expected = rho * strength * math.cos(math.radians(theta_degrees)) / math.pi
    # A zero-angle sun on a flat open plane gives every sample the same value, so
    # there is no Monte Carlo noise at all: only float32 rounding remains.
    np.testing.assert_allclose(result[..., :3], expected, rtol=1e-5)
    np.testing.assert_array_equal(result[..., 3], 1.0)


def test_point_light_is_p_cos_over_4_pi_d2(clean_scene):
    rho, power, height, size, res = 0.5, 1000.0, 2.0, 4.0, 32
    plane = _plane("Plane", size, _lambert_material("Lambert", rho))
    # Off the plane's centre in x and y, so a flipped row/column order would fail.
    light_xy = (0.5, 1.0)
    _light("POINT", "Point", power, location=(*light_xy, height), shadow_soft_size=0.0)
    result = bake_diffuse([plane], "UVMap", res, res, bounces=0, samples=16)["Plane"][..., 0]

    x, y = _texel_centres(res, size)
    dist2 = (x - light_xy[0]) ** 2 + (y - light_xy[1]) ** 2 + height**2
    cos = height / np.sqrt(dist2)
    expected = rho / math.pi * power * cos / (4.0 * math.pi * dist2)
    ratio = result / expected
    # No light sampling noise (radius 0, direct only). What remains is Cycles' jitter
    # over half a texel (0.0625 m here): E changes by at most ~3% across it where the
    # gradient is steepest, so 16 samples leave <1% noise and the curvature bias is
    # ~0.1%. Texels on the quad's diagonal only sample one triangle's half of the box:
    # up to ~1.5% off. Hence 3% everywhere, 0.5% for the median.
    centre = np.unravel_index(np.argmax(expected), expected.shape)
    print(f"\npoint light: centre texel ratio {ratio[centre]:.4f}, corner {ratio[0, 0]:.4f}, "
          f"median {np.median(ratio):.4f}, min {ratio.min():.4f}, max {ratio.max():.4f}")
    assert abs(np.median(ratio) - 1.0) < 0.005
    assert np.all(np.abs(ratio - 1.0) < 0.03)
    # The brightest texel is under the light, a corner texel sees it at a grazing angle.
    assert abs(ratio[centre] - 1.0) < 0.03 and abs(ratio[0, 0] - 1.0) < 0.03


def _box_lit_share(resolution, size, normal, offset, box_width, grid=64):
    """(resolution, resolution) share of each texel's box (``box_width`` texels wide, around
    its centre) on the lit side n . p > offset of a straight shadow edge, by a fine grid."""
    x, y = _texel_centres(resolution, size)
    steps = ((np.arange(grid) + 0.5) / grid - 0.5) * box_width * size / resolution
    gx, gy = np.meshgrid(steps, steps)
    along = (x[..., None] + gx.ravel()) * normal[0] + (y[..., None] + gy.ravel()) * normal[1]
    return (along > offset).mean(axis=-1)


def test_the_bake_averages_each_texel_over_the_box_this_blender_s_cycles_uses(clean_scene):
    # A sharp sun shadow edge, slanted 17 degrees, over a 2 m plane at 32^2: each texel is the
    # lit share of its box, and the box's width decides the share wherever the edge crosses.
    # Measured (256 samples, RMS over those texels): Blender 4.2.23-5.2.0 fit 0.5 texel
    # (Blender's bake differentials carried a factor 1/2), 5.2.1-5.3.0 the whole texel; the
    # other width is 4-10x further. VisiBake averages over the width compat names.
    size, resolution, rho = 2.0, 32, 0.5
    plane = _plane("Plane", size, _lambert_material("Lambert", rho))
    normal, offset = np.array([np.cos(0.3), np.sin(0.3)]), 0.05
    along, far = np.array([-normal[1], normal[0]]), 6.0
    a, b = offset * normal - far * along, offset * normal + far * along
    corners = [(*a, 0.5), (*(a - far * normal), 0.5), (*(b - far * normal), 0.5), (*b, 0.5)]
    blocker_mesh = bpy.data.meshes.new("Blocker")
    blocker_mesh.from_pydata(corners, [], [(0, 1, 2, 3)])
    blocker = bpy.data.objects.new("Blocker", blocker_mesh)
    bpy.context.scene.collection.objects.link(blocker)
    _light("SUN", "Sun", math.pi, angle=0.0)
    baked = bake_diffuse([plane], "UVMap", resolution, resolution, bounces=0, samples=256)["Plane"][..., 0] / rho
    errors = {}
    for width in (0.5, 1.0):
        share = _box_lit_share(resolution, size, normal, offset, width)
        crossed = (share > 0) & (share < 1)
        errors[width] = float(np.sqrt(np.mean((baked[crossed] - share[crossed]) ** 2)))
    print(f"\nbox 0.5: RMS {errors[0.5]:.4f}, box 1.0: RMS {errors[1.0]:.4f}")
    chosen = compat.CYCLES_BAKE_FOOTPRINT_WIDTH
    other = 1.5 - chosen
    assert errors[chosen] < 0.3 * errors[other], errors


def _rna_values(struct):
    values = {}
    for prop in struct.bl_rna.properties:
        if prop.identifier == "rna_type" or prop.type in {"POINTER", "COLLECTION"}:
            continue
        value = getattr(struct, prop.identifier)
        values[prop.identifier] = tuple(value) if hasattr(value, "__len__") and not isinstance(value, str) \
            else value
    return values


def _scene_state():
    scene = bpy.context.scene
    state = {
        "data": {name: sorted(item.name for item in getattr(bpy.data, name))
                 for name in ("images", "materials", "meshes", "objects", "node_groups", "textures")},
        "render": _rna_values(scene.render),
        "bake": _rna_values(scene.render.bake),
        "cycles": _rna_values(scene.cycles),
        "view": _rna_values(scene.view_settings),
        "selected": sorted(o.name for o in scene.objects if o.select_get()),
        "active": bpy.context.view_layer.objects.active,
    }
    for mat in bpy.data.materials:
        nodes = mat.node_tree.nodes
        state["nodes", mat.name] = (sorted(n.name for n in nodes), nodes.active and nodes.active.name)
    for obj in scene.objects:
        if obj.type == "MESH":
            state["slots", obj.name] = [s.material and s.material.name for s in obj.material_slots]
            state["uv", obj.name] = obj.data.uv_layers.active.name if obj.data.uv_layers.active else None
    return state


def test_bake_leaves_the_scene_unchanged(clean_scene):
    shared = _lambert_material("Shared", 0.5)
    a = _plane("A", 1.0, shared, extra_uv="Other")
    b = _plane("B", 1.0, shared, location=(2.0, 0.0, 0.0), extra_uv="Other")  # same material as A
    c = _plane("C", 1.0, None, location=(4.0, 0.0, 0.0))  # no material
    _light("SUN", "Sun", math.pi, angle=0.0)
    a.select_set(True)
    bpy.context.view_layer.objects.active = b
    before = _scene_state()
    assert before["render"]["engine"] != "CYCLES"  # so a forgotten restore would show

    result = bake_diffuse([a, b, c], "UVMap", 8, 8, bounces=1, samples=2)

    assert _scene_state() == before
    assert set(result) == {"A", "B", "C"}
    # A and B share a material, so they are baked in separate calls into separate images.
    np.testing.assert_allclose(result["A"][..., 0], 0.5, rtol=1e-5)
    np.testing.assert_allclose(result["B"][..., 0], 0.5, rtol=1e-5)
    # No material: a 0.8 grey Lambert, like Cycles' default surface.
    np.testing.assert_allclose(result["C"][..., 0], 0.8, rtol=1e-5)


def test_uncovered_texels_stay_clear_without_margin(clean_scene):
    plane = _plane("Plane", 1.0, _lambert_material("Lambert", 0.5))
    for loop_uv in plane.data.uv_layers["UVMap"].data:
        loop_uv.uv = loop_uv.uv * 0.5  # the quad covers the lower-left quarter
    _light("SUN", "Sun", math.pi, angle=0.0)
    result = bake_diffuse([plane], "UVMap", 8, 8, bounces=0, samples=1)["Plane"]
    np.testing.assert_allclose(result[:4, :4], np.broadcast_to([0.5, 0.5, 0.5, 1.0], (4, 4, 4)), rtol=1e-5)
    assert not result[4:].any() and not result[:, 4:].any()
    extended = bake_diffuse([plane], "UVMap", 8, 8, bounces=0, samples=1, margin=2)["Plane"]
    np.testing.assert_allclose(extended[:6, :4, 0], 0.5, rtol=1e-5)
    assert not extended[7].any()


DEMO_MESHES = {"Floor", "Ceiling", "WallRed", "WallGreen", "WallBack", "WallFront",
               "Pedestal", "Suzanne", "Torus", "Dome", "GlowBall"}


def test_demo_scene_contents(visibake, clean_scene, tmp_path):
    demo = _demo_scene(visibake)
    scene = bpy.context.scene
    meshes = demo.build_demo_scene(scene)

    assert {obj.name for obj in meshes} == DEMO_MESHES
    assert all(obj.type == "MESH" and scene.objects.get(obj.name) is obj for obj in meshes)
    sun, point = scene.objects["Sun"].data, scene.objects["PointLight"].data
    assert sun.type == "SUN" and sun.angle == 0.0 and 3.0 <= sun.energy <= 5.0
    assert point.type == "POINT" and point.shadow_soft_size == 0.0 and 100.0 <= point.energy <= 1000.0
    assert scene.camera is scene.objects["Camera"]

    depsgraph = bpy.context.evaluated_depsgraph_get()
    triangles = 0
    for obj in meshes:
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        mesh.calc_loop_triangles()
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        assert np.isfinite(co).all(), obj.name
        triangles += len(mesh.loop_triangles)
        evaluated.to_mesh_clear()
        if obj.name == "Pedestal":
            assert obj.data.uv_layers.keys() == ["UVMap"]
            uv = np.empty(len(obj.data.loops) * 2, np.float32)
            obj.data.uv_layers["UVMap"].uv.foreach_get("vector", uv)
            assert uv.min() >= 0.0 and uv.max() <= 1.0
        else:
            assert len(obj.data.uv_layers) == 0, obj.name
        for slot in obj.material_slots:
            color = slot.material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value
            assert max(color[:3]) <= 0.8 + 1e-6  # stored as float32
    assert 0 < triangles < 20000
    # The modifier matters: evaluated Suzanne has ~4x the triangles of its base mesh.
    assert scene.objects["Suzanne"].modifiers["Subdivision"].type == "SUBSURF"
    # The dome is the demo's vertex-mode object (results as a colour attribute).
    assert scene.objects["Dome"].visibake.mode == "vertex"

    world = scene.world
    background = world.node_tree.nodes["Background"]
    assert tuple(background.inputs["Color"].default_value)[:3] == (0.0, 0.0, 0.0) \
        or background.inputs["Strength"].default_value == 0.0

    # The checker is packed and keeps its pixels through save and load.
    image = bpy.data.images["Checker"]
    pixels = np.empty(len(image.pixels), np.float32)
    image.pixels.foreach_get(pixels)
    path = str(tmp_path / "demo.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    reloaded = bpy.data.images["Checker"]
    assert reloaded.packed_file is not None
    again = np.empty(len(reloaded.pixels), np.float32)
    reloaded.pixels.foreach_get(again)
    np.testing.assert_array_equal(again, pixels)


def test_demo_checker_albedo_reaches_cycles(visibake, clean_scene):
    _demo_scene(visibake).build_demo_scene(bpy.context.scene)
    pedestal = bpy.data.objects["Pedestal"]
    albedo = bake_diffuse([pedestal], "UVMap", 48, 48, bounces=0, samples=1, pass_filter=("COLOR",))["Pedestal"]
    rgb = albedo[albedo[..., 3] > 0][:, :3]
    # Cycles decodes the sRGB bytes back to the linear albedos the demo chose (8-bit
    # rounding: < 0.005); texels on a checker edge get bilinear blends of the two.
    light = np.all(np.abs(rgb - [0.8, 0.8, 0.8]) < 0.005, axis=1)
    dark = np.all(np.abs(rgb - [0.1, 0.2, 0.6]) < 0.005, axis=1)
    assert light.mean() > 0.2 and dark.mean() > 0.2 and (light | dark).mean() > 0.5


# --- bake_diffuse_vertex_colors ---------------------------------------------------------

def _loop_vertices(mesh):
    vertices = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", vertices)
    return vertices


def _world_vertices(obj):
    co = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", co)
    matrix = np.array(obj.matrix_world)
    return co.reshape(-1, 3).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


@pytest.mark.parametrize("domain", ["POINT", "CORNER"])
@pytest.mark.parametrize("theta_degrees", [0.0, 60.0])
def test_vertex_colors_sun_on_grid_is_rho_s_cos_over_pi(clean_scene, domain, theta_degrees):
    black_world()
    rho, strength = 0.6, 2.0
    plane = mesh_object("Grid", grid(1.0, 8), material("Lambert", (rho, rho, rho)))
    sun(strength, theta_degrees)
    result = bake_diffuse_vertex_colors([plane], bounces=0, samples=4, domain=domain)["Grid"]
    mesh = plane.data
    count = len(mesh.vertices) if domain == "POINT" else len(mesh.loops)
    assert count == (81 if domain == "POINT" else 256)
    assert result.shape == (count, 4) and result.dtype == np.float32
    expected = rho * strength * math.cos(math.radians(theta_degrees)) / math.pi
    # Zero-angle sun on an open plane: deterministic, only float32 rounding remains.
    np.testing.assert_allclose(result[:, :3], expected, rtol=1e-5)
    np.testing.assert_array_equal(result[:, 3], 1.0)


def test_vertex_colors_sample_the_vertex_itself(clean_scene):
    """No jitter: the value is rho E / pi at the vertex (moved 1e-4 m into its triangle)."""
    black_world()
    rho, power, height = 0.5, 100.0, 0.3
    plane = mesh_object("Grid", grid(1.0, 4), material("Lambert", (rho, rho, rho)))
    light = np.array([0.5, 0.5, height])  # right above the vertex at (0.5, 0.5)
    point(power, tuple(light))
    bpy.context.view_layer.update()
    d = light - _world_vertices(plane)
    dist2 = (d ** 2).sum(axis=1)
    expected = rho / math.pi * power * (d[:, 2] / np.sqrt(dist2)) / (4.0 * math.pi * dist2)

    one = bake_diffuse_vertex_colors([plane], bounces=0, samples=1)["Grid"][:, 0]
    many = bake_diffuse_vertex_colors([plane], bounces=0, samples=16)["Grid"][:, 0]
    corners = bake_diffuse_vertex_colors([plane], bounces=0, samples=1, domain="CORNER")["Grid"][:, 0]
    # Zero differentials: every sample is taken at the same point (measured: equal to 1e-7).
    np.testing.assert_allclose(many, one, rtol=1e-6)
    below = int(np.argmax(expected))
    print(f"\nvertex bake: ratio below the light {one[below] / expected[below]:.7f}, "
          f"range {np.min(one / expected):.5f}-{np.max(one / expected):.5f}")
    # Cycles' 1e-4 m nudge towards the triangle centre changes E by at most
    # ~3 * 1e-4 / 0.3 = 0.1% where the gradient is steepest (measured 0.035%); at the
    # vertex right below the light the gradient is zero.
    assert abs(one[below] / expected[below] - 1.0) < 1e-5
    np.testing.assert_allclose(one, expected, rtol=1e-3)
    np.testing.assert_allclose(corners, expected[_loop_vertices(plane.data)], rtol=1e-3)


def test_vertex_colors_point_is_the_mean_of_the_corners(clean_scene):
    """Flat shading: each corner uses its face's normal; POINT averages the corners."""
    black_world()
    rho, strength = 0.5, math.pi
    box = mesh_object("Box", cube(1.0), material("Lambert", (rho, rho, rho)), uv_map=None)
    sun(strength, 30.0)
    bpy.context.view_layer.update()
    to_light = np.array(bpy.data.objects["Sun"].matrix_world)[:3, 2]  # the sun shines along -z
    mesh = box.data
    normals = np.array([face.normal for face in mesh.polygons], np.float64)
    face_value = rho * strength * np.clip(normals @ to_light, 0.0, None) / math.pi
    loop_face = np.repeat(np.arange(len(mesh.polygons)), [face.loop_total for face in mesh.polygons])
    loop_vertex = _loop_vertices(mesh)

    corners = bake_diffuse_vertex_colors([box], bounces=0, samples=1, domain="CORNER")["Box"][:, 0]
    points = bake_diffuse_vertex_colors([box], bounces=0, samples=1, domain="POINT")["Box"][:, 0]
    np.testing.assert_allclose(corners, face_value[loop_face], atol=1e-6)
    mean_of_faces = np.bincount(loop_vertex, face_value[loop_face]) / np.bincount(loop_vertex)
    np.testing.assert_allclose(points, mean_of_faces, atol=1e-6)
    assert len(set(np.round(points, 5))) > 1  # not trivially equal


def _color_state(mesh):
    colors = mesh.color_attributes
    state = {"names": [a.name for a in mesh.attributes], "active": colors.active_color_name,
             "default": colors.default_color_name, "active_index": mesh.attributes.active_index}
    for attr in colors:
        values = np.empty(len(attr.data) * 4, np.float32)
        attr.data.foreach_get("color", values)
        state[attr.name] = (attr.data_type, attr.domain, values.tolist())
    return state


def test_vertex_colors_leave_user_attributes_and_scene_unchanged(clean_scene):
    black_world()
    rho, strength = 0.5, 3.0
    a = mesh_object("A", grid(1.0, 2), material("Lambert", (rho, rho, rho)))
    # B shares A's mesh, upside down: baked in its own call, else one would overwrite the other.
    b = bpy.data.objects.new("B", a.data)
    b.location = (3.0, 0.0, 0.0)
    b.rotation_euler = (math.pi, 0.0, 0.0)
    bpy.context.scene.collection.objects.link(b)
    c = mesh_object("C", grid(1.0, 2), None, location=(-3.0, 0.0, 0.0))  # no material, no colours
    sun(strength)
    mesh = a.data
    rng = np.random.default_rng(1)
    paint = mesh.color_attributes.new("Paint", "BYTE_COLOR", "CORNER")
    paint.data.foreach_set("color", rng.random(len(mesh.loops) * 4).astype(np.float32))
    mesh.color_attributes.new("Mask", "FLOAT_COLOR", "POINT").data.foreach_set(
        "color", rng.random(len(mesh.vertices) * 4).astype(np.float32))
    mesh.color_attributes.new("visibake_ref_color", "FLOAT_COLOR", "POINT")  # our temporary name
    mesh.color_attributes.active_color_name = "Mask"
    mesh.color_attributes.default_color_name = "Paint"
    mesh.attributes.active = mesh.attributes["Paint"]
    a.select_set(True)
    bpy.context.view_layer.objects.active = c
    before = _scene_state(), _color_state(mesh), _color_state(c.data)
    assert before[1]["active"] == "Mask" and before[1]["default"] == "Paint"

    result = bake_diffuse_vertex_colors([a, b, c], bounces=1, samples=2)

    assert (_scene_state(), _color_state(mesh), _color_state(c.data)) == before
    assert c.data.color_attributes.active_color_name == "" and len(c.data.color_attributes) == 0
    assert set(result) == {"A", "B", "C"}
    np.testing.assert_allclose(result["A"][:, :3], rho * strength / math.pi, rtol=1e-5)
    np.testing.assert_array_equal(result["B"][:, :3], 0.0)  # lit from behind
    # No material: Cycles' default surface, a 0.8 grey Lambert.
    np.testing.assert_allclose(result["C"][:, :3], 0.8 * strength / math.pi, rtol=1e-5)


def test_vertex_colors_restore_the_scene_after_a_failed_bake(clean_scene):
    good = mesh_object("Good", grid(1.0, 2), material("Lambert", (0.5, 0.5, 0.5)))
    good.data.color_attributes.new("Paint", "FLOAT_COLOR", "POINT")
    points_only = bpy.data.meshes.new("PointsOnly")
    points_only.from_pydata([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], [], [])
    bad = bpy.data.objects.new("Bad", points_only)
    bpy.context.scene.collection.objects.link(bad)
    sun(1.0)
    before = _scene_state(), _color_state(good.data), _color_state(points_only)
    with pytest.raises(RuntimeError):  # Blender: no faces found in the object
        bake_diffuse_vertex_colors([good, bad], bounces=0, samples=1)
    assert (_scene_state(), _color_state(good.data), _color_state(points_only)) == before
    with pytest.raises(ValueError):
        bake_diffuse_vertex_colors([good], bounces=0, samples=1, domain="FACE")
