"""Triangle geometry shared by every stage: face normals and areas.

Positions are world space (or UV space for areas of (m, 3, 2) corners); a triangle
whose corners are not finite or that has no area gets a zero area and an invalid
normal rather than NaN.
"""
from __future__ import annotations

import numpy as np

from . import kernels
from . import tolerances as tol


def edge_cross(corners: np.ndarray) -> np.ndarray:
    """(m, 3) float64 cross product of each triangle's two edges from corner 0: along
    the (unnormalised) face normal, counter-clockwise front, twice the area long.

    corners : (m, 3, 3) positions of each triangle's corners
    """
    corners = np.asarray(corners, np.float64)
    a = corners[:, 1] - corners[:, 0]
    b = corners[:, 2] - corners[:, 0]
    # np.cross's own products and differences, in its order (so the same bits), without
    # the axis shuffling that makes it 3-4x slower on (m, 3) rows.
    cross = np.empty_like(a)
    np.subtract(a[:, 1] * b[:, 2], a[:, 2] * b[:, 1], out=cross[:, 0])
    np.subtract(a[:, 2] * b[:, 0], a[:, 0] * b[:, 2], out=cross[:, 1])
    np.subtract(a[:, 0] * b[:, 1], a[:, 1] * b[:, 0], out=cross[:, 2])
    return cross


def face_normals(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals and a validity mask.

    Returns
    -------
    normals : (m, 3) float64, zero where the triangle is degenerate or not finite
    valid : (m,) bool
    """
    normals, valid, _ = _face_frames(positions, triangles)
    return normals, valid


def _face_frames(positions: np.ndarray, triangles: np.ndarray, threads: int = 0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`face_normals`' normals (m, 3) float64 and valid (m,) bool, and each triangle's
    area (m,) float64 (NaN where a corner is not finite), from one cross product: by the
    compiled kernel where this process has loaded the kernels (``threads``: 0 all cores),
    else in numpy, with the same bits."""
    if len(triangles) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0)
    module = kernels.compiled() if kernels.tried() else None
    if module is not None:
        count = len(triangles)
        normals, valid, areas = np.empty((count, 3)), np.empty(count, bool), np.empty(count)
        kernels.run(module.face_frames, threads, np.ascontiguousarray(positions, np.float64),
                    np.ascontiguousarray(triangles, np.int32), tol.DEGENERATE_TRIANGLE_RATIO, normals, valid, areas)
        return normals, valid, areas
    corners = np.asarray(positions, np.float64)[triangles]
    with np.errstate(invalid="ignore", over="ignore"):
        cross = edge_cross(corners)
        length = np.linalg.norm(cross, axis=1)
        # Each edge's length as one (m, 3) row norm: the sums run in the order of the
        # (m, 3, 3) norm this replaced, at a third of its time.
        longest = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
        np.maximum(longest, np.linalg.norm(corners[:, 2] - corners[:, 1], axis=1), out=longest)
        np.maximum(longest, np.linalg.norm(corners[:, 0] - corners[:, 2], axis=1), out=longest)
        valid = np.isfinite(length) & (length > tol.DEGENERATE_TRIANGLE_RATIO * longest * longest) & (length > 0)
    normals = np.zeros_like(cross)
    normals[valid] = cross[valid] / length[valid, None]
    return normals, valid, 0.5 * length


def mesh_face_normals(mesh, threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`face_normals` of a core.scene.Mesh, kept on it: samples, the hit geometry and
    the emitters each need them, and a dense mesh's cost 0.1 s each time in numpy.
    ``threads``: the kernel's, where it runs (the first caller's: the samples').

    Returns normals (m, 3) float64 and valid (m,) bool, not to be written into.
    """
    return _kept(mesh, "_face_frames", lambda: _face_frames(mesh.positions, mesh.triangles, threads))[:2]


def mesh_triangle_areas(mesh, threads: int = 0) -> np.ndarray:
    """(m,) float64 the world-space area of each triangle of a core.scene.Mesh (NaN where a
    corner is not finite), kept on it: the contact and near-field passes each need them."""
    return _kept(mesh, "_face_frames", lambda: _face_frames(mesh.positions, mesh.triangles, threads))[2]


def _kept(mesh, name: str, compute):
    """``compute()``'s tuple of arrays, kept on ``mesh`` under ``name`` (read-only) for as long
    as the mesh holds the same position and triangle arrays (they are never written in place)."""
    kept = getattr(mesh, name, None)
    if kept is not None and kept[0] is mesh.positions and kept[1] is mesh.triangles:
        return kept[2]
    values = compute()
    for value in values:
        value.flags.writeable = False
    setattr(mesh, name, (mesh.positions, mesh.triangles, values))
    return values


def any_valid_triangle(positions: np.ndarray, triangles: np.ndarray, block: int = 4096) -> bool:
    """Whether any triangle has a normal (:func:`face_normals`' ``valid``), looking at a
    block of triangles at a time: a mesh's first block nearly always answers.

    positions : (n, 3) float; triangles : (m, 3) int
    """
    return any(face_normals(positions, triangles[start:start + block])[1].any()
               for start in range(0, len(triangles), block))


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
