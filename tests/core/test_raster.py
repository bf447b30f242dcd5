"""core.sampling.raster: texel-centre coverage, the edge rule, and gutter dilation."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import kernels
from core import tolerances as tol
from core.outputs.dilation import dilate
from core.sampling.raster import TexelSamples, _rasterize_numpy, degenerate_uv_triangles, rasterize, texel_centres

UNIT_SQUARE = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)


def centres_of(samples: TexelSamples) -> np.ndarray:
    return texel_centres(samples.width, samples.height)[samples.pixel]


def interpolate(corner_uv, samples: TexelSamples) -> np.ndarray:
    return np.einsum("kc,kcd->kd", samples.barycentric.astype(np.float64),
                     np.asarray(corner_uv, np.float64)[samples.triangle])


def exact_weights(corner_uv, samples: TexelSamples) -> tuple[np.ndarray, np.ndarray]:
    """Unclipped barycentric weights of each sample's texel centre, in float64, and their error bound.

    Recomputing the weights rounds differently from the rasteriser; the error of
    either grows with the squared coordinate size over the doubled area.
    """
    w, h = samples.width, samples.height
    c = np.asarray(corner_uv, np.float64)[samples.triangle] * [w, h]
    return weights_at(c, centres_of(samples) * [w, h])


def weights_at(c: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b, cc = c[..., 0, :], c[..., 1, :], c[..., 2, :]

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    area = cross(b - a, cc - a)
    weights = np.stack([cross(cc - b, p - b), cross(a - cc, p - cc), cross(b - a, p - a)], axis=-1)
    size = np.max(np.abs(c), axis=(-2, -1)) + 1.0
    rounding = 1e-12 * size ** 2 / np.abs(area)
    return weights / area[..., None], rounding


def check_invariants(samples: TexelSamples, width: int, height: int) -> None:
    assert samples.pixel.dtype == np.int64 and samples.triangle.dtype == np.int32
    assert samples.barycentric.dtype == np.float32 and samples.barycentric.shape == (samples.pixel.size, 3)
    assert samples.coverage.shape == (height, width) and samples.coverage.dtype == bool
    assert np.all(np.diff(samples.pixel) > 0), "each texel once, in pixel order"
    assert np.array_equal(np.flatnonzero(samples.coverage.ravel()), samples.pixel)
    assert np.all(samples.barycentric >= 0)
    np.testing.assert_allclose(samples.barycentric.sum(axis=1), 1.0, atol=1e-6)


# ---------------------------------------------------------------------------------------
# rasterize: fixed cases


def test_unit_square_covers_every_texel_once():
    samples = rasterize(UNIT_SQUARE, 16, 16)
    check_invariants(samples, 16, 16)
    assert samples.pixel.size == 256 and samples.coverage.all()
    assert samples.overlap_count == 0
    # The 16 centres on the diagonal go to one triangle: the one above it (bottom-right rule).
    assert np.bincount(samples.triangle).tolist() == [120, 136]
    np.testing.assert_allclose(interpolate(UNIT_SQUARE, samples), centres_of(samples), atol=1e-6)


def test_texel_centres_follow_blender_pixel_order():
    uv = texel_centres(4, 3)
    assert uv.shape == (12, 2)
    np.testing.assert_allclose(uv[0], [0.125, 1 / 6])
    np.testing.assert_allclose(uv[4 * 2 + 3], [0.875, 5 / 6])  # y=2 is the top row


def test_bottom_left_triangle_lands_in_bottom_rows():
    tri = np.array([[[0.0, 0.0], [0.3, 0.0], [0.0, 0.3]]])
    samples = rasterize(tri, 10, 20)
    check_invariants(samples, 10, 20)
    ys, xs = np.nonzero(samples.coverage)
    assert samples.coverage[0, 0] and ys.max() < 6 and xs.max() < 3
    assert np.all(samples.pixel == ys * 10 + xs)


@pytest.mark.parametrize("size", [8, 64, 512])
def test_single_triangle_count_approaches_area(size):
    tri = np.array([[[0.1, 0.13], [0.91, 0.22], [0.37, 0.86]]])
    (ax, ay), (bx, by) = tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0]
    area = 0.5 * abs(ax * by - ay * bx)
    perimeter = np.sum(np.linalg.norm((tri[0, [1, 2, 0]] - tri[0]) * size, axis=1))
    count = rasterize(tri, size, size).pixel.size
    # Lattice points in a convex region differ from its area by less than its perimeter.
    assert abs(count - area * size * size) <= perimeter
    if size == 512:
        assert abs(count / (area * size * size) - 1) < 0.01


def test_orientation_does_not_matter():
    tri = np.array([[[0.05, 0.1], [0.8, 0.3], [0.3, 0.95]]])
    ccw = rasterize(tri, 37, 29)
    cw = rasterize(tri[:, ::-1], 37, 29)
    assert np.array_equal(ccw.pixel, cw.pixel)
    np.testing.assert_allclose(ccw.barycentric, cw.barycentric[:, ::-1], atol=1e-6)


@pytest.mark.parametrize("flip", [False, True])
def test_centres_on_the_outer_boundary_are_covered(flip):
    # Corners on texel centres: 36 centres lie inside or on the edges of this triangle,
    # on whichever side of each edge the interior is.
    tri = np.array([[[0.5, 0.5], [7.5, 0.5], [0.5, 7.5]]]) / 8
    if flip:
        tri = 1 - tri
    samples = rasterize(tri, 8, 8)
    assert samples.pixel.size == 36
    assert samples.overlap_count == 0
    np.testing.assert_allclose(interpolate(tri, samples), centres_of(samples), atol=1e-9)


def test_fan_around_a_texel_centre_claims_it_once():
    centre = np.array([4.5, 4.5]) / 9
    angles = np.linspace(0, 2 * np.pi, 9)[:-1] + 0.1
    ring = centre + 0.3 * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    fan = np.stack([np.broadcast_to(centre, ring.shape), ring, np.roll(ring, -1, axis=0)], axis=1)
    samples = rasterize(fan, 9, 9)
    check_invariants(samples, 9, 9)
    assert samples.overlap_count == 0
    assert samples.coverage[4, 4]
    # The same texels as the fan's outline polygon split another way.
    other = np.stack([np.broadcast_to(ring[0], (6, 2)), ring[1:7], ring[2:8]], axis=1)
    assert np.array_equal(rasterize(other, 9, 9).pixel, samples.pixel)


def test_overlapping_triangles_are_counted_and_given_to_the_lowest_index():
    square = UNIT_SQUARE * 0.5
    shifted = square + 0.25
    samples = rasterize(np.concatenate([shifted, square]), 16, 16)
    check_invariants(samples, 16, 16)
    # [0.25, 0.5]^2 overlaps: 4 x 4 texels.
    assert samples.overlap_count == 16
    shared = centres_of(samples)
    in_both = np.all((shared > 0.25) & (shared < 0.5), axis=1)
    assert in_both.sum() == 16 and np.all(samples.triangle[in_both] < 2)
    assert samples.pixel.size == 64 + 64 - 16


def test_identical_copies_overlap_everywhere():
    samples = rasterize(np.concatenate([UNIT_SQUARE, UNIT_SQUARE]), 8, 8)
    assert samples.overlap_count == 64
    assert np.all(samples.triangle < 2)


def test_degenerate_and_non_finite_triangles_are_skipped():
    bad = np.array([
        [[0.1, 0.1], [0.9, 0.9], [0.5, 0.5]],        # collinear
        [[0.2, 0.2], [0.2, 0.2], [0.2, 0.2]],        # a point
        [[np.nan, 0.1], [0.9, 0.1], [0.1, 0.9]],
        [[np.inf, 0.1], [0.9, 0.1], [0.1, 0.9]],
        [[1e300, 0.0], [-1e300, 0.0], [0.0, 1e300]],  # area overflows
    ])
    assert degenerate_uv_triangles(bad, 8, 8).all()
    samples = rasterize(np.concatenate([bad, UNIT_SQUARE]), 8, 8)
    check_invariants(samples, 8, 8)
    assert samples.pixel.size == 64 and set(samples.triangle.tolist()) == {5, 6}
    empty = rasterize(bad, 8, 8)
    assert empty.pixel.size == 0 and not empty.coverage.any() and empty.overlap_count == 0
    assert rasterize(np.zeros((0, 3, 2)), 4, 4).pixel.size == 0


def test_triangles_partly_outside_are_clipped():
    big = np.array([[[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]]])
    samples = rasterize(big, 5, 7)
    check_invariants(samples, 5, 7)
    assert samples.coverage.all()


def test_tiny_triangle_between_centres_gets_nothing():
    tiny = np.array([[[0.01, 0.01], [0.02, 0.01], [0.01, 0.02]]])
    assert rasterize(tiny, 8, 8).pixel.size == 0


def test_large_triangle_spans_several_chunks(monkeypatch):
    import core.sampling.raster as raster

    reference = _rasterize_numpy(UNIT_SQUARE, 64, 48)
    monkeypatch.setattr(raster, "RASTER_CHUNK_PAIRS", 100)
    monkeypatch.setattr(raster, "RASTER_CHUNK_ROWS", 7)
    chunked = _rasterize_numpy(UNIT_SQUARE, 64, 48)
    assert np.array_equal(chunked.pixel, reference.pixel)
    assert np.array_equal(chunked.triangle, reference.triangle)
    assert chunked.pixel.size == 64 * 48


def test_bad_sizes_and_shapes_raise():
    with pytest.raises(ValueError):
        rasterize(UNIT_SQUARE, 0, 4)
    with pytest.raises(ValueError):
        rasterize(UNIT_SQUARE[:, :2], 4, 4)


# ---------------------------------------------------------------------------------------
# rasterize: properties

coordinate = st.floats(-0.25, 1.25, allow_nan=False, width=32)
triangles = st.lists(st.tuples(*[st.tuples(coordinate, coordinate)] * 3), min_size=1, max_size=6)
sizes = st.integers(1, 24)


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(triangles, sizes, sizes)
def test_claimed_centres_lie_in_their_triangle(tris, width, height):
    corner_uv = np.array(tris, np.float64)
    samples = rasterize(corner_uv, width, height)
    check_invariants(samples, width, height)
    if samples.pixel.size == 0:
        return
    assert not degenerate_uv_triangles(corner_uv, width, height)[samples.triangle].any()
    weights, rounding = exact_weights(corner_uv, samples)
    assert np.all(weights.min(axis=1) >= -1.01 * tol.RASTER_EDGE_EPSILON - rounding)
    # Where the centre is well inside, the returned weights are the exact ones.
    inside = weights.min(axis=1) >= rounding
    np.testing.assert_allclose(samples.barycentric[inside], weights[inside],
                               atol=1e-5 + max(rounding[inside].max(initial=0), 0))


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(triangles, sizes, sizes)
def test_every_centre_inside_a_triangle_is_claimed(tris, width, height):
    corner_uv = np.array(tris, np.float64)
    samples = rasterize(corner_uv, width, height)
    live = ~degenerate_uv_triangles(corner_uv, width, height)
    centres = texel_centres(width, height) * [width, height]
    expected = np.zeros(width * height, bool)
    for t in np.flatnonzero(live):
        weights, rounding = weights_at(corner_uv[t] * [width, height], centres)
        expected |= weights.min(axis=1) > rounding
    assert not np.any(expected & ~samples.coverage.ravel())


def signed_area(corner_uv: np.ndarray) -> np.ndarray:
    u = corner_uv[:, 1] - corner_uv[:, 0]
    v = corner_uv[:, 2] - corner_uv[:, 0]
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


@st.composite
def partitions(draw):
    """A random triangulation of the unit square, vertices snapped to a fine grid.

    Snapping to quarter texels puts many texel centres exactly on edges and
    vertices, which is what the fill rule has to get right.
    """
    width = draw(st.integers(1, 12))
    height = draw(st.integers(1, 12))
    grid = np.array([4 * width, 4 * height])
    tris = [np.array([[0, 0], [1, 0], [1, 1]], float), np.array([[0, 0], [1, 1], [0, 1]], float)]
    for _ in range(draw(st.integers(0, 12))):
        index = draw(st.integers(0, len(tris) - 1))
        a, b, c = tris[index]
        weights = np.array(draw(st.tuples(*[st.floats(0.01, 1.0)] * 3)))
        point = np.round((weights @ np.array([a, b, c])) / weights.sum() * grid) / grid
        split = np.array([[a, b, point], [b, c, point], [c, a, point]])
        # Snapping can push the point onto an edge (leaving a T-junction) or out of
        # the triangle (folding the layout): neither is a partition any more.
        if not degenerate_uv_triangles(split, width, height).any() and np.all(
                np.sign(signed_area(split)) == np.sign(signed_area(np.array([[a, b, c]])))):
            tris[index:index + 1] = list(split)
    if draw(st.booleans()):
        tris = [t[::-1] for t in tris]  # mirrored islands are laid out clockwise
    return np.array(tris), width, height


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(partitions())
def test_partition_of_the_square_covers_each_texel_exactly_once(partition):
    corner_uv, width, height = partition
    samples = rasterize(corner_uv, width, height)
    check_invariants(samples, width, height)
    assert samples.coverage.all()
    assert samples.overlap_count == 0
    np.testing.assert_allclose(interpolate(corner_uv, samples), centres_of(samples), atol=1e-6)


# ---------------------------------------------------------------------------------------
# rasterize: the compiled kernels give the numpy code's bits


def assert_same_samples(ours: TexelSamples, reference: TexelSamples) -> None:
    for name in ("pixel", "triangle", "barycentric", "coverage"):
        a, b = getattr(ours, name), getattr(reference, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert a.tobytes() == b.tobytes(), name  # bitwise: -0.0 and NaN payloads too
    assert ours.overlap_count == reference.overlap_count


def compiled_matches_numpy(corner_uv, width, height) -> TexelSamples:
    if kernels.compiled() is None:
        pytest.skip(f"compiled kernels unavailable: {kernels.status().reason}")
    reference = _rasterize_numpy(corner_uv, width, height)
    for threads in (1, 2):
        assert_same_samples(rasterize(corner_uv, width, height, threads=threads), reference)
    return reference


def grid_mesh(columns, rows, width, height, mirrored=False):
    """A watertight grid of 2 * columns * rows triangles over the unit square, diagonals
    alternating, its lines on texel edges and centres wherever 2 * width / columns (or
    2 * height / rows) is a whole number."""
    u = np.linspace(0, 1, columns + 1)
    v = np.linspace(0, 1, rows + 1)
    tris = []
    for j in range(rows):
        for i in range(columns):
            a, b, c, d = (u[i], v[j]), (u[i + 1], v[j]), (u[i + 1], v[j + 1]), (u[i], v[j + 1])
            tris += [(a, b, c), (a, c, d)] if (i + j) % 2 else [(a, b, d), (b, c, d)]
    tris = np.array(tris)
    return tris[:, ::-1] if mirrored else tris


def random_soup(seed, count, low=-0.1, high=1.1):
    rng = np.random.default_rng(seed)
    centre = rng.uniform(low, high, size=(count, 1, 2))
    return centre + rng.normal(scale=rng.uniform(0.005, 0.3, size=(count, 1, 1)), size=(count, 3, 2))


def edge_cases():
    # Corners near the float64 limit differ by 1e292 or nothing: their squared edges overflow.
    huge, d = 1.2e307, 1e294
    bad = np.array([
        [[0.1, 0.1], [0.9, 0.9], [0.5, 0.5]],
        [[0.2, 0.2], [0.2, 0.2], [0.2, 0.2]],
        [[np.nan, 0.1], [0.9, 0.1], [0.1, 0.9]],
        [[np.inf, 0.1], [0.9, 0.1], [0.1, 0.9]],
        [[0.1, -np.inf], [0.9, 0.1], [0.1, 0.9]],
        [[1e300, 0.0], [-1e300, 0.0], [0.0, 1e300]],
        [[huge, huge], [huge + d, huge], [huge, huge + d]],
        [[-huge, -huge], [-huge - d, -huge], [-huge, -huge - d]],
        [[1e-3, 1e-3], [1e-3 + 1e-9, 1e-3], [1e-3, 1e-3 + 1e-9]],
        [[-1e150, -1e150], [1e150, -1e150], [0.0, 1e150]],  # live, edge functions near 1e300
        [[1e150, 1e150], [2e150, 1e150], [1e150, 2e150]],  # live, far away
    ])
    return np.concatenate([bad, UNIT_SQUARE * 0.6 + 0.2, bad[::-1]])


def slivers(width, height):
    # Thin triangles along a row of texel centres, a column of them, and a diagonal.
    yc = 2.5 / height
    xc = 3.5 / width
    return np.array([
        [[0.0, yc], [1.0, yc], [0.5, yc + 1e-7]],
        [[0.0, yc], [1.0, yc], [0.5, yc - 1e-9]],
        [[xc, 0.0], [xc, 1.0], [xc + 1e-8, 0.5]],
        [[0.0, 0.0], [1.0, 1.0], [0.5, 0.5 + 1e-6]],
        [[0.0, 0.0], [1.0, 1.0], [0.5 + 1e-12, 0.5]],
        [[0.05, 0.9], [0.95, 0.1], [0.95, 0.1 + 3e-4]],
    ])


COMPILED_CASES = {
    "soup": (random_soup(1, 300), 37, 29),
    "soup, non-square": (random_soup(2, 120), 7, 13),
    "soup, far outside": (random_soup(3, 200, -1.5, 2.5), 13, 7),
    "grid on centres and edges": (grid_mesh(16, 12, 8, 6), 8, 6),
    "grid on centres and edges, mirrored": (grid_mesh(16, 12, 8, 6, mirrored=True), 8, 6),
    "grid, non-square": (grid_mesh(14, 26, 7, 13), 7, 13),
    "grid on texel edges": (grid_mesh(8, 8, 16, 16), 16, 16),
    "grid of copies overlapping": (np.concatenate([grid_mesh(6, 6, 12, 12), grid_mesh(4, 4, 12, 12)]), 12, 12),
    "non-finite and degenerate": (edge_cases(), 7, 13),
    "partly outside": (np.array([[[-0.5, -0.3], [1.4, 0.2], [0.3, 1.7]], [[0.5, 0.5], [2.0, 0.5], [0.5, 2.0]]]), 11, 9),
    "one triangle over everything": (np.concatenate([[[[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]]],
                                                     random_soup(4, 20)]), 64, 48),
    "slivers": (slivers(16, 12), 16, 12),
    "empty": (np.zeros((0, 3, 2)), 7, 13),
    "nothing claimed": (np.array([[[0.01, 0.01], [0.02, 0.01], [0.01, 0.02]]]), 8, 8),
    "one texel": (UNIT_SQUARE, 1, 1),
}


@pytest.mark.parametrize("case", list(COMPILED_CASES))
def test_compiled_rasterize_is_bitwise_the_numpy_code(case):
    corner_uv, width, height = COMPILED_CASES[case]
    reference = compiled_matches_numpy(corner_uv, width, height)
    if case.startswith("grid") and "copies" not in case:
        assert reference.coverage.all() and reference.overlap_count == 0


def test_compiled_rasterize_of_float32_uvs_is_bitwise_the_numpy_code():
    compiled_matches_numpy(random_soup(5, 100).astype(np.float32), 24, 20)
    compiled_matches_numpy(np.asfortranarray(random_soup(6, 50)), 20, 24)


@settings(max_examples=100, suppress_health_check=[HealthCheck.too_slow])
@given(triangles, sizes, sizes)
def test_compiled_rasterize_of_random_triangles_is_bitwise_the_numpy_code(tris, width, height):
    compiled_matches_numpy(np.array(tris, np.float64), width, height)


@settings(max_examples=100, suppress_health_check=[HealthCheck.too_slow])
@given(partitions())
def test_compiled_rasterize_of_partitions_is_bitwise_the_numpy_code(partition):
    compiled_matches_numpy(*partition)


# ---------------------------------------------------------------------------------------
# dilate


def chessboard_distance(coverage: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(coverage)
    yy, xx = np.mgrid[: coverage.shape[0], : coverage.shape[1]]
    return np.min(np.maximum(abs(yy[..., None] - ys), abs(xx[..., None] - xs)), axis=-1)


@pytest.mark.parametrize("margin", [0, 1, 2, 5])
def test_dilate_fills_exactly_the_ring_within_margin(margin):
    rng = np.random.default_rng(1)
    coverage = np.zeros((30, 40), bool)
    coverage[10:14, 5:9] = True
    coverage[20:22, 25:35] = True
    coverage[0, 39] = True
    image = rng.normal(size=(30, 40, 3)).astype(np.float32)
    image[~coverage] = np.nan  # never read
    out, filled = dilate(image, coverage, margin)
    distance = chessboard_distance(coverage)
    assert np.array_equal(filled, (distance > 0) & (distance <= margin))
    assert not np.isnan(out).any()
    assert np.array_equal(out[coverage], image[coverage])
    assert np.all(out[~coverage & ~filled] == 0)
    assert out.dtype == np.float32 and out.shape == image.shape


def test_dilate_takes_the_mean_of_filled_neighbours():
    coverage = np.zeros((3, 5), bool)
    coverage[1, 1] = coverage[1, 3] = True
    image = np.zeros((3, 5, 1), np.float32)
    image[1, 1] = 2.0
    image[1, 3] = 4.0
    out, filled = dilate(image, coverage, 1)
    assert out[1, 2, 0] == pytest.approx(3.0)
    assert out[0, 0, 0] == pytest.approx(2.0)
    assert out[2, 4, 0] == pytest.approx(4.0)
    assert filled.sum() == 13


def test_dilate_constant_stays_constant_and_2d_images_work():
    coverage = np.zeros((16, 16), bool)
    coverage[6:9, 7:9] = True
    image = np.where(coverage, 0.7, 0.0).astype(np.float32)
    out, filled = dilate(image, coverage, 3)
    assert out.shape == (16, 16)
    np.testing.assert_allclose(out[coverage | filled], 0.7, rtol=1e-6)


def test_dilate_degenerate_coverage():
    image = np.ones((4, 4, 2), np.float32)
    out, filled = dilate(image, np.zeros((4, 4), bool), 3)
    assert not filled.any() and np.all(out == 0)
    out, filled = dilate(image, np.ones((4, 4), bool), 3)
    assert not filled.any() and np.all(out == 1)
    with pytest.raises(ValueError):
        dilate(image, np.ones((4, 4), bool), -1)
    with pytest.raises(ValueError):
        dilate(image, np.ones((4, 5), bool), 1)
