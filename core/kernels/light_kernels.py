"""Compiled (numba) kernels of direct light: one point of a lamp without extent (a sun of
angle 0, a point or spot of radius 0) at every sample, received at the sample or at one of
its footprint points (core.lights.lamps.LampPoints), in parallel over samples.

Imported only through :mod:`core.kernels`. Every value is computed in float64 from the
same inputs as the numpy code (core.lights.lamps._hard_contribution), so the two agree to
float rounding; the numpy code stays as the fallback and is what the kernel is tested
against.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import KERNEL_OPTIONS
from .bits import bits_float32, float32_bits

# Lamp kinds as the kernel takes them.
SUN, POINT, SPOT = 0, 1, 2


@nb.njit(inline="always")
def _dot(a0, a1, a2, b0, b1, b2):
    """A 3-vector dot product summed as numpy's einsum("kd,kd->k") sums it on x86-64
    (numpy 1.26: two SIMD lanes, (0 + 2) + 1), so the cosines match the numpy code's bits there."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@nb.njit(**KERNEL_OPTIONS)
def hard_lamp_point(kind, centre, direction, cos_half, band, position, normal, offsets, offset_slot,
                    point_normals, normal_slot, scale, irradiance, to_light, distance, receiver, lit):
    """One point of a hard lamp at every sample, and whether it can light the sample.

    kind : SUN, POINT or SPOT; centre : (3,) float64 the lamp's position; direction : (3,)
    float64 the unit direction the light travels along; cos_half, band : float64 a spot's
    cone (cosine of the half angle, and the blend band in cosine; band <= 0: a hard edge).
    position, normal : (K, 3) float64 the samples and their shading normals.
    offsets : (K, P, 3) float32 footprint offsets, received at slot ``offset_slot`` (< 0:
    at the sample itself). point_normals : (K, P, 3) float32 the shading normals at the
    footprint points, slot ``normal_slot`` (< 0: ``normal``). scale : (3,) float64 power x
    colour over the point count.

    Outputs: irradiance (K, 3) float64 unshadowed; to_light (K, 3) float64 unit; distance
    (K,) float64 (inf for a sun); receiver (K, 3) float64 where the point is received
    (written only with ``offset_slot`` >= 0); lit (K,) bool: the lamp is above the shading
    normal's horizon and gives some light (a shadow ray decides the rest).
    """
    for k in nb.prange(position.shape[0]):
        r0, r1, r2, n0, n1, n2, t0, t1, t2, far, value = _hard_point(
            kind, centre, direction, cos_half, band, position, normal, offsets, offset_slot, point_normals,
            normal_slot, k)
        if offset_slot >= 0:
            receiver[k, 0], receiver[k, 1], receiver[k, 2] = r0, r1, r2
        to_light[k, 0], to_light[k, 1], to_light[k, 2] = t0, t1, t2
        distance[k] = far
        gives = False
        for c in range(3):
            irradiance[k, c] = value * scale[c]
            gives = gives or irradiance[k, c] > 0.0
        lit[k] = gives and _dot(t0, t1, t2, n0, n1, n2) > 0.0


