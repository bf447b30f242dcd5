"""The user's errors are BakeRefused (exit status 2 on the command line); a bug is not.

Each check provokes the error the way a user would reach it and checks its class, so
that a refusal cannot silently turn into a traceback with exit status 1, nor a bug
into "bad input".
"""
import numpy as np
import pytest

from core import errors
from core.errors import BakeRefused, OutputRefused, SetupError, UnwrapFailed
from core.lights.setups import parse_sweep
from core.outputs.images import write_exr
from core.pipeline.relight import bake
from core.sampling.atlas import unwrap
from core.scene import Light, Scene
from core.settings import BakeSettings
from core_scenes import quad_mesh


def test_every_refusal_is_a_bake_refused_and_cancel_is_not():
    refusals = [errors.LayoutError, errors.UnwrapFailed, errors.OutputRefused, errors.DeviceError, errors.SetupError]
    assert all(issubclass(kind, BakeRefused) for kind in refusals)
    assert not issubclass(errors.Cancelled, BakeRefused)


def test_a_mesh_xatlas_cannot_use_is_refused_as_an_unwrap_failure():
    positions = np.zeros((3, 3))  # all corners in one point: no area
    with pytest.raises(UnwrapFailed, match="finite, non-zero area"):
        unwrap(positions, np.array([[0, 1, 2]], np.int32), 64)


def test_non_finite_results_are_refused_as_an_output_error(tmp_path):
    image = np.zeros((2, 2, 4), np.float32)
    image[0, 0, 0] = np.nan
    with pytest.raises(OutputRefused, match="non-finite"):
        write_exr(str(tmp_path / "x.exr"), image)
    assert not (tmp_path / "x.exr").exists()


def test_a_bad_sweep_is_refused_as_a_setup_error():
    with pytest.raises(SetupError, match="--sun-sweep"):
        parse_sweep("6-18")


def test_an_unusable_lamp_refuses_the_bake():
    scene = Scene([quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=4)],
                  [Light("Sun", "SUN", np.ones(3), float("inf"))])
    with pytest.raises(BakeRefused, match="not a usable number"):
        bake(scene, BakeSettings(directions=8, bounces=0))


def test_a_bug_is_not_a_refusal():
    """A numpy error from inconsistent arrays (a bug, not the user's input) stays what it is."""
    mesh = quad_mesh("Floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], resolution=4)
    mesh.corner_normals = mesh.corner_normals[:1]  # fewer corner normals than triangles
    with pytest.raises(Exception) as raised:
        bake(Scene([mesh], []), BakeSettings(directions=8, bounces=0))
    assert not isinstance(raised.value, BakeRefused), raised.value
