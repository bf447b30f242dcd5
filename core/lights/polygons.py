"""Light from polygons of uniform radiance in closed form (Lambert's formula): the emissive
triangles near a receiver (core.lights.emitters) and rectangular area lamps (core.lights.lamps).
A polygon partly below a receiver's horizon is clipped to it first."""
from __future__ import annotations

import numpy as np


def clip_above(corner: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles ``corner`` (..., 3, 3) clipped to where ``height`` (..., 3) is positive (one
    plane: at most 4 corners): (..., 6, 3) polygons whose kept corners come first in order and
    whose other slots repeat corner 0 (their edges have no length and add nothing), and the
    number of kept corners (...,) int."""
    inside = height > 0
    slots, keep = [], []
    for a in range(3):
        b = (a + 1) % 3
        slots.append(corner[..., a, :])
        keep.append(inside[..., a])
        share = height[..., a] / np.where(inside[..., a] != inside[..., b], height[..., a] - height[..., b], 1.0)
        slots.append(corner[..., a, :] + share[..., None] * (corner[..., b, :] - corner[..., a, :]))
        keep.append(inside[..., a] != inside[..., b])
    slots, keep = np.stack(slots, axis=-2), np.stack(keep, axis=-1)
    order = np.argsort(~keep, axis=-1, kind="stable")
    polygon = np.take_along_axis(slots, order[..., None], axis=-2)
    kept = keep.sum(axis=-1)
    unused = np.arange(6) >= kept[..., None]
    polygon = np.where(unused[..., None], polygon[..., :1, :], polygon)
    return polygon, kept


def polygon_form_factor(polygon: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(...,) irradiance per unit radiance, E / L, of polygons (..., V, 3) (corners relative to
    the receiver, above its horizon) at a receiver of unit ``normal`` (broadcast to (..., 3))."""
    unit = polygon / np.maximum(np.linalg.norm(polygon, axis=-1, keepdims=True), 1e-300)
    following = np.roll(unit, -1, axis=-2)
    cross = np.cross(unit, following)
    sine = np.linalg.norm(cross, axis=-1)
    angle = np.arctan2(sine, np.einsum("...vd,...vd->...v", unit, following))
    towards = np.einsum("...vd,...d->...v", cross, normal) / np.maximum(sine, 1e-300)
    return 0.5 * np.abs(np.sum(angle * towards, axis=-1))