@nb.njit(**KERNEL_OPTIONS)
def hard_lamp_decided(kind, centre, direction, cos_half, band, position, normal, offsets, point_normals, scale,
                      rows, decided, visible, count, small, first_points, small_factor, light, pending):
    """Every point of a hard lamp, summed, at the samples that need no shadow ray: what
    core.transport.direct.lamp_irradiance's loop adds up for them, point by point, in the
    same order and float operations, without a pass over memory per point.

    Arguments as :func:`hard_lamp_point`, with ``offsets`` (K, P, 3) float32 (point j at slot
    j % P) and ``point_normals`` (K, Q, 3) float32, or (K, 0, 3) for the samples' own normals.
    rows : (R,) int64 the samples to do; decided : (K,) bool whose shadow the probes decided,
    and visible : (K,) bool whether the lamp then reaches it (not shadowed, a receiver);
    count : the lamp's points; small : (K,) bool decided samples whose first ``first_points``
    points, times ``small_factor``, stand for all. Outputs, at ``rows`` only: light (K, 3)
    float64; pending (K,) bool an undecided sample some point of which is lit (it needs shadow
    rays: its light is not written). An undecided sample no point lights gets 0.
    """
    points, normal_points = offsets.shape[1], point_normals.shape[1]
    for j in nb.prange(rows.shape[0]):
        k = rows[j]
        a0, a1, a2 = 0.0, 0.0, 0.0
        seen = 1.0 if decided[k] and visible[k] else 0.0
        pending[k] = False
        for point in range(count):
            if point == first_points and small[k]:
                a0, a1, a2 = a0 * small_factor, a1 * small_factor, a2 * small_factor
                break
            _, _, _, n0, n1, n2, t0, t1, t2, _, value = _hard_point(
                kind, centre, direction, cos_half, band, position, normal, offsets, point % points, point_normals,
                point % normal_points if normal_points > 0 else -1, k)
            i0, i1, i2 = value * scale[0], value * scale[1], value * scale[2]
            lit = (i0 > 0.0 or i1 > 0.0 or i2 > 0.0) and _dot(t0, t1, t2, n0, n1, n2) > 0.0
            if lit and not decided[k]:
                pending[k] = True
                break
            weight = seen if lit else 0.0
            a0 += i0 * weight
            a1 += i1 * weight
            a2 += i2 * weight
        if not pending[k]:
            light[k, 0], light[k, 1], light[k, 2] = a0, a1, a2


@nb.njit(inline="always")
def _hard_point(kind, centre, direction, cos_half, band, position, normal, offsets, offset_slot, point_normals,
                normal_slot, k):
    """Sample k's receiver (r), shading normal (n), unit direction to the lamp (t), distance and
    unshadowed irradiance before the lamp's colour and power, as :func:`hard_lamp_point` documents."""
    r0, r1, r2 = position[k, 0], position[k, 1], position[k, 2]
    if offset_slot >= 0:
        r0 += np.float64(offsets[k, offset_slot, 0])
        r1 += np.float64(offsets[k, offset_slot, 1])
        r2 += np.float64(offsets[k, offset_slot, 2])
    if normal_slot >= 0:
        n0 = np.float64(point_normals[k, normal_slot, 0])
        n1 = np.float64(point_normals[k, normal_slot, 1])
        n2 = np.float64(point_normals[k, normal_slot, 2])
    else:
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
    if kind == SUN:
        t0, t1, t2 = -direction[0], -direction[1], -direction[2]
        far = np.inf
        cosine = max(_dot(n0, n1, n2, t0, t1, t2), 0.0)
        value = cosine
    else:
        o0, o1, o2 = centre[0] - r0, centre[1] - r1, centre[2] - r2
        far = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
        safe = max(far, 1e-12)
        t0, t1, t2 = o0 / safe, o1 / safe, o2 / safe
        cosine = max(_dot(n0, n1, n2, t0, t1, t2), 0.0)
        value = cosine / (4.0 * np.pi * safe * safe)
        if kind == SPOT:
            cos_angle = -t0 * direction[0] - t1 * direction[1] - t2 * direction[2]
            if band <= 0.0:
                value = value if cos_angle > cos_half else 0.0
            else:
                x = min(max((cos_angle - cos_half) / band, 0.0), 1.0)
                value = value * (x * x * (3.0 - 2.0 * x))
        if not far > 1e-12:
            value = 0.0
    return r0, r1, r2, n0, n1, n2, t0, t1, t2, far, value


@nb.njit(inline="always")
def _lift_amount(shading_cosine, geometric_cosine, cutoff):
    """core.sampling.terminator.lift_amount of one ray, in its float64 operations."""
    if not cutoff > 0.0:
        return 0.0
    nl = abs(shading_cosine)
    ngl = -geometric_cosine if shading_cosine < 0.0 else geometric_cosine
    if nl < cutoff:
        return min(max(2.0 - (ngl + nl) / cutoff, 0.0), 1.0)
    return min(max(1.0 - ngl / cutoff, 0.0), 1.0)


