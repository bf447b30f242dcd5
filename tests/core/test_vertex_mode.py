"""Vertex-table mode (the paper's section 5): samples at vertices, hits mixed from a triangle's samples."""
import numpy as np
import pytest

from core.pipeline.prepare import prepare
from core.pipeline.relight import bake, relight
from core.sampling.samples import build_vertex_samples
from core.scene import Light, Material, Mesh, Scene, World
from core.settings import BakeSettings
from core.visibility.cache import VisibilityCache
from core_scenes import grid_mesh, quad_mesh


def inward_sphere(material, rings=12, segments=24):
    """A closed UV sphere of radius 1 seen from inside, smooth inward normals."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring_points = np.stack([np.outer(np.sin(theta), np.cos(phi)).ravel(),
                            np.outer(np.sin(theta), np.sin(phi)).ravel(),
                            np.repeat(np.cos(theta), segments)], axis=1)
    positions = np.concatenate([[[0, 0, 1]], ring_points, [[0, 0, -1]]])
    south = len(positions) - 1
    triangles = []
    for j in range(segments):
        k = (j + 1) % segments
        triangles.append([0, 1 + k, 1 + j])
        base = 1 + (rings - 2) * segments
        triangles.append([south, base + j, base + k])
    for i in range(rings - 2):
        for j in range(segments):
            k = (j + 1) % segments
            a, b = 1 + i * segments + j, 1 + i * segments + k
            c, d = a + segments, b + segments
            triangles += [[a, b, d], [a, d, c]]
    triangles = np.array(triangles, np.int32)
    normals = -positions / np.linalg.norm(positions, axis=1, keepdims=True)
    return Mesh(name="Sphere", positions=positions, triangles=triangles,
                corner_normals=normals[triangles].astype(np.float32), material_index=np.zeros(len(triangles), np.int32),
                materials=[material], uv_maps={}, bake_uv_map="", resolution=(0, 0), mode="vertex",
                vertex_count=len(positions))


@pytest.mark.parametrize("bounces, expected", [(0, 0.5), (2, 0.875)])
def test_closed_sphere_furnace_is_exact_at_every_vertex(bounces, expected):
    # Inside a closed sphere of albedo 0.5 emitting radiance 1, the reflected light after
    # k bounces is 0.5 + 0.25 + ... (k + 1 terms): exact for any direction set, since
    # the gather weights are normalised and every ray lands on the sphere.
    sphere = inward_sphere(Material(base_color=np.full(3, 0.5), emission=np.ones(3)))
    result = bake(Scene([sphere], []), BakeSettings(directions=64, bounces=bounces))
    colors = result.objects[0].images["lighting"]
    assert result.objects[0].domain == "POINT" and colors.shape == (len(sphere.positions), 4)
    np.testing.assert_allclose(colors[:, :3], expected, rtol=1e-5)
    np.testing.assert_array_equal(colors[:, 3], 1.0)


def test_direct_light_at_vertices_is_the_analytic_value():
    plane = grid_mesh("Plane", segments=6, material=Material(base_color=np.full(3, 0.6)))
    lamp = Light("Lamp", "POINT", np.ones(3), 300.0, position=np.array([0.3, -0.2, 1.5]))
    colors = bake(Scene([plane], [lamp]), BakeSettings(directions=16, bounces=0)).objects[0].images["lighting"]
    offset = lamp.position - plane.positions
    distance = np.linalg.norm(offset, axis=1)
    expected = 0.6 / np.pi * 300.0 / (4 * np.pi) * (offset[:, 2] / distance) / distance ** 2
    # Samples sit 1e-4 towards their triangles' middle (tolerances.VERTEX_SAMPLE_INSET),
    # which moves the inverse-square value by up to ~2e-4 relative here.
    np.testing.assert_allclose(colors[:, 0], expected, rtol=5e-4)


def test_sharp_edges_sample_each_face_at_a_shared_vertex():
    # Two quads meeting at a right angle along x = 0 (a floor and a wall), flat shaded:
    # the two vertices on the edge get one sample per face, and results go per corner.
    floor = quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    wall = quad_mesh("Wall", [(1, -1, 0), (1, 1, 0), (1, 1, 1), (1, -1, 1)])
    positions = np.concatenate([floor.positions, wall.positions[2:]])
    triangles = np.concatenate([floor.triangles, np.array([[2, 1, 4], [2, 4, 5]], np.int32)])
    triangles[2:] = [[1, 2, 4], [1, 4, 5]]
    normals = np.concatenate([floor.corner_normals, np.tile(np.array([-1, 0, 0], np.float32), (2, 3, 1))])
    mesh = Mesh(name="L", positions=positions, triangles=triangles, corner_normals=normals,
                material_index=np.zeros(4, np.int32), materials=[Material()], uv_maps={}, bake_uv_map="",
                resolution=(0, 0), mode="vertex", corner_loops=np.arange(12).reshape(4, 3), vertex_count=6,
                loop_count=12)
    samples = build_vertex_samples(mesh)
    assert samples.domain == "CORNER"
    assert len(samples) == 8  # 6 vertices, the 2 on the edge twice
    assert np.all(samples.element_sample >= 0)
    for triangle in range(4):
        for corner in range(3):
            sample = samples.corner_sample[triangle, corner]
            np.testing.assert_allclose(samples.normal[sample], normals[triangle, corner], atol=1e-6)


def _bounce_scene(reflector_mode, segments=24):
    # A lit floor bounces light onto a ceiling that only the floor lights; the ceiling's
    # indirect light depends on how well the floor's light is looked up where rays land.
    floor = grid_mesh("Floor", size=2.0, segments=segments, material=Material(base_color=np.full(3, 0.8)),
                      mode=reflector_mode, resolution=96)
    ceiling = quad_mesh("Ceiling", [(-1, -1, 1), (-1, 1, 1), (1, 1, 1), (1, -1, 1)],
                        material=Material(base_color=np.full(3, 0.5)), resolution=16)
    spot = Light("Lamp", "POINT", np.ones(3), 400.0, position=np.array([0.6, 0.0, 0.3]))
    return Scene([floor, ceiling], [spot])


def test_interpolated_lookup_beats_nearest_vertex_against_an_atlas_reference():
    settings = BakeSettings(directions=256, bounces=1, passes=("indirect",))
    reference = bake(_bounce_scene("atlas"), settings).objects[1].images["indirect"][..., :3]
    errors = {}
    for lookup in ("interpolate", "nearest"):
        result = bake(_bounce_scene("vertex"), BakeSettings(directions=256, bounces=1, passes=("indirect",),
                                                           vertex_lookup=lookup))
        ceiling = result.objects[1].images["indirect"][..., :3]
        errors[lookup] = float(np.sqrt(np.mean((ceiling - reference) ** 2)) / np.sqrt(np.mean(reference ** 2)))
    print(f"\nceiling lit by a vertex-mode floor (24 x 24 quads) against an atlas floor: "
          f"interpolated {errors['interpolate']:.4f}, nearest vertex {errors['nearest']:.4f}")
    assert errors["interpolate"] < errors["nearest"]
    assert errors["interpolate"] < 0.05


def test_vertex_tables_are_cached_and_updated_like_atlas_tables(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    # A rotated set: an unrotated one has directions in the plane y = 0, and rays from
    # the floor's edge at y = 1 then graze the ceiling's edge exactly, where embree's
    # answer depends on the BVH it traverses (the update's and a fresh trace's differ).
    settings = BakeSettings(directions=48, bounces=1, rotate=True, seed=3)
    first = prepare(_bounce_scene("vertex", segments=8), settings, cache=cache, table_needed=True)
    assert first.table.vertex_cells is not None
    again = prepare(_bounce_scene("vertex", segments=8), settings, cache=cache, table_needed=True)
    assert again.cache_status.state == "hit"
    np.testing.assert_array_equal(first.table.vertex_cells, again.table.vertex_cells)
    np.testing.assert_array_equal(first.table.hit_uv_code, again.table.hit_uv_code)
    moved = _bounce_scene("vertex", segments=8)
    moved.meshes[1].positions = moved.meshes[1].positions + [0.0, 0.0, 0.2]
    updated = prepare(moved, settings, cache=cache, table_needed=True)
    assert updated.cache_status.state == "updated"
    fresh = prepare(moved, settings, table_needed=True)
    for name in ("hit_object", "hit_uv_code", "hit_distance_code", "vertex_cells"):
        np.testing.assert_array_equal(getattr(updated.table, name), getattr(fresh.table, name), err_msg=name)
    lights = moved.lights
    a, b = relight(updated, lights, World()), relight(fresh, lights, World())
    for x, y in zip(a.objects, b.objects):
        np.testing.assert_array_equal(x.images["lighting"], y.images["lighting"])


def test_a_convex_mesh_does_not_shadow_its_own_vertices():
    # An outward sphere under a sun: every vertex facing the sun is lit by exactly
    # rho * S * cos / pi. A sample nudged behind its own faces (the mean of its
    # triangles' middles lies inside a convex mesh) would be black instead.
    sphere = inward_sphere(Material(base_color=np.full(3, 0.5)))
    sphere.triangles = sphere.triangles[:, ::-1].copy()
    sphere.corner_normals = -sphere.corner_normals[:, ::-1]
    sun = Light("Sun", "SUN", np.ones(3), 2.0, direction=np.array([0.0, 0.0, -1.0]))
    colors = bake(Scene([sphere], [sun]), BakeSettings(directions=16, bounces=0)).objects[0].images["lighting"]
    up = sphere.positions[:, 2] / np.linalg.norm(sphere.positions, axis=1)
    lit = up > 0.05
    np.testing.assert_allclose(colors[lit, 0], 0.5 * 2.0 * up[lit] / np.pi, rtol=1e-3)
    assert np.all(colors[up < -0.05, 0] == 0)


def test_a_shadow_edge_inside_large_triangles_is_reported():
    # A spot light's cone edge crosses the middle of a 2 x 2 quad plane: the corners
    # see nothing of the light its middle gets. Finely tessellated, nothing is flagged.
    spot = Light("Spot", "SPOT", np.ones(3), 500.0, position=np.array([0.0, 0.0, 1.0]),
                 direction=np.array([0.0, 0.0, -1.0]), spot_size=np.radians(90), spot_blend=0.0)
    coarse = bake(Scene([grid_mesh("Coarse", segments=1)], [spot]), BakeSettings(directions=16, bounces=0))
    entry = coarse.report["objects"][0]
    assert entry["under_tessellated_triangles"] == 2 and entry["under_tessellated_area_share"] == 1.0
    assert any("which its vertices cannot show" in w for w in coarse.report["warnings"])
    fine = bake(Scene([grid_mesh("Fine", segments=64)], [spot]), BakeSettings(directions=16, bounces=0))
    entry = fine.report["objects"][0]
    assert entry["under_tessellated_area_share"] < 0.1


def test_world_light_and_shadow_fractions_reach_vertex_samples():
    # An open plane under a uniform sky of radiance L: E = pi L at every vertex, so the
    # lighting is rho * L (the gather through misses, normalised weights: exact).
    plane = grid_mesh("Plane", segments=4, material=Material(base_color=np.full(3, 0.5)))
    lit = bake(Scene([plane], [], World(np.full(3, 2.0))), BakeSettings(directions=64, bounces=1))
    np.testing.assert_allclose(lit.objects[0].images["lighting"][:, :3], 1.0, rtol=1e-5)
    # Shadow fractions are looked up per vertex like per texel: under a roof, the
    # fractions' soft shadow and the exact one darken the same vertices on average.
    roof = quad_mesh("Roof", [(-0.5, -0.5, 0.5), (-0.5, 0.5, 0.5), (0.5, 0.5, 0.5), (0.5, -0.5, 0.5)],
                     resolution=8)
    sun = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.0, 0.0, -1.0]))
    means = {}
    for shadows in ("exact", "fractions"):
        result = bake(Scene([grid_mesh("Plane", segments=16), roof], [sun]),
                      BakeSettings(directions=128, bounces=0, shadows=shadows))
        means[shadows] = float(result.objects[0].images["lighting"][:, 0].mean())
    unshadowed = 0.8 * 3.0 / np.pi
    assert means["exact"] < 0.95 * unshadowed and means["fractions"] < 0.95 * unshadowed
    assert means["fractions"] == pytest.approx(means["exact"], rel=0.25)


def test_the_lighting_cache_tells_the_vertex_lookups_apart(tmp_path):
    cache = VisibilityCache(str(tmp_path))
    results = {}
    for lookup in ("interpolate", "nearest", "interpolate"):
        settings = BakeSettings(directions=64, bounces=1, passes=("indirect",), vertex_lookup=lookup)
        scene = _bounce_scene("vertex", segments=6)
        result = relight(prepare(scene, settings, cache=cache), scene.lights, World())
        results.setdefault(lookup, []).append(result)
    # The second lookup is transported anew (its gathers differ), the third read back.
    assert results["nearest"][0].report["cache"]["lighting_reused"] == []
    assert results["interpolate"][1].report["cache"]["lighting_reused"] == ["all"]
    ceiling = {k: v[0].objects[1].images["indirect"] for k, v in results.items()}
    assert np.any(ceiling["nearest"] != ceiling["interpolate"])


def test_a_cached_table_coding_vertex_hits_for_other_meshes_is_rebuilt(tmp_path):
    from core.visibility import cache as cache_module

    cache = VisibilityCache(str(tmp_path))
    settings = BakeSettings(directions=16, bounces=1)
    first = prepare(_bounce_scene("vertex", segments=4), settings, cache=cache, table_needed=True)
    path = first.cache_status.path
    meta = cache_module._read_meta(path, "table")
    arrays = cache_module._read_arrays(path, meta, meta["arrays"])
    assert arrays["vertex_cells"].max() > 0
    arrays["vertex_cells"] = arrays["vertex_cells"] + (arrays["vertex_cells"] > 0)  # valid checksums, other grid
    cache_module._write(path, {k: v for k, v in meta.items() if k != "digests"}, arrays)
    again = prepare(_bounce_scene("vertex", segments=4), settings, cache=cache, table_needed=True)
    assert again.cache_status.state == "corrupt" and "vertex-mode hits" in again.cache_status.message
    np.testing.assert_array_equal(again.table.hit_uv_code, first.table.hit_uv_code)
    np.testing.assert_array_equal(again.table.vertex_cells, first.table.vertex_cells)
