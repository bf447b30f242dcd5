"""Lamp features Cycles renders, each as a probe baked by VisiBake and by Cycles (tools/cycles_bake.py).

Soft shadows (sun angle, point and spot radius), area lamps through the same sampler,
light and shadow linking, a lamp's shadow switch, an object's shadow visibility, and a
lamp's node tree. Direct light only (bounces 0), exact shadows unless a test says
otherwise; ``-s`` prints every measured number.

Tolerances: the reference is Cycles at ``SAMPLES`` samples per texel, whose own noise
(measured in :func:`test_sun_with_an_angle_has_cycles_penumbra`, printed) is about 1-2%
relative RMSE on these probes; VisiBake integrates each lamp with 64 stratified points
per texel but samples only texel centres, which leaves a few percent along shadow
edges, where Cycles averages the texel (issue 15). Hence the bounds below (5-8%),
against errors of 20-60% when the feature is ignored (each test measures that too).
"""
import importlib
import math

import bpy

import numpy as np
import pytest

from bpy_scenes import black_world, cube, grid, image_pixels, material, mesh_object, point, select_only, spot, sun
from tools.cycles_bake import bake_diffuse

SAMPLES = 256
RESOLUTION = 48


def _settings(shadows="exact", directions=64):
    props = bpy.context.scene.visibake
    props.directions = directions
    props.bounces = 0
    props.shadows = shadows
    props.resolution = RESOLUTION
    props.passes = {"lighting"}
    props.bake_all = False
    return props


def _block_scene():
    """A 2 m white ground with a 0.5 m grey block floating just above it."""
    black_world()
    ground = mesh_object("Ground", grid(1.0), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0.0, 0.0, 0.3),
                        uv_map=None)
    return ground, block


def _ours(objects, shadows="exact"):
    _settings(shadows)
    select_only(objects)
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    return {obj.name: image_pixels(f"VB_{obj.name}_lighting") for obj in objects}


def _reference(objects, seed=0):
    return bake_diffuse(objects, "UVMap", RESOLUTION, RESOLUTION, bounces=0, samples=SAMPLES, seed=seed)


def _error(ours, reference):
    """Relative RMSE over the texels, and the same over the penumbra alone (reference
    between 5% and 95% of its maximum)."""
    a, b = ours[..., :3], reference[..., :3]
    scale = float(np.mean(b))
    total = float(np.sqrt(np.mean((a - b) ** 2)) / scale)
    peak = float(b[..., 0].max())
    penumbra = (b[..., 0] > 0.05 * peak) & (b[..., 0] < 0.95 * peak)
    edge = float(np.sqrt(np.mean((a[penumbra] - b[penumbra]) ** 2)) / scale) if penumbra.any() else 0.0
    return total, edge, int(penumbra.sum())


def _soft_case(lamp_setter, label, shadows="exact", noise=False):
    """(before, after) errors against Cycles: the lamp hard (as VisiBake baked it before),
    then with its extent; Cycles renders the lamp with its extent both times."""
    ground, _ = _block_scene()
    lamp = lamp_setter()
    reference = _reference([ground])["Ground"]
    after = _error(_ours([ground], shadows)["Ground"], reference)
    extent = {name: getattr(lamp.data, name) for name in ("angle", "shadow_soft_size") if hasattr(lamp.data, name)}
    for name in extent:
        setattr(lamp.data, name, 0.0)
    before = _error(_ours([ground], shadows)["Ground"], reference)
    for name, value in extent.items():
        setattr(lamp.data, name, value)
    line = (f"\n{label} ({shadows}): relative RMSE before {before[0]:.4f} (penumbra {before[1]:.4f}), "
            f"after {after[0]:.4f} (penumbra {after[1]:.4f}); {after[2]} penumbra texels")
    if noise:
        again = _reference([ground], seed=1)["Ground"]
        own = _error(again, reference)
        line += f"; Cycles' own noise {own[0] / math.sqrt(2):.4f} (penumbra {own[1] / math.sqrt(2):.4f})"
    print(line)
    return before, after