@nb.njit(**KERNEL_OPTIONS)
def shadow_ray_setup(rays, sample_rows, distance, to_light, moved, position, normal, geometric, terminator, cutoff,
                     sample_origins, centre, centred, keep, int_scale, float_scale, origin_limit, origins, directions,
                     limits, lift):
    """The shadow rays of rows ``rays`` of one sampler point (core.transport.direct.shadow_rays),
    bitwise as its numpy code makes them: each ray's length (its distance times ``keep``, inf
    for a sun) and direction; its origin off the surface (core.visibility.rays.RayScene.
    ray_origins) from where the point was received, lifted towards the smooth surface
    (core.sampling.terminator) where the light is near or below the flat face's horizon; and
    where no ray of the call is lifted and the point was received at the samples themselves,
    the samples' own origins. In parallel over rays.

    rays, sample_rows : (n,) int64 rows of the point's arrays and the rays' samples
    distance : (m,) float64; to_light : (m, 3) float64 unit; moved : (m, 3) float64 where the
        point was received, or (0, 3): at the samples' positions
    position, normal, geometric : (K, 3) float64; terminator : (K, 3) float64 and cutoff : (K,)
        float64, or (0, 3) and (0,) where no sample is on a smooth face
    sample_origins : (K, 3) the samples' origins (float32, or float64 world positions where the
        ray scene is ``centred`` on ``centre`` (3,) float64)
    keep : float64 1 - core.tolerances.SHADOW_RAY_SHORTEN; int_scale, float_scale,
        origin_limit : float32, core.tolerances' RAY_OFFSET_* constants
    origins : (n, 3) sample_origins' dtype, out; directions : (n, 3) float64, out; limits :
        (n,) float32, out; lift : (n, 3) float64, scratch
    """
    count = rays.shape[0]
    smooth = terminator.shape[0] > 0
    for r in nb.prange(count):
        e = rays[r]
        s = sample_rows[r]
        length = distance[e]
        limits[r] = np.float32(length * keep if np.isfinite(length) else np.inf)
        t0, t1, t2 = to_light[e, 0], to_light[e, 1], to_light[e, 2]
        directions[r, 0] = t0
        directions[r, 1] = t1
        directions[r, 2] = t2
        if smooth:
            amount = _lift_amount(_dot(normal[s, 0], normal[s, 1], normal[s, 2], t0, t1, t2),
                                  _dot(geometric[s, 0], geometric[s, 1], geometric[s, 2], t0, t1, t2), cutoff[s])
            for axis in range(3):
                lift[r, axis] = terminator[s, axis] * amount
    # A serial scan, not a reduction in the loop above: numba 0.68.1 cannot type that
    # reduction under Python 3.13 ("unexpected cycle in lookup()").
    lifted = 0
    if smooth:
        for r in range(count):
            if lift[r, 0] != 0.0 or lift[r, 1] != 0.0 or lift[r, 2] != 0.0:
                lifted = 1
                break
    from_samples = moved.shape[0] == 0
    for r in nb.prange(count):
        s = sample_rows[r]
        if from_samples and lifted == 0:
            for axis in range(3):
                origins[r, axis] = sample_origins[s, axis]
            continue
        for axis in range(3):
            x = position[s, axis] if from_samples else moved[rays[r], axis]
            if lifted > 0:
                x = x + lift[r, axis]
            origins[r, axis] = _origin_axis(x, geometric[s, axis], centre[axis], centred, int_scale, float_scale,
                                            origin_limit)


@nb.njit(inline="always")
def _origin_axis(x, geometric, centre, centred, int_scale, float_scale, origin_limit):
    """One coordinate of a ray's origin stepped off the surface along the geometric normal's
    coordinate (core.visibility.rays.offset_ray_origins' float32 steps), for a ray scene
    ``centred`` on ``centre`` or at the origin. Returned as float64: back in world space where
    centred, else the float32 step itself (exact in a float32 array)."""
    if centred:
        x = x - centre
    p = np.float32(x)
    n = np.float32(geometric)
    if abs(p) < origin_limit:
        stepped = p + float_scale * n
    else:
        offset = np.int32(int_scale * n)
        bits = float32_bits(p)
        stepped = bits_float32(np.int32(bits - offset) if p < np.float32(0.0) else np.int32(bits + offset))
    if centred:
        return np.float64(stepped) + centre
    return np.float64(stepped)


