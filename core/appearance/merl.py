"""MERL isotropic BRDF tables: the file format, its lookup, and filling it from scattered samples.

The table
---------
A MERL table holds an isotropic BRDF on a regular grid of the Rusinkiewicz half/difference
angles (theta_h, theta_d, phi_d), 90 x 90 x 180 cells, three colour channels. In memory
(everything this module takes or returns) it is a ``(3, 90, 90, 180)`` float64 array of
physical BRDF values in 1/sr, indexed ``[channel, theta_h_index, theta_d_index, phi_d_index]``;
a cell with no data (its light or view below the horizon) holds ``NO_DATA`` (-1.0) (in every
channel, as the fill and MERL's own files mark them; a file read with one negative channel
keeps the others).

- theta_h index: ``floor(sqrt(theta_h / (pi/2) * 90 * 90))`` clamped to [0, 89], 0 for
  theta_h <= 0. The square root packs the cells near the specular peak (theta_h = 0).
- theta_d index: ``floor(theta_d / (pi/2) * 90)`` clamped to [0, 89].
- phi_d index: reciprocity makes (theta_d, phi_d) and (theta_d, phi_d + pi) the same pair
  with light and view swapped, so phi_d is folded into [0, pi) (pi is added when phi_d < 0),
  then ``floor(phi_d / pi * 180)`` clamped to [0, 179].

The half/difference angles of a (light, view) pair in the tile's frame (z the normal):
h = normalize(light + view) has spherical angles (theta_h, phi_h); the light rotated by
-phi_h about z and then by -theta_h about y (the binormal) has spherical angles
(theta_d, phi_d). phi_h is dropped: the table is isotropic.

The file
--------
Three little-endian int32 ``(90, 90, 180)`` (theta_h, theta_d, phi_d resolutions), then
3 x 1,458,000 little-endian float64, channel after channel (all red, then green, then blue),
cell ``phi_d_index + theta_d_index * 180 + theta_h_index * 180 * 90`` within a channel,
which is the C order of the in-memory array. Readers multiply the stored numbers by the
channel scales ``CHANNEL_SCALES`` (1/1500, 1.15/1500, 1.66/1500), so the writer divides by
them; a negative stored number means "no data" (written as -1.0). The reference reader
accepts any header whose product is 1,458,000; :func:`read_merl` wants exactly
(90, 90, 180), the only order any MERL file has, since another would be misread.

Filling the table from samples
------------------------------
:func:`fill_from_samples` turns ~10^4 scattered (light, view, BRDF) samples (a simulated
tile seen from a set of light and view directions) into the 1.458 million cells by kernel
regression in the MERL parameterisation, in cell-index units:
``u = sqrt(theta_h / (pi/2)) * 90``, ``v = theta_d / (pi/2) * 90``, ``w = phi_d / pi * 180``,
w periodic with period 180 (the reciprocity fold: phi_d near 0 and near 180 are
neighbours); cell centres sit at half-integers. A cell's value is the Gaussian-weighted
mean of the samples around it (Nadaraya-Watson), each sample also weighted by
``light_z * view_z``, with a bandwidth of its own: the smallest rung of a geometric ladder
(``FILL_SIGMAS``, sigma along theta_h; ``FILL_ASPECT`` = 2 times that along theta_d and
phi_d) whose kernel holds ``FILL_MIN_WEIGHT`` = 6 samples' worth of weight, blended with the
rung below so that the bandwidth, and the table, change smoothly from cell to cell. Samples
of an anisotropic tile that share (theta_h, theta_d, phi_d) but differ in phi_h are
averaged: the isotropic table of the tile.

It runs as a normalised convolution: the samples are splatted onto the grid (trilinearly,
which keeps a sample's position to second order), then each rung is a separable Gaussian
blur, three dense float32 matrix products (along theta_h and theta_d truncated at the
grid's edges, along phi_d circulant). All of it is numpy and BLAS, its cost independent of
the number of samples, with no neighbour search and no per-cell loop, so there is neither
scipy nor a compiled kernel. 10^4 samples fill in 1.8-2.2 s on 2 (shared) cores.

Why this method, from measurements (100 x 100 Fibonacci hemisphere pairs; relative RMSE of
:func:`evaluate` at 2,000 uniform random pairs in cells with data, against the analytic
BRDF; in brackets the floor, a table of the exact values at the cell centres):

- A constant BRDF fills back exactly (every cell is a weighted mean; 2e-6 from float32).
- Lambert + Blinn-Phong 50: 0.064 (0.012). GGX alpha 0.2 with Schlick Fresnel and Smith
  masking, + Lambert: 0.117 (0.018); alpha 0.5: 0.090 (0.016); anisotropic GGX (0.15, 0.4)
  against its phi_h average: 0.117 (0.018).
- An isotropic kernel (aspect 1) gives 0.100 / 0.117 / 0.078 / 0.110 on the same four:
  the lobe's top (theta_h index < 30) holds ~300 of the 10^4 samples, none below index 10,
  and a round kernel wide enough to reach them there blurs theta_h, along which BRDFs are
  sharpest. Aspect 3 takes Phong to 0.051 but GGX to 0.17: a kernel that long along theta_d
  mixes in grazing samples, where microfacet BRDFs grow like 1/(cos theta_i cos theta_o).
  The ``light_z * view_z`` weights (the BRDF's weight in rendering) damp exactly those
  (GGX 0.2 at aspect 2: 0.136 without, 0.117 with) and keep constants exact. min_weight
  from 3 to 10 changes these by a few per cent.
- Random pairs seldom land on the lobe's top, which is where the error is: per cell,
  against the exact centre values, the relative RMS error is 25-30% (Phong) and 50-57%
  (GGX 0.2) over theta_h index < 20, 2% and 10% past index 45.
- That is the samples' density more than the method: 300 x 300 pairs halve the errors.

Cells whose centre's light or view is at or below the horizon (``~valid_cells()``) get
``NO_DATA``, as in the MERL measurements.
"""
from __future__ import annotations

