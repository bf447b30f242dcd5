import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.visibility import rays
from core.visibility.rays import RayScene, offset_ray_origins, run_in_spans, run_together


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


def _random_rays(rng, count, scale):
    origins = rng.normal(scale=scale, size=(count, 3)).astype(np.float32)
    directions = rng.normal(size=(count, 3)).astype(np.float32)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return origins, directions


def test_meshes_attached_where_they_lie_answer_bitwise_as_embreex_s_copies(monkeypatch):
    """RayScene hands embree its arrays without embreex's copy (core.visibility.embree_shared),
    where the pinned embreex's layout proves itself: on this platform it must, and every query
    (nearest hits, their barycentrics and distances, occlusion, several meshes' ids, a NaN vertex,
    a degenerate triangle, an empty mesh) answers bitwise as with embreex's copy."""
    from core.visibility import embree_shared

    assert embree_shared.available()
    rng = np.random.default_rng(9)
    positions = rng.normal(size=(500, 3)) + [4.0, 0.0, 0.0]  # beside the rays' origins, between the planes
    positions[7] = np.nan
    triangles = rng.integers(0, len(positions), size=(2000, 3)).astype(np.int32)
    triangles[3] = [5, 5, 9]
    meshes = [(positions, triangles), *(_plane(z, 1.5) for z in (-1.0, 1.0)),
              (np.zeros((0, 3)), np.zeros((0, 3), np.int32))]
    origins, directions = _random_rays(rng, 20000, 0.3)
    limits = rng.uniform(0.1, 3.0, len(origins))
    attached = []
    real_attach = embree_shared.attach
    monkeypatch.setattr(embree_shared, "attach", lambda *args: attached.append(real_attach(*args)) or attached[-1])
    shared = RayScene(meshes, threads=2)
    assert attached == [0, 1, 2, 3]  # geometry ids in mesh order
    monkeypatch.setattr(embree_shared, "attach", lambda *args: None)
    copied = RayScene(meshes, threads=2)
    ours, theirs = shared.intersect(origins, directions), copied.intersect(origins, directions)
    assert len(np.unique(ours[0])) == 4  # misses and the three meshes with area
    for a, b in zip(ours, theirs):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(shared.occluded(origins, directions, limits),
                                  copied.occluded(origins, directions, limits))
    np.testing.assert_array_equal(shared.positions(1), copied.positions(1))


def test_a_scene_whose_fields_do_not_prove_themselves_is_not_attached_to():
    """The scene's handle is read only where the embreex objects are the ones made together
    (embree_shared.new_scene) and the vertices are padded for embree's 16-byte reads; else
    nothing is attached and RayScene uses embreex's copy."""
    from embreex.rtcore import EmbreeDevice

    from core.visibility import embree_shared

    scene, device = embree_shared.new_scene()
    vertices = embree_shared.padded_vertices(np.eye(3, dtype=np.float32))
    triangles = np.array([[0, 1, 2]], np.int32)
    assert embree_shared.attach(scene, EmbreeDevice(), vertices, triangles) is None
    assert embree_shared.attach(scene, device, np.eye(3, dtype=np.float32), triangles) is None  # not padded
    assert embree_shared.attach(scene, device, vertices, triangles.astype(np.int64)) is None
    assert embree_shared.attach(scene, device, vertices, triangles) == 0
    found = scene.run(np.array([[0.2, 0.2, 0.2]], np.float32), np.full((1, 3), 1 / np.sqrt(3), np.float32),
                      output=1)
    assert found["geomID"][0] == 0 and found["primID"][0] == 0


def test_calls_run_together_return_in_order_the_first_on_the_calling_thread():
    seen = []

    def call(i):
        seen.append((i, threading.current_thread().name))
        time.sleep(0.01)
        return i * i

    results = run_together([lambda i=i: call(i) for i in range(4)])
    assert results == [0, 1, 4, 9]
    names = dict(seen)
    assert names[0] == threading.current_thread().name
    assert all(names[i].startswith("visibake-helper") for i in (1, 2, 3))
    # The helpers are kept: a second batch runs on the same threads. (The pool may still start
    # the one it did not need the first time: a helper that has just set its result is not idle
    # yet, and a loaded machine reaches the second batch in that window. Never more than three.)
    pool = rays._helpers
    run_together([lambda i=i: call(i) for i in range(4)])
    assert rays._helpers is pool
    assert len({t.ident for t in threading.enumerate() if t.name.startswith("visibake-helper")}) <= 3


def test_an_error_is_raised_once_every_call_has_ended():
    finished = []

    def slow(i):
        time.sleep(0.05)
        finished.append(i)

    def fails():
        raise ValueError("helper failed")

    with pytest.raises(ValueError, match="helper failed"):
        run_together([lambda: slow(0), fails, lambda: slow(2)])
    assert sorted(finished) == [0, 2]
    with pytest.raises(KeyError):
        run_together([lambda: (_ for _ in ()).throw(KeyError("caller failed")), lambda: slow(1)])
    assert 1 in finished


def test_a_call_on_a_helper_runs_its_own_calls_there_without_waiting_for_another_helper():
    def nested(i):
        on_helper = threading.current_thread().name.startswith("visibake-helper")
        inner = run_together([lambda j=j: (threading.current_thread().name, i * 10 + j) for j in range(3)])
        if on_helper:
            assert {name for name, _ in inner} == {threading.current_thread().name}
        return [value for _, value in inner]

    results = run_together([lambda i=i: nested(i) for i in range(3)])
    assert results == [[0, 1, 2], [10, 11, 12], [20, 21, 22]]


def test_threads_calling_at_once_with_growing_batches_each_get_their_own_results():
    errors, outputs = [], {}

    def caller(who):
        try:
            for round_ in range(60):
                size = 2 + (who + round_) % 4  # the pool grows while others use it
                outputs.setdefault(who, []).append(
                    run_together([lambda k=k: (who, round_, k) for k in range(size)]) ==
                    [(who, round_, k) for k in range(size)])
        except BaseException as error:  # noqa: BLE001 - the test reports any failure
            errors.append(error)

    threads = [threading.Thread(target=caller, args=(who,)) for who in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert not errors
    assert all(all(ok) and len(ok) == 60 for ok in outputs.values()) and len(outputs) == 4
    rays.stop_helpers()
    assert run_together([lambda: 1, lambda: 2]) == [1, 2]


def test_spans_cover_every_item_once():
    hits = np.zeros(20_000, np.int32)

    def mark(a, b):
        hits[a:b] += 1

    run_in_spans(mark, len(hits), 4)
    assert np.all(hits == 1)
    run_in_spans(mark, 10, 4)  # one span: on the calling thread
    assert np.all(hits[:10] == 2)
