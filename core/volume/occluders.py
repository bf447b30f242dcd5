"""Meshes in a volume's scene: they stop the light of lamps and the world before it reaches
a voxel, end the rays of the scattering tables, and send back the light they reflect.

A mesh blocks light rays as a surface does in Cycles: a lamp's light reaches a voxel only
if no shadow-casting mesh lies between them, and a table ray that meets a mesh ends there
(its free flight is restricted to the stretch before it, and it no longer sees the world).
What the mesh sends back along that ray is its emission plus its diffuse reflection of the
lamps (:func:`reflected_light`); its reflection of the world and of the volume's own light
is left out (first order).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..geometry import face_normals
from ..visibility.rays import RayScene
from . import require_kernels
from .medium import Medium, padded
from .tables import CODE_MAX, STEP


@dataclass
class SurfaceMesh:
    """One mesh around a medium, in world space.

    positions : (n, 3) float64; triangles : (m, 3) int32
    casts_shadow : lamps' shadow rays stop at it (Blender's shadow visibility)
    seen_by_scattering : table rays end at it (Blender's volume scatter visibility)
    albedo : (m, 3) float32 diffuse albedo per triangle, or None (black)
    emission : (m, 3) float32 emitted radiance per triangle, or None (none)
    """

    positions: np.ndarray
    triangles: np.ndarray
    casts_shadow: bool = True
    seen_by_scattering: bool = True
    albedo: np.ndarray | None = None
    emission: np.ndarray | None = None

    @staticmethod
    def of(mesh) -> SurfaceMesh:
        """A SurfaceMesh, or one from a tuple (positions, triangles[, casts_shadow[, seen_by_scattering]])."""
        if isinstance(mesh, SurfaceMesh):
            return mesh
        return SurfaceMesh(np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int32), *mesh[2:])


@dataclass
class Occluders:
    """The meshes around a medium, as embree scenes.

    scattered : the meshes that end table rays and hide the world, or None
    shadows : the meshes that cast shadows from lamps, or None
    triangles : int, how many triangles in all (for the report)
    surfaces : the meshes of ``scattered``, in its geometry order (what a table ray meets)
    """

    scattered: RayScene | None
    shadows: RayScene | None
    triangles: int
    surfaces: list

    @staticmethod
    def from_meshes(meshes, threads: int = 0) -> Occluders | None:
        """``meshes``: SurfaceMesh, or tuples SurfaceMesh.of takes. None when there are no triangles."""
        meshes = [m for m in (SurfaceMesh.of(m) for m in meshes) if len(m.triangles)]
        if not meshes:
            return None
        finite = np.concatenate([m.positions[np.all(np.isfinite(m.positions), axis=1)] for m in meshes])
        # Embree traces in float32 around this centre (core.visibility.rays.RayScene); NaN
        # vertices (broken modifiers) stay NaN and are never hit.
        centre = 0.5 * (finite.min(axis=0) + finite.max(axis=0)) if len(finite) else np.zeros(3)
        every = RayScene([(m.positions, m.triangles) for m in meshes], threads, centre)
        shadows = every.subset([i for i, m in enumerate(meshes) if m.casts_shadow])
        seen = [i for i, m in enumerate(meshes) if m.seen_by_scattering]
        return Occluders(every.subset(seen), shadows, sum(len(m.triangles) for m in meshes),
                         [meshes[i] for i in seen])

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
        return self.hits(origins, direction)[2]

    def hits(self, origins: np.ndarray, direction: np.ndarray):
        """The first mesh each ray from ``origins`` (K, 3) along ``direction`` (3,) meets:
        (geometry (K,) int32 into :attr:`surfaces`, -1 for none; triangle (K,) int32;
        distance (K,) float64 world, inf for none)."""
        if self.scattered is None:
            return np.full(len(origins), -1, np.int32), np.zeros(len(origins), np.int32), np.full(len(origins), np.inf)
        directions = np.broadcast_to(np.asarray(direction, np.float32), (len(origins), 3))
        geometry, triangle, _, distance = self.scattered.intersect(np.asarray(origins, np.float64), directions)
        return geometry, triangle, distance.astype(np.float64)


def reflected_light(medium: Medium, tables, occluders: Occluders | None, lights: list, area_light_samples: int = 4,
                    threads: int = 0, first_voxel: int = 0) -> np.ndarray:
    """In-scattered radiance from the meshes that the table rays end at.

    Each such ray brings its escaping fraction (the medium's transmittance up to the mesh)
    times the radiance the mesh sends back along it: its emission, plus albedo / pi times
    the irradiance of ``lights`` at the hit point (Cycles' lamp sampling, core.lights.lamps),
    each lamp point shadowed by the meshes and by the medium (a march from the hit point to
    it). Both sides of a face reflect (a thin plane lights the volume from either side).

    tables : core.volume.tables.ScatteringTables built with these occluders (of the active
        voxels from ``first_voxel`` on: each hit point's lamp sampler is seeded by its voxel's
        index among all of them, so that ranges give the whole tables' light bit for bit)
    Returns (V, 3) float64 W/(m^2 sr), zero where no ray meets a mesh.
    """
    from ..distributed.volume_rows import SplitVolumeTables

    if isinstance(tables, SplitVolumeTables):
        return tables.reflected_light(lights, area_light_samples)
    result = np.zeros((len(tables.voxels), 3))
    if occluders is None or occluders.scattered is None or tables.sees_world is None or not len(tables.voxels):
        return result
    module = require_kernels()
    density = padded(medium.density)
    inverse = np.linalg.inv(medium.linear)
    for d, direction in enumerate(tables.directions):
        ended = np.flatnonzero(~tables.sees_world[d])
        if not len(ended):
            continue
        origins = medium.world_positions(tables.voxels[ended])
        geometry, triangle, distance = occluders.hits(origins, direction)
        found = geometry >= 0
        ended, origins, geometry, triangle, distance = (a[found] for a in (ended, origins, geometry, triangle,
                                                                             distance))
        points = origins + distance[:, None] * direction
        sent = np.zeros((len(ended), 3))
        normals = np.zeros((len(ended), 3))
        albedo = np.zeros((len(ended), 3))
        for number, surface in enumerate(occluders.surfaces):
            mine = geometry == number
            if not mine.any():
                continue
            normals[mine] = face_normals(surface.positions, surface.triangles[triangle[mine]])[0]
            if surface.albedo is not None:
                albedo[mine] = surface.albedo[triangle[mine]]
            if surface.emission is not None:
                sent[mine] += surface.emission[triangle[mine]]
        # Face the voxel the ray came from: a face seen from behind reflects as its front would.
        normals *= np.where(normals @ direction > 0.0, -1.0, 1.0)[:, None]
        lit = np.flatnonzero(albedo.max(axis=1) > 0.0)
        if len(lit):
            irradiance = _irradiance(module, medium, density, inverse, occluders, lights, points[lit],
                                     normals[lit], area_light_samples, threads, ended[lit] + first_voxel)
            sent[lit] += albedo[lit] / np.pi * irradiance
        escape = tables.escape_codes[d, ended].astype(np.float64) * (1.0 / CODE_MAX)
        result[ended] += escape[:, None] * sent
    return result / len(tables.directions)


def _irradiance(module, medium: Medium, density: np.ndarray, inverse: np.ndarray, occluders: Occluders,
                lights: list, points: np.ndarray, normals: np.ndarray, area_light_samples: int,
                threads: int, ids: np.ndarray) -> np.ndarray:
    """(K, 3) float64 irradiance of ``lights`` at world ``points`` (K, 3) with unit ``normals``,
    shadowed by the meshes and by the medium; ids (K,) int64 seed each point's lamp sampler."""
    from ..lights.lamps import light_contributions

    total = np.zeros((len(points), 3))
    origins = occluders.shadows.ray_origins(points, normals) if occluders.shadows is not None else points
    start = medium.to_index(points)
    ids = np.asarray(ids, np.int64)
    for light in lights:
        for contribution in light_contributions(light, points, normals, area_light_samples, ids):
            if not contribution.irradiance.any():
                continue
            shade = np.ones(len(points))
            if light.casts_shadows:
                shade = occluders.lamp_visibility(origins, contribution.to_light, contribution.distance)
                along = contribution.to_light @ inverse.T
                scale = np.linalg.norm(along, axis=1)
                world_per_index = 1.0 / scale
                transmittance = np.ones(len(points))
                kernels.run(module.march_transmittance, threads, density, start, along / scale[:, None],
                            contribution.distance * scale, world_per_index, float(medium.extinction), STEP,
                            transmittance)
                shade *= transmittance
            total += contribution.irradiance * shade[:, None]
    return total
