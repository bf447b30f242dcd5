"""Stress cases through the operator a user clicks: each one ends in correct numbers
within a stated tolerance, or in a clear refusal. Never NaN/Inf, never a half-changed scene."""
import math

import bpy

import bmesh  # only importable once bpy is
import numpy as np
import pytest

from bpy_scenes import black_world, cube, grid, image_pixels, material, mesh_object, point, select_only, sun
from tools.blender_compat import compat

RHO = 0.8


def _settings(**values):
    props = bpy.context.scene.visibake
    defaults = dict(directions=32, bounces=0, shadows="exact", resolution=32, bake_all=True, passes={"lighting"})
    for key, value in {**defaults, **values}.items():
        setattr(props, key, value)
    return props


def _all_finite():
    for image in bpy.data.images:
        if image.name.startswith("VB_"):
            assert np.isfinite(image_pixels(image.name)).all(), image.name


def _plane(size=1.0, location=(0.0, 0.0, 0.0), segments=1, name="Ground"):
    return mesh_object(name, grid(size, segments), material("White", (RHO, RHO, RHO)), location=location)


# --- analytic cases ---------------------------------------------------------------

@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_open_plane_under_a_sun_is_exact(clean_scene, shadows):
    black_world()
    _plane()
    sun(4.0, tilt_degrees=40.0)
    _settings(shadows=shadows, bounces=2)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    values = image_pixels("VB_Ground_lighting")[..., :3]
    # Nothing occludes or reflects: rho * S * cos / pi at every texel, to float32.
    np.testing.assert_allclose(values, RHO * 4.0 * math.cos(math.radians(40)) / math.pi, rtol=1e-5)


def test_point_light_falls_off_with_the_inverse_square(clean_scene):
    black_world()
    plane = _plane(size=2.0)
    point(500.0, (0.0, 0.0, 1.5))
    _settings(resolution=16, footprint_samples=1)  # the law at texel centres
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    values = image_pixels("VB_Ground_lighting")[..., 0]
    # Texel centres of the plane's [0,1] UV square map to [-2, 2]^2 in x, y.
    centres = (np.arange(16) + 0.5) / 16 * 4.0 - 2.0
    x, y = np.meshgrid(centres, centres)
    d2 = x * x + y * y + 1.5 ** 2
    expected = RHO / math.pi * 500.0 / (4 * math.pi * d2) * (1.5 / np.sqrt(d2))
    assert plane.data.uv_layers.active.name == "UVMap"
    # Texel centres on the quad's diagonal are moved 1e-4 (barycentric) into their
    # triangle (tolerances.SAMPLE_BARYCENTRIC_INSET): up to 0.4 mm on this 4 m plane,
    # 2.3e-4 relative at the steepest texel; every other texel agrees to float32.
    np.testing.assert_allclose(values, expected, rtol=3e-4)


# --- bad geometry -----------------------------------------------------------------

def _bad_mesh(name, build):
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _nan_vertex(bm):
    bmesh.ops.create_cube(bm, size=0.5)
    bm.verts.ensure_lookup_table()
    bm.verts[0].co = (float("nan"), 0.0, 1.0)
    bm.verts[1].co = (float("inf"), 0.0, 1.0)


def _degenerate(bm):
    a = bm.verts.new((0, 0, 1))
    b = bm.verts.new((1, 0, 1))
    c = bm.verts.new((2, 0, 1))  # collinear: zero area
    d = bm.verts.new((0, 0, 1.5))
    bm.faces.new((a, b, c))
    bm.faces.new((a, d, bm.verts.new((0, 0, 1.5))))  # duplicated vertex: zero area


def _non_manifold(bm):
    # Three quads sharing one edge.
    a, b = bm.verts.new((0, 0, 1)), bm.verts.new((1, 0, 1))
    for direction in ((0, 1, 0), (0, -1, 0), (0, 0, 1)):
        c = bm.verts.new((1 + direction[0], direction[1], 1 + direction[2]))
        d = bm.verts.new((direction[0], direction[1], 1 + direction[2]))
        bm.faces.new((a, b, c, d))


def _flipped(bm):
    bmesh.ops.create_cube(bm, size=0.6)
    bmesh.ops.translate(bm, vec=(0.0, 0.0, 1.0), verts=bm.verts)
    bmesh.ops.reverse_faces(bm, faces=bm.faces[:3])


def _no_faces(bm):
    bm.verts.new((0, 0, 1))
    bm.verts.new((1, 0, 1))


@pytest.mark.parametrize("build", [_nan_vertex, _degenerate, _non_manifold, _flipped, _no_faces],
                         ids=["nan-inf-vertex", "degenerate", "non-manifold", "flipped-normals", "no-faces"])
