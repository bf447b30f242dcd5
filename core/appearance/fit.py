"""Fit Blender's Principled BSDF (Cycles, "Principled v2" of Blender 4.x/5.x) to a sampled BRDF.

The caller has a BRDF table -- ``light`` (K, 3), ``view`` (K, 3) unit vectors in the tile
frame (z up, both above the horizon) and ``values`` (K, 3) in 1/sr, linear RGB -- and wants the
Principled BSDF parameters an artist can type into Blender so that a flat surface looks like the
table. :func:`fit_principled` returns a :class:`PrincipledFit`; :func:`principled_brdf` is the
numpy model of the node that the fit inverts (also usable on its own).

The model (what Cycles does; svm/closure.h, closure/bsdf_microfacet.h, bsdf_sheen.h)
------------------------------------------------------------------------------------
Layers from the top, each attenuating the weight ``w`` (RGB, starting at 1) of those below it by
``w *= clamp(1 - max_rgb(layer albedo / w), 0, 1)`` where the layer's albedo is estimated for the
*view* direction only (Cycles' ``closure_layering_weight``; so the model is not reciprocal):

* sheen: Zeltner et al. 2022 microfiber sheen, an LTC lobe with parameters (a, b) and albedo
  A_s from a 32x32 table over (cos theta_v, sheen_roughness); BRDF
  ``sheen_weight * sheen_tint * A_s * ltc(l) / cos theta_l``; its albedo is
  ``sheen_weight * sheen_tint * A_s``.
* metallic (weight ``metallic * w``): GGX with Schlick Fresnel F0 = base_color (F82 tint 1),
  multiple-scattering compensation; then ``w *= 1 - metallic``.
* transmission: the glass lobe's *reflection* only (a BRDF table sees no transmission):
  GGX with the real dielectric Fresnel at ``ior``; then ``w *= 1 - transmission_weight``.
* specular (dielectric): GGX (alpha = roughness^2; with anisotropy alpha_x = alpha / aspect,
  alpha_y = alpha * aspect, aspect = sqrt(1 - 0.9 anisotropic), tangent rotated by
  ``anisotropic_rotation * 2 pi`` about the normal), Fresnel = the real dielectric Fresnel of the
  IOR whose F0 is ``F0(ior) * 2 * specular_ior_level``; multiple scattering by Cycles' energy
  compensation: single scattering times ``1 + Fms (1 - E) / E`` with E(rough, mu_v) the GGX
  directional albedo, Fms = Fss E_avg / (1 - Fss (1 - E_avg)), Fss from the Kulla-Conty fit.
  Layer albedo ``(E + Fms (1 - E)) * mix(F0, 1, s(rough, mu_v, ior))`` with s the VNDF average of
  the Fresnel's interpolation factor (Cycles' ``ggx_gen_schlick_ior_s`` table).
* diffuse (Subsurface 0): Lambert ``base_color * w / pi`` at Diffuse Roughness 0 (Cycles takes
  the Lambert closure below 1e-5); otherwise Cycles' Oren-Nayar closure (closure/bsdf_oren_nayar.h:
  Fujii's "improved" Oren-Nayar plus the OpenPBR energy-compensating multiple-scattering term),
  with sigma = diffuse_roughness in [0, 1] and rho = clamp(base_color, 0, 1)::

      f_d = w * base_color * (A + B t + M(rho) (1 - E(mu_l)) (1 - E(mu_v)))
      A = 1 / (pi + sigma (pi/2 - 2/3)),   B = sigma A
      t = s / max(mu_l, mu_v) if s > 0 else s,   s = l.v - mu_l mu_v
      E(mu) = pi A + B G(theta),  G = sin(theta) (theta - 2/3 - sin(theta) cos(theta))
                                      + 2/3 tan(theta) (1 - sin(theta)^3)
      E_avg = pi A + B (2 pi - 5.6) / 3
      M(rho) = rho^2 E_avg / (pi (1 - E_avg) (1 - rho (1 - E_avg)))

  E is the single-scattering lobe's exact directional albedo, E_avg a fit of its cosine-weighted
  mean; the multiple-scattering term returns the missing 1 - E (for white, up to E_avg's fit).
  Like Cycles, the closure weight is base_color and M carries rho^2 again (rho^3 in all, where
  the OpenPBR text has rho^2; principled_check's coloured sets confirm it: rho^3 at Cycles' noise,
  rho^2 3-4% off). The term is reciprocal in (l, v). It is isotropic: the back-scatter of
  grooves in every direction (Oren-Nayar's V-cavities), not of one family of parallel grooves.

Approximations (all small next to the fit's own error; measured against Cycles renders in
``benchmarks/principled_check.py``):

* E, E_avg and s are computed here by deterministic stratified VNDF quadrature (64 x 64 samples
  per cell) on Cycles' grids (E: 32 x 32 over rough = (alpha_x alpha_y)^(1/4) and mu; s: 16 x 16
  at the exact IOR instead of Cycles' interpolation over 16 IOR slices), then bilinearly
  interpolated as Cycles does. Cycles' tables are Monte Carlo estimates with 2^20-2^23 samples.
* the sheen LTC table is replaced by a least-squares tensor-product linear spline on an 11 x 11
  grid in (sqrt(cos theta_v), roughness), fitted to Cycles' 32 x 32 table for roughness >= 0.05
  (RMS error of a, b, albedo: about 0.013, 0.003, 0.0014). Not exact at sheen_roughness < 0.1.
* transmission's reflection lobe has no energy compensation; coat, subsurface, emission, thin
  film and specular tint are not modelled (left at their defaults).

The tangent: anisotropy needs a tangent; the model takes the tile's +x axis as the tangent that
``anisotropic_rotation`` rotates (counter-clockwise about +z, 1 = 360 degrees), i.e. in Blender the
Principled BSDF's Tangent input must be the tile's x direction (a UV-map tangent with U along x).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

__all__ = ["PrincipledFit", "PrincipledParams", "fit_principled", "oren_nayar_brdf", "principled_brdf", "weighted_rmse"]

# Least-squares linear-spline fit (knots: rows sqrt(cos theta_v) = i/10, columns sheen
# roughness = j/10) to Cycles' sheen LTC table (a, b, albedo); see the module doc.
_SHEEN_A = (
    (-0.0048, 0.0324, 0.0618, 0.0990, 0.1534, 0.2277, 0.3117, 0.4112, 0.5256, 0.6365, 0.7247),
    (0.0208, 0.0266, 0.0612, 0.1043, 0.1537, 0.2340, 0.3110, 0.4111, 0.5234, 0.6346, 0.7223),
    (-0.0297, 0.0434, 0.0840, 0.1274, 0.1948, 0.2676, 0.3560, 0.4568, 0.5689, 0.6723, 0.7537),
    (0.0459, 0.0379, 0.1125, 0.1752, 0.2371, 0.3140, 0.4034, 0.5059, 0.6143, 0.7104, 0.7842),
    (0.0605, 0.0410, 0.1295, 0.2222, 0.2856, 0.3627, 0.4510, 0.5522, 0.6557, 0.7448, 0.8121),
    (0.1625, 0.0546, 0.1416, 0.2535, 0.3289, 0.4085, 0.4969, 0.5930, 0.6911, 0.7730, 0.8350),
    (0.4254, 0.0878, 0.1581, 0.2726, 0.3577, 0.4435, 0.5363, 0.6269, 0.7178, 0.7940, 0.8510),
    (-0.2998, 0.1531, 0.1743, 0.2915, 0.3810, 0.4702, 0.5672, 0.6560, 0.7389, 0.8095, 0.8626),
    (-0.3743, 0.2132, 0.2044, 0.3148, 0.4039, 0.4954, 0.5929, 0.6812, 0.7560, 0.8214, 0.8707),
    (-0.7662, 0.4222, 0.2452, 0.3524, 0.4330, 0.5238, 0.6174, 0.7039, 0.7719, 0.8300, 0.8759),
    (-0.2221, 0.0936, 0.4548, 0.3951, 0.4959, 0.5642, 0.6460, 0.7239, 0.7871, 0.8384, 0.8799),
)
_SHEEN_B = (
    (0.0793, -0.0642, -0.1938, -0.1707, -0.1816, -0.1717, -0.1611, -0.1411, -0.1091, -0.0602, -0.0002),
    (0.0408, -0.0328, -0.2665, -0.1505, -0.1986, -0.1591, -0.1588, -0.1359, -0.1075, -0.0592, -0.0004),
    (-0.0084, 0.0025, -0.0470, -0.1598, -0.1698, -0.1806, -0.1671, -0.1471, -0.1113, -0.0607, -0.0001),
    (-0.0048, -0.0018, -0.0118, -0.0733, -0.1413, -0.1562, -0.1573, -0.1404, -0.1078, -0.0593, -0.0002),
    (-0.0228, -0.0030, -0.0082, -0.0235, -0.0879, -0.1300, -0.1378, -0.1288, -0.1008, -0.0568, -0.0003),
    (-0.0150, -0.0110, -0.0078, -0.0188, -0.0410, -0.0968, -0.1166, -0.1134, -0.0922, -0.0535, -0.0005),
    (-0.0195, -0.0170, -0.0144, -0.0188, -0.0324, -0.0622, -0.0963, -0.0975, -0.0824, -0.0496, -0.0006),
    (0.0468, -0.0264, -0.0267, -0.0237, -0.0324, -0.0472, -0.0745, -0.0835, -0.0721, -0.0451, -0.0007),
    (0.0664, -0.0369, -0.0370, -0.0331, -0.0335, -0.0415, -0.0551, -0.0671, -0.0592, -0.0383, -0.0007),
    (0.0470, -0.0258, -0.0522, -0.0516, -0.0427, -0.0435, -0.0444, -0.0522, -0.0467, -0.0304, -0.0007),
    (0.0047, -0.0014, -0.0181, -0.0165, -0.0156, -0.0132, -0.0107, -0.0099, -0.0085, -0.0056, -0.0001),
)
_SHEEN_C = (
    (0.0243, 0.5865, 0.7022, 0.6971, 0.6968, 0.6933, 0.6952, 0.7012, 0.7132, 0.7305, 0.7497),
    (-0.0546, 0.6450, 0.6787, 0.6989, 0.6864, 0.6932, 0.6915, 0.7040, 0.7119, 0.7284, 0.7479),
    (-0.4292, 0.2649, 0.5560, 0.5965, 0.6299, 0.6417, 0.6557, 0.6690, 0.6882, 0.7100, 0.7319),
    (-0.0884, 0.0500, 0.3429, 0.4647, 0.5284, 0.5679, 0.5974, 0.6237, 0.6496, 0.6770, 0.7039),
    (0.0304, -0.0148, 0.1389, 0.3167, 0.4115, 0.4778, 0.5256, 0.5657, 0.6028, 0.6359, 0.6676),
    (0.0101, -0.0048, 0.0253, 0.1626, 0.2828, 0.3701, 0.4375, 0.4937, 0.5413, 0.5840, 0.6206),
    (-0.0003, 0.0002, 0.0022, 0.0593, 0.1623, 0.2568, 0.3373, 0.4072, 0.4674, 0.5192, 0.5642),
    (-0.0003, 0.0002, -0.0001, 0.0165, 0.0764, 0.1575, 0.2396, 0.3166, 0.3869, 0.4491, 0.5031),
    (-0.0000, 0.0000, 0.0001, 0.0042, 0.0298, 0.0848, 0.1561, 0.2325, 0.3086, 0.3793, 0.4437),
    (0.0000, -0.0000, 0.0001, 0.0013, 0.0104, 0.0395, 0.0915, 0.1601, 0.2365, 0.3154, 0.3896),
    (0.0000, -0.0000, 0.0000, 0.0005, 0.0036, 0.0159, 0.0474, 0.1016, 0.1744, 0.2573, 0.3417),
)


@dataclass
class PrincipledParams:
    """The Principled BSDF inputs the model uses (Blender's names and ranges)."""

    base_color: np.ndarray = field(default_factory=lambda: np.full(3, 0.8))
    roughness: float = 0.5
    metallic: float = 0.0
    ior: float = 1.5
    specular_ior_level: float = 0.5
    anisotropic: float = 0.0
    anisotropic_rotation: float = 0.0
    sheen_weight: float = 0.0
    sheen_roughness: float = 0.5
    sheen_tint: np.ndarray = field(default_factory=lambda: np.ones(3))
    transmission_weight: float = 0.0
    diffuse_roughness: float = 0.0


# --------------------------------------------------------------------------------------------
# GGX pieces (Cycles' bsdf_microfacet.h conventions)


def _fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance of a dielectric interface (eta = n2 / n1 > 0)."""
    c = np.abs(cos_i)
    g2 = eta * eta - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    a = (g - c) / np.maximum(g + c, 1e-12)
    b = (c * (g + c) - 1.0) / np.maximum(c * (g - c) + 1.0, 1e-12)
    return np.where(g2 > 0.0, 0.5 * a * a * (1.0 + b * b), 1.0)


def _f0_from_ior(eta):
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def _ior_from_f0(f0):
    s = math.sqrt(min(max(f0, 0.0), 0.9999))
    return (1.0 + s) / (1.0 - s)


def _lambda(ax, ay, x, y, z):
    """Smith Lambda of GGX for a local direction (x, y, z)."""
    t = ((ax * x) ** 2 + (ay * y) ** 2) / np.maximum(z * z, 1e-20)
    return 0.5 * (np.sqrt(1.0 + t) - 1.0)


def _ggx_d(ax, ay, hx, hy, hz):
    sx, sy = hx / ax, hy / ay
    return 1.0 / (math.pi * ax * ay * (sx * sx + sy * sy + hz * hz) ** 2)


def _sample_vndf(vx, vz, alpha, n: int = 64):
    """Deterministic stratified VNDF samples (Heitz 2018) for views (vx, 0, vz), isotropic alpha.

    vx, vz, alpha broadcast to shape S; returns H (S + (n*n,), 3 components) and the reflected L."""
    u = (np.arange(n) + 0.5) / n
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    u1, u2 = u1.ravel(), u2.ravel()
    # concentric disk
    a, b = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    big = np.abs(a) > np.abs(b)
    r = np.where(big, a, b)
    phi = np.where(big, (math.pi / 4) * b / np.where(a == 0, 1, a),
                   math.pi / 2 - (math.pi / 4) * a / np.where(b == 0, 1, b))
    tx, ty = r * np.cos(phi), r * np.sin(phi)
    vx, vz, alpha = (np.asarray(x, np.float64)[..., None] for x in (vx, vz, alpha))
    wx, wz = alpha * vx, vz
    norm = np.sqrt(wx * wx + wz * wz)
    wx, wz = wx / norm, wz / norm
    # T1 = (-w.y, w.x, 0)/len = (0, 1, 0) (w.y = 0, w.x > 0); T2 = cross(w, T1) = (-wz, 0, wx)
    ty2 = (1.0 - tx * tx).clip(0.0) ** 0.5 * (1.0 - 0.5 * (1.0 + wz)) + ty * 0.5 * (1.0 + wz)
    tz = np.sqrt(np.clip(1.0 - tx * tx - ty2 * ty2, 0.0, None))
    hx_ = -ty2 * wz + tz * wx
    hy_ = tx + 0.0 * wx
    hz_ = ty2 * wx + tz * wz
    hx, hy, hz = alpha * hx_, alpha * hy_, np.maximum(hz_, 0.0)
    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    vh = vx * hx + vz * hz
    lx, ly, lz = 2 * vh * hx - vx, 2 * vh * hy, 2 * vh * hz - vz
    return (hx, hy, hz), (lx, ly, lz), vh


def _grid(n):
    return np.clip(np.arange(n) / (n - 1), 1e-4, 1.0)


@lru_cache(maxsize=1)
def _ggx_energy_tables():
    """E(rough, mu) on Cycles' 32 x 32 grid (rows mu, columns rough) and E_avg(rough) (32)."""
    rough = _grid(32)
    mu = _grid(32)
    R, M = np.meshgrid(rough, mu, indexing="xy")  # (mu, rough)
    alpha = R * R
    vz = M
    vx = np.sqrt(1.0 - vz * vz)
    _, (lx, ly, lz), _ = _sample_vndf(vx, vz, alpha)
    lam_l = _lambda(alpha[..., None], alpha[..., None], lx, ly, np.maximum(lz, 1e-12))
    lam_v = _lambda(alpha, alpha, vx, 0.0, vz)[..., None]
    # estimator of the single-scattering albedo with VNDF sampling: G2 / G1(v) where valid
    weight = np.where(lz > 0.0, (1.0 + lam_v) / (1.0 + lam_v + lam_l), 0.0)
    E = np.clip(weight.mean(-1), 0.0, 1.0)
    # E_avg = integral of 2 mu E(mu) dmu (trapezoid on a fine mu grid of the same table)
    mu_f = np.linspace(0.0, 1.0, 257)
    E_f = np.stack([np.interp(mu_f, mu, E[:, j]) for j in range(32)], 1)
    y = 2.0 * mu_f[:, None] * E_f
    Eavg = ((y[1:] + y[:-1]) * 0.5 * np.diff(mu_f)[:, None]).sum(0)
    return E, np.clip(Eavg, 0.0, 1.0)


@lru_cache(maxsize=512)
def _schlick_s_table(eta: float):
    """Cycles' ggx_gen_schlick_ior_s at one IOR: the VNDF average of
    clamp((F(h.v) - F0) / (1 - F0), 0, 1), 16 x 16 grid (rows mu, columns rough)."""
    rough, mu = _grid(16), _grid(16)
    R, M = np.meshgrid(rough, mu, indexing="xy")
    alpha = R * R
    vx = np.sqrt(1.0 - M * M)
    _, (_, _, lz), vh = _sample_vndf(vx, M, alpha)
    f0 = _f0_from_ior(eta)
    s = np.clip((_fresnel_dielectric(vh, eta) - f0) / max(1.0 - f0, 1e-9), 0.0, 1.0)
    return np.where(lz > 0.0, s, 0.0).mean(-1)


def _lerp_table(table, x, y):
    """Cycles' lookup_table_read_2D: table[y, x] on a uniform grid over [0, 1]^2, bilinear."""
    ny, nx = table.shape
    x = np.clip(x, 0.0, 1.0) * (nx - 1)
    y = np.clip(y, 0.0, 1.0) * (ny - 1)
    ix = np.minimum(np.floor(x).astype(int), nx - 2)
    iy = np.minimum(np.floor(y).astype(int), ny - 2)
    fx, fy = x - ix, y - iy
    t00, t01 = table[iy, ix], table[iy, ix + 1]
    t10, t11 = table[iy + 1, ix], table[iy + 1, ix + 1]
    return (1 - fy) * ((1 - fx) * t00 + fx * t01) + fy * ((1 - fx) * t10 + fx * t11)


def _sheen_ltc(mu_v, roughness):
    """(a, b, albedo) of the sheen LTC for cos theta_v and sheen roughness (approximation)."""
    r = min(max(roughness, 1e-3), 1.0)
    out = []
    for table in (_SHEEN_A, _SHEEN_B, _SHEEN_C):
        t = np.asarray(table, np.float64)  # [sqrt(mu) knot, rough knot]
        out.append(_lerp_table(t, np.full_like(mu_v, r), np.sqrt(np.clip(mu_v, 0.0, 1.0))))
    a, b, c = out
    return np.maximum(a, 1e-4), b, np.clip(c, 0.0, 1.0)


def _ggx_single(ax, ay, rot, l, v, h, eta=None, f0_metal=None):
    """Single-scattering GGX BRDF (no cosine) and cos(h, v), anisotropic, tangent x rotated by rot."""
    c, s = math.cos(2 * math.pi * rot), math.sin(2 * math.pi * rot)

    def local(d):
        return c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]

    hx, hy, hz = local(h)
    lx, ly, lz = local(l)
    vx, vy, vz = local(v)
    D = _ggx_d(ax, ay, hx, hy, hz)
    G = 1.0 / (1.0 + _lambda(ax, ay, lx, ly, lz) + _lambda(ax, ay, vx, vy, vz))
    return D * G / (4.0 * lz * vz)


