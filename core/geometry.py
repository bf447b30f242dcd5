"""Triangle geometry shared by every stage: face normals and areas.

Positions are world space (or UV space for areas of (m, 3, 2) corners); a triangle
whose corners are not finite or that has no area gets a zero area and an invalid
normal rather than NaN.
"""
from __future__ import annotations

import numpy as np

from . import tolerances as tol


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
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(cross, axis=1)
        longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
        valid = np.isfinite(length) & (length > tol.DEGENERATE_TRIANGLE_RATIO * longest * longest) & (length > 0)
    normals = np.zeros_like(cross)
    normals[valid] = cross[valid] / length[valid, None]
    return normals, valid