def test_bad_geometry_bakes_finite_results(clean_scene, build):
    black_world()
    _plane(segments=2)
    _bad_mesh("Bad", build)  # also: no material at all
    sun(3.0, tilt_degrees=10.0)
    _settings(bounces=1, shadows="fractions", passes={"lighting", "direct", "indirect", "irradiance", "ao"})
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    _all_finite()
    ground = image_pixels("VB_Ground_lighting")
    assert ground[..., 3].all() and ground[..., :3].max() > 0
    # Energy never exceeds what the sun alone delivers plus one bounce of it.
    assert ground[..., :3].max() <= RHO * 3.0 / math.pi * (1 + RHO) + 1e-4


def test_zero_area_and_overlapping_user_uvs_are_replaced(clean_scene):
    black_world()
    ground = _plane(segments=4)
    uv = ground.data.uv_layers["UVMap"].uv
    data = np.empty(len(uv) * 2, np.float32)
    uv.foreach_get("vector", data)
    data[:8] = 0.5  # two faces with zero UV area
    data[8:] = np.tile([0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0], (len(data) - 8) // 8)  # all overlapping
    uv.foreach_set("vector", data)
    before = data.copy()
    sun(3.0)
    _settings()
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    after = np.empty_like(data)
    ground.data.uv_layers["UVMap"].uv.foreach_get("vector", after)
    np.testing.assert_array_equal(after, before)  # the user's map is untouched
    assert "VisiBake" in ground.data.uv_layers
    lighting = image_pixels("VB_Ground_lighting")
    np.testing.assert_allclose(lighting[..., 0][lighting[..., 3] > 0], RHO * 3.0 / math.pi, rtol=1e-5)


# --- bad scale ----------------------------------------------------------------------

@pytest.mark.parametrize("offset, scale", [((1e4, -1e4, 1e4), 1.0), ((0, 0, 0), 1e-3), ((0, 0, 0), 1e3)],
                         ids=["far-from-origin", "millimetre-scene", "kilometre-scene"])
def test_scale_and_distance_do_not_change_a_sunlit_scene(clean_scene, offset, scale):
    black_world()
    ground = _plane(location=offset)
    block = mesh_object("Block", cube(0.4), material("Grey", (0.5, 0.5, 0.5)), uv_map=None,
                        location=(offset[0], offset[1], offset[2] + 0.2 * scale))
    for obj in (ground, block):
        obj.scale = (scale, scale, scale)
    sun(3.0, tilt_degrees=0.0)
    _settings(bounces=1, resolution=32)
    select_only([ground])
    _settings(bake_all=False)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    values = image_pixels("VB_Ground_lighting")[..., 0]
    lit = RHO * 3.0 / math.pi
    # The block stands on the plane's centre: its footprint is dark, everything
    # outside it is lit (plus a little light bounced off the block's sides). No acne:
    # no texel away from the block is darker than the sun alone.
    corner = values[:6, :6]
    assert np.all(corner >= lit * (1 - 1e-5)) and np.all(corner <= lit * 1.05)
    assert values[14:18, 14:18].max() < 0.05 * lit


def test_thin_closed_walls_do_not_leak_light(clean_scene):
    black_world()
    # A closed box of 1 cm walls around a floor; the sun outside must not get in.
    outer = mesh_object("Outer", cube(2.0), material("White", (RHO, RHO, RHO)), uv_map=None)
    inner = mesh_object("Inner", cube(1.98), material("White", (RHO, RHO, RHO)), uv_map=None, flip=True)
    sun(5.0, tilt_degrees=30.0)
    _settings(bounces=2, shadows="exact")
    select_only([inner])
    _settings(bake_all=False)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    inside = image_pixels("VB_Inner_lighting")
    assert inside[..., :3].max() == 0.0
    assert outer.name in bpy.data.objects


def test_coplanar_overlapping_faces_stay_finite(clean_scene):
    black_world()
    _plane(name="A")
    _plane(name="B", segments=3)
    sun(3.0)
    _settings(bounces=2)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    _all_finite()
    # Neither plane is above the other's horizon: no shadow, no bounce, so both are the
    # open plane under a sun from straight above, rho * S / pi, to float32.
    for name in ("A", "B"):
        np.testing.assert_allclose(image_pixels(f"VB_{name}_lighting")[..., :3], RHO * 3.0 / math.pi, rtol=1e-6)


# --- bad settings ---------------------------------------------------------------------

@pytest.mark.parametrize("energy", [0.0, -5.0, 1e25])
def test_zero_negative_and_huge_lights(clean_scene, energy):
    black_world()
    _plane()
    sun(energy)
    _settings(bounces=1)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    _all_finite()
    values = image_pixels("VB_Ground_lighting")[..., :3]
    expected = max(energy, 0.0) * RHO / math.pi
    np.testing.assert_allclose(values, expected, rtol=1e-5)


def test_absurd_light_strength_is_refused(clean_scene):
    black_world()
    ground = _plane()
    light = sun(1.0)
    light.data.energy = 1e35
    _settings()
    with pytest.raises(RuntimeError, match="strength"):
        bpy.ops.visibake.bake()
    assert "VB_Ground_lighting" not in bpy.data.images
    assert [layer.name for layer in ground.data.uv_layers] == ["UVMap"]


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_one_direction_works(clean_scene, shadows):
    black_world()
    _plane()
    mesh_object("Block", cube(0.4), material("Grey", (0.5, 0.5, 0.5)), uv_map=None, location=(0, 0, 0.3))
    sun(3.0)
    # One set for every texel (interleaved rotations would turn the one direction per texel).
    _settings(directions=1, bounces=2, shadows=shadows, passes={"lighting", "ao"}, interleave=1)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    _all_finite()
    # The one spherical Fibonacci direction is (1, 0, 0), on the horizon of the ground and
    # of the block's top: only the block's +x side traces it, and it escapes. No gather
    # reaches any lit surface, so the lighting is the sun's direct light alone.
    ground, block = image_pixels("VB_Ground_lighting")[..., :3], image_pixels("VB_Block_lighting")[..., :3]
    np.testing.assert_array_equal(image_pixels("VB_Ground_ao")[..., :3], 0.0)
    assert image_pixels("VB_Block_ao")[..., :3].max() == 1.0
    if shadows == "fractions":
        # No region around the sun holds a traced direction: the estimate has nothing to
        # go on and reads 0 (shadows.ShadowFractions.visibility), so no texel is lit.
        np.testing.assert_array_equal(ground, 0.0)
        np.testing.assert_array_equal(block, 0.0)
        return
    # Exact shadow rays: the plane is lit but for the block's footprint (|x|, |y| < 0.2,
    # texels 12.8 to 19.2 of 32 on the 2 m plane), the block's top fully and nothing else of it.
    # Texels 12 and 19 are partly shadowed where their box is a whole texel wide (Blender 5.2.1 on).
    footprint = np.zeros((32, 32), bool)
    footprint[13:19, 13:19] = True
    half = compat.CYCLES_BAKE_FOOTPRINT_WIDTH / 2
    centres = np.arange(32) + 0.5
    # Each texel's box's share under the shadow along x (or y).
    overlap = np.clip(np.minimum(centres + half, 19.2) - np.maximum(centres - half, 12.8), 0.0, None) / (2 * half)
    shaded = overlap[:, None] * overlap[None, :]
    np.testing.assert_array_equal(ground[footprint], 0.0)
    np.testing.assert_allclose(ground[shaded == 0], RHO * 3.0 / math.pi, rtol=1e-6)
    # The ring's sides are a fifth in shadow; its corners a twenty-fifth, which 16 points may miss.
    sides = (shaded > 0.1) & ~footprint
    assert sides.sum() == (0 if half < 0.5 else 4 * 6)
    assert np.all((ground[sides] > 0.0) & (ground[sides] < RHO * 3.0 / math.pi))
    assert np.all(ground[(shaded > 0) & ~footprint] <= RHO * 3.0 / math.pi * (1 + 1e-6))
    np.testing.assert_allclose(block.max(), 0.5 * 3.0 / math.pi, rtol=1e-6)


def test_resolution_one_works(clean_scene):
    black_world()
    _plane()
    sun(3.0)
    _settings(resolution=1)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    values = image_pixels("VB_Ground_lighting")
    assert values.shape == (1, 1, 4) and values[0, 0, 3] == 1.0
    # One texel at the plane's centre: the open plane's rho * S / pi.
    np.testing.assert_allclose(values[0, 0, :3], RHO * 3.0 / math.pi, rtol=1e-6)


@pytest.mark.parametrize("setting", [{"directions": 100000, "resolution": 4096}, {"resolution": 60000}],
                         ids=["too-many-directions", "too-large-atlas"])
def test_what_memory_cannot_hold_is_refused_before_allocating(clean_scene, setting):
    black_world()
    ground = _plane()
    sun(3.0)
    _settings(**setting)
    with pytest.raises(RuntimeError, match="available"):
        bpy.ops.visibake.bake()
    assert "VB_Ground_lighting" not in bpy.data.images
    assert [layer.name for layer in ground.data.uv_layers] == ["UVMap"]
