"""Gutter dilation: results pushed out of each UV island so filtering never reads black.

Images are (H, W) or (H, W, C), row 0 at the bottom, as :mod:`core.sampling.raster`
lays texels out.
"""
from __future__ import annotations

import numpy as np

from .. import kernels


def check_dilate_arguments(image, coverage, margin) -> tuple[np.ndarray, np.ndarray, int]:
    """The arguments of :func:`dilate` (and of its GPU twin) checked: (image, coverage bool, margin int)."""
    if int(margin) != margin or margin < 0:
        raise ValueError(f"dilate: margin must be a non-negative integer, got {margin!r}")
    image = np.asarray(image)
    coverage = np.asarray(coverage, bool)
    if image.ndim not in (2, 3) or coverage.shape != image.shape[:2]:
        raise ValueError(f"dilate: image {image.shape} and coverage {coverage.shape} do not match")
    return image, coverage, int(margin)


def dilate(image: np.ndarray, coverage: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill the gutter: uncovered texels within ``margin`` texels of covered ones.

    Each of ``margin`` passes gives every still-empty texel that has at least one
    filled 8-neighbour the mean of those neighbours; it is then filled for the next
    pass. Texels farther than ``margin`` (in chessboard distance) are set to 0.

    Parameters
    ----------
    image : (H, W, C) or (H, W) float
        Values on covered texels; values elsewhere are ignored.
    coverage : (H, W) bool
    margin : int >= 0

    Returns
    -------
    image : same shape as the input, float32; covered texels are unchanged
    filled : (H, W) bool, texels filled by dilation (disjoint from ``coverage``)
    """
    image, coverage, margin = check_dilate_arguments(image, coverage, margin)
    flat_channels = image.ndim == 2
    height, width = coverage.shape
    values = np.zeros((height * width, 1 if flat_channels else image.shape[2]), np.float32)
    known = coverage.ravel().copy()
    values[known] = image.reshape(height * width, -1)[known]

    # Only the ring next to the filled region changes in a pass, so work on that
    # ring's texel indices rather than on whole-image shifted copies.
    frontier = np.flatnonzero(_grow8(coverage).ravel() & ~known) if margin else np.zeros(0, np.int64)
    module = kernels.compiled()
    if module is not None:
        module.dilate_rings(values, known, frontier.astype(np.int64), width, height, margin)
        margin = 0
    for _ in range(margin):
        if frontier.size == 0:
            break
        neighbour, inside = _neighbours8(frontier, width, height)
        weight = inside & known[neighbour]
        count = weight.sum(axis=1)
        total = np.einsum("fn,fnc->fc", weight.astype(np.float32), values[neighbour])
        values[frontier] = total / count[:, None]  # every frontier texel has count >= 1
        known[frontier] = True
        nxt = neighbour[inside & ~known[neighbour]]
        frontier = np.unique(nxt)
    filled = known.reshape(height, width) & ~coverage
    values = values.reshape(height, width, -1)
    return (values[..., 0] if flat_channels else values), filled


def _grow8(mask: np.ndarray) -> np.ndarray:
    """Texels with a True 8-neighbour (or True themselves)."""
    rows = mask.copy()
    rows[1:] |= mask[:-1]
    rows[:-1] |= mask[1:]
    out = rows.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _neighbours8(index: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of the 8 neighbours of each texel, and which lie inside the image.

    Returns
    -------
    neighbour : (f, 8) int64, clamped into the image where ``inside`` is False
    inside : (f, 8) bool
    """
    dx = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
    dy = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    x = index[:, None] % width + dx
    y = index[:, None] // width + dy
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    neighbour = np.clip(y, 0, height - 1) * width + np.clip(x, 0, width - 1)
    return neighbour, inside
