"""Scale-out (issue 20): a bake whose table is traced and read by ranges of sample rows
(core.distributed.split) gives bitwise the one-process bake's images, for any number of
ranges. Here the ranges are kept in this process (the in-process executor, the reference the
cluster is checked against in test_distributed.py)."""
import collections

import numpy as np
import pytest

from core.distributed.split import InProcessRows, SplitTable
from core.errors import BakeRefused
from core.pipeline.prepare import prepare
from core.pipeline.relight import bake, relight
from core.scene import Light, Material, Scene, World
from core.settings import BakeSettings
from core_scenes import box_interior, grid_mesh, quad_mesh

PASSES = ("lighting", "direct", "indirect", "ao")


def _interior() -> Scene:
    """A closed box with a tilted card (short hits, near hits, buried texels), a small emitting
    tile (sampled directly), a vertex-mode grid, a point lamp and a sun."""
    card = quad_mesh("Card", [(-0.2, -0.2, -0.1), (0.2, -0.2, -0.1), (0.2, 0.2, 0.1), (-0.2, 0.2, 0.1)],
                     resolution=16)
    tile = quad_mesh("Tile", [(0.3, 0.3, 0.45), (0.3, 0.4, 0.45), (0.4, 0.4, 0.45), (0.4, 0.3, 0.45)],
                     material=Material(base_color=np.full(3, 0.5), emission=np.array([4.0, 3.0, 2.0])), resolution=4)
    grid = grid_mesh("Grid", size=0.3, segments=2, z=-0.3, material=Material(base_color=np.full(3, 0.6)))
    lights = [Light("Lamp", "POINT", np.ones(3), 50.0, position=np.array([0.1, 0.2, 0.3])),
              Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.3, 0.0, -1.0]) / np.hypot(0.3, 1.0))]
    return Scene([box_interior(resolution=32), card, tile, grid], lights)


def _open_ground() -> Scene:
    """An open ground with a roof, under a world image seen per interleaved rotation."""
    rng = np.random.default_rng(5)
    ground = quad_mesh("Ground", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=20)
    roof = quad_mesh("Roof", [(-0.4, -0.4, 0.6), (-0.4, 0.4, 0.6), (0.4, 0.4, 0.6), (0.4, -0.4, 0.6)], resolution=8)
    world = World(color=np.full(3, 0.2), image=rng.random((8, 16, 3), dtype=np.float32))
    return Scene([ground, roof], [Light("Lamp", "SPOT", np.ones(3), 80.0, position=np.array([0.5, 0.2, 1.2]),
                                        direction=np.array([0.0, 0.0, -1.0]))], world)


class CountingRows(InProcessRows):
    """The in-process executor, counting the tasks it ran by name."""

    def __init__(self, parts):
        super().__init__(parts)
        self.tasks = collections.Counter()

    def run(self, task, per_range, shared, progress=None):
        self.tasks[task] += 1
        return super().run(task, per_range, shared, progress)


def _assert_same_images(ours, theirs):
    assert [o.name for o in ours.objects] == [o.name for o in theirs.objects]
    for a, b in zip(ours.objects, theirs.objects):
        assert list(a.images) == list(b.images)
        for name in a.images:
            assert a.images[name].dtype == b.images[name].dtype
            assert np.array_equal(a.images[name], b.images[name]), (a.name, name)


@pytest.mark.parametrize("shadows", ["exact", "fractions"])
def test_a_bake_by_row_ranges_equals_the_one_process_bake_bitwise(shadows):
    scene = _interior()
    settings = BakeSettings(directions=64, bounces=2, interleave=2, footprint_samples=4, seed=3, shadows=shadows,
                            passes=PASSES, emitter_samples=16)
    whole = bake(scene, settings)
    assert all(np.any(o.images["indirect"][..., :3] > 0) for o in whole.objects)
    for parts in (1, 3, 7):
        rows = CountingRows(parts)
        split = bake(scene, settings, split=rows)
        _assert_same_images(split, whole)
        # Every pass that reads the table ran by ranges: nothing read a joined table.
        assert rows.tasks["gather_rows"] >= 3 and rows.tasks["ambient_occlusion"] == 1
        assert rows.tasks["exposed_share"] == rows.tasks["normalisation"] == 1
        # Near hits, the emitted light's farther ones (the interior's emitter), and short hits (exact shadows).
        assert rows.tasks["close_entries"] == (3 if shadows == "exact" else 2)
        # Each lamp's direct light ran by ranges too, its shadow fractions in each range's own table.
        assert rows.tasks["direct_light"] == 2 and rows.tasks["shadow_fractions"] == 0
        assert "table" not in rows.tasks
        assert split.report["rays"]["visibility_in_table"] == whole.report["rays"]["visibility_in_table"]
        assert any("held by sample rows" in s for s in split.report["skipped"])


def test_world_light_per_rotation_and_a_spot_lamp_by_row_ranges():
    scene = _open_ground()
    settings = BakeSettings(directions=48, bounces=1, interleave=3, footprint_samples=4, passes=PASSES)
    whole = bake(scene, settings)
    for parts in (2, 5):
        _assert_same_images(bake(scene, settings, split=InProcessRows(parts)), whole)


def test_the_split_table_holds_the_whole_table_s_rows():
    scene = _interior()
    settings = BakeSettings(directions=32, bounces=1, interleave=2, footprint_samples=4)
    whole = prepare(scene, settings, table_needed=True)
    split = prepare(scene, settings, table_needed=True, split=InProcessRows(4))
    assert isinstance(split.table, SplitTable) and len(split.table.ranges) == 4
    joined = split.table.whole()
    for name in ("hit_object", "hit_uv_code", "hit_distance_code", "traced_per_sample", "backface_per_sample"):
        assert np.array_equal(getattr(joined, name), getattr(whole.table, name)), name
    assert np.array_equal(split.table.buried(), whole.table.buried())
    assert split.table.rays_cast == whole.table.rays_cast == split.visibility_rays
    # In process, the ranges are all here: the same entries, and each range's rows may end in a
    # word of entry bits of its own (16 bytes a direction with its first entry's index).
    extra = split.table.nbytes - whole.table.nbytes
    assert 0 <= extra <= 16 * len(whole.table.directions) * (len(split.table.ranges) - 1)


def test_a_split_table_is_not_read_by_another_device():
    class OtherDevice:
        name = "gpu"

    scene = _interior()
    p = prepare(scene, BakeSettings(directions=16, bounces=1), split=InProcessRows(2))
    with pytest.raises(BakeRefused, match="bake on the CPU device"):
        relight(p, scene.lights, scene.world, backend=OtherDevice())


def test_the_summary_says_where_the_table_was_held():
    from core.outputs.report import Report
    from core.outputs.summary import summary_lines

    scene = _interior()
    result = bake(scene, BakeSettings(directions=16, bounces=1), split=InProcessRows(3))
    report = Report.from_dict(result.report)
    assert report.split == {"ranges": 3, "executor": "in process",
                            "table_bytes_held_by_ranges": result.report["split"]["table_bytes_held_by_ranges"]}
    report.split["cluster"] = {"workers": 2, "scheduler": None}
    lines = summary_lines(report)
    assert any(line.startswith("  split: the table in 3 ranges of texels on 2 local workers") for line in lines)
