"""The global direction set D and the shadow regions c_j of the paper (Figure 5).

Every sample uses the same directions (the Method of Dependent Tests), so the table
is one "scattering texture" per direction and every gather is the same lookup.
"""
from __future__ import annotations

import numpy as np

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def spherical_fibonacci(count: int) -> np.ndarray:
    """Nearly uniform unit directions on the whole sphere.

    Parameters
    ----------
    count : int
        Number of directions, >= 1.

    Returns
    -------
    directions : (count, 3) float64
        Unit vectors; each stands for 4*pi/count steradians.
    """
    if count < 1:
        raise ValueError(f"need at least one direction, got {count}")
    i = np.arange(count, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / count
    radius = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = GOLDEN_ANGLE * i
    return np.stack([radius * np.cos(phi), radius * np.sin(phi), z], axis=1)


def random_rotation(seed: int) -> np.ndarray:
    """A uniformly distributed rotation matrix (3, 3) float64 from a seed.

    Rotating the set per bake turns the structured error of a fixed set ("ray
    effects") into noise that differs between bakes.
    """
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def interleaved_rotations(count: int, seed: int = 0) -> np.ndarray:
    """(count, 3, 3) float64: the identity, then ``count - 1`` random rotations (seeded), one
    per texel of an interleaving tile (Keller and Heidrich, "Interleaved Sampling", 2001)."""
    rotations = [np.eye(3)]
    rotations += [random_rotation(0x5EED0000 + 7919 * int(seed) + index) for index in range(1, count)]
    return np.stack(rotations)


def direction_set(count: int, rotate: bool = False, seed: int = 0) -> np.ndarray:
    """D: ``count`` spherical Fibonacci directions, optionally randomly rotated.

    Returns
    -------
    directions : (count, 3) float64
    """
    directions = spherical_fibonacci(count)
    if rotate:
        directions = directions @ random_rotation(seed).T
    return directions


class ShadowRegions:
    """Regions of the sphere around centres c_j, and the paper's weighted lookup.

    Parameters
    ----------
    directions : (N, 3) float64
        The direction set D the table was traced with.
    count : int
        Number of regions (the paper uses 32).

    Attributes
    ----------
    centres : (M, 3) float64
    nearest : (N,) int32
        Index of the region each direction belongs to (largest dot product).
    exponent : float
        k in a_j = max(0, l . c_j)^k, chosen so that the weight falls to one half
        at the angular radius of a region; neighbouring regions then blend instead
        of switching abruptly (the quantisation artefact the paper avoids).
    """

    def __init__(self, directions: np.ndarray, count: int = 32):
        if count < 1:
            raise ValueError(f"need at least one shadow region, got {count}")
        self.centres = spherical_fibonacci(count)
        self.nearest = np.argmax(directions @ self.centres.T, axis=1).astype(np.int32)
        self.count = count
        # A region covers 4*pi/M sr: a cap of angular radius r with cos r = 1 - 2/M.
        cos_radius = 1.0 - 2.0 / count
        if cos_radius <= 0.0:
            self.exponent = 1.0
        else:
            self.exponent = float(np.log(0.5) / np.log(cos_radius))

    def weights(self, light_directions: np.ndarray) -> np.ndarray:
        """a_j for each light direction.

        Parameters
        ----------
        light_directions : (L, 3) float64
            Unit vectors from the sample towards the light.

        Returns
        -------
        weights : (L, M) float64
        """
        cosines = np.clip(light_directions @ self.centres.T, 0.0, None)
        return cosines ** self.exponent
