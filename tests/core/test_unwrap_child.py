"""The unwrap in a child process: the same result as in this process, and a cancel that stops it."""
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from core.errors import Cancelled
from core.sampling import unwrap_child
from core.sampling.atlas import unwrap
from core.sampling.unwrap_child import ChildUnavailable, unwrap_in_child


def _sphere(segments: int, rings: int):
    theta = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    positions = np.concatenate([np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3),
                                [[0, 0, 1], [0, 0, -1]]])
    triangles = []
    for r in range(rings - 2):
        for s in range(segments):
            a, b = r * segments + s, r * segments + (s + 1) % segments
            c, d = a + segments, b + segments
            triangles += [(a, c, b), (b, c, d)]
    top, bottom, last = len(positions) - 2, len(positions) - 1, (rings - 2) * segments
    for s in range(segments):
        triangles += [(top, s, (s + 1) % segments), (bottom, last + (s + 1) % segments, last + s)]
    return positions, np.array(triangles)


def _record_children(monkeypatch, tmp_path) -> list:
    """The unwrap module's child processes, kept for the checks (filled as they start); its
    folders go in ``tmp_path``."""
    children = []

    def recording_popen(*args, **kwargs):
        children.append(subprocess.Popen(*args, **kwargs))
        return children[-1]

    monkeypatch.setattr(unwrap_child, "subprocess", SimpleNamespace(**{**vars(subprocess), "Popen": recording_popen}))
    monkeypatch.setattr(unwrap_child.tempfile, "tempdir", str(tmp_path))
    return children


def test_the_child_gives_the_in_process_unwrap_bit_for_bit():
    positions, triangles = _sphere(24, 12)
    here = unwrap(positions, triangles, 64)
    child = unwrap_in_child(positions, triangles, 64)
    np.testing.assert_array_equal(here.corner_uv, child.corner_uv)
    np.testing.assert_array_equal(here.degenerate, child.degenerate)
    assert (here.width, here.height, here.chart_count) == (child.width, child.height, child.chart_count)
    assert here.texels_per_unit == child.texels_per_unit


def test_the_child_s_errors_come_back_as_the_same_exceptions():
    positions, triangles = _sphere(24, 12)
    with pytest.raises(ValueError) as here:
        unwrap(positions, triangles, 4)
    with pytest.raises(ValueError) as there:
        unwrap_in_child(positions, triangles, 4)
    assert str(there.value) == str(here.value) and "too small" in str(here.value)
    with pytest.raises(RuntimeError, match="the unwrap process failed"):
        unwrap_in_child(positions, triangles, 64, python="/bin/false")


def test_without_a_usable_interpreter_the_child_says_so(tmp_path):
    positions, triangles = _sphere(8, 4)
    with pytest.raises(ChildUnavailable, match="cannot start"):
        unwrap_in_child(positions, triangles, 64, python="/nonexistent/python")
    # An interpreter without xatlas: this one, with xatlas blocked before the child's code runs.
    without_xatlas = tmp_path / "python-without-xatlas"
    prelude = ("import sys; sys.modules['xatlas'] = None; code = sys.argv[2]; "
               "sys.argv = sys.argv[:1] + sys.argv[3:]; exec(code)")
    without_xatlas.write_text(f'#!/bin/sh\nexec "{sys.executable}" -c "{prelude}" "$@"\n')
    without_xatlas.chmod(0o755)
    with pytest.raises(ChildUnavailable, match="cannot import"):
        unwrap_in_child(positions, triangles, 64, python=str(without_xatlas))


def test_a_cancel_kills_the_child_mid_unwrap_and_leaves_nothing(monkeypatch, tmp_path):
    positions, triangles = _sphere(256, 128)  # ~65k triangles: about 12 s of xatlas on 2 cores
    children = _record_children(monkeypatch, tmp_path)
    asked = []

    def cancelled():
        # Asked only while the child runs; cancel once it has had a few polls to get going.
        assert children and children[0].poll() is None
        asked.append(True)
        return len(asked) >= 3

    with pytest.raises(Cancelled):
        unwrap_in_child(positions, triangles, 1024, cancelled=cancelled, poll_seconds=0.05)
    assert len(asked) == 3 and len(children) == 1
    # Killed (not finished, not left running): SIGKILL is its exit status, and the
    # folder with its request (and any answer) is gone.
    assert children[0].returncode == -signal.SIGKILL
    assert list(tmp_path.iterdir()) == []


def test_a_child_past_its_deadline_is_killed_and_says_so():
    from core.sampling.unwrap_child import UnwrapHung

    positions, triangles = _sphere(24, 12)
    started = time.monotonic()
    with pytest.raises(UnwrapHung, match="ran past"):
        unwrap_in_child(positions, triangles, 64, deadline_seconds=0.01)
    assert time.monotonic() - started < 30  # killed, not waited for


def test_one_worker_unwraps_many_meshes_in_one_child_and_starts_another_after_a_kill(monkeypatch, tmp_path):
    from core.sampling.unwrap_child import UnwrapHung, UnwrapWorker

    children = _record_children(monkeypatch, tmp_path)
    meshes = [_sphere(8 + 4 * i, 4 + 2 * i) for i in range(4)]
    with UnwrapWorker() as worker:
        for positions, triangles in meshes[:3]:
            ours = unwrap_in_child(positions, triangles, 64, worker=worker)
            np.testing.assert_array_equal(ours.corner_uv, unwrap(positions, triangles, 64).corner_uv)
        assert len(children) == 1 and children[0].poll() is None  # one child for all three
        with pytest.raises(ValueError, match="too small"):
            unwrap_in_child(*meshes[0], 4, worker=worker)  # an error answer keeps the child
        assert len(children) == 1
        with pytest.raises(UnwrapHung):
            unwrap_in_child(*meshes[3], 64, worker=worker, deadline_seconds=0.0)
        assert children[0].returncode == -signal.SIGKILL
        again = unwrap_in_child(*meshes[3], 64, worker=worker)  # a new child
        np.testing.assert_array_equal(again.corner_uv, unwrap(*meshes[3], 64).corner_uv)
        assert len(children) == 2
    assert children[1].poll() is not None  # ended with the worker
    assert list(tmp_path.iterdir()) == []


def test_the_wait_for_an_answer_starts_short_and_doubles_up_to_the_poll_interval(monkeypatch):
    pauses = unwrap_child.poll_pauses(0.05)
    assert [next(pauses) for _ in range(8)] == [0.001, 0.002, 0.004, 0.008, 0.016, 0.032, 0.05, 0.05]
    shorter = unwrap_child.poll_pauses(0.0005)
    assert [next(shorter) for _ in range(3)] == [0.0005] * 3
    # A small unwrap is picked up as soon as it is written, not a whole poll interval later.
    slept = []
    real_sleep = time.sleep

    def recorded_sleep(seconds):
        slept.append(seconds)
        real_sleep(seconds)
    monkeypatch.setattr(unwrap_child.time, "sleep", recorded_sleep)
    positions, triangles = _sphere(8, 4)
    ours = unwrap_in_child(positions, triangles, 64, poll_seconds=60.0)
    np.testing.assert_array_equal(ours.corner_uv, unwrap(positions, triangles, 64).corner_uv)
    assert slept and slept[0] == unwrap_child.FIRST_POLL_SECONDS and max(slept) < 60.0
