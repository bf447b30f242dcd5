"""Bake and Relight: run :func:`job.run_bake` on the selected (or all) meshes."""
import json
import threading
import time

import bpy

from ..core.pipeline import Cancelled
from . import job


def summary(report: dict) -> str:
    objects = [o for o in report["objects"] if o["output"]]
    texels = sum(o["texels"] for o in objects)
    verb = "relit" if report.get("relight_only") else "baked"
    cache = report.get("cache", {}).get("state", "off")
    visibility = {"hit": "visibility from the cache", "updated": "visibility updated for changed objects",
                  "unused": "no visibility needed"}.get(cache, f"{report['rays']['visibility_cast']} visibility rays")
    return (f"VisiBake: {verb} {len(objects)} object(s), {texels} texels, {visibility}, "
            f"in {report['total_seconds']:.1f} s")


# The stages of a bake in the order they run, and their rough share of its time (the
# demo: layout and samples a few percent, visibility and transport the rest).
STAGES = (("layout", 0.05), ("samples", 0.03), ("cache", 0.07), ("visibility", 0.45), ("transport", 0.38),
          ("outputs", 0.02))


class Progress:
    """Progress of a running bake, written by the bake (any thread) and read by the UI.

    The callback the core calls raises :class:`Cancelled` once :meth:`cancel` was
    asked for: the core calls it every batch of rays or directions (a fraction of a
    second), so a cancel takes effect within about a second.
    """

    def __init__(self):
        self.stage = "layout"
        self.fraction = 0.0
        self.stage_started = time.perf_counter()
        self.cancelled = False
        self.done_share = 0.0  # of the stages finished before the current one

    def __call__(self, stage: str, fraction: float) -> None:
        if self.cancelled:
            raise Cancelled()
        if stage != self.stage:
            shares = dict(STAGES)
            if stage in shares and self.stage in shares:
                order = [name for name, _ in STAGES]
                if order.index(stage) > order.index(self.stage):
                    self.done_share = sum(shares[name] for name in order[:order.index(stage)])
            self.stage, self.stage_started = stage, time.perf_counter()
        self.fraction = min(max(float(fraction), 0.0), 1.0)

    def cancel(self) -> None:
        self.cancelled = True

    @property
    def percent(self) -> int:
        share = dict(STAGES).get(self.stage, 0.0)
        return int(100 * min(1.0, self.done_share + share * self.fraction))

    def stage_seconds_left(self) -> float | None:
        """Time left in the running stage at its present rate; None before a first estimate."""
        if self.fraction < 0.02:
            return None
        elapsed = time.perf_counter() - self.stage_started
        return elapsed * (1.0 - self.fraction) / self.fraction

    # Rates assumed until the bake has measured its own (this machine, 2 cores: embree
    # 5.4 Mrays/s, the numpy gather ~15 M lookups/s on the demo; docs/benchmarks.md).
    ASSUMED_RATES = {"visibility": 5e6, "transport": 1.5e7}

    def plan(self, work: dict) -> None:
        """The bake's known work: {"visibility": rays to trace, "transport": table lookups}."""
        self.work = dict(work)
        self.rates = dict(self.ASSUMED_RATES)

    def seconds_left(self) -> float | None:
        """Time left for the whole bake, from the work still to do at the rates seen so far.

        None without a :meth:`plan`. The running stage's rate replaces the assumed one
        once it has done a few percent of its work.
        """
        work = getattr(self, "work", None)
        if work is None:
            return None
        order = [name for name, _ in STAGES]
        current = order.index(self.stage) if self.stage in order else 0
        if self.stage in work and self.fraction >= 0.02:
            elapsed = time.perf_counter() - self.stage_started
            self.rates[self.stage] = max(work[self.stage] * self.fraction / max(elapsed, 1e-6), 1.0)
        left = 0.0
        for index, name in enumerate(order):
            if name not in work or index < current:
                continue
            remaining = work[name] * ((1.0 - self.fraction) if index == current else 1.0)
            left += remaining / self.rates[name]
        return left

    def status_text(self) -> str:
        left = self.seconds_left()
        if left is None:
            left = self.stage_seconds_left()
            eta = f", about {left:.0f} s left in this stage" if left is not None else ""
        else:
            eta = f", about {left:.0f} s left"
        return f"VisiBake: {self.stage} {int(100 * self.fraction)}% ({self.percent}% of the bake{eta}) - Esc to cancel"


