"""How finely a light field's views see each object: the texel density a bake made for them needs.

A surface at depth d (metres along the optical axis) covers ``f / d`` pixels per metre, where
f is the projection's focal length in pixels (P[0, 0] * width / 2). A bake that gives the
surface that many texels per metre at the nearest depth where any view sees it has a texel
per pixel there and more texels than pixels everywhere else; more would not be seen.

The depths come from ray casting the grid's four corner views and its centre view at pixel
centres (plus the pixel filter's margin) with embree: the parallax between those extremes
bounds every other view's, and an occluded part of an object does not count. An object that
no probe ray sees first (hidden behind others in every probe, or thinner than a pixel) gets
density 0; the caller gives it the smallest atlas rather than none, so that a view between
the probes that glimpses it still finds light there.
"""
from __future__ import annotations

import numpy as np

from .raycast import RaycastRenderer
from .scene import DrawMesh, DrawScene


def probe_views(views: list, columns: int, rows: int) -> list:
    """The grid's corner views and its centre view (each once), from ``views`` in HCI order."""
    chosen = {0, columns - 1, (rows - 1) * columns, rows * columns - 1, (rows // 2) * columns + columns // 2}
    return [views[index] for index in sorted(chosen)]


def focal_pixels(projection_matrix: np.ndarray, width: int, height: int) -> float:
    """Pixels per metre of a fronto-parallel surface at depth 1 m (the larger of the two axes)."""
    return float(max(projection_matrix[0, 0] * width / 2.0, projection_matrix[1, 1] * height / 2.0))


def nearest_depths(meshes: list[np.ndarray], views: list, clip: tuple[float, float], width: int, height: int,
                   threads: int = 0) -> np.ndarray:
    """(len(meshes),) float64: the least depth (metres) at which any of ``views`` sees each mesh
    first, at pixel centres; inf where none does.

    meshes : (3 n, 3) float32 world positions of each mesh's triangle corners, unshared.
    views : core.lightfield.cameras.GridView; clip : (clip_start, clip_end) metres.
    """
    scene = DrawScene([DrawMesh(corners, np.zeros_like(corners)) for corners in meshes], np.zeros((1, 1, 3)))
    nearest = np.full(len(meshes), np.inf)
    with RaycastRenderer(scene, width, height, supersampling=1, threads=threads) as caster:
        for view in views:
            nearest = np.minimum(nearest, caster.nearest_depths(view.view_matrix, view.projection_matrix, *clip))
    return nearest


def texel_densities(depths: np.ndarray, pixels_at_one_metre: float, texels_per_pixel: float = 1.0) -> np.ndarray:
    """(n,) float64 texels per metre from :func:`nearest_depths`' (n,) depths; 0 where inf."""
    depths = np.asarray(depths, np.float64)
    densities = np.zeros(depths.shape)
    seen = np.isfinite(depths) & (depths > 0)
    densities[seen] = texels_per_pixel * pixels_at_one_metre / depths[seen]
    return densities
