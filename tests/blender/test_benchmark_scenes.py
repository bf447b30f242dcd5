"""The benchmark scenes (benchmarks/scenes.py) and the Cycles reference cache
(benchmarks/reference.py), in real bpy, at smoke size. No timing is asserted here."""
import math

import bpy

import numpy as np
import pytest

from benchmarks import reference, scenes
from blender_support import is_enabled
from tools.cycles_bake import bake_diffuse


def _world_positions(obj) -> np.ndarray:
    co = np.empty(3 * len(obj.data.vertices), np.float64)
    obj.data.vertices.foreach_get("co", co)
    matrix = np.array(obj.matrix_world)
    return co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


def _planar_uv(obj, name: str) -> str:
    """A UV map projecting a flat horizontal object's x, y onto [0, 1]^2."""
    xy = _world_positions(obj)[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    uv_vert = (xy - lo) / np.where(hi > lo, hi - lo, 1.0)
    loop_vertex = np.empty(len(obj.data.loops), np.int32)
    obj.data.loops.foreach_get("vertex_index", loop_vertex)
    layer = obj.data.uv_layers.new(name=name)
    layer.data.foreach_set("uv", uv_vert[loop_vertex].astype(np.float32).ravel())
    return name


def _texel_centres(lo, hi, resolution: int) -> np.ndarray:
    """(R, R, 2) world x, y of the texel centres of a planar map of [lo, hi]; [row v, column u]."""
    t = (np.arange(resolution) + 0.5) / resolution
    x = lo[0] + t * (hi[0] - lo[0])
    y = lo[1] + t * (hi[1] - lo[1])
    return np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)


def _in_box(centres, x_range, y_range) -> np.ndarray:
    return ((centres[..., 0] > x_range[0]) & (centres[..., 0] < x_range[1])
            & (centres[..., 1] > y_range[0]) & (centres[..., 1] < y_range[1]))


@pytest.mark.parametrize("name", list(scenes.SCENES))
def test_smoke_scene_is_well_formed(clean_scene, name):
    objects = scenes.SCENES[name]("smoke")

    assert objects and all(obj.type == "MESH" for obj in objects)
    assert all(clean_scene.objects.get(obj.name) is obj for obj in objects)
    triangles = 0
    for obj in objects:
        assert len(obj.data.polygons) > 0, obj.name
        assert np.isfinite(_world_positions(obj)).all(), obj.name
        triangles += len(obj.data.loop_triangles)
    # Smoke scenes are for tests: a few hundred triangles (the terrain's grid ~2k).
    assert triangles <= (2500 if name == "dense_mesh" else 500)

    lights = [obj.data for obj in clean_scene.objects if obj.type == "LIGHT"]
    assert lights
    for light in lights:
        assert (light.angle if light.type == "SUN" else light.shadow_soft_size) == 0.0

    background = clean_scene.world.node_tree.nodes["Background"].inputs
    if name in scenes.OUTSIDE_SCENE_NAMES + scenes.ISSUE_52_SCENE_NAMES:
        # A uniform sky: the colour the world's extraction reads, nothing Cycles alone would see.
        assert min(background["Color"].default_value[:3]) > 0.0 and background["Strength"].default_value > 0.0
        assert len(clean_scene.world.node_tree.nodes) == 2  # Background and World Output
    else:
        assert tuple(background["Color"].default_value[:3]) == (0.0, 0.0, 0.0)

    # Every surface, baked or only occluding, is pure Lambert with albedo <= 0.8.
    for obj in clean_scene.objects:
        if obj.type != "MESH":
            continue
        assert obj.material_slots, obj.name
        for slot in obj.material_slots:
            bsdf = slot.material.node_tree.nodes["Principled BSDF"]
            assert bsdf.inputs["Specular IOR Level"].default_value == 0.0
            assert bsdf.inputs["Roughness"].default_value == 1.0
            assert max(bsdf.inputs["Base Color"].default_value[:3]) <= np.float32(scenes.MAX_ALBEDO)
            assert bsdf.inputs["Emission Strength"].default_value == 0.0

    for obj in objects:
        maps = obj.data.uv_layers.keys()
        if name == "dense_mesh":
            assert maps == ["UVMap"]
            uv = np.empty(2 * len(obj.data.loops), np.float32)
            obj.data.uv_layers["UVMap"].data.foreach_get("uv", uv)
            assert uv.min() >= 0.0 and uv.max() <= 1.0
        else:
            assert maps == [], f"{obj.name} should be left for VisiBake to unwrap"


def test_reset_empties_the_file_and_keeps_the_extension(clean_scene, visibake):
    scenes.SCENES["many_objects"]("smoke")
    scenes.reset()
    assert len(bpy.data.objects) == 0 and len(bpy.data.meshes) == 0 and len(bpy.data.lights) == 0
    assert is_enabled()
    assert hasattr(bpy.context.scene, "visibake")


