"""The Cycles gonioreflectometer (benchmarks/brdf_reference.py) and its tiles, in real bpy.

No extension is needed: the harness only uses bpy, so these tests take no fixture of
tests/blender_support.py (bpy is imported here after tests/conftest.py has isolated the
user profile). Tiny renders: the whole file takes seconds.

Tolerances: ``noise`` is the standard error of each value, from the per-pixel variance
over two seed renders (thousands of pixels, so the estimate itself is stable); a value
may differ from the truth by 5 of them, plus 1e-5 relative (of at least 0.1/sr) for float32
rounding (a pair whose edges fall on pixel boundaries has no noise at all).
"""
import math
import sys
from pathlib import Path

import bpy

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks import brdf_tiles  # noqa: E402
from benchmarks.brdf_reference import cycles_brdf, direction  # noqa: E402

SIGMAS = 5.0
FLOAT_FLOOR = 1e-5

# (light, view): normal/normal; oblique, theta_l 60 and theta_v 45 deg at azimuths 30 and
# 200 deg; a grazing view (75 deg) at right angles to a 40 deg light.
PAIRS = [(direction(0, 0), direction(0, 0)),
         (direction(60, 30), direction(45, 200)),
         (direction(40, 0), direction(75, 90))]


def _within(values, truth, noise):
    return np.abs(values - truth) <= SIGMAS * noise + FLOAT_FLOOR * np.maximum(np.abs(truth), 0.1)


def test_flat_white_lambert_tile_is_one_over_pi():
    scenes = len(bpy.data.scenes)
    objects = len(bpy.data.objects)
    ref = cycles_brdf(*brdf_tiles.flat_tile(), albedo=1.0, pairs=PAIRS, samples=4, resolution=32)
    values, noise = ref
    assert values.shape == noise.shape == (3, 3)
    assert np.all(noise >= 0) and np.all(np.isfinite(noise))
    # the oblique pairs have partly covered pixels along the copy's edges: real noise
    assert noise[1:, 0].min() > 0
    assert np.all(_within(values, 1.0 / math.pi, noise)), (values * math.pi, noise * math.pi)
    # a tile without holes covers its whole projected cell; flat: radiance / alpha is constant,
    # so the coverage has the same relative noise as the values
    assert np.all(np.abs(ref.coverage - 1.0) <= SIGMAS * noise[:, 0] * math.pi + FLOAT_FLOOR)
    assert len(ref.seed_values) == 2 and ref.seconds.shape == (3,)
    # the renders happened in a scene of their own, removed after
    assert len(bpy.data.scenes) == scenes and len(bpy.data.objects) == objects


def test_v_groove_direct_light_matches_the_closed_form_with_neighbour_shadows():
    """A ridge tile (rims in the middle, valleys on the borders) is the V-groove with its
    lattice shifted by half a period: every shadow and every masking of a valley comes from
    the neighbouring copy, a holdout. Direct light only (bounces = 0)."""
    depth, albedo = 0.5, np.array([0.8, 0.5, 0.2])
    ridge = brdf_tiles.heightfield_tile(np.array([[0.0, depth]]))
    pairs = PAIRS + [(direction(60, 0), direction(45, 0)), (direction(60, 0), direction(45, 180))]
    values, noise = cycles_brdf(*ridge, albedo=albedo, pairs=pairs, samples=4, resolution=32, bounces=0)
    truth = np.array([brdf_tiles.v_groove_direct_brdf(depth, albedo, l, v) for l, v in pairs])
    assert truth[-1, 0] < 1e-12 and truth[-2, 0] > 0.3  # seen facets unlit / lit (the test has teeth)
    assert np.all(_within(values, truth, noise)), (values, truth, noise)


