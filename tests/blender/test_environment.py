"""Equirectangular world light against Cycles' DIFFUSE bake (DIRECT+INDIRECT+COLOR).

The environment is a procedural float image that is not symmetric in any axis (a sky
gradient, a dim ground and a warm patch at one azimuth above the horizon), so a
flipped u, v or a wrong Mapping rotation would light the wrong side of the sphere
and move the cube's shadow. Each test prints the errors it measured (``-s``).
"""
import importlib
import math

import bpy

import numpy as np

from bpy_scenes import bake_both, cube, grid, image_pixels, material, mesh_object, relative_rmse, uv_sphere
from tools.blender_compat import compat

WIDTH, HEIGHT = 128, 64
RESOLUTION = 48
DIRECTIONS = 512
SAMPLES = 128


def extract_module():
    from blender_support import extension_module_name
    return importlib.import_module(extension_module_name() + ".operators.adapter.extract")


def euler_matrix(degrees):
    """Rz @ Ry @ Rx, written out independently of the code under test."""
    x, y, z = (math.radians(a) for a in degrees)
    rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _sky_pixels():
    """(HEIGHT, WIDTH, 4) float32, row 0 at the bottom, as Blender stores pixels."""
    v = (np.arange(HEIGHT) + 0.5) / HEIGHT
    image = np.ones((HEIGHT, WIDTH, 4), np.float32)
    sky = (0.3 + 0.9 * np.clip(v - 0.5, 0, None) * 2)[:, None] * np.array([0.45, 0.65, 1.0])
    ground = np.array([0.12, 0.09, 0.06])
    image[..., :3] = np.where((v >= 0.5)[:, None, None], sky[:, None, :], ground)
    # Warm patch centred at u = 0.17 (azimuth phi = pi - 2 pi u = 119 degrees: -X, +Y
    # side), elevation ~31 degrees; ~22 x 17 degrees, several cells at N = 512.
    image[38:44, 18:26, :3] = (12.0, 7.0, 3.0)
    return image


def _environment_world(mapping_rotation=None):
    image = bpy.data.images.new("Sky", WIDTH, HEIGHT, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(_sky_pixels().ravel())
    world = bpy.data.worlds.new("Sky")
    tree = compat.ensure_node_tree(world)
    background = tree.nodes["Background"]
    background.inputs["Strength"].default_value = 1.5
    texture = tree.nodes.new("ShaderNodeTexEnvironment")
    texture.image = image
    tree.links.new(texture.outputs["Color"], background.inputs["Color"])
    if mapping_rotation is not None:
        coordinates = tree.nodes.new("ShaderNodeTexCoord")
        mapping = tree.nodes.new("ShaderNodeMapping")
        mapping.vector_type = "POINT"
        mapping.inputs["Rotation"].default_value = [math.radians(a) for a in mapping_rotation]
        tree.links.new(coordinates.outputs["Generated"], mapping.inputs["Vector"])
        tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
    bpy.context.scene.world = world
    return world


def _scene():
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0.0, 0.0, 0.25), uv_map=None)
    ball = mesh_object("Ball", uv_sphere(0.3, 24, 12), material("Ball", (0.7, 0.7, 0.7)), location=(0.0, 0.0, 1.2))
    return [ground, ball]


def _bake_and_compare(objects, label):
    references = bake_both(objects, DIRECTIONS, RESOLUTION, SAMPLES)
    errors = {}
    for obj in objects:
        ours = image_pixels(f"VB_{obj.name}_lighting")
        reference = references[obj.name]
        assert np.isfinite(ours).all()
        covered = (ours[..., 3] > 0) & (reference[..., 3] > 0)
        assert covered.sum() > 0.3 * covered.size
        error = relative_rmse(ours, reference, covered)
        bias = float(np.mean(ours[covered][:, :3]) / np.mean(reference[covered][:, :3]) - 1)
        print(f"\n{label} {obj.name}: N={DIRECTIONS}, Cycles {SAMPLES} spp, {RESOLUTION}^2: "
              f"relative RMSE {error:.4f}, bias {bias:+.4f}")
        errors[obj.name] = (error, bias, ours, reference, covered)
    return errors