import os

import numpy as np

from ..outputs.atomic import atomic_file

THETA_H_RES = 90
THETA_D_RES = 90
PHI_D_RES = 180
CELLS = THETA_H_RES * THETA_D_RES * PHI_D_RES  # 1,458,000
TABLE_SHAPE = (3, THETA_H_RES, THETA_D_RES, PHI_D_RES)
# What readers multiply the stored numbers by, per channel (red, green, blue).
CHANNEL_SCALES = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
NO_DATA = -1.0
HEADER = np.array([THETA_H_RES, THETA_D_RES, PHI_D_RES], dtype="<i4")
FILE_BYTES = HEADER.nbytes + 3 * CELLS * 8

# The fill's bandwidth ladder (Gaussian sigma along theta_h, in cell-index units), how many
# samples' worth of kernel weight a cell needs before its bandwidth stops growing, the
# kernel's length along theta_d and phi_d over its length along theta_h, and a cap on the
# latter (past it the kernel is flat across the table anyway). Chosen by measurement: see
# the module's docstring.
FILL_SIGMAS = (0.75, 1.1, 1.6, 2.4, 3.5, 5.0, 7.5, 11.0, 16.0, 24.0, 36.0, 54.0, 80.0, 120.0)
FILL_MIN_WEIGHT = 6.0
FILL_ASPECT = 2.0
FILL_SIGMA_CAP = 240.0

_HALF_PI = np.pi / 2.0


# --- angles ------------------------------------------------------------------------------


def _directions(name, array, count=None):
    """``array`` as a finite (K, 3) float64 array, or ValueError."""
    d = np.asarray(array, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"{name} must be a (K, 3) array of directions, got shape {d.shape}")
    if count is not None and d.shape[0] != count:
        raise ValueError(f"{name} has {d.shape[0]} directions, expected {count}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} holds NaN or infinite values")
    return d


def _unit(d):
    """Rows of ``d`` scaled to unit length; zero rows stay zero."""
    n = np.sqrt(np.einsum("ij,ij->i", d, d))
    return d / np.where(n > 0.0, n, 1.0)[:, None]


