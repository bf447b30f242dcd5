"""Seam stitching (core.outputs.seams): both sides of a UV seam between smooth faces read the
same light under bilinear filtering, and nothing else moves."""
import numpy as np
import pytest

from core.outputs.seams import _bilinear_taps, find_seams, stitch
from core.pipeline.relight import bake
from core.scene import Light, Material, Mesh, Scene
from core.settings import BakeSettings
from core_scenes import box_interior


def _hinge(bend_degrees=20.0, smooth=True, resolution=32):
    """Two 1 m quads meeting at the edge x = 0, the right one bent up by ``bend_degrees``;
    the left in UV [0.05, 0.45] x [0.1, 0.9], the right in [0.55, 0.95] x [0.1, 0.9], so the
    shared edge is a seam. Smooth: corner normals on the edge are the two faces' mean."""
    angle = np.radians(bend_degrees)
    right = np.array([np.cos(angle), 0.0, np.sin(angle)])
    positions = np.array([[-1, 0, 0], [0, 0, 0], [0, 1, 0], [-1, 1, 0],
                          [0, 0, 0], right, right + [0, 1, 0], [0, 1, 0]], np.float64)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int32)
    uv = np.array([[0.05, 0.1], [0.45, 0.1], [0.45, 0.9], [0.05, 0.9],
                   [0.55, 0.1], [0.95, 0.1], [0.95, 0.9], [0.55, 0.9]], np.float32)
    up_left = np.array([0, 0, 1.0])
    up_right = np.cross(right, [0, 1, 0])
    edge = (up_left + up_right) / np.linalg.norm(up_left + up_right) if smooth else None
    normals = np.zeros((8, 3))
    normals[:4] = up_left
    normals[4:] = up_right
    if smooth:
        normals[[1, 2, 4, 7]] = edge
    return Mesh(name="Hinge", positions=positions, triangles=triangles, corner_normals=normals[triangles].astype(
        np.float32), material_index=np.zeros(4, np.int32), materials=[Material(base_color=np.full(3, 0.8))],
        uv_maps={"UVMap": uv[triangles]}, bake_uv_map="UVMap", resolution=(resolution, resolution))


def _islands(resolution=32):
    centres = (np.arange(resolution) + 0.5) / resolution
    u, v = np.meshgrid(centres, centres)  # row 0 at v = 0
    inside_v = (v > 0.1) & (v < 0.9)
    left = (u > 0.05) & (u < 0.45) & inside_v
    right = (u > 0.55) & (u < 0.95) & inside_v
    return left, right


def test_a_seam_between_smooth_faces_is_found_once_and_a_sharp_edge_is_not():
    mesh = _hinge()
    left, right = _islands()
    seams = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps["UVMap"], mesh.corner_normals, 32, 32,
                       left | right)
    assert seams is not None and seams.edges == 1
    # Three points per texel of the edge's 0.8 * 32 texels, each reading four texels a side.
    assert len(seams.index) == int(np.ceil(3 * 0.8 * 32)) and seams.index.shape[1] == 8
    np.testing.assert_allclose(seams.weight[:, :4].sum(1), 1.0)
    np.testing.assert_allclose(seams.weight[:, 4:].sum(1), -1.0)
    sharp = _hinge(smooth=False)
    assert find_seams(sharp.positions, sharp.triangles, sharp.uv_maps["UVMap"], sharp.corner_normals, 32, 32,
                      left | right) is None


def test_a_mesh_split_at_its_seam_is_welded_by_position():
    mesh = _hinge()  # vertices 1/4 and 2/7 are distinct indices at equal positions
    assert not np.array_equal(mesh.triangles[0], mesh.triangles[2])
    seams = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps["UVMap"], mesh.corner_normals, 32, 32,
                       np.ones((32, 32), bool))
    assert seams is not None and seams.edges == 1


def test_stitching_makes_the_two_sides_agree_and_moves_only_texels_the_seam_reads():
    mesh = _hinge()
    left, right = _islands()
    image = np.zeros((32, 32, 3), np.float32)
    image[left] = (1.0, 0.5, 0.25)
    image[right] = (2.0, 1.0, 0.5)
    # The dilated gutter, as sample_image leaves it: each side's value pushed outwards.
    image[:, :16][~left[:, :16]] = (1.0, 0.5, 0.25)
    image[:, 16:][~right[:, 16:]] = (2.0, 1.0, 0.5)
    seams = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps["UVMap"], mesh.corner_normals, 32, 32,
                       left | right)
    done = stitch(image, seams)
    assert done.before > 0.3
    assert done.after < 0.01 * done.before
    touched = np.zeros(32 * 32, bool)
    touched[seams.texels] = True
    moved = np.abs(done.image - image).max(axis=2).reshape(-1) > 0
    assert moved.any() and not (moved & ~touched).any()
    # The two sides meet in between: the stitched seam is neither side's value.
    lookups = np.einsum("sk,skc->sc", np.abs(seams.weight[:, :4]), done.image.reshape(-1, 3)[seams.texels][
        seams.index[:, :4]])
    assert (lookups[:, 0] > 1.05).all() and (lookups[:, 0] < 1.95).all()
    assert np.isfinite(done.image).all() and (done.image >= 0).all()


