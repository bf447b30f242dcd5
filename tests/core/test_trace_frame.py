"""Tracing far from the world origin: the ray scene is centred on the geometry (prepare.trace_frame)."""
import dataclasses

import numpy as np
import pytest

from core.pipeline.prepare import PRECISION_EXTENT_RATIO, prepare, trace_frame
from core.pipeline.relight import bake
from core.scene import Light, Material, Scene
from core.settings import BakeSettings
from core.visibility.cache import VisibilityCache
from core.visibility.rays import RayScene
from core_scenes import box_interior, quad_mesh


def _scene(offset, mode="atlas"):
    """A box interior lit by a point lamp inside it, and a plate over its floor, moved by ``offset``."""
    shift = np.full(3, offset)
    box = box_interior(1.0, Material(base_color=np.full(3, 0.6)), resolution=24)
    plate = quad_mesh("Plate", [(-0.2, -0.2, -0.3), (0.2, -0.2, -0.3), (0.2, 0.2, -0.3), (-0.2, 0.2, -0.3)],
                      resolution=8)
    meshes = [dataclasses.replace(m, positions=m.positions + shift, mode=mode) for m in (box, plate)]
    lamp = Light("Lamp", "POINT", np.ones(3), 40.0, position=np.array([0.1, 0.05, 0.2]) + shift)
    return Scene(meshes=meshes, lights=[lamp])


def test_a_scene_near_the_origin_keeps_the_world_frame():
    centre, warning = trace_frame(_scene(0.0).meshes)
    np.testing.assert_array_equal(centre, 0.0)
    assert warning is None


@pytest.mark.parametrize("mode", ["atlas", "vertex"])
@pytest.mark.parametrize("offset", [1e3, 1e5, 1e6])
def test_lighting_far_from_the_origin_equals_the_lighting_at_it(offset, mode):
    settings = BakeSettings(directions=48, bounces=1, shadows="exact", passes=("lighting",), rotate=False)
    near = bake(_scene(0.0, mode), settings)
    far = bake(_scene(offset, mode), settings)
    centre, warning = trace_frame(_scene(offset, mode).meshes)
    # The centre is a multiple of a power of two above the scene's size, so the scene's
    # coordinates in that frame are those at the origin, to the last bit.
    np.testing.assert_array_equal(centre, offset)
    assert warning is None
    for a, b in zip(near.objects, far.objects):
        np.testing.assert_allclose(b.images["lighting"], a.images["lighting"], rtol=1e-5, atol=1e-6)


def test_recentred_origins_give_the_hits_of_the_same_scene_at_the_origin():
    box = box_interior(1.0)
    offset = np.array([3e5, -2e5, 1e5])
    near = RayScene([(box.positions, box.triangles)])
    far = RayScene([(box.positions + offset, box.triangles)], centre=offset)
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.4, 0.4, (500, 3))
    points[:, 2] = -0.5
    normals = np.tile([0.0, 0.0, 1.0], (500, 1))
    directions = rng.normal(size=(500, 3))
    directions[:, 2] = np.abs(directions[:, 2])
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    hits_near = near.intersect(near.ray_origins(points, normals), directions)
    hits_far = far.intersect(far.ray_origins(points + offset, normals), directions)
    # The sample points themselves round when moved out (float64 steps of 6e-11 at 3e5).
    np.testing.assert_array_equal(hits_far[0], hits_near[0])
    np.testing.assert_array_equal(hits_far[1], hits_near[1])
    np.testing.assert_allclose(hits_far[2], hits_near[2], atol=1e-6)
    np.testing.assert_allclose(hits_far[3], hits_near[3], rtol=1e-6)
    # Without the centre, float32 positions at 3e5 step by 1/32: hits land elsewhere.
    plain = RayScene([(box.positions + offset, box.triangles)])
    distance_plain = plain.intersect(plain.ray_origins(points + offset, normals), directions)[3]
    assert np.max(np.abs(distance_plain - hits_near[3])) > 1e-3


def test_the_cache_recognises_a_far_scene_and_its_moved_objects(tmp_path):
    settings = BakeSettings(directions=32, bounces=1, shadows="exact", passes=("lighting",), rotate=False)
    cache = VisibilityCache(str(tmp_path), "far")
    first = prepare(_scene(1e5), settings, table_needed=True, cache=cache)
    assert first.cache_status.state == "miss"
    again = prepare(_scene(1e5), settings, table_needed=True, cache=cache)
    assert again.cache_status.state == "hit"
    # Moved by a millimetre, 1e5 units out: a different scene, so no false hit.
    moved = _scene(1e5)
    moved.meshes[1].positions = moved.meshes[1].positions + [0.0, 0.0, 1e-3]
    assert prepare(moved, settings, table_needed=True, cache=cache).cache_status.state == "updated"


def test_a_scene_float32_cannot_resolve_says_so():
    scene = _scene(0.0)
    tiny = dataclasses.replace(scene.meshes[1], positions=scene.meshes[1].positions * 1e-4)
    far = dataclasses.replace(scene.meshes[0], positions=scene.meshes[0].positions * 1e2 + 1e3, output=False)
    _, warning = trace_frame([far, tiny])
    assert warning is not None and warning.startswith("precision:")
    assert f"{PRECISION_EXTENT_RATIO:.0e}" in warning


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_bounds_column_by_column_are_the_finite_rows_bounds(dtype):
    """trace_frame's bounds (prepare._finite_bounds, reduced column by column) are those of the
    finite rows reduced along the first axis, in the positions' own dtype; None without any."""
    from core.pipeline.prepare import _finite_bounds
    rng = np.random.default_rng(9)
    positions = (rng.normal(size=(5000, 3)) * [1.0, 30.0, 1e-3] + [1e4, -2.0, 0.5]).astype(dtype)
    low, high = _finite_bounds(positions)
    assert low.dtype == dtype and high.dtype == dtype
    np.testing.assert_array_equal(low, positions.min(axis=0))
    np.testing.assert_array_equal(high, positions.max(axis=0))
    spoiled = positions.copy()
    spoiled[[3, 70, 4000], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    finite = spoiled[np.all(np.isfinite(spoiled), axis=1)]
    low, high = _finite_bounds(spoiled)
    np.testing.assert_array_equal(low, finite.min(axis=0))
    np.testing.assert_array_equal(high, finite.max(axis=0))
    assert _finite_bounds(np.full((4, 3), np.nan, dtype)) is None
    assert _finite_bounds(np.zeros((0, 3), dtype)) is None
