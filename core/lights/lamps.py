"""Direct irradiance from lamps, in Cycles' units (see DESIGN.md, verified by tests).

Every lamp is reduced to one or more "virtual points" per sample: the irradiance
it would deliver unshadowed, the unit direction towards it and its distance.
Shadowing is applied by the caller (fractions or exact rays).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import tolerances as tol
from ..errors import BakeRefused
from ..scene import Light


@dataclass
class LightContribution:
    """Unshadowed irradiance of one virtual point of a lamp at every sample.

    irradiance : (K, 3) float64 W/m^2 (RGB)
    to_light : (K, 3) float64 unit vectors
    distance : (K,) float64 (inf for a sun)
    """

    irradiance: np.ndarray
    to_light: np.ndarray
    distance: np.ndarray


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def spot_mask(light: Light, from_light: np.ndarray) -> np.ndarray:
    """Cycles' spot cone: smoothstep of (cos - cos(half angle)) over the blend band."""
    cos_angle = from_light @ np.asarray(light.direction, np.float64)
    cos_half = np.cos(light.spot_size / 2.0)
    band = (1.0 - cos_half) * light.spot_blend
    if band <= 0.0:
        return (cos_angle > cos_half).astype(np.float64)
    return _smoothstep((cos_angle - cos_half) / band)


def _unit_square_grid(n: int) -> np.ndarray:
    """Cell centres of an n x n grid on [-0.5, 0.5]^2, (n*n, 2)."""
    t = (np.arange(n) + 0.5) / n - 0.5
    gx, gy = np.meshgrid(t, t)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def _concentric_disk(square: np.ndarray) -> np.ndarray:
    """Shirley-Chiu map of [-0.5,0.5]^2 to the disk of radius 0.5 (area preserving)."""
    a = 2.0 * square[:, 0]
    b = 2.0 * square[:, 1]
    radius = np.where(np.abs(a) > np.abs(b), a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(np.abs(a) > np.abs(b), (np.pi / 4) * (b / a), (np.pi / 2) - (np.pi / 4) * (a / b))
    phi = np.nan_to_num(phi)
    return 0.5 * np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)


def area_light_points(light: Light, samples_per_side: int) -> tuple[np.ndarray, float]:
    """Points spread evenly over an area lamp and the area each one stands for.

    Returns
    -------
    points : (n, 3) float64 world space
    cell_area : float
    """
    unit = _unit_square_grid(samples_per_side)
    if light.area_shape in ("DISK", "ELLIPSE"):
        unit = _concentric_disk(unit)
        area = np.pi / 4.0 * light.size_x * light.size_y
    else:
        area = light.size_x * light.size_y
    offsets = (unit[:, :1] * light.size_x * np.asarray(light.axis_x, np.float64)
               + unit[:, 1:] * light.size_y * np.asarray(light.axis_y, np.float64))
    return np.asarray(light.position, np.float64) + offsets, area / len(unit)


def surface_to_point(position: np.ndarray, normal: np.ndarray, point: np.ndarray, point_normal: np.ndarray):
    """Geometry between receivers and one small emitting patch facing ``point_normal``.

    Returns
    -------
    to_point : (K, 3) float64 unit vectors from each receiver to the patch
    distance : (K,) float64
    transfer : (K,) float64 cos(receiver) * cos(patch) / distance^2 (0 behind either
        side, or where receiver and patch coincide); times radiance * patch area it is
        the irradiance the patch delivers
    """
    offset = point - position
    distance = np.linalg.norm(offset, axis=1)
    safe = np.maximum(distance, 1e-12)
    to_point = offset / safe[:, None]
    cos_receiver = np.clip(np.einsum("kd,kd->k", normal, to_point), 0.0, None)
    cos_patch = np.clip(-(to_point @ np.asarray(point_normal, np.float64)), 0.0, None)
    transfer = np.where(distance > 1e-12, cos_receiver * cos_patch / (safe * safe), 0.0)
    return to_point, distance, transfer


