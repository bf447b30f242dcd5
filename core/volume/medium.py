"""A participating medium on a regular grid, checked once so that every pass may trust it.

The medium is what Cycles renders for a Volume object with a Principled Volume: the grid's
values at voxel centres, interpolated trilinearly (Blender's default volume interpolation),
zero outside the grid. Extinction is ``sigma_t = extinction * density`` per world unit
(``extinction`` is the material's Density), the single-scattering albedo is the
Principled Volume's colour (scattering ``sigma_s = albedo * sigma_t``), the phase is
isotropic (the paper's section 6), and emission is radiance added per world unit of path.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import VolumeRefused

# Largest grid side and voxel count a volume may have: 1024^3 float32 densities alone are
# 4 GiB, and each pass keeps a few grids of that size beside the tables.
MAX_SIDE = 1024
MAX_VOXELS = 512 ** 3


@dataclass
class Medium:
    """A checked medium.

    name : str, the volume's name in messages
    density : (nx, ny, nz) float32, finite and >= 0, the values at voxel centres
    index_to_world : (4, 4) float64, invertible: voxel (i, j, k)'s centre is at
        ``index_to_world @ (i, j, k, 1)``
    extinction : float, sigma_t per unit density per world unit, finite and >= 0
    albedo : (nx, ny, nz, 3) float32 in [0, 1]
    emission : (nx, ny, nz, 3) float32 >= 0 (radiance per world unit), or None
    warnings : what was changed to make the medium usable (for the report)
    """

    name: str
    density: np.ndarray
    index_to_world: np.ndarray
    extinction: float
    albedo: np.ndarray
    emission: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.density.shape)

    @property
    def linear(self) -> np.ndarray:
        """(3, 3) float64: index-space vectors to world vectors."""
        return self.index_to_world[:3, :3]

    def active(self) -> np.ndarray:
        """(V, 3) int32: the voxels that hold medium (density > 0), in C order."""
        return np.argwhere(self.density > 0).astype(np.int32)

    def world_positions(self, voxels: np.ndarray) -> np.ndarray:
        """(V, 3) float64 world positions of the centres of ``voxels`` (V, 3) integer."""
        return voxels.astype(np.float64) @ self.linear.T + self.index_to_world[:3, 3]

    def to_index(self, points: np.ndarray) -> np.ndarray:
        """(K, 3) float64 index-space coordinates of world ``points`` (K, 3)."""
        return (np.asarray(points, np.float64) - self.index_to_world[:3, 3]) @ np.linalg.inv(self.linear).T


def check_grid_shape(name: str, shape) -> tuple[int, int, int]:
    """Refuse a grid too large to light before anything of its size is allocated.

    shape : three sides (the grid's bounding box in voxels, as a file states it)
    """
    sides = tuple(int(n) for n in shape)
    if len(sides) != 3 or min(sides) < 1:
        raise VolumeRefused(f"volume {name!r}: its grid has no voxels (sides {sides})")
    if max(sides) > MAX_SIDE or int(np.prod(sides, dtype=np.int64)) > MAX_VOXELS:
        raise VolumeRefused(
            f"volume {name!r}: its grid is {sides[0]} x {sides[1]} x {sides[2]} voxels, more than VisiBake "
            f"lights (at most {MAX_SIDE} per side and {MAX_VOXELS:,} in all); lower the resolution")
    return sides


def check_density_values(name: str, density: np.ndarray) -> None:
    """VolumeRefused where the density grid ``density`` (any shape, real) of volume ``name``
    holds NaN, infinite or negative voxels, with how many.

    A reader checks the grid as the file holds it, before any resampling: averaged with its
    neighbours, a negative voxel would vanish at one resolution and be refused at another."""
    bad = ~np.isfinite(density)
    if bad.any():
        raise VolumeRefused(f"volume {name!r}: {int(bad.sum()):,} of its density voxels are NaN or infinite; "
                            "fix the grid (or its simulation cache) and bake again")
    negative = density < 0
    if negative.any():
        raise VolumeRefused(f"volume {name!r}: {int(negative.sum()):,} of its density voxels are negative "
                            f"(lowest {float(density.min()):g}); densities must be >= 0")


def make_medium(name: str, density, index_to_world, extinction: float = 1.0, albedo=(1.0, 1.0, 1.0),
                emission=None) -> Medium:
    """Check a medium's grids and settings and return it as a :class:`Medium`.

    density : (nx, ny, nz) real; index_to_world : (4, 4) real (or (3, 4))
    albedo : (3,) or (nx, ny, nz, 3) or (nx, ny, nz) real; emission : None, (3,) or
        (nx, ny, nz, 3) real (a constant is emitted where density > 0)
    Raises VolumeRefused with what to change: NaN, infinite or negative densities, a grid
    too large, a singular transform, a non-finite setting. Albedos outside [0, 1] and
    negative emission are clamped, with a warning.
    """
    density = np.asarray(density)
    if density.ndim != 3:
        raise VolumeRefused(f"volume {name!r}: its density grid has {density.ndim} dimensions, not 3")
    check_grid_shape(name, density.shape)
    density = np.ascontiguousarray(density, np.float32)
    check_density_values(name, density)
    matrix = np.asarray(index_to_world, np.float64)
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise VolumeRefused(f"volume {name!r}: its grid transform is not a finite 4 x 4 matrix")
    determinant = float(np.linalg.det(matrix[:3, :3]))
    scale = float(np.abs(matrix[:3, :3]).max())
    if not abs(determinant) > 1e-12 * max(scale, 1e-300) ** 3:
        raise VolumeRefused(f"volume {name!r}: its grid transform is singular (a voxel has no volume); "
                            "check the object's scale")
    extinction = float(extinction)
    if not np.isfinite(extinction) or extinction < 0:
        raise VolumeRefused(f"volume {name!r}: density {extinction:g} is not a usable number; use a value >= 0")
    warnings: list[str] = []
    albedo = _per_voxel(name, "colour", albedo, density.shape)
    if albedo.min() < 0 or albedo.max() > 1:
        warnings.append(f"volume {name!r}: its colour was clamped to [0, 1] (a scattering albedo above 1 "
                        "creates light)")
        albedo = np.clip(albedo, 0.0, 1.0)
    if emission is not None:
        emission = _per_voxel(name, "emission", emission, density.shape)
        if emission.min() < 0:
            warnings.append(f"volume {name!r}: negative emission was set to 0")
            emission = np.clip(emission, 0.0, None)
        emission = np.where(density[..., None] > 0, emission, np.float32(0.0))
        if not emission.any():
            emission = None
    return Medium(name, density, matrix, extinction, albedo, emission, warnings)


def _per_voxel(name: str, what: str, value, shape) -> np.ndarray:
    """(nx, ny, nz, 3) float32 from a constant (3,), a scalar grid (nx, ny, nz) or an RGB grid."""
    array = np.asarray(value, np.float32)
    if array.shape == (3,) or array.shape == ():
        array = np.broadcast_to(array, (*shape, 3))
    elif array.shape == tuple(shape):
        array = np.broadcast_to(array[..., None], (*shape, 3))
    elif array.shape != (*shape, 3):
        raise VolumeRefused(f"volume {name!r}: its {what} grid is {array.shape}, not the density's {tuple(shape)}")
    if not np.all(np.isfinite(array)):
        raise VolumeRefused(f"volume {name!r}: its {what} has NaN or infinite values")
    return np.ascontiguousarray(array, np.float32)


def padded(grid: np.ndarray) -> np.ndarray:
    """``grid`` (nx, ny, nz[, C]) as the kernels read it: float32, with one layer of zeros
    below and two above on each spatial axis (core.kernels.volume_kernels)."""
    pad = [(1, 2)] * 3 + [(0, 0)] * (grid.ndim - 3)
    return np.ascontiguousarray(np.pad(np.asarray(grid, np.float32), pad))
