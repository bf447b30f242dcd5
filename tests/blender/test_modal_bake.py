"""The bake the panel runs: beside the UI, with progress and a cancel.

Background mode has no window and no event loop, so the modal operator itself cannot
run here (bpy does not let a test make an operator instance either). Everything its
``modal`` does is in plain objects that can: ``ModalBake``, which the operator ticks on
every timer event, ``event_action``, which decides what each event does, ``Progress``,
which the status bar reads and Esc cancels through, and ``failure_message``. The tests
below drive them exactly as ``modal`` does, with a real bake.
"""
import json
import signal
import subprocess
import threading
import time
from types import SimpleNamespace

import bpy

import pytest

from bpy_scenes import (
    assert_same_light,
    black_world,
    cube,
    grid,
    image_pixels,
    material,
    mesh_object,
    point,
    select_only,
    uv_sphere,
)


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


class _Clock:
    """``time`` as core.pipeline.progress sees it: a perf_counter that moves only when set."""

    def __init__(self):
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


@pytest.fixture
def clock(visibake, monkeypatch):
    """The time-left model on a clock the test sets, so its estimates are exact numbers."""
    controlled = _Clock()
    monkeypatch.setattr(visibake.core.pipeline.progress, "time", controlled)
    return controlled


def test_progress_percentages_status_and_cancel(visibake):
    progress = visibake.core.pipeline.progress.Progress()
    seen = []
    for stage in ("layout", "samples", "visibility", "transport", "outputs"):
        for fraction in (0.0, 0.5, 1.0):
            progress(stage, fraction)
            seen.append(progress.percent)
    assert seen == sorted(seen) and seen[-1] == 100 and seen[0] == 0
    assert "Esc to cancel" in progress.status_text()
    progress.cancel()
    with pytest.raises(visibake.core.errors.Cancelled):
        progress("transport", 0.6)


def test_time_left_comes_from_the_known_work_and_the_measured_rate(visibake, scene, clock):
    job = visibake.operators.adapter.job
    bake_job = job.BakeJob(bpy.context, list(scene))
    bake_job.start()
    try:
        work = bake_job.expected_work()
        # Ground 32 x 32 texels and the block's atlas, 64 directions, 2 bounces, one lamp
        # with exact shadows (a shadow ray weighs as SHADOW_RAY_IN_LOOKUPS lookups). The hard
        # lamp over 16-point texel footprints probes each box's 4 corners, then traces every
        # point in the share of texels a shadow edge crosses.
        assert work["visibility"] > 0.7 * 32 * 32 * 64 / 2
        samples = work["visibility"] / 32
        rays = bake_job.shadow_rays_per_sample
        assert rays == pytest.approx(4 + visibake.core.transport.direct.TYPICAL_PENUMBRA_SHARE * 16)
        assert work["transport"] == pytest.approx(3 * work["visibility"] + job.SHADOW_RAY_IN_LOOKUPS * samples * rays)
        progress = visibake.core.pipeline.progress.Progress()
        progress.plan({"visibility": 1e6, "transport": 3e6})
        progress("visibility", 0.0)
        assert progress.seconds_left() == pytest.approx(1e6 / 5e6 + 3e6 / 1.5e7)  # the assumed rates
        clock.now = 0.1
        progress("visibility", 0.25)  # the first step of real work: rates are measured from here
        clock.now = 0.3
        progress("visibility", 0.75)  # half the rays in 0.2 s: 2.5e6 rays/s replaces the assumed rate
        assert progress.seconds_left() == pytest.approx(0.25 * 1e6 / 2.5e6 + 3e6 / 1.5e7)
        # What the visibility stage did not do is still to come, at its measured rate.
        progress("transport", 0.5)
        assert progress.seconds_left() == pytest.approx(0.25 * 1e6 / 2.5e6 + 0.5 * 3e6 / 1.5e7)
        assert "s left" in progress.status_text()
    finally:
        bake_job.abort()


def test_time_left_counts_down_through_a_step_that_reports_only_at_its_end(visibake, clock):
    progress = visibake.core.pipeline.progress.Progress()
    progress.plan({"unwrap": 2.0, "visibility": 5e6})  # an unwrap of 2 s, then 1 s of rays at 5e6 rays/s
    progress("unwrap", 0.0)
    assert progress.seconds_left() == pytest.approx(3.0)
    clock.now = 0.25
    progress("unwrap", 0.0)  # a cancel check: no progress, but the clock ran on
    assert progress.seconds_left() == pytest.approx(2.75)
    clock.now = 2.5  # longer than planned: the unwrap's share stops at 0, not below
    assert progress.seconds_left() == pytest.approx(1.0)
    progress("unwrap", 1.0)  # as run_unwraps reports at the end
    progress("visibility", 0.0)
    assert progress.seconds_left() == pytest.approx(1.0)
    clock.now = 3.0
    progress("visibility", 0.25)
    clock.now = 4.0
    progress("visibility", 0.5)  # a quarter of the rays in 1 s: 1.25e6 rays/s, so 2 s for the other half
    assert progress.seconds_left() == pytest.approx(2.0)
    assert progress.percent == 66 and "about 2 s left" in progress.status_text()  # 4 s of 6


