import numpy as np
import pytest

from core.lights.lamps import light_contributions, spot_mask
from core.scene import Light

UP = np.array([[0.0, 0.0, 1.0]])


def _single(light, position=None, normal=UP, samples=8):
    position = np.zeros((1, 3)) if position is None else position
    parts = light_contributions(light, position, normal, samples)
    return sum(p.irradiance for p in parts)[0]


def test_sun_is_irradiance_times_cosine():
    angle = np.radians(60)
    sun = Light("sun", "SUN", np.ones(3), 3.0, direction=np.array([np.sin(angle), 0.0, -np.cos(angle)]))
    np.testing.assert_allclose(_single(sun), 3.0 * np.cos(angle))


def test_point_is_inverse_square_with_cosine():
    point = Light("p", "POINT", np.array([1.0, 0.5, 0.25]), 1000.0, position=np.array([0.0, 0.0, 2.0]))
    np.testing.assert_allclose(_single(point), 1000 / (4 * np.pi * 4) * np.array([1.0, 0.5, 0.25]))
    off = np.array([[1.5, 0.0, 0.0]])
    d2 = 1.5 ** 2 + 4
    np.testing.assert_allclose(_single(point, off)[0], 1000 / (4 * np.pi * d2) * 2 / np.sqrt(d2))


def test_spot_is_a_point_inside_the_cone_and_dark_outside():
    spot = Light("s", "SPOT", np.ones(3), 1000.0, position=np.array([0.0, 0.0, 2.0]),
                 direction=np.array([0.0, 0.0, -1.0]), spot_size=np.radians(60), spot_blend=0.0)
    np.testing.assert_allclose(_single(spot), 1000 / (4 * np.pi * 4))
    assert _single(spot, np.array([[3.0, 0.0, 0.0]]))[0] == 0.0
    blended = Light("s", "SPOT", np.ones(3), 1.0, direction=np.array([0.0, 0.0, -1.0]),
                    spot_size=np.radians(60), spot_blend=0.5)
    inner = spot_mask(blended, np.array([[0.0, 0.0, -1.0]]))
    edge = spot_mask(blended, np.array([[np.sin(np.radians(29.9)), 0.0, -np.cos(np.radians(29.9))]]))
    assert inner[0] == 1.0 and 0.0 <= edge[0] < 0.05


@pytest.mark.parametrize("shape", ["SQUARE", "RECTANGLE", "DISK", "ELLIPSE"])
def test_area_light_far_away_matches_a_point_of_equal_flux(shape):
    # Radiance P/(pi A) from a small one-sided emitter: far away it delivers
    # E = L A cos cos / d^2 = P/(pi d^2) at normal incidence.
    area = Light("a", "AREA", np.ones(3), 100.0, position=np.array([0.0, 0.0, 50.0]),
                 direction=np.array([0.0, 0.0, -1.0]), area_shape=shape, size_x=0.5, size_y=0.3)
    assert _single(area)[0] == pytest.approx(100 / (np.pi * 2500), rel=1e-3)


def test_lights_behind_the_surface_give_nothing():
    below = Light("p", "POINT", np.ones(3), 100.0, position=np.array([0.0, 0.0, -1.0]))
    assert np.all(_single(below) == 0)
    bad = Light("p", "POINT", np.ones(3), np.inf)
    with pytest.raises(ValueError):
        _single(bad)
    negative = Light("p", "POINT", np.ones(3), -5.0, position=np.array([0.0, 0.0, 1.0]))
    assert np.all(_single(negative) == 0)
