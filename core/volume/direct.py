"""Direct light in a medium: each lamp's transmittance to every voxel by the paper's slice
sweep (section 6.1), and the light it scatters there.

A sun is swept once, along the grid axis closest to its direction. A lamp at a position is
swept six times, outwards from it along each axis and sign, and each voxel takes the sweep
of the pyramid it lies in (the axis along which its ray to the lamp moves fastest), so
that every ray crosses each slice within one voxel of where it left the last one.

The sweep is a semi-Lagrangian integration: it is exact where the transmittance is linear
across a slice between grid points (a homogeneous slab), and otherwise blurs a shadow's
edge by up to a voxel per slice's worth of bilinear interpolation. tests/core/test_volume.py
measures it against a fine ray march of the same medium.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from ..lights.lamps import centre_probe, light_contributions
from ..scene import Light
from . import require_kernels
from .medium import Medium, padded


@dataclass(frozen=True)
class SweepFrame:
    """A grid seen with the sweep axis first and increasing away from the lamp (the kernel
    reads the grid permuted to ``order``, and its first axis backwards when ``flip``).

    order : (3,) the original axes in this frame's order; flip : the sweep axis is reversed
    """

    order: tuple[int, int, int]
    flip: bool

    @staticmethod
    def along(axis: int, flip: bool) -> SweepFrame:
        return SweepFrame((axis, *(a for a in range(3) if a != axis)), flip)

    def vector(self, vector: np.ndarray) -> np.ndarray:
        """An index-space direction (3,) in this frame."""
        moved = np.asarray(vector, np.float64)[list(self.order)].copy()
        if self.flip:
            moved[0] = -moved[0]
        return moved

    def point(self, point: np.ndarray, shape) -> np.ndarray:
        """An index-space point (3,) in this frame, for a grid of ``shape`` (original axes)."""
        moved = np.asarray(point, np.float64)[list(self.order)].copy()
        if self.flip:
            moved[0] = shape[self.order[0]] - 1 - moved[0]
        return moved

    def linear(self, linear: np.ndarray) -> np.ndarray:
        """The index-to-world linear map (3, 3) for this frame's index vectors."""
        moved = np.asarray(linear, np.float64)[:, list(self.order)].copy()
        if self.flip:
            moved[:, 0] = -moved[:, 0]
        return moved


def transmittance(medium: Medium, light: Light, threads: int = 0, sweep_pass=None) -> np.ndarray:
    """The fraction of ``light``'s light reaching every voxel centre through the medium.

    Returns (nx, ny, nz) float32 in [0, 1]. A lamp that casts no shadows is not attenuated
    (Blender's Cast Shadow off). An area lamp is swept from its centre.
    sweep_pass : None for the CPU kernel (core.kernels.volume_kernels.sweep_transmittance),
        or a callable with its arguments that does the same sweep elsewhere (the GPU twin,
        gpu_shaders.volume_sweep)
    """
    if not light.casts_shadows or medium.extinction == 0:
        return np.ones(medium.shape, np.float32)
    module = require_kernels()
    inverse = np.linalg.inv(medium.linear)
    result = np.ones(medium.shape, np.float32)
    permuted: dict[int, np.ndarray] = {}

    def density_along(axis: int) -> np.ndarray:
        """The padded density with ``axis`` first: one copy per axis, shared by its two sweeps."""
        if axis not in permuted:
            permuted[axis] = padded(medium.density.transpose(SweepFrame.along(axis, False).order))
        return permuted[axis]

    def sweep(frame: SweepFrame, is_point: bool, light_in_frame: np.ndarray, lamp_density: float) -> None:
        arguments = (density_along(frame.order[0]), medium.extinction, is_point, light_in_frame,
                     frame.linear(medium.linear), is_point, frame.flip, np.array(frame.order, np.int64),
                     lamp_density, result)
        if sweep_pass is None:
            kernels.run(module.sweep_transmittance, threads, *arguments)
        else:
            sweep_pass(*arguments)

    if light.kind == "SUN":
        towards = inverse @ -np.asarray(light.direction, np.float64)
        axis = int(np.argmax(np.abs(towards)))
        frame = SweepFrame.along(axis, bool(towards[axis] > 0))
        step = frame.vector(towards)
        sweep(frame, False, step / -step[0], 0.0)
        return result
    lamp = medium.to_index(np.asarray(light.position, np.float64)[None])[0]
    for axis in range(3):
        for flip in (False, True):
            frame = SweepFrame.along(axis, flip)
            where = frame.point(lamp, medium.shape)
            if np.floor(where[0]) + 1 >= medium.shape[axis]:
                continue  # the lamp lies beyond the grid's last slice on this side
            unflipped = SweepFrame.along(axis, False).point(lamp, medium.shape)
            lamp_density = float(module.trilinear(density_along(axis), *unflipped))
            sweep(frame, True, where, lamp_density)
    return result


def lamp_inscatter(medium: Medium, light: Light, voxels: np.ndarray, area_light_samples: int = 4,
                   threads: int = 0, chunk: int = 1 << 18, occluders=None, sweep_pass=None) -> np.ndarray:
    """In-scattered radiance of one lamp at ``voxels``, shadowed by the medium and, with
    ``occluders`` (core.volume.occluders.Occluders), by the meshes: a shadow ray per voxel
    and lamp point, so an area lamp's mesh shadows are soft.

    With an isotropic phase it is the unshadowed irradiance at normal incidence over 4 pi,
    times the transmittance: a small lamp's radiance arriving from its solid angle, averaged
    over the sphere. An area lamp or a soft lamp is integrated over its extent with the
    surface baker's sampler (Cycles' sampling of each lamp, core.lights.lamps), each point
    at normal incidence, and shadowed as from its centre.

    voxels : (V, 3) int32. Returns (V, 3) float64 W/(m^2 sr).
    """
    shadow = transmittance(medium, light, threads, sweep_pass)[tuple(voxels.T)].astype(np.float64)
    meshes_shadow = occluders is not None and light.casts_shadows
    result = np.zeros((len(voxels), 3))
    for start in range(0, len(voxels), chunk):
        part = slice(start, start + chunk)
        positions = medium.world_positions(voxels[part])
        towards, _ = centre_probe(light, positions)
        ids = np.arange(start, start + len(positions), dtype=np.int64)
        for contribution in light_contributions(light, positions, towards, area_light_samples, ids):
            if meshes_shadow:
                seen = occluders.lamp_visibility(positions, contribution.to_light, contribution.distance)
                result[part] += contribution.irradiance * seen[:, None]
            else:
                result[part] += contribution.irradiance
    return result * (shadow / (4.0 * np.pi))[:, None]