def test_thin_panel_does_not_leak_sunlight(clean_scene):
    floor = scenes.SCENES["thin_geometry"]("smoke")[0]
    resolution = 64
    uv_map = _planar_uv(floor, "Planar")
    image = bake_diffuse([floor], uv_map, resolution, resolution, bounces=0, samples=4)["Floor"]
    centres = _texel_centres((-2.0, -2.0), (2.0, 2.0), resolution)
    # The panel spans x in [-1.6, -0.1] at y = 0.50-0.51 and the sun comes from -y.
    behind = _in_box(centres, (-1.2, -0.5), (0.56, 0.9))
    in_front = _in_box(centres, (-1.2, -0.5), (-0.5, 0.4))
    assert behind.sum() >= 20 and in_front.sum() >= 20
    assert np.all(image[behind][:, :3] == 0.0), "sunlight leaks through the 1 cm panel"
    lit = 0.6 * 4.0 * math.sin(math.radians(35.0)) / math.pi  # albedo * E / pi
    np.testing.assert_allclose(image[in_front][:, :3], lit, rtol=1e-3)


def test_room_sun_enters_through_the_window_only(clean_scene):
    objects = {obj.name: obj for obj in scenes.SCENES["interior_opening"]("smoke")}
    floor, ceiling = objects["Floor"], objects["Ceiling"]
    for obj in (floor, ceiling):
        _planar_uv(obj, "Planar")
    images = bake_diffuse([floor, ceiling], "Planar", 32, 32, bounces=0, samples=1)
    covered = images["Ceiling"][..., 3] > 0
    assert covered.all()
    assert np.all(images["Ceiling"][covered][:, :3] == 0.0), "direct sunlight reaches the ceiling"
    lit = images["Floor"][..., 0] > 0
    # The window (1.4 x 1.0 m) projects to ~1.9 m^2 of the 20 m^2 floor, part of it on the block.
    assert 0.02 < lit.mean() < 0.12


def _key(objects, uv_maps, resolution=16, bounces=1, samples=4, **kw):
    return reference.scene_key(objects, uv_maps, resolution, bounces, samples, **kw)


def test_scene_key_is_stable_and_sees_what_changes_the_bake(clean_scene):
    def build():
        objects = scenes.SCENES["sun_occluders"]("smoke")
        uv_maps = {obj.name: _planar_uv(obj, "KeyUV") for obj in objects}
        return objects, uv_maps

    objects, uv_maps = build()
    key = _key(objects, uv_maps)
    assert len(key) == 64 and key == _key(objects, uv_maps)
    scenes.reset()
    objects, uv_maps = build()
    assert _key(objects, uv_maps) == key, "two builds of the same scene must share a key"

    sun = bpy.data.objects["Sun"]
    original = tuple(sun.rotation_euler)  # restored exactly: float32 += / -= may not round-trip
    sun.rotation_euler.x += 0.01
    assert _key(objects, uv_maps) != key
    sun.rotation_euler = original
    assert _key(objects, uv_maps) == key
    sun.data.energy = 5.0
    assert _key(objects, uv_maps) != key
    sun.data.energy = 4.0

    box = bpy.data.objects["BoxA"]
    original = tuple(box.location)
    box.location.x += 0.01
    assert _key(objects, uv_maps) != key
    box.location = original
    assert _key(objects, uv_maps) == key

    uv = box.data.uv_layers["KeyUV"].data[0]
    original = tuple(uv.uv)
    uv.uv = (0.5, 0.5)
    assert _key(objects, uv_maps) != key
    uv.uv = original

    colour = box.material_slots[0].material.node_tree.nodes["Principled BSDF"].inputs["Base Color"]
    original = tuple(colour.default_value)
    colour.default_value[0] = 0.1
    assert _key(objects, uv_maps) != key
    colour.default_value = original
    # An image node that feeds nothing (where a bake writes) does not change the shading.
    node = box.material_slots[0].material.node_tree.nodes.new("ShaderNodeTexImage")
    node.image = bpy.data.images.new("Unlinked", 4, 4, float_buffer=True)
    assert _key(objects, uv_maps) == key

    # An occluder that is not baked still changes the bake.
    assert _key(objects, {"Ground": "KeyUV"}) != key
    ground_only = _key(objects, {"Ground": "KeyUV"})
    bpy.data.objects["Pole"].location.y += 0.1
    assert _key(objects, {"Ground": "KeyUV"}) != ground_only

    assert len({key, _key(objects, uv_maps, resolution=32), _key(objects, uv_maps, bounces=2),
                _key(objects, uv_maps, samples=8), _key(objects, uv_maps, halves=False)}) == 5