# Below this Diffuse Roughness Cycles uses its Lambert closure (svm/closure.h, CLOSURE_WEIGHT_CUTOFF).
DIFFUSE_ROUGHNESS_CUTOFF = 1e-5


def _oren_nayar_g(mu):
    """G(theta) of the Oren-Nayar directional albedo E = pi A + B G, for cos theta = mu in [0, 1]."""
    mu = np.clip(np.asarray(mu, np.float64), 0.0, 1.0)
    safe = np.maximum(mu, 1e-6)
    sin = np.sqrt(np.maximum(1.0 - safe * safe, 0.0))
    theta = np.arccos(safe)
    g = sin * (theta - 2.0 / 3.0 - sin * safe) + (2.0 / 3.0) * (sin / safe) * (1.0 - sin ** 3)
    # at grazing angles tan(theta) is ill-conditioned: the first-order expansion about mu = 0
    return np.where(mu < 1e-6, (math.pi / 2 - 2.0 / 3.0) - mu, g)


def oren_nayar_brdf(light, view, base_color, sigma: float) -> np.ndarray:
    """Cycles' Oren-Nayar diffuse closure of colour ``base_color`` (K, 3), 1/sr, no layering
    weight (see the module doc); Lambert base_color / pi below the cutoff."""
    l = np.asarray(light, np.float64).reshape(-1, 3)
    v = np.asarray(view, np.float64).reshape(-1, 3)
    base = np.clip(np.asarray(base_color, np.float64), 0.0, None).reshape(-1, 3)
    sigma = min(max(float(sigma), 0.0), 1.0)
    if sigma < DIFFUSE_ROUGHNESS_CUTOFF:
        return np.broadcast_to(base / math.pi, (len(l), 3)).copy()
    mu_l, mu_v = np.maximum(l[:, 2], 0.0), np.maximum(v[:, 2], 0.0)
    a = 1.0 / (math.pi + sigma * (math.pi / 2 - 2.0 / 3.0))
    b = sigma * a
    s = (l * v).sum(1) - mu_l * mu_v
    t = np.where(s > 0.0, s / np.maximum(np.maximum(mu_l, mu_v), 1e-300), s)
    e_avg = math.pi * a + b * (2.0 * math.pi - 5.6) / 3.0
    rho = np.minimum(base, 1.0)
    m = rho * rho * e_avg / (math.pi * (1.0 - e_avg) * (1.0 - rho * (1.0 - e_avg)))
    missing = (1.0 - (math.pi * a + b * _oren_nayar_g(mu_l))) * (1.0 - (math.pi * a + b * _oren_nayar_g(mu_v)))
    return base * ((a + b * t)[:, None] + m * missing[:, None])


