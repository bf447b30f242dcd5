"""The emitters' exact light at close range (core.lights.emitters.triangle_irradiance)."""
import numpy as np
import pytest

from core.lights.emitters import EmissiveTriangles, near_triangles, triangle_irradiance


class ClearScene:
    """A ray scene with nothing in it."""

    def occluded(self, origins, directions, distances=None):
        return np.zeros(len(origins), bool)


class BlockedScene:
    """A ray scene where every ray is blocked."""

    def occluded(self, origins, directions, distances=None):
        return np.ones(len(origins), bool)


def _square(half: float, height: float, radiance=(1.0, 1.0, 1.0), index: int = 0) -> EmissiveTriangles:
    """A square of side 2 * ``half`` at z = ``height`` centred on the z axis, emitting downwards."""
    a, b, c, d = (-half, -half, height), (half, -half, height), (half, half, height), (-half, half, height)
    return EmissiveTriangles(np.array([[a, b, c], [a, c, d]], float), np.array([[0.0, 0.0, -1.0]] * 2),
                             np.array([radiance] * 2, float), np.full(2, index, np.int64))


def _at_origin(triangles, normal=(0.0, 0.0, 1.0), scene=None):
    position = np.zeros((1, 3))
    return triangle_irradiance(triangles, position, np.array([normal], float), position, scene or ClearScene())[0]


def test_a_square_above_gives_its_form_factor():
    # A 2 x 2 m square 1 m above: four corner rectangles 1 x 1 at 1 m, 0.13853 each (Howell's catalogue).
    assert _at_origin(_square(1.0, 1.0))[0] == pytest.approx(np.pi * 4 * 0.138528, rel=1e-4)
    # Unbounded, it is the whole hemisphere: pi L.
    assert _at_origin(_square(1e4, 1.0))[0] == pytest.approx(np.pi, rel=1e-6)
    # Small and far, L A cos cos / d^2.
    assert _at_origin(_square(0.005, 2.0))[0] == pytest.approx(1e-4 / 4.0, rel=1e-4)


def test_only_the_part_above_the_horizon_lights():
    # A receiver facing +x under an unbounded ceiling sees half of it: pi L / 2.
    assert _at_origin(_square(1e4, 1.0), normal=(1.0, 0.0, 0.0))[0] == pytest.approx(np.pi / 2, rel=1e-3)
    # An emitter below the receiver's horizon, or seen from its back, gives nothing.
    assert np.all(_at_origin(_square(1.0, -1.0)) == 0.0)
    assert np.all(_at_origin(_square(1.0, 1.0), normal=(0.0, 0.0, -1.0)) == 0.0)
    behind = _square(1.0, 1.0)
    behind.normal = -behind.normal  # emitting upwards, away from the receiver
    assert np.all(_at_origin(behind) == 0.0)


def test_colour_and_shadow_are_per_triangle():
    lit = _at_origin(_square(1.0, 1.0, radiance=(2.0, 1.0, 0.0)))
    assert lit[0] == pytest.approx(2 * lit[1]) and lit[2] == 0.0
    assert np.all(_at_origin(_square(1.0, 1.0), scene=BlockedScene()) == 0.0)


def test_near_triangles_measures_from_the_bounding_box():
    strip = _square(0.5, 3.0)
    positions = np.array([[0.0, 0.0, 2.9], [0.0, 0.0, 2.0], [0.7, 0.0, 3.0]])
    assert near_triangles(strip, positions, np.full(3, 0.25)).tolist() == [True, False, True]
