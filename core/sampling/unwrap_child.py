"""Unwrapping in a child process, so that a long xatlas unwrap can be cancelled, and a hung
one killed (xatlas's task scheduler can miss its shutdown signal and wait forever).

xatlas keeps Python's GIL for the whole unwrap: on this 2-core machine, a 65k-triangle
sphere takes 12.6 s, and no other Python thread runs in that time. On a worker thread it
would still freeze Blender's UI, and nothing can stop it. A child process leaves the UI
free, and a cancel kills it at once. It also keeps a crash inside xatlas out of Blender.

The child is the same Python that runs Blender (``sys.executable``), with the parent's
module path. It loads this package from its folder under a private name, so the
extension's ``__init__`` (which needs bpy) is never imported there.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from ..errors import Cancelled, UnwrapFailed
from .atlas import UnwrapResult, unwrap

_CHILD_PACKAGE = "_visibake_core_child"
_CANNOT_IMPORT = 3  # the child's exit status when it cannot import what it needs
# The child unwraps one request per line of its standard input (a JSON [request, answer] pair
# of paths) until that closes.
_BOOTSTRAP = f"""
import importlib.util, json, os, sys
core_dir = sys.argv[1]
try:
    import numpy, xatlas
    spec = importlib.util.spec_from_file_location(
        {_CHILD_PACKAGE!r}, os.path.join(core_dir, "__init__.py"), submodule_search_locations=[core_dir])
    package = importlib.util.module_from_spec(spec)
    sys.modules[{_CHILD_PACKAGE!r}] = package
    spec.loader.exec_module(package)
    child = importlib.import_module({_CHILD_PACKAGE!r} + ".sampling.unwrap_child")
except ImportError as error:
    print(error, file=sys.stderr)
    sys.exit({_CANNOT_IMPORT})
for line in sys.stdin:
    child.child_main(*json.loads(line))
"""
# How long a worker's child may take to exit once its input is closed before it is killed
# (xatlas can hang in its shutdown; the answers are written by then).
_EXIT_SECONDS = 2.0


# The first wait for an answer, in seconds; each wait after it is twice as long, up to the
# poll interval. A small object unwraps in 25-35 ms, which a fixed 50 ms poll rounded up to
# 50-100 ms (docs/benchmarks.md, "Speed, part 12").
FIRST_POLL_SECONDS = 0.001


def poll_pauses(poll_seconds: float):
    """The pauses (seconds) between looks at the child's answer: FIRST_POLL_SECONDS, doubling
    up to ``poll_seconds``, then ``poll_seconds`` for ever."""
    pause = min(FIRST_POLL_SECONDS, poll_seconds)
    while True:
        yield pause
        pause = min(2.0 * pause, poll_seconds)


class ChildUnavailable(RuntimeError):
    """No child process could unwrap (no usable interpreter): unwrap in this process instead."""


def child_main(request_path: str, answer_path: str) -> None:
    """The child's side: unwrap the request, write the answer (or the error) atomically."""
    with np.load(request_path) as request:
        positions, triangles = request["positions"], request["triangles"]
        resolution = int(request["resolution"])
    temporary = answer_path + ".part.npz"
    try:
        result = unwrap(positions, triangles, resolution)
    except (RuntimeError, ValueError) as error:
        np.savez(temporary, error=np.array(str(error)))
    else:
        np.savez(temporary, corner_uv=result.corner_uv, width=result.width, height=result.height,
                 degenerate=result.degenerate, texels_per_unit=result.texels_per_unit,
                 chart_count=result.chart_count)
    os.replace(temporary, answer_path)


class UnwrapHung(RuntimeError):
    """The unwrap process ran past its deadline (it was killed)."""