# Thresholds, for both tests. Cycles' own per-texel noise at 128 spp with one bounce,
# measured as the RMSE between seeds 0 and 1 over sqrt(2): 1.4% (ground), 2.4% (ball).
# VisiBake's error with N = 512 cell means on top of it is ~1% (measured totals
# 1.6% and 2.5%): the patch (~22 x 17 degrees, ~8 cells of 0.0245 sr) gives the
# cube's penumbra in steps where Cycles' is smooth. 5% bounds both with room for
# another Cycles build's noise; a flipped axis or a wrong rotation moves half the
# light to the other side of the ball and the shadow across the cube (30% and more,
# checked in each test). The mean is exact up to the cells' area deviation summed
# over the ~40 cells the patch touches (measured bias <= 0.13%) and Cycles' mean
# noise (~0.03%): 2% leaves room for a different Cycles build, not for a lost factor.
MAX_RMSE = 0.05
MAX_BIAS = 0.02


def test_equirect_world_matches_cycles(clean_scene):
    _environment_world()
    objects = _scene()
    errors = _bake_and_compare(objects, "equirect world")
    for name, (error, bias, ours, reference, covered) in errors.items():
        assert error < MAX_RMSE, name
        assert abs(bias) < MAX_BIAS, name
    # The comparison can tell orientation apart: the ball's lighting mirrored in u
    # (the warm side moved to the other hemisphere, as a flipped u would) is far from Cycles.
    _, _, ours, reference, covered = errors["Ball"]
    mirrored = relative_rmse(ours[:, ::-1], reference, covered & covered[:, ::-1])
    print(f"ball mirrored in u against Cycles: relative RMSE {mirrored:.4f}")
    assert mirrored > 3 * MAX_RMSE


def test_mapping_rotated_world_matches_cycles(clean_scene):
    # A Mapping node (POINT, Euler XYZ 20, -35, 110 degrees) fed by Generated
    # coordinates: Cycles looks up R d with R = Rz Ry Rx, which World.rotation holds.
    _environment_world(mapping_rotation=(20.0, -35.0, 110.0))
    objects = _scene()
    errors = _bake_and_compare(objects, "rotated world")
    for name, (error, bias, _, _, _) in errors.items():
        assert error < MAX_RMSE, name
        assert abs(bias) < MAX_BIAS, name
    # Extraction represents the rotation exactly, without a warning.
    warnings = []
    world = extract_module().read_world(bpy.context.scene, warnings)
    assert warnings == []
    np.testing.assert_allclose(world.rotation, euler_matrix((20.0, -35.0, 110.0)), atol=1e-6)
    # The comparison can tell the rotation and its direction apart: the same Euler
    # angles as TEXTURE mapping (Cycles then applies the inverse, R^T) and no rotation
    # at all are both far from Cycles' rotated bake.
    mapping = bpy.context.scene.world.node_tree.nodes["Mapping"]
    _, _, _, reference, covered = errors["Ball"]
    for vector_type, rotation in (("TEXTURE", (20.0, -35.0, 110.0)), ("POINT", (0.0, 0.0, 0.0))):
        mapping.vector_type = vector_type
        mapping.inputs["Rotation"].default_value = [math.radians(a) for a in rotation]
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        wrong = relative_rmse(image_pixels("VB_Ball_lighting"), reference, covered)
        print(f"ball with {vector_type} mapping {rotation} against Cycles' rotated bake: relative RMSE {wrong:.4f}")
        assert wrong > 3 * MAX_RMSE