def _half_difference(light, view):
    """half_difference without the checks. A pair whose half vector vanishes (light = -view,
    never the case above the horizon) gets h = z rather than NaN."""
    l = _unit(light)
    h = _unit(l + _unit(view))
    h[~np.any(h != 0.0, axis=1)] = (0.0, 0.0, 1.0)
    rho = np.hypot(h[:, 0], h[:, 1])  # sin(theta_h)
    theta_h = np.arctan2(rho, h[:, 2])
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    # cos and sin of phi_h straight from h; at theta_h = 0, phi_h = atan2(0, 0) = 0.
    safe = np.where(rho > 0.0, rho, 1.0)
    c = np.where(rho > 0.0, h[:, 0] / safe, 1.0)
    s = np.where(rho > 0.0, h[:, 1] / safe, 0.0)
    # By -phi_h about z ...
    x1 = l[:, 0] * c + l[:, 1] * s
    y1 = l[:, 1] * c - l[:, 0] * s
    z1 = l[:, 2]
    # ... then by -theta_h about y.
    x2 = x1 * h[:, 2] - z1 * rho
    z2 = x1 * rho + z1 * h[:, 2]
    theta_d = np.arctan2(np.hypot(x2, y1), z2)
    phi_d = np.arctan2(y1, x2)
    return theta_h, phi_h, theta_d, phi_d


def half_difference(light, view):
    """The Rusinkiewicz half/difference angles of (light, view) pairs.

    Parameters
    ----------
    light, view : (K, 3) float64
        Unit directions in the tile's frame (z the surface normal); normalised here anyway.

    Returns
    -------
    theta_h, phi_h, theta_d, phi_d : (K,) float64
        Radians. theta_h in [0, pi], phi_h in (-pi, pi], theta_d in [0, pi],
        phi_d in (-pi, pi] (not folded; :func:`cell_index` folds it).
    """
    light = _directions("light", light)
    view = _directions("view", view, light.shape[0])
    return _half_difference(light, view)


def direction_pair(theta_h, theta_d, phi_d, phi_h=0.0):
    """The (light, view) pair of given half/difference angles: the inverse of
    :func:`half_difference`.

    Parameters
    ----------
    theta_h, theta_d, phi_d, phi_h : float64 arrays (or scalars) broadcasting to a shape S
        Radians; phi_h defaults to 0 (the table is isotropic: any phi_h stands for all).

    Returns
    -------
    light, view : S + (3,) float64
        Unit directions in the tile's frame; either may be below the horizon (z <= 0).
    """
    th, td, pd, ph = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d, phi_h)))
    sd = np.sin(td)
    dx, dy, dz = sd * np.cos(pd), sd * np.sin(pd), np.cos(td)
    ct, st = np.cos(th), np.sin(th)
    cp, sp = np.cos(ph), np.sin(ph)

    def to_tile(x, y, z):
        # By theta_h about y, then by phi_h about z: the rotations of half_difference undone.
        x1, z1 = x * ct + z * st, z * ct - x * st
        return np.stack([x1 * cp - y * sp, x1 * sp + y * cp, z1], axis=-1)

    # In the half vector's frame the view is the light mirrored about the half vector (z).
    return to_tile(dx, dy, dz), to_tile(-dx, -dy, dz)


def _theta_h_index(theta_h):
    # Same operations, in the same order, as the reference reader, so both agree on every
    # cell boundary.
    t = np.sqrt(np.maximum(theta_h, 0.0) / _HALF_PI * THETA_H_RES * THETA_H_RES)
    return np.where(theta_h <= 0.0, 0, np.clip(np.floor(t), 0, THETA_H_RES - 1)).astype(np.int64)


def _theta_d_index(theta_d):
    return np.clip(np.trunc(theta_d / _HALF_PI * THETA_D_RES), 0, THETA_D_RES - 1).astype(np.int64)


def _phi_d_index(phi_d):
    folded = np.where(phi_d < 0.0, phi_d + np.pi, phi_d)
    return np.clip(np.trunc(folded / np.pi * PHI_D_RES), 0, PHI_D_RES - 1).astype(np.int64)


def _cell_index(theta_h, theta_d, phi_d):
    return (_theta_h_index(theta_h) * THETA_D_RES + _theta_d_index(theta_d)) * PHI_D_RES + _phi_d_index(phi_d)


