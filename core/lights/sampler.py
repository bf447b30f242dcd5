"""The direct-light sampler: M stratified points per surface sample over a lamp's extent.

Dimensions 0-1 of a 4D point set pick a point on the lamp (a direction in a sun's cone, a
point on a sphere, disk or area lamp); the texel's footprint has its own fixed points per
texel (core.sampling.footprint, shared with the visibility table), and lamp point j is
received at footprint point j % P. The set is the first four dimensions of Sobol's
sequence (Joe & Kuo's direction numbers), Owen-scrambled
per sample by the hash of Burley ("Practical Hash-based Owen Scrambling", JCGT 2020),
seeded by the sample's index, the lamp and the bake seed. So every sample sees a
differently scrambled, still stratified set (shadow banding becomes fine noise), and a
bake is deterministic: the same seed gives the same points.

Owen scrambling keeps each point uniformly distributed, so every estimate built on the
points is unbiased, and the first 2^m points of each sample stay an elementary net.
"""
from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass

import numpy as np

DIMENSIONS = 4
_BITS = 32

# (degree s, coefficients a, initial m) of Sobol dimensions 2..4 (Joe & Kuo, new-joe-kuo-6.21201);
# dimension 1 is the van der Corput sequence.
_SOBOL_PARAMETERS = ((1, 0, (1,)), (2, 1, (1, 3)), (3, 1, (1, 3, 1)))


def _direction_numbers(degree: int, coefficients: int, initial: tuple[int, ...]) -> np.ndarray:
    """(32,) uint64 direction numbers v_1..v_32 of one Sobol dimension, as 32-bit fractions."""
    v = [0] * (_BITS + 1)
    for i in range(1, degree + 1):
        v[i] = initial[i - 1] << (_BITS - i)
    for i in range(degree + 1, _BITS + 1):
        v[i] = v[i - degree] ^ (v[i - degree] >> degree)
        for k in range(1, degree):
            if (coefficients >> (degree - 1 - k)) & 1:
                v[i] ^= v[i - k]
    return np.array(v[1:], np.uint64)


_DIRECTIONS = np.stack([np.array([1 << (_BITS - 1 - k) for k in range(_BITS)], np.uint64)]
                       + [_direction_numbers(*p) for p in _SOBOL_PARAMETERS])  # (4, 32)


def sobol_point(index: int) -> np.ndarray:
    """(4,) uint32 point ``index`` of the unscrambled 4D Sobol sequence, as 32-bit fractions."""
    if index < _KEPT_POINTS:
        return sobol_points(_KEPT_POINTS)[index]
    return _sobol_point(index)


# The first points, which every texel's footprint and every lamp's sampler use, are
# computed once per process (each costs ~1 ms of Python).
_KEPT_POINTS = 256


@functools.lru_cache(maxsize=1)
def sobol_points(count: int) -> np.ndarray:
    """(count, 4) uint32 points 0 .. count - 1 of :func:`sobol_point`; read-only."""
    points = np.stack([_sobol_point(index) for index in range(count)]) if count else np.zeros((0, 4), np.uint32)
    points.flags.writeable = False
    return points


def _sobol_point(index: int) -> np.ndarray:
    bits = np.array([(index >> k) & 1 for k in range(_BITS)], bool)
    point = np.zeros(DIMENSIONS, np.uint64)
    for dimension in range(DIMENSIONS):
        for value in _DIRECTIONS[dimension][bits]:
            point[dimension] ^= value
    return point.astype(np.uint32)


def hash32(x: np.ndarray) -> np.ndarray:
    """A 32-bit integer mixer (lowbias32, Wellons); (n,) uint32 -> (n,) uint32."""
    x = np.asarray(x, np.uint32).copy()
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def _reverse_bits(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.uint32)
    x = ((x >> np.uint32(1)) & np.uint32(0x55555555)) | ((x & np.uint32(0x55555555)) << np.uint32(1))
    x = ((x >> np.uint32(2)) & np.uint32(0x33333333)) | ((x & np.uint32(0x33333333)) << np.uint32(2))
    x = ((x >> np.uint32(4)) & np.uint32(0x0F0F0F0F)) | ((x & np.uint32(0x0F0F0F0F)) << np.uint32(4))
    x = ((x >> np.uint32(8)) & np.uint32(0x00FF00FF)) | ((x & np.uint32(0x00FF00FF)) << np.uint32(8))
    return (x >> np.uint32(16)) | (x << np.uint32(16))