@nb.njit(inline="always")
def _shadow_ray(k, r0, r1, r2, t0, t1, t2, far, normal, geometric, terminator, cutoff, keep, ray_centre, centred,
                int_scale, float_scale, origin_limit):
    """Sample k's shadow ray from where its point was received (r0, r1, r2) towards the unit
    (t0, t1, t2), ``far`` away: its origin, lifted towards the smooth surface where
    ``terminator`` has rows and stepped off the face (:func:`_origin_axis`), and its length,
    as :func:`shadow_ray_setup` makes them (arguments as there)."""
    if terminator.shape[0] > 0:
        amount = _lift_amount(_dot(normal[k, 0], normal[k, 1], normal[k, 2], t0, t1, t2),
                              _dot(geometric[k, 0], geometric[k, 1], geometric[k, 2], t0, t1, t2), cutoff[k])
        r0 = r0 + terminator[k, 0] * amount
        r1 = r1 + terminator[k, 1] * amount
        r2 = r2 + terminator[k, 2] * amount
    return (_origin_axis(r0, geometric[k, 0], ray_centre[0], centred, int_scale, float_scale, origin_limit),
            _origin_axis(r1, geometric[k, 1], ray_centre[1], centred, int_scale, float_scale, origin_limit),
            _origin_axis(r2, geometric[k, 2], ray_centre[2], centred, int_scale, float_scale, origin_limit),
            np.float32(far * keep if np.isfinite(far) else np.inf))


@nb.njit(**KERNEL_OPTIONS)
def hard_lamp_edge_rays(kind, centre, direction, cos_half, band, position, normal, geometric, terminator, cutoff,
                        offsets, point_normals, first, receives, scale, keep, ray_centre, centred, int_scale,
                        float_scale, origin_limit, irradiance, lit, origins, directions, limits):
    """Points ``first`` to ``first + J - 1`` of a hard lamp at E samples that a shadow edge
    crosses, each received at its own point of the samples' dense footprints, and each lit
    point's shadow ray: in one pass what :func:`hard_lamp_point` then :func:`shadow_ray_setup`
    give point by point (core.transport.direct._edge_irradiance), bitwise. In parallel over samples.

    kind, centre, direction, cos_half, band, scale : the lamp, as :func:`hard_lamp_point`
    position, normal, geometric : (E, 3) float64 the samples, their shading and geometric
        normals; terminator : (E, 3) float64 and cutoff : (E,) float64, or (0, 3) and (0,)
        where no sample is on a smooth face (core.sampling.terminator)
    offsets : (E, P, 3) float32 footprint offsets (point j at slot j % P); point_normals :
        (E, Q, 3) float32 the shading normals there, or (E, 0, 3): the samples' own
    first : int the first point; receives : (E,) bool the lamp lights the sample (light linking)
    keep, ray_centre, centred, int_scale, float_scale, origin_limit : as :func:`shadow_ray_setup`
        (``ray_centre`` its ``centre``)
    Outputs, (J, E, ...) point by point: irradiance (J, E, 3) float64 unshadowed; lit (J, E)
    bool (the point gives light above its normal's horizon at a receiving sample); origins
    (J, E, 3) (float32, or float64 where ``centred``), directions (J, E, 3) float64 and limits
    (J, E) float32, written where ``lit`` only.
    """
    points, normal_points = offsets.shape[1], point_normals.shape[1]
    for k in nb.prange(position.shape[0]):
        for j in range(lit.shape[0]):
            point = first + j
            r0, r1, r2, n0, n1, n2, t0, t1, t2, far, value = _hard_point(
                kind, centre, direction, cos_half, band, position, normal, offsets, point % points, point_normals,
                point % normal_points if normal_points > 0 else -1, k)
            gives = False
            for c in range(3):
                irradiance[j, k, c] = value * scale[c]
                gives = gives or irradiance[j, k, c] > 0.0
            on = gives and _dot(t0, t1, t2, n0, n1, n2) > 0.0 and receives[k]
            lit[j, k] = on
            if not on:
                continue
            directions[j, k, 0], directions[j, k, 1], directions[j, k, 2] = t0, t1, t2
            origins[j, k, 0], origins[j, k, 1], origins[j, k, 2], limits[j, k] = _shadow_ray(
                k, r0, r1, r2, t0, t1, t2, far, normal, geometric, terminator, cutoff, keep, ray_centre, centred,
                int_scale, float_scale, origin_limit)


