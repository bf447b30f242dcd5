"""The GPU gather against core.transport.gather on the same random tables.

Tolerance: both sum the same float32 terms per direction; only the order of the sums
(per worker in numpy, per sample on the GPU) and fused multiply-adds differ, so they
agree to ~1e-5 relative for sums of a few hundred terms. 1e-4 relative plus 1e-6
absolute bounds that with room, and catches any misplaced texel (errors of order 1).
"""
import numpy as np
import pytest

RTOL, ATOL = 1e-4, 1e-6


def _random_case(core, samples=3000, directions=96, objects=3, channels=3, seed=0):
    rng = np.random.default_rng(seed)
    sizes = [(int(rng.integers(3, 40)), int(rng.integers(3, 40))) for _ in range(objects)]
    layout = core.transport.AtlasLayout.from_sizes(sizes)
    dirs = core.directions.spherical_fibonacci(directions)
    normals = rng.normal(size=(samples, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    codes = rng.choice([-3, -2, -1] + list(range(objects)), size=(directions, samples),
                       p=[0.05, 0.35, 0.2] + [0.4 / objects] * objects).astype(np.int16)
    # Below-horizon entries where the direction faces away, as the tracer writes them.
    codes[(dirs @ normals.T) <= 0] = core.visibility.BELOW_HORIZON
    uv = rng.uniform(-0.05, 1.05, size=(directions, samples, 2)).astype(np.float32)
    table = core.visibility.VisibilityTable(directions=dirs, hit_object=codes, hit_uv=uv,
                                            hit_distance=np.ones((directions, samples), np.float32))
    scale = core.transport.gather_normalisation(table, normals)
    radiance = rng.uniform(0, 2, size=(layout.size, channels)).astype(np.float32)
    world = rng.uniform(0, 1, size=(directions, channels))
    return table, normals, scale, layout, radiance, world


@pytest.mark.parametrize("channels", [3, 6, 15, 51])
def test_gather_matches_numpy(visibake, gpu_shaders, channels):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, channels=channels, seed=channels)
    ours = gpu_shaders.gather.gather(table, normals, scale, layout, radiance, world)
    twin = core.transport.gather(table, normals, scale, layout, radiance, world)
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
    ours = gpu_shaders.gather.gather(table, normals, scale, layout, radiance, world, exclude=exclude,
                                     samples=chosen, budget_bytes=fixed + 5 * 2048 * 2 * 12)
    twin = core.transport.gather(table, normals, scale, layout, radiance, world, exclude=exclude, samples=chosen)
    np.testing.assert_allclose(ours, twin, rtol=RTOL, atol=ATOL)
    assert np.all(ours[np.setdiff1d(np.arange(len(normals)), chosen)] == 0)


def test_a_budget_too_small_for_one_direction_is_refused(visibake, gpu_shaders):
    core = visibake.core
    table, normals, scale, layout, radiance, world = _random_case(core, samples=500, directions=8)
    with pytest.raises(MemoryError, match="GPU budget"):
        gpu_shaders.gather.gather(table, normals, scale, layout, radiance, world, budget_bytes=1000)


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