def principled_brdf(light, view, params: PrincipledParams) -> np.ndarray:
    """The Principled BSDF's reflection (1/sr), (K, 3), for unit light/view directions (K, 3)."""
    p = params
    l = np.asarray(light, np.float64).reshape(-1, 3)
    v = np.asarray(view, np.float64).reshape(-1, 3)
    mu_l, mu_v = l[:, 2], v[:, 2]
    h = l + v
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    cos_hv = np.clip((h * v).sum(1), 0.0, 1.0)
    E_tab, Eavg_tab = _ggx_energy_tables()
    base = np.clip(np.asarray(p.base_color, np.float64), 0.0, None)
    w = np.ones((len(l), 3))
    out = np.zeros((len(l), 3))

    # sheen
    if p.sheen_weight > 0.0:
        a, b, alb = _sheen_ltc(mu_v, p.sheen_roughness)
        # frame: T = view projected on the plane, B = N x T (make_orthonormals_tangent(N, wi))
        vt = np.sqrt(np.maximum(v[:, 0] ** 2 + v[:, 1] ** 2, 1e-24))
        tx, ty = v[:, 0] / vt, v[:, 1] / vt
        ox = tx * l[:, 0] + ty * l[:, 1]
        oy = -ty * l[:, 0] + tx * l[:, 1]
        oz = mu_l
        len_sqr = (a * ox + b * oz) ** 2 + (a * oy) ** 2 + oz ** 2
        ltc = (a / len_sqr) ** 2 / math.pi  # = eval / cos theta_l
        sw = p.sheen_weight * np.clip(np.asarray(p.sheen_tint, np.float64), 0.0, None)
        out += (sw[None, :] * alb[:, None]) * ltc[:, None]
        albedo = sw[None, :] * alb[:, None]
        w = w * np.clip(1.0 - albedo.max(1), 0.0, 1.0)[:, None]

    rough = min(max(p.roughness, 0.0), 1.0)
    alpha = rough * rough
    aniso = min(max(p.anisotropic, 0.0), 1.0)
    ax = ay = alpha
    if aniso > 0.0:
        aspect = math.sqrt(1.0 - 0.9 * aniso)
        ax, ay = min(alpha / aspect, 1.0), alpha * aspect
    ax, ay = max(ax, 1e-4), max(ay, 1e-4)
    r_e = (ax * ay) ** 0.25
    E = _lerp_table(E_tab, np.full_like(mu_v, r_e), mu_v)
    Eavg = float(np.interp(r_e, _grid(32), Eavg_tab))
    missing = (1.0 - E) / np.maximum(E, 1e-6)
    single = _ggx_single(ax, ay, p.anisotropic_rotation, l, v, h)

    # metallic: Schlick Fresnel with F0 = base colour (F82 tint 1), energy compensated
    metallic = min(max(p.metallic, 0.0), 1.0)
    if metallic > 0.0:
        f0m = np.minimum(base, 1.0)
        F = f0m[None, :] + (1.0 - f0m[None, :]) * ((1.0 - cos_hv) ** 5)[:, None]
        Fss = f0m + (1.0 - f0m) / 21.0
        Fms = Fss * Eavg / (1.0 - Fss * (1.0 - Eavg))
        out += metallic * w * F * single[:, None] * (1.0 + Fms[None, :] * missing[:, None])
        w = w * (1.0 - metallic)

    # transmission: only its reflection lobe is visible in a BRDF (no energy compensation)
    trans = min(max(p.transmission_weight, 0.0), 1.0)
    if trans > 0.0:
        iso = _ggx_single(max(alpha, 1e-4), max(alpha, 1e-4), 0.0, l, v, h)
        out += trans * w * (_fresnel_dielectric(cos_hv, p.ior) * iso)[:, None]
        w = w * (1.0 - trans)

    # dielectric specular
    f0 = _f0_from_ior(p.ior)
    eta = p.ior
    level = max(p.specular_ior_level, 0.0)
    if level != 0.5:
        f0 = f0 * 2.0 * level
        eta = _ior_from_f0(f0)
        if p.ior < 1.0:
            eta = 1.0 / eta
    if f0 > 1e-7 and abs(eta - 1.0) > 1e-6:
        F = _fresnel_dielectric(cos_hv, eta)
        real_fss = (eta - 1.0) / (4.08567 + 1.00071 * eta)
        f0r = _f0_from_ior(eta)
        s_fss = min(max((real_fss - f0r) / (1.0 - f0r), 0.0), 1.0)
        Fss = f0 + (1.0 - f0) * s_fss
        Fms = Fss * Eavg / (1.0 - Fss * (1.0 - Eavg))
        boost = 1.0 + Fms * missing
        out += w * (F * single * boost)[:, None]
        # s varies slowly with the IOR: tables at IORs 0.01 apart, interpolated (keeps the cache small)
        q = float(eta) * 100.0
        q0 = math.floor(q)
        s_tab = (1.0 - (q - q0)) * _schlick_s_table(q0 / 100.0) + (q - q0) * _schlick_s_table((q0 + 1) / 100.0)
        s = _lerp_table(s_tab, np.full_like(mu_v, r_e), mu_v)
        layer_albedo = E * boost * (f0 + (1.0 - f0) * s)
        w = w * np.clip(1.0 - layer_albedo, 0.0, 1.0)[:, None]

    # diffuse: Lambert, or Oren-Nayar with Diffuse Roughness
    if p.diffuse_roughness >= DIFFUSE_ROUGHNESS_CUTOFF:
        out += w * oren_nayar_brdf(l, v, base[None, :], p.diffuse_roughness)
    else:
        out += w * base[None, :] / math.pi
    return out


