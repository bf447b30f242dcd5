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
(``FILL_SIGMAS``, sigma along theta_h; ``FILL_ASPECT`` = 2 times that along theta_d; along
phi_d, on theta_h row u, that times ``(FILL_PHI_ARC_ROW / u)^2`` with FILL_PHI_ARC_ROW =
160) whose kernel holds ``FILL_MIN_WEIGHT`` = 10 samples' worth of weight, blended with the
rung below so that the bandwidth, and the table, change smoothly from cell to cell. Samples
of an anisotropic tile that share (theta_h, theta_d, phi_d) but differ in phi_h are
averaged: the isotropic table of the tile.

The width along phi_d follows the geometry: a step of phi_d turns the pair about the half
vector, which, an isotropic BRDF ignoring turns about the normal, moves it by about
theta_h * delta_phi_d; and theta_h grows like u^2. So the kernel spans the same arc on every
row, 3.2 times aspect (of the theta_h width) on the last row, the whole of phi_d near the
peak, where every phi_d is nearly the same pair and the samples are few.

It runs as a normalised convolution: the samples are splatted onto the grid (trilinearly,
which keeps a sample's position to second order), then each rung is a Gaussian blur, three
dense float32 matrix products (along theta_h and theta_d truncated at the grid's edges,
along phi_d circulant, one matrix per theta_h row). The same linear, positive map applies
to the values and to the weights, so constants stay exact. All of it is numpy and BLAS, its
cost independent of the number of samples, with no neighbour search and no per-cell loop,
so there is neither scipy nor a compiled kernel. 10^4 samples fill in 1.4-2.4 s on 2 (shared)
cores.

Choosing the directions
-----------------------
Which pairs the samples are matters as much as the fill: :func:`merl_direction_sets` picks
them. Fibonacci light and view sets (``gonio.hemisphere_directions``) put no 100 x 100 pair
below theta_h row 10 (1.1 degrees) and ~40 in rows 10-19, since uniform pairs fall in row u
with density ~u^3 while every row has as many cells. The same set for lights and views (what
the BRDF job did) also wastes half its pairs: (a, b) and (b, a) fill the same cell (with the
old fill, Phong 0.076 against 0.059 from a view set turned 1 radian away). The
chosen sets keep the smaller set a Fibonacci spiral and give each of its directions a
partner in the larger set near its mirror (-x, -y, z), at a theta_h drawn evenly over rows
0-30 (``PARTNER_THETA_H_ROWS``) and a phi_d drawn evenly too (the R2 sequence); 20% of the
larger set more go to second partners, the rest is a spiral; views stay at z >= 0.02.

Measurements (``benchmarks/merl_fill.py``, its table in ``docs/appearance/merl_fill.json``;
100 x 100 pairs; relative RMSE of :func:`evaluate` against the analytic BRDF in cells with
data, at 20,000 pairs uniform in solid angle, "all", and at 4,000 uniform in cell-index
space with theta_h index < 20, "peak"), old = Fibonacci x the same Fibonacci set with the
old fill (phi_d width 2 x theta_h's on every row, min_weight 6), fib = the same sets with
today's fill, new = merl_direction_sets (mean of seeds 0-2) with today's fill, floor = a
table of the exact values at the cell centres:

=============================  =============  =============  =============  =============
BRDF (all / peak)              old            fib            new            floor
=============================  =============  =============  =============  =============
Lambert                        0 / 0          0 / 0          0 / 0          0 / 0
Lambert + Blinn-Phong 50       0.076 / 0.260  0.029 / 0.152  0.015 / 0.023  0.012 / 0.003
GGX 0.2 + Lambert              0.115 / 0.522  0.064 / 0.462  0.049 / 0.193  0.011 / 0.028
GGX 0.5 + Lambert              0.072 / 0.372  0.039 / 0.323  0.034 / 0.145  0.006 / 0.016
Oren-Nayar 0.5                 0.049 / 0      0.039 / 0      0.036 / 0      0.015 / 0
Minnaert 0.7                   0.120 / 0.259  0.113 / 0.223  0.118 / 0.125  0.098 / 0.028
Phong 50 x (1 + cos 2phi_h)/2  0.087 / 0.257  0.040 / 0.149  0.059 / 0.068  0.012 / 0.003
=============================  =============  =============  =============  =============

(GGX: Schlick Fresnel from F0 = the specular colour, separable Smith masking. The last row
is an anisotropic BRDF against its phi_h average: how many different phi_h a cell's kernel
gathers, as with noisy samples.) What wins, and what it costs:

- The partners fill the peak: with the old fill they take Phong's peak from 0.260 to 0.130,
  with today's from 0.152 to 0.023 (the floor 0.003), and halve GGX's (0.46 -> 0.19 at
  alpha 0.2, 0.32 -> 0.15 at 0.5); at theta_d > 70 degrees (the grazing peak, which a
  microfacet BRDF's 1/(cos theta_i cos theta_o) makes hard) 0.67 -> 0.39 at alpha 0.2.
  Tried instead, at the same pair count: exact mirrors (row 0 only, and (a, m(b)) and
  (b, m(a)) share a cell: hardly better than Fibonacci); partners over rows 0-10 (too few
  rows), 0-20 (best at the peak, worse overall), 0-45 (as good overall, worse at the peak
  and on the anisotropic row below); only half the views partners, the rest a spiral (no
  better, and less even); polar-uniform lights (more near the normal: GGX worse); partners
  placed by a smooth field on the mirrored spiral (good isotropic numbers, poor phi_h
  coverage).
- The phi_d width: on the new sets the old fill scores Phong 0.037 / 0.130 and GGX 0.2
  0.080 / 0.380; today's 0.015 / 0.023 and 0.049 / 0.193 (on Fibonacci sets it helps too:
  the "fib" column). Wider still keeps helping the lobes, which hardly depend on phi_d, but
  Minnaert (which does, through cos theta_i cos theta_o) is best at FILL_PHI_ARC_ROW 120-160
  and worse past it (at min_weight 6: 0.110-0.111, 0.122 at 240, 0.139 with phi_d flat), as
  is Oren-Nayar; hence 160. A stretch of (k / u)^1 (a fixed arc in u, not in theta_h) did
  worse at the peak, a constant stretch worse still.
- What the partners cost: they are a jittered copy of the mirrored spiral, less even than a
  spiral, so a kernel of min_weight samples gathers fewer distinct phi_h (and averages noise
  less): the anisotropic row's cells with theta_h index >= 45 err 0.058 against 0.029 on
  Fibonacci sets (0.050 old). min_weight 10 (not 6) buys much of that back at a small price
  on the lobes (seed 0, all / peak; at 6: Phong 0.015 / 0.020, GGX 0.2 0.046 / 0.185, the
  anisotropic row 0.077 / 0.109, Minnaert 0.114; at 10: 0.015 / 0.025, 0.050 / 0.202,
  0.062 / 0.080, 0.122; at 14: 0.016 / 0.030, 0.054 / 0.219, 0.053 / 0.069, 0.127). Far
  from the peak the new sets are on a par with Fibonacci (theta_h index >= 45: GGX 0.2
  0.070 against 0.066).
- A constant BRDF fills back exactly with any sets (every cell is a weighted mean; 2e-6 from
  float32).

Earlier measurements, of the fill's other choices (100 x 100 Fibonacci pairs, the view set
turned 1 radian from the lights, the old fill; 2,000 uniform random pairs; a GGX with a
floor of 0.018):

- Lambert + Blinn-Phong 50: 0.064 (floor 0.012). GGX alpha 0.2 with Schlick Fresnel and
  Smith masking, + Lambert: 0.117 (0.018); alpha 0.5: 0.090 (0.016); anisotropic GGX
  (0.15, 0.4) against its phi_h average: 0.117 (0.018).
- An isotropic kernel (aspect 1) gives 0.100 / 0.117 / 0.078 / 0.110 on the same four:
  the lobe's top (theta_h index < 30) holds ~300 of the 10^4 samples, none below index 10,
  and a round kernel wide enough to reach them there blurs theta_h, along which BRDFs are
  sharpest. Aspect 3 takes Phong to 0.051 but GGX to 0.17: a kernel that long along theta_d
  mixes in grazing samples, where microfacet BRDFs grow like 1/(cos theta_i cos theta_o).
  The ``light_z * view_z`` weights (the BRDF's weight in rendering) damp exactly those
  (GGX 0.2 at aspect 2: 0.136 without, 0.117 with) and keep constants exact.
- Per cell, against the exact centre values, the relative RMS error was 25-30% (Phong) and
  50-57% (GGX 0.2) over theta_h index < 20, 2% and 10% past index 45; 300 x 300 pairs
  halved the errors: the samples' density more than the method, which the partners above
  address.

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
FILL_MIN_WEIGHT = 10.0
FILL_ASPECT = 2.0
FILL_SIGMA_CAP = 240.0
# The theta_h row (in cell-index units; past the table's 90 rows, so it widens every row) at
# which the kernel's width along phi_d is FILL_ASPECT times its width along theta_h; on row u
# it is that times (FILL_PHI_ARC_ROW / u)^2, the same arc theta_h * delta_phi_d on every row.
FILL_PHI_ARC_ROW = 160.0

# merl_direction_sets: the views' lowest elevation (cos theta; a view ray that grazes the tile
# crosses many periods before it meets a face), the share of the larger set beyond one partner
# per direction of the smaller set that goes to near-mirror partners, and the theta_h rows
# (cell-index units) the near-mirror pairs spread over.
VIEW_MIN_Z = 0.02
EXTRA_PARTNER_SHARE = 0.2
PARTNER_THETA_H_ROWS = 30.0

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


# --- choosing the directions ---------------------------------------------------------------


_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
_PLASTIC = 1.324717957244746  # the real root of x^3 = x + 1


def _spiral(count, lowest_z, turn):
    """(count, 3) float64 unit directions spread evenly over the cap z in [lowest_z, 1]: a
    Fibonacci spiral, equal-area rings in z (``gonio.hemisphere_directions`` when
    ``lowest_z`` and ``turn`` are 0), turned by ``turn`` radians about z."""
    index = np.arange(count) + 0.5
    z = 1.0 - index / count * (1.0 - lowest_z)
    radius = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    angle = index * _GOLDEN_ANGLE + turn
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), z])