def light_contributions(light: Light, position: np.ndarray, normal: np.ndarray,
                        area_light_samples: int = 8) -> list[LightContribution]:
    """Unshadowed irradiance of ``light`` at every sample, split into virtual points.

    Parameters
    ----------
    position, normal : (K, 3) float64 sample positions and unit shading normals
    """
    color = np.asarray(light.color, np.float64)[:3]
    strength = max(float(light.strength), 0.0)
    if not np.isfinite(strength):
        raise ValueError(f"light {light.name!r} has a non-finite strength")
    if light.kind == "SUN":
        to_light = np.broadcast_to(-np.asarray(light.direction, np.float64), position.shape).copy()
        cosine = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        return [LightContribution(strength * cosine[:, None] * color, to_light, np.full(len(position), np.inf))]

    if light.kind in ("POINT", "SPOT"):
        offset = np.asarray(light.position, np.float64) - position
        distance = np.linalg.norm(offset, axis=1)
        safe = np.maximum(distance, 1e-12)
        to_light = offset / safe[:, None]
        cosine = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        irradiance = strength / (4.0 * np.pi) * cosine / (safe * safe)
        if light.kind == "SPOT":
            irradiance = irradiance * spot_mask(light, -to_light)
        irradiance = np.where(distance > 1e-12, irradiance, 0.0)
        return [LightContribution(irradiance[:, None] * color, to_light, distance)]

    if light.kind == "AREA":
        points, cell_area = area_light_points(light, area_light_samples)
        total_area = cell_area * len(points)
        radiance = strength / (np.pi * total_area) if total_area > 0 else 0.0
        facing = np.asarray(light.direction, np.float64)
        contributions = []
        for point in points:
            to_light, distance, transfer = surface_to_point(position, normal, point, facing)
            irradiance = radiance * cell_area * transfer
            contributions.append(LightContribution(irradiance[:, None] * color, to_light, distance))
        return contributions

    raise ValueError(f"light {light.name!r}: unsupported kind {light.kind!r}")


def usable_lights(lights, warnings: list[str]):
    """The lamps that can be baked; refuse the bake for strengths no output could hold."""
    usable = []
    for light in lights:
        strength = float(light.strength)
        if not np.isfinite(strength) or abs(strength) > tol.MAX_LIGHT_STRENGTH:
            raise BakeRefused(f"light {light.name!r}: strength {strength:g} is not a usable number; set it to a "
                              f"finite value of at most {tol.MAX_LIGHT_STRENGTH:g}")
        color = np.asarray(light.color, np.float64)
        if not np.all(np.isfinite(color)):
            raise BakeRefused(f"light {light.name!r}: its colour is not finite; set its colour again")
        if strength < 0 or np.any(color < 0):
            warnings.append(f"light {light.name!r}: negative light is not supported (Cycles subtracts it); "
                            "it was left out")
            continue
        if strength == 0 or not np.any(color > 0):
            continue
        usable.append(light)
    return usable


def cycles_strength(kind: str, energy: float, exposure: float = 0.0, normalize: bool = True,
                    area_shape: str = "SQUARE", size: float = 1.0, size_y: float = 1.0,
                    scale: tuple[float, float] = (1.0, 1.0), sun_angle: float = 0.0) -> float:
    """A Blender lamp's ``strength`` in the units of :class:`core.scene.Light` (Cycles').

    energy : the lamp's Power (W) or, for a sun, Strength (W/m^2); exposure : stops
    normalize : Blender 5's "Normalize"; off, a point or spot emits four times its
        normalised intensity, an area lamp radiance P/pi whatever its size (so its power
        grows with its area: size x size_y in the lamp's frame, times ``scale``, the
        object's scale along the lamp's X and Y, and pi/4 for disks and ellipses), and a
        sun of angle ``sun_angle`` (radians) its strength per steradian of its disc.
    Measured against Cycles bakes (tests/blender/test_cycles_bake.py).
    """
    strength = float(energy) * 2.0 ** float(exposure)
    if not normalize:
        if kind in {"POINT", "SPOT"}:
            strength *= 4.0
        elif kind == "AREA":
            area = float(size) * float(size_y)
            area *= float(scale[0] * scale[1]) * (np.pi / 4 if area_shape in {"DISK", "ELLIPSE"} else 1.0)
            strength *= area
        elif kind == "SUN":
            half = float(sun_angle) / 2.0
            strength *= 2.0 * np.pi * (1.0 - np.cos(half)) if half > 0 else 1.0
    return strength
