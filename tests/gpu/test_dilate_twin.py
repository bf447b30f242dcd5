"""The GPU gutter dilation against core.outputs.dilation.dilate on the same random images.

Tolerance: none. The shader adds the filled neighbours in the order numpy's einsum
does (one after the other for several channels, SIMD lanes for one channel) and
divides with correct rounding, so on llvmpipe the images are compared bit for bit
(assert_array_equal: NaN equals NaN, -0 equals 0) and the filled masks exactly. The
values span 7 decades so that any other summation order would show as a difference.
"""
import importlib
import time

import numpy as np
import pytest


@pytest.fixture(scope="module")
def gpu_dilate(gpu_shaders):
    return importlib.import_module(f"{gpu_shaders.__name__}.dilate").dilate


def _coverage(kind: str, height: int, width: int, rng) -> np.ndarray:
    y, x = np.mgrid[:height, :width]
    mask = np.zeros((height, width), bool)
    if kind == "islands":  # discs and rectangles of a few texels to a third of the image
        for _ in range(4):
            cy, cx = rng.integers(0, height), rng.integers(0, width)
            r = rng.uniform(0.5, max(1.0, min(height, width) / 6))
            mask |= (y - cy) ** 2 + (x - cx) ** 2 <= r * r
            y0, x0 = rng.integers(0, height), rng.integers(0, width)
            mask[y0:y0 + rng.integers(1, height // 3 + 2), x0:x0 + rng.integers(1, width // 3 + 2)] = True
    elif kind == "lines":  # one texel wide: a row, a column, a diagonal and lone texels
        mask[rng.integers(0, height), :] = True
        mask[:, rng.integers(0, width)] = True
        mask[(y - x) == rng.integers(-height // 2, width // 2 + 1)] = True
        mask[rng.integers(0, height, 5), rng.integers(0, width, 5)] = True
    elif kind == "noise":
        mask = rng.random((height, width)) < 0.04
    elif kind == "border":  # neighbours outside the image are clamped into it by numpy
        mask[[0, -1], :] = rng.random((2, width)) < 0.5
        mask[:, [0, -1]] |= rng.random((height, 2)) < 0.5
    elif kind == "full":
        mask[:] = True
    else:
        assert kind == "empty"
    return mask


def _image(shape, coverage, rng, dtype=np.float32):
    """Values over 7 decades on covered texels, garbage (NaN, huge) elsewhere."""
    values = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape)
    garbage = rng.choice([np.nan, 1e30, -7.0], size=shape)
    covered = coverage if len(shape) == 2 else coverage[..., None]
    return np.where(covered, values, garbage).astype(dtype)


def _compare(twin, ours, image, coverage, margin):
    expected, expected_filled = twin(image, coverage, margin)
    got, filled = ours(image, coverage, margin)
    assert got.shape == expected.shape and got.dtype == expected.dtype == np.float32
    assert filled.shape == expected_filled.shape == coverage.shape and filled.dtype == bool
    np.testing.assert_array_equal(filled, expected_filled)
    np.testing.assert_array_equal(got, expected)
    return got, filled


# (coverage kind, height, width, channels; None is a 2D (H, W) image)
CASES = [
    ("islands", 64, 64, 3),
    ("islands", 37, 101, 1),
    ("lines", 50, 77, 4),
    ("lines", 129, 64, None),
    ("noise", 45, 45, 7),
    ("border", 33, 20, 3),
    ("border", 21, 40, None),
    ("empty", 31, 17, 3),
    ("full", 16, 23, 7),
    ("islands", 9, 1, 3),
    ("lines", 1, 13, 1),
    ("islands", 96, 80, 48),
    ("islands", 256, 200, 3),
]


@pytest.mark.parametrize("margin", [0, 1, 4, 40])
@pytest.mark.parametrize("kind,height,width,channels", CASES)
def test_dilate_matches_numpy(visibake, gpu_dilate, kind, height, width, channels, margin):
    rng = np.random.default_rng([height, width, channels or 0, margin])
    coverage = _coverage(kind, height, width, rng)
    shape = (height, width) if channels is None else (height, width, channels)
    image = _image(shape, coverage, rng)
    got, filled = _compare(visibake.core.outputs.dilation.dilate, gpu_dilate, image, coverage, margin)
    if margin and coverage.any() and not coverage.all():
        assert filled.any()  # the case exercises the passes
    assert not np.any(filled & coverage)


def test_single_channel_2d_and_3d_agree_and_float64_input(visibake, gpu_dilate):
    rng = np.random.default_rng(5)
    coverage = _coverage("islands", 70, 90, rng)
    image = _image((70, 90, 1), coverage, rng, np.float64)
    flat, _ = _compare(visibake.core.outputs.dilation.dilate, gpu_dilate, image[..., 0], coverage, 6)
    stacked, _ = _compare(visibake.core.outputs.dilation.dilate, gpu_dilate, image, coverage, 6)
    np.testing.assert_array_equal(flat, stacked[..., 0])


def test_non_finite_covered_values_spread_as_in_numpy(visibake, gpu_dilate):
    rng = np.random.default_rng(11)
    for channels in (None, 3):
        coverage = _coverage("border", 40, 30, rng) | _coverage("noise", 40, 30, rng)
        shape = (40, 30) if channels is None else (40, 30, channels)
        image = _image(shape, coverage, rng)
        image[rng.random(shape) < 0.05] = np.inf
        image[rng.random(shape) < 0.05] = -np.inf
        image[rng.random(shape) < 0.05] = np.nan
        got, _ = _compare(visibake.core.outputs.dilation.dilate, gpu_dilate, image, coverage, 5)
        assert np.isnan(got).any() and np.isinf(got).any()


def test_channels_in_several_rounds_under_a_small_budget(visibake, gpu_shaders, gpu_dilate):
    module = importlib.import_module(f"{gpu_shaders.__name__}.dilate")
    rng = np.random.default_rng(2)
    coverage = _coverage("islands", 48, 64, rng)
    image = _image((48, 64, 48), coverage, rng)
    texels = 48 * 64
    budget = texels * (module.FIXED_BYTES_PER_TEXEL + 2 * module.LAYER_BYTES_PER_TEXEL)
    assert module.layers_per_chunk(64, 48, 12, budget) == 2
    expected = visibake.core.outputs.dilation.dilate(image, coverage, 7)
    got = gpu_dilate(image, coverage, 7, budget_bytes=budget)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    with pytest.raises(MemoryError, match="GPU budget"):
        gpu_dilate(image, coverage, 7, budget_bytes=texels * 40)


@pytest.mark.parametrize("image_shape,coverage_shape,margin", [
    ((8, 8, 3), (8, 8), -1),
    ((8, 8, 3), (8, 8), 1.5),
    ((8, 8, 3), (8, 9), 2),
    ((8, 8, 3, 1), (8, 8), 2),
    ((8,), (8,), 2),
])
def test_invalid_arguments_fail_as_in_numpy(visibake, gpu_dilate, image_shape, coverage_shape, margin):
    image, coverage = np.zeros(image_shape, np.float32), np.ones(coverage_shape, bool)
    with pytest.raises(ValueError) as expected:
        visibake.core.outputs.dilation.dilate(image, coverage, margin)
    with pytest.raises(ValueError) as got:
        gpu_dilate(image, coverage, margin)
    assert str(got.value) == str(expected.value)


@pytest.mark.parametrize("height,width", [(1, 16385), (16385, 1)])
def test_images_beyond_the_texture_limit_are_refused(gpu_dilate, height, width):
    with pytest.raises(ValueError, match="exceeds the GPU texture limit of 16384"):
        gpu_dilate(np.zeros((height, width, 3), np.float32), np.ones((height, width), bool), 1)


def test_large_rgb_image_and_timing(visibake, gpu_dilate):
    """The one large case: a 1024^2 RGB atlas with margin 4; prints both times."""
    rng = np.random.default_rng(1024)
    coverage = _coverage("islands", 1024, 1024, rng) | _coverage("noise", 1024, 1024, rng)
    image = _image((1024, 1024, 3), coverage, rng)
    gpu_dilate(image[:64, :64], coverage[:64, :64], 4)  # compile outside the timing
    started = time.perf_counter()
    got, filled = gpu_dilate(image, coverage, 4)
    gpu_seconds = time.perf_counter() - started
    started = time.perf_counter()
    expected, expected_filled = visibake.core.outputs.dilation.dilate(image, coverage, 4)
    numpy_seconds = time.perf_counter() - started
    print(f"\ndilate 1024^2 RGB, margin 4: GPU {gpu_seconds:.3f} s, numpy {numpy_seconds:.3f} s")
    np.testing.assert_array_equal(filled, expected_filled)
    np.testing.assert_array_equal(got, expected)