def cell_index(theta_h, theta_d, phi_d):
    """The flat cell of half/difference angles, as the MERL reference reader finds it.

    Parameters
    ----------
    theta_h, theta_d, phi_d : float64 arrays (or scalars) broadcasting to a shape S
        Radians; phi_d in (-pi, pi] as :func:`half_difference` gives it (folded here).

    Returns
    -------
    index : S int64
        ``phi_d_index + theta_d_index * 180 + theta_h_index * 180 * 90``, in [0, 1458000),
        the index into one channel of the table flattened in C order.
    """
    th, td, pd = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d)))
    if not (np.all(np.isfinite(th)) and np.all(np.isfinite(td)) and np.all(np.isfinite(pd))):
        raise ValueError("cell_index needs finite angles (got NaN or infinity)")
    return _cell_index(th, td, pd)


def _centre_coordinates():
    """The cells' centres along each axis, in radians: (90,), (90,), (180,) float64."""
    theta_h = ((np.arange(THETA_H_RES) + 0.5) / THETA_H_RES) ** 2 * _HALF_PI
    theta_d = (np.arange(THETA_D_RES) + 0.5) / THETA_D_RES * _HALF_PI
    phi_d = (np.arange(PHI_D_RES) + 0.5) / PHI_D_RES * np.pi
    return theta_h, theta_d, phi_d


def cell_centres():
    """Each cell's representative angles: its centre in each parameter's own indexing.

    Returns
    -------
    theta_h, theta_d, phi_d : (1458000,) float64
        Radians, in flat cell order (``cell_index(*cell_centres())`` is ``arange(1458000)``):
        ``theta_h = ((i + 0.5) / 90)**2 * pi/2`` (the centre in the square-root indexing),
        ``theta_d = (j + 0.5) / 90 * pi/2``, ``phi_d = (k + 0.5) / 180 * pi``.
    """
    th, td, pd = np.meshgrid(*_centre_coordinates(), indexing="ij")
    return th.ravel(), td.ravel(), pd.ravel()


def valid_cells():
    """Which cells have data: both directions of the cell centre's pair above the horizon.

    Returns
    -------
    valid : (90, 90, 180) bool
        Indexed like one channel of the table.
    """
    th, td, pd = _centre_coordinates()
    th, td, pd = th[:, None, None], td[None, :, None], pd[None, None, :]
    # z of direction_pair's light and view, without building them: the light's is
    # cos(th)cos(td) - sin(th)sin(td)cos(pd), the view's has + instead.
    a = np.cos(th) * np.cos(td)
    b = np.sin(th) * np.sin(td) * np.abs(np.cos(pd))
    return (a - b) > 0.0


# --- the file ------------------------------------------------------------------------------


def _table(name, table):
    t = np.asarray(table, dtype=np.float64)
    if t.shape != TABLE_SHAPE:
        raise ValueError(f"{name} must have shape {TABLE_SHAPE} (channel, theta_h, theta_d, phi_d), got {t.shape}")
    return t


def _stored_numbers(table):
    """The numbers a file stores for a physical table: divided by the channel scales, each
    nudged by an ulp where that makes a reader's ``stored * scale`` give back the value
    exactly (so a table read from a MERL file is written back to the same values: none of
    2.2e7 tried missed; others come back within an ulp), and -1 for no data."""
    scales = np.broadcast_to(CHANNEL_SCALES[:, None, None, None], TABLE_SHAPE)
    stored = table / scales
    off = np.nonzero((stored * scales != table) & (table >= 0.0))
    if off[0].size:
        s, t, r = scales[off], table[off], stored[off]
        up, down = np.nextafter(r, np.inf), np.nextafter(r, -np.inf)
        stored[off] = np.where(up * s == t, up, np.where(down * s == t, down, r))
    stored[table < 0.0] = NO_DATA
    return stored


