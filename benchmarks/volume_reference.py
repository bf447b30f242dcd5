"""An independent reference for media (core.volume): the same medium (voxel centres
interpolated trilinearly, zero outside the grid) looked up and marched in plain numpy,
nothing shared with core.volume or core.kernels. Used by tests/core/test_volume.py and
benchmarks/volume_accuracy.py."""
import numpy as np


def trilinear(grid: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K,) float64 the zero-padded trilinear interpolation of ``grid`` (nx, ny, nz) at
    index-space ``points`` (K, 3)."""
    padded = np.pad(grid.astype(np.float64), 2)
    p = points + 2.0
    base = np.floor(p).astype(np.int64)
    inside = np.all((base >= 0) & (base < np.array(padded.shape) - 1), axis=1)
    base = np.clip(base, 0, np.array(padded.shape) - 2)
    f = p - base
    value = np.zeros(len(points))
    for corner in range(8):
        offset = np.array([corner & 1, (corner >> 1) & 1, corner >> 2])
        weight = np.prod(np.where(offset, f, 1.0 - f), axis=1)
        idx = base + offset
        value += weight * padded[idx[:, 0], idx[:, 1], idx[:, 2]]
    return np.where(inside, value, 0.0)


def segment_transmittance(density: np.ndarray, linear: np.ndarray, extinction: float, starts: np.ndarray,
                          ends: np.ndarray, step: float = 0.05) -> np.ndarray:
    """(K,) transmittance along index-space segments ``starts`` -> ``ends`` (K, 3) by a
    midpoint march of at most ``step`` index units; ``linear`` (3, 3) maps index vectors to
    world vectors, ``extinction`` is sigma_t per unit density per world unit."""
    offset = ends - starts
    index_length = np.linalg.norm(offset, axis=1)
    world_length = np.linalg.norm(offset @ linear.T, axis=1)
    steps = max(1, int(np.ceil(index_length.max() / step)))
    depth = np.zeros(len(starts))
    for s in range(steps):
        points = starts + offset * ((s + 0.5) / steps)
        depth += trilinear(density, points) * world_length / steps
    return np.exp(-extinction * depth)
