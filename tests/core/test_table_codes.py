"""The compact table entries: 16-bit atlas coordinates and logarithmic distances."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.visibility.table import (
    DISTANCE_CODES_PER_OCTAVE,
    NO_HIT_DISTANCE_CODE,
    UV_CODE_SCALE,
    VisibilityTable,
    decode_distance,
    decode_uv,
    encode_distance,
    encode_uv,
    table_bytes,
)

# Half a code step, relative: the worst rounding of a distance.
DISTANCE_HALF_STEP = 2.0 ** (0.5 / DISTANCE_CODES_PER_OCTAVE) - 1.0


@given(st.floats(0.0, 1.0, width=32))
@settings(max_examples=300)
def test_a_coordinate_comes_back_within_half_a_code(u):
    back = decode_uv(encode_uv(np.array([[u, 1.0 - u]])))
    assert back.dtype == np.float32
    assert np.all(np.abs(back - [[u, 1.0 - u]]) <= 0.5 / UV_CODE_SCALE + 1e-7)


def test_coordinates_outside_the_atlas_are_clamped_and_nan_is_zero():
    codes = encode_uv(np.array([[-0.5, 1.5], [np.nan, 1.0]]))
    assert codes.dtype == np.uint16
    np.testing.assert_array_equal(codes, [[0, UV_CODE_SCALE], [0, UV_CODE_SCALE]])
    np.testing.assert_array_equal(decode_uv(codes), [[0.0, 1.0], [0.0, 1.0]])


@given(st.floats(2.0 ** -16, 65000.0))
@settings(max_examples=300)
def test_a_distance_comes_back_within_half_a_step_at_every_scale(distance):
    back = float(decode_distance(encode_distance(np.array([distance])))[0])
    # The float32 of the stored value adds at most one float32 rounding.
    assert abs(back - distance) <= distance * (DISTANCE_HALF_STEP + 2.0 ** -23)


def test_distance_codes_keep_order_and_mark_what_was_not_hit():
    distances = np.array([0.0, 1e-9, 2.0 ** -16, 1e-3, 0.5, 1.0, 7.0, 1e4, 2.0 ** 16, 1e9, np.inf, np.nan])
    codes = encode_distance(distances)
    assert codes.dtype == np.uint16
    assert np.all(np.diff(codes[:10].astype(int)) >= 0)
    assert codes[10] == codes[11] == NO_HIT_DISTANCE_CODE
    assert np.all(codes[:10] < NO_HIT_DISTANCE_CODE)
    back = decode_distance(codes)
    assert np.isinf(back[10]) and np.all(np.isfinite(back[:10]))
    assert back[5] == 1.0 and back[4] == 0.5  # powers of two are stored exactly


def test_an_entry_takes_eight_bytes_and_twelve_with_vertex_triangles():
    assert table_bytes(10, 100) == 8 * 1000
    assert table_bytes(10, 100, vertex_objects=True) == 12 * 1000
    d = np.eye(3)
    table = VisibilityTable.from_values(d, np.zeros((3, 100), np.int16), np.full((3, 100, 2), 0.25),
                                        np.ones((3, 100)))
    assert table.nbytes == table_bytes(3, 100)
    np.testing.assert_allclose(table.hit_uv(1, np.arange(4)), 0.25, atol=1e-5)
    assert np.all(table.hit_distance(2) == 1.0)


@pytest.mark.parametrize("resolution", [512, 4096])
def test_a_code_step_is_a_small_fraction_of_a_texel(resolution):
    # 16 bits over the atlas: 1/16 texel at 4096^2, 1/128 at 512^2.
    assert resolution / UV_CODE_SCALE <= 1 / 15.9