def weighted_rmse(model, values, light, view, weights=None):
    """Relative RMSE sqrt(sum w (m - f)^2 / sum w f^2), w = cos theta_l cos theta_v (x weights):
    overall (all channels) and per channel (3,)."""
    m = np.asarray(model, np.float64).reshape(-1, 3)
    f = np.asarray(values, np.float64).reshape(-1, 3)
    w = np.asarray(light, np.float64).reshape(-1, 3)[:, 2] * np.asarray(view, np.float64).reshape(-1, 3)[:, 2]
    if weights is not None:
        w = w * np.asarray(weights, np.float64).reshape(-1)
    w = w[:, None]
    num = (w * (m - f) ** 2).sum(0)
    den = np.maximum((w * f ** 2).sum(0), 1e-300)
    return float(math.sqrt(num.sum() / den.sum())), np.sqrt(num / den)


# --------------------------------------------------------------------------------------------
# The fit


@dataclass
class PrincipledFit:
    """Principled BSDF inputs fitted to a BRDF table, and the fit's error.

    anisotropic_rotation follows Blender: 0..1 is 0..360 degrees of the tangent about the normal
    (here in [0, 0.5): a GGX lobe is symmetric under a half turn), the tangent being the tile's
    +x axis. rmse: relative RMSE of the model against the values, weighted by
    cos theta_l cos theta_v (x the caller's weights), i.e. the error in reflected radiance under
    uniform directional sampling; per_channel_rmse the same per RGB channel.
    """

    base_color: np.ndarray
    roughness: float
    anisotropic: float = 0.0
    anisotropic_rotation: float = 0.0
    specular_ior_level: float = 0.5
    ior: float = 1.5
    sheen_weight: float = 0.0
    sheen_roughness: float = 0.5
    sheen_tint: np.ndarray = field(default_factory=lambda: np.ones(3))
    transmission_weight: float = 0.0
    metallic: float = 0.0
    diffuse_roughness: float = 0.0
    rmse: float = float("nan")
    per_channel_rmse: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    model: str = ""
    candidates: dict = field(default_factory=dict)

    def params(self) -> PrincipledParams:
        return PrincipledParams(base_color=np.asarray(self.base_color, np.float64), roughness=self.roughness,
                                metallic=self.metallic, ior=self.ior, specular_ior_level=self.specular_ior_level,
                                anisotropic=self.anisotropic, anisotropic_rotation=self.anisotropic_rotation,
                                sheen_weight=self.sheen_weight, sheen_roughness=self.sheen_roughness,
                                sheen_tint=np.asarray(self.sheen_tint, np.float64),
                                transmission_weight=self.transmission_weight,
                                diffuse_roughness=self.diffuse_roughness)

    def evaluate(self, light, view) -> np.ndarray:
        return principled_brdf(light, view, self.params())

    def describe(self) -> str:
        def rgb(c):
            return "(" + ", ".join(f"{x:.3f}" for x in np.asarray(c).ravel()) + ")"

        lines = [f"Principled BSDF fit ({self.model}):",
                 f"  Base Color            {rgb(self.base_color)}",
                 f"  Metallic              {self.metallic:.3f}",
                 f"  Roughness             {self.roughness:.3f}",
                 f"  Diffuse Roughness     {self.diffuse_roughness:.3f}",
                 f"  IOR                   {self.ior:.3f}",
                 f"  Specular IOR Level    {self.specular_ior_level:.3f}",
                 f"  Anisotropic           {self.anisotropic:.3f}",
                 f"  Anisotropic Rotation  {self.anisotropic_rotation:.3f}"
                 f" ({360.0 * self.anisotropic_rotation:.1f} deg from the tile's +x; Tangent = +x)",
                 f"  Sheen Weight          {self.sheen_weight:.3f}",
                 f"  Sheen Roughness       {self.sheen_roughness:.3f}",
                 f"  Sheen Tint            {rgb(self.sheen_tint)}",
                 f"  Transmission Weight   {self.transmission_weight:.3f}",
                 f"  error: relative RMSE {100 * self.rmse:.2f}% (R {100 * self.per_channel_rmse[0]:.2f}%,"
                 f" G {100 * self.per_channel_rmse[1]:.2f}%, B {100 * self.per_channel_rmse[2]:.2f}%),"
                 " weighted by cos theta_l cos theta_v"]
        if self.candidates:
            lines.append("  candidates: " + ", ".join(f"{k} {100 * v:.2f}%" for k, v in self.candidates.items()))
        return "\n".join(lines)