@nb.njit(**KERNEL_OPTIONS)
def corner_probe_rays(is_sun, centre, direction, position, normal, geometric, terminator, cutoff, corners, corner,
                      receives, keep, ray_centre, centred, int_scale, float_scale, origin_limit, aimed, origins,
                      directions, limits):
    """One corner probe of a texel's footprint box at every sample (core.transport.direct.
    _penumbra_probes): the ray from the box's corner to the lamp's centre, made in one pass as
    core.lights.lamps.centre_probe, the aim test and :func:`shadow_ray_setup` make it, bitwise.
    In parallel over samples.

    is_sun : bool (a sun's centre is its direction, at infinity); centre : (3,) float64 the
    lamp's position; direction : (3,) float64 the direction its light travels
    position, normal, geometric : (K, 3) float64; terminator : (K, 3) float64 and cutoff :
        (K,) float64, or (0, 3) and (0,) where no sample is on a smooth face
    corners : (K, 4, 3) float32 the footprint boxes' corners, offsets from the samples;
        corner : int, which one; receives : (K,) bool the lamp lights the sample
    keep, ray_centre, centred, int_scale, float_scale, origin_limit : as :func:`shadow_ray_setup`
    Outputs: aimed (K,) bool (the lamp's centre above the sample's shading horizon, at a
    receiving sample); origins (K, 3) (float32, or float64 where ``centred``), directions
    (K, 3) float64 and limits (K,) float32, written where ``aimed`` only.
    """
    for k in nb.prange(position.shape[0]):
        m0 = position[k, 0] + np.float64(corners[k, corner, 0])
        m1 = position[k, 1] + np.float64(corners[k, corner, 1])
        m2 = position[k, 2] + np.float64(corners[k, corner, 2])
        if is_sun:
            t0, t1, t2 = -direction[0], -direction[1], -direction[2]
            far = np.inf
        else:
            o0, o1, o2 = centre[0] - m0, centre[1] - m1, centre[2] - m2
            far = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
            safe = max(far, 1e-12)
            t0, t1, t2 = o0 / safe, o1 / safe, o2 / safe
        on = _dot(t0, t1, t2, normal[k, 0], normal[k, 1], normal[k, 2]) > 0.0 and receives[k]
        aimed[k] = on
        if not on:
            continue
        directions[k, 0], directions[k, 1], directions[k, 2] = t0, t1, t2
        origins[k, 0], origins[k, 1], origins[k, 2], limits[k] = _shadow_ray(
            k, m0, m1, m2, t0, t1, t2, far, normal, geometric, terminator, cutoff, keep, ray_centre, centred,
            int_scale, float_scale, origin_limit)


@nb.njit(**KERNEL_OPTIONS)
def edge_light_add(irradiance, lit, light):
    """Adds each sample's lit points' irradiance (J, E, 3) float64 where ``lit`` (J, E) bool
    (shadowed points cleared), point by point in order, to ``light`` (E, 3) float64: bitwise
    the numpy loop's ``light += irradiance[j] * lit[j][:, None]``. In parallel over samples."""
    for k in nb.prange(light.shape[0]):
        for j in range(lit.shape[0]):
            if lit[j, k]:
                for c in range(3):
                    light[k, c] += irradiance[j, k, c]


@nb.njit(inline="always")
def _clip_below(x):
    """np.clip(x, 0.0, None) of one value: NaN stays NaN, -0.0 becomes +0.0."""
    return x if x > 0.0 or x != x else 0.0