def test_the_gutter_takes_the_stitch_and_the_covered_texels_keep_their_baked_light():
    """Covered texels hold the light Cycles bakes there; where gutter texels can make the two
    sides' lookups agree, the covered ones move by a thousandth of the step across the seam
    (GUTTER_KEEP 0.1 moved them by 0.6%)."""
    mesh = _hinge()
    left, right = _islands()
    image = np.zeros((32, 32, 3), np.float32)
    image[:, :16] = (1.0, 0.5, 0.25)  # each side's value, dilated into its gutter
    image[:, 16:] = (2.0, 1.0, 0.5)
    seams = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps["UVMap"], mesh.corner_normals, 32, 32,
                       left | right)
    done = stitch(image, seams)
    assert done.after < 0.002 * done.before
    change = np.abs(done.image - image)[..., 0].reshape(-1)
    covered = (left | right).reshape(-1)[seams.texels]
    assert change[seams.texels][covered].max() < 1e-3
    assert change[seams.texels][~covered].max() > 0.3


def test_bilinear_taps_match_the_gather_s_convention():
    image = np.arange(12.0).reshape(3, 4)  # row 0 at v = 0
    uv = np.array([[0.125, 1 / 6], [0.5, 0.5], [1.0, 1.0], [0.0, 0.0]])
    texels, weights = _bilinear_taps(uv, 4, 3)
    values = (image.reshape(-1)[texels] * weights).sum(1)
    np.testing.assert_allclose(values, [0.0, 5.5, 11.0, 0.0])


def _hinge_bake(stitch_seams):
    mesh = _hinge(bend_degrees=30.0)
    towards_sun = np.array([0.5, -0.3, 0.8])
    sun = Light("Sun", "SUN", np.ones(3), 3.0, direction=-towards_sun / np.linalg.norm(towards_sun))
    settings = BakeSettings(directions=64, bounces=0, passes=("lighting",), stitch_seams=stitch_seams)
    return bake(Scene([mesh], [sun]), settings)


def test_a_bake_stitches_its_seams_and_reports_how_far_the_sides_disagreed():
    plain, stitched = _hinge_bake(False), _hinge_bake(True)
    entry = stitched.report["objects"][0]
    assert entry["seam_edges"] == 1
    before, after = entry["seam_disagreement"]
    assert before > 0.02 and after < 0.1 * before
    assert "seam stitching: off" in plain.report["skipped"]
    assert "seam_edges" not in plain.report["objects"][0]
    assert any(p["pass"].startswith("seam stitching") for p in stitched.report["passes"])
    a, b = plain.objects[0].images["lighting"], stitched.objects[0].images["lighting"]
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(a[..., 3], b[..., 3])
    # Texels far from the seam (the outer quarter of each island) keep their values.
    np.testing.assert_array_equal(a[:, :6], b[:, :6])


def test_a_box_seen_from_inside_has_only_sharp_edges_so_nothing_is_stitched():
    settings = BakeSettings(directions=32, bounces=0, passes=("lighting",))
    light = Light("Lamp", "POINT", np.ones(3), 50.0, position=np.zeros(3))
    result = bake(Scene([box_interior()], [light]), settings)
    assert "seam_edges" not in result.report["objects"][0]
    assert any(s.startswith("seam stitching of 1 objects without UV seams") for s in result.report["skipped"])


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_texels_never_leave_the_stitch(value):
    mesh = _hinge()
    left, right = _islands()
    image = np.ones((32, 32, 3), np.float32)
    image[16, 14] = value
    seams = find_seams(mesh.positions, mesh.triangles, mesh.uv_maps["UVMap"], mesh.corner_normals, 32, 32,
                       left | right)
    assert np.isfinite(stitch(image, seams).image).all()


def test_each_lighting_of_a_batch_reports_its_own_seams():
    from core.pipeline.prepare import prepare
    from core.pipeline.relight import relight_many
    from core.scene import World

    mesh = _hinge(bend_degrees=30.0)
    settings = BakeSettings(directions=64, bounces=0, passes=("lighting",))
    p = prepare(Scene([mesh], []), settings, table_needed=False)

    def sun(towards):
        towards = np.asarray(towards, np.float64)
        return [Light("Sun", "SUN", np.ones(3), 3.0, direction=-towards / np.linalg.norm(towards))]

    # Along the hinge's edge the two faces' light differs more under a low sun across it.
    results = relight_many(p, [(sun([0.5, -0.3, 0.8]), World()), (sun([0.9, 0.0, 0.2]), World())])
    before = [r.report["objects"][0]["seam_disagreement"][0] for r in results]
    alone = [relight_many(p, [(sun(t), World())])[0].report["objects"][0]["seam_disagreement"][0]
             for t in ([0.5, -0.3, 0.8], [0.9, 0.0, 0.2])]
    assert before[0] != before[1]
    np.testing.assert_allclose(before, alone, rtol=1e-6)


