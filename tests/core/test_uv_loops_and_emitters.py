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


def _glowing_bar(length=1.5, width=0.12, height=0.05):
    """A closed box along x, faces outwards, glowing on every side (a strip light)."""
    from core.scene import Mesh

    x, y, z = length / 2, width / 2, height / 2
    positions = np.array([[sx * x, sy * y, sz * z] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    # Corners 0-7: index = 4 * (x > 0) + 2 * (y > 0) + (z > 0). Quads counter-clockwise from outside.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    corners = positions[triangles]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    assert np.all(np.einsum("td,td->t", normal, corners.mean(axis=1)) > 0)
    return Mesh(name="Bar", positions=positions, triangles=triangles,
                corner_normals=np.repeat(normal[:, None, :], 3, axis=1).astype(np.float32),
                material_index=np.zeros(len(triangles), np.int32),
                materials=[Material(base_color=np.zeros(3), emission=np.full(3, 5.0))],
                uv_maps={}, bake_uv_map=None, resolution=(8, 8), output=False)


def test_a_strip_s_points_cover_each_of_its_faces():
    """A 1.5 m glowing bar seen end on from 3 m: its 12 x 5 cm end faces the wall square on and
    lights it as much as a long side does, yet by area it was owed a fifth of a point of 16. Each
    flat face now has its own points, at least one (core.lights.emitters.find_emitters)."""
    from core.lights.emitters import EmissiveTriangles, triangle_irradiance

    bar = _glowing_bar()
    (emitter,) = find_emitters([bar], 16)
    assert emitter.area.sum() == pytest.approx(2 * (1.5 * 0.12 + 1.5 * 0.05 + 0.12 * 0.05))
    faces = {tuple(np.round(n).astype(int)) for n in emitter.normal}
    assert len(faces) == 6 and len(emitter.position) == 16
    # Receivers on a wall 3 m past the bar's end, facing it, across its height and width.
    ys, zs = np.meshgrid(np.linspace(-1.0, 1.0, 9), np.linspace(-1.0, 1.0, 9))
    wall = np.stack([np.full(ys.size, 3.75), ys.ravel(), zs.ravel()], axis=1)
    facing = np.tile([-1.0, 0.0, 0.0], (len(wall), 1))
    nothing = RayScene([(wall[:3] + 100.0, np.array([[0, 1, 2]], np.int32))])
    sampled, _ = emitter_irradiance(emitter, wall, facing, facing, offset_ray_origins(wall, facing), nothing)
    triangles = EmissiveTriangles(bar.positions[bar.triangles], bar.corner_normals[:, 0].astype(np.float64),
                                  np.full((len(bar.triangles), 3), 5.0), np.zeros(len(bar.triangles), np.int64))
    never = type("Never", (), {"occluded": lambda self, o, d, limit: np.zeros(len(o), bool)})()
    exact = triangle_irradiance(triangles, wall, facing, wall, never)
    # Spread by area over the whole bar: -16% in the mean, 25% RMS, and the receivers square to the
    # end (which sees the long sides edge on) dark. Now +4%, 9% RMS, 18% at worst (a long side's
    # light from two or three points, 3 to 4.5 m away).
    off = sampled[:, 0] / exact[:, 0] - 1.0
    assert abs(off.mean()) < 0.06 and np.sqrt(np.mean(off ** 2)) < 0.12 and np.abs(off).max() < 0.25


def test_a_long_strip_s_light_is_shadowed_where_it_comes_from():
    """A ceiling 5 cm over an 8 m glowing strip that passes through a column: one shadow ray per
    triangle, aimed at the triangle's middle, crossed the column from the far side, and the ceiling
    above the strip there was dark (and so the strip's top face, lit by that ceiling: seed 19 of
    ../shared/tools/scenegen.py, 0.55 of Cycles' strip alone). Aimed at the triangle's point nearest the
    receiver, it sees the strip below it."""
    from core.lights.emitters import EmissiveTriangles, triangle_irradiance

    strip = np.array([[-4.0, -0.06, 0.0], [4.0, -0.06, 0.0], [4.0, 0.06, 0.0], [-4.0, 0.06, 0.0]])
    triangles = EmissiveTriangles(strip[[[0, 1, 2], [0, 2, 3]]], np.tile([0.0, 0.0, 1.0], (2, 1)),
                                  np.full((2, 3), 5.0), np.zeros(2, np.int64))
    s = 0.2  # a column 40 cm across, from the floor to the ceiling, around the strip at x = 0
    column = np.array([[x, y, z] for x in (-s, s) for y in (-s, s) for z in (-3.0, 0.2)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int32)
    scene = RayScene([(column, faces)])
    ceiling = np.array([[x, 0.0, 0.05] for x in (1.0, 2.0, 3.0, -2.5)])
    down = np.tile([0.0, 0.0, -1.0], (len(ceiling), 1))
    never = type("Never", (), {"occluded": lambda self, o, d, limit: np.zeros(len(o), bool)})()
    open_light = triangle_irradiance(triangles, ceiling, down, ceiling, never)
    shadowed = triangle_irradiance(triangles, ceiling, down, offset_ray_origins(ceiling, down), scene)
    assert np.all(open_light[:, 0] > 1.0)
    np.testing.assert_allclose(shadowed, open_light, rtol=1e-12)