@pytest.mark.parametrize("name", ["flat", "vgroove", "vgroove3", "heightfield"])
def test_height_tiles_are_periodic_and_face_up(name):
    tile = {"flat": lambda: brdf_tiles.flat_tile(2.0),
            "vgroove": lambda: brdf_tiles.v_groove_tile(0.5),
            "vgroove3": lambda: brdf_tiles.v_groove_tile(0.2, period=2.0, grooves=3),
            "heightfield": lambda: brdf_tiles.heightfield_tile(np.random.default_rng(0).random((5, 7)), (1.0, 2.0)),
            }[name]
    positions, triangles, period = tile()
    assert positions.dtype == np.float64 and triangles.dtype == np.int32 and period.shape == (2,)
    a, b, c = (positions[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert normals[:, 2].min() > 0  # a height field seen from above: counter-clockwise
    assert np.isclose(0.5 * normals[:, 2].sum(), period[0] * period[1])  # covers the cell once
    for axis in (0, 1):  # the border at 0 is the border at the period, translated
        low = positions[np.isclose(positions[:, axis], 0.0)]
        high = positions[np.isclose(positions[:, axis], period[axis])].copy()
        high[:, axis] -= period[axis]
        assert len(low) == len(high) > 0
        assert np.allclose(low[np.lexsort(low.T)], high[np.lexsort(high.T)])


def test_woven_tile_threads_keep_their_gap_and_face_out():
    gap = 0.02
    positions, triangles, period = brdf_tiles.woven_tile(gap=gap)
    assert len(triangles) <= 4000
    assert positions[:, :2].min() >= 0.0 and np.all(positions[:, :2].max(0) <= period + 1e-12)
    per_thread = len(triangles) // 4
    xy = np.random.default_rng(1).random((1500, 2)) * period
    columns = [brdf_tiles.vertical_intervals(positions, triangles[k * per_thread:(k + 1) * per_thread], xy)
               for k in range(4)]
    smallest = np.inf
    for q in range(len(xy)):
        spans = []
        for column in columns:  # a closed tube crosses a vertical line an even number of times
            z = column[q]
            assert len(z) % 2 == 0
            spans += [(z[m], z[m + 1]) for m in range(0, len(z), 2)]
        spans.sort()
        for (_, top), (bottom, _) in zip(spans, spans[1:]):
            smallest = min(smallest, bottom - top)
    assert smallest >= gap * 0.99, smallest
    # closed periodic tubes: the signed projected area cancels; normals point away from the axis
    a, b, c = (positions[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert abs(normals[:, 2].sum()) < 1e-9
    centroid = (a + b + c) / 3.0
    for k in range(4):
        part = slice(k * per_thread, (k + 1) * per_thread)
        across = 0 if k < 2 else 1  # warps run along y (section in x), wefts along x
        axis = ((k % 2) + 0.5) * period[across] / 2.0
        side = np.abs(centroid[part, across] - axis) > 0.1
        assert np.all((normals[part, across] * (centroid[part, across] - axis))[side] > 0)


def test_a_flat_translucent_sheet_reflects_and_transmits_its_shares_on_both_sides():
    """The harness's thin sheet (Diffuse (1 - t) albedo + Translucent t albedo) against the
    closed forms VisiBake's model gives: (1 - t) albedo / pi on the light's side, t albedo /
    pi on the other, lit and seen from above or below."""
    albedo, t = 0.8, 0.5
    below = np.array([1.0, 1.0, -1.0])
    pairs = [(direction(30, 0), direction(20, 180)), (direction(30, 0), direction(25, 90) * below),
             (direction(40, 60) * below, direction(10, 0)), (direction(40, 60) * below, direction(35, 270) * below)]
    values, noise = cycles_brdf(*brdf_tiles.flat_tile(), albedo=albedo, pairs=pairs, samples=4, resolution=32,
                                transmission=t, bounces=2)
    truth = np.array([1 - t, t, t, 1 - t])[:, None] * albedo / math.pi * np.ones((1, 3))
    assert np.all(_within(values, truth, noise)), (values * math.pi, truth * math.pi, noise)
