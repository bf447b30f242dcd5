"""The modal bake's steps driver: a plain object the Bake operator ticks from a timer
(and the tests tick by hand), running :class:`job.BakeJob`'s long steps on a worker
thread so that Blender's UI stays live."""
from __future__ import annotations

import threading

from ...core import kernels
from ...core.errors import Cancelled
from ...core.pipeline.progress import Progress


class ModalBake:
    """The panel's bake as :class:`job.BakeJob`'s steps, advanced one timer tick at a time.

    Main-thread steps run inside :meth:`tick`; each long step runs on a worker thread
    that ``tick`` looks at without waiting, so Blender's UI stays live. Unwraps run in
    child processes, because xatlas keeps the GIL for the whole unwrap. A cancel is
    honoured between steps, and inside a worker step through the progress callback
    (every batch of rays or directions; a child unwrap is killed at once).
    """

    def __init__(self, bake_job, progress: Progress):
        """``bake_job``: a :class:`job.BakeJob`, or any job with ``modal_steps()``, ``abort()``
        and ``needs_main_thread``."""
        self.job, self.progress = bake_job, progress
        if hasattr(bake_job, "modal_steps"):  # a job that names its own steps (volume_job.VolumeJob)
            self.steps = bake_job.modal_steps()
        else:
            self.steps = self._bake_steps(bake_job)
        self.next_step = 0
        self.outcome = None
        self.error = None
        self.done = False
        self._thread = None
        self._thread_error = None

    @staticmethod
    def _bake_steps(bake_job) -> list:
        if bake_job.cluster is not None:
            # The cluster holds the table's rows from the trace to the last gather: one step (CPU only).
            compute = [("visibility and lighting", bake_job.compute, True)]
        else:
            # None: a worker unless the GPU needs main. The chosen steps do nothing without a Target Error.
            compute = [("visibility", bake_job.compute_visibility, True),
                       ("lighting", bake_job.compute_lighting, None),
                       ("visibility at the chosen directions", bake_job.compute_chosen_visibility, True),
                       ("lighting at the chosen directions", bake_job.compute_chosen_lighting, None)]
        return [("plan", bake_job.plan, False),
                ("unwrap", lambda: bake_job.unwrap(in_child=True), True),
                ("extract", bake_job.extract, False),
                *compute,
                ("finish", bake_job.finish, False)]

    def tick(self) -> bool:
        """Advance the bake as far as it can go without waiting; True once it has ended.

        Then either :attr:`outcome` (a :class:`job.JobResult`) or :attr:`error` is set,
        and after an error the scene is as it was before the bake.
        """
        while not self.done:
            if self._thread is not None:
                if self._thread.is_alive():
                    return False
                self._thread = None
                if self._thread_error is not None:
                    return self._end(self._thread_error)
            if self.progress.cancelled:
                return self._end(Cancelled())
            name, step, on_worker = self.steps[self.next_step]
            self.next_step += 1
            if on_worker is None:
                on_worker = not self.job.needs_main_thread
            if on_worker:
                self._thread = threading.Thread(target=self._run_on_worker, args=(step,),
                                                name=f"VisiBake {name}", daemon=True)
                self._thread.start()
                continue
            try:
                with kernels.blas_on_one_thread():
                    result = step()
            except BaseException as error:  # noqa: BLE001  (reported by the operator)
                return self._end(error)
            if name == "plan":
                self.progress.plan(self.job.expected_work())
            if name == "finish":
                self.outcome, self.done = result, True
        return True

    def _run_on_worker(self, step) -> None:
        try:
            with kernels.blas_on_one_thread():
                step()
        except BaseException as error:  # noqa: BLE001  (handed to the main thread in tick())
            self._thread_error = error

    def _end(self, error: BaseException) -> bool:
        self.error, self.done = error, True
        self.job.abort()
        return True


class SteppedJob:
    """A job that names its own steps (``modal_steps()``: (name, step, on a worker thread)
    triples, the last one returning the outcome) and can take back what it did (``abort()``):
    ModalBake advances it a tick at a time; :meth:`run` does it all at once."""

    def expected_work(self) -> dict:
        return {}

    def run(self):
        """Every step in turn (the command line, scripts); an error or a cancel aborts first."""
        try:
            *steps, (_, finish, _) = self.modal_steps()
            with kernels.blas_on_one_thread():
                for _, step, _ in steps:
                    step()
                return finish()
        except BaseException:
            self.abort()
            raise
