"""The visibility bake: the paper's scattering textures S_i for every sample.

For every sample p and every direction d_i above p's geometric horizon one ray is
traced; the table stores where it lands as a continuous coordinate in the hit
object's atlas (so later lookups filter bilinearly), or a code for why it holds no
landing point. Directions below the horizon are never traced.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rays import RayScene, offset_ray_origins

MISS = -1
BELOW_HORIZON = -2
BACKFACE = -3


@dataclass
class VisibilityTable:
    """S_i[p] for all samples of all objects, one row per direction.

    directions : (N, 3) float64
    hit_object : (N, K) int16, object index, or MISS / BELOW_HORIZON / BACKFACE
    hit_uv : (N, K, 2) float32, atlas coordinate of the hit (0 where no hit)
    hit_distance : (N, K) float32, distance to the hit (inf where nothing was hit),
        so shadow fractions can ignore occluders beyond a local light
    """

    directions: np.ndarray
    hit_object: np.ndarray
    hit_uv: np.ndarray
    hit_distance: np.ndarray
    rays_cast: int = 0
    rays_below_horizon: int = 0
    backface_hits: int = 0
    backface_per_sample: np.ndarray | None = None  # (K,) int32
    traced_per_sample: np.ndarray | None = None  # (K,) int32

    def buried(self) -> np.ndarray:
        """(K,) bool: samples most of whose rays hit the back of a face.

        Such texels lie inside other geometry (a wall overlapping a floor slab);
        nobody sees them, and their backface hits say nothing about the scene.
        """
        return 2 * self.backface_per_sample > self.traced_per_sample

    @property
    def nbytes(self) -> int:
        return self.hit_object.nbytes + self.hit_uv.nbytes + self.hit_distance.nbytes


def table_bytes(directions: int, samples: int) -> int:
    """Memory the table of ``samples`` samples needs, for refusing before allocating."""
    return directions * samples * (2 + 8 + 4)


def trace_table(ray_scene: RayScene, directions: np.ndarray, positions: np.ndarray,
                geometric_normals: np.ndarray, corner_uv: np.ndarray, triangle_offset: np.ndarray,
                face_normals: np.ndarray, chunk_rays: int = 1 << 20, progress=None) -> VisibilityTable:
    """Trace every (sample, direction) pair above the sample's horizon.

    Parameters
    ----------
    ray_scene : RayScene with one geometry per object, in object order
    directions : (N, 3) float64
    positions, geometric_normals : (K, 3) float64 of all samples, objects concatenated
    corner_uv : (T, 3, 2) float32 bake-UV corners of all objects' triangles, concatenated
    triangle_offset : (objects,) int64 index of each object's first triangle in corner_uv
    face_normals : (T, 3) float64 unit face normals, concatenated like corner_uv
    chunk_rays : rays per batch (bounds memory)
    progress : callable(fraction) or None; may raise to cancel

    Returns
    -------
    VisibilityTable
    """
    count = len(directions)
    samples = len(positions)
    hit_object = np.full((count, samples), BELOW_HORIZON, np.int16)
    hit_uv = np.zeros((count, samples, 2), np.float32)
    hit_distance = np.full((count, samples), np.inf, np.float32)
    origins_all = offset_ray_origins(positions, geometric_normals)
    directions32 = directions.astype(np.float32)
    chunk = max(1, chunk_rays // max(count, 1))
    rays_cast = 0
    backfaces = 0
    backface_per_sample = np.zeros(samples, np.int32)
    traced_per_sample = np.count_nonzero(geometric_normals @ directions.T > 0.0, axis=1).astype(np.int32)
    for start in range(0, samples, chunk):
        stop = min(samples, start + chunk)
        # Direction-major order: consecutive rays share a direction (coherent for
        # embree) and land in one row of the table (contiguous writes).
        above = (directions @ geometric_normals[start:stop].T) > 0.0
        direction_index, sample_index = np.nonzero(above)
        if len(sample_index):
            geometry, triangle, bary, distance = ray_scene.intersect(origins_all[start:stop][sample_index],
                                                           directions32[direction_index])
            rows = direction_index
            cols = sample_index + start
            missed = geometry < 0
            hit_object[rows[missed], cols[missed]] = MISS
            hit = ~missed
            global_triangle = triangle_offset[geometry[hit]] + triangle[hit]
            facing = np.einsum("kd,kd->k", face_normals[global_triangle], directions[direction_index[hit]])
            back = facing > 0.0
            backfaces += int(np.count_nonzero(back))
            backface_per_sample += np.bincount(cols[hit][back], minlength=samples).astype(np.int32)
            u = bary[hit, 0:1]
            v = bary[hit, 1:2]
            uv = corner_uv[global_triangle]
            landing = (1.0 - u - v) * uv[:, 0] + u * uv[:, 1] + v * uv[:, 2]
            code = np.where(back, BACKFACE, geometry[hit]).astype(np.int16)
            hit_object[rows[hit], cols[hit]] = code
            hit_uv[rows[hit], cols[hit]] = np.where(back[:, None], 0.0, landing)
            hit_distance[rows[hit], cols[hit]] = distance[hit]
            rays_cast += len(sample_index)
        if progress is not None:
            progress(stop / samples)
    return VisibilityTable(directions=directions, hit_object=hit_object, hit_uv=hit_uv, hit_distance=hit_distance,
                           rays_cast=rays_cast, rays_below_horizon=count * samples - rays_cast,
                           backface_hits=backfaces, backface_per_sample=backface_per_sample,
                           traced_per_sample=traced_per_sample)