def test_sun_with_an_angle_has_cycles_penumbra(clean_scene):
    def setter():
        lamp = sun(3.0, tilt_degrees=35.0)
        lamp.data.angle = math.radians(10.0)
        return lamp

    before, after = _soft_case(setter, "sun, angle 10 deg", noise=True)
    assert after[2] > 40  # a real penumbra: dozens of texels
    # Measured on the penumbra: 0.026 of 0.287 against Cycles 5.0 (boxes half a texel wide,
    # Cycles' own noise 0.014), 0.029 of 0.227 against 5.3 (whole-texel boxes, noise 0.017).
    # Before footprint and sun points were one jointly stratified 4D set (core.lights.lamps
    # LampPoints.contribution) they were 0.067 and 0.121: the wider box only showed the
    # correlated set's noise more.
    assert after[0] < 0.015 and after[1] < 0.045
    assert after[1] < 0.2 * before[1]


def test_sun_with_an_angle_in_shadow_fractions(clean_scene):
    def setter():
        lamp = sun(3.0, tilt_degrees=35.0)
        lamp.data.angle = math.radians(10.0)
        return lamp

    before, after = _soft_case(setter, "sun, angle 10 deg", shadows="fractions")
    # Fractions are the paper's approximation (32 regions of 64 directions): bounded, and
    # averaging them over the sun's cone must not make them worse.
    assert after[0] < 0.35 and after[0] <= before[0] * 1.02


@pytest.mark.parametrize("soft_falloff", [True, False])
def test_point_with_a_radius_has_cycles_penumbra(clean_scene, soft_falloff):
    def setter():
        lamp = point(150.0, (0.3, 0.2, 1.6))
        lamp.data.shadow_soft_size = 0.5
        lamp.data.use_soft_falloff = soft_falloff
        return lamp

    before, after = _soft_case(setter, f"point, radius 0.5, soft falloff {soft_falloff}")
    assert after[2] > 40
    # Measured: 0.012-0.014 against Cycles 5.0, 0.016-0.017 against 5.3 (0.015 and 0.026 before
    # the lamp's points and the footprint's were one stratified set).
    assert after[0] < 0.022 and after[1] < 0.022
    assert after[1] < 0.2 * before[1]


def test_spot_with_a_radius_has_cycles_penumbra(clean_scene):
    def setter():
        return _soft_spot()

    before, after = _soft_case(setter, "spot, radius 0.3, 80 deg cone")
    # Measured: 0.013 against Cycles 5.0, 0.015 against 5.3 (0.017 and 0.032 before the stratified set).
    assert after[0] < 0.022 and after[1] < 0.022
    assert after[1] < 0.2 * before[1]


def _soft_spot():
    lamp = spot(300.0, (0.4, -0.3, 1.5), (15.0, 10.0, 0.0), 80.0, 0.2)
    lamp.data.shadow_soft_size = 0.3
    return lamp


def test_area_lamp_through_the_sampler_matches_cycles(clean_scene):
    from bpy_scenes import area

    ground, _ = _block_scene()
    area(120.0, (0.2, 0.1, 1.4), (10.0, -15.0, 0.0), "RECTANGLE", 0.8, 0.4)
    total, edge, count = _error(_ours([ground])["Ground"], _reference([ground])["Ground"])
    print(f"\narea 0.8 x 0.4: relative RMSE {total:.4f} (penumbra {edge:.4f}, {count} texels)")
    # Measured: 0.012 against Cycles 5.0, 0.016 against 5.3 (0.016 and 0.028 before the stratified set).
    assert count > 40 and total < 0.022 and edge < 0.022


def test_area_lamp_a_few_centimetres_above_the_ground_matches_cycles(clean_scene):
    # A 0.5 x 0.3 m panel 4 cm over the ground, beside the block: the texels under it get cos / r^2
    # from a lamp as close as they are wide. Measured against Cycles 5.0 (its own noise 0.020):
    # points uniform on the lamp's area 0.85; uniform in its solid angle 0.039; and wholly lit
    # texels in closed form 0.021.
    from bpy_scenes import area

    ground, _ = _block_scene()
    area(30.0, (0.55, 0.45, 0.04), (0.0, 0.0, 0.0), "RECTANGLE", 0.5, 0.3)
    reference = _reference([ground])["Ground"]
    total, _, _ = _error(_ours([ground])["Ground"], reference)
    own = _error(_reference([ground], seed=1)["Ground"], reference)[0] / math.sqrt(2)
    print(f"\narea 0.5 x 0.3 at 4 cm: relative RMSE {total:.4f}; Cycles' own noise {own:.4f}")
    assert total < 3.0 * own + 0.01


