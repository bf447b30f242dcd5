"""World light through the table's misses: the environment's radiance per direction.

A miss in direction d_i sees the world; the gather needs one radiance per d_i, the
same for every sample, so the environment is reduced to (N, 3) once per lighting.

An equirectangular image is not point-sampled at the N directions: a small bright
patch would be missed or hit by luck. Each d_i gets instead the solid-angle-weighted
mean radiance over its cell (the sphere points whose nearest direction is d_i), so
sum_i L_i * 4*pi/N is the image's integral up to the cells' deviation from 4*pi/N.

Cycles' convention (``kernel/camera/projection.h``, ``direction_to_equirectangular``
with range (-2*pi, pi, -pi, pi); ``kernel/svm/image.h``, ``svm_node_tex_environment``),
for a texture-space direction t = R d:

    u = 0.5 - atan2(t_y, t_x) / (2*pi)        (u = 0.5 looks along +X, u = 0.25 along +Y)
    v = 1 - acos(t_z) / pi                    (v = 1 is the zenith, row 0 the nadir)

looked up with bilinear interpolation at x = u*w - 0.5, y = v*h - 0.5 and periodic
wrapping in both axes (``EnvironmentTextureNode::image_params``: EXTENSION_REPEAT).
Orientation, Mapping rotations and the wrap were confirmed with Cycles bakes (planes
facing +-X, +-Y, +-Z under an off-axis patch agree within 0.3%; tests/blender).
"""
from __future__ import annotations

import numpy as np

from ..outputs.images import bilinear_wrap
from ..scene import Light, World
from ..tolerances import ENV_NEAREST_DOT_SLACK

