"""The bake the panel runs: on a worker thread, with progress and a cancel.

Background mode has no event loop, so the modal operator itself cannot run here; what
it is built from can: BakeJob's three steps with compute() on a thread, and the
Progress object the modal loop reads and cancels through.
"""
import threading

import bpy
import numpy as np
import pytest

from bpy_scenes import black_world, cube, grid, image_pixels, material, mesh_object, point, select_only


@pytest.fixture
def scene(clean_scene):
    black_world()
    ground = mesh_object("Ground", grid(1.0, segments=4), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.4), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.4), uv_map=None)
    point(80.0, (0.5, 0.3, 1.2), name="Lamp")
    props = bpy.context.scene.visibake
    props.directions, props.bounces, props.resolution, props.use_cache = 64, 2, 32, False
    select_only([ground, block])
    return ground, block


def test_progress_percentages_status_and_cancel(visibake):
    progress = visibake.operators.bake.Progress()
    seen = []
    for stage in ("layout", "samples", "visibility", "transport", "outputs"):
        for fraction in (0.0, 0.5, 1.0):
            progress(stage, fraction)
            seen.append(progress.percent)
    assert seen == sorted(seen) and seen[-1] == 100 and seen[0] == 0
    assert "Esc to cancel" in progress.status_text()
    progress.cancel()
    with pytest.raises(visibake.core.pipeline.Cancelled):
        progress("transport", 0.6)


def test_time_left_comes_from_the_known_work_and_the_measured_rate(visibake, scene):
    job = visibake.operators.job
    bake_job = job.BakeJob(bpy.context, list(scene))
    bake_job.start()
    try:
        work = bake_job.expected_work()
        # Ground 32 x 32 texels and the block's atlas, 64 directions, 2 bounces.
        assert work["visibility"] > 0.7 * 32 * 32 * 64 / 2 and work["transport"] == 3 * work["visibility"]
        progress = visibake.operators.bake.Progress()
        progress.plan({"visibility": 1e6, "transport": 3e6})
        progress("visibility", 0.0)
        at_start = progress.seconds_left()
        assert at_start == pytest.approx(1e6 / 5e6 + 3e6 / 1.5e7)  # the assumed rates
        progress("transport", 0.5)
        assert progress.seconds_left() < at_start and "s left" in progress.status_text()
    finally:
        bake_job.abort()


def test_a_bake_on_a_worker_thread_gives_the_blocking_bake_s_images(visibake, scene):
    job = visibake.operators.job
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    blocking = image_pixels("VB_Ground_lighting")
    progress = visibake.operators.bake.Progress()
    bake_job = job.BakeJob(bpy.context, list(scene), progress=progress)
    bake_job.start()
    worker = threading.Thread(target=bake_job.compute)
    worker.start()
    worker.join()
    outcome = bake_job.finish()
    assert progress.percent == 100 and outcome.report["total_seconds"] > 0
    np.testing.assert_array_equal(blocking, image_pixels("VB_Ground_lighting"))


def test_cancel_from_another_thread_leaves_the_scene_as_it_was(visibake, scene):
    job = visibake.operators.job
    ground, block = scene
    progress = visibake.operators.bake.Progress()
    stages = []

    def cancel_during_visibility(stage, fraction):
        stages.append(stage)
        if stage == "visibility" and fraction > 0:
            progress.cancel()  # as the modal loop does when Esc is pressed
        progress(stage, fraction)

    bake_job = job.BakeJob(bpy.context, list(scene), progress=cancel_during_visibility)
    bake_job.start()
    assert "VisiBake" in block.data.uv_layers  # made by start(), for the unwrapped block
    errors = []

    def compute():
        try:
            bake_job.compute()
        except BaseException as error:  # what the modal operator's worker keeps
            errors.append(error)

    worker = threading.Thread(target=compute)
    worker.start()
    worker.join(timeout=60)
    assert not worker.is_alive()
    assert errors and isinstance(errors[0], visibake.core.pipeline.Cancelled)
    assert "transport" not in stages  # stopped in the visibility stage
    bake_job.abort()
    assert "VisiBake" not in block.data.uv_layers
    assert "VB_Ground_lighting" not in bpy.data.images and "VB_Block_lighting" not in bpy.data.images