def _check_inputs(light, view, values, weights):
    l = np.asarray(light, np.float64)
    v = np.asarray(view, np.float64)
    f = np.asarray(values, np.float64)
    if l.ndim != 2 or l.shape[1] != 3 or v.shape != l.shape:
        raise ValueError(f"light and view must both be (K, 3) arrays, got {l.shape} and {v.shape}")
    if f.ndim == 1 and len(l) > 0 and f.shape[0] == len(l):
        f = np.repeat(f[:, None], 3, 1)
    if f.shape != l.shape:
        raise ValueError(f"values must be (K, 3) like light and view (K = {len(l)}), got {f.shape}")
    if len(l) == 0:
        raise ValueError("the BRDF table is empty (K = 0): nothing to fit")
    for name, a in (("light", l), ("view", v), ("values", f)):
        if not np.isfinite(a).all():
            raise ValueError(f"{name} contains NaN or infinite entries")
    for name, a in (("light", l), ("view", v)):
        n = np.linalg.norm(a, axis=1)
        if np.abs(n - 1.0).max() > 1e-3:
            raise ValueError(f"{name} directions must be unit vectors (norms {n.min():.4g}..{n.max():.4g})")
        if (a[:, 2] <= 0.0).any():
            raise ValueError(f"{name} directions must be above the horizon (z > 0); "
                             f"{int((a[:, 2] <= 0).sum())} of {len(a)} are not")
    if (f < 0.0).any():
        raise ValueError("values must be non-negative (a BRDF)")
    if weights is None:
        w = np.ones(len(l))
    else:
        w = np.asarray(weights, np.float64).reshape(-1)
        if w.shape != (len(l),) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise ValueError("weights must be K finite, non-negative numbers, not all zero")
    if not (f.max() > 0.0):
        raise ValueError("values are all zero: a black BRDF has no Principled fit")
    return l / np.linalg.norm(l, axis=1, keepdims=True), v / np.linalg.norm(v, axis=1, keepdims=True), f, w