def test_a_bake_on_a_worker_thread_gives_the_blocking_bake_s_images(visibake, scene):
    job = visibake.operators.adapter.job
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    blocking = image_pixels("VB_Ground_lighting")
    progress = visibake.core.pipeline.progress.Progress()
    bake_job = job.BakeJob(bpy.context, list(scene), progress=progress)
    bake_job.start()
    worker = threading.Thread(target=bake_job.compute)
    worker.start()
    worker.join()
    outcome = bake_job.finish()
    assert progress.percent == 100 and outcome.report["total_seconds"] > 0
    assert_same_light(blocking, image_pixels("VB_Ground_lighting"))


def test_cancel_from_another_thread_leaves_the_scene_as_it_was(visibake, scene):
    job = visibake.operators.adapter.job
    ground, block = scene
    progress = visibake.core.pipeline.progress.Progress()
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
    assert errors and isinstance(errors[0], visibake.core.errors.Cancelled)
    assert "transport" not in stages  # stopped in the visibility stage
    bake_job.abort()
    assert "VisiBake" not in block.data.uv_layers
    assert "VB_Ground_lighting" not in bpy.data.images and "VB_Block_lighting" not in bpy.data.images


def _modal(visibake, objects, **job_options):
    progress = visibake.core.pipeline.progress.Progress()
    bake_job = visibake.operators.adapter.job.BakeJob(bpy.context, list(objects), progress=progress, **job_options)
    return visibake.operators.adapter.modal.ModalBake(bake_job, progress)


def _tick_until_done(modal, on_tick=None, limit_seconds=120.0):
    """Tick as the operator does on its 0.1 s timer; returns the ticks that found the bake running."""
    waiting = 0
    deadline = time.perf_counter() + limit_seconds
    while not modal.tick():
        waiting += 1
        if on_tick is not None:
            on_tick(modal)
        assert time.perf_counter() < deadline, "the bake never ended"
        time.sleep(0.02)
    return waiting


def test_the_modal_bake_ticks_to_the_blocking_bake_s_images(visibake, scene):
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    blocking = image_pixels("VB_Ground_lighting")
    bpy.data.images.remove(bpy.data.images["VB_Ground_lighting"])
    modal = _modal(visibake, scene)
    waiting = _tick_until_done(modal)
    assert modal.error is None and modal.outcome is not None
    assert waiting > 0  # the long steps ran beside the ticks, not inside them
    assert modal.progress.percent == 100
    assert_same_light(blocking, image_pixels("VB_Ground_lighting"))


def test_a_target_error_bake_ticks_through_its_pilot_to_the_blocking_bake_s_images(visibake, scene):
    props = bpy.context.scene.visibake
    props.target_error = 0.005
    assert bpy.ops.visibake.bake() == {"FINISHED"}
    chosen = props.chosen_directions
    # The pilot's estimate (0.59%: lamps 0.22%, gathered 0.55%) is above the target: the bake chose more.
    assert chosen > 64, json.loads(bpy.context.scene["visibake_report"])["target"]
    blocking = image_pixels("VB_Ground_lighting")
    bpy.data.images.remove(bpy.data.images["VB_Ground_lighting"])
    props.chosen_directions = 0  # the same pilot again
    modal = _modal(visibake, scene)
    _tick_until_done(modal)
    assert modal.error is None and props.chosen_directions == chosen
    assert_same_light(blocking, image_pixels("VB_Ground_lighting"))


def test_a_cancel_at_the_chosen_directions_leaves_the_scene_and_the_choice_as_they_were(visibake, scene):
    props = bpy.context.scene.visibake
    props.target_error, props.chosen_directions = 0.005, 0
    images = set(bpy.data.images.keys())
    progress = visibake.core.pipeline.progress.Progress()
    seen = []

    def esc_when_the_second_table_starts(name, fraction):
        if name == "visibility" and "transport" in seen:
            progress.cancel()
        seen.append(name)
        progress(name, fraction)

    modal = visibake.operators.adapter.modal.ModalBake(visibake.operators.adapter.job.BakeJob(
        bpy.context, list(scene), progress=esc_when_the_second_table_starts), progress)
    _tick_until_done(modal)
    assert isinstance(modal.error, visibake.core.errors.Cancelled), modal.error
    assert set(bpy.data.images.keys()) == images and props.chosen_directions == 0
    assert "VisiBake" not in scene[1].data.uv_layers


@pytest.mark.parametrize("stage", ["unwrap", "visibility", "transport"])
def test_a_cancel_in_any_stage_leaves_the_scene_as_it_was(visibake, scene, stage):
    uv_maps = {obj.name: [layer.name for layer in obj.data.uv_layers] for obj in scene}
    images = set(bpy.data.images.keys())
    progress = visibake.core.pipeline.progress.Progress()
    seen = []

    def esc_when_the_stage_starts(name, fraction):
        # Esc pressed just as the stage starts (on a tiny scene a tick might miss it).
        seen.append(name)
        if name == stage:
            progress.cancel()
        progress(name, fraction)

    modal = visibake.operators.adapter.modal.ModalBake(visibake.operators.adapter.job.BakeJob(bpy.context, list(scene),
                                                         progress=esc_when_the_stage_starts), progress)
    _tick_until_done(modal)
    assert isinstance(modal.error, visibake.core.errors.Cancelled), modal.error
    assert stage in seen and "outputs" not in seen
    assert {obj.name: [layer.name for layer in obj.data.uv_layers] for obj in scene} == uv_maps
    assert set(bpy.data.images.keys()) == images
    level, message = visibake.operators.bake.failure_message(modal.error)
    assert level == "WARNING" and "nothing was changed" in message