def owen_scramble(x: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Burley's hash-based nested uniform (Owen) scramble of 32-bit fractions ``x`` (n,) uint32
    (or one shared by all) with one ``seed`` (n,) uint32 each: a bit flips depending on all
    the bits above it only."""
    x = _reverse_bits(x)
    x = x + np.asarray(seed, np.uint32)
    x ^= x * np.uint32(0x6C50B47C)
    x ^= x * np.uint32(0xB82F1E52)
    x ^= x * np.uint32(0xC7AFE638)
    x ^= x * np.uint32(0x8D22F6E6)
    return _reverse_bits(x)


def stream_of(name: str) -> int:
    """A lamp's stream number (so two lamps never share scrambles), stable across runs."""
    return zlib.crc32(name.encode("utf-8", "surrogatepass"))


@dataclass(frozen=True)
class DirectSampler:
    """M jointly stratified 4D points per sample, decorrelated per sample, lamp and seed.

    count : points per sample (1: a single point, the lamp's centre and the sample's own
        position, which is how a hard lamp is traced)
    seed : the bake seed
    """

    count: int
    seed: int = 0

    def scrambles(self, sample_ids: np.ndarray, stream: int = 0) -> np.ndarray:
        """(4, K) uint32 Owen-scramble seeds of samples ``sample_ids`` (K,) integer (their
        indices in the bake) for a lamp's ``stream`` (:func:`stream_of`), one per dimension."""
        ids = np.asarray(sample_ids).astype(np.uint32)
        base = hash32(ids ^ hash32(np.array([self.seed & 0xFFFFFFFF], np.uint32))
                     ^ hash32(np.array([stream & 0xFFFFFFFF], np.uint32) + np.uint32(0x9E3779B9)))
        return np.stack([hash32(base + np.uint32((0x68E31DA4 * (d + 1)) & 0xFFFFFFFF)) for d in range(DIMENSIONS)])

    def uniforms(self, point: int, sample_ids: np.ndarray | None = None, stream: int = 0,
                 scrambles: np.ndarray | None = None) -> np.ndarray:
        """Point ``point`` (0 <= point < count) of every sample's scrambled set.

        sample_ids, stream : as :meth:`scrambles`, or ``scrambles`` computed once for all points
        Returns (K, 4) float64 in [0, 1), 24 bits each (exact in float32).
        """
        seeds = self.scrambles(sample_ids, stream) if scrambles is None else scrambles
        sobol = sobol_point(point)
        result = np.empty((seeds.shape[1], DIMENSIONS))
        for dimension in range(DIMENSIONS):
            scrambled = owen_scramble(np.array([sobol[dimension]], np.uint32), seeds[dimension])
            result[:, dimension] = (scrambled >> np.uint32(8)) * 2.0 ** -24
        return result


def square_to_disk(u: np.ndarray) -> np.ndarray:
    """Shirley-Chiu concentric map of [0, 1)^2 (n, 2) to the unit disk (n, 2): area preserving,
    so the points keep their stratification."""
    a = 2.0 * u[:, 0] - 1.0
    b = 2.0 * u[:, 1] - 1.0
    first = np.abs(a) > np.abs(b)
    radius = np.where(first, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(first, (np.pi / 4) * (b / a), (np.pi / 2) - (np.pi / 4) * (a / b))
    phi = np.nan_to_num(phi)
    return np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)


def orthonormal_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (n, 3) completing unit ``axis`` (n, 3) to a right-handed frame
    (Duff et al. 2017, branchless)."""
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    tangent = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    bitangent = np.stack([b, sign + y * y * a, -y], axis=1)
    return tangent, bitangent


def uniform_cone(axis: np.ndarray, one_minus_cos, u: np.ndarray) -> np.ndarray:
    """Unit directions (n, 3) uniform in solid angle in the cone around unit ``axis`` (n, 3),
    or (1, 3) shared by all, with 1 - cos(half angle) ``one_minus_cos`` (n,) or a float,
    from [0, 1)^2 points ``u`` (n, 2).
    The disk-then-lift mapping Cycles uses (``sample_uniform_cone``), which keeps strata."""
    disk = square_to_disk(u)
    r2 = np.einsum("nd,nd->n", disk, disk)
    cos_theta = 1.0 - r2 * one_minus_cos
    sin_theta = np.sqrt(np.clip(1.0 - cos_theta * cos_theta, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(r2 > 0, sin_theta / np.sqrt(r2), 0.0)
    tangent, bitangent = orthonormal_frame(axis)
    return ((disk[:, :1] * scale[:, None]) * tangent + (disk[:, 1:] * scale[:, None]) * bitangent
            + cos_theta[:, None] * axis)


def cosine_hemisphere(normal: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Cosine-distributed unit directions (n, 3) about unit ``normal`` (n, 3)."""
    disk = square_to_disk(u)
    z = np.sqrt(np.clip(1.0 - np.einsum("nd,nd->n", disk, disk), 0.0, None))
    tangent, bitangent = orthonormal_frame(normal)
    return disk[:, :1] * tangent + disk[:, 1:] * bitangent + z[:, None] * normal


def spherical_rectangle(origin: np.ndarray, corner: np.ndarray, edge_x: np.ndarray, edge_y: np.ndarray,
                        u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of a rectangle uniform in the solid angle it subtends from each origin (Ureña,
    Fajardo and King, "An Area-Preserving Parametrization for Spherical Rectangles", EGSR 2013;
    Cycles samples rectangular area lamps so). Area preserving, so ``u``'s strata carry over.

    Near the rectangle, uniform points on its area give irradiance estimates of unbounded
    variance (cos / r^2 of the nearest points); uniform in solid angle, only the receiver's
    cosine varies.

    Parameters
    ----------
    origin : (n, 3) float64 where the rectangle is seen from
    corner : (3,) float64 one corner; ``edge_x``, ``edge_y`` (3,) float64 the two orthogonal
        edges from it
    u : (n, 2) float64 points of [0, 1)^2

    Returns
    -------
    point : (n, 3) float64 the chosen points on the rectangle
    solid_angle : (n,) float64 the solid angle the rectangle subtends from each origin (the
        points' density is its inverse); 0 where the origin lies in the rectangle's plane
    usable : (n,) bool where the mapping is numerically sound (origins not in the plane, and
        a solid angle that float64 resolves); elsewhere ``point`` is meaningless
    """
    length_x, length_y = float(np.linalg.norm(edge_x)), float(np.linalg.norm(edge_y))
    axis_x, axis_y = edge_x / length_x, edge_y / length_y
    axis_z = np.cross(axis_x, axis_y)
    offset = corner[None, :] - origin
    z0 = offset @ axis_z
    # The frame's z points away from the rectangle, as the parametrization assumes.
    flip = np.where(z0 > 0.0, -1.0, 1.0)
    z0 = z0 * flip
    x0, y0 = offset @ axis_x, offset @ axis_y
    x1, y1 = x0 + length_x, y0 + length_y

    def corner_vector(x, y):
        return np.stack([x, y, z0], axis=1)

    v00, v01, v10, v11 = corner_vector(x0, y0), corner_vector(x0, y1), corner_vector(x1, y0), corner_vector(x1, y1)

    def unit_normal(a, b):
        c = np.cross(a, b)
        return c / np.maximum(np.linalg.norm(c, axis=1), 1e-300)[:, None]

    n0, n1, n2, n3 = unit_normal(v00, v10), unit_normal(v10, v11), unit_normal(v11, v01), unit_normal(v01, v00)

    def angle(a, b):
        return np.arccos(np.clip(-np.einsum("nd,nd->n", a, b), -1.0, 1.0))

    g0, g1, g2, g3 = angle(n0, n1), angle(n1, n2), angle(n2, n3), angle(n3, n0)
    b0, b1 = n0[:, 2], n2[:, 2]
    k = 2.0 * np.pi - g2 - g3
    solid_angle = np.maximum(g0 + g1 - k, 0.0)
    # Below ~1e-9 sr the sum of four angles near pi/2 has lost its digits to cancellation.
    usable = (z0 < -1e-9 * max(length_x, length_y)) & (solid_angle > 1e-9)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        au = u[:, 0] * solid_angle + k
        fu = (np.cos(au) * b0 - b1) / np.sin(au)
        cu = np.clip(np.sign(fu) / np.sqrt(fu * fu + b0 * b0), -1.0, 1.0)
        xu = np.clip(-(cu * z0) / np.sqrt(np.maximum(1.0 - cu * cu, 1e-300)), x0, x1)
        d = np.sqrt(xu * xu + z0 * z0)
        h0 = y0 / np.sqrt(d * d + y0 * y0)
        h1 = y1 / np.sqrt(d * d + y1 * y1)
        hv = h0 + u[:, 1] * (h1 - h0)
        hv2 = hv * hv
        yv = np.where(hv2 < 1.0 - 1e-6, hv * d / np.sqrt(np.maximum(1.0 - hv2, 1e-300)), y1)
    usable &= np.isfinite(xu) & np.isfinite(yv)
    local = np.stack([np.where(usable, xu, 0.0), np.where(usable, yv, 0.0)], axis=1)
    point = origin + local[:, :1] * axis_x + local[:, 1:] * axis_y + (z0 * flip)[:, None] * axis_z
    return point, np.where(usable, solid_angle, 0.0), usable
