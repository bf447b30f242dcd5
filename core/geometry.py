"""Triangle geometry shared by every stage: face normals and areas.

Positions are world space (or UV space for areas of (m, 3, 2) corners); a triangle
whose corners are not finite or that has no area gets a zero area and an invalid
normal rather than NaN.
"""
from __future__ import annotations

import numpy as np

from . import tolerances as tol


def edge_cross(corners: np.ndarray) -> np.ndarray:
    """(m, 3) float64 cross product of each triangle's two edges from corner 0: along
    the (unnormalised) face normal, counter-clockwise front, twice the area long.

    corners : (m, 3, 3) positions of each triangle's corners
    """
    corners = np.asarray(corners, np.float64)
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def face_normals(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals and a validity mask.

    Returns
    -------
    normals : (m, 3) float64, zero where the triangle is degenerate or not finite
    valid : (m,) bool
    """
    if len(triangles) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    corners = positions[triangles].astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        cross = edge_cross(corners)
        length = np.linalg.norm(cross, axis=1)
        longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
        valid = np.isfinite(length) & (length > tol.DEGENERATE_TRIANGLE_RATIO * longest * longest) & (length > 0)
    normals = np.zeros_like(cross)
    normals[valid] = cross[valid] / length[valid, None]
    return normals, valid


def triangle_areas(corners: np.ndarray) -> np.ndarray:
    """Areas of triangles given by their corners.

    corners : (m, 3, 2) (UV space) or (m, 3, 3) (world space)

    Returns (m,) float, 0 where a corner is not finite.
    """
    corners = np.where(np.isfinite(corners), corners, 0.0)
    if corners.shape[-1] == 2:
        a = corners[:, 1] - corners[:, 0]
        b = corners[:, 2] - corners[:, 0]
        return 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    return 0.5 * np.linalg.norm(edge_cross(corners), axis=1)
