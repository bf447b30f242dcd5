"""Ray tracing through embreex: robust origins, batched threaded queries.

Embree's ``tnear`` is fixed at 0 in embreex, so every origin is pushed off its
surface here with the integer-ULP offset of Waechter & Binder (Ray Tracing Gems,
ch. 6), which stays robust at any distance from the world origin where a fixed
epsilon does not.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import tolerances as tol


def offset_ray_origins(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Move points off their surface along ``normals`` by a few float ULPs.

    Parameters
    ----------
    points : (n, 3) float
        Points on the surface (world space).
    normals : (n, 3) float
        Unit geometric normals on the side the rays leave from.

    Returns
    -------
    origins : (n, 3) float32
    """
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    int_offset = (tol.RAY_OFFSET_INT_SCALE * n).astype(np.int32)
    bits = p.view(np.int32)
    stepped = np.where(p < 0, bits - int_offset, bits + int_offset).astype(np.int32).view(np.float32)
    near_origin = p + np.float32(tol.RAY_OFFSET_FLOAT_SCALE) * n
    return np.where(np.abs(p) < tol.RAY_OFFSET_ORIGIN, near_origin, stepped).astype(np.float32)


def default_threads() -> int:
    return max(1, os.cpu_count() or 1)


class RayScene:
    """An embree scene of several meshes; geometry ids are the mesh order.

    Parameters
    ----------
    meshes : list of ((n, 3) float, (m, 3) int) pairs
        World-space positions and triangles of each mesh.
    threads : int
        Worker threads (embree releases the GIL during a query).
    """

    def __init__(self, meshes, threads: int = 0):
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        self._scene = EmbreeScene()
        self._meshes = []
        self._positions = []
        for positions, triangles in meshes:
            vertices = np.ascontiguousarray(positions, dtype=np.float32)
            indices = np.ascontiguousarray(triangles, dtype=np.int32)
            if len(indices) == 0:
                # embree rejects empty buffers; a single degenerate triangle keeps
                # geometry ids aligned with mesh indices and is never hit.
                vertices = np.zeros((3, 3), np.float32)
                indices = np.array([[0, 1, 2]], np.int32)
            self._meshes.append(TriangleMesh(self._scene, vertices, indices))
            self._positions.append(vertices)
        self.threads = threads or default_threads()

    def positions(self, index: int) -> np.ndarray:
        """(n, 3) float32 vertices of geometry ``index`` as embree holds them."""
        return self._positions[index]

    def _split(self, count: int):
        parts = min(self.threads, max(1, count // 4096))
        bounds = np.linspace(0, count, parts + 1).astype(np.int64)
        return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]

    def intersect(self, origins: np.ndarray, directions: np.ndarray):
        """Nearest hit of each ray.

        Returns
        -------
        geometry : (n,) int32, -1 for a miss
        triangle : (n,) int32
        barycentric_uv : (n, 2) float32, embree's (u, v): hit = (1-u-v) p0 + u p1 + v p2
        distance : (n,) float32 along the (unit) direction, inf for a miss
        """
        count = len(origins)
        geometry = np.empty(count, np.int32)
        triangle = np.empty(count, np.int32)
        bary = np.empty((count, 2), np.float32)
        distance = np.empty(count, np.float32)

        def run(span):
            a, b = span
            out = self._scene.run(np.ascontiguousarray(origins[a:b], np.float32),
                                  np.ascontiguousarray(directions[a:b], np.float32), output=1)
            geometry[a:b] = out["geomID"]
            triangle[a:b] = out["primID"]
            bary[a:b, 0] = out["u"]
            bary[a:b, 1] = out["v"]
            distance[a:b] = np.where(out["geomID"] >= 0, out["tfar"], np.inf)

        self._map(run, count)
        return geometry, triangle, bary, distance

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray | None = None) -> np.ndarray:
        """Whether anything lies on each ray before ``distances`` (default: infinity).

        Returns
        -------
        occluded : (n,) bool
        """
        count = len(origins)
        result = np.empty(count, bool)

        def run(span):
            a, b = span
            kwargs = {}
            if distances is not None:
                kwargs["dists"] = np.ascontiguousarray(distances[a:b], np.float32)
            hits = self._scene.run(np.ascontiguousarray(origins[a:b], np.float32),
                                   np.ascontiguousarray(directions[a:b], np.float32),
                                   query="OCCLUDED", **kwargs)
            result[a:b] = hits >= 0

        self._map(run, count)
        return result

    def _map(self, function, count: int) -> None:
        spans = self._split(count)
        if len(spans) <= 1:
            for span in spans:
                function(span)
            return
        with ThreadPoolExecutor(len(spans)) as pool:
            list(pool.map(function, spans))