def test_a_cancel_between_steps_is_honoured_before_the_next_one(visibake, scene):
    modal = _modal(visibake, scene)
    assert modal.tick() is False  # planned; the unwrap of the block runs on a worker
    modal.progress.cancel()
    _tick_until_done(modal)
    assert isinstance(modal.error, visibake.core.errors.Cancelled)
    assert "VisiBake" not in scene[1].data.uv_layers and "VB_Ground_lighting" not in bpy.data.images


def test_a_cancel_stops_a_long_unwrap_at_once(visibake, clean_scene, monkeypatch):
    # ~65k triangles: xatlas takes about 12 s here, during which it holds the GIL, so
    # on a thread it could be neither interrupted nor left to run beside the UI.
    children = []

    def recording_popen(*args, **kwargs):
        children.append(subprocess.Popen(*args, **kwargs))
        return children[-1]

    unwrap_child = visibake.core.sampling.unwrap_child
    monkeypatch.setattr(unwrap_child, "subprocess", SimpleNamespace(**{**vars(subprocess), "Popen": recording_popen}))
    sphere = mesh_object("Sphere", uv_sphere(1.0, segments=256, rings=128), material("W", (0.8, 0.8, 0.8)),
                         uv_map=None)
    sphere.visibake.mode = "atlas"
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.use_cache = 16, 256, False
    select_only([sphere])
    modal = _modal(visibake, [sphere])
    ticks_in_unwrap = []

    def cancel_in_unwrap(modal):
        if modal.progress.stage == "unwrap":
            ticks_in_unwrap.append(bool(children) and children[0].poll() is None)
            # Esc once the ticks have kept coming for a while with the child unwrapping.
            if ticks_in_unwrap.count(True) == 5:
                modal.progress.cancel()

    _tick_until_done(modal, cancel_in_unwrap)
    assert isinstance(modal.error, visibake.core.errors.Cancelled)
    # The UI stayed live while xatlas ran (ticks with the child running), and the cancel
    # did not wait for the unwrap: the one child was killed, not left to finish.
    assert ticks_in_unwrap.count(True) >= 5 and modal.progress.cancelled
    assert len(children) == 1 and children[0].returncode == -signal.SIGKILL
    assert "VisiBake" not in sphere.data.uv_layers


def test_with_the_gpu_passes_the_lighting_runs_on_the_main_thread(visibake, scene):
    threads = {}
    progress = visibake.core.pipeline.progress.Progress()

    def record(stage, fraction):
        threads.setdefault(stage, set()).add(threading.current_thread() is threading.main_thread())
        progress(stage, fraction)

    bake_job = visibake.operators.adapter.job.BakeJob(bpy.context, list(scene), progress=record, device_name="gpu")
    modal = visibake.operators.adapter.modal.ModalBake(bake_job, progress)
    _tick_until_done(modal)
    assert modal.error is None, modal.error
    assert threads["visibility"] == {False} and threads["transport"] == {True}


def test_bad_input_ends_the_modal_bake_on_its_first_tick(visibake, scene):
    bpy.context.scene.visibake.passes = set()
    modal = _modal(visibake, scene)
    assert modal.tick() is True
    level, message = visibake.operators.bake.failure_message(modal.error)
    assert level == "ERROR" and "passes" in message


def test_events_during_a_bake_navigation_passes_edits_are_held_esc_cancels(visibake):
    action = visibake.operators.bake.event_action
    assert action("ESC", "PRESS") == "cancel"
    assert action("TIMER", "NOTHING") == "tick"
    for navigation in ("MOUSEMOVE", "MIDDLEMOUSE", "WHEELUPMOUSE", "TRACKPADPAN", "NUMPAD_5", "NDOF_MOTION",
                       "TIMER_REPORT"):
        assert action(navigation, "PRESS") == "pass", navigation
    for edit in ("Z", "LEFTMOUSE", "RIGHTMOUSE", "G", "X", "DEL", "TAB", "F12", "RET"):
        assert action(edit, "PRESS") == "hold", edit


def test_failure_messages_say_what_happened_and_what_to_do(visibake):
    message = visibake.operators.bake.failure_message
    assert message(visibake.core.errors.BakeRefused("no mesh objects to bake: select some")) == (
        "ERROR", "no mesh objects to bake: select some")
    level, text = message(ReferenceError("StructRNA of type Object has been removed"))
    assert level == "ERROR" and "bake again" in text
    level, text = message(ZeroDivisionError("division by zero"))
    assert level == "ERROR" and "nothing was changed" in text and "report" in text
