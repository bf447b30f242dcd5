"""Light in participating media from precomputed visibility (the paper's section 6), free of bpy.

- :mod:`.medium`: the medium on a grid (density, albedo, emission), checked once.
- :mod:`.direct`: each lamp's transmittance to every voxel by slice sweeps, and its light.
- :mod:`.tables`: the scattering tables S_i, one 3D table per global direction.
- :mod:`.transport`: direct light and K bounces by 3D table lookups.

The compiled kernels are in :mod:`core.kernels.volume_kernels`.
"""


def require_kernels():
    """The compiled volume kernels (core.kernels.volume); refuses the bake with the reason where
    numba cannot load. Volumes have no numpy fallback: their passes are the compiled kernels
    and (to come) their GPU twins."""
    from .. import kernels
    from ..errors import VolumeRefused
    module = kernels.volume()
    if module is None:
        raise VolumeRefused(f"volume lighting needs VisiBake's compiled kernels, which cannot load here: "
                            f"{kernels.status().reason}")
    return module
