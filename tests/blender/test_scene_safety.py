"""The user's data is never overwritten, and a failed or cancelled bake changes nothing."""
import bpy

import numpy as np
import pytest

from bpy_scenes import black_world, cube, grid, image_pixels, material, mesh_object, select_only, sun


def _uv(mesh, name):
    layer = mesh.uv_layers[name]
    data = np.empty(len(mesh.loops) * 2, np.float32)
    layer.uv.foreach_get("vector", data)
    return data


def _scene_with_user_uv(clean_scene):
    black_world()
    ground = mesh_object("Ground", grid(1.0, segments=4), material("White", (0.8, 0.8, 0.8)), uv_map="Mine")
    # Collapse the user's UV map onto one point: invalid for baking, and theirs.
    layer = ground.data.uv_layers["Mine"]
    layer.uv.foreach_set("vector", np.full(len(ground.data.loops) * 2, 0.5, np.float32))
    sun(2.0, tilt_degrees=10.0)
    select_only([ground])
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = 16, 16, 1
    return ground


def test_user_uv_map_is_left_alone_and_visibake_adds_its_own(clean_scene):
    ground = _scene_with_user_uv(clean_scene)
    before = _uv(ground.data, "Mine")
    active = ground.data.uv_layers.active.name
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    np.testing.assert_array_equal(_uv(ground.data, "Mine"), before)
    assert ground.data.uv_layers.active.name == active
    assert "VisiBake" in ground.data.uv_layers
    lighting = image_pixels("VB_Ground_lighting")
    assert np.isfinite(lighting).all() and lighting[..., 3].any()
    # Baking again reuses VisiBake's map and image: nothing is duplicated.
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    assert [layer.name for layer in ground.data.uv_layers] == ["Mine", "VisiBake"]
    assert [i.name for i in bpy.data.images if i.name.startswith("VB_Ground_lighting")] == ["VB_Ground_lighting"]


def test_a_users_image_is_never_overwritten(clean_scene):
    ground = _scene_with_user_uv(clean_scene)
    theirs = bpy.data.images.new("VB_Ground_lighting", 4, 4)
    theirs.pixels.foreach_set(np.full(64, 0.25, np.float32))
    before = image_pixels("VB_Ground_lighting")
    with pytest.raises(RuntimeError, match="not created by VisiBake"):
        bpy.ops.visibake.bake()
    np.testing.assert_array_equal(image_pixels("VB_Ground_lighting"), before)
    # Refused before anything changed: no UV map was added either.
    assert "VisiBake" not in ground.data.uv_layers


def test_cancel_leaves_the_scene_as_it_was(visibake, clean_scene):
    ground = _scene_with_user_uv(clean_scene)
    images = set(bpy.data.images.keys())

    def cancel_in_transport(stage, fraction):
        if stage == "transport":
            raise visibake.core.errors.Cancelled()

    with pytest.raises(visibake.core.errors.Cancelled):
        visibake.operators.adapter.job.run_bake(bpy.context, [ground], progress=cancel_in_transport)
    assert "VisiBake" not in ground.data.uv_layers
    assert set(bpy.data.images.keys()) == images


def test_broken_geometry_gives_finite_outputs(clean_scene):
    black_world()
    mesh_object("Ground", grid(1.0, segments=4), material("White", (0.8, 0.8, 0.8)))
    bad = mesh_object("Bad", cube(0.4), None, location=(0, 0, 0.5), uv_map=None)
    coords = np.empty(len(bad.data.vertices) * 3, np.float32)
    bad.data.vertices.foreach_get("co", coords)
    coords[0:3] = np.nan  # one vertex at NaN: its faces are degenerate, never hit
    coords[3:6] = coords[6:9]  # and a zero-area face
    bad.data.vertices.foreach_set("co", coords)
    bad.data.update()
    mesh_object("Empty", lambda bm, uv: None, None, uv_map=None)
    sun(3.0)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bake_all = 16, 16, True
    props.footprint_samples = 1  # texel centres: each texel sees the sun or not
    props.passes = {"lighting", "direct", "indirect", "irradiance", "ao"}
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    for name in ("Ground", "Bad"):
        for pass_name in props.passes:
            assert np.isfinite(image_pixels(f"VB_{name}_{pass_name}")).all()
    rho, sun_alone = 0.8, 0.8 * 3.0 / np.pi
    passes = {name: image_pixels(f"VB_Ground_{name}")[..., :3] for name in props.passes}
    # Exact shadows of a sun straight above: each ground texel sees it or not, and every
    # texel outside the cube's footprint (|x|, |y| < 0.2: texels 6 to 9 of 16 on the
    # 2 m plane) sees it. The faces the broken vertices leave still cast a shadow.
    footprint = np.zeros((16, 16), bool)
    footprint[6:10, 6:10] = True
    direct = passes["direct"]
    np.testing.assert_allclose(direct[~footprint], sun_alone, rtol=1e-6)
    lit = np.isclose(direct, sun_alone, rtol=1e-6)
    assert np.all(lit | (direct == 0.0)) and not lit[footprint].all()
    # The passes add up as they are defined (core.transport.passes), bounces included.
    np.testing.assert_allclose(passes["lighting"], passes["direct"] + passes["indirect"], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(passes["lighting"], rho * passes["irradiance"], rtol=1e-6)
    assert passes["indirect"].min() >= 0.0 and passes["indirect"].max() > 0.0
    assert passes["ao"].min() >= 0.0 and passes["ao"].max() <= 1.0
    # The broken cube: no face gets more than the sun from straight above.
    assert image_pixels("VB_Bad_direct")[..., :3].max() <= sun_alone * (1 + 1e-6)


def test_baking_again_at_another_resolution_resizes_visibakes_image(clean_scene):
    ground = _scene_with_user_uv(clean_scene)
    props = bpy.context.scene.visibake
    for resolution in (16, 32, 8):
        props.resolution = resolution
        assert bpy.ops.visibake.bake() == {"FINISHED"}
        image = bpy.data.images["VB_Ground_lighting"]
        assert tuple(image.size) == (resolution, resolution)
        assert image_pixels("VB_Ground_lighting")[..., 3].any()
    assert "VisiBake" in ground.data.uv_layers