# The image is box-filtered down to at most this before cells are formed: a pixel of
# 1024 x 512 spans 0.35 degrees, well below a cell even at N = 16384 (~1.6 degrees).
MAX_WORK_WIDTH = 1024
MAX_WORK_HEIGHT = 512
# A smaller image is first resampled (bilinearly, as Cycles looks it up) to at least
# this many rows per sqrt(N): a cell is then ~9 pixels across, so assigning whole
# pixels to cells misplaces little of a cell's area.
WORK_ROWS_PER_SQRT_N = 8.0
# Directions searched for a pixel's nearest: those within this many nominal cell
# diameters in polar angle (a result farther than that is re-checked against all).
SEARCH_BAND_CELLS = 1.5
# Bound on the (pixels x candidates) dot-product blocks: 2^22 float64 = 32 MB.
MAX_BLOCK_ELEMENTS = 1 << 22
# Rows of a large image resampled at once (bounds the float64 copy of a huge HDRI).
DOWNSAMPLE_ROW_CHUNK = 256
# A sun disc in an environment: pixels this many times brighter than the image's mean
# luminance (a sky stays within ~100x of its mean; Cycles' sky sun is ~1e5x), all within
# SUN_MAX_RADIUS of their centre. Its light is taken out of the image and given to a sun
# lamp: in a cell it would light from the cell's direction (degrees off at N = 1024) with
# the cell's area in place of the disc's, and shadow from there too.
SUN_HOT_FACTOR = 1000.0
SUN_MAX_RADIUS = np.radians(5.0)


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
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    if world.image is None:
        radiance = np.broadcast_to(np.asarray(world.color, np.float64)[:3], (len(directions), 3))
    else:
        rotation = np.asarray(world.rotation, np.float64).reshape(3, 3)
        radiance = cell_mean_radiance(world.image, directions @ rotation.T)
    radiance = np.nan_to_num(np.asarray(radiance, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(radiance, 0.0, None)


def has_light(world: World) -> bool:
    """Whether the world sends any light (cheap: no cells are formed)."""
    if getattr(world, "suns", None):
        return True
    values = world.color if world.image is None else world.image
    values = np.asarray(values, np.float64)
    return bool(np.any(np.isfinite(values) & (values > 0)))


def cell_mean_radiance(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Solid-angle-weighted mean of an equirectangular image over each direction's cell.

    Parameters
    ----------
    image : (h, w, 3) float linear RGB, row 0 at the bottom (v = 0, the nadir)
    directions : (N, 3) float64 unit directions in texture space

    Returns
    -------
    radiance : (N, 3) float64, finite and non-negative
    """
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    count = len(directions)
    image = _clean(image)
    if image is None or count == 0:
        return np.zeros((count, 3))
    work = _work_image(image, count)
    height, width = work.shape[:2]
    z_edges = _row_z_edges(height)
    # Equirect pixels of one row all have the same solid angle: dphi * dz.
    row_solid_angle = (2.0 * np.pi / width) * np.diff(z_edges)
    owner = _nearest_for_rows(directions, width, height)
    weights = np.repeat(row_solid_angle, width)
    area = np.bincount(owner, weights=weights, minlength=count)
    flat = work.reshape(-1, 3)
    sums = np.stack([np.bincount(owner, weights=weights * flat[:, c], minlength=count) for c in range(3)], axis=1)
    radiance = np.empty((count, 3))
    filled = area > 0
    radiance[filled] = sums[filled] / area[filled, None]
    if not filled.all():
        # Only when pixels are coarser than cells (a cap on the work size hit with a
        # huge N): the cell's own direction is then the best estimate there is.
        u, v = direction_to_equirectangular(directions[~filled])
        radiance[~filled] = bilinear_wrap(image, u, v)
    return np.clip(np.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def direction_to_equirectangular(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cycles' ``direction_to_equirectangular``: texture coordinates of directions.

    Parameters
    ----------
    directions : (n, 3) float, any length (a zero vector maps to (0, 0) as in Cycles)

    Returns
    -------
    u, v : (n,) float64 each, u in [0, 1), v in [0, 1] (v = 1 at +Z)
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    length = np.linalg.norm(d, axis=1)
    safe = np.where(length > 0, length, 1.0)
    u = 0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi)
    v = 1.0 - np.arccos(np.clip(d[:, 2] / safe, -1.0, 1.0)) / np.pi
    zero = ~(length > 0)
    u[zero] = 0.0
    v[zero] = 0.0
    return u, v


def equirectangular_to_direction(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`direction_to_equirectangular`.

    Parameters
    ----------
    u, v : (n,) float texture coordinates

    Returns
    -------
    directions : (n, 3) float64 unit vectors
    """
    phi = np.pi - 2.0 * np.pi * np.asarray(u, np.float64)
    theta = np.pi * (1.0 - np.asarray(v, np.float64))
    sin_theta = np.sin(theta)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)], axis=-1)


def constant_lookup(image: np.ndarray, vector) -> np.ndarray:
    """What an Environment Texture shows when its Vector input is one constant vector.

    Cycles normalises the vector and maps it like a direction; the zero vector maps to
    (u, v) = (0, 0), the bilinear mix of the four corner pixels.

    Parameters
    ----------
    image : (h, w, 3) float, row 0 at the bottom
    vector : (3,) float

    Returns
    -------
    radiance : (3,) float64, finite and non-negative
    """
    image = _clean(image)
    if image is None:
        return np.zeros(3)
    u, v = direction_to_equirectangular(np.asarray(vector, np.float64).reshape(1, 3))
    return np.clip(np.nan_to_num(bilinear_wrap(image, u, v)[0]), 0.0, None)


def mirror_ball_mean(image: np.ndarray) -> np.ndarray:
    """Mean radiance of a mirror-ball environment image over the sphere.

    A mirror ball maps equal disc areas to equal solid angles (a point at radius r
    reflects the direction 2*asin(r) from the axis, and d(omega)/dA = 4 everywhere),
    so the plain mean of the pixels inside the inscribed disc is the sphere's mean.

    Parameters
    ----------
    image : (h, w, 3) float, row 0 at the bottom

    Returns
    -------
    radiance : (3,) float64, finite and non-negative
    """
    image = _clean(image)
    if image is None:
        return np.zeros(3)
    height, width = image.shape[:2]
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = (np.arange(height) + 0.5) / height * 2.0 - 1.0
    inside = (x[None, :] ** 2 + y[:, None] ** 2) <= 1.0
    if not inside.any():
        return np.asarray(image, np.float64).mean(axis=(0, 1))
    return np.asarray(image, np.float64)[inside].mean(axis=0)


