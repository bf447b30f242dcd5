"""The GPU gather against core.transport.gather.gather on the same random tables.

Tolerance: both sum the same float32 terms per direction; only the order of the sums
(per worker in numpy, per sample on the GPU) and fused multiply-adds differ, so they
agree to ~1e-5 relative for sums of a few hundred terms. 1e-4 relative plus 1e-6
absolute bounds that with room, and catches any misplaced texel (errors of order 1).
The same tolerance holds with vertex-mode objects: their barycentric mix is the same
float32 expression in the same order on both sides, and a wrong corner or a wrong
nearest-corner pick (the weights of those cases include exact ties) is an error of
order 1.
"""
import numpy as np
import pytest

RTOL, ATOL = 1e-4, 1e-6


def _random_codes(core, rng, samples, directions, objects):
    """Directions, unit normals, random hit codes (below the horizon where the direction
    faces away, as the tracer writes them) and hit coordinates."""
    dirs = core.visibility.directions.spherical_fibonacci(directions)
    normals = rng.normal(size=(samples, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    codes = rng.choice([-3, -2, -1] + list(range(objects)), size=(directions, samples),
                       p=[0.05, 0.35, 0.2] + [0.4 / objects] * objects).astype(np.int16)
    codes[(dirs @ normals.T) <= 0] = core.visibility.table.BELOW_HORIZON
    uv = rng.uniform(-0.05, 1.05, size=(directions, samples, 2)).astype(np.float32)
    return dirs, normals, codes, uv


def _case(core, rng, layout, dirs, normals, codes, uv, channels, triangles=None, vertex_cells=None):
    table = core.visibility.table.VisibilityTable.from_values(dirs, codes, uv, np.ones(codes.shape, np.float32),
                                                          triangles, vertex_cells)
    scale = core.transport.gather.gather_normalisation(table, normals, np.pi)
    radiance = rng.uniform(0, 2, size=(layout.size, channels)).astype(np.float32)
    world = rng.uniform(0, 1, size=(len(dirs), channels))
    return table, normals, scale, layout, radiance, world


def _random_case(core, samples=3000, directions=96, objects=3, channels=3, seed=0):
    rng = np.random.default_rng(seed)
    sizes = [(int(rng.integers(3, 40)), int(rng.integers(3, 40))) for _ in range(objects)]
    layout = core.transport.gather.AtlasLayout.from_sizes(sizes)
    dirs, normals, codes, uv = _random_codes(core, rng, samples, directions, objects)
    return _case(core, rng, layout, dirs, normals, codes, uv, channels)


# Barycentrics with exactly equal largest weights in float32 (w0 = 1 - u - v): the
# nearest-vertex lookup must pick the first of them, as np.argmax does.
TIES = [(0.5, 0.5), (0.25, 0.5), (0.25, 0.25), (0.4, 0.4), (0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.25)]


def _vertex_case(core, samples=3000, directions=96, objects=6, channels=3, nearest=False, seed=0):
    """Like _random_case, with every other object in vertex mode (a one-row atlas of its
    samples, hit by triangle and barycentrics)."""
    rng = np.random.default_rng(seed)
    sizes, corner_samples = [], []
    for index in range(objects):
        if index % 2:
            count = int(rng.integers(3, 60))
            corners = rng.integers(0, count, size=(int(rng.integers(1, 80)), 3))
            corners[rng.random(len(corners)) < 0.05] = -1  # degenerate triangles
            sizes.append((count, 1))
            corner_samples.append(corners)
        else:
            sizes.append((int(rng.integers(3, 40)), int(rng.integers(3, 40))))
            corner_samples.append(None)
    layout = core.transport.gather.AtlasLayout.from_sizes(sizes, corner_samples, nearest)
    dirs, normals, codes, uv = _random_codes(core, rng, samples, directions, objects)
    triangles = np.zeros((directions, samples), np.int32)
    for index, corners in enumerate(corner_samples):
        if corners is None:
            continue
        on = codes == index
        triangles[on] = rng.integers(0, len(corners), size=int(on.sum()))
        bary = rng.uniform(0, 1, size=(int(on.sum()), 2))
        folded = bary.sum(axis=1) > 1
        bary[folded] = 1 - bary[folded][:, ::-1]
        tied = rng.random(len(bary)) < 0.2
        bary[tied] = np.array(TIES)[rng.integers(0, len(TIES), size=int(tied.sum()))]
        uv[on] = bary.astype(np.float32)
    cells = core.visibility.table.vertex_cells([1 if c is None else len(c) for c in corner_samples],
                                               [c is not None for c in corner_samples])
    return _case(core, rng, layout, dirs, normals, codes, uv, channels, triangles, cells)



def _gather(function, visibake, table, normals, scale, layout, radiance, world, exclude=None, samples=None,
            **keywords):
    """A gather (GPU or CPU twin) through the transport contract's structures."""
    contract = visibake.core.transport.contract
    return function(contract.GatherGeometry(table, normals, scale, layout),
                    contract.GatherSource(radiance, world, exclude), samples=samples, **keywords)


def _report(name, ours, twin):
    difference = np.abs(ours - twin)
    relative = difference / np.maximum(np.abs(twin), 1e-30)
    print(f"\n{name}: max |GPU - numpy| {difference.max():.3g}, "
          f"max relative (where |numpy| > 1e-3) {relative[np.abs(twin) > 1e-3].max(initial=0):.3g}")


@pytest.mark.parametrize("channels", [3, 6, 15, 51])
def test_gather_matches_numpy(visibake, gpu_shaders, channels):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, channels=channels, seed=channels)
    ours = _gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, radiance, world)
    twin = _gather(core.transport.gather.gather, visibake, table, normals, scale, layout, radiance, world)
    assert ours.shape == twin.shape == (len(normals), channels)
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL)
    assert np.abs(twin).max() > 0.1  # the case is not trivially zero


