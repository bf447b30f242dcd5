"""Compiled (numba) kernels of the virtual gonioreflectometer (core.appearance.gonio): the
micro-BRDF's glossy lobe, and the per-direction transport of its bounces.

Imported only through :func:`core.kernels.appearance`, the first time a tile is simulated.

The table is dense per sample and direction: ``hit_corner`` (S, N, 3) int32 the samples at
the corners of the face the ray from sample s along direction i meets (-1: it met none, or
the direction is below s's horizon), ``hit_weight`` (S, N, 3) float32 their barycentric
weights, ``cos_weight`` (S, N) float32 max(0, n_s . d_i) scaled to sum to pi per sample
(about 4 pi / N each). Light arriving at s
from direction d_i left the hit point towards -d_i.

Each parallel loop writes disjoint outputs (one sample's rows) and sums in a fixed order,
so the results do not depend on the thread count.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from . import KERNEL_OPTIONS, SERIAL_OPTIONS


@nb.njit(**SERIAL_OPTIONS)
def lobe(nx, ny, nz, ix, iy, iz, ox, oy, oz, roughness, exponent):
    """The glossy lobe's BRDF (1/sr, white) at normal n for light from unit wi towards unit
    wo; 0 unless both lie above the surface.

    roughness >= 0: a GGX microfacet lobe (alpha = roughness^2, Smith's separable masking),
    with no Fresnel term (the mixture's weight plays that part), so its directional albedo
    is at most 1. roughness < 0: the paper's Phong lobe, energy-normalised:
    (exponent + 2) / (2 pi) cos^exponent of the angle to the mirror direction.
    """
    cos_i = nx * ix + ny * iy + nz * iz
    cos_o = nx * ox + ny * oy + nz * oz
    if cos_i <= 0.0 or cos_o <= 0.0:
        return 0.0
    if roughness < 0.0:
        # Mirror of wi about n, against wo.
        mirror = 2.0 * cos_i * (nx * ox + ny * oy + nz * oz) - (ix * ox + iy * oy + iz * oz)
        if mirror <= 0.0:
            return 0.0
        return (exponent + 2.0) / (2.0 * math.pi) * mirror ** exponent
    hx = ix + ox
    hy = iy + oy
    hz = iz + oz
    length = math.sqrt(hx * hx + hy * hy + hz * hz)
    if length <= 0.0:
        return 0.0
    cos_h = (nx * hx + ny * hy + nz * hz) / length
    alpha = max(roughness * roughness, 1e-4)
    a2 = alpha * alpha
    denominator = cos_h * cos_h * (a2 - 1.0) + 1.0
    distribution = a2 / (math.pi * denominator * denominator)
    g_i = 2.0 * cos_i / (cos_i + math.sqrt(a2 + (1.0 - a2) * cos_i * cos_i))
    g_o = 2.0 * cos_o / (cos_o + math.sqrt(a2 + (1.0 - a2) * cos_o * cos_o))
    return distribution * g_i * g_o / (4.0 * cos_i * cos_o)


@nb.njit(**KERNEL_OPTIONS)
def lobe_many(normal, specular, roughness, exponent, incoming, outgoing, out):
    """``out[k] = specular[s_k] * lobe(normal[s_k], incoming[k], outgoing[k])`` for K triples.

    normal : (K, 3) float64; specular, roughness : (K,) float32; exponent : float64
    incoming, outgoing : (K, 3) float64 unit; out : (K,) float64
    """
    for k in nb.prange(normal.shape[0]):
        out[k] = specular[k] * lobe(normal[k, 0], normal[k, 1], normal[k, 2], incoming[k, 0], incoming[k, 1],
                                    incoming[k, 2], outgoing[k, 0], outgoing[k, 1], outgoing[k, 2], roughness[k],
                                    exponent)


@nb.njit(**KERNEL_OPTIONS)
def gather_diffuse(sent, hit_corner, hit_weight, cos_weight, out):
    """Irradiance from light that leaves every sample the same way towards every direction.

    sent : (S, B, 3) float32 radiance each sample sends (B lightings at once)
    Output out (S, B, 3) float64: sum over directions of cos_weight times the radiance of
    the point hit.
    """
    count, directions = cos_weight.shape
    batch = sent.shape[1]
    for s in nb.prange(count):
        for b in range(batch):
            for c in range(3):
                out[s, b, c] = 0.0
        for i in range(directions):
            w = cos_weight[s, i]
            if w <= 0.0 or hit_corner[s, i, 0] < 0:
                continue
            for corner in range(3):
                t = hit_corner[s, i, corner]
                share = w * hit_weight[s, i, corner]
                for b in range(batch):
                    for c in range(3):
                        out[s, b, c] += share * sent[t, b, c]


@nb.njit(**KERNEL_OPTIONS)
def incoming_radiance(outgoing, hit_corner, hit_weight, out):
    """The radiance arriving at every sample from every direction: what the hit point sends
    back along it (0 where nothing is hit).

    outgoing : (S, N, B, 3) float32, each sample's radiance towards -d_i
    Output out (S, N, B, 3) float32.
    """
    count, directions = hit_corner.shape[0], hit_corner.shape[1]
    batch = outgoing.shape[2]
    for s in nb.prange(count):
        for i in range(directions):
            for b in range(batch):
                for c in range(3):
                    out[s, i, b, c] = 0.0
            if hit_corner[s, i, 0] < 0:
                continue
            for corner in range(3):
                t = hit_corner[s, i, corner]
                share = hit_weight[s, i, corner]
                for b in range(batch):
                    for c in range(3):
                        out[s, i, b, c] += share * outgoing[t, i, b, c]


@nb.njit(**KERNEL_OPTIONS)
def glossy_outgoing(incoming, directions, normal, specular, roughness, exponent, cos_weight, diffuse, out):
    """The radiance every sample sends towards every -d_j after one bounce: its diffuse part
    (the same for all j) plus the glossy lobe over the incoming radiance.

    incoming : (S, N, B, 3) float32; directions : (N, 3) float64 unit
    normal : (S, 3) float64; specular, roughness : (S,) float32; exponent : float64
    cos_weight : (S, N) float32; diffuse : (S, B, 3) float32, the diffuse radiance
    Output out (S, N, B, 3) float32.
    """
    count, n = cos_weight.shape
    batch = incoming.shape[2]
    for s in nb.prange(count):
        nx, ny, nz = normal[s, 0], normal[s, 1], normal[s, 2]
        acc = np.zeros((batch, 3), np.float64)
        for j in range(n):
            ox, oy, oz = -directions[j, 0], -directions[j, 1], -directions[j, 2]
            for b in range(batch):
                for c in range(3):
                    acc[b, c] = diffuse[s, b, c]
            if specular[s] > 0.0 and nx * ox + ny * oy + nz * oz > 0.0:
                for i in range(n):
                    w = cos_weight[s, i]
                    if w <= 0.0:
                        continue
                    g = specular[s] * w * lobe(nx, ny, nz, directions[i, 0], directions[i, 1], directions[i, 2],
                                               ox, oy, oz, roughness[s], exponent)
                    if g <= 0.0:
                        continue
                    for b in range(batch):
                        for c in range(3):
                            acc[b, c] += g * incoming[s, i, b, c]
            for b in range(batch):
                for c in range(3):
                    out[s, j, b, c] = acc[b, c]


@nb.njit(**KERNEL_OPTIONS)
def glossy_towards(incoming, directions, normal, specular, roughness, exponent, cos_weight, rows, view, out):
    """The glossy radiance the samples ``rows`` send towards ``view`` from the incoming
    radiance: sum_i specular * lobe(d_i, view) * cos_weight * incoming.

    incoming : (S, N, B, 3) float32; rows : (R,) int64 the samples the view sees;
    view : (3,) float64 unit. Output out (R, B, 3) float64.
    """
    n = directions.shape[0]
    batch = incoming.shape[2]
    for r in nb.prange(rows.shape[0]):
        s = rows[r]
        for b in range(batch):
            for c in range(3):
                out[r, b, c] = 0.0
        if specular[s] <= 0.0:
            continue
        for i in range(n):
            w = cos_weight[s, i]
            if w <= 0.0:
                continue
            g = specular[s] * w * lobe(normal[s, 0], normal[s, 1], normal[s, 2], directions[i, 0], directions[i, 1],
                                       directions[i, 2], view[0], view[1], view[2], roughness[s], exponent)
            if g <= 0.0:
                continue
            for b in range(batch):
                for c in range(3):
                    out[r, b, c] += g * incoming[s, i, b, c]


@nb.njit(**KERNEL_OPTIONS)
def splat_pixels(pixel, corners, weights, values, out):
    """Images from rays: out[k, pixel[r]] += sum over corners of weights[r] * values[corners[r], k].

    pixel : (R,) int64; corners : (R, 3) int64 rows of ``values``; weights : (R, 3) float32
    values : (Rows, B, 3) float64; out : (B, P, 3) float64, zeroed by the caller.
    One image per task, so the sums run in ray order whatever the thread count.
    """
    for k in nb.prange(values.shape[1]):
        for r in range(pixel.shape[0]):
            p = pixel[r]
            for corner in range(3):
                w = weights[r, corner]
                t = corners[r, corner]
                for c in range(3):
                    out[k, p, c] += w * values[t, k, c]


def warm_up() -> None:
    """Compile (or read from the cache) each kernel for the dtypes its callers pass."""
    s, n, b = 2, 3, 1
    normal = np.tile(np.array([0.0, 0.0, 1.0]), (s, 1))
    directions = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    specular = np.ones(s, np.float32)
    roughness = np.full(s, 0.5, np.float32)
    cos_weight = np.ones((s, n), np.float32)
    corners = np.zeros((s, n, 3), np.int32)
    weights = np.full((s, n, 3), 1 / 3, np.float32)
    field = np.zeros((s, n, b, 3), np.float32)
    lobe_many(normal, specular, roughness, 8.0, normal, normal, np.zeros(s))
    gather_diffuse(np.zeros((s, b, 3), np.float32), corners, weights, cos_weight, np.zeros((s, b, 3)))
    incoming_radiance(field, corners, weights, np.zeros_like(field))
    glossy_outgoing(field, directions, normal, specular, roughness, 8.0, cos_weight, np.zeros((s, b, 3), np.float32),
                    np.zeros_like(field))
    splat_pixels(np.zeros(1, np.int64), np.zeros((1, 3), np.int64), np.ones((1, 3), np.float32),
                 np.zeros((1, b, 3)), np.zeros((b, 1, 3)))
    glossy_towards(field, directions, normal, specular, roughness, 8.0, cos_weight, np.arange(s, dtype=np.int64),
                   np.array([0.0, 0.0, 1.0]), np.zeros((s, b, 3)))