def write_merl(path, table):
    """Write a table as a MERL ``.binary`` file, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The file; written to a temporary file in the same folder, then renamed over it, so
        a reader never sees half a file.
    table : (3, 90, 90, 180) float64
        RGB BRDF values in 1/sr; ``NO_DATA`` (-1.0) marks a cell with no data.

    Raises
    ------
    ValueError
        Wrong shape, NaN or infinite values, or negative values other than -1 (nothing is
        written).
    """
    t = _table("table", table)
    if not np.all(np.isfinite(t)):
        raise ValueError(f"table holds {np.count_nonzero(~np.isfinite(t))} NaN or infinite values; not written")
    bad = (t < 0.0) & (t != NO_DATA)
    if np.any(bad):
        raise ValueError(f"table holds {np.count_nonzero(bad)} negative values other than the no-data "
                         f"marker {NO_DATA}, e.g. {t[bad][0]!r}; not written")
    data = _stored_numbers(t).astype("<f8", copy=False)
    path = os.fspath(path)
    with atomic_file(path) as f:
        f.write(HEADER.tobytes())
        f.write(data.tobytes())


def read_merl(path):
    """Read a MERL ``.binary`` file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    table : (3, 90, 90, 180) float64
        RGB BRDF values in 1/sr (the stored numbers times ``CHANNEL_SCALES``); cells stored
        negative (no data) are ``NO_DATA`` (-1.0).

    Raises
    ------
    ValueError
        A header other than (90, 90, 180) (the reference reader checks only that the product
        is 1,458,000; no MERL file has another order, and one would be misread), a file
        shorter (truncated) or longer than 12 + 3 * 1458000 * 8 bytes, or NaN/infinite data.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        data = f.read(FILE_BYTES + 1)
    if len(data) < HEADER.nbytes:
        raise ValueError(f"{path}: not a MERL BRDF file: {len(data)} bytes, less than its 12-byte header")
    dims = tuple(int(d) for d in np.frombuffer(data, dtype="<i4", count=3))
    if dims != tuple(HEADER):
        product = int(np.prod(np.array(dims, dtype=np.int64)))
        raise ValueError(f"{path}: not a MERL BRDF file: header dimensions {dims} (product {product}), "
                         f"expected {tuple(int(d) for d in HEADER)} (product {CELLS})")
    if len(data) < FILE_BYTES:
        raise ValueError(f"{path}: MERL BRDF file truncated: {len(data)} bytes, expected {FILE_BYTES} "
                         f"(12 header bytes and 3 x {CELLS} float64)")
    if len(data) > FILE_BYTES:
        raise ValueError(f"{path}: MERL BRDF file has bytes after its data: more than the {FILE_BYTES} expected")
    stored = np.frombuffer(data, dtype="<f8", count=3 * CELLS, offset=HEADER.nbytes).reshape(TABLE_SHAPE)
    bad = np.count_nonzero(~np.isfinite(stored))
    if bad:
        raise ValueError(f"{path}: MERL BRDF file holds {bad} NaN or infinite values")
    table = stored * CHANNEL_SCALES[:, None, None, None]
    table[stored < 0.0] = NO_DATA
    return table


# --- lookup ------------------------------------------------------------------------------


def evaluate(table, light, view):
    """The table's BRDF at (light, view) pairs, looked up as the reference reader does
    (the cell the pair falls in, no interpolation).

    Parameters
    ----------
    table : (3, 90, 90, 180) float64
        As :func:`read_merl` returns it.
    light, view : (K, 3) float64
        Unit directions in the tile's frame (z the normal).

    Returns
    -------
    brdf : (K, 3) float64
        RGB in 1/sr; 0 where the light or the view is at or below the horizon, and 0 where
        the pair falls in a no-data cell (the reference reader would return the negative
        marker there).
    """
    t = _table("table", table)
    light = _directions("light", light)
    view = _directions("view", view, light.shape[0])
    theta_h, _, theta_d, phi_d = _half_difference(light, view)
    out = t.reshape(3, CELLS)[:, _cell_index(theta_h, theta_d, phi_d)].T
    out = np.maximum(out, 0.0)
    out[(light[:, 2] <= 0.0) | (view[:, 2] <= 0.0)] = 0.0
    return out


# --- filling from samples --------------------------------------------------------------------


def _index_coordinates(light, view):
    """The samples' continuous positions in the cell-index space: (K,) u, v, w float64."""
    theta_h, _, theta_d, phi_d = _half_difference(light, view)
    u = np.sqrt(theta_h / _HALF_PI) * THETA_H_RES
    v = theta_d / _HALF_PI * THETA_D_RES
    w = np.mod(phi_d / np.pi * PHI_D_RES, PHI_D_RES)
    return u, v, w