def test_exclusions_samples_and_small_batches_match_numpy(visibake, gpu_shaders):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, samples=2500, objects=70, seed=7)
    rng = np.random.default_rng(3)
    exclude = rng.random((len(normals), 70)) < 0.3
    chosen = np.sort(rng.choice(len(normals), 900, replace=False))
    # A budget that holds the fixed textures and only a few directions: many batches.
    fixed = 4 * (2500 * 4 * 3) + layout.size * 16 + 200_000
    case = (table, normals, scale, layout, radiance, world)
    ours = _gather(gpu_shaders.gather.gather, visibake, *case, exclude=exclude, samples=chosen,
                   budget_bytes=fixed + 5 * 2048 * 2 * 12)
    twin = _gather(core.transport.gather.gather, visibake, *case, exclude=exclude, samples=chosen)
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL)
    assert np.all(ours[np.setdiff1d(np.arange(len(normals)), chosen)] == 0)


@pytest.mark.parametrize("nearest", [False, True], ids=["interpolate", "nearest"])
@pytest.mark.parametrize("channels", [3, 15, 51])
def test_vertex_objects_match_numpy(visibake, gpu_shaders, channels, nearest):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _vertex_case(core, channels=channels, nearest=nearest,
                                                                  seed=100 + channels + nearest)
    assert layout.is_vertex is not None and layout.is_vertex.any() and not layout.is_vertex.all()
    ours = _gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, radiance, world)
    twin = _gather(core.transport.gather.gather, visibake, table, normals, scale, layout, radiance, world)
    _report(f"vertex objects, {channels} channels, nearest={nearest}", ours, twin)
    assert ours.shape == twin.shape == (len(normals), channels)
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL)
    assert np.abs(twin).max() > 0.1
    # The vertex objects matter: with their radiance zeroed the result changes.
    vertex_rows = np.zeros(layout.size, bool)
    for index in np.nonzero(layout.is_vertex)[0]:
        start = layout.offsets[index]
        vertex_rows[start:start + (layout.widths[index] + 1) * 2] = True
    dark = np.where(vertex_rows[:, None], 0, radiance).astype(np.float32)
    without = _gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, dark, world)
    assert np.abs(without - ours).max() > 0.1


