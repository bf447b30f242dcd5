"""Bake and Relight: run :func:`job.run_bake` on the selected (or all) meshes."""
import json

import bpy

from ..core.errors import BakeRefused, Cancelled
from ..core.outputs import summary as report_texts
from ..core.pipeline.progress import Progress
from .adapter import cache_status, job
from .adapter.modal import ModalBake


def summary(report: dict) -> str:
    """The operator's one-line report of a bake (core.outputs.summary.summary_line)."""
    return report_texts.summary_line(report)


def failure_message(error: BaseException) -> tuple[str, str]:
    """(report level, plain words) for a bake that ended with ``error``."""
    if isinstance(error, Cancelled):
        return "WARNING", "VisiBake: bake cancelled; nothing was changed"
    if isinstance(error, BakeRefused):
        return "ERROR", str(error)
    if isinstance(error, (KeyError, ReferenceError)):
        # An object deleted or renamed under the bake (by a script: the UI is held).
        return "ERROR", f"VisiBake: the scene changed during the bake ({error}); nothing was changed, bake again"
    return "ERROR", (f"VisiBake: the bake failed ({type(error).__name__}: {error}); nothing was changed. "
                     "Please report this with the file and the console output")


# Events a running bake lets through: view navigation and timers. Everything else is
# held, so the scene cannot be edited (or undone) under the bake; Esc cancels.
_NAVIGATION_EVENTS = frozenset({
    "MOUSEMOVE", "INBETWEEN_MOUSEMOVE", "MIDDLEMOUSE", "WHEELUPMOUSE", "WHEELDOWNMOUSE", "WHEELINMOUSE",
    "WHEELOUTMOUSE", "TRACKPADPAN", "TRACKPADZOOM", "MOUSEROTATE", "MOUSESMARTZOOM", "WINDOW_DEACTIVATE", "NONE",
    "NUMPAD_0", "NUMPAD_1", "NUMPAD_2", "NUMPAD_3", "NUMPAD_4", "NUMPAD_5", "NUMPAD_6", "NUMPAD_7", "NUMPAD_8",
    "NUMPAD_9", "NUMPAD_PERIOD", "NUMPAD_PLUS", "NUMPAD_MINUS"})


def event_action(event_type: str, value: str) -> str:
    """What the running bake does with an event: 'cancel', 'tick', 'pass' or 'hold'."""
    if event_type == "ESC":
        return "cancel" if value == "PRESS" else "hold"
    if event_type.startswith("TIMER"):
        return "tick" if event_type == "TIMER" else "pass"
    if event_type in _NAVIGATION_EVENTS or event_type.startswith("NDOF_"):
        return "pass"
    return "hold"


class _BakeOperator:
    relight_only = False

    def _job(self, context, progress) -> "job.BakeJob":
        props = context.scene.visibake
        return job.BakeJob(context, job.output_objects(context, props),
                           bpy.path.abspath(props.output_dir) or None, False, progress,
                           relight_only=self.relight_only, keep_preparation=True,
                           cluster=None if self.relight_only else job.preferred_cluster(context))

    def _finished(self, context, outcome) -> set:
        context.scene["visibake_last_report"] = summary(outcome.report)
        context.scene["visibake_report"] = json.dumps(outcome.report, default=float)
        cache_status.remember_bake(context.scene, context.evaluated_depsgraph_get(), outcome.report)
        for warning in outcome.report["warnings"]:
            self.report({"WARNING"}, warning)
        self.report({"INFO"}, summary(outcome.report))
        return {"FINISHED"}

    def _failed(self, error: BaseException) -> set:
        level, message = failure_message(error)
        self.report({level}, message)
        return {"CANCELLED"}

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
        except (BakeRefused, Cancelled) as error:
            return self._failed(error)
        finally:
            window_manager.progress_end()
        return self._finished(context, outcome)

    def invoke(self, context, event):
        """From the panel: the bake runs beside the UI, which shows progress; Esc cancels."""
        if bpy.app.background or context.window is None:
            return self.execute(context)
        progress = Progress()
        self._bake = ModalBake(self._job(context, progress), progress)
        if self._bake.tick():  # ended at once: bad input, or nothing left to wait for
            return self._ended(context)
        window_manager = context.window_manager
        self._timer = window_manager.event_timer_add(0.1, window=context.window)
        self._area = context.area  # its header shows the stage
        window_manager.progress_begin(0, 100)
        window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _show(self, context, text) -> None:
        """``text`` in the status bar and the header of the area the bake started from; None clears."""
        if context.workspace is not None:
            context.workspace.status_text_set(text)
        try:
            if self._area is not None:
                self._area.header_text_set(text)
        except ReferenceError:  # the area was closed
            self._area = None

    def modal(self, context, event):
        action = event_action(event.type, event.value)
        if action == "cancel":
            self._bake.progress.cancel()
        if action != "tick":
            return {"PASS_THROUGH"} if action == "pass" else {"RUNNING_MODAL"}
        window_manager = context.window_manager
        try:
            window_manager.progress_update(self._bake.progress.percent)  # the cursor shows it
            self._show(context, self._bake.progress.status_text())
            if not self._bake.tick():
                return {"PASS_THROUGH"}
        except BaseException as error:  # noqa: BLE001  (a fault of ours: end the bake, never leave the UI held)
            self._bake.error = self._bake.error or error
            self._bake.job.abort()
        window_manager.event_timer_remove(self._timer)
        window_manager.progress_end()
        self._show(context, None)
        return self._ended(context)

    def _ended(self, context) -> set:
        if self._bake.error is not None:
            return self._failed(self._bake.error)
        return self._finished(context, self._bake.outcome)


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