def _splat(u, v, w, values, cosines):
    """Trilinear splat of the samples onto the cell centres.

    Returns (5, 90, 90, 180) float64: the sums of ``cosines * value`` of the three channels,
    of ``cosines``, and of 1 (the sample count), each times the trilinear weight."""
    def corners(x, n, periodic):
        t = x - 0.5  # cell centres sit at half-integers
        i0 = np.floor(t)
        f = t - i0
        i0 = i0.astype(np.int64)
        i1 = i0 + 1
        if periodic:
            i0, i1 = np.mod(i0, n), np.mod(i1, n)
        else:
            i0, i1 = np.clip(i0, 0, n - 1), np.clip(i1, 0, n - 1)
        return (i0, 1.0 - f), (i1, f)

    per_sample = np.concatenate([values * cosines[:, None], cosines[:, None], np.ones((len(u), 1))], axis=1)
    moments = np.zeros((5, CELLS))
    for iu, wu in corners(u, THETA_H_RES, False):
        for iv, wv in corners(v, THETA_D_RES, False):
            for iw, ww in corners(w, PHI_D_RES, True):
                flat = (iu * THETA_D_RES + iv) * PHI_D_RES + iw
                weight = wu * wv * ww
                for c in range(5):
                    moments[c] += np.bincount(flat, weights=weight * per_sample[:, c], minlength=CELLS)
    return moments.reshape(5, THETA_H_RES, THETA_D_RES, PHI_D_RES)


def _gaussian_matrix(n, sigma, periodic):
    """(n, n) float32: the Gaussian of ``sigma`` cells between cell centres, 1 at distance 0;
    circulant (all periodic images summed) when ``periodic``."""
    d = (np.arange(n)[:, None] - np.arange(n)[None, :]).astype(np.float64)
    if not periodic:
        return np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
    images = int(np.ceil(6.0 * sigma / n)) + 1
    return sum(np.exp(-0.5 * ((d + m * n) / sigma) ** 2) for m in range(-images, images + 1)).astype(np.float32)


def _blur(moments, sigma_h, sigma_d):
    """``moments`` (C, 90, 90, 180) float32 convolved with a Gaussian of ``sigma_h`` cells
    along theta_h and ``sigma_d`` cells along theta_d and phi_d: three matrix products, along
    theta_h and theta_d with the grid's edges truncating the kernel, along phi_d periodically.
    float32 halves the time; the fill's ratios need nowhere near float64's precision."""
    c = moments.shape[0]
    gh = _gaussian_matrix(THETA_H_RES, sigma_h, False)
    gd = _gaussian_matrix(THETA_D_RES, sigma_d, False)
    gp = _gaussian_matrix(PHI_D_RES, sigma_d, True)
    out = np.matmul(gh, moments.reshape(c, THETA_H_RES, THETA_D_RES * PHI_D_RES))
    out = np.matmul(gd, out.reshape(c * THETA_H_RES, THETA_D_RES, PHI_D_RES))
    out = out.reshape(-1, PHI_D_RES) @ gp  # gp is symmetric
    return out.reshape(moments.shape)