class _BakeOperator:
    relight_only = False

    def _job(self, context, progress) -> "job.BakeJob":
        props = context.scene.visibake
        return job.BakeJob(context, job.output_objects(context, props),
                           bpy.path.abspath(props.output_dir) or None, False, progress,
                           relight_only=self.relight_only)

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_last_report"] = summary(outcome.report)
        context.scene["visibake_report"] = json.dumps(outcome.report, default=float)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}

    def execute(self, context):
        """The whole bake, blocking (scripts, the command line, background mode)."""
        window_manager = context.window_manager
        window_manager.progress_begin(0, 100)
        progress = Progress()

        def report_progress(stage, fraction):
            progress(stage, fraction)
            window_manager.progress_update(progress.percent)

        try:
            outcome = self._job(context, report_progress).run()
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except Cancelled:
            self.report({"WARNING"}, "VisiBake: bake cancelled; nothing was changed")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
        return self._finished(context, outcome)

    def invoke(self, context, event):
        """From the panel: the bake runs on a worker thread; the UI shows progress and Esc cancels."""
        if bpy.app.background or context.window is None:
            return self.execute(context)
        self._progress = Progress()
        self._job_state = self._job(context, self._progress)
        try:
            self._job_state.start()
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except Cancelled:
            return {"CANCELLED"}
        self._progress.plan(self._job_state.expected_work())
        if self._job_state.needs_main_thread:
            # The GPU passes need Blender's GL context, which lives on the main thread.
            return self._run_here(context)
        self._error = None
        self._thread = threading.Thread(target=self._compute, name="VisiBake bake", daemon=True)
        self._thread.start()
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(0.1, window=context.window)
        window_manager.progress_begin(0, 100)
        window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _compute(self) -> None:
        try:
            self._job_state.compute()
        except BaseException as error:  # noqa: BLE001  (handed to the main thread in modal())
            self._error = error

    def _run_here(self, context) -> set:
        try:
            return self._finished(context, self._job_state.compute_and_finish())
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
        except Cancelled:
            self.report({"WARNING"}, "VisiBake: bake cancelled; nothing was changed")
        return {"CANCELLED"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._progress.cancel()
        if event.type != "TIMER":
            return {"RUNNING_MODAL"} if event.type == "ESC" else {"PASS_THROUGH"}
        window_manager = context.window_manager
        window_manager.progress_update(self._progress.percent)
        if context.workspace is not None:
            context.workspace.status_text_set(self._progress.status_text())
        if self._thread.is_alive():
            return {"RUNNING_MODAL"}
        window_manager.event_timer_remove(self._timer)
        window_manager.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        if self._error is not None:
            self._job_state.abort()
            if isinstance(self._error, Cancelled):
                self.report({"WARNING"}, "VisiBake: bake cancelled; nothing was changed")
            elif isinstance(self._error, job.BakeInputError):
                self.report({"ERROR"}, str(self._error))
            else:
                self.report({"ERROR"}, f"VisiBake: the bake failed ({type(self._error).__name__}: {self._error}); "
                                       "nothing was changed")
            return {"CANCELLED"}
        try:
            return self._finished(context, self._job_state.finish())
        except job.BakeInputError as error:
            self.report({"ERROR"}, str(error))
        except (KeyError, ReferenceError) as error:
            # The scene changed under the running bake (an object deleted or renamed).
            self.report({"ERROR"}, f"VisiBake: the scene changed during the bake ({error}); bake again")
        return {"CANCELLED"}


class VISIBAKE_OT_bake(_BakeOperator, bpy.types.Operator):
    """Precompute visibility (or reuse the cached visibility) and bake lighting into textures for the selected meshes"""

    bl_idname = "visibake.bake"
    bl_label = "Bake"
    bl_options = {"REGISTER", "UNDO"}


class VISIBAKE_OT_relight(_BakeOperator, bpy.types.Operator):
    """Recompute only the lighting from the cached visibility, after lights, materials or the world changed. \
Refuses if the geometry changed since the last bake"""

    bl_idname = "visibake.relight"
    bl_label = "Relight"
    bl_options = {"REGISTER", "UNDO"}
    relight_only = True


classes = (VISIBAKE_OT_bake, VISIBAKE_OT_relight)
