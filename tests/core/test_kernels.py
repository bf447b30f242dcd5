"""The compiled CPU kernels (core.kernels) against the numpy passes they replace, their
determinism across thread counts and call splits, and the numpy fallback."""
import json
import os
import subprocess
import sys
from dataclasses import astuple

import numpy as np
import pytest

from core import kernels
from core.transport import gather as gather_module
from core.transport.contract import GatherGeometry, GatherSource
from core.transport.gather import AtlasLayout, ambient_occlusion, gather, gather_normalisation, gather_numpy
from core.visibility.directions import spherical_fibonacci
from core.visibility.table import BELOW_HORIZON, VisibilityTable, vertex_cells

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

pytestmark = pytest.mark.skipif(kernels.compiled() is None,
                                reason=f"numba kernels unavailable here: {kernels.status().reason}")


def _random_scene(seed, samples=300, count=97, channels=6, vertex=True, nearest=False):
    """A table over two atlases and (with ``vertex``) one vertex-mode object, every kind of
    entry (hits, misses, backfaces, below the horizon), and radiance of ``channels`` channels."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(samples, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = spherical_fibonacci(count)
    above = (normals @ d.T).T > 0
    objects = 3 if vertex else 2
    hit = np.where(above, rng.integers(-3, objects, size=above.shape), BELOW_HORIZON).astype(np.int16)
    uv = rng.uniform(-0.1, 1.1, size=(count, samples, 2)).astype(np.float32)
    triangles = None
    corner_samples = None
    sizes = [(5, 3), (7, 9)]
    if vertex:
        vertex_samples = 10
        corners = rng.integers(0, vertex_samples, size=(12, 3))
        triangles = rng.integers(0, 12, size=(count, samples)).astype(np.int32)
        on_vertex = hit == 2
        bary = rng.uniform(0, 1, size=(count, samples, 2)).astype(np.float32)
        bary = np.where(bary.sum(axis=2, keepdims=True) > 1, 1 - bary, bary)
        uv = np.where(on_vertex[..., None], bary, uv).astype(np.float32)
        sizes.append((vertex_samples, 1))
        corner_samples = [None, None, corners]
    table = VisibilityTable.from_values(d, hit, uv, np.ones((count, samples), np.float32), hit_triangle=triangles,
                                        vertex_cells=None if triangles is None else vertex_cells([1, 1, 12], [0, 0, 1]))
    layout = AtlasLayout.from_sizes(sizes, corner_samples, nearest_vertex=nearest)
    radiance = rng.uniform(0, 3, size=(layout.size, channels)).astype(np.float32)
    world = rng.uniform(0, 1, size=(count, channels))
    exclude = rng.random((samples, objects)) < 0.2
    return table, normals, layout, radiance, world, exclude


# Three channels (one light group's RGB) take the kernel's unrolled lookup; six, its general one.
@pytest.mark.parametrize("vertex, nearest, channels", [(False, False, 6), (True, False, 6), (True, True, 6),
                                                       (False, False, 3), (True, False, 3)])
def test_compiled_gather_matches_numpy(vertex, nearest, channels):
    table, normals, layout, radiance, world, exclude = _random_scene(1, vertex=vertex, nearest=nearest,
                                                                     channels=channels)
    scale = gather_normalisation(table, normals, np.pi)
    geometry = GatherGeometry(table, normals, scale, layout, threads=2)
    for source in (GatherSource(radiance, world, exclude), GatherSource(radiance, np.zeros(channels)),
                   GatherSource(radiance, world[0])):
        compiled = gather(geometry, source)
        reference = gather_numpy(geometry, source)
        assert np.any(compiled > 0)
        np.testing.assert_allclose(compiled, reference, rtol=2e-6, atol=1e-9)


@pytest.mark.parametrize("dark", [[0], [2], [0, 1, 2]])
def test_entries_on_dark_objects_are_skipped_and_the_gather_is_bitwise_the_same(dark):
    """An object whose atlas holds only zeros (every non-emitter in an emission gather) is not
    looked up: the sums are bitwise those of a gather that looks every entry up."""
    table, normals, layout, radiance, world, exclude = _random_scene(7, vertex=True, channels=3)
    for index in dark:
        start = layout.offsets[index]
        stop = layout.offsets[index + 1] if index + 1 < len(layout.offsets) else layout.size
        radiance[start:stop] = 0.0
    lit = layout.lit_objects(radiance)
    assert lit.tolist() == [index not in dark for index in range(3)]
    geometry = GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi), layout, threads=2)
    chosen = np.arange(len(normals), dtype=np.int64)
    for source in (GatherSource(radiance, world, exclude), GatherSource(radiance, np.zeros(3))):
        before, after = gather_module.gather_kernel_arguments(geometry, source, chosen)
        assert np.array_equal(after[-2], lit)
        every = (*after[:-2], np.ones(3, bool), np.zeros_like(after[-1]))
        kernels.run(kernels.compiled().gather, 2, *before, 0, len(table.directions), *after)
        kernels.run(kernels.compiled().gather, 2, *before, 0, len(table.directions), *every)
        assert np.array_equal(after[-1], every[-1])
        np.testing.assert_allclose(after[-1], gather_numpy(geometry, source), rtol=2e-6, atol=1e-9)


def test_compiled_gather_of_chosen_samples_and_direction_ranges_matches_numpy():
    table, normals, layout, radiance, world, exclude = _random_scene(2)
    geometry = GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi), layout, threads=2)
    source = GatherSource(radiance, world, exclude)
    chosen = np.array([5, 0, 299, 17, 17, 120])
    np.testing.assert_allclose(gather(geometry, source, samples=chosen, directions=range(10, 60)),
                               gather_numpy(geometry, source, samples=chosen, directions=range(10, 60)),
                               rtol=2e-6, atol=1e-9)
    empty = gather(geometry, source, samples=np.zeros(0, np.int64))
    assert empty.shape == (300, 6) and not np.any(empty)


def test_the_bare_walk_reads_one_texel_per_hit_entry_walking_words_or_finding_each_entry():
    from core.visibility.table import decode_uv

    table, normals, layout, radiance, *_ = _random_scene(4, samples=300)
    entries = table.entries
    objects, uv = entries.dense("hit_object"), decode_uv(entries.dense("hit_uv_code"))
    widths, heights, offsets = (np.asarray(a, np.int64) for a in (layout.widths, layout.heights, layout.offsets))

    def walk(samples, first, stop):
        out = np.zeros((len(samples), radiance.shape[1]))
        kernels.run(kernels.compiled().bare_lookup, 2, entries.above_words, entries.word_base, entries.hit_object,
                    entries.hit_uv_code, samples, first, stop, radiance, widths, heights, offsets, out)
        return out

    def expected(samples, first, stop):
        out = np.zeros((len(samples), radiance.shape[1]))
        for i in range(first, stop):
            for j, s in enumerate(samples):
                obj = objects[i, s]
                if obj >= 0:
                    x = np.int64(uv[i, s, 0] * np.float32(widths[obj]))
                    y = np.int64(uv[i, s, 1] * np.float32(heights[obj]))
                    out[j] += radiance[offsets[obj] + y * (widths[obj] + 1) + x]
        return out

    # Every sample (whole words, the last one partial), a run not starting on a word, a scattered choice.
    for samples in (np.arange(300), np.arange(70, 300), np.array([5, 0, 299, 17, 17, 120]), np.arange(64)):
        samples = samples.astype(np.int64)
        np.testing.assert_allclose(walk(samples, 3, 40), expected(samples, 3, 40), rtol=1e-6)


def test_normalisation_and_ambient_occlusion_match_numpy(monkeypatch):
    table, normals, *_ = _random_scene(3, vertex=False)
    scale = gather_normalisation(table, normals, np.pi)
    occlusion = ambient_occlusion(table, normals, scale)
    monkeypatch.setattr(kernels, "_module", None)  # the numpy passes, as where numba cannot load
    # float32 cosines: numpy's dot product rounds in another order (a few ULPs).
    np.testing.assert_allclose(scale, gather_normalisation(table, normals, np.pi), rtol=1e-6)
    np.testing.assert_allclose(occlusion, ambient_occlusion(table, normals, scale), rtol=1e-12, atol=1e-15)
    assert np.any(scale > 0) and np.any((occlusion > 0) & (occlusion < 1))


def test_gather_is_bitwise_the_same_for_any_thread_count_and_call_split(monkeypatch):
    """Each sample sums its directions in one fixed order, whatever the threads or the
    number of kernel calls the directions are walked in (the scale-out contract)."""
    table, normals, layout, radiance, world, exclude = _random_scene(4, samples=1000)
    scale = gather_normalisation(table, normals, np.pi, threads=1)
    assert np.array_equal(scale, gather_normalisation(table, normals, np.pi, threads=2))
    source = GatherSource(radiance, world, exclude)
    results = [gather(GatherGeometry(table, normals, scale, layout, threads=t), source) for t in (1, 2)]
    monkeypatch.setattr(gather_module, "LOOKUPS_PER_CALL", 3000)  # three directions a call
    calls = []
    results.append(gather(GatherGeometry(table, normals, scale, layout, threads=2), source, progress=calls.append))
    assert len(calls) == 33 and calls[-1] == 1.0
    for result in results[1:]:
        assert np.array_equal(result, results[0])


def _run_python(code, **environment):
    env = dict(os.environ, **environment)
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


_STATUS_AND_FURNACE = """
import json, numpy as np
from core import kernels
from core.transport.contract import GatherGeometry, GatherSource
from core.transport.gather import AtlasLayout, gather, gather_normalisation
from core.visibility.directions import spherical_fibonacci
from core.visibility.table import MISS, BELOW_HORIZON, VisibilityTable
normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
d = spherical_fibonacci(64)
hit = np.where((normals @ d.T).T > 0, MISS, BELOW_HORIZON).astype(np.int16)
table = VisibilityTable.from_values(d, hit, np.zeros((64, 2, 2), np.float32), np.ones((64, 2), np.float32))
layout = AtlasLayout.from_sizes([(2, 2)])
e = gather(GatherGeometry(table, normals, gather_normalisation(table, normals, np.pi), layout),
           GatherSource(np.zeros((layout.size, 3), np.float32), np.ones(3)))
