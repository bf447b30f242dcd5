"""The GPU volume slice sweep (gpu_shaders.volume_sweep) against the numba kernel
(core.kernels.volume_kernels.sweep_transmittance), through core.volume.direct.transmittance.

Tolerance: both sweep the same slices with the same arithmetic and the same decisions
(the GPU pass takes which voxels each sweep writes, and which branch, from the kernel's
own float64 tests, evaluated on the CPU); the GPU carries the value in float32, the kernel in float64. Each slice
adds a few float32 roundings relative to the transmittance (the segment, exp, the bilinear
read, the product or the mean extinction; about 1e-7 each), which the bilinear reads
average rather than amplify, so over the at most 64 slices here the difference stays
below ~2e-5 even if every rounding went the same way; a GPU's exp may be a few ulp less
exact than llvmpipe's. An absolute 1e-4 bounds that with room, and every mistake of
index, bound, border, branch or selection changes transmittances in these dense clouds
by 1e-2 or more. In the shadows (T < 1/2), down to transmittances of 1e-18 where 1e-4
says nothing, the optical depths (-log T) must agree to 1e-4 relative: float32 keeps
~1e-7 of them per slice (llvmpipe: at most 1e-5 here, and 4e-6 absolute in T).

Grids are non-cubic (no two sides equal), so rows, columns and slices cannot be mixed
up unnoticed, and every cloud casts real shadows (transmittance well below 1/2).
"""
import importlib

import numpy as np
import pytest

ATOL = 1e-4
DEPTH_RTOL = 1e-4
SHAPE = (21, 17, 24)


def _smooth_cloud(shape, seed):
    """A cloud of a few Gaussian blobs (tests/core/test_volume.py's smooth_density, any shape)."""
    rng = np.random.default_rng(seed)
    cells = np.indices(shape).reshape(3, -1).T.astype(np.float64)
    sides = np.array(shape, np.float64)
    density = np.zeros(len(cells))
    for _ in range(5):
        centre = rng.uniform(0.25, 0.75, 3) * sides
        width = rng.uniform(0.1, 0.2) * sides.mean()
        density += rng.uniform(0.5, 1.5) * np.exp(-np.sum((cells - centre) ** 2, axis=1) / (2 * width * width))
    density[density < 0.05] = 0.0
    return density.reshape(shape).astype(np.float32)


def _rotation(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                     [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                     [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]])


def _index_to_world(kind):
    """Anisotropic voxels, axis-aligned or rotated (and moved off the origin)."""
    scale = np.diag([0.05, 0.07, 0.04])
    matrix = np.eye(4)
    if kind == "aligned":
        matrix[:3, :3] = scale
    else:
        matrix[:3, :3] = _rotation([0.4, -0.3, 1.0], 0.6) @ scale
        matrix[:3, 3] = [0.3, -0.2, 0.15]
    return matrix


def _unit(vector):
    vector = np.asarray(vector, np.float64)
    return vector / np.linalg.norm(vector)


# Suns by the direction they shine in; lamps by a point in index space (fractions of the grid).
SUNS = {"+x": [1, 0, 0], "-x": [-1, 0, 0], "+y": [0, 1, 0], "-y": [0, -1, 0], "+z": [0, 0, 1], "-z": [0, 0, -1],
        "oblique": [0.3, 0.5, -0.8],
        # Offsets across the slices of almost a voxel per slice, on two axes at once.
        "steep oblique": [-0.7, 0.62, 0.55]}


def _lamp_index(kind, shape):
    """Where a lamp of ``kind`` sits in index space."""
    sides = np.array(shape, np.float64)
    if kind == "inside":
        return np.array([0.43, 0.58, 0.37]) * sides + np.array([0.13, -0.21, 0.29])
    if kind == "outside":
        return np.array([1.6, -0.4, 0.55]) * sides
    centre = np.floor(np.array([0.5, 0.4, 0.6]) * sides)
    if kind == "near a voxel centre":
        return centre + np.array([0.3, -0.25, 0.2])
    # Exactly at a voxel centre: a ray of length 0, and voxels exactly on the pyramids'
    # diagonals, which two sweeps claim.
    return centre


LAMPS = ("inside", "outside", "near a voxel centre", "at a voxel centre")


def _core(visibake, name):
    """A module of the installed extension's core (its volume modules load on first use)."""
    return importlib.import_module(f"{visibake.__name__}.core.{name}")


@pytest.fixture(scope="module")
def volume_sweep(gpu_shaders, visibake):
    return importlib.import_module(f"{visibake.__name__}.gpu_shaders.volume_sweep")


def _medium(visibake, transform, shape=SHAPE, seed=5, extinction=12.0):
    make_medium = _core(visibake, "volume.medium").make_medium
    return make_medium("cloud", _smooth_cloud(shape, seed), _index_to_world(transform), extinction=extinction)


def _light(visibake, kind, medium):
    Light = _core(visibake, "scene").Light
    if kind in SUNS:
        return Light("sun", "SUN", np.ones(3), 3.0, direction=_unit(SUNS[kind]))
    position = medium.world_positions(_lamp_index(kind, medium.shape)[None].astype(np.float64))[0]
    return Light("lamp", "POINT", np.ones(3), 100.0, position=position)


