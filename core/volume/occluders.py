"""Meshes in a volume's scene: they stop the light of lamps and the world before it reaches
a voxel, and end the rays of the scattering tables.

A mesh blocks light rays as a surface does in Cycles: a lamp's light reaches a voxel only
if no shadow-casting mesh lies between them, and a table ray that meets a mesh ends there
(its free flight is restricted to the stretch before it, and it no longer sees the world).
The light a mesh reflects into the volume is not baked (the report says so).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..visibility.rays import RayScene


@dataclass
class Occluders:
    """The meshes around a medium, in world space, as embree scenes.

    scattered : the meshes that end table rays and hide the world (Blender's volume scatter
        visibility), or None
    shadows : the meshes that cast shadows from lamps (Blender's shadow visibility), or None
    triangles : int, how many triangles in all (for the report)
    """

    scattered: RayScene | None
    shadows: RayScene | None
    triangles: int

    @staticmethod
    def from_meshes(meshes, threads: int = 0) -> Occluders | None:
        """``meshes``: [(positions (n, 3) float64 world, triangles (m, 3) int32, casts_shadow bool[,
        seen_by_scattering bool, default True])]. None when there are no triangles."""
        meshes = [(np.asarray(m[0], np.float64), np.asarray(m[1], np.int32), bool(m[2]),
                   bool(m[3]) if len(m) > 3 else True) for m in meshes if len(m[1])]
        if not meshes:
            return None
        finite = np.concatenate([m[0][np.all(np.isfinite(m[0]), axis=1)] for m in meshes])
        # Embree traces in float32 around this centre (core.visibility.rays.RayScene); NaN
        # vertices (broken modifiers) stay NaN and are never hit.
        centre = 0.5 * (finite.min(axis=0) + finite.max(axis=0)) if len(finite) else np.zeros(3)
        every = RayScene([(m[0], m[1]) for m in meshes], threads, centre)
        shadows = every.subset([i for i, m in enumerate(meshes) if m[2]])
        scattered = every.subset([i for i, m in enumerate(meshes) if m[3]])
        return Occluders(scattered, shadows, sum(len(m[1]) for m in meshes))

    def lamp_visibility(self, origins: np.ndarray, to_light: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """(K,) float64 1 where no shadow-casting mesh lies between ``origins`` (K, 3) world and
        the lamp (``to_light`` (K, 3) unit, ``distance`` (K,), inf for a sun), else 0."""
        if self.shadows is None or not len(origins):
            return np.ones(len(origins))
        distances = np.where(np.isfinite(distance), distance, np.float32(np.finfo(np.float32).max))
        blocked = self.shadows.occluded(np.asarray(origins, np.float64), to_light, distances.astype(np.float32))
        return (~blocked).astype(np.float64)

    def first_hits(self, origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """(K,) float64 world distance from each of ``origins`` (K, 3) along the unit world
        ``direction`` (3,) to the first mesh that volume scattering sees, inf where none."""
        if self.scattered is None:
            return np.full(len(origins), np.inf)
        directions = np.broadcast_to(np.asarray(direction, np.float32), (len(origins), 3))
        _, _, _, distance = self.scattered.intersect(np.asarray(origins, np.float64), directions)
        return distance.astype(np.float64)