@pytest.mark.parametrize("nearest", [False, True], ids=["interpolate", "nearest"])
def test_vertex_objects_with_exclusions_samples_and_small_batches_match_numpy(visibake, gpu_shaders, nearest):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _vertex_case(core, samples=2500, objects=70, channels=6,
                                                                  nearest=nearest, seed=11 + nearest)
    rng = np.random.default_rng(5)
    exclude = rng.random((len(normals), 70)) < 0.3
    chosen = np.sort(rng.choice(len(normals), 900, replace=False))
    gather = gpu_shaders.gather
    texels = 2048 * 2  # the sample grid of 2500 samples
    per_direction = texels * (gather.TABLE_BYTES_PER_ENTRY + gather.VERTEX_BYTES_PER_ENTRY)
    # The fixed textures, from above: normals, 2 accumulator and 2 exclusion layers (16
    # bytes per texel each), radiance (2 layers of 4096 wide rows), the corner table (16
    # bytes per texel, 4096 wide rows, 2 texels per triangle), the small rest.
    rows = -(-layout.size // 4096)
    corner_rows = -(-2 * len(layout.corner_flat) // 4096)
    fixed = 5 * 16 * texels + 32 * 4096 * rows + 16 * 4096 * corner_rows + 10_000
    progress = []
    case = (table, normals, scale, layout, radiance, world)
    ours = _gather(gather.gather, visibake, *case, exclude=exclude, samples=chosen,
                   budget_bytes=fixed + 5 * per_direction, progress=progress.append)
    twin = _gather(core.transport.gather.gather, visibake, *case, exclude=exclude, samples=chosen)
    _report(f"vertex objects, exclusions, {len(progress)} batches, nearest={nearest}", ours, twin)
    assert len(progress) >= 12  # many batches (the budget holds a few directions)
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL)
    assert np.abs(twin).max() > 0.1
    assert np.all(ours[np.setdiff1d(np.arange(len(normals)), chosen)] == 0)


def test_vertex_objects_add_the_hit_triangle_to_each_batch(visibake):
    import importlib

    gather = importlib.import_module(f"{visibake.__name__}.gpu_shaders.gather")
    samples, fixed, budget = 1 << 20, 100 << 20, 1 << 30
    atlas = gather.batch_directions(samples, budget, fixed)
    vertex = gather.batch_directions(samples, budget, fixed, vertex=True)
    assert atlas == (budget - fixed) // (samples * 12)
    assert vertex == (budget - fixed) // (samples * 16) < atlas


def test_a_budget_too_small_for_one_direction_is_refused(visibake, gpu_shaders):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, samples=500, directions=8)
    with pytest.raises(MemoryError, match="GPU budget"):
        _gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, radiance, world, budget_bytes=1000)


def test_a_1024_atlas_with_256_directions_fits_the_default_budget(visibake):
    # The planner alone (no GPU needed): a 1024 x 1024 atlas fully covered, 256
    # directions, RGB. Fixed textures: normals, accumulator, radiance (16 bytes per
    # sample or texel each), the rest is small; each batch adds 12 bytes per sample
    # and direction. Everything must stay within the default 1 GiB.
    import importlib

    gather = importlib.import_module(f"{visibake.__name__}.gpu_shaders.gather")
    samples = 1024 * 1024
    fixed = 3 * 16 * samples + 1_000_000
    batch = gather.batch_directions(samples, gather.DEFAULT_BUDGET_BYTES, fixed)
    assert batch >= 32
    assert fixed + batch * samples * gather.TABLE_BYTES_PER_ENTRY <= gather.DEFAULT_BUDGET_BYTES
    batches = -(-256 // batch)
    print(f"\n1024^2 atlas, 256 directions, 1 GiB: {batch} directions per batch, {batches} batches")
    assert batches <= 8


def test_direction_subsets_match_numpy_and_add_up(visibake, gpu_shaders):
    """The scale-out contract on the GPU: each direction range matches the CPU twin's, and
    the ranges together give the whole gather."""
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, channels=6, seed=21)
    chunks = core.transport.contract.direction_chunks(len(table.directions), 3)
    parts = [_gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, radiance, world,
                     directions=chunk) for chunk in chunks]
    for chunk, part in zip(chunks, parts):
        twin = _gather(core.transport.gather.gather, visibake, table, normals, scale, layout, radiance, world,
                       directions=chunk)
        np.testing.assert_allclose(part, twin, rtol=RTOL, atol=ATOL)
    whole = _gather(gpu_shaders.gather.gather, visibake, table, normals, scale, layout, radiance, world)
    np.testing.assert_allclose(sum(parts), whole, rtol=RTOL, atol=ATOL)
    assert np.abs(whole).max() > 0.1
