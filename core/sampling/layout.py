"""Layout policy: how many texels an object's atlas gets, and when mode auto gives an
object vertex tables instead.

Plain values in, plain values out: an object's own resolution and texel density (0:
none of its own), the scene's :class:`core.settings.LayoutSettings`, and world-space
positions and triangles. The Blender side (operators/adapter/layout.py) reads those
from an object and acts on the answers.
"""
from __future__ import annotations

import numpy as np

from ..geometry import triangle_areas
from ..settings import LayoutSettings

# Share of the UV square xatlas typically fills; sizes a texel-density atlas before unwrapping.
TYPICAL_PACKED_UV_AREA = 0.7

# Mode auto leaves the unwrap to vertex tables above this many triangles: xatlas took
# ~2 s at 20k and ~140 s at 180k triangles (growing faster than linearly) on a 2-core
# machine, so 100k triangles keeps an unwrap under about a minute.
UNWRAP_TRIANGLE_BUDGET = 100_000

# "Dense" needs many vertices as well as close ones: a low-poly object at a draft
# resolution (a quad at 1 x 1 texels) has vertices farther apart than a texel's size
# too, but an artist still expects an image for it.
DENSE_MIN_VERTICES = 1024


def unwrap_seconds(triangles: int) -> float:
    """Rough time of one unwrap on the machine of UNWRAP_TRIANGLE_BUDGET's measurements,
    for the time-left estimate: a power law through them (exponent ln 70 / ln 9 = 1.93;
    it predicts 19 s at 65k triangles, where 18-21 s was measured), plus starting the
    child process."""
    return 2.0 * (triangles / 20_000) ** 1.93 + 0.2


def surface_area(positions: np.ndarray, triangles: np.ndarray) -> float:
    """Total area of (m, 3) ``triangles`` into (n, 2 or 3) ``positions``; 0 without triangles."""
    return float(np.sum(triangle_areas(positions[triangles]))) if len(triangles) else 0.0


def object_resolution(own_resolution: int, own_density: float, settings: LayoutSettings, world_area: float,
                      uv_area: float) -> tuple[int, int]:
    """Atlas size (width, height): the object's own resolution or texel density, else
    the scene's texel density, else the scene's resolution.

    world_area : the object's surface area in world space
    uv_area : the share of the UV square its layout covers
    """
    if own_resolution > 0:
        return own_resolution, own_resolution
    density = own_density if own_density > 0 else settings.texel_density
    if density > 0 and world_area > 0:
        size = int(np.ceil(np.sqrt(world_area / max(uv_area, 1e-6)) * density))
        size = int(np.clip(size, 8, 8192))
        return size, size
    return settings.resolution, settings.resolution


def planned_resolution(own_resolution: int, own_density: float, settings: LayoutSettings, positions: np.ndarray,
                       triangles: np.ndarray) -> tuple[int, int]:
    """The atlas size an object will get, known before its UV map is looked at.

    With a texel density the real size depends on how much of the UV square the
    layout fills; the typical packed share stands in for it here.
    """
    return object_resolution(own_resolution, own_density, settings, surface_area(positions, triangles),
                             TYPICAL_PACKED_UV_AREA)


def auto_vertex_reason(positions: np.ndarray, triangles: np.ndarray, own_resolution: int, own_density: float,
                       settings: LayoutSettings) -> str | None:
    """Why mode auto should give an object vertex tables before trying an atlas, or None.

    positions : (n, 3) world space; triangles : (m, 3) int. The caller checks first that
    vertex results can be written back at all (the mesh's modifiers keep its vertices).
    """
    count = len(triangles)
    if count > UNWRAP_TRIANGLE_BUDGET:
        return (f"{count} triangles: unwrapping would take over a minute (the budget is "
                f"{UNWRAP_TRIANGLE_BUDGET} triangles)")
    corners = positions[triangles]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
    edges = edges[np.isfinite(edges) & (edges > 0)]
    area = float(np.sum(triangle_areas(corners)))
    resolution = object_resolution(own_resolution, own_density, settings, area, TYPICAL_PACKED_UV_AREA)
    if len(edges) == 0 or area <= 0:
        return None
    texel = np.sqrt(area / (TYPICAL_PACKED_UV_AREA * resolution[0] * resolution[1]))
    spacing = float(np.median(edges))
    if spacing < texel and len(positions) >= DENSE_MIN_VERTICES:
        return (f"its vertices are {spacing:.3g} apart, finer than a texel ({texel:.3g}) at "
                f"{resolution[0]}x{resolution[1]}")
    return None
