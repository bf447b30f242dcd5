"""Scale-out (issue 20) foundations: a bake split by sample rows gives bitwise the one-process
numbers. The visibility table of row ranges (TraceRequest.rows), joined by concatenate_columns,
equals the whole table; the direct light of row ranges (SampleSet.rows, which keeps each sample's
index in the bake) equals those rows of the whole set's, penumbra edge refinement included."""
import dataclasses

import numpy as np
import pytest

from core.pipeline.prepare import prepare
from core.scene import Light, Scene
from core.settings import BakeSettings
from core.transport.contract import SampleSet, direction_chunks
from core.transport.direct import lamp_irradiance
from core.visibility.table import VisibilityTable, concatenate_columns, trace_table
from core_scenes import grid_mesh, quad_mesh

TABLE_ARRAYS = ("hit_object", "hit_uv_code", "hit_distance_code", "traced_per_sample", "backface_per_sample")
TABLE_COUNTERS = ("rays_cast", "rays_below_horizon", "backface_hits")


def _scene(lights=()):
    """An atlas ground, an atlas blocker over half of it (a straight shadow edge) and a
    vertex-mode card between them."""
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=14)
    blocker = quad_mesh("Blocker", [(-1.2, -1.2, 0.6), (0.1, -1.2, 0.6), (0.1, 1.2, 0.6), (-1.2, 1.2, 0.6)],
                        resolution=5)
    card = grid_mesh("Card", size=0.5, segments=3, z=0.3, mode="vertex")
    card.positions = card.positions + np.array([0.45, 0.3, 0.0])
    return Scene([ground, blocker, card], list(lights))


def _assert_same_table(joined: VisibilityTable, whole: VisibilityTable):
    np.testing.assert_array_equal(joined.directions, whole.directions)
    for name in TABLE_ARRAYS:
        ours, theirs = getattr(joined, name), getattr(whole, name)
        assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs), name
    for name in TABLE_COUNTERS:
        assert getattr(joined, name) == getattr(whole, name), name
    np.testing.assert_array_equal(joined.vertex_cells, whole.vertex_cells)


@pytest.fixture(scope="module")
def traced():
    # Interleaved rotations (3 x 3), footprints of 8 points, a vertex-mode object; a small
    # chunk so that the whole trace and every range run in several batches.
    settings = BakeSettings(directions=48, bounces=1, footprint_samples=8, interleave=3, chunk_rays=48 * 37)
    p = prepare(_scene(), settings, table_needed=True)
    return p, p.trace_request()