def fill_from_samples(light, view, values, *, min_weight=FILL_MIN_WEIGHT, aspect=FILL_ASPECT, sigmas=FILL_SIGMAS):
    """An isotropic MERL table from scattered BRDF samples (the method and why: the module's
    docstring).

    Parameters
    ----------
    light, view : (K, 3) float64
        Unit directions of the samples in the tile's frame, both above the horizon (z > 0).
        Typically every pair of a light set and a view set (e.g. 100 x 100). Samples of an
        anisotropic tile that differ only in phi_h are averaged.
    values : (K, 3) float64
        The samples' RGB BRDF in 1/sr, >= 0.
    min_weight : float
        How many samples' worth of kernel weight a cell gathers before its bandwidth stops
        growing: larger is smoother (and averages more noise away), smaller is sharper.
    aspect : float
        The kernel's width along theta_d and phi_d over its width along theta_h.
    sigmas : sequence of float
        The theta_h bandwidths (Gaussian sigma in cell-index units) to try, increasing; the
        last should reach across the table so that every cell gets a value.

    Returns
    -------
    table : (3, 90, 90, 180) float64
        BRDF values in 1/sr; ``NO_DATA`` (-1.0) in the cells whose centre's light or view is
        at or below the horizon (``~valid_cells()``), a value >= 0 in every other cell.

    Raises
    ------
    ValueError
        Wrong shapes, no samples, NaN/infinite input, a direction at or below the horizon,
        a negative value, or a bad ``sigmas``/``min_weight``/``aspect``.
    """
    light = _directions("light", light)
    k = light.shape[0]
    view = _directions("view", view, k)
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (k, 3):
        raise ValueError(f"values must have shape ({k}, 3) (RGB per sample), got {values.shape}")
    if k == 0:
        raise ValueError("no samples to fill the table from")
    if not np.all(np.isfinite(values)):
        raise ValueError("values hold NaN or infinite BRDF values")
    if np.any(values < 0.0):
        raise ValueError(f"values hold {np.count_nonzero(values < 0.0)} negative BRDF values")
    light, view = _unit(light), _unit(view)
    below = ~((light[:, 2] > 0.0) & (view[:, 2] > 0.0))
    if np.any(below):
        raise ValueError(f"{np.count_nonzero(below)} samples have the light or the view at or below the horizon")
    sigmas = np.asarray(sigmas, dtype=np.float64)
    if sigmas.ndim != 1 or sigmas.size == 0 or sigmas[0] <= 0.0 or np.any(np.diff(sigmas) <= 0.0):
        raise ValueError(f"sigmas must be positive and increasing, got {sigmas}")
    if not (min_weight > 0.0 and aspect > 0.0):
        raise ValueError(f"min_weight and aspect must be positive, got {min_weight} and {aspect}")

    moments = _splat(*_index_coordinates(light, view), values, light[:, 2] * view[:, 2]).astype(np.float32)
    valid = valid_cells()

    def rung(i, channels=slice(None)):
        return _blur(moments[channels], sigmas[i], min(aspect * sigmas[i], FILL_SIGMA_CAP))

    # The narrow rungs no cell fills need only their weights (a fifth of the work) to be
    # skipped; the rung before the first one that fills a cell is computed in full for the
    # blend below.
    first = 0
    while first < len(sigmas) - 1 and not np.any(rung(first, slice(4, 5))[0][valid] >= min_weight):
        first += 1
    table = np.full((3,) + valid.shape, NO_DATA)
    todo = valid.copy()
    previous = None
    for i in range(max(first - 1, 0), len(sigmas)):
        blurred = rung(i).astype(np.float64)
        count = blurred[4]
        with np.errstate(invalid="ignore", divide="ignore"):
            value = blurred[:3] / blurred[3]
        reached = todo & (count >= min_weight)
        if previous is None:
            table[:, reached] = value[:, reached]
        else:
            # Blend with the previous rung where the count crossed min_weight between the
            # two, so that the bandwidth, and the table, vary smoothly from cell to cell.
            c0, v0 = previous[0][reached], previous[1][:, reached]
            c1, v1 = count[reached], value[:, reached]
            t = np.clip((min_weight - c0) / (c1 - c0), 0.0, 1.0)
            v0 = np.where(np.isfinite(v0), v0, v1)
            table[:, reached] = v0 + t * (v1 - v0)
        todo &= ~reached
        if not todo.any():
            break
        previous = (count, value)
    if todo.any():
        # Fewer samples than min_weight in all: the widest kernel's mean, or the samples'
        # cosine-weighted mean where even that underflowed.
        cosines = light[:, 2] * view[:, 2]
        mean = (values * cosines[:, None]).sum(axis=0) / cosines.sum()
        fallback = np.where(np.isfinite(value), value, mean[:, None, None, None])
        table[:, todo] = fallback[:, todo]
    return table
