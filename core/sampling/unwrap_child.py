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

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from ..errors import Cancelled, UnwrapFailed
from .atlas import UnwrapResult, unwrap

_CHILD_PACKAGE = "_visibake_core_child"
_CANNOT_IMPORT = 3  # the child's exit status when it cannot import what it needs
_BOOTSTRAP = f"""
import importlib.util, os, sys
core_dir, request, answer = sys.argv[1:4]
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
child.child_main(request, answer)
"""


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


def unwrap_in_child(positions: np.ndarray, triangles: np.ndarray, resolution: int, cancelled=None,
                    poll_seconds: float = 0.05, python: str | None = None,
                    deadline_seconds: float | None = None) -> UnwrapResult:
    """:func:`core.sampling.atlas.unwrap` in a child process; the same result, bit for bit.

    ``cancelled`` () -> bool is asked every ``poll_seconds``; when it says yes the child
    is killed and :class:`core.errors.Cancelled` raised. Raises ``ValueError`` where
    ``unwrap`` would, ``RuntimeError`` if the child dies (a crash in xatlas),
    :class:`UnwrapHung` if it runs past ``deadline_seconds`` (killed), and
    :class:`ChildUnavailable` if no child can run the unwrap at all. A child whose answer is
    written is done, even if it has not exited yet.
    """
    core_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    paths = [path for path in sys.path if path and os.path.isdir(path)]
    environment = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
    with tempfile.TemporaryDirectory(prefix="visibake-unwrap-") as folder:
        request, answer = os.path.join(folder, "request.npz"), os.path.join(folder, "answer.npz")
        np.savez(request, positions=np.asarray(positions, np.float64), triangles=np.asarray(triangles, np.int64),
                 resolution=int(resolution))
        with open(os.path.join(folder, "stderr.txt"), "w+b") as errors:
            try:
                child = subprocess.Popen([python or sys.executable, "-c", _BOOTSTRAP, core_dir, request, answer],
                                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=errors,
                                         env=environment)
            except OSError as error:
                raise ChildUnavailable(f"cannot start {python or sys.executable}: {error}") from None
            started = time.monotonic()
            try:
                while child.poll() is None and not os.path.exists(answer):
                    if cancelled is not None and cancelled():
                        raise Cancelled()
                    if deadline_seconds is not None and time.monotonic() - started > deadline_seconds:
                        raise UnwrapHung(f"the unwrap process ran past its {deadline_seconds:.0f} s")
                    time.sleep(poll_seconds)
            finally:
                if child.poll() is None:
                    child.kill()
                    child.wait()
            errors.seek(0)
            message = errors.read().decode("utf-8", "replace").strip().splitlines()
        last = message[-1] if message else f"exit status {child.returncode}"
        if child.returncode == _CANNOT_IMPORT:
            raise ChildUnavailable(f"the unwrap process cannot import what it needs: {last}")
        if not os.path.exists(answer):
            raise RuntimeError(f"the unwrap process failed: {last}")
        with np.load(answer) as data:
            if "error" in data:
                raise UnwrapFailed(str(data["error"]))
            return UnwrapResult(corner_uv=data["corner_uv"], width=int(data["width"]), height=int(data["height"]),
                                degenerate=data["degenerate"], texels_per_unit=float(data["texels_per_unit"]),
                                chart_count=int(data["chart_count"]))
