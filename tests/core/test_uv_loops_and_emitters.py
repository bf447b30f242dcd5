import numpy as np
import pytest

from core.lights.emitters import emitter_irradiance, find_emitters, sampled_directly
from core.pipeline.relight import bake
from core.sampling.atlas import loop_uvs, uv_layout_problems
from core.scene import Material, Scene
from core.settings import BakeSettings
from core.visibility.rays import RayScene, offset_ray_origins
from core_scenes import box_interior, quad_mesh


def test_loop_uvs_keeps_a_split_quad_in_one_chart():
    # A unit quad (loops 0..3) as two triangles that an unwrapper put into two
    # distant charts: corners 0 and 2 (shared loops) disagree.
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    loops = np.array([[0, 1, 2], [0, 2, 3]])
    corner_uv = np.array([[[0.1, 0.1], [0.4, 0.1], [0.4, 0.4]],
                          [[0.6, 0.6], [0.8, 0.8], [0.6, 0.8]]], np.float32)
    per_loop, remapped = loop_uvs(positions, triangles, loops, corner_uv, 4)
    assert remapped == 1
    # The larger triangle's chart wins and the other corner follows its affine map.
    np.testing.assert_allclose(per_loop, [[0.1, 0.1], [0.4, 0.1], [0.4, 0.4], [0.1, 0.4]], atol=1e-6)
    assert uv_layout_problems(per_loop[loops], 32, 32) == []


def test_loop_uvs_leaves_consistent_input_alone():
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    loops = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)
    per_loop, remapped = loop_uvs(positions, triangles, loops, uv[loops], 4)
    assert remapped == 0
    np.testing.assert_array_equal(per_loop, uv)


def _glowing_square(size, height, resolution=8):
    s = size / 2
    # Facing down (-z): corners counter-clockwise seen from below.
    return quad_mesh("Glow", [(-s, -s, height), (-s, s, height), (s, s, height), (s, -s, height)],
                     material=Material(base_color=np.zeros(3), emission=np.full(3, 10.0)), resolution=resolution)


def test_emitter_points_carry_the_whole_emitting_area():
    glow = _glowing_square(0.2, 3.0)
    (emitter,) = find_emitters([glow], 16)
    assert emitter.area.sum() == pytest.approx(0.04)
    np.testing.assert_allclose(emitter.normal, np.tile([0.0, 0.0, -1.0], (16, 1)))
    assert np.all(np.abs(emitter.position[:, :2]) <= 0.1 + 1e-12)
    # Small and far: sampled directly; from right next to it: gathered.
    far = np.array([[0.0, 0.0, 0.0]])
    near = np.array([[0.0, 0.0, 2.99]])
    assert sampled_directly(emitter, far, 128)[0]
    assert not sampled_directly(emitter, near, 128)[0]


def test_directly_sampled_emitter_matches_the_far_field_formula():
    glow = _glowing_square(0.2, 3.0)
    (emitter,) = find_emitters([glow], 16)
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    scene = RayScene([(ground.positions, ground.triangles), (glow.positions, glow.triangles)])
    point = np.array([[0.0, 0.0, 0.0]])
    up = np.array([[0.0, 0.0, 1.0]])
    irradiance, rays = emitter_irradiance(emitter, point, up, up, offset_ray_origins(point, up), scene)
    # E = L * A * cos * cos / d^2 for a small source straight above; the square's
    # extent (0.2 at distance 3) lowers the exact value by ~(0.1/3)^2 relative.
    assert irradiance[0, 0] == pytest.approx(10.0 * 0.04 / 9.0, rel=3e-3)
    assert rays == 16


def test_sampled_emitter_agrees_with_a_dense_gather():
    """Direct sampling and a 4096-direction gather see the same small emitter."""
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
                       material=Material(base_color=np.full(3, 0.5)), resolution=16)
    glow = _glowing_square(0.3, 1.0)
    sampled = bake(Scene([ground, glow], []), BakeSettings(directions=64, bounces=0, emitter_samples=64))
    assert sampled.report["emitters_sampled"] == ["Glow"]
    gathered = bake(Scene([ground, glow], []), BakeSettings(directions=4096, bounces=0))
    a = sampled.objects[0].images["lighting"][..., 0]
    b = gathered.objects[0].images["lighting"][..., 0]
    assert abs(a.mean() / b.mean() - 1) < 0.03


def _closed_cube(name, centre, size):
    """A cube with outward normals: box_interior turned inside out and moved."""
    cube = box_interior(size, Material(base_color=np.full(3, 0.5)), resolution=32)
    cube.name = name
    cube.positions = cube.positions + np.asarray(centre, float)
    cube.triangles = cube.triangles[:, [0, 2, 1]]
    cube.corner_normals = -cube.corner_normals[:, [0, 2, 1]]
    cube.uv_maps = {k: v[:, [0, 2, 1]] for k, v in cube.uv_maps.items()}
    return cube


def test_texels_inside_other_geometry_are_reported_as_buried():
    # Two overlapping closed cubes: the part of each one's surface inside the other
    # sees only the other's back faces. Those texels are buried, not a modelling error.
    a = _closed_cube("A", (0.0, 0.0, 0.0), 1.0)
    b = _closed_cube("B", (0.5, 0.0, 0.0), 1.0)
    result = bake(Scene([a, b], []), BakeSettings(directions=64, bounces=1))
    entries = {o["name"]: o for o in result.report["objects"]}
    for name in ("A", "B"):
        texels = entries[name]["texels"]
        # One face of each lies inside the other cube (their side faces are coplanar,
        # on the other's surface, not inside it): 1 of 6.
        assert entries[name]["buried_texels"] == pytest.approx(texels / 6, rel=0.05)
    assert not any("back of a face" in w for w in result.report["warnings"])
    assert all(np.isfinite(r.images["lighting"]).all() for r in result.objects)
