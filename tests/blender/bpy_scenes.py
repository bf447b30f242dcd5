"""Test scenes built with bmesh (no operators, no assets) for the bpy tests."""
import math

import bpy

import bmesh
import numpy as np

from tools.blender_compat import compat


def material(name, color, emission=(0.0, 0.0, 0.0), strength=0.0):
    mat = bpy.data.materials.new(name)
    bsdf = compat.ensure_node_tree(mat).nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    # No specular layer: Principled's diffuse lobe is then exactly Lambert, which is
    # what VisiBake models (the layer would take a few percent from the diffuse).
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bsdf.inputs["Emission Color"].default_value = (*emission, 1.0)
    bsdf.inputs["Emission Strength"].default_value = strength
    return mat


def mesh_object(name, build, mat=None, location=(0.0, 0.0, 0.0), uv_map="UVMap", flip=False):
    """An object whose mesh ``build(bm, uv_layer)`` fills; optionally facing inwards."""
    bm = bmesh.new()
    uv_layer = bm.loops.layers.uv.new(uv_map) if uv_map else None
    build(bm, uv_layer)
    if flip:
        bmesh.ops.reverse_faces(bm, faces=bm.faces)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    if mat is not None:
        mesh.materials.append(mat)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def grid(size, segments=1):
    return lambda bm, uv: bmesh.ops.create_grid(bm, x_segments=segments, y_segments=segments, size=size,
                                                 calc_uvs=uv is not None)


def cube(size):
    return lambda bm, uv: bmesh.ops.create_cube(bm, size=size, calc_uvs=uv is not None)


def open_box(size):
    """A cube without its top face."""
    def build(bm, uv):
        bmesh.ops.create_cube(bm, size=size, calc_uvs=uv is not None)
        top = [f for f in bm.faces if f.normal.z > 0.9]
        bmesh.ops.delete(bm, geom=top, context="FACES_ONLY")
    return build


def uv_sphere(radius, segments=32, rings=16):
    return lambda bm, uv: bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=rings, radius=radius,
                                                     calc_uvs=uv is not None)


def sun(strength, tilt_degrees=0.0, name="Sun"):
    light = bpy.data.lights.new(name, "SUN")
    light.energy = strength
    light.angle = 0.0
    obj = bpy.data.objects.new(name, light)
    obj.rotation_euler = (math.radians(tilt_degrees), 0.0, 0.0)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def point(power, location, name="Point"):
    light = bpy.data.lights.new(name, "POINT")
    light.energy = power
    light.shadow_soft_size = 0.0
    obj = bpy.data.objects.new(name, light)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    return obj


def black_world():
    world = bpy.data.worlds.new("Black")
    compat.ensure_node_tree(world)
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    bpy.context.scene.world = world


def image_pixels(name):
    image = bpy.data.images[name]
    width, height = image.size
    pixels = np.empty(width * height * 4, np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(height, width, 4)


def assert_same_light(actual, expected, err_msg=""):
    """The same light up to float32 rounding: a bake whose preparation is kept for relights
    adds each lamp's transported light, scaled by its power, where one that is not
    transports the lamps' sum (core.pipeline.transport.transport_pending); the two orders
    of the same sums differ in the last bits only (a few float32 ulps). Any difference of
    settings, samples or light is orders of magnitude above this bound.
    """
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    assert np.isfinite(actual).all() and np.isfinite(expected).all(), err_msg
    scale = float(np.abs(expected).max()) if expected.size else 0.0
    np.testing.assert_allclose(actual, expected, rtol=1e-6, atol=1e-6 * scale, err_msg=err_msg)


def bake_uv_map(obj):
    """The UV map VisiBake baked ``obj`` on: its own map if it made one, else the render map."""
    layers = obj.data.uv_layers
    if "VisiBake" in layers:
        return "VisiBake"
    return next(layer.name for layer in layers if layer.active_render)


def relative_rmse(ours, reference, mask):
    difference = ours[mask][:, :3] - reference[mask][:, :3]
    return float(np.sqrt(np.mean(difference ** 2)) / np.mean(reference[mask][:, :3]))


def select_only(objects):
    for obj in bpy.context.scene.objects:
        obj.select_set(obj in objects)


def spot(power, location, rotation, size_degrees, blend, name="Spot"):
    light = bpy.data.lights.new(name, "SPOT")
    light.energy = power
    light.shadow_soft_size = 0.0
    light.spot_size = math.radians(size_degrees)
    light.spot_blend = blend
    obj = bpy.data.objects.new(name, light)
    obj.location = location
    obj.rotation_euler = [math.radians(a) for a in rotation]
    bpy.context.scene.collection.objects.link(obj)
    return obj


def area(power, location, rotation, shape, size, size_y=None, scale=(1.0, 1.0, 1.0), name="Area"):
    light = bpy.data.lights.new(name, "AREA")
    light.energy = power
    light.shape = shape
    light.size = size
    if size_y is not None:
        light.size_y = size_y
    obj = bpy.data.objects.new(name, light)
    obj.location = location
    obj.rotation_euler = [math.radians(a) for a in rotation]
    obj.scale = scale
    bpy.context.scene.collection.objects.link(obj)
    return obj


def ground_block_lamp():
    """The panel tests' small scene: a white ground, a red block without a UV map (so it
    is unwrapped) and a point lamp, both meshes selected, at 16 directions, 32 texels and
    1 bounce. Returns (ground, block)."""
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Red", (0.7, 0.2, 0.1)), location=(0, 0, 0.4), uv_map=None)
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 32, 1
    select_only([ground, block])
    return ground, block


def small_bake_settings(mode="vertex", passes=("lighting",), bounces=0):
    """scene.visibake for a quick bake of the selected objects: 32 directions, 32², no cache."""
    props = bpy.context.scene.visibake
    props.mode, props.directions, props.bounces, props.resolution = mode, 32, bounces, 32
    props.passes = set(passes)
    props.bake_all = False
    props.use_cache = False
    return props


def color_attribute(obj, name="VB_lighting"):
    """(domain, (n, 4) float32 values) of the colour attribute ``name`` on ``obj``'s mesh."""
    attribute = obj.data.color_attributes[name]
    values = np.empty(len(attribute.data) * 4, np.float32)
    attribute.data.foreach_get("color", values)
    return attribute.domain, values.reshape(-1, 4)


def scene_report():
    """The report the last operator bake stored on the scene, as a dict."""
    import json

    return json.loads(bpy.context.scene["visibake_report"])


def bake_both(objects, directions, resolution, samples, bounces=1):
    """Bake ``objects`` with VisiBake's operator (exact shadows, rotated directions, the lighting
    pass on each object's UVMap) and with Cycles at ``samples``; returns Cycles' images by object."""
    from tools.cycles_bake import bake_diffuse

    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.shadows, props.resolution = directions, bounces, "exact", resolution
    props.passes = {"lighting"}
    props.bake_all = False
    props.rotate = True  # ray effects of a fixed set become noise, as Cycles' are
    select_only(objects)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return bake_diffuse(objects, "UVMap", resolution, resolution, bounces=bounces, samples=samples)