def _near_mirrors(anchors, theta_h, tilt_azimuth, lowest_z):
    """(K, 3) float64: each anchor (K, 3) reflected about its own half vector, the normal
    tilted by ``theta_h`` (K,) towards ``tilt_azimuth`` (K,), radians from the anchor's
    azimuth; so the pair (anchor, partner) has exactly that theta_h. A partner that would
    lie below ``lowest_z`` is made again with the tilt towards the anchor, which raises it,
    and theta_h grown as far as that takes."""
    anchor_azimuth = np.arctan2(anchors[:, 1], anchors[:, 0])

    def reflected(about, theta, azimuth):
        s = np.sin(theta)
        half = np.column_stack([s * np.cos(azimuth), s * np.sin(azimuth), np.cos(theta)])
        return 2.0 * np.einsum("ij,ij->i", about, half)[:, None] * half - about

    partners = reflected(anchors, theta_h, anchor_azimuth + tilt_azimuth)
    low = partners[:, 2] < lowest_z
    if np.any(low):
        # Tilted towards the anchor, the partner sits at polar angle theta_anchor - 2 theta_h.
        anchor_polar = np.arccos(np.clip(anchors[low, 2], -1.0, 1.0))
        least = 0.5 * (anchor_polar - np.arccos(lowest_z)) + 1e-9
        partners[low] = reflected(anchors[low], np.maximum(theta_h[low], least), anchor_azimuth[low])
    return _unit(partners)


