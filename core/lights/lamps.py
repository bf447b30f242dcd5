"""Direct irradiance from lamps, in Cycles' units (see DESIGN.md, verified by tests).

Every lamp is reduced to one or more points per sample (one for a hard lamp, the
direct-light sampler's stratified points over a lamp's extent otherwise): the
irradiance each would deliver unshadowed, the unit direction towards it and its
distance. Shadowing is applied by the caller (fractions or exact rays).
"""
from __future__ import annotations

import copy
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..errors import BakeRefused
from ..scene import Light
from .polygons import clip_above, polygon_form_factor
from .sampler import (
    DirectSampler,
    cosine_hemisphere,
    orthonormal_frame,
    spherical_rectangle,
    square_to_disk,
    stream_of,
    uniform_cone,
)


@dataclass
class LightContribution:
    """Unshadowed irradiance of one virtual point of a lamp at every sample.

    irradiance : (K, 3) float64 W/m^2 (RGB)
    to_light : (K, 3) float64 unit vectors
    distance : (K,) float64 (inf for a sun)
    position : (K, 3) float64 where in its footprint each sample received it; None: at the
        sample itself (shadow rays then start from the sample's own origin)
    lit : (K,) bool the point is above the horizon of the normal it is received with and
        gives some light, where the compiled kernel computed it; None: the caller tests it
    """

    irradiance: np.ndarray
    to_light: np.ndarray
    distance: np.ndarray
    position: np.ndarray | None = None
    lit: np.ndarray | None = None


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def spot_mask(light: Light, from_light: np.ndarray) -> np.ndarray:
    """Cycles' spot cone: smoothstep of (cos - cos(half angle)) over the blend band."""
    cos_angle = from_light @ np.asarray(light.direction, np.float64)
    cos_half = np.cos(light.spot_size / 2.0)
    band = (1.0 - cos_half) * light.spot_blend
    if band <= 0.0:
        return (cos_angle > cos_half).astype(np.float64)
    return _smoothstep((cos_angle - cos_half) / band)


def surface_to_point(position: np.ndarray, normal: np.ndarray, point: np.ndarray, point_normal: np.ndarray):
    """Geometry between receivers and one small emitting patch facing ``point_normal``.

    Returns
    -------
    to_point : (K, 3) float64 unit vectors from each receiver to the patch
    distance : (K,) float64
    transfer : (K,) float64 cos(receiver) * cos(patch) / distance^2 (0 behind either
        side, or where receiver and patch coincide); times radiance * patch area it is
        the irradiance the patch delivers
    """
    offset = point - position
    distance = np.linalg.norm(offset, axis=1)
    safe = np.maximum(distance, 1e-12)
    to_point = offset / safe[:, None]
    cos_receiver = np.clip(np.einsum("kd,kd->k", normal, to_point), 0.0, None)
    # Summed in the order of core.kernels.light_kernels._dot (a matrix product's BLAS order
    # could not be matched by the compiled twin, emitter_patch).
    n = np.asarray(point_normal, np.float64)
    cos_patch = np.clip(-((to_point[:, 0] * n[0] + to_point[:, 2] * n[2]) + to_point[:, 1] * n[1]), 0.0, None)
    transfer = np.where(distance > 1e-12, cos_receiver * cos_patch / (safe * safe), 0.0)
    return to_point, distance, transfer


# What a lamp's direct light is proportional to rather than shaped by.
_SCALE_FIELDS = ("strength", "color", "group")


def lamp_shape_key(light: Light) -> tuple:
    """A hashable key of everything about ``light`` except its power, colour and light group.

    A lamp's direct light (shadows, sampler points and all) is its :func:`unit_lamp`'s
    times :func:`lamp_scale`, so two lamps with equal keys differ only by that factor.
    """
    parts = []
    for spec in fields(light):
        if spec.name in _SCALE_FIELDS:
            continue
        value = getattr(light, spec.name)
        if isinstance(value, np.ndarray):
            value = tuple(np.asarray(value, np.float64).ravel().tolist())
        parts.append((spec.name, value))
    return tuple(parts)


