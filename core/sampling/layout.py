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


# The smallest atlas a camera-sized object gets (one no view sees included): small enough to
# cost nothing, large enough that xatlas's gutters still fit.
MIN_VIEW_SIZED_RESOLUTION = 16


def _density_size(world_area: float, uv_area: float, density: float, smallest: int) -> int:
    """Texels across an atlas that gives ``density`` texels per unit of surface."""
    return int(np.clip(np.ceil(np.sqrt(world_area / max(uv_area, 1e-6)) * density), smallest, 8192))


def needs_areas(own_resolution: int, own_density: float, settings: LayoutSettings, view_density: float = 0.0) -> bool:
    """Whether :func:`object_resolution` reads its ``world_area`` and ``uv_area``: only where a
    texel density sizes the atlas. Elsewhere callers skip measuring them (0.1 s on a
    200k-triangle mesh)."""
    if own_resolution > 0:
        return False
    return own_density > 0 or settings.texel_density > 0 or view_density > 0


def object_resolution(own_resolution: int, own_density: float, settings: LayoutSettings, world_area: float,
                      uv_area: float, view_density: float = 0.0) -> tuple[int, int]:
    """Atlas size (width, height): the object's own resolution or texel density, else
    the scene's texel density, else the scene's resolution.

    world_area : the object's surface area in world space
    uv_area : the share of the UV square its layout covers
    view_density : above zero, the texels per unit of surface that the cameras which will
        see the bake need (core.lightfield.coverage): it lowers the scene's size to that,
        never raises it, and leaves an object's own size alone
    """
    if own_resolution > 0:
        return own_resolution, own_resolution
    density = own_density if own_density > 0 else settings.texel_density
    if density > 0 and world_area > 0:
        size = _density_size(world_area, uv_area, density, 8)
    else:
        size = settings.resolution
    if view_density > 0 and own_density <= 0 and world_area > 0:
        size = min(size, _density_size(world_area, uv_area, view_density, MIN_VIEW_SIZED_RESOLUTION))
    return size, size


def planned_resolution(own_resolution: int, own_density: float, settings: LayoutSettings, positions: np.ndarray,
                       triangles: np.ndarray, view_density: float = 0.0) -> tuple[int, int]:
    """The atlas size an object will get, known before its UV map is looked at.

    With a texel density the real size depends on how much of the UV square the
    layout fills; the typical packed share stands in for it here.
    """
    world_area = (surface_area(positions, triangles)
                  if needs_areas(own_resolution, own_density, settings, view_density) else 0.0)
    return object_resolution(own_resolution, own_density, settings, world_area, TYPICAL_PACKED_UV_AREA, view_density)


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