print(json.dumps({"status": kernels.status().as_dict(), "line": kernels.status().describe(),
                  "furnace": float(np.max(np.abs(e - np.pi)))}))
"""


@pytest.mark.parametrize("switch, reason", [("numpy", "VISIBAKE_KERNELS=numpy"),
                                            ("fortran", "neither 'numba' nor 'numpy'")])
def test_the_numpy_fallback_runs_and_says_why(switch, reason):
    result = _run_python(_STATUS_AND_FURNACE, VISIBAKE_KERNELS=switch)
    assert result["status"]["backend"] == "numpy"
    assert reason in result["status"]["reason"] and reason in result["line"]
    assert result["furnace"] < 1e-5


# The furnace of _STATUS_AND_FURNACE with the package imported as Blender imports the
# extension's: under a dotted name whose parents (the extension's __init__ needs bpy) stand empty.
_EXTENSION_PACKAGE = "bl_ext.user_default.visibake.core"
_AS_EXTENSION = f"""
import importlib, importlib.util, os, sys, types
for depth in range(1, 4):
    name = ".".join({_EXTENSION_PACKAGE!r}.split(".")[:depth])
    sys.modules[name] = types.ModuleType(name)
    sys.modules[name].__path__ = []
spec = importlib.util.spec_from_file_location({_EXTENSION_PACKAGE!r}, os.path.join("core", "__init__.py"),
                                              submodule_search_locations=[os.path.abspath("core")])
