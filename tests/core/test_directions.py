import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.visibility.directions import ShadowRegions, direction_set, random_rotation, spherical_fibonacci


@given(st.integers(min_value=1, max_value=4096))
@settings(max_examples=40, deadline=None)
def test_fibonacci_directions_are_unit_and_balanced(count):
    d = spherical_fibonacci(count)
    assert d.shape == (count, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    # A balanced set has its centroid near the origin: the z spacing is exact,
    # x and y follow the golden angle.
    if count >= 16:
        assert np.linalg.norm(d.mean(axis=0)) < 2.0 / count ** 0.5


def test_fibonacci_integrates_cosine_over_hemisphere():
    # sum_i max(0, d_i . n) * 4pi/N -> pi, with the error falling as N grows.
    errors = []
    for count in (32, 128, 512):
        d = spherical_fibonacci(count)
        n = np.array([0.3, -0.5, 0.81])
        n /= np.linalg.norm(n)
        errors.append(abs(np.clip(d @ n, 0, None).sum() * 4 * np.pi / count - np.pi) / np.pi)
    assert errors[0] < 0.05 and errors[2] < errors[0]


@given(st.integers(min_value=0, max_value=2**31))
@settings(max_examples=30, deadline=None)
def test_random_rotation_is_a_rotation(seed):
    r = random_rotation(seed)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)


def test_rotated_set_depends_on_seed_only():
    a = direction_set(64, rotate=True, seed=3)
    b = direction_set(64, rotate=True, seed=3)
    c = direction_set(64, rotate=True, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_array_equal(direction_set(64), spherical_fibonacci(64))


def test_regions_partition_directions_and_blend():
    d = spherical_fibonacci(512)
    regions = ShadowRegions(d, 32)
    assert regions.nearest.shape == (512,)
    counts = np.bincount(regions.nearest, minlength=32)
    # Every region gets a fair share of an even direction set.
    assert counts.min() >= 8 and counts.max() <= 24
    # The weight halves at the region's angular radius.
    radius = np.arccos(1 - 2 / 32)
    light = np.array([[np.sin(radius), 0.0, np.cos(radius)]])
    regions_z = ShadowRegions(d, 32)
    regions_z.centres = np.array([[0.0, 0.0, 1.0]])
    assert regions_z.weights(light)[0, 0] == pytest.approx(0.5, rel=1e-9)


def test_invalid_counts_are_refused():
    with pytest.raises(ValueError):
        spherical_fibonacci(0)
    with pytest.raises(ValueError):
        ShadowRegions(spherical_fibonacci(8), 0)