@nb.njit(**KERNEL_OPTIONS)
def emitter_patch(position, normal, geometric, point, point_normal, to_point, distance, transfer, lit):
    """One patch of a small emitter (core.lights.emitters) seen from every sample, bitwise
    as core.lights.lamps.surface_to_point and emitter_irradiance's lit test compute it
    (numpy's norm sums (0 + 1) + 2; its einsum as :func:`_dot`). In parallel over samples.

    position, normal, geometric : (K, 3) float64 the samples, shading and geometric normals
    point, point_normal : (3,) float64 the patch and the unit normal it emits along
    to_point : (K, 3) float64 unit, distance : (K,) float64, transfer : (K,) float64
        cos(receiver) cos(patch) / distance^2, lit : (K,) bool (transfer > 0 and the patch
        in front of the geometric face): out
    """
    p0, p1, p2 = point[0], point[1], point[2]
    n0, n1, n2 = point_normal[0], point_normal[1], point_normal[2]
    for k in nb.prange(position.shape[0]):
        o0, o1, o2 = p0 - position[k, 0], p1 - position[k, 1], p2 - position[k, 2]
        length = np.sqrt((o0 * o0 + o1 * o1) + o2 * o2)
        # np.maximum: a NaN length stays NaN.
        safe = 1e-12 if length < 1e-12 else length
        t0, t1, t2 = o0 / safe, o1 / safe, o2 / safe
        to_point[k, 0] = t0
        to_point[k, 1] = t1
        to_point[k, 2] = t2
        distance[k] = length
        cos_receiver = _clip_below(_dot(normal[k, 0], normal[k, 1], normal[k, 2], t0, t1, t2))
        cos_patch = _clip_below(-_dot(t0, t1, t2, n0, n1, n2))
        value = cos_receiver * cos_patch / (safe * safe) if length > 1e-12 else 0.0
        transfer[k] = value
        lit[k] = value > 0.0 and _dot(geometric[k, 0], geometric[k, 1], geometric[k, 2], t0, t1, t2) > 0.0


@nb.njit(**KERNEL_OPTIONS)
def emitter_rays(index, origins, to_point, distance, keep, ray_origins, directions, limits):
    """The shadow rays of the lit samples ``index`` (n,) int64 towards one patch: their
    origins (n, 3) (``origins``' dtype), directions (n, 3) float64 and lengths (n,) float32
    (``distance`` times ``keep``), out. In parallel over rays."""
    for r in nb.prange(index.shape[0]):
        k = index[r]
        for axis in range(3):
            ray_origins[r, axis] = origins[k, axis]
            directions[r, axis] = to_point[k, axis]
        limits[r] = np.float32(distance[k] * keep)


@nb.njit(**KERNEL_OPTIONS)
def emitter_add(index, occluded, transfer, area, radiance, irradiance):
    """Adds one patch's light, area x transfer x radiance (3,) float64, to ``irradiance``
    (K, 3) float64 at the lit samples ``index`` (n,) int64 whose ray is not ``occluded``
    (n,) bool, as emitter_irradiance's numpy code adds it. In parallel over rays (each
    sample once)."""
    for r in nb.prange(index.shape[0]):
        if occluded[r]:
            continue
        k = index[r]
        weight = area * transfer[k]
        for channel in range(3):
            irradiance[k, channel] += weight * radiance[channel]


@nb.njit(**KERNEL_OPTIONS)
def footprint_curvature(footprint_normals, normal, cosine, curved):
    """Whether any footprint point's normal turns away from its sample's ``normal`` by more
    than ``cosine``: core.transport.direct.curved_footprints' einsum and minimum, bitwise
    (the float32 normals widened to float64, summed as :func:`_dot`), without its (K, P)
    float64 temporary. In parallel over samples.

    footprint_normals : (K, P, 3) float32; normal : (K, 3) float64; cosine : float64;
    curved : (K,) bool, out
    """
    for k in nb.prange(normal.shape[0]):
        n0, n1, n2 = normal[k, 0], normal[k, 1], normal[k, 2]
        lowest = np.inf
        for p in range(footprint_normals.shape[1]):
            value = _dot(np.float64(footprint_normals[k, p, 0]), np.float64(footprint_normals[k, p, 1]),
                         np.float64(footprint_normals[k, p, 2]), n0, n1, n2)
            # numpy's minimum: a NaN wins.
            if value < lowest or value != value:
                lowest = value
                if value != value:
                    break
        curved[k] = lowest < cosine