def merl_direction_sets(lights: int, views: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Light and view directions whose grid of pairs fills a MERL table well, the specular
    peak (small theta_h) included, for :func:`fill_from_samples` (why this choice: the
    module's docstring).

    The smaller set (the lights when there are as many views) is a Fibonacci spiral over
    the hemisphere. Every direction of it gets one partner from the larger set placed near
    its mirror direction, (-x, -y, z), at an exact theta_h spread evenly over the first
    ``PARTNER_THETA_H_ROWS`` theta_h rows (each partner pair its own row and tilt, from a
    two-dimensional low-discrepancy sequence); a further ``EXTRA_PARTNER_SHARE`` of the larger set goes to
    second partners (spread evenly over the smaller set), and the rest of the larger set is
    a Fibonacci spiral of its own. With as many lights as views every view is a partner.

    Parameters
    ----------
    lights, views : int
        How many directions of each, >= 1.
    seed : int
        Draws the sets' turn about the normal, the turn of the larger set's spiral relative
        to the smaller one, and the shifts of the partners' sequences: the same seed gives
        the same sets.

    Returns
    -------
    light, view : (lights, 3), (views, 3) float64
        Unit directions in the tile's frame (z the normal). Lights have z > 0; views have
        z >= ``VIEW_MIN_Z`` (a light near the horizon gets a view partner further from its
        mirror, tilted up just enough).
    """
    lights, views = int(lights), int(views)
    if lights < 1 or views < 1:
        raise ValueError(f"merl_direction_sets needs at least one light and one view, got {lights} and {views}")
    rng = np.random.default_rng(seed)
    turn, spiral_turn = rng.uniform(0.0, 2.0 * np.pi, 2)
    row_shift, azimuth_shift = rng.uniform(0.0, 1.0, 2)
    views_move = views >= lights
    small, large = (lights, views) if views_move else (views, lights)
    # The anchors are the smaller set; the views, whichever they are, keep above VIEW_MIN_Z.
    anchors = _spiral(small, 0.0 if views_move else VIEW_MIN_Z, turn)
    partner_count = min(large, small + int(round(EXTRA_PARTNER_SHARE * large)))
    j = np.arange(partner_count)
    anchor_of = j * small // partner_count
    # The R2 sequence (steps 1/g and 1/g^2, g the plastic number) gives the partner pairs'
    # theta_h rows and tilts (which set phi_d), evenly over their square. Not the golden
    # ratio: the anchors, pole first, step by the golden angle, and anchor azimuth plus
    # tilt, the pair's phi_h, was then the same for every partner pair (an anisotropic
    # tile's phi_h average saw one phi_h). Drawing phi_h itself from R2 instead of the tilt
    # did worse at the peak (anisotropic Phong, seeds 0-2: 0.092 against 0.068).
    rows = PARTNER_THETA_H_ROWS * np.mod(j / _PLASTIC + row_shift, 1.0)
    theta_h = (rows / THETA_H_RES) ** 2 * _HALF_PI
    tilt_azimuth = 2.0 * np.pi * np.mod(j / _PLASTIC ** 2 + azimuth_shift, 1.0)
    partners = _near_mirrors(anchors[anchor_of], theta_h, tilt_azimuth, VIEW_MIN_Z)
    rest = _spiral(large - partner_count, VIEW_MIN_Z if views_move else 0.0, turn + spiral_turn)
    moved = np.concatenate([partners, rest])
    return (anchors, moved) if views_move else (moved, anchors)


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


def _gaussian_matrix(n, sigma):
    """(n, n) float32: the Gaussian of ``sigma`` cells between cell centres, 1 at distance 0."""
    d = (np.arange(n)[:, None] - np.arange(n)[None, :]).astype(np.float64)
    return np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)


def _circulant_gaussians(n, sigmas):
    """(len(sigmas), n, n) float32: per sigma the periodic Gaussian of that many cells
    between cell centres (all periodic images summed, 1 at distance 0 with no image near),
    built from its first row since a circulant matrix repeats it."""
    sigmas = np.asarray(sigmas, dtype=np.float64)
    offsets = np.arange(n, dtype=np.float64)
    images = int(np.ceil(6.0 * sigmas.max() / n)) + 1
    shifted = offsets[None, :] + n * np.arange(-images, images + 1)[:, None]  # (images, n)
    rows = np.exp(-0.5 * (shifted[None, :, :] / sigmas[:, None, None]) ** 2).sum(axis=1)  # (S, n)
    lag = (np.arange(n)[:, None] - np.arange(n)[None, :]) % n
    # Contiguous: a strided matrix sends matmul off BLAS onto a loop 50 times slower.
    return np.ascontiguousarray(rows[:, lag], dtype=np.float32)


def _blur(moments, sigma_h, sigma_d, sigma_phi):
    """``moments`` (C, 90, 90, 180) float32 convolved with a Gaussian of ``sigma_h`` cells
    along theta_h, ``sigma_d`` cells along theta_d and, on theta_h row i, ``sigma_phi[i]``
    cells along phi_d ((90,) float64): three matrix products, along theta_h and theta_d with
    the grid's edges truncating the kernel, along phi_d periodically, one matrix per row.
    The phi_d product comes last, so its per-row width applies to the already blurred rows:
    the operator is not a convolution any more, but it is the same linear, positive map on
    the values and on the weights, which is all a normalised convolution needs (constants
    stay exact). float32 halves the time; the fill's ratios need nowhere near float64's
    precision."""
    c = moments.shape[0]
    gh = _gaussian_matrix(THETA_H_RES, sigma_h)
    gd = _gaussian_matrix(THETA_D_RES, sigma_d)
    gp = _circulant_gaussians(PHI_D_RES, sigma_phi)  # symmetric, one per theta_h row
    out = np.matmul(gh, moments.reshape(c, THETA_H_RES, THETA_D_RES * PHI_D_RES))
    out = np.matmul(gd, out.reshape(c * THETA_H_RES, THETA_D_RES, PHI_D_RES))
    out = np.matmul(out.reshape(c, THETA_H_RES, THETA_D_RES, PHI_D_RES), gp)
    return out.reshape(moments.shape)


def fill_from_samples(light, view, values, *, min_weight=FILL_MIN_WEIGHT, aspect=FILL_ASPECT, sigmas=FILL_SIGMAS,
                      phi_arc_row=FILL_PHI_ARC_ROW):
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
        The kernel's width along theta_d (and along phi_d on row ``phi_arc_row``) over its
        width along theta_h.
    sigmas : sequence of float
        The theta_h bandwidths (Gaussian sigma in cell-index units) to try, increasing; the
        last should reach across the table so that every cell gets a value.
    phi_arc_row : float or None
        The theta_h row (cell-index units, > 0, may lie past 90) on which the kernel's width
        along phi_d is ``aspect`` times its width along theta_h; on row u it is that times
        ``(phi_arc_row / u)**2`` (u the row's centre), which keeps the arc theta_h * delta_phi_d
        it spans the same on every row. None: ``aspect`` times on every row, as along theta_d.

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
    if phi_arc_row is not None and not phi_arc_row > 0.0:
        raise ValueError(f"phi_arc_row must be positive or None, got {phi_arc_row}")
    row_centres = np.arange(THETA_H_RES) + 0.5
    phi_stretch = np.ones(THETA_H_RES) if phi_arc_row is None else (phi_arc_row / row_centres) ** 2

    moments = _splat(*_index_coordinates(light, view), values, light[:, 2] * view[:, 2]).astype(np.float32)
    valid = valid_cells()

    def rung(i, channels=slice(None)):
        sigma_d = aspect * sigmas[i]
        return _blur(moments[channels], sigmas[i], min(sigma_d, FILL_SIGMA_CAP),
                     np.minimum(sigma_d * phi_stretch, FILL_SIGMA_CAP))

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
