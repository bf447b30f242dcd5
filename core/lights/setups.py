"""Lighting setups for batch relighting: a JSON file of lights and world, or a sun sweep.

One visibility bake serves every setup; each setup only changes lamps and world.

JSON format (every key but ``setups`` and ``name`` optional)::

    {"setups": [
      {"name": "evening",
       "lights": [
         {"object": "Sun", "strength": 2.0, "color": [1.0, 0.6, 0.4], "elevation": 10, "azimuth": 250},
         {"type": "POINT", "name": "Fill", "strength": 100, "location": [0, 0, 2]}
       ],
       "others": "off",
       "world": {"color": [0.05, 0.07, 0.1], "strength": 1.0}}
    ]}

A light entry either names a lamp of the scene (``object``) and overrides some of its
values, or defines a new lamp (``type``: SUN, POINT, SPOT or AREA). Units are
Blender's lamp settings: ``strength`` is a sun's Strength (W/m^2) or a lamp's Power (W),
before exposure. Directions: ``direction`` (where the light travels, world space) or
``elevation`` and ``azimuth`` in degrees (where it comes from; azimuth clockwise from
+Y, the Sun Position add-on's default north, towards +X, east). ``spot_size`` is in
degrees. ``others``: "off" (default) switches off the scene's lamps the setup does not
name; "keep" keeps them. Without ``lights`` the scene's lamps are used as they are;
without ``world`` the scene's world.
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass

import numpy as np

from ..errors import SetupError
from ..scene import AREA_SHAPES, LIGHT_KINDS, Light, World


@dataclass
class Setup:
    name: str
    lights: list
    world: World


_LIGHT_KEYS = {"object", "type", "name", "strength", "color", "location", "direction", "elevation", "azimuth",
               "spot_size", "spot_blend", "shape", "size", "size_y", "group"}


def _vector(value, where: str, length: int = 3) -> np.ndarray:
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise SetupError(f"{where}: expected {length} numbers, got {value!r}") from None
    if array.shape != (length,) or not np.all(np.isfinite(array)):
        raise SetupError(f"{where}: expected {length} finite numbers, got {value!r}")
    return array


def _number(value, where: str, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SetupError(f"{where}: expected a number, got {value!r}")
    if minimum is not None and value < minimum:
        raise SetupError(f"{where}: must be at least {minimum:g}, got {value!r}")
    return float(value)


def direction_from_angles(elevation_degrees: float, azimuth_degrees: float) -> np.ndarray:
    """The direction light travels when it comes from ``elevation`` above the horizon at ``azimuth``.

    Azimuth is clockwise from +Y (north) towards +X (east). Returns a (3,) unit vector.
    """
    elevation, azimuth = math.radians(elevation_degrees), math.radians(azimuth_degrees)
    towards_light = np.array([math.cos(elevation) * math.sin(azimuth), math.cos(elevation) * math.cos(azimuth),
                              math.sin(elevation)])
    return -towards_light


def _apply(light: Light, entry: dict, where: str) -> Light:
    unknown = set(entry) - _LIGHT_KEYS
    if unknown:
        raise SetupError(f"{where}: unknown key {', '.join(sorted(unknown))} (known: {', '.join(sorted(_LIGHT_KEYS))})")
    if "strength" in entry:
        light.strength = _number(entry["strength"], f"{where}.strength", 0.0)
    if "color" in entry:
        light.color = _vector(entry["color"], f"{where}.color")
        if np.any(light.color < 0):
            raise SetupError(f"{where}.color: must not be negative")
    if "location" in entry:
        light.position = _vector(entry["location"], f"{where}.location")
    if "direction" in entry:
        direction = _vector(entry["direction"], f"{where}.direction")
        length = np.linalg.norm(direction)
        if length == 0:
            raise SetupError(f"{where}.direction: must not be zero")
        light.direction = direction / length
    if "elevation" in entry or "azimuth" in entry:
        if "direction" in entry:
            raise SetupError(f"{where}: give either direction or elevation and azimuth, not both")
        elevation = _number(entry.get("elevation", 90.0), f"{where}.elevation")
        azimuth = _number(entry.get("azimuth", 0.0), f"{where}.azimuth")
        light.direction = direction_from_angles(elevation, azimuth)
    if "spot_size" in entry:
        light.spot_size = math.radians(_number(entry["spot_size"], f"{where}.spot_size", 0.0))
    if "spot_blend" in entry:
        light.spot_blend = _number(entry["spot_blend"], f"{where}.spot_blend", 0.0)
    if "shape" in entry:
        if entry["shape"] not in AREA_SHAPES:
            raise SetupError(f"{where}.shape: one of {', '.join(AREA_SHAPES)}, got {entry['shape']!r}")
        light.area_shape = entry["shape"]
    if "size" in entry:
        light.size_x = _number(entry["size"], f"{where}.size", 0.0)
        if light.area_shape in ("SQUARE", "DISK"):
            light.size_y = light.size_x
    if "size_y" in entry:
        light.size_y = _number(entry["size_y"], f"{where}.size_y", 0.0)
    if "group" in entry:
        light.group = str(entry["group"])
    return light


def _world(entry, base: World, where: str) -> World:
    if entry is None or entry == "scene":
        return base
    if not isinstance(entry, dict) or set(entry) - {"color", "strength"}:
        raise SetupError(f"{where}: expected \"scene\" or {{\"color\": [r, g, b], \"strength\": s}}")
    color = _vector(entry.get("color", [1.0, 1.0, 1.0]), f"{where}.color")
    strength = _number(entry.get("strength", 1.0), f"{where}.strength", 0.0)
    if np.any(color < 0):
        raise SetupError(f"{where}.color: must not be negative")
    return World(color=color * strength, light_group=base.light_group)


def parse_setups(data, scene_lights: list[Light], scene_world: World) -> list[Setup]:
    """Setups from the parsed JSON ``data`` (see the module docstring)."""
    if not isinstance(data, dict) or not isinstance(data.get("setups"), list) or not data["setups"]:
        raise SetupError('expected {"setups": [ ... ]} with at least one setup')
    by_name = {light.name: light for light in scene_lights}
    setups, names = [], set()
    for index, entry in enumerate(data["setups"]):
        where = f"setups[{index}]"
        if not isinstance(entry, dict):
            raise SetupError(f"{where}: expected an object")
        unknown = set(entry) - {"name", "lights", "others", "world"}
        if unknown:
            raise SetupError(f"{where}: unknown key {', '.join(sorted(unknown))}")
        name = entry.get("name")
        if not isinstance(name, str) or not name.strip():
            raise SetupError(f"{where}.name: every setup needs a name (it names its output folder)")
        if name in names:
            raise SetupError(f"{where}.name: {name!r} is used twice")
        names.add(name)
        others = entry.get("others", "off")
        if others not in ("off", "keep"):
            raise SetupError(f"{where}.others: \"off\" or \"keep\", got {others!r}")
        if "lights" not in entry:
            lights = [copy.deepcopy(light) for light in scene_lights]
        else:
            if not isinstance(entry["lights"], list):
                raise SetupError(f"{where}.lights: expected a list")
            lights, named = [], set()
            for number, light_entry in enumerate(entry["lights"]):
                light_where = f"{where}.lights[{number}]"
                if not isinstance(light_entry, dict):
                    raise SetupError(f"{light_where}: expected an object")
                if "object" in light_entry:
                    source = light_entry["object"]
                    if source not in by_name:
                        raise SetupError(f"{light_where}.object: the scene has no lamp named {source!r} "
                                         f"(it has: {', '.join(sorted(by_name)) or 'none'})")
                    light = copy.deepcopy(by_name[source])
                    named.add(source)
                else:
                    kind = light_entry.get("type")
                    if kind not in LIGHT_KINDS:
                        raise SetupError(f"{light_where}: give \"object\" (a scene lamp) or \"type\" "
                                         f"(one of {', '.join(LIGHT_KINDS)})")
                    light = Light(name=str(light_entry.get("name", f"{kind.title()} {number}")), kind=kind,
                                  color=np.ones(3), strength=1000.0 if kind != "SUN" else 1.0)
                lights.append(_apply(light, {k: v for k, v in light_entry.items() if k not in ("object", "type")},
                                     light_where))
            if others == "keep":
                lights += [copy.deepcopy(light) for light in scene_lights if light.name not in named]
        setups.append(Setup(name=name, lights=lights, world=_world(entry.get("world"), scene_world, f"{where}.world")))
    return setups


def load_setups(path: str, scene_lights: list[Light], scene_world: World) -> list[Setup]:
    try:
        with open(path, encoding="utf-8") as handle:
            data = json.load(handle)
    except OSError as error:
        raise SetupError(f"cannot read {path}: {error.strerror or error}") from None
    except json.JSONDecodeError as error:
        raise SetupError(f"{path} is not valid JSON: {error}") from None
    return parse_setups(data, scene_lights, scene_world)


def sun_position(hour: float, latitude_degrees: float, day_of_year: int) -> np.ndarray:
    """Unit vector towards the sun (x east, y north, z up) at local solar time ``hour``.

    A textbook model (declination from the day of the year, hour angle 15 degrees an
    hour, no equation of time or refraction): within about a degree, which is what a
    lighting study needs, not an ephemeris.
    """
    declination = math.radians(23.44) * math.sin(2.0 * math.pi * (284 + day_of_year) / 365.0)
    hour_angle = math.radians(15.0 * (hour - 12.0))
    latitude = math.radians(latitude_degrees)
    east = -math.cos(declination) * math.sin(hour_angle)
    north = (math.cos(latitude) * math.sin(declination)
             - math.sin(latitude) * math.cos(declination) * math.cos(hour_angle))
    up = math.sin(latitude) * math.sin(declination) + math.cos(latitude) * math.cos(declination) * math.cos(hour_angle)
    vector = np.array([east, north, up])
    return vector / np.linalg.norm(vector)


def parse_sweep(text: str) -> tuple[float, float, int]:
    """``START:END:STEPS`` in hours, e.g. ``6:18:7`` (06:00 to 18:00 in 7 steps)."""
    parts = text.split(":")
    try:
        start, end, steps = float(parts[0]), float(parts[1]), int(parts[2])
    except (IndexError, ValueError):
        raise SetupError(f"--sun-sweep: expected START:END:STEPS in hours, e.g. 6:18:7, got {text!r}") from None
    if len(parts) != 3 or steps < 1 or not (0.0 <= start <= 24.0 and 0.0 <= end <= 24.0):
        raise SetupError(f"--sun-sweep: hours in 0..24 and at least one step, got {text!r}")
    if steps > MAX_SWEEP_STEPS:
        # Each step is a setup with a folder of outputs: more than one a minute is never meant.
        raise SetupError(f"--sun-sweep: at most {MAX_SWEEP_STEPS} steps (one a minute), got {steps}")
    return start, end, steps


MAX_SWEEP_STEPS = 24 * 60


def sun_sweep(start: float, end: float, steps: int, latitude: float, day_of_year: int, scene_lights: list[Light],
              scene_world: World, sun_name: str | None = None, strength: float = 3.0) -> list[Setup]:
    """One setup per time of day; the chosen sun follows the sky, other lamps stay.

    The sun is the scene's sun named ``sun_name``, else its first sun, else a new
    white sun of ``strength`` W/m^2. Below the horizon it is switched off.
    """
    if not -90.0 <= latitude <= 90.0:
        raise SetupError(f"--latitude must be in -90..90, got {latitude:g}")
    if not 1 <= day_of_year <= 366:
        raise SetupError(f"--day must be in 1..366, got {day_of_year}")
    suns = [light for light in scene_lights if light.kind == "SUN"]
    if sun_name is not None:
        suns = [light for light in suns if light.name == sun_name]
        if not suns:
            raise SetupError(f"--sun: the scene has no sun lamp named {sun_name!r}")
    base = suns[0] if suns else Light(name="Sun", kind="SUN", color=np.ones(3), strength=strength)
    others = [light for light in scene_lights if light is not base]
    hours = np.linspace(start, end, steps) if steps > 1 else np.array([start])
    setups = []
    for hour in hours:
        towards_sun = sun_position(float(hour), latitude, day_of_year)
        minutes = int(round(hour * 60))
        name = f"sun_{minutes // 60:02d}{minutes % 60:02d}"
        if any(setup.name == name for setup in setups):
            name = f"{name}_{len(setups)}"
        lights = [copy.deepcopy(light) for light in others]
        if towards_sun[2] > 0:
            sun = copy.deepcopy(base)
            sun.direction = -towards_sun
            lights.append(sun)
        setups.append(Setup(name=name, lights=lights, world=scene_world))
    return setups
