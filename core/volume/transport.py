"""Light in a medium by table lookups: direct light, then K bounces through the scattering
tables, each the same 3D lookup for every voxel (the paper's section 6.2).

What is stored per voxel is the in-scattered radiance S: the phase-weighted integral of the
radiance arriving there, which for the isotropic phase is the radiance averaged over the
sphere, W/(m^2 sr). The medium re-emits ``sigma_s * S`` per world unit towards every
direction, so an emission-absorption volume with that emission and the same extinction
renders the scattered look (FORMATS.md, "Rendering baked light").

    S_0(x) = sum over lamps of E(x) T(x) / (4 pi)                      lamps (core.volume.direct)
           + 1/N sum_i escape_i(x) L_world(d_i)                         the world (rays no mesh ends)
           + 1/N sum_i (1 - escape_i(x)) <emission / sigma_t>_i(x)      the medium's own emission
    S_k+1(x) = 1/N sum_i (1 - escape_i(x)) <albedo S_k>_i(x)            one bounce
             + [k = 0] 1/N sum_i escape_i(x) L_mesh(hit_i)              meshes (rays a mesh ends;
                                                                        core.volume.occluders)

The meshes' light joins the first bounce because Cycles counts it so: a path reaches a mesh
only by leaving a scattering point, which is a volume bounce.

where <f>_i(x) is the mean of f over the ray's stored scattering points, each read as a
trilinear interpolation of f dilated one voxel beyond the medium (dilated_source).
With albedo <= 1 every bounce is at most the one before it times the largest albedo, and a
uniform world's radiance is a fixed point: the furnace of tests/core/test_volume.py.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .. import kernels
from ..errors import VolumeRefused
from ..lights.environment import has_light, world_radiance
from ..lights.lamps import usable_lights
from ..scene import Light, World
from . import require_kernels
from .direct import lamp_inscatter
from .medium import Medium
from .occluders import reflected_light
from .tables import ScatteringTables


@dataclass
class VolumeLight:
    """The in-scattered radiance of a medium, per voxel.

    direct : (nx, ny, nz, 3) float32, light that reached each voxel without scattering
        (lamps, the world, the medium's emission)
    indirect : (nx, ny, nz, 3) float32, the sum of the bounces
    bounce_means : mean S over the active voxels after each bounce, (3,) each (for the report)
    warnings : what was left out and why
    """

    direct: np.ndarray
    indirect: np.ndarray
    bounce_means: list[np.ndarray] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def total(self) -> np.ndarray:
        """(nx, ny, nz, 3) float32 direct plus indirect."""
        return self.direct + self.indirect


def dilated_source(medium: Medium, voxels: np.ndarray, sent: np.ndarray) -> np.ndarray:
    """The gather's source grid: ``sent`` (V, 3) at ``voxels`` (V, 3) int32, and every other
    voxel that touches one of them (26-neighbourhood) given the mean of the ones it touches.

    A stored scattering point lies where the medium's trilinear density is positive, so at
    least one corner of its cell is a medium voxel and every other corner touches it: one
    ring of dilation is enough for a plain trilinear read never to mix in the zeros outside
    the medium. (The read used to weight the corners by density and divide; the dilated
    grid reads three channels instead of four and divides nothing.)

    Returns (nx + 3, ny + 3, nz + 3, 3) float32, padded as the kernels read it.
    """
    index = tuple(np.asarray(voxels).T + 1)
    shape = tuple(n + 3 for n in medium.shape)
    summed = np.zeros((*shape, 4), np.float32)
    summed[index + (slice(0, 3),)] = sent
    summed[index + (3,)] = 1.0
    inside = summed[..., 3] > 0
    source = summed[..., :3].copy()
    for axis in range(3):
        shifted = summed.copy()
        below = [slice(None)] * 4
        above = [slice(None)] * 4
        below[axis] = slice(1, None)
        above[axis] = slice(None, -1)
        shifted[tuple(below)] += summed[tuple(above)]
        shifted[tuple(above)] += summed[tuple(below)]
        summed = shifted
    touching = ~inside & (summed[..., 3] > 0)
    source[touching] = summed[touching, :3] / summed[touching, 3:]
    return source


def gather(medium: Medium, tables: ScatteringTables, sent: np.ndarray, threads: int = 0) -> np.ndarray:
    """One lookup pass: the light arriving at every table voxel from the scattering points.

    sent : (V, 3) float64 what each table voxel's scattering sends (albedo times S for a
        bounce; emission over extinction for emission)
    Returns (V, 3) float64.
    """
    from ..distributed.volume_rows import SplitVolumeTables

    if isinstance(tables, SplitVolumeTables):
        return tables.gather(dilated_source(medium, tables.voxels, sent))
    return gather_source(tables, dilated_source(medium, tables.voxels, sent), threads)


def gather_source(tables: ScatteringTables, source: np.ndarray, threads: int = 0) -> np.ndarray:
    """:func:`gather` from the dilated ``source`` grid (X, Y, Z, 3) float32 padded; (V, 3) float64."""
    module = require_kernels()
    result = np.zeros((len(tables.voxels), 3))
    kernels.run(module.gather_volume, threads, source, tables.voxels,
                tables.index_directions, tables.distance_codes, tables.escape_codes, tables.distance_per_code,
                module.BLOCK, result)
    return result


def light_medium(medium: Medium, tables: ScatteringTables, lights: list[Light] = (), world: World | None = None,
                 bounces: int = 1, area_light_samples: int = 4, threads: int = 0,
                 progress: Callable[[str, float], None] | None = None, occluders=None,
                 sweep_pass=None) -> VolumeLight:
    """Direct light and ``bounces`` bounces of scattering in ``medium``.

    lights : lamps in Cycles' units (core.scene.Light); world : its radiance reaches the
    voxels through the tables' escaping fractions (and only along rays no mesh ends, when
    the tables were built with meshes). ``progress(stage, fraction)`` is called between
    passes and may raise core.errors.Cancelled.
    occluders : core.volume.occluders.Occluders, the meshes that shadow the lamps and, where
        the tables were built with them, send their emission and reflected lamp light back
        into the medium; or None
    sweep_pass : the medium's transmittance sweep (core.volume.direct.transmittance)
    """
    if bounces < 0:
        raise ValueError(f"bounces must be >= 0, got {bounces}")
    warnings = list(medium.warnings)
    voxels = tables.voxels
    if len(voxels) and not np.array_equal(voxels, medium.active()):
        raise VolumeRefused(f"volume {medium.name!r}: the scattering tables were built for another grid; "
                            "bake its tables again")
    direct = np.zeros((len(voxels), 3))
    world_suns = list(getattr(world, "suns", None) or []) if world is not None else []
    usable = usable_lights(list(lights) + world_suns, warnings)
    # Light from meshes reaches a voxel after its path has left a scattering point once: Cycles
    # counts it as one volume bounce (measured: with it in the direct light, one bounce came
    # out 10% brighter than Cycles' one volume bounce over a floor), so it joins the first bounce.
    meshes_send_light = occluders is not None and tables.sees_world is not None
    reflecting = meshes_send_light and bounces > 0
    if meshes_send_light and bounces == 0:
        warnings.append("the light the meshes send into the volumes counts as a bounce (as in Cycles): with 0 "
                        "bounces it is left out")
    steps = len(usable) + 2 + int(reflecting) + bounces
    done = 0

    def report(stage: str) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(stage, done / steps)

    for light in usable:
        direct += lamp_inscatter(medium, light, voxels, area_light_samples, threads, occluders=occluders,
                                 sweep_pass=sweep_pass)
        report(f"direct light: {light.name}")
    if world is not None and has_light(world):
        direct += world_light(tables, world_radiance(world, tables.directions), threads)
    report("world light")
    from_meshes = None
    if reflecting:
        from_meshes = reflected_light(medium, tables, occluders, usable, area_light_samples, threads)
        report("light from meshes")
    if medium.emission is not None and medium.extinction > 0:
        direct += gather(medium, tables, medium.emission[tuple(voxels.T)] / medium.extinction, threads)
    report("emission")
    albedo = medium.albedo[tuple(voxels.T)].astype(np.float64)
    indirect = np.zeros_like(direct)
    means = []
    previous = direct
    for bounce in range(bounces):
        previous = gather(medium, tables, albedo * previous, threads)
        if bounce == 0 and from_meshes is not None:
            previous += from_meshes
        indirect += previous
        means.append(previous.mean(axis=0) if len(previous) else np.zeros(3))
        report(f"bounce {bounce + 1}")
    return VolumeLight(_to_grid(medium, voxels, direct), _to_grid(medium, voxels, indirect), means, warnings)


def world_light(tables, radiance: np.ndarray, threads: int = 0) -> np.ndarray:
    """(V, 3) float64 the world's radiance (N, 3) arriving at each table voxel through the
    fraction of each ray that leaves unscattered and meets no mesh (per range where the
    tables are held by ranges of voxels). ``threads``: the kernel's (0: all cores); the
    result does not depend on it."""
    from ..distributed.volume_rows import SplitVolumeTables

    if isinstance(tables, SplitVolumeTables):
        return tables.world_light(radiance)
    module = require_kernels()
    result = np.empty((len(tables.voxels), 3))
    kernels.run(module.world_light, threads, np.ascontiguousarray(radiance, np.float64),
                np.ascontiguousarray(tables.world_escape(), np.float32), result)
    return result


def _to_grid(medium: Medium, voxels: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(nx, ny, nz, 3) float32 with ``values`` (V, 3) at ``voxels`` and 0 elsewhere."""
    if not np.all(np.isfinite(values)):
        raise RuntimeError(f"volume {medium.name!r}: the transport produced non-finite values (a bug)")
    grid = np.zeros((*medium.shape, 3), np.float32)
    grid[tuple(voxels.T)] = values
    return grid