def unit_lamp(light: Light) -> Light:
    """``light`` with power 1 and white colour (its light group dropped): see :func:`lamp_shape_key`."""
    return replace(light, strength=1.0, color=np.ones(3), group="")


def lamp_scale(light: Light) -> np.ndarray:
    """(3,) float64: what a lamp's direct light is its :func:`unit_lamp`'s times (power x colour)."""
    return max(float(light.strength), 0.0) * np.asarray(light.color, np.float64)[:3]


def lamp_points(light: Light, area_light_samples: int) -> int:
    """Sampler points per sample a lamp is integrated with: one for a hard lamp (a sun of
    angle 0, a point or spot of radius 0), ``area_light_samples`` squared for a lamp with
    an extent (an area lamp, a sun with an angle, a point or spot with a radius)."""
    if light.kind == "AREA" or (light.kind == "SUN" and light.angle > 0) or (
            light.kind in ("POINT", "SPOT") and light.radius > 0):
        return max(1, int(area_light_samples)) ** 2
    return 1


def angular_radius(light: Light, position: np.ndarray) -> np.ndarray:
    """(K,) float64 radians: about how far a lamp's extent reaches from its centre, seen from
    each sample at ``position`` (K, 3) (pi where a sample is at or inside it)."""
    if light.kind == "SUN":
        return np.full(len(position), light.angle / 2.0)
    extent = light.radius if light.kind in ("POINT", "SPOT") else 0.5 * np.hypot(light.size_x, light.size_y)
    distance = np.linalg.norm(position - np.asarray(light.position, np.float64), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(distance > extent, extent / np.maximum(distance, 1e-300), np.inf)
    return np.where(np.isfinite(ratio), np.arcsin(np.clip(ratio, 0.0, 1.0)), np.pi)


def centre_probe(light: Light, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first of :func:`outline_probes` alone, bitwise the same: the direction (K, 3) unit
    and distance (K,) from ``position`` (K, 3) to the lamp's centre (a sun: its direction, at
    infinity). The footprint's corner probes need only this."""
    if light.kind == "SUN":
        axis = np.broadcast_to(-np.asarray(light.direction, np.float64), position.shape)
        return np.array(axis), np.full(len(position), np.inf)
    offset = np.asarray(light.position, np.float64) - position
    distance = np.linalg.norm(offset, axis=1)
    return offset / np.maximum(distance, 1e-12)[:, None], distance


def outline_probes(light: Light, position: np.ndarray, rotation: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Shadow-ray targets that tell a penumbra from full light or full shadow: the lamp's
    centre and points on its outline, as (to_light (K, 3) unit, distance (K,)) one after the
    other (each is made when asked for: at the demo's 403k texels they are 12 MiB each).

    An occluder edge that is straight at the lamp's scale and crosses the lamp separates
    two of them: a rectangle's four corners always are, and eight points on a round
    outline (a sun's cone, a point lamp's disk, a disk lamp) leave at most a 1.2% cap
    between two of them unseen. ``rotation`` (K,) radians turns each sample's round
    outline, so the unseen caps do not line up from sample to sample.
    """
    centre = np.asarray(light.position, np.float64)
    if light.kind == "SUN":
        axis = np.broadcast_to(-np.asarray(light.direction, np.float64), position.shape)
        tangent, bitangent = orthonormal_frame(np.ascontiguousarray(axis))
        half = light.angle / 2.0
        yield np.array(axis), np.full(len(position), np.inf)
        for k in range(8):
            phi = (rotation + k * np.pi / 4.0)[:, None]
            direction = np.cos(half) * axis + np.sin(half) * (np.cos(phi) * tangent + np.sin(phi) * bitangent)
            yield direction, np.full(len(position), np.inf)
        return
    if light.kind == "AREA":
        _, edge_x, edge_y = area_edges(light)
        axis_x, axis_y = 0.5 * edge_x, 0.5 * edge_y
        if light.area_shape in ("DISK", "ELLIPSE"):
            angles = rotation[:, None] + np.arange(8) * np.pi / 4.0
            targets = (centre + np.cos(angles[:, k:k + 1]) * axis_x + np.sin(angles[:, k:k + 1]) * axis_y
                       for k in range(8))
        else:
            targets = (centre + sx * axis_x + sy * axis_y for sx in (-1, 1) for sy in (-1, 1))
        targets = itertools.chain([centre], targets)
    else:
        # A point or spot lamp: the disk of its radius facing the receiver (a sphere's outline
        # is a little smaller; outside it a probe only errs towards "penumbra").
        towards = position - centre
        tangent, bitangent = orthonormal_frame(towards / np.maximum(np.linalg.norm(towards, axis=1), 1e-300)[:, None])
        del towards
        targets = itertools.chain(
            [np.broadcast_to(centre, position.shape)],
            (centre + light.radius * (np.cos(phi) * tangent + np.sin(phi) * bitangent)
             for phi in ((rotation + k * np.pi / 4.0)[:, None] for k in range(8))))
    for target in targets:
        offset = target - position
        distance = np.linalg.norm(offset, axis=1)
        yield offset / np.maximum(distance, 1e-12)[:, None], distance


def light_contributions(light: Light, position: np.ndarray, normal: np.ndarray, area_light_samples: int = 8,
                        sample_ids: np.ndarray | None = None, seed: int = 0, footprint: np.ndarray | None = None,
                        points: int | None = None) -> Iterator[LightContribution]:
    """Unshadowed irradiance of ``light`` at every sample, one sampler point at a time.

    The lamp's extent (and the sample's footprint, if ``footprint`` is given) is integrated
    with :class:`core.lights.sampler.DirectSampler`'s ``points`` points per sample (default
    :func:`lamp_points`); each yielded contribution is one point's share (the sum of all
    of them is the estimate). The lamps are sampled as Cycles samples them
    (``kernel/light/*.h``): a sun uniformly in its cone of half-angle ``angle / 2``, a
    sphere lamp uniformly in the cone it subtends (cosine-weighted from inside it), a
    soft-falloff point or spot over a disk of its radius facing the receiver, an area lamp
    uniformly over its surface, or, a rectangle near the receiver, uniformly in the solid angle
    it subtends (:func:`_area_point`).

    Parameters
    ----------
    position, normal : (K, 3) float64 sample positions and unit shading normals
    sample_ids : (K,) integer, each sample's index in the bake (default 0..K-1): seeds its scramble
    seed : the bake seed
    footprint : (K, P, 3) float offsets of each sample's footprint points (core.sampling.footprint);
        point j is received at footprint point j % P; None: every point at the sample itself
    """
    lamp = LampPoints(light, position, normal, area_light_samples, sample_ids, seed, footprint, points)
    for point in range(lamp.count):
        yield lamp.contribution(point)


class LampPoints:
    """The sampler points of one lamp at every sample, any point for any subset of the samples.

    :func:`light_contributions` walks all of them; the exact-shadow pass asks for the later
    points of the samples that still need them only. Arguments as :func:`light_contributions`.
    """

    def __init__(self, light: Light, position: np.ndarray, normal: np.ndarray, area_light_samples: int = 8,
                 sample_ids: np.ndarray | None = None, seed: int = 0, footprint: np.ndarray | None = None,
                 points: int | None = None, footprint_normals: np.ndarray | None = None, threads: int = 0):
        if not np.isfinite(float(light.strength)):
            raise ValueError(f"light {light.name!r} has a non-finite strength")
        if light.kind not in ("SUN", "POINT", "SPOT", "AREA"):
            raise ValueError(f"light {light.name!r}: unsupported kind {light.kind!r}")
        self.light, self.position, self.normal, self.footprint = light, position, normal, footprint
        # (K, P, 3) the shading normal at each footprint point, or None: the sample's own for all.
        self.footprint_normals = footprint_normals if footprint is not None else None
        self.scale = lamp_scale(light)
        self.count = lamp_points(light, area_light_samples) if points is None else max(1, int(points))
        # A lamp without extent is one exact point; over a footprint it is that point seen from each footprint point.
        self.point_lamp = lamp_points(light, area_light_samples) == 1 and light.kind != "AREA"
        self.hard = self.count == 1 and footprint is None and self.point_lamp
        self.threads = threads
        if not self.hard:
            self.sampler = DirectSampler(self.count, seed)
            ids = np.arange(len(position)) if sample_ids is None else np.asarray(sample_ids)
            self.scrambles = self.sampler.scrambles(ids, stream_of(light.name))

    def subset(self, rows: np.ndarray) -> LampPoints:
        """The same lamp's points at the samples ``rows`` (an index array) only, each sample
        keeping its own scramble; contributions then have one row per chosen sample."""
        chosen = copy.copy(self)
        chosen.position, chosen.normal = self.position[rows], self.normal[rows]
        if self.footprint is not None:
            chosen.footprint = self.footprint[rows]
        if self.footprint_normals is not None:
            chosen.footprint_normals = self.footprint_normals[rows]
        if not self.hard:
            chosen.scrambles = self.scrambles[:, rows]
        return chosen

    def point_normal(self, point: int) -> np.ndarray:
        """(K, 3) the shading normal where point ``point`` is received."""
        if self.footprint_normals is None:
            return self.normal
        return self.footprint_normals[:, point % self.footprint_normals.shape[1]].astype(np.float64)

    def add_untraced(self, rows: np.ndarray, decided: np.ndarray, visible: np.ndarray, small: np.ndarray,
                     first_points: int, light: np.ndarray) -> np.ndarray | None:
        """Add up, in one compiled pass, every point of a lamp without extent over a footprint
        at the samples ``rows`` (K,) bool that need no shadow ray: those whose shadows are
        ``decided`` (K,) bool, and the others where no point is lit. ``light`` (K, 3) float64
        gets the sum over points of their irradiance where the point is lit and the sample
        ``visible`` (K,) bool, the first ``first_points`` points times count / first_points
        where ``small`` (K,) bool: bitwise what adding :meth:`contribution`'s points one by one
        gives. Returns (K,) bool the rows left to trace (not written), or None, nothing done,
        where the kernel does not apply (a lamp with extent, no footprint, no compiled kernels)."""
        module = kernels.compiled()
        if module is None or not self.point_lamp or self.footprint is None:
            return None
        light_kind = self.light
        point_normals = (np.zeros((len(self.position), 0, 3), np.float32) if self.footprint_normals is None
                         else np.ascontiguousarray(self.footprint_normals, np.float32))
        pending = np.zeros(len(self.position), bool)
        kernels.run(module.hard_lamp_decided, self.threads, KERNEL_KINDS[light_kind.kind],
                    np.asarray(light_kind.position, np.float64), np.asarray(light_kind.direction, np.float64),
                    *spot_cone(light_kind), np.ascontiguousarray(self.position, np.float64),
                    np.ascontiguousarray(self.normal, np.float64),
                    np.ascontiguousarray(self.footprint, np.float32), point_normals, self.scale / self.count,
                    np.nonzero(rows)[0].astype(np.int64), np.ascontiguousarray(decided, bool),
                    np.ascontiguousarray(visible, bool), self.count, np.ascontiguousarray(small, bool),
                    first_points, self.count / first_points, light, pending)
        return pending

    def contribution(self, point: int) -> LightContribution:
        """Point ``point``'s share (weighted 1 / count) at every sample."""
        position, normal = self.position, self.normal
        if self.point_lamp and len(position):
            compiled = _compiled_point(self, point)
            if compiled is not None:
                return compiled
        if self.hard:
            return _hard_contribution(self.light, position, normal, self.scale)
        receiver = position if self.footprint is None else position + self.footprint[:, point % self.footprint.shape[1]]
        normal = self.point_normal(point)
        if self.point_lamp:
            part = _hard_contribution(self.light, receiver, normal, self.scale / self.count)
        else:
            u = self.sampler.uniforms(point, scrambles=self.scrambles)
            # Over a footprint, whose points are dimensions 0 and 1 of their own Sobol set, the lamp
            # takes dimensions 2 and 3: footprint and lamp point j are then one 4D point of a jointly
            # stratified set. With dimensions 0 and 1 for both, point j's footprint and lamp strata
            # were tied (both set by j's bits), and a small lamp's penumbra kept 2-5x the noise.
            lamp_u = u[:, 2:4] if self.footprint is not None else u[:, :2]
            part = _sampled_contribution(self.light, receiver, normal, lamp_u, self.scale / self.count)
        if self.footprint is not None:
            part.position = receiver
        return part


# Lamp kinds numbered as core.kernels.light_kernels numbers them (that module imports numba,
# so it is not imported here).
KERNEL_KINDS = {"SUN": 0, "POINT": 1, "SPOT": 2}
# Stand-ins for the kernel's footprint and receiver arrays where there are none (one
# signature for all calls).
_NO_FOOTPRINT = np.zeros((1, 1, 3), np.float32)
_NO_RECEIVER = np.zeros((0, 3))


def spot_cone(light: Light) -> tuple[float, float]:
    """A spot's cone as the compiled kernels take it: the cosine of its half angle, and its
    blend band in cosine (<= 0: a hard edge)."""
    cos_half = float(np.cos(light.spot_size / 2.0))
    return cos_half, (1.0 - cos_half) * float(light.spot_blend)


def _compiled_point(lamp: LampPoints, point: int) -> LightContribution | None:
    """Point ``point`` of a lamp without extent through the compiled kernel
    (core.kernels.light_kernels.hard_lamp_point), with ``lit`` set; None where the kernels
    do not run (the numpy code then does the same)."""
    module = kernels.compiled()
    if module is None:
        return None
    light, count = lamp.light, len(lamp.position)
    offsets, offset_slot = _NO_FOOTPRINT, -1
    if lamp.footprint is not None:
        offsets, offset_slot = lamp.footprint, point % lamp.footprint.shape[1]
    point_normals, normal_slot = _NO_FOOTPRINT, -1
    if lamp.footprint_normals is not None:
        point_normals, normal_slot = lamp.footprint_normals, point % lamp.footprint_normals.shape[1]
    cos_half, band = spot_cone(light)
    part = LightContribution(np.empty((count, 3)), np.empty((count, 3)), np.empty(count),
                             np.empty((count, 3)) if offset_slot >= 0 else None, np.empty(count, bool))
    kernels.run(module.hard_lamp_point, lamp.threads, KERNEL_KINDS[light.kind],
                np.asarray(light.position, np.float64), np.asarray(light.direction, np.float64), cos_half, band,
                np.ascontiguousarray(lamp.position, np.float64), np.ascontiguousarray(lamp.normal, np.float64),
                np.ascontiguousarray(offsets, np.float32), offset_slot,
                np.ascontiguousarray(point_normals, np.float32), normal_slot,
                lamp.scale / lamp.count, part.irradiance, part.to_light, part.distance,
                part.position if part.position is not None else _NO_RECEIVER, part.lit)
    return part


def _hard_contribution(light: Light, position: np.ndarray, normal: np.ndarray, scale: np.ndarray
                       ) -> LightContribution:
    """A sun of angle 0 or a point or spot of radius 0: one exact direction per sample."""
    if light.kind == "SUN":
        to_light = np.broadcast_to(-np.asarray(light.direction, np.float64), position.shape).copy()
        cosine = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        return LightContribution(cosine[:, None] * scale, to_light, np.full(len(position), np.inf))
    offset = np.asarray(light.position, np.float64) - position
    distance = np.linalg.norm(offset, axis=1)
    safe = np.maximum(distance, 1e-12)
    to_light = offset / safe[:, None]
    cosine = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
    irradiance = cosine / (4.0 * np.pi * safe * safe)
    if light.kind == "SPOT":
        irradiance = irradiance * spot_mask(light, -to_light)
    irradiance = np.where(distance > 1e-12, irradiance, 0.0)
    return LightContribution(irradiance[:, None] * scale, to_light, distance)


def _sampled_contribution(light: Light, position: np.ndarray, normal: np.ndarray, u: np.ndarray,
                          scale: np.ndarray) -> LightContribution:
    """One sampler point's irradiance; ``u`` (K, 2) in [0, 1)^2 picks the point on the lamp and
    ``scale`` (3,) is colour x strength over the point count."""
    k = len(position)
    if light.kind == "SUN":
        half = light.angle / 2.0
        one_minus_cos = 2.0 * np.sin(half / 2.0) ** 2  # 1 - cos(half) without cancellation
        to_light = uniform_cone(-np.asarray(light.direction, np.float64).reshape(1, 3), one_minus_cos, u)
        cosine = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        return LightContribution(cosine[:, None] * scale, to_light, np.full(k, np.inf))
    if light.kind == "AREA":
        return _area_point(light, position, normal, u, scale)

    centre = np.asarray(light.position, np.float64)
    offset = position - centre  # from the lamp to the receiver (Cycles' lightN times d)
    d = np.linalg.norm(offset, axis=1)
    safe = np.maximum(d, 1e-12)
    light_n = offset / safe[:, None]
    r = float(light.radius)
    if light.sphere:
        outside = d > r
        ratio = np.where(outside, (r * r) / (safe * safe), 0.0)
        one_minus_cos = ratio / (1.0 + np.sqrt(np.clip(1.0 - ratio, 0.0, None)))
        cone = uniform_cone(-light_n, one_minus_cos, u)
        inside = cosine_hemisphere(normal, u)
        to_light = np.where(outside[:, None], cone, inside)
        cos_theta = -np.einsum("kd,kd->k", to_light, light_n)
        root = np.sqrt(np.clip(r * r - d * d + d * d * cos_theta * cos_theta, 0.0, None))
        distance = d * cos_theta - np.where(outside, root, -root)
        cos_receiver = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        # Radiance P / (4 pi * pi r^2) over the sampled solid angle 2 pi (1 - cos): the
        # irradiance of a point of power P at d >> r; pi * radiance from inside.
        factor = np.where(outside, 2.0 * one_minus_cos * cos_receiver, 1.0)
        factor = factor / (4.0 * np.pi * r * r)
        if light.kind == "SPOT":
            factor = np.where(outside, factor * spot_mask(light, -to_light), factor)
    else:
        tangent, bitangent = orthonormal_frame(light_n)
        disk = square_to_disk(u) * r
        point = centre + disk[:, :1] * tangent + disk[:, 1:] * bitangent
        towards = point - position
        distance = np.linalg.norm(towards, axis=1)
        to_light = towards / np.maximum(distance, 1e-12)[:, None]
        cos_disk = np.clip(-np.einsum("kd,kd->k", light_n, to_light), 0.0, None)
        cos_receiver = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
        # pdf t^2 / (pi r^2 cos_disk) against radiance P / (4 pi * pi r^2): the disk
        # delivers the point's irradiance far away.
        factor = cos_disk * cos_receiver / (4.0 * np.pi * np.maximum(distance, 1e-12) ** 2)
        factor = np.where(distance > 1e-12, factor, 0.0)
        if light.kind == "SPOT":
            factor = factor * spot_mask(light, -to_light)
    factor = np.where(d > 1e-12, factor, 0.0)
    return LightContribution(factor[:, None] * scale, to_light, distance)


def area_edges(light: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An area lamp's centre and its two edges along its axes, (3,) float64 each: the lamp
    spans centre + s * edge_x + t * edge_y for s, t in [-1/2, 1/2]."""
    return (np.asarray(light.position, np.float64), light.size_x * np.asarray(light.axis_x, np.float64),
            light.size_y * np.asarray(light.axis_y, np.float64))


# Within this many half-diagonals of a rectangular lamp's centre its points are drawn uniform in
# solid angle: at 4, 1 / r^2 changes by up to about 3x over the lamp; nearer it grows without bound.
NEAR_AREA_LAMP = 4.0


def _area_point(light: Light, position: np.ndarray, normal: np.ndarray, u: np.ndarray,
                scale: np.ndarray) -> LightContribution:
    """One point of an area lamp: radiance P / (pi A) over the solid angle or area a point stands for.

    Near a rectangle (within NEAR_AREA_LAMP half-diagonals of its centre) its points are uniform
    in the solid angle it subtends (as Cycles draws them): a receiver a few centimetres from a
    lamp then gets its light with the noise of its own cosine only, where uniform points on the
    area gave cos / r^2 of unbounded variance. Farther away cos / r^2 barely changes over the
    lamp, and points uniform on the area cost far less (applied at every texel, the solid-angle
    points doubled seed 13 of ../shared/tools/scenegen.py's direct light). A disk's or ellipse's points,
    and a rectangle's seen edge-on, are uniform on its area."""
    if light.area_shape in ("DISK", "ELLIPSE"):
        unit = 0.5 * square_to_disk(u)
        area = np.pi / 4.0 * light.size_x * light.size_y
    else:
        unit = u - 0.5
        area = light.size_x * light.size_y
    if area <= 0:
        return LightContribution(np.zeros((len(position), 3)), np.broadcast_to(
            -np.asarray(light.direction, np.float64), position.shape).copy(), np.zeros(len(position)))
    centre, edge_x, edge_y = area_edges(light)
    points = centre + unit[:, :1] * edge_x + unit[:, 1:] * edge_y
    solid = None
    if light.area_shape not in ("DISK", "ELLIPSE"):
        half_diagonal = 0.5 * float(np.hypot(light.size_x, light.size_y))
        near = np.nonzero(np.einsum("kd,kd->k", position - centre, position - centre)
                          < (NEAR_AREA_LAMP * half_diagonal) ** 2)[0]
        if len(near):
            on_sphere, solid_angle, usable = spherical_rectangle(
                position[near], centre - 0.5 * (edge_x + edge_y), edge_x, edge_y, u[near])
            points[near[usable]] = on_sphere[usable]
            solid = (near[usable], solid_angle[usable])
    offset = points - position
    distance = np.linalg.norm(offset, axis=1)
    safe = np.maximum(distance, 1e-12)
    to_light = offset / safe[:, None]
    cos_receiver = np.clip(np.einsum("kd,kd->k", normal, to_light), 0.0, None)
    cos_patch = np.clip(-(to_light @ np.asarray(light.direction, np.float64)), 0.0, None)
    # Per unit radiance: the area each point stands for, A / count (count and P are in scale),
    # times cos cos / r^2; or, uniform in solid angle, S / count times the receiver's cosine.
    transfer = np.where(distance > 1e-12, cos_receiver * cos_patch / (safe * safe), 0.0)
    if solid is not None:
        rows, solid_angle = solid
        transfer[rows] = np.where(cos_patch[rows] > 0.0, cos_receiver[rows] * solid_angle / area, 0.0)
    return LightContribution((transfer / np.pi)[:, None] * scale, to_light, distance)


def is_rectangle(light: Light) -> bool:
    """An area lamp of a rectangular or square shape with an extent."""
    return light.kind == "AREA" and light.area_shape not in ("DISK", "ELLIPSE") and light.size_x * light.size_y > 0


# Receivers (footprint points) a closed-form evaluation handles at a time: 2^15 keep its
# (n, 2, 6, 3) float64 polygons near 10 MB.
RECTANGLE_CHUNK = 1 << 15


def rectangle_irradiance(light: Light, position: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(n, 3) float64 unshadowed irradiance of a rectangular area lamp (:func:`is_rectangle`) at
    receivers ``position`` (n, 3) with unit shading ``normal`` (n, 3), in closed form: the lamp's
    radiance P / (pi A) times its form factor (Lambert's polygon formula, the lamp clipped to the
    receiver's horizon; core.lights.polygons). What the lamp's points average to, without their
    noise; 0 behind the lamp, which emits on its front only."""
    centre, edge_x, edge_y = area_edges(light)
    corners = np.array([centre + 0.5 * (sx * edge_x + sy * edge_y) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    triangles = np.stack([corners[[0, 1, 2]], corners[[0, 2, 3]]])  # (2, 3, 3)
    radiance = lamp_scale(light) / (np.pi * light.size_x * light.size_y)
    form = np.zeros(len(position))
    facing = (position - centre) @ np.asarray(light.direction, np.float64) > 0.0  # in front of the lamp
    for first in range(0, len(position), RECTANGLE_CHUNK):
        rows = slice(first, min(len(position), first + RECTANGLE_CHUNK))
        corner = triangles[None] - position[rows, None, None, :]  # (k, 2, 3, 3) from the receiver
        height = np.einsum("ktcd,kd->ktc", corner, normal[rows])
        polygon, _ = clip_above(corner, height)
        part = polygon_form_factor(polygon, normal[rows][:, None, :]).sum(axis=1)
        form[rows] = np.where(np.any(height > 0, axis=(1, 2)) & facing[rows], part, 0.0)
    return form[:, None] * radiance[None, :]


def usable_lights(lights, warnings: list[str]):
    """The lamps that can be baked; refuse the bake for strengths no output could hold."""
    usable = []
    for light in lights:
        strength = float(light.strength)
        if not np.isfinite(strength) or abs(strength) > tol.MAX_LIGHT_STRENGTH:
            raise BakeRefused(f"light {light.name!r}: strength {strength:g} is not a usable number; set it to a "
                              f"finite value of at most {tol.MAX_LIGHT_STRENGTH:g}")
        color = np.asarray(light.color, np.float64)
        if not np.all(np.isfinite(color)):
            raise BakeRefused(f"light {light.name!r}: its colour is not finite; set its colour again")
        if strength < 0 or np.any(color < 0):
            warnings.append(f"light {light.name!r}: negative light is not supported (Cycles subtracts it); "
                            "it was left out")
            continue
        if strength == 0 or not np.any(color > 0):
            continue
        usable.append(light)
    return usable


def cycles_strength(kind: str, energy: float, exposure: float = 0.0, normalize: bool = True,
                    area_shape: str = "SQUARE", size: float = 1.0, size_y: float = 1.0,
                    scale: tuple[float, float] = (1.0, 1.0), sun_angle: float = 0.0) -> float:
    """A Blender lamp's ``strength`` in the units of :class:`core.scene.Light` (Cycles').

    energy : the lamp's Power (W) or, for a sun, Strength (W/m^2); exposure : stops
    normalize : Blender 5's "Normalize"; off, a point or spot emits four times its
        normalised intensity, an area lamp radiance P/pi whatever its size (so its power
        grows with its area: size x size_y in the lamp's frame, times ``scale``, the
        object's scale along the lamp's X and Y, and pi/4 for disks and ellipses), and a
        sun of angle ``sun_angle`` (radians) its strength per steradian of its disc.
    Measured against Cycles bakes (tests/blender/test_cycles_bake.py).
    """
    strength = float(energy) * 2.0 ** float(exposure)
    if not normalize:
        if kind in {"POINT", "SPOT"}:
            strength *= 4.0
        elif kind == "AREA":
            area = float(size) * float(size_y)
            area *= float(scale[0] * scale[1]) * (np.pi / 4 if area_shape in {"DISK", "ELLIPSE"} else 1.0)
            strength *= area
        elif kind == "SUN":
            half = float(sun_angle) / 2.0
            strength *= 2.0 * np.pi * (1.0 - np.cos(half)) if half > 0 else 1.0
    return strength
