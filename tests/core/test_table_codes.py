"""The compact table entries: 16-bit atlas coordinates and logarithmic distances."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.visibility.table import (
    BELOW_HORIZON,
    DISTANCE_CODES_PER_OCTAVE,
    MAX_VERTEX_TRIANGLES,
    NO_HIT_DISTANCE_CODE,
    UV_CODE_SCALE,
    VisibilityTable,
    decode_distance,
    decode_uv,
    decode_vertex_hit,
    encode_distance,
    encode_uv,
    encode_vertex_hit,
    table_bytes,
    vertex_cells,
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


def test_an_entry_takes_eight_bytes_also_with_vertex_mode_objects():
    # 8 bytes an entry, and 16 per direction and 64 samples: the entry bits and each word's first entry.
    assert table_bytes(10, 100) == 8 * 1000 + 10 * 2 * 16
    d = np.eye(3)
    table = VisibilityTable.from_values(d, np.zeros((3, 100), np.int16), np.full((3, 100, 2), 0.25),
                                        np.ones((3, 100)))
    assert table.nbytes == table_bytes(3, 100)
    np.testing.assert_allclose(table.entry_uv(table.entries.index(np.ones(4, int), np.arange(4))), 0.25, atol=1e-5)
    assert np.all(table.entry_distance(table.entries.row_span(2, 3)) == 1.0)
    # Object 1 in vertex mode, 7 triangles: its hits keep triangle and barycentrics in the same codes.
    objects = np.tile(np.array([0, 1], np.int16), (3, 50))
    triangles = np.tile(np.arange(100) % 7, (3, 1))
    mixed = VisibilityTable.from_values(d, objects, np.full((3, 100, 2), 0.25), np.ones((3, 100)), triangles,
                                        vertex_cells([4, 7], [False, True]))
    assert mixed.nbytes == table_bytes(3, 100)
    rows, columns = np.nonzero(objects == 1)
    triangle, bary = mixed.entry_vertex(mixed.entries.index(rows, columns))
    np.testing.assert_array_equal(triangle, triangles[rows, columns])
    np.testing.assert_allclose(bary, 0.25, atol=0.5 / (65536 // 3 - 1) + 1e-7)
    np.testing.assert_allclose(mixed.entry_uv(mixed.entries.index([0], [0])), 0.25, atol=1e-5)
    # Half the entries below the horizon: only the other half is stored.
    below = np.where(np.arange(100) % 2 == 0, objects, BELOW_HORIZON)
    half = VisibilityTable.from_values(d, below, np.full((3, 100, 2), 0.25), np.ones((3, 100)))
    assert half.nbytes == table_bytes(3, 100) - 3 * 50 * 8


@pytest.mark.parametrize("count", [1, 2, 4, 5, 1280, 65536, 1_000_003, MAX_VERTEX_TRIANGLES])
def test_every_triangle_and_its_barycentrics_come_back_from_the_codes(count):
    cells = vertex_cells([count], [True])
    assert cells[0] ** 2 >= count and (cells[0] - 1) ** 2 < count
    steps = 65536 // int(cells[0])
    assert steps >= 16  # a barycentric step of at most 1/15 of the triangle
    rng = np.random.default_rng(count)
    triangle = np.unique(np.concatenate([[0, count - 1], rng.integers(0, count, 2000)]))
    bary = rng.uniform(0, 1, (len(triangle), 2)).astype(np.float32)
    bary[0], bary[-1] = (0.0, 0.0), (1.0, 1.0)
    codes = encode_vertex_hit(triangle, bary, np.repeat(cells, len(triangle)))
    assert codes.dtype == np.uint16
    back, decoded = decode_vertex_hit(codes, np.repeat(cells, len(triangle)))
    np.testing.assert_array_equal(back, triangle)
    assert decoded.dtype == np.float32
    assert np.max(np.abs(decoded - bary)) <= 0.5 / (steps - 1) + 1e-7


def test_a_vertex_mode_object_beyond_the_codes_is_refused_and_atlas_objects_have_no_grid():
    assert vertex_cells([10, 20], None) is None
    np.testing.assert_array_equal(vertex_cells([10, 20], [False, True]), [0, 5])
    with pytest.raises(ValueError, match="at most"):
        vertex_cells([MAX_VERTEX_TRIANGLES + 1], [True])


@pytest.mark.parametrize("resolution", [512, 4096])
def test_a_code_step_is_a_small_fraction_of_a_texel(resolution):
    # 16 bits over the atlas: 1/16 texel at 4096^2, 1/128 at 512^2.
    assert resolution / UV_CODE_SCALE <= 1 / 15.9
