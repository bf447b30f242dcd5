"""World light through the table's misses: the environment's radiance per direction.

A miss in direction d_i sees the world; the gather needs one radiance per d_i, the
same for every sample, so the environment is reduced to (N, 3) once per lighting.
"""
from __future__ import annotations

import numpy as np

from .scene import World


def world_radiance(world: World, directions: np.ndarray) -> np.ndarray:
    """Radiance the world sends back along each direction of the set.

    Parameters
    ----------
    world : World
    directions : (N, 3) float64 unit directions (the direction a ray travels)

    Returns
    -------
    radiance : (N, 3) float64, finite and non-negative
    """
    directions = np.asarray(directions, np.float64)
    if world.image is None:
        radiance = np.broadcast_to(np.asarray(world.color, np.float64)[:3], (len(directions), 3))
    else:
        raise NotImplementedError("environment images are not supported yet")
    radiance = np.nan_to_num(np.asarray(radiance, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(radiance, 0.0, None)
