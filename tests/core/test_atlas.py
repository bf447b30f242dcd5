"""core.sampling.atlas: UV layout checks and xatlas unwrapping."""
import numpy as np
import pytest

from core.sampling.atlas import UnwrapResult, _curved_planar_regions, unwrap, uv_layout_problems, uv_layout_stats
from core.sampling.raster import rasterize

UNIT_SQUARE = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)


def cube():
    positions = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return positions, triangles


def torus(nu=24, nv=12, major=1.0, minor=0.35):
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    positions = np.stack([(major + minor * np.cos(vv)) * np.cos(uu), (major + minor * np.cos(vv)) * np.sin(uu),
                          minor * np.sin(vv)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = i * nv + j
    b = (i + 1) % nu * nv + j
    c = (i + 1) % nu * nv + (j + 1) % nv
    d = i * nv + (j + 1) % nv
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return positions, triangles


def cylinder(segments, radius=1.0, height=0.2):
    t = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(t), radius * np.sin(t), np.zeros_like(t)], axis=1)
    positions = np.concatenate([ring, ring + [0, 0, height]])
    j = np.arange(segments)
    a, b = j, (j + 1) % segments
    triangles = np.concatenate([np.stack([a, b, b + segments], 1), np.stack([a, b + segments, a + segments], 1)])
    return positions, triangles


def areas_3d(positions, triangles):
    c = positions[triangles]
    return 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)


def areas_uv(corner_uv):
    c = np.asarray(corner_uv, np.float64)
    u, v = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]
    return 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])


def angles(corners):
    """Interior angles (m, 3) of triangles given as (m, 3, d) corners."""
    out = []
    for k in range(3):
        e1 = corners[:, (k + 1) % 3] - corners[:, k]
        e2 = corners[:, (k + 2) % 3] - corners[:, k]
        cos = np.sum(e1 * e2, axis=1) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        out.append(np.arccos(np.clip(cos, -1, 1)))
    return np.stack(out, axis=1)


def check_unwrap(result: UnwrapResult, positions, triangles, resolution, stretch=0.15):
    m = len(triangles)
    assert result.corner_uv.shape == (m, 3, 2) and result.corner_uv.dtype == np.float32
    assert result.width == result.height == resolution
    assert result.degenerate.shape == (m,)
    assert np.all(result.corner_uv >= 0) and np.all(result.corner_uv <= 1)
    assert uv_layout_problems(result.corner_uv, resolution, resolution) == []
    good = ~result.degenerate
    assert np.all(areas_uv(result.corner_uv[good]) > 0)
    assert np.all(result.corner_uv[result.degenerate] == 0)
    # Every chart is scaled to texels_per_unit, then stretched by under one texel
    # per axis to whole-texel extents, so the summed UV area is the surface area
    # times texels_per_unit squared, plus a little (more for small charts). A wrong
    # triangle order breaks this too.
    uv_area = areas_uv(result.corner_uv[good]).sum() * resolution ** 2
    nominal = areas_3d(positions, triangles[good]).sum() * result.texels_per_unit ** 2
    assert nominal * 0.999 <= uv_area <= nominal * (1 + stretch)


# ---------------------------------------------------------------------------------------
# uv_layout_problems


def test_valid_layout_has_no_problems():
    assert uv_layout_problems(UNIT_SQUARE, 16, 16) == []
    stats = uv_layout_stats(UNIT_SQUARE, 16, 16)
    assert stats.covered_texels == 256 and stats.overlap_texels == 0


def test_overlap_is_reported_with_its_texel_count():
    overlapping = np.concatenate([UNIT_SQUARE * 0.5, UNIT_SQUARE * 0.5 + 0.25])
    problems = uv_layout_problems(overlapping, 16, 16)
    assert problems == ["UV islands overlap (16 texels covered twice)"]


def test_out_of_range_uvs_are_reported():
    shifted = UNIT_SQUARE * 0.5 + [0.7, 0.0]
    problems = uv_layout_problems(shifted, 16, 16)
    assert problems == ["3 of 6 UV coordinates outside [0, 1]"]
    # Float32 rounding at the border is not a problem.
    nudged = UNIT_SQUARE.astype(np.float32) * np.float32(1 + 2e-7)
    assert uv_layout_problems(nudged, 16, 16) == []


def test_nan_uvs_are_reported():
    bad = UNIT_SQUARE.copy()
    bad[0, 1, 0] = np.nan
    bad[1, 2, 1] = np.inf
    problems = uv_layout_problems(bad, 16, 16)
    assert "2 of 6 UV coordinates are NaN or infinite" in problems
    assert not any("outside" in p for p in problems)