sys.modules[{_EXTENSION_PACKAGE!r}] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(sys.modules[{_EXTENSION_PACKAGE!r}])
""" + _STATUS_AND_FURNACE.replace("from core", "from " + _EXTENSION_PACKAGE)


def test_first_use_compiles_into_the_configured_folder_and_later_loads_read_it(tmp_path):
    # One cold compile (a minute or two on a CI machine) checks both ways of choosing the
    # folder: configure() before the first load (a later call moves nothing), then
    # NUMBA_CACHE_DIR alone, which must read what the first process compiled, helpers included
    # (each under the package's import name, here the extension's).
    cache = str(tmp_path / "kernels")
    configured = _AS_EXTENSION.replace("import json, numpy as np\n", "import json, numpy as np\n"
                                       f"from {_EXTENSION_PACKAGE} import kernels; kernels.configure({cache!r})\n")
    configured = configured.replace("print(json.dumps({", "kernels.configure('/elsewhere')\n"
                                    "print(json.dumps({'root': kernels.cache_root(), 'left': "
                                    "[n for n in os.listdir(__import__('tempfile').gettempdir()) "
                                    "if n.startswith('visibake-compile-')], ")
    first = _run_python(configured, NUMBA_CACHE_DIR=str(tmp_path / "not-this-one"), VISIBAKE_KERNELS="numba",
                        VISIBAKE_COMPILE_HELPERS="", TMPDIR=str(tmp_path))
    second = _run_python(_AS_EXTENSION, NUMBA_CACHE_DIR=cache, VISIBAKE_KERNELS="numba")
    assert first["status"]["backend"] == second["status"]["backend"] == "numba"
    assert first["status"]["compiled"] and not second["status"]["compiled"]
    assert "compiled on first use" in first["line"] and "from the kernel cache" in second["line"]
    # Helper processes shared the compile wherever there is a core to spare, and cleaned up.
    assert first["status"]["helpers"] == min(3, (os.cpu_count() or 1) - 1) and not first["left"]
    assert second["status"]["helpers"] == 0
    # One folder per import name of the package, inside the one asked for.
    folder = os.path.join(cache, _EXTENSION_PACKAGE)
    assert first["status"]["cache_dir"] == second["status"]["cache_dir"] == folder
    assert first["root"] == cache and os.listdir(folder)
    assert not os.path.exists(tmp_path / "not-this-one")
    assert first["furnace"] < 1e-5 and second["furnace"] < 1e-5


@pytest.mark.parametrize("vertex", [False, True])
@pytest.mark.parametrize("masked", [False, True])
def test_compiled_table_writes_are_bitwise_those_of_numpy(vertex, masked):
    from core.visibility import table as table_module

    rng = np.random.default_rng(7)
    count, samples, objects, triangles_per_object = 9, 200, 3, 5
    geometry = table_module.HitGeometry(
        corner_uv=rng.uniform(-0.05, 1.05, (objects * triangles_per_object, 3, 2)).astype(np.float32),
        triangle_offset=np.arange(objects, dtype=np.int64) * triangles_per_object,
        face_normals=rng.normal(size=(objects * triangles_per_object, 3)),
        vertex_object=np.array([False, True, False]) if vertex else None)
    rows, cols = np.nonzero(rng.random((count, samples)) < 0.7)
    n = len(rows)
    hit_geometry = rng.integers(-1, objects, n).astype(np.int32)
    triangle = rng.integers(0, triangles_per_object, n).astype(np.int32)
    bary = rng.random((n, 2), dtype=np.float32)
    distance = np.where(rng.random(n) < 0.05, np.inf, rng.lognormal(0, 3, n)).astype(np.float32)
    # Distances on and next to the codes' boundaries, beyond both ends of the code range, and zero.
    splits = table_module.DISTANCE_SPLITS[rng.integers(0, len(table_module.DISTANCE_SPLITS), 60)]
    edges = np.concatenate([splits, np.nextafter(splits, np.inf), np.nextafter(splits, 0), [0.0, 1e-30, 1e30]])
    distance[:len(edges)] = edges.astype(np.float32)
    directions = rng.normal(size=(n, 3)).astype(np.float32)
    where = rng.random(n) < 0.5 if masked else None
    # An old table whose stored entries are the rays' (and a few more), partly overwritten when masked.
    stored = np.zeros((count, samples), bool)
    stored[rows, cols] = True
    stored |= rng.random((count, samples)) < 0.1
    old = np.where(stored, 1, table_module.BELOW_HORIZON).astype(np.int16)
    written = []
    for record in (table_module._record, table_module._record_numpy):
        entries = table_module.TableEntries.from_dense(old, np.zeros((count, samples, 2), np.uint16),
                                                       np.zeros((count, samples), np.uint16))
        entry = entries.index(rows, cols)
        assert np.all(entry >= 0)
        record(entries, geometry, directions, entry, hit_geometry, triangle, bary, distance, where)
        written.append(entries)
    for name in table_module.ENTRY_ARRAYS:
        np.testing.assert_array_equal(getattr(written[0], name), getattr(written[1], name), err_msg=name)
    assert np.any(written[0].hit_object == -3) and np.any(written[0].hit_uv_code > 0)
    if vertex:
        # The vertex-mode hits' triangles and barycentrics come back from their codes.
        on_vertices = written[0].hit_object[entry] == 1
        if masked:
            on_vertices &= where & (hit_geometry >= 0)
        table = VisibilityTable(np.zeros((count, 3)), written[0], vertex_cells=geometry.vertex_cells())
        back, barycentric = table.entry_vertex(entry[on_vertices])
        np.testing.assert_array_equal(back, triangle[on_vertices])
        steps = 65536 // geometry.vertex_cells()[1] - 1
        assert np.max(np.abs(barycentric - bary[on_vertices])) <= 0.5 / steps + 1e-7


def test_compiled_distance_codes_are_numpy_s_at_every_scale_and_at_the_codes_edges():
    # The kernel guesses a code from the float32's bits and steps to the answer: it must land
    # where numpy's search of the splits does, at the splits themselves, far outside the coded
    # range (subnormals, the largest floats) and at the octaves' edges.
    from core.visibility import table as table_module

    rng = np.random.default_rng(12)
    splits32 = table_module.DISTANCE_SPLITS.astype(np.float32)
    near_splits = np.concatenate([splits32, np.nextafter(splits32, np.float32(0)),
                                  np.nextafter(splits32, np.float32(np.inf))])
    octaves = np.float32(2.0) ** np.arange(-149, 128, dtype=np.float64).astype(np.float32)
    wide = np.float32(2.0) ** rng.uniform(-149, 127.9, 20000).astype(np.float32)
    extremes = np.array([0.0, -1.0, 3.4e38, np.inf, np.nan], np.float32)
    distance = np.concatenate([near_splits, octaves, np.nextafter(octaves, np.float32(0)), wide, extremes])
    count = len(distance)
    entries = table_module.TableEntries.from_dense(np.zeros((1, count), np.int16), np.zeros((1, count, 2), np.uint16),
                                                   np.zeros((1, count), np.uint16))
    geometry = table_module.HitGeometry(np.zeros((1, 3, 2), np.float32), np.zeros(1, np.int64), np.zeros((1, 3)))
    table_module._record(entries, geometry, np.tile([[0.0, 0.0, -1.0]], (count, 1)).astype(np.float32),
                         np.arange(count), np.zeros(count, np.int32), np.zeros(count, np.int32),
                         np.zeros((count, 2), np.float32), distance)
    np.testing.assert_array_equal(entries.hit_distance_code, table_module.encode_distance(distance))


@pytest.mark.parametrize("footprint, rotated, centre", [(False, False, 0.0), (True, True, 0.0),
                                                        (True, False, 1000.0), (False, True, -3.5)])
def test_compiled_rays_are_bitwise_those_of_numpy(monkeypatch, footprint, rotated, centre):
    from core.visibility import table as table_module
    from core.visibility.rays import RayScene

    rng = np.random.default_rng(11)
    samples, count = 300, 40
    # Points near the origin, on it, and far from it: every branch of the origin offset.
    positions = rng.normal(scale=rng.choice([1e-3, 1.0, 1e3], samples)[:, None], size=(samples, 3))
    positions[:5] = 0.0
    positions += centre
    normals = rng.normal(size=(samples, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64) + centre
    scene = RayScene([(quad, np.array([[0, 1, 2], [0, 2, 3]], np.int32))], 2, np.full(3, centre))
    rotations = None
    if rotated:
        rotations = np.stack([np.eye(3), np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])])
    request = table_module.TraceRequest(
        spherical_fibonacci(count), positions, normals,
        table_module.HitGeometry(np.zeros((2, 3, 2), np.float32), np.zeros(1, np.int64), np.zeros((2, 3))),
        footprint=rng.normal(scale=0.01, size=(samples, 4, 3)).astype(np.float32) if footprint else None,
        rotations=rotations, group=rng.integers(0, 2, samples) if rotated else None)
    direction_index, sample_index = np.nonzero(rng.random((count, samples)) < 0.5)
    compiled = request.rays(scene, direction_index, sample_index)
    # Into reused buffers, larger than needed and holding an earlier chunk's numbers.
    buffers = table_module.RayBuffers(len(direction_index) + 17)
    for name in ("origins", "directions"):
        getattr(buffers, name)[:] = 7
    buffered = [array.copy() for array in request.rays(scene, direction_index, sample_index, buffers)]
    monkeypatch.setattr(kernels, "_module", None)
    reference = request.rays(scene, direction_index, sample_index)
    for ours, kept, theirs in zip(compiled, buffered, reference):
        assert ours.dtype == kept.dtype == theirs.dtype == np.float32
        np.testing.assert_array_equal(ours, theirs)
        np.testing.assert_array_equal(kept, theirs)


def test_compiled_rays_to_trace_are_numpy_s_nonzero_for_any_thread_count(monkeypatch):
    from core.visibility.table import RayBuffers, rays_where

    rng = np.random.default_rng(5)
    above = rng.random((37, 211)) < 0.4
    above[3] = False  # a direction no sample sees
    above[4] = True
    above[:, 7] = False
    buffers = RayBuffers(above.size)
    buffers.direction_index[:] = -9
    buffers.sample_index[:] = -9
    for start, threads in ((0, 0), (1000, 1), (2**33, 2)):
        rows, cols = rays_where(above, start, buffers, threads)
        expected_rows, expected_cols = np.nonzero(above)
        assert rows.dtype == cols.dtype == np.int64
        np.testing.assert_array_equal(rows, expected_rows)
        np.testing.assert_array_equal(cols, expected_cols + start)
    # Without buffers, or with too small ones, it makes its own.
    rows, cols = rays_where(above, 3, RayBuffers(5))
    np.testing.assert_array_equal(cols, np.nonzero(above)[1] + 3)
    rows, cols = rays_where(np.zeros((4, 9), bool), 0)
    assert len(rows) == len(cols) == 0
    monkeypatch.setattr(kernels, "_module", None)
    rows, cols = rays_where(above, 1000, buffers)
    np.testing.assert_array_equal(rows, np.nonzero(above)[0])
    np.testing.assert_array_equal(cols, np.nonzero(above)[1] + 1000)


def test_compiled_horizon_bits_are_numpy_s_even_for_directions_in_the_horizon_s_plane(monkeypatch):
    from core.visibility.table import above_horizon, mask_of

    rng = np.random.default_rng(4)
    directions = spherical_fibonacci(97)
    normals = rng.normal(size=(333, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Normals at right angles to a direction (dot 0, or a rounding away from it either way),
    # and normals along the axes (exact zeros in the products).
    for k in range(0, 120, 3):
        d = directions[k % len(directions)]
        normals[k] = np.cross(d, rng.normal(size=3))
        normals[k] /= np.linalg.norm(normals[k])
    normals[200:206] = np.vstack([np.eye(3), -np.eye(3)])
    words, counts = above_horizon(directions, normals, 97 * 64, threads=2)
    dots = (directions[:, None, 0] * normals[None, :, 0] + directions[:, None, 1] * normals[None, :, 1]) \
        + directions[:, None, 2] * normals[None, :, 2]
    np.testing.assert_array_equal(mask_of(words, len(normals)), dots > 0.0)
    np.testing.assert_array_equal(counts, np.count_nonzero(dots > 0.0, axis=0))
    for threads in (1, 0):
        again = above_horizon(directions, normals, 97 * 64, threads=threads)
        np.testing.assert_array_equal(again[0], words)
    monkeypatch.setattr(kernels, "_module", None)
    for chunk_rays in (1, 97 * 64, 10**9):  # numpy, in batches of samples
        theirs = above_horizon(directions, normals, chunk_rays)
        np.testing.assert_array_equal(theirs[0], words)
        np.testing.assert_array_equal(theirs[1], counts)


def test_any_span_of_a_chunk_s_rays_is_that_span_of_the_whole_list():
    # Each thread of the trace lists its own span of a chunk's rays (rays_of_span): it must be
    # exactly that slice of the chunk's whole list, wherever the span starts (inside a word,
    # at a row's end, across rows without rays).
    from core.visibility.table import TableEntries, _row_offsets, mask_of, rays_of_entries, words_of

    rng = np.random.default_rng(8)
    samples = 300
    above = rng.random((23, samples)) < 0.45
    above[4] = False  # a direction no sample sees
    above[5] = False
    above[9, 64:192] = False  # whole words without rays
    entries = TableEntries.empty(words_of(above), samples)
    module = kernels.compiled()
    for first_word, last_word in ((0, 5), (1, 3), (4, 5), (2, 2)):
        whole = rays_of_entries(entries, first_word, last_word)
        row_offset, count = _row_offsets(entries, first_word, last_word)
        assert count == len(whole[0]) == np.count_nonzero(
            mask_of(entries.above_words[:, first_word:last_word], min(samples, 64 * last_word) - 64 * first_word))
        cuts = sorted({0, count, *rng.integers(0, count + 1, 12).tolist(), *row_offset.tolist()})
        for a, b in zip(cuts[:-1], cuts[1:]):
            span = [np.full(b - a, -1, np.int64) for _ in range(3)]
            module.rays_of_span(entries.above_words, entries.word_base, first_word, last_word, row_offset, a, *span)
            for ours, theirs in zip(span, whole):
                np.testing.assert_array_equal(ours, theirs[a:b])


@pytest.mark.parametrize("samples", [101, 128, 1])
def test_stored_entries_are_found_alike_compiled_and_in_numpy(monkeypatch, samples):
    from core.visibility.table import (
        BELOW_HORIZON,
        ENTRY_ARRAYS,
        TableEntries,
        entries_at,
        mask_of,
        rays_of_entries,
        words_of,
    )

    rng = np.random.default_rng(7)
    shape = (37, samples)
    hit_object = rng.integers(-3, 4, shape).astype(np.int16)
    hit_object[5] = BELOW_HORIZON  # a row with nothing stored
    hit_object[:, 0] = 2  # a column with everything stored
    hit_uv_code = rng.integers(0, 65536, (*shape, 2), np.uint16)
    hit_distance_code = rng.integers(0, 65536, shape, np.uint16)
    entries = TableEntries.from_dense(hit_object, hit_uv_code, hit_distance_code)
    stored = hit_object != BELOW_HORIZON
    np.testing.assert_array_equal(mask_of(words_of(stored), samples), stored)
    assert entries.stored == np.count_nonzero(stored) and entries.above_words.shape == (37, -(-samples // 64))
    # The dense view gives back every stored entry, and no-entry values elsewhere.
    for name, dense in (("hit_object", hit_object), ("hit_uv_code", hit_uv_code),
                        ("hit_distance_code", hit_distance_code)):
        fill = ENTRY_ARRAYS[name][2]
        np.testing.assert_array_equal(entries.dense(name), np.where(stored[(...,) + (None,) * (dense.ndim - 2)],
                                                                    dense, fill), err_msg=name)
        np.testing.assert_array_equal(entries.dense(name, 3, 9), entries.dense(name)[3:9], err_msg=name)
    direction, sample = np.meshgrid(np.arange(shape[0]), np.arange(samples), indexing="ij")
    direction, sample = direction.reshape(-1), sample.reshape(-1)
    numpy_index = entries.index(direction, sample)
    np.testing.assert_array_equal(numpy_index, np.where(stored.reshape(-1), np.cumsum(stored.reshape(-1)) - 1, -1))
    np.testing.assert_array_equal(entries_at(entries, direction, sample, threads=3), numpy_index)
    # Per-sample counts of a code among the stored entries (BELOW_HORIZON is never stored).
    for code in (2, -3, BELOW_HORIZON):
        expected = np.count_nonzero((hit_object == code) & stored, axis=0)
        np.testing.assert_array_equal(entries.per_sample(code), expected)
    words = entries.above_words.shape[1]
    compiled = [array.copy() for array in rays_of_entries(entries, 0, words)]
    compiled_part = [array.copy() for array in rays_of_entries(entries, words - 1, words)]
    monkeypatch.setattr(kernels, "_module", None)
    reference = rays_of_entries(entries, 0, words)
    part = rays_of_entries(entries, words - 1, words)
    np.testing.assert_array_equal(entries_at(entries, direction, sample), numpy_index)
    for code in (2, -3):
        np.testing.assert_array_equal(entries.per_sample(code), np.count_nonzero(hit_object == code, axis=0))
    expected_rows, expected_cols = np.nonzero(stored)
    for ours, theirs, expected in zip(compiled, reference, (expected_rows, expected_cols,
                                                             np.arange(entries.stored))):
        np.testing.assert_array_equal(ours, expected)
        np.testing.assert_array_equal(theirs, expected)
    last = expected_cols >= (words - 1) * 64
    for ours, theirs, expected in zip(compiled_part, part, (expected_rows[last], expected_cols[last],
                                                             np.nonzero(last)[0])):
        np.testing.assert_array_equal(ours, expected)
        np.testing.assert_array_equal(theirs, expected)


def test_compiled_footprints_are_bitwise_those_of_numpy_and_their_corners_agree(monkeypatch):
    from core.sampling import footprint as footprint_module

    # An irregular mesh with small and sliver triangles, seams and UVs off its faces' shapes:
    # many first draws miss, redraw, or fall back to the centre.
    rng = np.random.default_rng(11)
    count = 300
    corners = rng.normal(size=(count, 3, 3))
    corner_uv = rng.uniform(0, 1, (count, 3, 2)).astype(np.float32)
    corner_uv[::7, 2] = corner_uv[::7, 1]  # degenerate in UV
    width = height = 64
    triangle = rng.integers(0, count, 5000).astype(np.int32)
    pixel = rng.integers(0, width * height, 5000)
    pixel[:40] += np.int64(1) << 33  # the seeds keep a texel index's low 32 bits, both ways
    position = corners[triangle].mean(axis=1)
    arguments = (pixel, triangle, width, height, corner_uv, corners, position)
    for points in (1, 5, 64):  # the scrambled jitter alone: one point, a count not a power of two, a dense footprint
        np.testing.assert_array_equal(footprint_module.footprint_jitter(pixel, triangle, points, kernels.compiled(), 2),
                                      footprint_module.footprint_jitter(pixel, triangle, points))
    offsets = footprint_module.footprint_offsets(*arguments, 16, threads=3)
    box = footprint_module.footprint_corners(*arguments, offsets, threads=2)
    # The redraws are exercised: some slots land on a later draw, some never (the centre).
    monkeypatch.setattr(footprint_module, "REDRAWS", 1)
    first_only = footprint_module.footprint_offsets(*arguments, 16, threads=3)
    monkeypatch.setattr(footprint_module, "REDRAWS", 10)
    redrawn = np.any(offsets != first_only, axis=2)
    at_centre = np.all(offsets == 0, axis=2)
    assert redrawn.sum() > 100 and at_centre.sum() > 1000, (redrawn.sum(), at_centre.sum())
    monkeypatch.setattr(kernels, "_module", None)
    # Bit for bit (signed zeros included).
    numpy_offsets = footprint_module.footprint_offsets(*arguments, 16)
    np.testing.assert_array_equal(offsets.view(np.uint32), numpy_offsets.view(np.uint32))
    numpy_box = footprint_module.footprint_corners(*arguments, offsets)
    # The corners steer exact-shadow probes only (never the table): equal to float rounding,
    # or where two footprint points are equally near a corner outside the triangle, either.
    close = np.all(np.isclose(box, numpy_box, rtol=1e-5, atol=1e-6), axis=2)
    assert close.mean() > 0.999, close.mean()


def test_compiled_footprint_normals_are_bitwise_those_of_numpy(monkeypatch):
    """The shading normal at every footprint point of smooth samples, on triangles of every
    shape (slivers, degenerate ones, corner normals facing away from the sample's): the
    compiled pass gives the numpy pass's bits, and flat samples keep their own normal."""
    from core.sampling import footprint as footprint_module

    rng = np.random.default_rng(23)
    count, samples, points = 200, 3000, 16
    corners = rng.normal(size=(count, 3, 3))
    corners[::9, 2] = corners[::9, 1]  # degenerate triangles
    corner_normals = rng.normal(size=(count, 3, 3)).astype(np.float32)
    corner_normals /= np.linalg.norm(corner_normals, axis=2, keepdims=True)
    triangle = rng.integers(0, count, samples)
    weights = rng.dirichlet(np.ones(3), samples)
    position = np.einsum("kc,kcd->kd", weights, corners[triangle])
    # Points around the sample, some off the triangle (their weights are clamped).
    offsets = (rng.normal(scale=0.05, size=(samples, points, 3))).astype(np.float32)
    normal = rng.normal(size=(samples, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    smooth = rng.random(samples) < 0.8
    arguments = (offsets, position, triangle, corners, corner_normals, normal, smooth)
    compiled = footprint_module.footprint_normals(*arguments, threads=2)
    monkeypatch.setattr(kernels, "_module", None)
    expected = footprint_module.footprint_normals(*arguments)
    np.testing.assert_array_equal(compiled, expected)
    assert compiled.dtype == np.float32
    flat = ~smooth
    np.testing.assert_array_equal(compiled[flat], np.broadcast_to(normal[flat, None].astype(np.float32),
                                                                  compiled[flat].shape))
    # Both kinds of smooth point occur: the blended normal, and the sample's own where it faces away.
    own = np.all(compiled[smooth] == normal[smooth, None].astype(np.float32), axis=2)
    assert 0.05 < own.mean() < 0.95


def test_a_table_with_nothing_above_the_horizon_packs_to_nothing_and_back():
    from core.visibility import cache as cache_module
    from core.visibility.table import BELOW_HORIZON, NO_HIT_DISTANCE_CODE, VisibilityTable

    shape = (3, 9)
    table = VisibilityTable.from_dense(np.zeros((3, 3)), np.full(shape, BELOW_HORIZON, np.int16),
                                       np.zeros((*shape, 2), np.uint16),
                                       np.full(shape, NO_HIT_DISTANCE_CODE, np.uint16))
    packed = cache_module.pack_entries(table)
    assert len(packed["hit_object"]) == len(packed["hit_uv_code"]) == 0
    unpacked = cache_module.unpack_entries(packed, shape[1])
    for name in ("hit_object", "hit_uv_code", "hit_distance_code"):
        np.testing.assert_array_equal(unpacked.dense(name), getattr(table, name), err_msg=name)


def test_compiled_bilinear_points_are_bitwise_those_of_numpy(monkeypatch):
    rng = np.random.default_rng(11)
    layout = AtlasLayout.from_sizes([(5, 3), (7, 9), (1, 1)])
    flat = rng.uniform(0.0, 4.0, size=(layout.size, 4)).astype(np.float32)
    obj = rng.integers(0, 3, size=5000).astype(np.int16)
    uv = rng.uniform(-0.2, 1.2, size=(5000, 2)).astype(np.float32)
    compiled = layout.bilinear(flat, obj, uv)
    monkeypatch.setattr(kernels, "_module", None)
    expected = layout.bilinear(flat, obj, uv)
    assert compiled.dtype == expected.dtype == np.float64
    np.testing.assert_array_equal(compiled, expected)


def test_compiled_contact_correction_is_bitwise_that_of_numpy(monkeypatch):
    from core.transport.contacts import ShortHits, contact_correction
    rng = np.random.default_rng(17)
    layout = AtlasLayout.from_sizes([(5, 3), (7, 9), (1, 1)])
    hits, samples, groups = 4000, 300, 2
    reflected = rng.uniform(0.0, 4.0, size=(layout.size, 3 * groups)).astype(np.float32)
    albedo = rng.uniform(0.0, 0.9, size=(layout.size, 3)).astype(np.float32)
    # Samples repeat out of order: the sums must follow the hits' order, as sum_by_sample's do.
    short = ShortHits(rng.integers(0, samples, hits), rng.uniform(0.0, 2.0, hits).astype(np.float32),
                      rng.integers(0, 3, hits), rng.uniform(-0.1, 1.1, (hits, 2)).astype(np.float32), None)
    at_hits = rng.uniform(0.0, 10.0, size=(hits, 3 * groups))
    compiled = contact_correction(short, layout, reflected, at_hits, albedo, samples)
    monkeypatch.setattr(kernels, "_module", None)
    expected = contact_correction(short, layout, reflected, at_hits, albedo, samples)
    assert compiled.shape == (samples, 3 * groups) and np.any(compiled != 0)
    np.testing.assert_array_equal(compiled, expected)


def test_compiled_seam_stitch_and_dilation_match_numpy(monkeypatch):
    from core.outputs import dilation, seams
    rng = np.random.default_rng(5)
    size = 48
    coverage = np.zeros((size, size), bool)
    coverage[4:20, 5:22] = True
    coverage[26:44, 24:45] = True
    coverage[30:34, 2:6] = True
    image = rng.uniform(0.0, 2.0, size=(size, size, 3)).astype(np.float32)
    # Two islands with a shared edge: the same edge of two triangles placed in each.
    triangles = np.array([[0, 1, 2], [2, 1, 3]])
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    uvs = np.array([[[0.1, 0.1], [0.4, 0.1], [0.1, 0.4]], [[0.6, 0.9], [0.9, 0.6], [0.9, 0.9]]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 3, 1))
    found = seams.find_seams(positions, triangles, uvs, normals, size, size, coverage)
    assert found is not None and found.edges > 0
    results = []
    for module in (kernels.compiled(), None):
        monkeypatch.setattr(kernels, "_module", module)
        dilated, filled = dilation.dilate(image, coverage, 4)
        stitched = seams.stitch(dilated, found)
        results.append((dilated, filled, stitched))
    (dilated, filled, stitched), (dilated_np, filled_np, stitched_np) = results
    np.testing.assert_array_equal(filled, filled_np)
    assert filled.sum() > 0
    np.testing.assert_array_equal(dilated, dilated_np)  # numpy's summation order, to the bit
    assert stitched.after < 0.5 * stitched.before
    np.testing.assert_allclose(stitched.image, stitched_np.image, rtol=1e-5, atol=1e-6)
    assert abs(stitched.after - stitched_np.after) <= 1e-4 * stitched_np.before


def test_compiled_sums_per_sample_are_bitwise_those_of_bincount(monkeypatch):
    from core.transport.contacts import sum_by_sample
    rng = np.random.default_rng(3)
    sample = rng.integers(0, 50, size=20000)
    values = rng.normal(size=(20000, 9)) * 10.0 ** rng.integers(-8, 8, size=(20000, 1))
    compiled = sum_by_sample(sample, values, 60)
    rows = rng.integers(0, 20000, size=30000)
    indexed = sum_by_sample(sample[rows], values, 60, rows=rows)
    monkeypatch.setattr(kernels, "_module", None)
    np.testing.assert_array_equal(compiled, sum_by_sample(sample, values, 60))
    np.testing.assert_array_equal(indexed, sum_by_sample(sample[rows], values[rows], 60))
    np.testing.assert_array_equal(indexed, sum_by_sample(sample[rows], values, 60, rows=rows))
    assert not compiled[50:].any()


def test_compiled_one_channel_dilation_is_bitwise_that_of_numpy(monkeypatch):
    # One channel is where numpy's einsum sums in SIMD lanes: the kernel follows it, and
    # outside neighbours clamped into the image keep 0 * inf = NaN as in numpy.
    from core.outputs import dilation
    rng = np.random.default_rng(9)
    coverage = rng.random((40, 37)) < 0.05
    coverage[0, :] = True
    image = rng.normal(size=(40, 37)) * 10.0 ** rng.integers(-3, 4, size=(40, 37))
    image[0, 0] = np.inf
    results = []
    for module in (kernels.compiled(), None):
        monkeypatch.setattr(kernels, "_module", module)
        results.append(dilation.dilate(image.astype(np.float32), coverage, 6))
    np.testing.assert_array_equal(results[0][1], results[1][1])
    np.testing.assert_array_equal(results[0][0], results[1][0])
    assert np.isnan(results[0][0][1, 0])  # its neighbour outside the image clamps onto the inf: 0 * inf


@pytest.mark.parametrize("kind, blend", [("SUN", 0.0), ("POINT", 0.0), ("SPOT", 0.0), ("SPOT", 0.3)])
@pytest.mark.parametrize("footprint", ["none", "offsets", "offsets and normals"])
def test_compiled_hard_lamp_points_match_numpy(monkeypatch, kind, blend, footprint):
    from core.lights import lamps
    from core.scene import Light
    from core.transport.direct import _lit
    rng = np.random.default_rng([len(kind), int(blend * 10), len(footprint)])
    count, points = 4000, 16
    position = rng.normal(size=(count, 3))
    normal = rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offsets = normals = None
    if footprint != "none":
        offsets = (rng.normal(size=(count, points, 3)) * 0.01).astype(np.float32)
    if footprint == "offsets and normals":
        normals = rng.normal(size=(count, points, 3))
        normals = (normals / np.linalg.norm(normals, axis=2, keepdims=True)).astype(np.float32)
    direction = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    light = Light("Lamp", kind, np.array([1.0, 0.8, 0.5]), 100.0, position=np.array([0.2, 0.1, 2.0]),
                  direction=direction, spot_size=1.2, spot_blend=blend)
    lamp = lamps.LampPoints(light, position, normal, 8, None, 0, offsets, None if offsets is None else points, normals)
    for point in (0, 5, 21):
        got = lamp.contribution(point)
        assert got.lit is not None
        monkeypatch.setattr(kernels, "_module", None)
        expected = lamp.contribution(point)
        monkeypatch.undo()
        assert expected.lit is None
        # Bitwise but for a blended spot's cone, whose cosine numpy takes from BLAS (fused
        # multiply-adds) where the kernel adds products; the smoothstep's narrow band
        # amplifies that last bit a thousandfold.
        np.testing.assert_allclose(got.irradiance, expected.irradiance, rtol=1e-11 if blend else 0, atol=0)
        np.testing.assert_array_equal(got.to_light, expected.to_light)
        np.testing.assert_array_equal(got.distance, expected.distance)
        np.testing.assert_array_equal(got.lit, _lit(expected, lamp.point_normal(point)))
        assert 0.2 < got.lit.mean() < 0.8
        if offsets is None:
            assert got.position is None and expected.position is None
        else:
            np.testing.assert_array_equal(got.position, expected.position)


def test_compiled_close_entries_and_exposed_shares_are_bitwise_numpy_s_for_any_thread_count():
    from types import SimpleNamespace

    from core.transport import contacts
    from core.visibility.table import encode_distance

    rng = np.random.default_rng(13)
    # Every kind of entry, distances of every scale, and more samples than one block of exposed_share.
    table, normals, *_ = _random_scene(13, samples=1500, vertex=False)
    stored = table.entries.hit_distance_code
    stored[:] = encode_distance(rng.lognormal(-2.0, 2.0, stored.shape))
    scale = gather_normalisation(table, normals, np.pi)
    reaches = [(np.array([0.05, np.inf]), None), (np.array([0.3, 0.0]), rng.uniform(0, 0.5, 1500).astype(np.float32))]
    for threads in (1, 2):
        p = SimpleNamespace(table=table, frame_normal=normals, gather_scale=lambda: scale,
                            settings=SimpleNamespace(threads=threads))
        for target, by_sample in reaches:
            theirs = contacts._close_entries_numpy(p, target, by_sample)
            assert len(theirs.sample) > 1000
            ours = contacts.close_entries(p, target, by_sample)
            for a, b in zip(astuple(ours), astuple(theirs)):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
        for slots in (1, 7, 16, 97, 200):
            share = contacts.exposed_share(table, slots, threads=threads)
            assert share.dtype == np.float64
            np.testing.assert_array_equal(share, contacts._exposed_share_numpy(table, slots))
            assert slots == 1 or np.any((share > 0) & (share < 1))


@pytest.mark.parametrize("compiled", [True, False])
def test_columns_copy_run_by_run_between_tables_and_refuse_other_entry_bits(monkeypatch, compiled):
    """copy_columns and dense_columns, compiled and in numpy: the copied columns read back as the
    source's, any range of columns (within a word, across words, empty, to the end) reads as
    the dense table's, and columns whose entry bits differ are refused."""
    from core.visibility.table import BELOW_HORIZON, TableEntries, copy_columns, dense_columns

    if not compiled:
        monkeypatch.setattr(kernels, "_module", None)
    rng = np.random.default_rng(2)
    shape = (11, 150)
    hit_object = np.where(rng.random(shape) < 0.6, rng.integers(-3, 5, shape), BELOW_HORIZON).astype(np.int16)
    uv = rng.integers(0, 65536, (*shape, 2), np.uint16)
    distance = rng.integers(0, 65536, shape, np.uint16)
    source = TableEntries.from_dense(hit_object, uv, distance)
    # Columns 20..90 of the source become columns 50..120 of a table with the same bits there.
    target_object = np.where(rng.random(shape) < 0.5, 7, BELOW_HORIZON).astype(np.int16)
    target_object[:, 50:120] = np.where(hit_object[:, 20:90] == BELOW_HORIZON, BELOW_HORIZON, 9)
    target = TableEntries.from_dense(target_object, np.zeros((*shape, 2), np.uint16), np.zeros(shape, np.uint16))
    copy_columns(source, 20, target, 50, 70)
    for name, dense in (("hit_object", hit_object), ("hit_uv_code", uv), ("hit_distance_code", distance)):
        np.testing.assert_array_equal(dense_columns(target, name, 50, 120), dense_columns(source, name, 20, 90),
                                      err_msg=name)
        np.testing.assert_array_equal(dense_columns(source, name, 20, 90), source.dense(name)[:, 20:90], err_msg=name)
    # Outside the copied columns the target is untouched.
    np.testing.assert_array_equal(target.dense("hit_object")[:, :50], target_object[:, :50])
    for start, stop in ((0, 150), (3, 9), (63, 65), (64, 128), (70, 70), (100, 150), (149, 150)):
        for name in ("hit_object", "hit_distance_code"):
            np.testing.assert_array_equal(dense_columns(source, name, start, stop, threads=2),
                                          source.dense(name)[:, start:stop], err_msg=f"{name} {start}:{stop}")
    with pytest.raises(ValueError, match="entry bits differ"):
        copy_columns(source, 0, target, 0, 150)


def test_numpy_s_blas_runs_on_one_thread_inside_the_block_and_as_before_after_it():
    import threadpoolctl  # pinned in requirements.txt: missing is a broken install, not a skip

    def blas_threads():
        return [pool["num_threads"] for pool in threadpoolctl.threadpool_info() if pool["user_api"] == "blas"]

    np.ones((64, 64)) @ np.ones((64, 64))  # numpy loads its BLAS on first use
    before = blas_threads()
    if not before:
        pytest.skip("this numpy links no BLAS that threadpoolctl can see: nothing to limit")
    with kernels.blas_on_one_thread():
        assert blas_threads() == [1] * len(before)
        with kernels.blas_on_one_thread():
            assert blas_threads() == [1] * len(before)
        assert blas_threads() == [1] * len(before)  # until the outermost block ends
    assert blas_threads() == before
    with pytest.raises(ZeroDivisionError):
        with kernels.blas_on_one_thread():
            1 / 0
    assert blas_threads() == before


@pytest.mark.parametrize("centre", [None, (1000.0, -5.0, 3.0)])
@pytest.mark.parametrize("moved", [False, True])
@pytest.mark.parametrize("smooth", ["none", "flat lights", "some lifted"])
def test_compiled_shadow_rays_are_bitwise_those_of_numpy(monkeypatch, centre, moved, smooth):
    """The shadow rays' set-up (core.transport.direct.shadow_rays): origins from the samples'
    own, from footprint points, lifted towards smooth surfaces; lamps at a distance and suns;
    a ray scene at the world origin (float32 origins) and one centred far from it (float64)."""
    from core.lights.lamps import LightContribution
    from core.transport import direct
    from core.transport.contract import SampleSet
    from core.visibility.rays import RayScene

    rng = np.random.default_rng(5)
    count, points = 2000, 1500
    offset = np.zeros(3) if centre is None else np.asarray(centre)
    scene = RayScene([(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]) + offset, np.array([[0, 1, 2]]))], 2,
                     None if centre is None else offset)
    position = rng.uniform(-2, 2, (count, 3)) + offset
    position[:20] = offset + rng.uniform(-1e-3, 1e-3, (20, 3))  # near the frame's origin: the float step
    position[20:25, 0] = offset[0]  # a coordinate exactly at it
    geometric = rng.normal(size=(count, 3))
    geometric /= np.linalg.norm(geometric, axis=1, keepdims=True)
    normal = geometric + 0.2 * rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    terminator = cutoff = None
    if smooth != "none":
        terminator = 0.01 * rng.normal(size=(count, 3))
        cutoff = np.where(rng.uniform(size=count) < 0.2, 0.0, rng.uniform(0.05, 0.3, count))
    samples = SampleSet(position, normal, geometric, scene.ray_origins(position, geometric),
                        terminator=terminator, terminator_cutoff=cutoff)
    rows = rng.permutation(points)[:1200]
    sample_rows = rng.integers(0, count, 1200)
    to_light = rng.normal(size=(points, 3))
    if smooth == "flat lights":  # each ray's light well above its face: no ray is lifted
        to_light[rows] = geometric[sample_rows] + 0.01 * rng.normal(size=(len(rows), 3))
    to_light /= np.linalg.norm(to_light, axis=1, keepdims=True)
    distance = rng.uniform(0.1, 10.0, points)
    distance[::7] = np.inf
    part = LightContribution(None, to_light, distance,
                             position[:points] + 0.01 * rng.normal(size=(points, 3)) if moved else None)
    compiled = direct.shadow_rays(scene, samples, part, rows, sample_rows)
    monkeypatch.setattr(kernels, "_module", None)
    reference = direct.shadow_rays(scene, samples, part, rows, sample_rows)
    if smooth == "some lifted":
        unlifted = SampleSet(position, normal, geometric, samples.origins)
        assert not np.array_equal(reference[0], direct.shadow_rays(scene, unlifted, part, rows, sample_rows)[0])
    elif not moved:  # nothing lifted: the samples' own origins
        np.testing.assert_array_equal(reference[0], samples.origins[sample_rows])
    for ours, theirs in zip(compiled, reference):
        assert ours.dtype == theirs.dtype and ours.shape == theirs.shape
        np.testing.assert_array_equal(ours.view(np.uint8), theirs.view(np.uint8))


@pytest.mark.parametrize("centre", [None, (1000.0, -5.0, 3.0)])
def test_compiled_emitter_light_is_bitwise_that_of_numpy(monkeypatch, centre):
    """A small emitter's light (core.lights.emitters.emitter_irradiance) through the kernels
    and through numpy: samples in front of its patches, behind them, behind their own face
    (shading normal towards the patch, geometric normal away), on a patch itself, and shadowed
    by a blocker; float32 ray origins and a ray scene centred far from the world's origin
    (float64)."""
    from core.lights.emitters import Emitter, emitter_irradiance
    from core.visibility.rays import RayScene

    rng = np.random.default_rng(11)
    offset = np.zeros(3) if centre is None else np.asarray(centre)
    count, patches = 3000, 16
    blocker = np.array([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.0, 0.5, 1.0]]) + offset
    scene = RayScene([(blocker, np.array([[0, 1, 2]]))], 2, None if centre is None else offset)
    position = rng.uniform(-2, 2, (count, 3)) + offset
    geometric = rng.normal(size=(count, 3))
    geometric /= np.linalg.norm(geometric, axis=1, keepdims=True)
    normal = geometric + 0.5 * rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal[::5, 2] = np.abs(normal[::5, 2]) + 0.1  # shading normals up, some geometric ones down
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    points = rng.uniform(-0.3, 0.3, (patches, 3)) + offset + [0.0, 0.0, 2.0]
    point_normal = np.tile([0.0, 0.0, -1.0], (patches, 1)) + 0.1 * rng.normal(size=(patches, 3))
    point_normal /= np.linalg.norm(point_normal, axis=1, keepdims=True)
    position[:3] = points[:3]  # samples on a patch: no light from that one (distance 0)
    emitter = Emitter(0, points, point_normal, rng.uniform(0.01, 0.02, patches), rng.uniform(0, 5, (patches, 3)),
                      points.mean(axis=0), 0.5)
    origins = scene.ray_origins(position, geometric)
    compiled, compiled_rays = emitter_irradiance(emitter, position, normal, geometric, origins, scene)
    monkeypatch.setattr(kernels, "_module", None)
    reference, reference_rays = emitter_irradiance(emitter, position, normal, geometric, origins, scene)
    assert compiled_rays == reference_rays > 0
    assert 0 < np.count_nonzero(reference[:, 0]) < count
    unshadowed, _ = emitter_irradiance(emitter, position, normal, geometric, origins, RayScene([], 1))
    assert np.count_nonzero(unshadowed[:, 0]) > np.count_nonzero(reference[:, 0])  # the blocker shadows some
    np.testing.assert_array_equal(compiled.view(np.uint8), reference.view(np.uint8))


