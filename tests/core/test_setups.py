"""Lighting setups: the JSON format, its error messages, and the sun sweep."""
import math

import numpy as np
import pytest

from core.lights.setups import SetupError, direction_from_angles, parse_setups, parse_sweep, sun_position, sun_sweep
from core.scene import Light, World

SUN = Light("Sun", "SUN", np.ones(3), 3.0, direction=np.array([0.0, 0.0, -1.0]))
LAMP = Light("Lamp", "POINT", np.array([1.0, 0.9, 0.8]), 100.0, position=np.array([1.0, 2.0, 3.0]))
WORLD = World(np.full(3, 0.1))


def test_a_setup_overrides_named_lamps_and_adds_new_ones_without_touching_the_scene():
    setups = parse_setups({"setups": [
        {"name": "a", "lights": [{"object": "Lamp", "strength": 50, "location": [0, 0, 1]},
                                 {"type": "SPOT", "name": "Key", "strength": 500, "spot_size": 30,
                                  "direction": [0, 0, -2]}],
         "world": {"color": [1, 0.5, 0.25], "strength": 2}},
        {"name": "b", "lights": [{"object": "Sun", "elevation": 90}], "others": "keep"},
        {"name": "c"},
    ]}, [SUN, LAMP], WORLD)
    a, b, c = setups
    assert [l.name for l in a.lights] == ["Lamp", "Key"]
    assert a.lights[0].strength == 50 and np.allclose(a.lights[0].position, [0, 0, 1])
    assert np.allclose(a.lights[0].color, LAMP.color)  # what the setup does not say stays
    assert a.lights[1].spot_size == pytest.approx(math.radians(30))
    assert np.allclose(a.lights[1].direction, [0, 0, -1])
    assert np.allclose(a.world.color, [2, 1, 0.5]) and a.world.image is None
    assert [l.name for l in b.lights] == ["Sun", "Lamp"]  # others kept
    assert c.lights[0] is not SUN and [l.name for l in c.lights] == ["Sun", "Lamp"] and c.world is WORLD
    assert LAMP.strength == 100.0 and np.allclose(LAMP.position, [1, 2, 3])  # scene lamps untouched


@pytest.mark.parametrize("data, where", [
    ({}, "setups"),
    ({"setups": []}, "setups"),
    ({"setups": [{"lights": []}]}, "setups[0].name"),
    ({"setups": [{"name": "x"}, {"name": "x"}]}, "setups[1].name"),
    ({"setups": [{"name": "x", "lights": [{"object": "Nope"}]}]}, "setups[0].lights[0].object"),
    ({"setups": [{"name": "x", "lights": [{"type": "LASER"}]}]}, "setups[0].lights[0]"),
    ({"setups": [{"name": "x", "lights": [{"object": "Sun", "strength": -1}]}]}, "setups[0].lights[0].strength"),
    ({"setups": [{"name": "x", "lights": [{"object": "Sun", "color": [1, 2]}]}]}, "setups[0].lights[0].color"),
    ({"setups": [{"name": "x", "lights": [{"object": "Sun", "strength": float("nan")}]}]}, "strength"),
    ({"setups": [{"name": "x", "lights": [{"object": "Sun", "direction": [0, 0, 0]}]}]}, "direction"),
    ({"setups": [{"name": "x", "lights": [{"object": "Sun", "colour": [1, 1, 1]}]}]}, "unknown key colour"),
    ({"setups": [{"name": "x", "world": {"color": [1, 1, 1], "strength": "bright"}}]}, "setups[0].world.strength"),
    ({"setups": [{"name": "x", "others": "maybe"}]}, "setups[0].others"),
])
def test_mistakes_name_their_place(data, where):
    with pytest.raises(SetupError, match=where.replace("[", r"\[").replace("]", r"\]")):
        parse_setups(data, [SUN, LAMP], WORLD)


def test_angles_give_the_direction_light_travels():
    np.testing.assert_allclose(direction_from_angles(90, 0), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(direction_from_angles(0, 90), [-1, 0, 0], atol=1e-12)  # from the east
    np.testing.assert_allclose(direction_from_angles(0, 0), [0, -1, 0], atol=1e-12)  # from the north


def test_sun_position_against_textbook_values():
    # Equator at the equinox: overhead at noon, rising due east at 6:00.
    np.testing.assert_allclose(sun_position(12, 0, 81), [0, 0, 1], atol=1e-3)
    np.testing.assert_allclose(sun_position(6, 0, 81), [1, 0, 0], atol=1e-3)
    # 45 N at midsummer: noon elevation 90 - 45 + 23.44, due south.
    noon = sun_position(12, 45, 172)
    assert math.degrees(math.asin(noon[2])) == pytest.approx(68.44, abs=0.1)
    assert noon[1] < 0 and abs(noon[0]) < 1e-9
    # Morning sun in the east, afternoon in the west, symmetric about noon.
    morning, evening = sun_position(9, 45, 172), sun_position(15, 45, 172)
    assert morning[0] > 0 > evening[0]
    np.testing.assert_allclose(morning * [-1, 1, 1], evening, atol=1e-12)


def test_sun_sweep_moves_the_scene_sun_and_switches_it_off_at_night():
    setups = sun_sweep(0, 12, 5, 50, 172, [SUN, LAMP], WORLD)
    assert [s.name for s in setups] == ["sun_0000", "sun_0300", "sun_0600", "sun_0900", "sun_1200"]
    assert [l.name for l in setups[0].lights] == ["Lamp"]  # midnight: the sun is below the horizon
    for setup in setups[2:]:
        sun = next(l for l in setup.lights if l.name == "Sun")
        assert sun.direction[2] < 0 and sun.strength == SUN.strength
    assert SUN.direction[2] == -1  # the scene's sun is untouched
    with pytest.raises(SetupError, match="--sun"):
        sun_sweep(6, 18, 3, 45, 172, [SUN], WORLD, sun_name="Moon")
    # Without a sun in the scene, a new one of the given strength is made.
    assert next(l for l in sun_sweep(12, 12, 1, 0, 81, [LAMP], WORLD, strength=4.0)[0].lights
                if l.kind == "SUN").strength == 4.0


@pytest.mark.parametrize("text", ["6-18-7", "6:18", "6:30:7", "6:18:0", "a:b:c"])
def test_bad_sweeps_are_refused(text):
    with pytest.raises(SetupError, match="--sun-sweep"):
        parse_sweep(text)
