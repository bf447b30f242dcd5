"""Ray tracing on a surface that repeats in X and Y: a ray that leaves one period re-enters
from the opposite side (the paper's section 7.1), so neighbouring periods shadow and mask.

Embree holds the tile with its eight neighbours (3 x 3 copies), and each ray is walked
through the central period's column [origin, origin + period) in X and Y: it is traced
only up to where it leaves the column, and then moved back by one period and traced on.
Geometry that reaches into the column from a neighbour (a tile whose faces overhang its
footprint by less than a period) is therefore found too. A ray ends at the first face it
meets, or when it leaves the slab of the tile's heights, upwards (it escapes to the sky)
or downwards (it passes through the surface: the BSDF's transparency).
"""
from __future__ import annotations

import numpy as np

from ..visibility.rays import RayScene

# What happened to a ray (PeriodicHits.fate).
HIT = 0
ESCAPED_UP = 1
ESCAPED_DOWN = 2
# A ray this close to horizontal crosses many periods before leaving the slab; after this
# many crossings it is taken to have hit nothing and to leave the way it was heading.
MAX_CROSSINGS = 2048


class PeriodicHits:
    """Where each ray of a periodic trace ended.

    fate : (n,) int8 HIT, ESCAPED_UP or ESCAPED_DOWN
    triangle : (n,) int32 the tile's triangle that was hit (-1 otherwise)
    barycentric : (n, 3) float32 weights of the triangle's corners at the hit
    distance : (n,) float64 along the ray (inf when it escaped)
    """

    def __init__(self, count: int):
        self.fate = np.full(count, ESCAPED_UP, np.int8)
        self.triangle = np.full(count, -1, np.int32)
        self.barycentric = np.zeros((count, 3), np.float32)
        self.distance = np.full(count, np.inf)


class PeriodicScene:
    """The tile's triangles repeated 3 x 3 around its footprint, for periodic queries.

    positions : (P, 3) float64; triangles : (T, 3) int32; period, origin : (2,) float64;
    z_range : (lowest, highest) z of the geometry (the slab rays leave)
    """

    def __init__(self, positions: np.ndarray, triangles: np.ndarray, period, origin, threads: int = 0):
        self.period = np.asarray(period, np.float64)
        self.origin = np.asarray(origin, np.float64)
        self.triangle_count = len(triangles)
        used = positions[np.unique(triangles)]
        self.z_range = (float(used[:, 2].min()), float(used[:, 2].max()))
        centre = np.array([*(self.origin + 0.5 * self.period), 0.5 * sum(self.z_range)])
        copies = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                shift = np.array([dx * self.period[0], dy * self.period[1], 0.0])
                copies.append(positions + shift)
        count = len(positions)
        all_triangles = np.concatenate([triangles + k * count for k in range(9)]).astype(np.int32)
        self.scene = RayScene([(np.concatenate(copies), all_triangles)], threads, centre=centre)
        # Faces hit within this share of the slab's thickness of a ray's start are its own surface.
        self.slab_margin = 1e-6 * max(float(self.period.max()), self.z_range[1] - self.z_range[0])

    def wrap(self, points: np.ndarray) -> np.ndarray:
        """``points`` (n, 3) moved by whole periods into the central column (float64)."""
        out = np.array(points, np.float64)
        out[:, :2] = self.origin + np.mod(out[:, :2] - self.origin, self.period)
        return out

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> PeriodicHits:
        """The first face each ray meets on the periodic surface.

        origins : (n, 3) float64 (anywhere: moved into the central column first, which the
            surface's periodicity allows); directions : (n, 3) float64 unit
        """
        count = len(origins)
        hits = PeriodicHits(count)
        position = self.wrap(origins)
        direction = np.asarray(directions, np.float64)
        travelled = np.zeros(count)
        live = np.arange(count)
        low, high = self.z_range
        low -= self.slab_margin
        high += self.slab_margin
        for _ in range(MAX_CROSSINGS):
            if len(live) == 0:
                break
            p = position[live]
            d = direction[live]
            # Distances to the central column's walls and to the slab's faces.
            with np.errstate(divide="ignore", invalid="ignore"):
                wall = np.full((len(live), 2), np.inf)
                for axis in range(2):
                    lower = self.origin[axis]
                    upper = lower + self.period[axis]
                    step = np.where(d[:, axis] > 0, (upper - p[:, axis]) / d[:, axis],
                                    np.where(d[:, axis] < 0, (lower - p[:, axis]) / d[:, axis], np.inf))
                    wall[:, axis] = np.maximum(step, 0.0)
                slab = np.where(d[:, 2] > 0, (high - p[:, 2]) / d[:, 2],
                                np.where(d[:, 2] < 0, (low - p[:, 2]) / d[:, 2], np.inf))
                slab = np.maximum(slab, 0.0)
            to_wall = wall.min(axis=1)
            reach = np.minimum(to_wall, slab)
            # Embree traces in float32: a little beyond the wall, so a face on it is not missed.
            limit = np.where(np.isfinite(reach), reach * (1 + 1e-6) + self.slab_margin, np.float32(3e38))
            geometry, triangle, uv, distance = self.scene.intersect(p, d, limit)
            hit = geometry >= 0
            if np.any(hit):
                rows = live[hit]
                hits.fate[rows] = HIT
                hits.triangle[rows] = triangle[hit] % self.triangle_count
                u = uv[hit, 0]
                v = uv[hit, 1]
                hits.barycentric[rows] = np.column_stack([1 - u - v, u, v])
                hits.distance[rows] = travelled[rows] + distance[hit]
            leaving = ~hit & (slab <= to_wall)
            if np.any(leaving):
                rows = live[leaving]
                hits.fate[rows] = np.where(direction[rows, 2] > 0, ESCAPED_UP, ESCAPED_DOWN)
            onward = ~hit & ~leaving
            rows = live[onward]
            if len(rows) == 0:
                break
            step = to_wall[onward]
            moved = p[onward] + d[onward] * step[:, None]
            travelled[rows] += step
            # Back by one period across the wall that was reached (both, at a corner).
            for axis in range(2):
                crossed = wall[onward, axis] <= step
                moved[crossed, axis] -= np.sign(d[onward][crossed, axis]) * self.period[axis]
            position[rows] = moved
            live = rows
        else:
            # Rays still walking: nearly horizontal. Taken to leave the way they head.
            hits.fate[live] = np.where(direction[live, 2] >= 0, ESCAPED_UP, ESCAPED_DOWN)
        return hits