def _sig(x):
    return 1.0 / (1.0 + np.exp(-np.clip(x, -60.0, 60.0)))


def _logit(p):
    p = min(max(p, 1e-6), 1 - 1e-6)
    return math.log(p / (1.0 - p))


_BOUNDS = {"roughness": (0.03, 1.0), "specular_ior_level": (0.0, 1.0), "sheen_roughness": (0.05, 1.0),
           "anisotropic": (0.0, 1.0), "diffuse_roughness": (0.0, 1.0)}


class _Problem:
    """Parameter vector <-> PrincipledParams for one model variant, and the residuals."""

    def __init__(self, l, v, f, w, variant, transmission, fixed):
        self.l, self.v, self.f, self.variant, self.transmission = l, v, f, variant, transmission
        self.fixed = fixed
        cw = l[:, 2] * v[:, 2] * w
        self.sw = np.sqrt(cw / cw.sum())[:, None]
        self.eps = 0.02 * np.maximum((cw[:, None] * f).sum(0) / cw.sum(), 1e-12)
        self.logf = np.log(f + self.eps)
        self.names = ["b0", "b1", "b2", "roughness"]
        if "specular_ior_level" not in fixed:
            self.names.append("specular_ior_level")
        if "rough_diffuse" in variant:
            self.names.append("diffuse_roughness")
        if "sheen" in variant:
            self.names += ["s0", "s1", "s2", "sheen_roughness"]
        if "aniso" in variant:
            self.names += ["anisotropic", "rot"]

    def _bounded(self, name, x):
        lo, hi = _BOUNDS[name]
        return lo + (hi - lo) * _sig(x)

    def params(self, x) -> PrincipledParams:
        d = dict(zip(self.names, x))
        p = PrincipledParams(base_color=_sig(np.array([d["b0"], d["b1"], d["b2"]])),
                             roughness=float(self._bounded("roughness", d["roughness"])),
                             transmission_weight=self.transmission)
        p.specular_ior_level = float(self.fixed.get("specular_ior_level", 0.5))
        p.ior = float(self.fixed.get("ior", 1.5))
        if "specular_ior_level" in d:
            p.specular_ior_level = float(self._bounded("specular_ior_level", d["specular_ior_level"]))
        if "diffuse_roughness" in d:
            p.diffuse_roughness = float(self._bounded("diffuse_roughness", d["diffuse_roughness"]))
        if "s0" in d:
            amount = _sig(np.array([d["s0"], d["s1"], d["s2"]]))
            p.sheen_weight = float(amount.max())
            p.sheen_tint = amount / max(p.sheen_weight, 1e-12)
            p.sheen_roughness = float(self._bounded("sheen_roughness", d["sheen_roughness"]))
        if "anisotropic" in d:
            p.anisotropic = float(self._bounded("anisotropic", d["anisotropic"]))
            p.anisotropic_rotation = float(d["rot"] % 0.5)
        return p

    def encode(self, p: PrincipledParams) -> np.ndarray:
        x = []
        for name in self.names:
            if name in ("b0", "b1", "b2"):
                x.append(_logit(p.base_color[int(name[1])]))
            elif name in ("s0", "s1", "s2"):
                x.append(_logit(p.sheen_weight * p.sheen_tint[int(name[1])]))
            elif name == "rot":
                x.append(p.anisotropic_rotation)
            else:
                lo, hi = _BOUNDS[name]
                x.append(_logit((getattr(p, name) - lo) / (hi - lo)))
        return np.array(x, np.float64)

    def residuals(self, x) -> np.ndarray:
        m = principled_brdf(self.l, self.v, self.params(x))
        return (self.sw * (np.log(np.maximum(m, 0.0) + self.eps) - self.logf)).ravel()