def _two_grounds():
    """Two white planes side by side (A at x < 0, B at x > 0) under a hard point lamp."""
    black_world()
    a = mesh_object("A", grid(0.5), material("White", (0.8, 0.8, 0.8)), location=(-0.6, 0.0, 0.0))
    b = mesh_object("B", grid(0.5), material("White2", (0.8, 0.8, 0.8)), location=(0.6, 0.0, 0.0))
    lamp = point(100.0, (0.0, 0.0, 1.2), name="Lamp")
    return a, b, lamp


def _linking_collection(lamp, attribute, members):
    collection = bpy.data.collections.new(f"{lamp.name} {attribute}")
    setattr(lamp.light_linking, attribute, collection)
    for obj, state in members:
        collection.objects.link(obj)
        # collection_objects runs parallel to objects (its items do not name their object).
        index = list(collection.objects).index(obj)
        collection.collection_objects[index].light_linking.link_state = state
    return collection


@pytest.mark.parametrize("state", ["INCLUDE", "EXCLUDE"])
def test_receiver_linking_matches_cycles(clean_scene, state):
    a, b, lamp = _two_grounds()
    # INCLUDE A: only A is lit. EXCLUDE B: everything but B is lit. Both leave B dark.
    _linking_collection(lamp, "receiver_collection", [(a, "INCLUDE")] if state == "INCLUDE" else [(b, "EXCLUDE")])
    ours = _ours([a, b])
    reference = _reference([a, b])
    error_a = _error(ours["A"], reference["A"])[0]
    print(f"\nreceiver linking ({state}): A relative RMSE {error_a:.4f}, B max ours {ours['B'][..., :3].max():.3g} "
          f"Cycles {reference['B'][..., :3].max():.3g}")
    assert error_a < 0.03
    assert reference["B"][..., :3].max() < 1e-3 and ours["B"][..., :3].max() == 0.0


def _shadow_case(configure, label):
    ground, block = _block_scene()
    lamp = point(150.0, (0.3, 0.2, 1.6), name="Lamp")
    unshadowed_ours = _ours([ground])["Ground"]
    configure(lamp, ground, block)
    reference = _reference([ground])["Ground"]
    ours = _ours([ground])["Ground"]
    error = _error(ours, reference)[0]
    ignored = _error(unshadowed_ours, reference)[0]
    print(f"\n{label}: relative RMSE {error:.4f} (the feature ignored: {ignored:.4f})")
    return error, ignored


def test_blocker_linking_matches_cycles(clean_scene):
    # The block is left out of the lamp's blockers: it casts no shadow of that lamp.
    error, ignored = _shadow_case(
        lambda lamp, ground, block: _linking_collection(lamp, "blocker_collection", [(ground, "INCLUDE")]),
        "blocker linking (only the ground blocks)")
    assert error < 0.02 and ignored > 0.1


def test_use_shadow_off_matches_cycles(clean_scene):
    def configure(lamp, ground, block):
        lamp.data.use_shadow = False

    error, ignored = _shadow_case(configure, "use_shadow off")
    assert error < 0.02 and ignored > 0.1


def test_shadow_visibility_off_matches_cycles(clean_scene):
    def configure(lamp, ground, block):
        block.visible_shadow = False

    error, ignored = _shadow_case(configure, "block's shadow visibility off")
    assert error < 0.02 and ignored > 0.1