class UnwrapWorker:
    """A child process that unwraps one request after another: starting a child (Python and its
    imports) takes about 0.3 s, paid once for all of a scene's unwraps instead of once per
    object. A cancel or a hang kills the child; the next request starts a new one.

    Use as a context manager (``with UnwrapWorker() as worker: worker.unwrap(...)``): leaving it
    ends the child and removes its folder. ``python``: the interpreter (default this one).
    """

    def __init__(self, python: str | None = None):
        self.python = python or sys.executable
        self._child = None
        self._errors = None
        self._folder = None
        self._requests = 0

    def __enter__(self) -> UnwrapWorker:
        self._folder = tempfile.mkdtemp(prefix="visibake-unwrap-")
        return self

    def __exit__(self, *exc) -> None:
        self._stop(graceful=True)
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def _start(self) -> None:
        core_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        paths = [path for path in sys.path if path and os.path.isdir(path)]
        environment = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
        self._errors = open(os.path.join(self._folder, f"stderr-{self._requests}.txt"), "w+b")
        try:
            self._child = subprocess.Popen([self.python, "-c", _BOOTSTRAP, core_dir], stdin=subprocess.PIPE,
                                           stdout=subprocess.DEVNULL, stderr=self._errors, env=environment)
        except OSError as error:
            self._errors.close()
            raise ChildUnavailable(f"cannot start {self.python}: {error}") from None

    def _stop(self, graceful: bool = False) -> None:
        child, self._child = self._child, None
        if child is not None:
            try:
                child.stdin.close()  # the end of its requests: a live child exits
            except OSError:
                pass
            if graceful:
                try:
                    child.wait(_EXIT_SECONDS)
                except subprocess.TimeoutExpired:
                    pass
            if child.poll() is None:
                child.kill()
                child.wait()
        if self._errors is not None:
            self._errors.close()
            self._errors = None

    def _last_error(self, child) -> str:
        self._errors.seek(0)
        message = self._errors.read().decode("utf-8", "replace").strip().splitlines()
        return message[-1] if message else f"exit status {child.returncode}"

    def unwrap(self, positions: np.ndarray, triangles: np.ndarray, resolution: int, cancelled=None,
               poll_seconds: float = 0.05, deadline_seconds: float | None = None) -> UnwrapResult:
        """:func:`unwrap_in_child` in this worker's child (parameters and errors as there)."""
        if self._folder is None:
            raise RuntimeError("UnwrapWorker is used outside its with block")
        self._requests += 1
        request = os.path.join(self._folder, f"request-{self._requests}.npz")
        answer = os.path.join(self._folder, f"answer-{self._requests}.npz")
        np.savez(request, positions=np.asarray(positions, np.float64), triangles=np.asarray(triangles, np.int64),
                 resolution=int(resolution))
        try:
            if self._child is None or self._child.poll() is not None:
                self._stop()
                self._start()
            child = self._child
            try:
                child.stdin.write((json.dumps([request, answer]) + "\n").encode())
                child.stdin.flush()
            except OSError:
                pass  # the child has exited: said below
            started = time.monotonic()
            try:
                for pause in poll_pauses(poll_seconds):
                    if child.poll() is not None or os.path.exists(answer):
                        break
                    if cancelled is not None and cancelled():
                        raise Cancelled()
                    if deadline_seconds is not None and time.monotonic() - started > deadline_seconds:
                        raise UnwrapHung(f"the unwrap process ran past its {deadline_seconds:.0f} s")
                    time.sleep(pause)
            except BaseException:
                self._stop()
                raise
            if not os.path.exists(answer):
                child.wait()
                last = self._last_error(child)
                self._stop()
                if child.returncode == _CANNOT_IMPORT:
                    raise ChildUnavailable(f"the unwrap process cannot import what it needs: {last}")
                raise RuntimeError(f"the unwrap process failed: {last}")
            with np.load(answer) as data:
                if "error" in data:
                    raise UnwrapFailed(str(data["error"]))
                return UnwrapResult(corner_uv=data["corner_uv"], width=int(data["width"]),
                                    height=int(data["height"]), degenerate=data["degenerate"],
                                    texels_per_unit=float(data["texels_per_unit"]),
                                    chart_count=int(data["chart_count"]))
        finally:
            for path in (request, answer):
                if os.path.exists(path):
                    os.remove(path)


def unwrap_in_child(positions: np.ndarray, triangles: np.ndarray, resolution: int, cancelled=None,
                    poll_seconds: float = 0.05, python: str | None = None,
                    deadline_seconds: float | None = None, worker: UnwrapWorker | None = None) -> UnwrapResult:
    """:func:`core.sampling.atlas.unwrap` in a child process; the same result, bit for bit.

    ``cancelled`` () -> bool is asked at least every ``poll_seconds`` (more often at first:
    :func:`poll_pauses`); when it says yes the child
    is killed and :class:`core.errors.Cancelled` raised. Raises ``ValueError`` where
    ``unwrap`` would, ``RuntimeError`` if the child dies (a crash in xatlas),
    :class:`UnwrapHung` if it runs past ``deadline_seconds`` (killed), and
    :class:`ChildUnavailable` if no child can run the unwrap at all. A child whose answer is
    written is done, even if it has not exited yet.

    ``worker``: an open :class:`UnwrapWorker` whose child runs it (``python`` is then the
    worker's); without one, a child is started for this unwrap alone.
    """
    if worker is not None:
        return worker.unwrap(positions, triangles, resolution, cancelled, poll_seconds, deadline_seconds)
    with UnwrapWorker(python) as own:
        return own.unwrap(positions, triangles, resolution, cancelled, poll_seconds, deadline_seconds)