def test_the_table_of_row_ranges_joined_equals_the_whole_table_bitwise(traced):
    p, request = traced
    assert request.footprint is not None and request.footprint.shape[1] == 8
    assert request.rotations is not None and len(np.unique(request.group)) == 9
    assert p.table.vertex_cells is not None and np.count_nonzero(p.table.vertex_cells) == 1
    whole = trace_table(p.ray_scene, request)
    _assert_same_table(whole, p.table)  # the request is the bake's
    samples = len(p.position)
    # The vertex card's samples come last: a range boundary inside each object, and one between them.
    splits = [[0, samples], [0, samples // 2, samples], [0, 61, int(p.sample_offset[2]) + 5, samples],
              [0, int(p.sample_offset[1]), int(p.sample_offset[1]), int(p.sample_offset[2]), samples]]
    for bounds in splits:
        parts = [trace_table(p.ray_scene, request.rows(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]
        assert [t.hit_object.shape[1] for t in parts] == list(np.diff(bounds))
        _assert_same_table(concatenate_columns(parts), whole)


def test_the_table_is_the_same_in_any_chunking_and_without_the_kernels(traced, monkeypatch):
    # Every chunk's rays reuse one set of buffers (RayBuffers), chunk sizes vary (the last is
    # short), and the numpy fallback makes fresh arrays: all must give the same table.
    from core import kernels
    from core.visibility.table import BACKFACE

    p, request = traced
    whole = trace_table(p.ray_scene, request)
    # Counted chunk by chunk during the trace: the count over the finished table.
    assert whole.backface_hits > 0
    np.testing.assert_array_equal(whole.backface_per_sample, np.count_nonzero(whole.hit_object == BACKFACE, axis=0))
    for chunk_rays in (1, 48 * 5, 48 * 64 + 7, 10**9):
        _assert_same_table(trace_table(p.ray_scene, dataclasses.replace(request, chunk_rays=chunk_rays)), whole)
    monkeypatch.setattr(kernels, "_module", None)
    _assert_same_table(trace_table(p.ray_scene, dataclasses.replace(request, chunk_rays=48 * 11)), whole)


@pytest.mark.parametrize("span_rays, threads", [(1, 2), (7, 3), (100, 1), (4096, 2)])
def test_the_table_is_the_same_whatever_the_span_and_thread_count(traced, monkeypatch, span_rays, threads):
    # Each thread sets up, traces and records spans of SPAN_RAYS rays, taking the next free
    # span in turn (SpanTracer): which thread takes which span varies from run to run, and the
    # last span of a chunk is short; each ray still owns its entry.
    from core.visibility import table as table_module

    p, request = traced
    whole = trace_table(p.ray_scene, request)
    monkeypatch.setattr(table_module, "SPAN_RAYS", span_rays)
    monkeypatch.setattr(p.ray_scene, "threads", threads)
    _assert_same_table(trace_table(p.ray_scene, dataclasses.replace(request, chunk_rays=48 * 23)), whole)


def test_an_error_in_one_span_stops_the_trace_and_reaches_the_caller(traced, monkeypatch):
    from core.visibility import table as table_module

    p, request = traced
    monkeypatch.setattr(table_module, "SPAN_RAYS", 16)
    monkeypatch.setattr(p.ray_scene, "threads", 2)
    calls = []
    real_setup = type(request).ray_setup

    def failing_setup(self, ray_scene):
        set_up = real_setup(self, ray_scene)

        def counted(*arguments):
            calls.append(1)
            if len(calls) == 5:
                raise MemoryError("span 5")
            set_up(*arguments)
        return counted

    monkeypatch.setattr(type(request), "ray_setup", failing_setup)
    with pytest.raises(MemoryError, match="span 5"):
        trace_table(p.ray_scene, request)
    # The other thread stopped at its next span, not at the end of the chunk.
    spans = -(-int(p.table.traced_per_sample.sum()) // 16)
    assert 5 <= len(calls) <= 7 < spans


def test_a_row_request_slices_the_samples_and_shares_the_rest(traced):
    _, request = traced
    part = request.rows(10, 30)
    assert len(part.positions) == len(part.geometric_normals) == len(part.footprint) == len(part.group) == 20
    np.testing.assert_array_equal(part.positions, request.positions[10:30])
    np.testing.assert_array_equal(part.group, request.group[10:30])
    assert part.directions is request.directions and part.rotations is request.rotations
    assert part.hits is request.hits and part.chunk_rays == request.chunk_rays
    bare = dataclasses.replace(request, footprint=None, rotations=None, group=None).rows(3, 3)
    assert bare.footprint is None and bare.group is None and len(bare.positions) == 0
    with pytest.raises(ValueError, match="outside"):
        request.rows(5, len(request.positions) + 1)


def test_tables_that_do_not_belong_together_are_refused(traced):
    p, request = traced
    a = trace_table(p.ray_scene, request.rows(0, 20))
    with pytest.raises(ValueError, match="no table"):
        concatenate_columns([])
    other = dataclasses.replace(a, directions=a.directions[::-1].copy())
    with pytest.raises(ValueError, match="directions"):
        concatenate_columns([a, other])
    with pytest.raises(ValueError, match="vertex"):
        concatenate_columns([a, dataclasses.replace(a, vertex_cells=None)])
    with pytest.raises(ValueError, match="traced_per_sample"):
        concatenate_columns([a, dataclasses.replace(a, traced_per_sample=a.traced_per_sample[:-1])])


def test_sample_set_rows_slice_every_per_sample_array_and_keep_global_ids():
    k, points = 7, 3
    rng = np.random.default_rng(5)
    full = SampleSet(rng.random((k, 3)), rng.random((k, 3)), rng.random((k, 3)), rng.random((k, 3)).astype(np.float32),
                     np.arange(k) % 2, rng.random((k, points, 3)).astype(np.float32),
                     rng.random((k, 4, 3)).astype(np.float32), rng.random((k, 3)), rng.random(k),
                     rng.random((k, points, 3)).astype(np.float32), dense_footprint=print)
    full.derived["kept"] = np.ones(k)
    part = full.rows(2, 6)
    for name in ("position", "normal", "geometric", "origins", "owner", "footprint", "footprint_corners",
                 "terminator", "terminator_cutoff", "footprint_normals"):
        np.testing.assert_array_equal(getattr(part, name), getattr(full, name)[2:6])
    assert part.dense_footprint is print and part.derived == {}
    assert part.sample_ids().dtype == np.int64 and part.sample_ids().tolist() == [2, 3, 4, 5]
    # Rows of rows keep the bake's indices.
    assert part.rows(1, 3).sample_ids().tolist() == [3, 4]
    assert full.sample_ids().tolist() == list(range(k)) and full.ids is None
    bare = SampleSet.on_surface(np.zeros((4, 3)), np.tile([0.0, 0.0, 1.0], (4, 1))).rows(1, 4)
    assert bare.footprint is None and bare.owner is None and bare.terminator is None and len(bare) == 3
    with pytest.raises(ValueError, match="outside"):
        full.rows(3, 2)


LIGHTS = {
    "soft sun": Light("Sun", "SUN", np.array([1.0, 0.9, 0.8]), 3.0, direction=np.array([0.35, 0.1, -1.0])
                      / np.linalg.norm([0.35, 0.1, -1.0]), angle=0.25),
    "area lamp": Light("Area", "AREA", np.array([0.8, 0.9, 1.0]), 200.0, position=np.array([0.5, 0.2, 1.6]),
                       size_x=0.7, size_y=0.4),
    "point lamp with radius": Light("Bulb", "POINT", np.ones(3), 150.0, position=np.array([0.6, -0.2, 1.3]),
                                    radius=0.15),
    # A lamp without extent over footprints: the compiled pass for decided samples (LampPoints.add_untraced).
    "hard spot": Light("Spot", "SPOT", np.ones(3), 300.0, position=np.array([0.4, 0.1, 1.5]),
                       direction=np.array([0.0, 0.0, -1.0]), spot_size=1.6),
}


@pytest.fixture(scope="module")
def direct_scene():
    settings = BakeSettings(directions=16, bounces=0, footprint_samples=16, shadows="exact", interleave=3)
    p = prepare(_scene(LIGHTS.values()), settings, table_needed=False)
    assert p.footprint is not None and p.sample_set().dense_footprint is not None
    return p


@pytest.mark.parametrize("kind", list(LIGHTS))
def test_direct_light_of_row_ranges_equals_those_rows_of_the_whole_set_bitwise(direct_scene, kind):
    p = direct_scene
    light = LIGHTS[kind]
    asked = []

    def dense_footprint(rows, count):
        asked.append(np.array(rows))
        return p.dense_footprint(rows, count)

    # Edge refinement is on: record which (global) rows ask for a dense footprint.
    samples = dataclasses.replace(p.sample_set(), dense_footprint=dense_footprint, derived={})
    whole, whole_rays = lamp_irradiance(samples, p.shadowing(), [light])
    edges = np.concatenate(asked)
    assert len(edges) > 0, "no texel is crossed by a shadow edge: the edge refinement did not run"
    assert np.any(whole > 0) and np.any(whole == 0)
    count = len(samples)
    for parts in (2, 3):
        rays = 0
        for r in direction_chunks(count, parts):
            asked.clear()
            part, part_rays = lamp_irradiance(samples.rows(r.start, r.stop), p.shadowing(), [light])
            rays += part_rays
            assert np.array_equal(part, whole[r.start:r.stop]), (kind, parts, r)
            # The refined rows are the whole set's edges in this range, asked for by their global index.
            asked_rows = np.concatenate(asked) if asked else np.zeros(0, np.int64)
            np.testing.assert_array_equal(asked_rows, edges[(edges >= r.start) & (edges < r.stop)])
        assert rays == whole_rays


def test_direct_light_of_all_lamps_in_uneven_ranges_is_bitwise_the_whole(direct_scene):
    p = direct_scene
    samples = p.sample_set()
    whole, _ = lamp_irradiance(samples, p.shadowing(), list(LIGHTS.values()))
    bounds = [0, 1, 97, int(p.sample_offset[2]) + 3, len(samples)]
    joined = np.concatenate([lamp_irradiance(samples.rows(a, b), p.shadowing(), list(LIGHTS.values()))[0]
                             for a, b in zip(bounds[:-1], bounds[1:])])
    assert joined.dtype == whole.dtype and np.array_equal(joined, whole)


def test_sample_ids_none_gives_the_light_of_explicit_indices_0_to_k(direct_scene):
    p = direct_scene
    samples = p.sample_set()
    assert samples.ids is None
    lights = list(LIGHTS.values())
    implicit, implicit_rays = lamp_irradiance(samples, p.shadowing(), lights)
    explicit, explicit_rays = lamp_irradiance(dataclasses.replace(samples, ids=np.arange(len(samples)), derived={}),
                                              p.shadowing(), lights)
    assert np.array_equal(implicit, explicit) and implicit_rays == explicit_rays
    # The ids do seed the light: other ids give other sampler points (without the dense
    # footprint, whose rows the shifted ids would leave).
    sparse = dataclasses.replace(samples, dense_footprint=None, derived={})
    shifted, _ = lamp_irradiance(dataclasses.replace(sparse, ids=np.arange(len(samples)) + 1000), p.shadowing(),
                                 [LIGHTS["area lamp"]])
    alone, _ = lamp_irradiance(sparse, p.shadowing(), [LIGHTS["area lamp"]])
    assert not np.array_equal(shifted, alone)


@pytest.mark.parametrize("interleave, footprint", [(3, 4), (1, 1)])
def test_a_worker_builds_only_its_rows_objects_and_gets_the_whole_preparation_s_rows_bitwise(
        monkeypatch, interleave, footprint):
    """core.distributed.rows.PackagedBake: rows [start, stop) built from the objects they
    cover (counted by the raster alone) equal those rows of the whole preparation, across
    object boundaries, inside one object, empty, and with a vertex-mode object."""
    from core.distributed import rows as rows_module
    from core.sampling import samples as samples_module

    scene = _scene()
    settings = BakeSettings(directions=24, bounces=1, interleave=interleave, footprint_samples=footprint, threads=1)
    whole = prepare(scene, settings, table_needed=False)
    bake = rows_module.PackagedBake.read(scene, settings)
    np.testing.assert_array_equal(bake.sample_offset, whole.sample_offset)
    for name in ("widths", "heights", "offsets"):
        np.testing.assert_array_equal(getattr(bake.layout, name), getattr(whole.layout, name))
    np.testing.assert_array_equal(bake.layout.corner_flat, whole.layout.corner_flat)
    built = []
    real_build = samples_module.build_samples
    monkeypatch.setattr(rows_module, "build_samples", lambda mesh, *a: built.append(mesh.name) or real_build(mesh, *a))
    ground_end, blocker_end = int(whole.sample_offset[1]), int(whole.sample_offset[2])
    for start, stop, objects in [(0, ground_end + 3, ["Ground", "Blocker"]), (5, 9, ["Ground"]),
                                 (ground_end + 1, len(whole.position), ["Blocker"]), (7, 7, []),
                                 (blocker_end, len(whole.position), [])]:
        built.clear()
        ours, theirs = bake.rows(start, stop), rows_module.rows_of(whole, start, stop)
        assert built == objects  # the vertex-mode card was built once, up front
        assert (ours.samples, ours.start, ours.stop) == (theirs.samples, start, stop)
        for name in ("positions", "geometric_normals", "footprint", "group", "directions", "rotations"):
            a, b = getattr(ours.request, name), getattr(theirs.request, name)
            assert (a is None) == (b is None), name
            if a is not None:
                assert a.dtype == b.dtype and np.array_equal(a, b), (name, start, stop)
        for name in ("frame_normal", "group"):
            a, b = getattr(ours, name), getattr(theirs, name)
            assert (a is None) == (b is None) and (a is None or np.array_equal(a, b)), name
        _assert_same_table(trace_table(ours.ray_scene, ours.request), trace_table(theirs.ray_scene, theirs.request))
    with pytest.raises(ValueError, match="outside"):
        bake.rows(0, len(whole.position) + 1)


def _smooth_scene(lights=()):
    """_scene's objects and a smooth-shaded atlas bump (footprint normals, terminator lifts)."""
    scene = _scene(lights)
    bump = grid_mesh("Bump", size=0.8, segments=4, z=0.15, mode="atlas", resolution=12)
    tilt = bump.positions[bump.triangles][..., :2] * 0.6  # corner normals lean away from the middle
    normals = np.concatenate([tilt, np.ones(tilt.shape[:2] + (1,))], axis=2)
    bump.corner_normals = (normals / np.linalg.norm(normals, axis=2, keepdims=True)).astype(np.float32)
    bump.positions = bump.positions + np.array([-0.3, -0.3, 0.0])
    scene.meshes.insert(1, bump)
    return scene


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_a_worker_s_sample_rows_and_their_direct_light_are_the_whole_preparation_s_bitwise(shadows):
    """PackagedBake.sample_rows (what row_tasks.direct_light lights) equals those rows of the
    whole SampleSet, dense footprints included, and the lamps' light of each range, with the
    range's own table for shadow fractions, equals those rows of the whole bake's light."""
    from core.distributed import row_tasks
    from core.distributed import rows as rows_module
    from core.transport.direct import lamp_irradiance

    lights = [Light("Lamp", "POINT", np.ones(3), 40.0, position=np.array([0.2, 0.1, 1.0]), radius=0.2),
              Light("Sun", "SUN", np.ones(3), 2.0, direction=np.array([0.4, 0.1, -1.0]) / np.sqrt(1.17))]
    scene = _smooth_scene(lights)
    settings = BakeSettings(directions=32, bounces=1, interleave=2, footprint_samples=4, threads=1, shadows=shadows)
    whole = prepare(scene, settings, table_needed=True)
    assert whole.terminator is not None and whole.footprint[2] is not None  # the bump is smooth
    bake = rows_module.PackagedBake.read(scene, settings)
    expected, expected_rays = lamp_irradiance(whole.sample_set(), whole.shadowing(), lights)
    total_rays = 0
    for r in rows_module.row_ranges(len(whole.position), 3):
        ours, theirs = bake.sample_rows(r.start, r.stop), whole.sample_rows(r.start, r.stop)
        assert bake.sample_rows(r.start, r.stop) is ours  # kept for the next task
        for name in ("position", "normal", "geometric", "origins", "owner", "footprint", "footprint_corners",
                     "terminator", "terminator_cutoff", "footprint_normals", "ids"):
            a, b = getattr(ours, name), getattr(theirs, name)
            assert (a is None) == (b is None), name
            if a is not None:
                assert a.dtype == b.dtype and np.array_equal(a, b), (name, r)
        picked = np.arange(r.start, r.stop, 3, dtype=np.int64)
        for a, b in zip(ours.dense_footprint(picked, 9), theirs.dense_footprint(picked, 9)):
            assert (a is None) == (b is None) and (a is None or np.array_equal(a, b))
        kept = rows_module.keep_rows(bake.rows(r.start, r.stop))
        irradiance, rays = row_tasks.direct_light(bake, kept, lights)
        assert irradiance.dtype == expected.dtype and np.array_equal(irradiance, expected[r.start:r.stop]), r
        total_rays += rays
    assert total_rays == expected_rays
