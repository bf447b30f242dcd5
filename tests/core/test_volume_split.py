"""Scale-out (issue 20): a medium's scattering tables built and read by ranges of active voxels
(core.distributed.volume_rows) give the same light as the whole tables, bit for bit: the
bounces, the world's light, a lamp, the medium's emission, and the light meshes reflect."""
from __future__ import annotations

import numpy as np
import pytest

from core import kernels
from core.distributed.volume_rows import InProcessVolumeRows, SplitVolumeTables, VolumeSetup, split_tables
from core.scene import Light, World
from core.visibility.directions import direction_set
from core.volume import tables, transport
from core.volume.medium import make_medium
from core.volume.occluders import Occluders

pytestmark = pytest.mark.skipif(kernels.compiled() is None,
                                reason=f"numba kernels unavailable here: {kernels.status().reason}")

N = 12
TO_WORLD = np.diag([0.1, 0.1, 0.1, 1.0])


def _medium():
    rng = np.random.default_rng(4)
    density = rng.uniform(0.0, 2.0, (N, N, N))
    density[density < 0.5] = 0.0  # a sparse medium: voxel ranges do not follow the grid's rows
    emission = np.zeros((N, N, N, 3))
    emission[5:7, 5:7, 5:7] = (2.0, 1.0, 0.5)
    return make_medium("cloud", density, TO_WORLD, extinction=3.0, albedo=(0.8, 0.7, 0.6), emission=emission)


def _floor():
    positions = np.array([[-1.0, -1.0, -0.05], [2.0, -1.0, -0.05], [2.0, 2.0, -0.05], [-1.0, 2.0, -0.05]])
    return positions, np.array([[0, 1, 2], [0, 2, 3]], np.int32), True, True, np.full((2, 3), 0.7), None


@pytest.mark.parametrize("with_floor", [False, True])
def test_the_light_of_voxel_ranges_equals_the_whole_tables_bitwise(with_floor):
    medium = _medium()
    directions = direction_set(32, rotate=True, seed=2)
    meshes = [_floor()] if with_floor else []
    occluders = Occluders.from_meshes(meshes) if meshes else None
    lights = [Light("lamp", "POINT", np.ones(3), 30.0, position=np.array([0.6, 0.5, 1.6]))]
    world = World(color=np.array([0.2, 0.3, 0.5]))
    whole_tables = tables.build_tables(medium, directions, points=2, jitter_seed=5, occluders=occluders)
    whole = transport.light_medium(medium, whole_tables, lights, world, bounces=2, occluders=occluders)
    assert np.any(whole.indirect > 0) and np.any(whole.direct > 0)
    setup = VolumeSetup.of(medium, directions, 2, tables.STEP, 5, meshes)
    for parts in (1, 3, 7):
        split = split_tables(InProcessVolumeRows(setup, parts), setup)
        assert isinstance(split, SplitVolumeTables) and split.nbytes == whole_tables.nbytes
        assert (split.sees_world is None) == (whole_tables.sees_world is None)
        light = transport.light_medium(medium, split, lights, world, bounces=2, occluders=occluders)
        assert np.array_equal(light.direct, whole.direct), parts
        assert np.array_equal(light.indirect, whole.indirect), parts


def test_the_tables_of_voxel_ranges_join_to_the_whole_tables():
    medium = _medium()
    directions = direction_set(16, rotate=True, seed=1)
    whole = tables.build_tables(medium, directions, points=3, jitter_seed=9)
    count = len(medium.active())
    cuts = [0, count // 3, count // 3 + 1, count]
    parts = [tables.build_tables(medium, directions, points=3, jitter_seed=9, voxel_range=range(a, b))
             for a, b in zip(cuts[:-1], cuts[1:])]
    assert np.array_equal(np.concatenate([p.voxels for p in parts]), whole.voxels)
    assert np.array_equal(np.concatenate([p.distance_codes for p in parts], axis=1), whole.distance_codes)
    assert np.array_equal(np.concatenate([p.escape_codes for p in parts], axis=1), whole.escape_codes)