def test_zero_area_triangles_are_counted_but_only_all_of_them_is_a_problem():
    points = np.zeros((3, 3, 2))
    mixed = np.concatenate([UNIT_SQUARE, points])
    assert uv_layout_problems(mixed, 8, 8) == []
    assert uv_layout_stats(mixed, 8, 8).zero_area_triangles == 3
    collinear = np.array([[[0.1, 0.1], [0.5, 0.5], [0.9, 0.9]]])
    assert uv_layout_problems(np.concatenate([points, collinear]), 8, 8) == ["all 4 triangles have zero UV area"]
    assert uv_layout_problems(np.zeros((0, 3, 2)), 8, 8) == ["the UV map has no triangles"]


def test_islands_too_small_for_the_resolution_are_reported():
    tiny = UNIT_SQUARE * 0.01 + 0.3
    assert uv_layout_problems(tiny, 8, 8) == ["no texel centre is covered at 8x8; the UV islands are too small"]
    assert uv_layout_problems(tiny, 1024, 1024) == []


def test_overlap_is_judged_at_the_target_resolution():
    # Islands overlapping in a strip 1/100 wide: no texel centre of a 16-texel
    # image falls in it, ten columns of a 1000-texel image do.
    left = UNIT_SQUARE * [0.505, 1.0]
    right = UNIT_SQUARE * [0.505, 1.0] + [0.495, 0.0]
    layout = np.concatenate([left, right])
    assert uv_layout_problems(layout, 16, 16) == []
    assert uv_layout_problems(layout, 1000, 1000) == ["UV islands overlap (10000 texels covered twice)"]


# ---------------------------------------------------------------------------------------
# unwrap


def test_unwrap_cube():
    positions, triangles = cube()
    result = unwrap(positions, triangles, 1024)
    check_unwrap(result, positions, triangles, 1024, stretch=0.01)
    assert result.degenerate_count == 0
    # Flat faces are mapped without distortion, all at one scale (up to the
    # whole-texel stretch, under 1 / 300 per axis for charts this size).
    ratio = areas_uv(result.corner_uv) / areas_3d(positions, triangles)
    assert ratio.max() / ratio.min() < 1.01
    np.testing.assert_allclose(angles(result.corner_uv.astype(np.float64)), angles(positions[triangles]), atol=0.01)


def test_unwrap_torus_keeps_triangle_order():
    positions, triangles = torus()
    result = unwrap(positions, triangles, 256)
    check_unwrap(result, positions, triangles, 256)
    ratio = areas_uv(result.corner_uv) / areas_3d(positions, triangles)
    # xatlas's charts are near-conformal with bounded stretch (measured within a
    # factor 1.3 of the median here); triangles matched to the wrong faces would
    # differ in area by the torus's inner/outer ratio (~2) and in shape.
    assert np.all(ratio > np.median(ratio) / 1.6) and np.all(ratio < np.median(ratio) * 1.6)
    angle_error = np.abs(angles(result.corner_uv.astype(np.float64)) - angles(positions[triangles]))
    assert np.median(angle_error) < np.radians(2) and angle_error.max() < np.radians(20)


def test_unwrap_fills_but_never_exceeds_the_resolution():
    positions, triangles = torus(32, 16)
    for resolution in (128, 512):
        result = unwrap(positions, triangles, resolution, padding_texels=4)
        check_unwrap(result, positions, triangles, resolution)
        used = result.corner_uv.reshape(-1, 2).max(axis=0)
        assert used.max() > 0.85
        covered = rasterize(result.corner_uv, resolution, resolution).coverage
        assert covered.mean() > 0.3


def test_padding_separates_charts():
    positions, triangles = cube()
    result = unwrap(positions, triangles, 128, padding_texels=3)
    samples = rasterize(result.corner_uv, 128, 128)
    face_of_triangle = np.arange(12) // 2
    owner = np.full((128, 128), -1)
    owner.ravel()[samples.pixel] = face_of_triangle[samples.triangle]
    # Texels of different faces (separate charts on a cube) are never 8-neighbours.
    for dy, dx in [(0, 1), (1, 0), (1, 1), (1, -1)]:
        a = owner[max(dy, 0):, max(dx, 0): 128 + min(dx, 0)]
        b = owner[: 128 - dy, max(-dx, 0): 128 - max(dx, 0)]
        clash = (a >= 0) & (b >= 0) & (a != b)
        assert not clash.any()


