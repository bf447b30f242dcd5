"""The scattering tables S_i of the paper's section 6.2: for every voxel of the medium and
every global direction d_i, where a ray from the voxel along d_i scatters, and how much of
it leaves the grid unscattered.

The paper marches each ray in fixed steps and stores one point chosen at random with the
probability that the ray scatters there (a free-flight sample), plus the transmittance
up to it. Here the escaping fraction is stored apart (it sees the world) and M points
are stratified over the free-flight distribution restricted to the grid: point j is its
quantile (j + u) / M, with u uniform per voxel, direction and point (hashed from a seed, so
a table is reproducible). Each point then carries the weight (1 - escape) / M exactly. With
M = 1 this is the paper's table.

Measured (benchmarks/volume_accuracy.py: one bounce in a 64^3 cloud against a Monte Carlo
reference, relative RMSE; docs/benchmarks.md):
- the deterministic alternative, u = 1/2 (each ray's median point, no noise), is biased:
  12% at M = 1, 5.7% at M = 2, 2.9% at M = 4, whatever the direction count, because the
  quantile function has a logarithmic end where a ray's light is still changing;
- the random points are unbiased: 6.6%, 3.3% and 2.1% at M = 1, 2, 4 with 64 directions,
  3.4% and 2.3% at M = 1, 2 with 256. At an equal number of lookups (N x M) more points
  per ray beat more directions, and take fewer bytes.
So the default is random points with M = 2 (3.3% at 64 directions, 6 bytes an entry), and
``jitter_seed=None`` keeps the midpoints for comparison.

Storage: a distance code (uint16, index-space distance along the direction) per point and an
escape code (uint16) per ray: 2 M + 2 bytes an entry, 4 bytes with M = 1 (the paper stored
a position and a transmittance per entry).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..errors import VolumeRefused
from . import require_kernels
from .medium import Medium, padded

CODE_MAX = 65535
# The march step in index units: half a voxel, so that the trapezoid rule samples the
# trilinear density at twice the grid's rate.
STEP = 0.5
# Tables above this many bytes are refused with the size and what to lower.
MAX_TABLE_BYTES = 8 << 30


@dataclass
class ScatteringTables:
    """The tables of one medium for one direction set.

    directions : (N, 3) float64 unit world directions d_i (the ray travels along d_i)
    index_directions : (N, 3) float64 the same, as unit index-space vectors
    world_per_index : (N,) float64 world length of one index unit along each
    voxels : (V, 3) int32 the voxels with a row (the medium's active voxels)
    distance_codes : (N, V, M) uint16; escape_codes : (N, V) uint16 (one 3D table per direction)
    distance_per_code : float index units per distance code
    step : float march step in index units; jitter_seed : the seed of the points' strata, or
        None for the quantile midpoints
    sees_world : (N, V) bool, False where a mesh ends the ray (its escaping fraction then
        reaches the mesh, not the world); None when no mesh is in the scene
    """

    directions: np.ndarray
    index_directions: np.ndarray
    world_per_index: np.ndarray
    voxels: np.ndarray
    distance_codes: np.ndarray
    escape_codes: np.ndarray
    distance_per_code: float
    step: float
    jitter_seed: int | None = None
    sees_world: np.ndarray | None = None

    @property
    def points(self) -> int:
        return int(self.distance_codes.shape[2])

    @property
    def nbytes(self) -> int:
        hits = 0 if self.sees_world is None else self.sees_world.nbytes
        return int(self.distance_codes.nbytes + self.escape_codes.nbytes + self.voxels.nbytes + hits)

    def escape(self) -> np.ndarray:
        """(N, V) float32 the fraction of each ray that leaves the grid unscattered."""
        return self.escape_codes.astype(np.float32) * np.float32(1.0 / CODE_MAX)

    def world_escape(self) -> np.ndarray:
        """(N, V) float32 the fraction of each ray that leaves unscattered and meets no mesh."""
        escape = self.escape()
        return escape if self.sees_world is None else escape * self.sees_world

    def distances(self) -> np.ndarray:
        """(N, V, M) float64 index-space distance of each stored point from its voxel."""
        return self.distance_codes.astype(np.float64) * self.distance_per_code


def table_bytes(voxels: int, directions: int, points: int, meshes: bool = False) -> int:
    """Bytes the tables of ``voxels`` active voxels take (what :func:`build_tables` refuses above);
    ``meshes``: with the per-ray flag of a mesh in the scene."""
    return int(voxels) * int(directions) * (2 * int(points) + 2 + int(bool(meshes))) + 12 * int(voxels)


# Rays traced against the meshes per chunk of directions: their hit distances (4 bytes each)
# are held only while the chunk is marched.
MESH_RAYS_PER_CHUNK = 1 << 23


def build_tables(medium: Medium, directions: np.ndarray, points: int = 2, step: float = STEP,
                 jitter_seed: int | None = 0, threads: int = 0, occluders=None,
                 progress=None, voxel_range: range | None = None) -> ScatteringTables:
    """March every active voxel's ray along every direction (core.kernels.volume_kernels.scatter_table).

    directions : (N, 3) float64 unit world directions; points : M >= 1; step : index units
    jitter_seed : an int for points drawn uniformly within their strata (hashed from it), None
        for the quantile midpoints
    occluders : core.volume.occluders.Occluders or None: each ray is traced against the
        meshes first, and ends at the first one it meets
    progress : called with the fraction done between chunks of directions (may raise
        core.errors.Cancelled)
    voxel_range : only these of the medium's active voxels (C order), or None for all: the
        tables of ranges, joined, are the whole tables bit for bit (core.distributed.volume_rows)
    """
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    if points < 1 or not 0 < step <= 2:
        raise ValueError(f"points must be >= 1 and step in (0, 2], got {points}, {step}")
    voxels = medium.active()
    first_voxel = 0
    if voxel_range is not None:
        voxels = voxels[voxel_range.start:voxel_range.stop]
        first_voxel = voxel_range.start
    size = table_bytes(len(voxels), len(directions), points, occluders is not None)
    if size > MAX_TABLE_BYTES:
        raise VolumeRefused(
            f"volume {medium.name!r}: its scattering tables would take {size / 2**30:.1f} GiB "
            f"({len(voxels):,} voxels x {len(directions)} directions), more than {MAX_TABLE_BYTES / 2**30:.0f} GiB; "
            "lower the resolution or the direction count")
    module = require_kernels()
    in_index = directions @ np.linalg.inv(medium.linear).T
    lengths = np.linalg.norm(in_index, axis=1)
    index_directions = in_index / lengths[:, None]
    world_per_index = 1.0 / lengths
    nx, ny, nz = medium.shape
    longest = float(np.sqrt((nx + 1.0) ** 2 + (ny + 1.0) ** 2 + (nz + 1.0) ** 2)) + 2 * step
    code_scale = CODE_MAX / longest
    distance_codes = np.zeros((len(directions), len(voxels), points), np.uint16)
    escape_codes = np.zeros((len(directions), len(voxels)), np.uint16)
    sees_world = None if occluders is None else np.ones((len(directions), len(voxels)), bool)
    if len(voxels):
        seed = -1 if jitter_seed is None else int(jitter_seed) & 0x7FFFFFFF
        density = padded(medium.density)
        origins = medium.world_positions(voxels) if occluders is not None else None
        no_meshes = np.zeros((0, 0), np.float32)
        chunk = len(directions) if occluders is None else max(1, MESH_RAYS_PER_CHUNK // len(voxels))
        for first in range(0, len(directions), chunk):
            part = slice(first, min(first + chunk, len(directions)))
            blocked = no_meshes
            if occluders is not None:
                blocked = np.stack([occluders.first_hits(origins, direction) for direction in directions[part]])
                sees_world[part] = ~np.isfinite(blocked)
                blocked = (blocked / world_per_index[part, None]).astype(np.float32)
            kernels.run(module.scatter_table, threads, density, voxels, index_directions[part],
                        world_per_index[part], float(medium.extinction), float(step), int(points), np.int64(seed),
                        code_scale, module.BLOCK, blocked, np.int64(first), np.int64(first_voxel), distance_codes[part],
                        escape_codes[part])
            if progress is not None:
                progress(part.stop / len(directions))
    return ScatteringTables(directions, index_directions, world_per_index, voxels, distance_codes, escape_codes,
                            1.0 / code_scale, float(step), jitter_seed, sees_world)
