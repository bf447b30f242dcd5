import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.visibility.rays import RayScene, offset_ray_origins


def _plane(z, size, centre=(0.0, 0.0)):
    cx, cy = centre
    positions = np.array([[cx - size, cy - size, z], [cx + size, cy - size, z],
                          [cx + size, cy + size, z], [cx - size, cy + size, z]])
    return positions, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


@given(st.floats(min_value=-1e5, max_value=1e5, allow_nan=False),
       st.floats(min_value=-1e5, max_value=1e5, allow_nan=False),
       st.floats(min_value=-1e5, max_value=1e5, allow_nan=False))
@settings(max_examples=200, deadline=None)
def test_offset_moves_to_the_normal_side(x, y, z):
    p = np.array([[x, y, z]])
    for n in (np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]]), np.array([[0.6, 0.0, 0.8]])):
        o = offset_ray_origins(p, n)
        p32 = p.astype(np.float32).astype(np.float64)
        moved = (o.astype(np.float64) - p32) @ n[0]
        assert moved[0] > 0
        assert np.all(np.isfinite(o))


@pytest.mark.parametrize("distance", [0.0, 1.0, 1e2, 1e4, 1e5])
def test_no_self_hits_far_from_origin(distance):
    # A plane far from the world origin: rays leaving it upwards must never hit it.
    positions, triangles = _plane(distance, 10.0, centre=(distance, -distance))
    scene = RayScene([(positions, triangles)])
    rng = np.random.default_rng(0)
    count = 20000
    xy = rng.uniform(-9.0, 9.0, size=(count, 2)) + [distance, -distance]
    points = np.column_stack([xy, np.full(count, distance)])
    normals = np.tile([0.0, 0.0, 1.0], (count, 1))
    dirs = rng.normal(size=(count, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 1e-3
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    geometry, _, _, _ = scene.intersect(offset_ray_origins(points, normals), dirs)
    assert np.count_nonzero(geometry >= 0) == 0


def test_intersect_and_occluded_agree_with_geometry():
    ground = _plane(0.0, 1.0)
    roof = _plane(1.0, 0.25)
    scene = RayScene([ground, roof])
    origins = np.array([[0.0, 0.0, 0.5], [0.9, 0.9, 0.5], [0.0, 0.0, 0.5]])
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    geometry, triangle, bary, distance = scene.intersect(origins, dirs)
    np.testing.assert_allclose(distance[[0, 2]], [0.5, 0.5], rtol=1e-6)
    assert np.isinf(distance[1])
    assert list(geometry) == [1, -1, 0]
    assert list(scene.occluded(origins, dirs)) == [True, False, True]
    # A bounded shadow ray stops short of the roof.
    assert list(scene.occluded(origins, dirs, np.array([0.4, 10.0, 0.4]))) == [False, False, False]


def test_empty_and_degenerate_meshes_are_never_hit():
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    degenerate = (np.array([[0, 0, 1.0], [1, 0, 1.0], [2, 0, 1.0]]), np.array([[0, 1, 2]], np.int32))
    nan = (np.array([[np.nan, 0, 1.0], [1, 0, 1.0], [0, 1, 1.0]]), np.array([[0, 1, 2]], np.int32))
    scene = RayScene([empty, degenerate, nan])
    geometry, _, _, _ = scene.intersect(np.array([[0.5, 0.0, 0.0], [0.2, 0.2, 0.0]]),
                                        np.array([[0, 0, 1.0], [0, 0, 1.0]]))
    assert list(geometry) == [-1, -1]


def test_meshes_given_to_embree_as_python_objects_are_the_arrays_own():
    """RayScene hands embreex its arrays as Python objects (core.visibility.rays._triangle_mesh):
    embree must hold exactly the geometry the arrays say, NaN vertex and degenerate triangle
    included, so every hit equals that of the arrays given as they are."""
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    from core.visibility import rays

    rng = np.random.default_rng(4)
    positions = rng.normal(size=(500, 3)).astype(np.float32)
    positions[7] = np.nan
    triangles = rng.integers(0, len(positions), size=(2000, 3)).astype(np.int32)
    triangles[3] = [5, 5, 9]
    origins = rng.normal(scale=0.2, size=(20000, 3)).astype(np.float32)
    directions = rng.normal(size=(20000, 3)).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    hits = []
    for build in (lambda scene: TriangleMesh(scene, positions, triangles),
                  lambda scene: rays._triangle_mesh(TriangleMesh, scene, positions, triangles)):
        scene = EmbreeScene()
        build(scene)
        hits.append(scene.run(origins, directions, output=1))
    assert (hits[0]["geomID"] >= 0).sum() > 1000
    for key in ("geomID", "primID", "u", "v", "tfar"):
        np.testing.assert_array_equal(hits[0][key], hits[1][key])