def euler_xyz_matrix(euler) -> np.ndarray:
    """Rotation of an XYZ Euler triple as Cycles' ``euler_to_transform`` builds it.

    Parameters
    ----------
    euler : (3,) float radians

    Returns
    -------
    matrix : (3, 3) float64, Rz @ Ry @ Rx (applied to column vectors)
    """
    x, y, z = (float(a) for a in euler)
    cx, cy, cz = np.cos([x, y, z])
    sx, sy, sz = np.sin([x, y, z])
    return np.array([
        [cy * cz, sy * sx * cz - cx * sz, sy * cx * cz + sx * sz],
        [cy * sz, sy * sx * sz + cx * cz, sy * cx * sz - sx * cz],
        [-sy, cy * sx, cy * cx],
    ])


def _clean(image) -> np.ndarray | None:
    """(h, w, 3) float32 with NaN, Inf and negative radiance set to 0; None if empty."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0 or image.shape[2] == 0:
        return None
    if image.shape[2] < 3:
        image = np.repeat(image[..., :1], 3, axis=2)
    image = np.asarray(image[..., :3], np.float32)
    # Negative radiance is not light; cancelling a bright pixel with it would hide energy.
    finite = np.isfinite(image)
    if finite.all() and not (image < 0).any():
        return image
    return np.where(finite & (image > 0), image, np.float32(0.0))


def _work_image(image: np.ndarray, count: int) -> np.ndarray:
    """The image at the resolution cells are formed at: (H, W, 3) float64."""
    height, width = image.shape[:2]
    if width > MAX_WORK_WIDTH or height > MAX_WORK_HEIGHT:
        image = _box_downsample(image, min(width, MAX_WORK_WIDTH), min(height, MAX_WORK_HEIGHT))
        height, width = image.shape[:2]
    need_rows = min(MAX_WORK_HEIGHT, int(np.ceil(WORK_ROWS_PER_SQRT_N * np.sqrt(count))))
    need_cols = min(MAX_WORK_WIDTH, 2 * need_rows)
    if height < need_rows or width < need_cols:
        # Cycles shows a small image bilinearly interpolated, not as flat pixels:
        # resample it the same way so every cell averages what Cycles would see.
        new_h, new_w = max(height, need_rows), max(width, need_cols)
        u = (np.arange(new_w) + 0.5) / new_w
        v = (np.arange(new_h) + 0.5) / new_h
        uu, vv = np.meshgrid(u, v)
        image = bilinear_wrap(image, uu.ravel(), vv.ravel()).reshape(new_h, new_w, 3)
    return np.asarray(image, np.float64)


def _row_z_edges(height: int) -> np.ndarray:
    """z = cos(theta) at the row boundaries, bottom (-1) to top (+1): (height + 1,) float64."""
    return -np.cos(np.pi * np.arange(height + 1) / height)


def _box_downsample(image: np.ndarray, new_width: int, new_height: int) -> np.ndarray:
    """Area-weighted downsampling that keeps the integral over the sphere.

    Columns are averaged by their overlap in phi, rows by their overlap in
    z = cos(theta): equirect rows near the poles carry less solid angle, and a plain
    row average would overweight them.

    Parameters
    ----------
    image : (h, w, 3) float32
    new_width, new_height : output size, at most (w, h)

    Returns
    -------
    image : (new_height, new_width, 3) float64
    """
    height, width = image.shape[:2]
    column_edges = np.arange(new_width + 1) * (width / new_width)
    columns = np.empty((height, new_width, 3))
    for start in range(0, height, DOWNSAMPLE_ROW_CHUNK):
        block = np.asarray(image[start:start + DOWNSAMPLE_ROW_CHUNK], np.float64)
        columns[start:start + len(block)] = _resample_axis(block, np.arange(width + 1, dtype=np.float64),
                                                           column_edges, axis=1)
    return _resample_axis(columns, _row_z_edges(height), _row_z_edges(new_height), axis=0)


def _resample_axis(values: np.ndarray, edges: np.ndarray, new_edges: np.ndarray, axis: int) -> np.ndarray:
    """Means of a piecewise-constant function over new intervals along one axis.

    Parameters
    ----------
    values : (..., n, ...) float64, constant on [edges[k], edges[k+1]) along ``axis``
    edges : (n + 1,) increasing; new_edges : (m + 1,) increasing, same span

    Returns
    -------
    means : values with ``axis`` of length m
    """
    values = np.moveaxis(values, axis, 0)
    widths = np.diff(edges)
    shape = (-1,) + (1,) * (values.ndim - 1)
    prefix = np.concatenate([np.zeros((1,) + values.shape[1:]),
                             np.cumsum(values * widths.reshape(shape), axis=0)])
    # The integral up to x is piecewise linear: the prefix at the interval's start
    # plus the part of the interval x covers.
    index = np.clip(np.searchsorted(edges, new_edges, side="right") - 1, 0, len(widths) - 1)
    part = (new_edges - edges[index]).reshape(shape)
    integral = prefix[index] + part * values[index]
    integral[-1] = prefix[-1]
    means = np.diff(integral, axis=0) / np.diff(new_edges).reshape(shape)
    return np.moveaxis(means, 0, axis)


def _nearest_for_rows(directions: np.ndarray, width: int, height: int) -> np.ndarray:
    """Index of the nearest direction (largest dot product) for every pixel centre.

    Only directions whose polar angle is within a band around a block of rows are
    compared; a pixel whose best candidate is farther away than the band could
    still have a nearer direction outside it and is checked against all of them.

    Parameters
    ----------
    directions : (N, 3) float64 unit directions in texture space
    width, height : size of the equirect grid, row 0 at the bottom

    Returns
    -------
    owner : (height * width,) int64, pixels in row-major order
    """
    count = len(directions)
    u = (np.arange(width) + 0.5) / width
    phi = np.pi - 2.0 * np.pi * u
    row_theta = np.pi * (1.0 - (np.arange(height) + 0.5) / height)
    polar = np.arccos(np.clip(directions[:, 2], -1.0, 1.0))
    order = np.argsort(polar)
    polar_sorted = polar[order]
    band = min(np.pi, SEARCH_BAND_CELLS * np.sqrt(4.0 * np.pi / count))
    cos_band = np.cos(band)
    owner = np.empty(height * width, np.int64)
    rows_per_block = max(1, (1 << 15) // width)
    for first in range(0, height, rows_per_block):
        rows = np.arange(first, min(height, first + rows_per_block))
        theta = row_theta[rows]
        lo = np.searchsorted(polar_sorted, theta.min() - band, side="left")
        hi = np.searchsorted(polar_sorted, theta.max() + band, side="right")
        candidates = order[lo:hi]
        sin_t = np.sin(theta)[:, None]
        points = np.stack([(sin_t * np.cos(phi)).ravel(), (sin_t * np.sin(phi)).ravel(),
                           np.repeat(np.cos(theta), width)], axis=1)
        span = slice(rows[0] * width, (rows[-1] + 1) * width)
        if len(candidates) == 0:
            owner[span] = _nearest(points, directions, np.arange(count))[0]
            continue
        best, dot = _nearest(points, directions, candidates)
        # Every direction outside the band is at least `band` away in angle.
        unsure = dot < cos_band + ENV_NEAREST_DOT_SLACK
        if unsure.any():
            best[unsure] = _nearest(points[unsure], directions, np.arange(count))[0]
        owner[span] = best
    return owner


def _nearest(points: np.ndarray, directions: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest of ``directions[candidates]`` to each point.

    Returns
    -------
    index : (n,) int64 into ``directions``; dot : (n,) float64 the largest dot product
    """
    subset = directions[candidates]
    index = np.empty(len(points), np.int64)
    dot = np.empty(len(points))
    step = max(1, MAX_BLOCK_ELEMENTS // max(1, len(subset)))
    for start in range(0, len(points), step):
        dots = points[start:start + step] @ subset.T
        local = np.argmax(dots, axis=1)
        index[start:start + step] = candidates[local]
        dot[start:start + step] = dots[np.arange(len(local)), local]
    return index, dot


def split_sun(image: np.ndarray, name: str = "world sun") -> tuple[np.ndarray, Light | None]:
    """Take a sun disc out of an equirectangular image, as a sun lamp of the same light.

    The disc is the pixels above ``SUN_HOT_FACTOR`` times the mean luminance and their
    neighbours (the partly covered pixels of its rim). Their radiance above the sky
    around them (the median of the ring one pixel further out) goes to the lamp: its
    irradiance at normal incidence is that excess integrated over the pixels' solid
    angles, its direction the excess-weighted mean direction, its angle the diameter of
    a disc of the hot pixels' solid angle. The pixels keep the sky's level. Nothing is
    split when there is no such disc or it is not compact (a bright band, a sun cut by
    the image's u = 0 edge is still one disc: neighbours wrap around in u).

    Parameters
    ----------
    image : (h, w, 3) float linear RGB, row 0 at the bottom

    Returns
    -------
    image : (h, w, 3) float32, a copy without the disc (or the cleaned input, if none)
    sun : a 'SUN' :class:`Light` of strength 1 and colour its irradiance, or None
    """
    clean = _clean(image)
    if clean is None:
        return np.zeros((0, 0, 3), np.float32), None
    height, width = clean.shape[:2]
    luminance = clean @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    mean = float(luminance.mean())
    hot = luminance > SUN_HOT_FACTOR * mean if mean > 0 else np.zeros_like(luminance, bool)
    if not hot.any():
        return clean, None
    disc = _grow(hot)
    ring = _grow(disc) & ~disc
    z_edges = _row_z_edges(height)
    solid_angle = np.broadcast_to(((2.0 * np.pi / width) * np.diff(z_edges))[:, None], (height, width))
    rows, columns = np.nonzero(disc)
    u = (columns + 0.5) / width
    v = (rows + 0.5) / height
    directions = equirectangular_to_direction(u, v)
    sky = np.median(clean[ring], axis=0) if ring.any() else np.zeros(3, np.float32)
    excess = np.clip(np.asarray(clean[disc], np.float64) - sky, 0.0, None) * solid_angle[disc][:, None]
    weight = excess.sum(axis=1)
    if not weight.sum() > 0:
        return clean, None
    axis = (directions * weight[:, None]).sum(axis=0)
    axis /= np.linalg.norm(axis)
    if np.min(directions[hot[disc]] @ axis) < np.cos(SUN_MAX_RADIUS):
        return clean, None
    hot_solid_angle = float(solid_angle[hot].sum())
    angle = 2.0 * float(np.arccos(np.clip(1.0 - hot_solid_angle / (2.0 * np.pi), -1.0, 1.0)))
    residual = np.array(clean, np.float32)
    residual[disc] = np.minimum(residual[disc], sky.astype(np.float32))
    sun = Light(name=name, kind="SUN", color=excess.sum(axis=0), strength=1.0, direction=-axis, angle=angle)
    return residual, sun


def _grow(mask: np.ndarray) -> np.ndarray:
    """``mask`` with its 8 neighbours added, wrapping in u (columns) and clamped in v (rows)."""
    grown = mask.copy()
    for row_shift in (-1, 0, 1):
        shifted = np.roll(mask, row_shift, axis=0)
        if row_shift == 1:
            shifted[0] = False
        elif row_shift == -1:
            shifted[-1] = False
        for column_shift in (-1, 0, 1):
            grown |= np.roll(shifted, column_shift, axis=1)
    return grown