def _levenberg_marquardt(fun, x0, iterations: int = 40, step: float = 1e-4):
    """Minimise |fun(x)|^2: Levenberg-Marquardt with forward-difference Jacobians."""
    x = np.asarray(x0, np.float64).copy()
    r = fun(x)
    cost = float(r @ r)
    lam = 1e-2
    for _ in range(iterations):
        J = np.empty((len(r), len(x)))
        for j in range(len(x)):
            xj = x.copy()
            xj[j] += step
            J[:, j] = (fun(xj) - r) / step
        A = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(8):
            try:
                dx = -np.linalg.solve(A + lam * (np.diag(np.diag(A)) + 1e-9 * np.eye(len(x))), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            xn = x + dx
            rn = fun(xn)
            cn = float(rn @ rn)
            if cn < cost:
                improved = cost - cn > 1e-10 * max(cost, 1e-30)
                x, r, cost = xn, rn, cn
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 10.0
        if not improved:
            break
    return x, cost


def _initial_base(l, v, f):
    """Base colour guess: pi x the lower-quartile BRDF away from the mirror direction."""
    h = l + v
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    off = h[:, 2] < np.quantile(h[:, 2], 0.5) if len(h) > 4 else np.ones(len(h), bool)
    level = np.quantile(f[off], 0.25, axis=0) if off.sum() else f.mean(0)
    return np.clip(math.pi * level / 0.92, 0.02, 0.98)


def fit_principled(light, view, values, weights=None, transparency: float | None = None,
                   fit_specular: bool = True, ior: float = 1.5, try_sheen: bool = True,
                   try_anisotropy: bool = True, improvement: float = 0.10,
                   try_diffuse_roughness: bool = True) -> PrincipledFit:
    """Fit the Principled BSDF to a sampled BRDF.

    light, view : (K, 3) unit directions (tile frame, z up, above the horizon)
    values : (K, 3) BRDF in 1/sr (linear RGB)
    weights : optional (K,) extra weights (e.g. solid angles of the direction sets)
    transparency : the caller's transmitted fraction; passed through as Transmission Weight
        (its reflection lobe is modelled, its transmission is not in a BRDF table)
    fit_specular : fit Specular IOR Level (else 0.5); ior : the IOR (not fitted)
    try_diffuse_roughness, try_sheen, try_anisotropy : also fit those variants, in that order,
        each on top of the variant chosen so far; a richer variant replaces the simpler one only
        if it lowers the relative RMSE by more than ``improvement`` (10%). Diffuse Roughness
        (Oren-Nayar, in [0, 1]) is the back-scatter of rough or grooved diffuse surfaces.

    Minimises the cos theta_l cos theta_v weighted squared difference of log(f + eps),
    eps = 2% of the weighted mean BRDF per channel (relative errors; the specular peak does not
    swamp the diffuse level), by Levenberg-Marquardt from several deterministic starts.
    """
    l, v, f, w = _check_inputs(light, view, values, weights)
    trans = 0.0 if transparency is None else float(min(max(transparency, 0.0), 1.0))
    fixed = {"ior": float(ior)}
    if not fit_specular:
        fixed["specular_ior_level"] = 0.5
    base0 = _initial_base(l, v, f)

    def run(variant, starts):
        prob = _Problem(l, v, f, w, variant, trans, fixed)
        best = None
        for p0 in starts:
            x, cost = _levenberg_marquardt(prob.residuals, prob.encode(p0))
            if best is None or cost < best[1] - 1e-15:
                best = (x, cost)
        p = prob.params(best[0])
        rmse, per = weighted_rmse(principled_brdf(l, v, p), f, l, v, w)
        return p, rmse, per

    def variant_of(p: PrincipledParams) -> str:
        return " ".join(name for name, on in (("rough_diffuse", p.diffuse_roughness > 0.0),
                                              ("sheen", p.sheen_weight > 0.0)) if on)

    iso_starts = [PrincipledParams(base_color=base0.copy(), roughness=r, ior=ior) for r in (0.15, 0.4, 0.8)]
    chosen = ("isotropic", *run("iso", iso_starts))
    candidates = {"isotropic": chosen[2]}
    if try_diffuse_roughness:
        p0 = chosen[1]
        starts = []
        for sigma in (0.5, 1.0):
            q = PrincipledParams(**{**p0.__dict__})
            q.diffuse_roughness = sigma
            # Oren-Nayar darkens the diffuse level at normal incidence: start the colour higher
            q.base_color = np.clip(p0.base_color / (1.0 - 0.2 * sigma), 0.01, 0.99)
            starts.append(q)
        cand = (chosen[0] + " + diffuse roughness", *run("rough_diffuse", starts))
        candidates[cand[0]] = cand[2]
        if cand[2] < (1.0 - improvement) * chosen[2]:
            chosen = cand
    if try_sheen:
        p0 = chosen[1]
        starts = []
        for sr in (0.3, 0.7):
            q = PrincipledParams(**{**p0.__dict__})
            q.base_color = np.clip(p0.base_color * 0.8, 0.01, 0.99)
            q.sheen_weight, q.sheen_roughness, q.sheen_tint = 0.5, sr, np.ones(3)
            starts.append(q)
        cand = (chosen[0] + " + sheen", *run(variant_of(p0) + " sheen", starts))
        candidates[cand[0]] = cand[2]
        if cand[2] < (1.0 - improvement) * chosen[2]:
            chosen = cand
    if try_anisotropy:
        p0 = chosen[1]
        starts = []
        for rot in (0.0, 0.125, 0.25, 0.375):
            q = PrincipledParams(**{**p0.__dict__})
            q.anisotropic, q.anisotropic_rotation = 0.5, rot
            if q.sheen_weight > 0:
                q.sheen_tint = np.maximum(q.sheen_tint, 1e-3)
            starts.append(q)
        cand = (chosen[0] + " + anisotropic", *run(variant_of(p0) + " aniso", starts))
        candidates[cand[0]] = cand[2]
        if cand[2] < (1.0 - improvement) * chosen[2]:
            chosen = cand
    name, p, rmse, per = chosen
    return PrincipledFit(base_color=p.base_color, roughness=p.roughness, anisotropic=p.anisotropic,
                         anisotropic_rotation=p.anisotropic_rotation, specular_ior_level=p.specular_ior_level,
                         ior=p.ior, sheen_weight=p.sheen_weight, sheen_roughness=p.sheen_roughness,
                         sheen_tint=np.asarray(p.sheen_tint, np.float64), transmission_weight=p.transmission_weight,
                         metallic=p.metallic, diffuse_roughness=p.diffuse_roughness, rmse=rmse,
                         per_channel_rmse=per, model=name, candidates=candidates)