def test_unwrap_handles_degenerate_triangles():
    positions, triangles = cube()
    extra_positions = np.array([
        [0.0, 0.0, 0.0],            # duplicate of vertex 0
        [np.nan, 0.0, 0.0],
        [np.inf, 1.0, 0.0],
        [0.5, 0.5, 0.5], [0.6, 0.6, 0.6], [0.7, 0.7, 0.7],  # collinear
    ])
    positions = np.concatenate([positions, extra_positions])
    n = 8
    bad = np.array([
        [0, n, 1],                  # two corners at the same position
        [0, 0, 1],                  # repeated index
        [0, 1, n + 1],              # NaN vertex
        [n + 2, 1, 2],              # infinite vertex
        [n + 3, n + 4, n + 5],      # zero area
    ])
    all_triangles = np.concatenate([triangles[:6], bad, triangles[6:]])
    result = unwrap(positions, all_triangles, 64)
    assert result.degenerate.tolist() == [False] * 6 + [True] * 5 + [False] * 6
    assert result.degenerate_count == 5
    check_unwrap(result, positions, all_triangles, 64)
    # The good triangles are laid out exactly as without the bad ones.
    clean = unwrap(cube()[0], triangles, 64)
    np.testing.assert_allclose(result.corner_uv[~result.degenerate], clean.corner_uv, atol=1e-6)


def test_unwrap_is_scale_invariant():
    positions, triangles = cube()
    small = unwrap(positions * 1e-4, triangles, 64)
    large = unwrap(positions * 1e4 + 5e4, triangles, 64)
    reference = unwrap(positions, triangles, 64)
    np.testing.assert_allclose(small.corner_uv, reference.corner_uv, atol=1e-5)
    np.testing.assert_allclose(large.corner_uv, reference.corner_uv, atol=1e-5)
    assert small.texels_per_unit == pytest.approx(reference.texels_per_unit * 1e4, rel=1e-4)


def test_unwrap_with_texels_per_unit():
    positions, triangles = cube()
    result = unwrap(positions, triangles, 128, texels_per_unit=20.0)
    check_unwrap(result, positions, triangles, 128)
    assert result.texels_per_unit == pytest.approx(20.0, rel=1e-3)
    with pytest.raises(ValueError, match="texels_per_unit"):
        unwrap(positions, triangles, 64, texels_per_unit=1000.0)


def test_smooth_dense_surface_is_not_flattened_into_one_overlapping_chart():
    # Neighbouring faces 0.6 degrees apart: xatlas alone chains them all into one
    # "planar" chart and projects the cylinder flat onto itself.
    positions, triangles = cylinder(600)
    welded = triangles.astype(np.int64)
    assert _curved_planar_regions(positions.astype(np.float32), triangles.astype(np.uint32), welded).all()
    result = unwrap(positions, triangles, 256)
    # Its charts are strips a few texels wide, which the whole-texel stretch widens most.
    check_unwrap(result, positions, triangles, 256, stretch=0.3)
    assert result.chart_count > 1


def test_coarse_surface_is_left_alone():
    positions, triangles = torus()
    hazard = _curved_planar_regions(positions.astype(np.float32), triangles.astype(np.uint32),
                                    triangles.astype(np.int64))
    assert not hazard.any()


@pytest.mark.parametrize("bad_input, message", [
    ((np.zeros((3, 3)), np.zeros((0, 3), int)), "no triangles"),
    ((np.zeros((3, 3)), np.array([[0, 1, 3]])), "indices"),
    ((np.zeros((3, 2)), np.array([[0, 1, 2]])), "positions"),
    ((np.zeros((3, 3)), np.array([[0, 1, 2]])), "non-zero area"),
    ((np.full((3, 3), np.nan), np.array([[0, 1, 2]])), "non-zero area"),
])
def test_unwrap_rejects_unusable_meshes(bad_input, message):
    with pytest.raises(ValueError, match=message):
        unwrap(*bad_input, 64)


def test_unwrap_rejects_bad_sizes():
    positions, triangles = cube()
    with pytest.raises(ValueError):
        unwrap(positions, triangles, 4, padding_texels=2)
    with pytest.raises(ValueError):
        unwrap(positions, triangles, 64, texels_per_unit=-1.0)


def test_the_layout_check_never_loads_the_compiled_kernels():
    """The UV layout check runs on Blender's main thread before a bake starts: it must not be
    what loads (and in a fresh cache, compiles for many seconds) the kernels. It uses them
    once the process has them, with the same answer."""
    import json
    import os
    import subprocess
    import sys
    code = """
import json, numpy as np
from core import kernels
from core.sampling.atlas import uv_layout_stats
square = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)
before = uv_layout_stats(square, 16, 16)
loaded_by_check = kernels.tried()
backend = kernels.status().backend
after = uv_layout_stats(square, 16, 16)
print(json.dumps([loaded_by_check, backend, before == after, before.covered_texels]))
"""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    loaded_by_check, backend, same, covered = json.loads(done.stdout.strip().splitlines()[-1])
    assert not loaded_by_check
    assert same and covered == 256, backend