def test_cached_reference_hits_and_rebakes_damaged_files(clean_scene, tmp_path):
    objects = scenes.SCENES["dense_mesh"]("smoke")
    uv_maps = {"Terrain": "UVMap"}
    args = (objects, uv_maps, 16, 1, 4, str(tmp_path))

    first = reference.cached_reference(*args)
    assert not first.cached and first.seconds > 0
    image = first.images["Terrain"]
    assert image.shape == (16, 16, 4) and image.dtype == np.float32
    assert (image[..., 3] > 0).all() and image[..., :3].max() > 0
    assert first.noise is not None and 0 < first.noise < 1
    path = tmp_path / f"{reference.scene_key(objects, uv_maps, 16, 1, 4)}.npz"
    assert path.is_file() and [p.name for p in tmp_path.iterdir()] == [path.name]

    second = reference.cached_reference(*args)
    assert second.cached
    np.testing.assert_array_equal(second.images["Terrain"], image)
    assert (second.seconds, second.noise) == (first.seconds, first.noise)

    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    rebaked = reference.cached_reference(*args)
    assert not rebaked.cached
    # Same seeds, same samples: Cycles gives the same texels.
    np.testing.assert_allclose(rebaked.images["Terrain"], image, rtol=1e-5, atol=1e-6)
    assert reference.cached_reference(*args).cached

    with np.load(path) as stored:
        kept = {k: stored[k] for k in stored.files if k != "seconds"}
    np.savez_compressed(path, **kept)
    assert not reference.cached_reference(*args).cached


def test_relative_errors():
    ref = np.zeros((2, 2, 4), np.float32)
    ref[..., :3] = [[[1.0], [2.0]], [[3.0], [0.0]]]
    ref[..., 3] = [[1, 1], [1, 0]]  # the last texel is not covered
    ours = ref.copy()
    ours[0, 0, :3] = 1.5
    ours[1, 1, :3] = 100.0  # uncovered in the reference: ignored
    errors = reference.relative_errors({"A": ours}, {"A": ref})
    assert errors["texels"] == 3
    mean = 2.0
    assert errors["relative_rmse"] == pytest.approx(math.sqrt(0.25 / 3) / mean)
    assert errors["max_abs_error"] == pytest.approx(0.5)
    assert errors["max_relative_error"] == pytest.approx(0.5)
    assert errors["bias"] == pytest.approx(6.5 / 6.0 - 1.0)
    with pytest.raises(ValueError):
        reference.relative_errors({"A": ours}, {"B": ref})


def test_hidden_texels_are_inside_or_face_to_face_with_other_geometry(clean_scene):
    # A floor plane, a 1 m cube resting on it, and a thin post through the cube: the cube's
    # bottom face lies on the floor, the post's middle is inside the cube; a free ball hides nothing.
    bpy.ops.mesh.primitive_plane_add(size=6.0)
    floor = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.5))
    cube = bpy.context.active_object
    bpy.ops.mesh.primitive_cylinder_add(vertices=16, radius=0.1, depth=3.0, location=(0.0, 0.0, 1.5))
    post = bpy.context.active_object
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.4, location=(2.0, 2.0, 1.0))
    ball = bpy.context.active_object
    objects = [floor, cube, post, ball]
    uv_maps = {}
    for obj in objects:
        bpy.context.view_layer.objects.active = obj
        for other in objects:
            other.select_set(other is obj)
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.smart_project(island_margin=0.02)
        bpy.ops.object.mode_set(mode="OBJECT")
        uv_maps[obj.name] = obj.data.uv_layers.active.name
    hidden = reference.hidden_texels(objects, uv_maps, 32)
    covered = {}
    for obj in objects:
        _, _, pixels = reference._texel_points(*reference._uv_triangles(obj, uv_maps[obj.name], 32), 32)
        covered[obj.name] = len(np.unique(pixels, axis=0))
    assert not hidden[ball.name].any()
    # The cube: its bottom face (a sixth of its area, the post's hole aside) lies on the floor,
    # and the texels along its bottom edges are partly on it.
    assert 0.12 < hidden[cube.name].sum() / covered[cube.name] < 0.3
    # The post: 1 m of its 3 m side inside the cube, its bottom cap on the floor.
    assert 0.25 < hidden[post.name].sum() / covered[post.name] < 0.4
    # The floor: only under the cube (1 of 36 m^2) is face to face with it.
    assert 0.0 < hidden[floor.name].sum() / covered[floor.name] < 0.05
    ours = {obj.name: np.ones((32, 32, 4), np.float32) for obj in objects}
    ref = reference.Reference({k: v.copy() for k, v in ours.items()}, 0.0, None, False)
    seen, seen_ref = reference.without_hidden(ours, ref, hidden)
    assert (seen[cube.name][..., 3] == 0).sum() == hidden[cube.name].sum()
    assert np.all(ours[cube.name][..., 3] == 1.0)  # the inputs are left as they were