def test_welding_by_one_key_groups_and_orders_vertices_as_rows_do():
    """The welded labels of find_seams (one int64 key per grid cell) are those of np.unique
    over the cells' rows: the same vertices share a label, in the same order, so seams pair
    and list their edges the same way. A non-finite vertex welds to nothing and leaves the
    others apart (its NaN extent once welded the whole mesh into one vertex)."""
    from core.outputs.seams import WELD_FRACTION, _welded
    rng = np.random.default_rng(7)
    for scale in (1e-3, 1.0, 1e5):
        positions = rng.integers(-50, 50, (400, 3)) * scale * 0.25
        positions[200:] = positions[:200] + rng.normal(0, scale * 1e-9, (200, 3))  # near-duplicates weld
        cells = np.round(positions / (np.ptp(positions, axis=0).max() * WELD_FRACTION)).astype(np.int64)
        _, expected = np.unique(cells, axis=0, return_inverse=True)
        labels = _welded(positions)
        np.testing.assert_array_equal(labels, expected.reshape(-1))
        assert np.array_equal(labels[:200], labels[200:])
    with_nan = rng.random((50, 3))
    with_nan[3] = np.nan
    labels = _welded(with_nan)
    assert len(labels) == 50 and len(np.unique(labels)) == 50


def test_ranks_through_a_stable_sort_are_np_unique_s_inverse():
    """_ranks (the welding's labels) equals np.unique's inverse on keys in order, nearly in
    order (a grid's rows), shuffled, all equal, one key and none repeated."""
    from core.outputs.seams import _ranks
    rng = np.random.default_rng(3)
    grid = (np.arange(300)[:, None] << 21 | np.arange(300)[None, :]).reshape(-1).astype(np.int64)
    cases = [grid, grid[::-1].copy(), rng.permutation(grid), rng.integers(0, 50, 5000).astype(np.int64),
             np.full(10, 7, np.int64), np.array([1 << 62], np.int64), rng.integers(-(1 << 40), 1 << 40, 1000)]
    for keys in cases:
        _, expected = np.unique(keys, return_inverse=True)
        ranks = _ranks(keys)
        assert ranks.dtype == np.int64
        np.testing.assert_array_equal(ranks, expected.reshape(-1))


def test_edges_between_unsplit_vertices_are_left_out_without_changing_the_seams(monkeypatch):
    """find_seams pairs only edges with a split vertex at an end (_split_vertices): on a
    smooth grid cut into islands, with UVs jittered well under SPLIT_TEXELS, a NaN corner
    and a flat-shaded block, the seams are those found when every edge is paired."""
    from core.outputs import seams as module

    rng = np.random.default_rng(11)
    n = 40
    xs, ys = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="xy")
    positions = np.column_stack([xs.ravel(), ys.ravel(), 0.1 * np.sin(xs.ravel() / 3.0)]).astype(np.float64)
    cells = np.arange(n * n)
    corner = (cells // n) * (n + 1) + cells % n
    triangles = np.concatenate([np.column_stack([corner, corner + 1, corner + n + 2]),
                                np.column_stack([corner, corner + n + 2, corner + n + 1])]).astype(np.int32)
    # Islands of 10 x 10 cells, each moved to its own place in the atlas.
    cell = np.concatenate([cells, cells])
    island = (cell // n) // 10 * 4 + (cell % n) // 10
    shift = rng.uniform(0.0, 0.2, size=(16, 2))
    uv = positions[triangles][..., :2] / (n * 1.3) + shift[island][:, None, :]
    uv += rng.uniform(-1e-4, 1e-4, size=uv.shape)  # 0.05 texels at 256^2 is 2e-4
    uv[17, 1] = np.nan
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (len(triangles), 3, 1))
    normals[island == 5] = [0.0, 0.6, 0.8]
    coverage = rng.random((256, 256)) > 0.3
    found = find_seams(positions, triangles, uv, normals, 256, 256, coverage)
    monkeypatch.setattr(module, "_split_vertices", lambda corners, uvs, scale: np.ones(int(corners.max()) + 1, bool))
    every_edge = find_seams(positions, triangles, uv, normals, 256, 256, coverage)
    assert found is not None and found.edges > 100
    assert found.edges == every_edge.edges
    for name in ("texels", "keep", "index", "weight"):
        np.testing.assert_array_equal(getattr(found, name), getattr(every_edge, name))