def test_compiled_footprint_curvature_is_bitwise_that_of_numpy(monkeypatch):
    """core.transport.direct.curved_footprints through the kernel and through numpy's einsum,
    with footprint normals whose cosine to the sample's lies within 1e-6 of the threshold,
    on both sides of it, and a NaN normal."""
    from core.transport.direct import CURVED_COSINE, curved_footprints

    rng = np.random.default_rng(13)
    count, points = 4000, 16
    normal = rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tilt = rng.normal(size=(count, points, 3)) * rng.choice([1e-4, 0.0316, 0.3], (count, 1, 1))
    footprint = (normal[:, None, :] + tilt).astype(np.float32)
    footprint /= np.linalg.norm(footprint, axis=2, keepdims=True)
    # A point of 600 samples turned by the threshold's angle itself, give or take float32 rounding.
    edge = np.arange(600)
    side = np.cross(normal[edge], rng.normal(size=(600, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    angle = np.arccos(CURVED_COSINE) * (1.0 + rng.uniform(-1e-4, 1e-4, 600))
    footprint[edge, 5] = (np.cos(angle)[:, None] * normal[edge] + np.sin(angle)[:, None] * side).astype(np.float32)
    cosine = np.einsum("kpd,kd->kp", footprint, normal)
    footprint[7, 3, 1] = np.nan
    compiled = curved_footprints(footprint, normal)
    monkeypatch.setattr(kernels, "_module", None)
    reference = curved_footprints(footprint, normal)
    near = np.abs(cosine.min(axis=1) - CURVED_COSINE) < 1e-6
    assert near.sum() > 100 and 0 < reference.sum() < count and not reference[7]
    assert 0 < reference[near].sum() < near.sum()  # the near ones fall on both sides
    np.testing.assert_array_equal(compiled, reference)


def test_compiled_face_normals_and_areas_are_bitwise_those_of_numpy(monkeypatch):
    """core.geometry's face frames through the kernel and in numpy: random triangles over
    twelve orders of magnitude, slivers on both sides of the degenerate ratio, a repeated
    corner, and corners at NaN, infinity and 1e200 (whose squares overflow)."""
    from core import geometry
    from core import tolerances as tol

    kernels.status()
    if kernels.compiled() is None:
        pytest.skip("the compiled kernels are not available here (the numpy fallback runs)")
    rng = np.random.default_rng(17)
    positions = rng.normal(size=(3000, 3)) * 10.0 ** rng.uniform(-6, 6, (3000, 1))
    triangles = rng.integers(0, 3000, size=(9000, 3)).astype(np.int32)
    # Slivers: a third corner off the first edge by a height around the degenerate ratio.
    sliver = np.arange(3000, 3600)
    base = rng.normal(size=(600, 3))
    tip = base + rng.normal(size=(600, 3))
    away = np.cross(tip - base, rng.normal(size=(600, 3)))
    away /= np.linalg.norm(away, axis=1, keepdims=True)
    span = np.linalg.norm(tip - base, axis=1, keepdims=True)
    third = (base + tip) / 2 + away * span * tol.DEGENERATE_TRIANGLE_RATIO * rng.uniform(0.2, 5.0, (600, 1))
    positions = np.concatenate([positions, base, tip, third])
    triangles[sliver] = np.column_stack([3000 + np.arange(600), 3600 + np.arange(600), 4200 + np.arange(600)])
    positions[[5, 6, 7]] = [[np.nan, 0, 0], [np.inf, 1, 1], [1e200, -1e200, 1e200]]
    triangles[:3] = [[5, 1, 2], [6, 1, 2], [7, 1, 2]]
    triangles[3] = [9, 9, 10]
    compiled = geometry._face_frames(positions, triangles, 2)
    monkeypatch.setattr(kernels, "_module", None)
    with np.errstate(all="ignore"):
        reference = geometry._face_frames(positions, triangles)
    valid = reference[1]
    assert 0 < valid[sliver].sum() < len(sliver) and not valid[:4].any() and valid.sum() > 8000
    for ours, numpy_s in zip(compiled, reference):
        assert ours.dtype == numpy_s.dtype and ours.tobytes() == numpy_s.tobytes()


def test_compile_helpers_find_what_this_process_imports_from(tmp_path, monkeypatch):
    """A helper process gets this process's module path, where Blender puts the extensions'
    wheels at run time (numba among them), and the cache folder it compiles into."""
    extra = tmp_path / "wheels-added-at-run-time"
    extra.mkdir()
    monkeypatch.syspath_prepend(str(extra))
    environment = kernels._helper_environment(str(tmp_path / "cache"))
    paths = environment["PYTHONPATH"].split(os.pathsep)
    assert paths[0] == str(extra)
    assert os.path.dirname(os.path.dirname(np.__file__)) in paths
    assert environment["NUMBA_CACHE_DIR"] == str(tmp_path / "cache")
    done = subprocess.run([sys.executable, "-S", "-c", "import numpy, numba; print('ok')"], env=environment,
                          capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "ok", done.stderr


def test_each_run_gets_the_thread_count_asked_for_on_every_thread():
    """kernels.run sets numba's count only where the calling thread's differs from the last it
    set: every call still runs on the count asked for, on this thread and on new ones."""
    import threading

    import numba

    kernels.status()
    if kernels.compiled() is None:
        pytest.skip("the compiled kernels are not available here (the numpy fallback runs)")
    seen = []

    def record():
        seen.append(numba.get_num_threads())

    most = numba.config.NUMBA_NUM_THREADS
    asked = [1, 1, 2, 0, 1]
    for threads in asked:
        kernels.run(record, threads)
    worker = threading.Thread(target=lambda: [kernels.run(record, t) for t in (1, 0)])
    worker.start()
    worker.join()
    expected = [min(t or os.cpu_count(), most) for t in asked + [1, 0]]
    assert seen == expected


def test_compiled_uv_layout_counts_are_numpy_s(monkeypatch):
    """core.sampling.atlas.uv_layout_stats through the kernel and in numpy: random UVs, some
    outside [0, 1] by less and by more than the slack, non-finite corners, zero-area and
    sliver triangles at the degenerate ratio, at two atlas sizes."""
    from core import tolerances as tol
    from core.sampling.atlas import uv_layout_stats

    kernels.status()
    if kernels.compiled() is None:
        pytest.skip("the compiled kernels are not available here (the numpy fallback runs)")
    rng = np.random.default_rng(23)
    # Small triangles (the raster holds every claim at once) about centres across the atlas.
    uv = rng.uniform(-0.01, 1.01, size=(5000, 1, 2)) + rng.uniform(-0.02, 0.02, size=(5000, 3, 2))
    uv[:50, 0, 0] = 1.0 + tol.UV_RANGE_SLACK * rng.uniform(0.5, 1.5, 50)
    uv[50:60, 1] = np.nan
    uv[60:70, 2, 1] = np.inf
    uv[70:80, 1] = uv[70:80, 0]
    sliver = np.arange(80, 400)
    uv[sliver, 2] = (uv[sliver, 0] + uv[sliver, 1]) / 2 + rng.uniform(-1e-7, 1e-7, (len(sliver), 2))
    for width, height in ((64, 64), (4096, 512)):
        compiled = uv_layout_stats(uv, width, height)
        monkeypatch.setattr(kernels, "_module", None)
        reference = uv_layout_stats(uv, width, height)
        monkeypatch.undo()
        assert compiled == reference
        assert reference.non_finite_corners == 20 and reference.out_of_range_corners > 100
        assert 20 < reference.zero_area_triangles < 350


@pytest.mark.parametrize("kind", ["SUN", "POINT", "SPOT"])
@pytest.mark.parametrize("centre", [None, (1000.0, -5.0, 3.0)])
@pytest.mark.parametrize("smooth", [False, True])
def test_compiled_shadow_edges_of_a_hard_lamp_are_bitwise_the_point_by_point_loop(monkeypatch, kind, centre, smooth):
    """A hard lamp's light over the dense footprints of the samples a shadow edge crosses
    (core.transport.direct._edge_irradiance): one compiled pass of points and shadow rays
    against the loop of one contribution and one set-up a point, through the kernels and
    through numpy; a blocker that shadows some points, light linking, points batched (more
    edge samples than one batch of EDGE_BATCH_ROWS holds for every point), footprint normals,
    rays lifted towards smooth surfaces, a ray scene at the origin and one centred far away."""
    from types import SimpleNamespace

    from core.lights import lamps
    from core.scene import Light
    from core.transport import direct
    from core.transport.contract import SampleSet

    rng = np.random.default_rng([len(kind), int(smooth), centre is None])
    offset, scene, position, geometric, normal, terminator, cutoff = _half_shadowed_floor(rng, centre, smooth, 3000)
    count = len(position)
    dense_points = direct.EDGE_FOOTPRINT_POINTS

    def dense_footprint(ids, points):
        local = np.random.default_rng(ids)  # the same points for the same samples on every call
        offsets = (local.normal(size=(len(ids), points, 3)) * [0.02, 0.02, 0.0]).astype(np.float32)
        normals = normal[ids][:, None, :] + 0.05 * local.normal(size=(len(ids), points, 3))
        return offsets, (normals / np.linalg.norm(normals, axis=2, keepdims=True)).astype(np.float32)

    samples = SampleSet(position, normal, geometric, scene.ray_origins(position, geometric),
                        terminator=terminator, terminator_cutoff=cutoff, dense_footprint=dense_footprint)
    direction = np.array([0.2, 0.1, -1.0]) / np.linalg.norm([0.2, 0.1, -1.0])
    light = Light("Lamp", kind, np.array([1.0, 0.8, 0.5]), 100.0, position=offset + [0.1, 0.0, 2.5],
                  direction=direction, spot_size=2.0, spot_blend=0.0)
    shadowing = SimpleNamespace(area_light_samples=8, seed=0, ray_scene=scene)
    receives = rng.uniform(size=count) < 0.9
    edges = np.sort(rng.choice(count, 2 * direct.EDGE_BATCH_ROWS // dense_points + 7, replace=False))
    assert lamps.lamp_points(light, 8) == 1
    compiled_calls = []
    compiled_pass = direct._hard_edge_irradiance
    monkeypatch.setattr(direct, "_hard_edge_irradiance", lambda *a: compiled_calls.append(1) or compiled_pass(*a))
    ours, our_rays, our_half = direct._edge_irradiance(light, samples, edges, shadowing, scene, receives, 16)
    monkeypatch.setattr(kernels, "_module", None)
    theirs, their_rays, their_half = direct._edge_irradiance(light, samples, edges, shadowing, scene, receives, 16)
    assert compiled_calls == [1]  # the kernels' pass, then the loop
    assert our_rays == their_rays > 0
    np.testing.assert_array_equal(ours, theirs)
    # The first half of the points (the error estimate's) is the same light in both passes.
    np.testing.assert_allclose(our_half, their_half, rtol=1e-12, atol=1e-15)
    assert np.all(our_half <= ours + 1e-12) and np.any((our_half > 0) & (our_half < ours))
    lit_share = np.mean(ours[:, 0] > 0)
    assert 0.3 < lit_share < 0.95  # some edge samples shadowed wholly, some not
    assert np.any((ours[:, 0] > 0) & (ours[:, 0] < np.max(ours[:, 0]) * 0.5))  # and some in part


@pytest.mark.parametrize("kind, radius", [("SUN", 0.0), ("POINT", 0.0), ("POINT", 0.3), ("SPOT", 0.0)])
@pytest.mark.parametrize("centre", [None, (1000.0, -5.0, 3.0)])
@pytest.mark.parametrize("smooth", [False, True])
def test_compiled_corner_probes_answer_as_the_numpy_probes(monkeypatch, kind, radius, centre, smooth):
    """The penumbra probes (core.transport.direct._penumbra_probes) with a footprint box: its
    four corner probes made by one kernel a corner, against the numpy probes, for lamps with
    and without extent (whose outline probes stay numpy), a ray scene centred far away, smooth
    faces' lifts and light linking: the same decided, shadowed and mixed samples and rays."""
    from core.lights import lamps
    from core.scene import Light
    from core.transport import direct
    from core.transport.contract import SampleSet

    rng = np.random.default_rng([len(kind), int(radius * 10), int(smooth), centre is None])
    offset, scene, position, geometric, normal, terminator, cutoff = _half_shadowed_floor(rng, centre, smooth, 4000)
    count = len(position)
    footprint = (rng.normal(size=(count, 16, 3)) * [0.02, 0.02, 0.0]).astype(np.float32)
    corners = (np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * 0.03
               * rng.uniform(0.5, 1.5, (count, 1, 1))).astype(np.float32)
    samples = SampleSet(position, normal, geometric, scene.ray_origins(position, geometric), footprint=footprint,
                        footprint_corners=corners, terminator=terminator, terminator_cutoff=cutoff)
    direction = np.array([0.2, 0.1, -1.0]) / np.linalg.norm([0.2, 0.1, -1.0])
    light = Light("Lamp", kind, np.array([1.0, 0.8, 0.5]), 100.0, position=offset + [0.1, 0.0, 2.5],
                  direction=direction, spot_size=2.0, spot_blend=0.0, radius=radius)
    receives = rng.uniform(size=count) < 0.9
    # A lamp with a radius looks wide from the floor (core.transport.direct.WIDE_LAMP_RADIUS): with
    # 64 points its probes add its first 16 (with 16 it would trace them all and probe nothing).
    lamp = lamps.LampPoints(light, position, normal, 8, None, 0, footprint, 64 if radius > 0 else 16)
    corner_calls = []
    compiled_corners = direct._corner_probes
    monkeypatch.setattr(direct, "_corner_probes", lambda *a: corner_calls.append(1) or compiled_corners(*a))
    ours = direct._penumbra_probes(light, lamp, samples, scene, receives)
    monkeypatch.setattr(kernels, "_module", None)
    theirs = direct._penumbra_probes(light, lamp, samples, scene, receives)
    assert corner_calls == [1]  # the kernels' corners, then numpy's
    for a, b in zip(ours[:3], theirs[:3]):
        np.testing.assert_array_equal(a, b)
    assert ours[3] == theirs[3] > 0
    decided, shadowed, mixed, _ = ours
    assert shadowed.any() and (decided & ~shadowed).any() and mixed.any()


def _half_shadowed_floor(rng, centre, smooth: bool, count: int):
    """A floor of ``count`` samples in [-1, 1]^2 at z = 0 (around ``centre``, or the origin) under a
    blocker over its x < -0.2 side at z = 1, in a ray scene centred there: (offset (3,), the
    RayScene, position, geometric and shading normals (count, 3) float64, and the smooth faces'
    terminator lifts (count, 3) and cutoffs (count,), or None twice)."""
    from core.visibility.rays import RayScene

    offset = np.zeros(3) if centre is None else np.asarray(centre)
    blocker = np.array([[-2.0, -2.0, 1.0], [-0.2, -2.0, 1.0], [-0.2, 2.0, 1.0], [-2.0, 2.0, 1.0]]) + offset
    scene = RayScene([(blocker, np.array([[0, 1, 2], [0, 2, 3]]))], 2, None if centre is None else offset)
    position = np.column_stack([rng.uniform(-1, 1, (count, 2)), np.zeros(count)]) + offset
    geometric = np.tile([0.0, 0.0, 1.0], (count, 1))
    normal = geometric + 0.05 * rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    terminator = cutoff = None
    if smooth:
        terminator = 0.002 * rng.normal(size=(count, 3))
        cutoff = rng.uniform(0.0, 0.4, count)
    return offset, scene, position, geometric, normal, terminator, cutoff