def test_shadow_visibility_off_is_warned_about_with_shadow_fractions(clean_scene, visibake):
    ground, block = _block_scene()
    point(150.0, (0.3, 0.2, 1.6), name="Lamp")
    block.visible_shadow = False
    extracted = _adapter(visibake, "extraction").extract_scene(bpy.context, [ground])
    try:
        assert [m.casts_shadow for m in extracted.scene.meshes if m.name == "Block"] == [False]
        settings = visibake.core.settings.BakeSettings(directions=16, bounces=0, shadows="fractions")
        prepared = visibake.core.pipeline.prepare.prepare(extracted.scene, settings)
    finally:
        extracted.undo()
    assert any("shadow visibility is off" in w and "Block" in w for w in prepared.warnings)


def _adapter(visibake, name):
    return importlib.import_module(f"{visibake.__name__}.operators.adapter.{name}")


def test_lamp_node_tree_matches_cycles(clean_scene, visibake):
    ground, _ = _block_scene()
    lamp = point(150.0, (0.3, 0.2, 1.6), name="Lamp")
    light = lamp.data
    if light.node_tree is None:
        light.use_nodes = True
    emission = next(n for n in light.node_tree.nodes if n.bl_idname == "ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 0.3
    emission.inputs["Color"].default_value = (1.0, 0.6, 0.2, 1.0)
    reference = _reference([ground])["Ground"]
    ours = _ours([ground])["Ground"]
    lit = reference[..., 0] > 0.5 * reference[..., 0].max()
    ratio = ours[lit][:, :3].mean(axis=0) / reference[lit][:, :3].mean(axis=0)
    error = _error(ours, reference)[0]
    print(f"\nlamp node tree (strength 0.3, colour (1, 0.6, 0.2)): ours / Cycles per channel {np.round(ratio, 4)}, "
          f"relative RMSE {error:.4f}")
    np.testing.assert_allclose(ratio, 1.0, atol=0.02)
    # A texture feeding the colour cannot be baked from constants: it is said, with the value used.
    texture = light.node_tree.nodes.new("ShaderNodeTexNoise")
    light.node_tree.links.new(texture.outputs["Color"], emission.inputs["Color"])
    warnings = []
    read = _adapter(visibake, "extract").read_light(lamp, warnings)
    assert any("Lamp" in w and "ShaderNodeTexNoise" in w and "Color value" in w for w in warnings)
    np.testing.assert_allclose(read.color, [1.0, 0.6, 0.2], rtol=1e-6)


def test_a_lamp_in_a_collection_disabled_for_rendering_gives_no_light(clean_scene):
    ground, _ = _block_scene()
    lamp = point(150.0, (0.3, 0.2, 1.6), name="Lamp")
    hidden = bpy.data.collections.new("Hidden lamps")
    bpy.context.scene.collection.children.link(hidden)
    hidden.objects.link(lamp)
    bpy.context.scene.collection.objects.unlink(lamp)
    hidden.hide_render = True
    reference = _reference([ground])["Ground"]
    ours = _ours([ground])["Ground"]
    print(f"\nlamp in a collection disabled in renders: max ours {ours[..., :3].max():.3g}, "
          f"Cycles {reference[..., :3].max():.3g}")
    assert reference[..., :3].max() < 1e-4 and ours[..., :3].max() == 0.0


def test_linking_the_extraction_cannot_follow_is_warned_about(clean_scene, visibake):
    a, b, lamp = _two_grounds()
    _linking_collection(lamp, "receiver_collection", [(b, "EXCLUDE")])
    warnings = []
    read = _adapter(visibake, "extract").read_light(lamp, warnings)  # without the scene's objects
    assert read.receivers is None and any("Lamp" in w and "only excludes" in w for w in warnings)
    read = _adapter(visibake, "extract").read_light(lamp, [], ["A", "B"])
    assert read.receivers == ("A",)
    # An emissive object's own linking is not followed: said, naming the object.
    glow = material("Glow", (0.8, 0.8, 0.8), emission=(1.0, 1.0, 1.0), strength=2.0)
    a.data.materials[0] = glow
    _linking_collection(a, "receiver_collection", [(b, "INCLUDE")])
    extracted = _adapter(visibake, "extraction").extract_scene(bpy.context, [a, b])
    extracted.undo()
    assert any("'A'" in w and "emissive objects" in w for w in extracted.warnings)