def _compare(visibake, volume_sweep, medium, light, label):
    """GPU and CPU transmittance of ``light`` through ``medium``; asserts they agree."""
    direct = _core(visibake, "volume.direct")
    calls = []

    def gpu_pass(*arguments):
        calls.append((int(arguments[7][0]), bool(arguments[6])))  # (sweep axis, flipped)
        volume_sweep.sweep_transmittance(*arguments)

    ours = direct.transmittance(medium, light, sweep_pass=gpu_pass)
    twin = direct.transmittance(medium, light)
    assert ours.shape == twin.shape == medium.shape and ours.dtype == np.float32
    assert twin.min() < 0.5, f"{label}: no real shadow to get right ({twin.min()})"
    np.testing.assert_allclose(ours, twin, rtol=0, atol=ATOL, err_msg=label)
    deep = (twin < 0.5) & (twin > 1e-30)
    depth_ours, depth_twin = -np.log(ours[deep].astype(np.float64)), -np.log(twin[deep].astype(np.float64))
    np.testing.assert_allclose(depth_ours, depth_twin, rtol=DEPTH_RTOL, atol=0, err_msg=f"{label} (depths)")
    return ours, twin, calls


@pytest.mark.parametrize("transform", ["aligned", "rotated"])
@pytest.mark.parametrize("kind", list(SUNS))
def test_suns_match_the_kernel(visibake, volume_sweep, transform, kind):
    medium = _medium(visibake, transform)
    _, _, calls = _compare(visibake, volume_sweep, medium, _light(visibake, kind, medium), f"sun {kind} {transform}")
    assert len(calls) == 1


@pytest.mark.parametrize("transform", ["aligned", "rotated"])
@pytest.mark.parametrize("kind", LAMPS)
def test_point_lamps_match_the_kernel(visibake, volume_sweep, transform, kind):
    medium = _medium(visibake, transform)
    _, _, calls = _compare(visibake, volume_sweep, medium, _light(visibake, kind, medium), f"lamp {kind} {transform}")
    if kind != "outside":
        # A lamp within the grid is swept along every axis and sign: all six pyramids.
        assert sorted(calls) == [(axis, flip) for axis in range(3) for flip in (False, True)]
    else:
        assert 1 <= len(calls) < 6


@pytest.mark.parametrize("kind", ["steep oblique", "inside"])
def test_more_slices_still_match_the_kernel(visibake, volume_sweep, kind):
    # 64 slices along the longest axis: float32's rounding grows with the slices swept.
    medium = _medium(visibake, "rotated", shape=(40, 64, 48), seed=9, extinction=8.0)
    _compare(visibake, volume_sweep, medium, _light(visibake, kind, medium), f"{kind}, 64 slices")


def _recorded_sweeps(visibake, medium, light):
    """The argument tuples direct.transmittance passes to each sweep (``out`` excluded)."""
    recorded = []
    _core(visibake, "volume.direct").transmittance(medium, light, sweep_pass=lambda *arguments: recorded.append(
        tuple(np.copy(a) if isinstance(a, np.ndarray) else a for a in arguments[:-1])))
    return recorded


@pytest.mark.parametrize("kind", ["at a voxel centre", "inside", "oblique"])
def test_each_sweep_writes_exactly_the_voxels_the_kernel_writes(visibake, volume_sweep, kind):
    # Called directly with ``out`` pre-filled with a value no sweep writes: the voxels each
    # sweep leaves alone must be the kernel's, also on the pyramids' diagonals, which a
    # lamp at a voxel centre puts exactly on the bound of the kernel's selection test.
    kernel = _core(visibake, "volume").require_kernels().sweep_transmittance
    medium = _medium(visibake, "rotated")
    sweeps = _recorded_sweeps(visibake, medium, _light(visibake, kind, medium))
    assert sweeps
    for arguments in sweeps:
        ours = np.full(medium.shape, 7.0, np.float32)
        twin = np.full(medium.shape, 7.0, np.float32)
        volume_sweep.sweep_transmittance(*arguments, ours)
        kernel(*arguments, twin)
        np.testing.assert_array_equal(ours == 7.0, twin == 7.0)
        np.testing.assert_allclose(ours, twin, rtol=0, atol=ATOL)
    if kind != "oblique":
        assert (twin == 7.0).any()  # a lamp's sweep selects its pyramid only


def test_results_read_back_in_several_atlases_are_the_same(visibake, volume_sweep, monkeypatch):
    # An atlas of 2 x 3 tiles: the slices come back in rounds, the last one partial.
    medium = _medium(visibake, "aligned")
    light = _light(visibake, "inside", medium)
    whole = _core(visibake, "volume.direct").transmittance(medium, light, sweep_pass=volume_sweep.sweep_transmittance)
    monkeypatch.setattr(volume_sweep, "ATLAS_SIDE", 54)
    assert volume_sweep._atlas_layout(SHAPE[0], SHAPE[1], SHAPE[2]) == (2, 3)
    rounds = _core(visibake, "volume.direct").transmittance(medium, light, sweep_pass=volume_sweep.sweep_transmittance)
    np.testing.assert_array_equal(rounds, whole)
