"""A volume's scattering tables in the visibility cache (core.volume.cache)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from core import kernels
from core.visibility.cache import VOLUME_TABLE_FILE, VisibilityCache
from core.visibility.directions import direction_set
from core.volume import cache as volume_cache
from core.volume import tables
from core.volume.medium import make_medium
from core.volume.occluders import Occluders

pytestmark = pytest.mark.skipif(kernels.compiled() is None,
                                reason=f"numba kernels unavailable here: {kernels.status().reason}")

TO_WORLD = np.diag([0.1, 0.1, 0.1, 1.0])
WALL = [(np.array([[0.55, -5.0, -5.0], [0.55, 5.0, -5.0], [0.55, 5.0, 5.0], [0.55, -5.0, 5.0]]),
         np.array([[0, 1, 2], [0, 2, 3]], np.int32), True)]


def cloud(seed=4):
    return make_medium("cloud", np.random.default_rng(seed).uniform(0.0, 2.0, (10, 9, 8)), TO_WORLD, extinction=3.0)


def fetch(cache, medium, directions, meshes, built: list, warnings=None):
    def build():
        built.append(1)
        return tables.build_tables(medium, directions, points=2, jitter_seed=3,
                                   occluders=Occluders.from_meshes(meshes))
    return volume_cache.cached_tables(cache, "cloud", medium, directions, 2, 0.5, 3, meshes, build,
                                      [] if warnings is None else warnings)


def test_a_second_bake_reads_the_same_tables_and_a_changed_medium_or_mesh_builds_them_again(tmp_path):
    cache = VisibilityCache(str(tmp_path), "scene")
    medium, directions, built = cloud(), direction_set(8, rotate=True, seed=1), []
    first, how = fetch(cache, medium, directions, WALL, built)
    assert how == "built" and len(built) == 1
    again, how = fetch(cache, medium, directions, WALL, built)
    assert how == "cached" and len(built) == 1
    for name in ("distance_codes", "escape_codes", "voxels", "index_directions", "sees_world"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    assert again.distance_per_code == first.distance_per_code and again.jitter_seed == 3
    assert not again.sees_world.all()  # the wall is in the stored flags

    _, how = fetch(cache, cloud(seed=5), directions, WALL, built)
    assert how == "built" and len(built) == 2
    moved = [(WALL[0][0] + [0.1, 0.0, 0.0], WALL[0][1], True)]
    _, how = fetch(cache, cloud(seed=5), directions, moved, built)
    assert how == "built" and len(built) == 3
    _, how = fetch(cache, cloud(seed=5), directions, moved, built)
    assert how == "cached" and len(built) == 3


def test_a_damaged_file_is_reported_and_rebuilt(tmp_path):
    cache = VisibilityCache(str(tmp_path), "scene")
    medium, directions, built = cloud(), direction_set(8, rotate=True, seed=1), []
    fetch(cache, medium, directions, [], built)
    [path] = [os.path.join(root, name) for root, _, names in os.walk(tmp_path) for name in names
              if name == VOLUME_TABLE_FILE]
    data = bytearray(open(path, "rb").read())
    data[len(data) // 2] ^= 0xFF
    open(path, "wb").write(bytes(data))
    warnings = []
    rebuilt, how = fetch(cache, medium, directions, [], built, warnings)
    assert how == "built" and len(built) == 2
    assert any("cached scattering tables were not used" in line for line in warnings)
    assert fetch(cache, medium, directions, [], built)[1] == "cached"
    assert rebuilt.sees_world is None


def test_no_cache_builds_every_time():
    built = []
    assert fetch(None, cloud(), direction_set(8), [], built)[1] == "built"
    assert fetch(None, cloud(), direction_set(8), [], built)[1] == "built" and len(built) == 2
