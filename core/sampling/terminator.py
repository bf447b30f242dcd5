"""The shadow terminator of smooth-shaded low-poly meshes, as Cycles handles it.

A smooth-shaded face is lit by its interpolated (shading) normal, so light reaches it at
angles below the flat face's own plane, where a shadow ray from the flat face runs into
the mesh itself. Cycles (``light/sample.h``: ``shadow_ray_offset`` and
``shadow_ray_smooth_surface_offset``) lets such a face be lit where the shading normal
faces the light, and starts its shadow rays from a point lifted towards the smooth surface
the vertex normals describe (a parabolic patch), by an amount that grows as the light
nears the flat face's horizon; the object's "Shadow Terminator > Geometry Offset" (default
0.1) sets the cosine where that starts. VisiBake follows the same rule, so the terminator
of a low-poly sphere, pole or torus falls where Cycles puts it.

:func:`smooth_surface_offsets` gives each sample its lift vector once (it depends on the
geometry alone); :func:`lift_amount` scales it per shadow ray.
"""
from __future__ import annotations

import numpy as np


def smooth_surface_offsets(positions: np.ndarray, triangles: np.ndarray, corner_normals: np.ndarray,
                           face_normal: np.ndarray, triangle: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(k, 3) float64: from each sample to Cycles' smooth surface over its triangle.

    positions (n, 3), triangles (m, 3), corner_normals (m, 3, 3): the mesh; face_normal
    (k, 3) unit, triangle (k,) and weights (k, 3) (barycentric, of corners 0, 1, 2): where
    each sample lies. Zero on flat-shaded faces (all corner normals the face's).
    """
    v = np.asarray(positions, np.float64)[np.asarray(triangles)[triangle]]  # (k, 3, 3)
    n = np.asarray(corner_normals, np.float64)[triangle]
    u, w1 = weights[:, 0], weights[:, 1]
    point = np.einsum("kc,kcd->kd", weights, v)
    normal = np.einsum("kc,kcd->kd", weights, n)  # not normalised, as in Cycles

    def dot(a, b):
        return np.einsum("kd,kd->k", a, b)

    # The parabolic approximation of the smooth surface's height over the flat face.
    a = dot(n[:, 2] - n[:, 0], v[:, 0] - v[:, 2])
    b = dot(n[:, 2] - n[:, 1], v[:, 1] - v[:, 2])
    c = dot(n[:, 1] - n[:, 0], v[:, 1] - v[:, 0])
    h = a * u * (u - 1) + (a + b + c) * u * w1 + b * w1 * (w1 - 1)
    outward = dot(normal, face_normal) > 0
    # The local linear envelope bounds it (signs mirrored where the normals are flipped).
    sign = np.where(outward, 1.0, -1.0)
    envelope = []
    for i, j, k in ((0, 1, 2), (1, 0, 2), (2, 0, 1)):
        reach = np.maximum(np.maximum(sign * dot(v[:, j] - v[:, i], n[:, i]), sign * dot(v[:, k] - v[:, i], n[:, i])),
                           0.0)
        envelope.append(np.maximum(sign * dot(v[:, i] - point, n[:, i]) + reach, 0.0))
    lowest = np.minimum(np.minimum(envelope[0], envelope[1]), envelope[2])
    h = np.where(outward, np.maximum(lowest, h * 0.5), np.minimum(-lowest, h * 0.5))
    return normal * h[:, None]


def lift_amount(shading_cosine: np.ndarray, geometric_cosine: np.ndarray, cutoff: np.ndarray) -> np.ndarray:
    """How much of the lift a shadow ray gets, (n,) in [0, 1], from cos(shading normal, light)
    and cos(face normal, light) (n,) each and the object's geometry offset ``cutoff`` (n,):
    full below the face's horizon, fading out as the light rises above ``cutoff``."""
    nl = np.abs(shading_cosine)
    ngl = np.where(shading_cosine < 0, -geometric_cosine, geometric_cosine)
    with np.errstate(divide="ignore", invalid="ignore"):
        near = np.clip(2.0 - (ngl + nl) / cutoff, 0.0, 1.0)
        far = np.clip(1.0 - ngl / cutoff, 0.0, 1.0)
    return np.where(cutoff > 0, np.where(nl < cutoff, near, far), 0.0)