def test_read_world_nodes_and_fallbacks(clean_scene):
    """What the node reading makes of the set-ups it supports, and of those it does not.

    read_world renders every set-up this reading approximates through Cycles instead
    (tests/blender/test_scene_world.py); the reading stays its fallback."""
    extract = extract_module()
    world = _environment_world()
    tree = world.node_tree
    background = tree.nodes["Background"]
    texture = tree.nodes["Environment Texture"]
    sky = _sky_pixels()[..., :3]

    def read():
        warnings = []
        result = extract._read_world_nodes(bpy.context.scene.world, warnings)
        assert result.image is None or np.isfinite(result.image).all()
        assert np.isfinite(result.color).all() and np.isfinite(result.rotation).all()
        return result, warnings

    result, warnings = read()
    assert warnings == []
    np.testing.assert_allclose(result.image, sky * 1.5, rtol=1e-6)
    np.testing.assert_array_equal(result.rotation, np.eye(3))

    # Through a reroute node, as Cycles follows it.
    reroute = tree.nodes.new("NodeReroute")
    tree.links.new(texture.outputs["Color"], reroute.inputs[0])
    tree.links.new(reroute.outputs[0], background.inputs["Color"])
    result, warnings = read()
    assert warnings == [] and result.image is not None

    # A byte image in sRGB is linearised; one in a colour space we cannot convert warns.
    byte = bpy.data.images.new("Byte", 8, 4, alpha=True, float_buffer=False)
    byte.pixels.foreach_set(np.tile([0.5, 0.25, 0.1, 1.0], 32).astype(np.float32))
    texture.image = byte
    result, warnings = read()
    assert warnings == []
    # 8-bit 0.5 is 128/255, linear 0.2158; Cycles baked 0.2154 (16 spp).
    np.testing.assert_allclose(result.image[0, 0], 1.5 * np.array([0.2158, 0.0513, 0.0103]), rtol=5e-3)
    byte.colorspace_settings.name = "ACEScg"
    result, warnings = read()
    assert any("ACEScg" in w for w in warnings)

    # Strength from a node: its value is used, with a warning.
    texture.image = bpy.data.images["Sky"]
    value = tree.nodes.new("ShaderNodeValue")
    link = tree.links.new(value.outputs[0], background.inputs["Strength"])
    result, warnings = read()
    assert any("strength" in w for w in warnings)
    np.testing.assert_allclose(result.image, sky * 1.5, rtol=1e-6)
    tree.links.remove(link)

    # Mirror ball: a uniform world with the image's mean radiance over the sphere.
    texture.projection = "MIRROR_BALL"
    result, warnings = read()
    assert result.image is None and any("mirror ball" in w for w in warnings)
    assert np.all(result.color > 0)
    texture.projection = "EQUIRECTANGULAR"

    # Mapping: TEXTURE applies the inverse rotation, a negative uniform scale mirrors,
    # location and non-uniform scale are ignored with a warning.
    coordinates = tree.nodes.new("ShaderNodeTexCoord")
    mapping = tree.nodes.new("ShaderNodeMapping")
    tree.links.new(coordinates.outputs["Object"], mapping.inputs["Vector"])
    tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
    angles = (10.0, 50.0, -30.0)
    mapping.inputs["Rotation"].default_value = [math.radians(a) for a in angles]
    mapping.vector_type = "TEXTURE"
    result, warnings = read()
    assert warnings == []
    np.testing.assert_allclose(result.rotation, euler_matrix(angles).T, atol=1e-6)
    mapping.vector_type = "VECTOR"
    mapping.inputs["Scale"].default_value = (-2.0, -2.0, -2.0)
    result, warnings = read()
    assert warnings == []
    np.testing.assert_allclose(result.rotation, -euler_matrix(angles), atol=1e-6)
    mapping.vector_type = "POINT"
    mapping.inputs["Scale"].default_value = (1.0, 2.0, 1.0)
    mapping.inputs["Location"].default_value = (0.0, 0.0, 3.0)
    result, warnings = read()
    assert any("location" in w for w in warnings) and any("scale" in w for w in warnings)
    np.testing.assert_allclose(result.rotation, euler_matrix(angles), atol=1e-6)

    # Nothing linked to the Mapping's vector: one constant texel, as Cycles shows it
    # (here the direction of the location (0, 0, 3): the zenith, u = 0.5, v = 1).
    tree.links.remove(mapping.inputs["Vector"].links[0])
    result, warnings = read()
    assert result.image is None and any("constant" in w for w in warnings)
    # v = 1 wraps to the bottom row: the four texels around (u, v) = (0.5, 1) are mixed equally.
    top = sky[[-1, -1, 0, 0], [WIDTH // 2 - 1, WIDTH // 2] * 2].mean(axis=0)
    np.testing.assert_allclose(result.color, 1.5 * top, rtol=1e-5)

    # No image: black, with a warning (Cycles would show magenta).
    texture.image = None
    result, warnings = read()
    assert result.image is None and np.all(result.color == 0) and warnings

    # Another colour source: its default colour, with a warning.
    noise = tree.nodes.new("ShaderNodeTexNoise")
    tree.links.new(noise.outputs["Color"], reroute.inputs[0])
    background.inputs["Color"].default_value = (0.2, 0.3, 0.4, 1.0)
    result, warnings = read()
    assert any("ShaderNodeTexNoise" in w for w in warnings)
    np.testing.assert_allclose(result.color, np.array([0.2, 0.3, 0.4]) * 1.5, rtol=1e-6)

    # The uniform colour path is unchanged.
    tree.links.remove(background.inputs["Color"].links[0])
    result, warnings = read()
    assert warnings == [] and result.image is None
    np.testing.assert_allclose(result.color, np.array([0.2, 0.3, 0.4]) * 1.5, rtol=1e-6)
