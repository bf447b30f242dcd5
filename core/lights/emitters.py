"""Emissive meshes as light sources: direct sampling where the gather would alias.

Seen from far away, a small glowing object covers only a few of the fixed
directions, so gathering it paints blobs (the Method of Dependent Tests' "ray
effects"). From such samples its light is integrated over points spread evenly on
its emissive triangles instead, with exact shadow rays, and the gather skips it.
Near or large emitters stay in the gather, which is exact for them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..geometry import mesh_face_normals, triangle_areas
from ..scene import Mesh
from .lamps import surface_to_point
from .polygons import clip_above, polygon_form_factor

GOLDEN_RATIO_FRACTION = (np.sqrt(5.0) - 1.0) / 2.0


@dataclass
class Emitter:
    """Points spread over one object's emissive triangles.

    object_index : index of the mesh in the bake
    position, normal : (n, 3) float64 world space, unit normals (front side emits)
    area : (n,) float64 area each point stands for
    radiance : (n, 3) float64 emitted radiance
    centre, radius : bounding sphere of the emissive triangles
    """

    object_index: int
    position: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    radiance: np.ndarray
    centre: np.ndarray
    radius: float


def find_emitters(meshes: list[Mesh], points_per_emitter: int) -> list[Emitter]:
    """One :class:`Emitter` per mesh with emissive, non-degenerate triangles."""
    emitters = []
    for index, mesh in enumerate(meshes):
        if not mesh.materials or len(mesh.triangles) == 0:
            continue
        emission = np.array([np.clip(np.nan_to_num(m.emission[:3]), 0.0, None) for m in mesh.materials])
        material = np.clip(mesh.material_index, 0, len(mesh.materials) - 1)
        normals, valid = mesh_face_normals(mesh)
        emissive = valid & np.any(emission[material] > 0, axis=1)
        if not np.any(emissive):
            continue
        triangles = np.nonzero(emissive)[0]
        corners = mesh.positions[mesh.triangles[triangles]].astype(np.float64)
        areas = triangle_areas(corners)
        total = float(areas.sum())
        if not np.isfinite(total) or total <= 0:
            continue
        count = max(1, points_per_emitter)
        faces = _flat_faces(normals[triangles], material[triangles])
        if faces.max() < count:
            # Each flat face (a box's six sides) gets its own points, at least one, the rest by area.
            # Spread by area over the whole mesh, a 2 x 0.1 x 0.05 m strip's small ends, which face a
            # far wall square on and light it as much as its long sides do, got a point or none, and
            # the walls lit by them were 25% off (seed 11 of ../shared/tools/scenegen.py).
            face_area = np.bincount(faces, weights=areas)
            per_face = _apportion(face_area, count)
            members = [np.nonzero(faces == face)[0] for face in range(len(per_face))]
            chosen = np.concatenate([m[_stratified(areas[m], n)] for m, n in zip(members, per_face)])
            area = np.repeat(face_area / per_face, per_face)
        else:
            chosen, area = _stratified(areas, count), np.full(count, total / count)
        r1 = np.sqrt(np.mod((np.arange(count) + 0.5) * GOLDEN_RATIO_FRACTION, 1.0))
        r2 = np.mod((np.arange(count) + 0.5) * GOLDEN_RATIO_FRACTION * GOLDEN_RATIO_FRACTION + 0.5, 1.0)
        bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
        position = np.einsum("nc,ncd->nd", bary, corners[chosen])
        everything = corners.reshape(-1, 3)
        centre = 0.5 * (everything.min(axis=0) + everything.max(axis=0))
        radius = float(np.max(np.linalg.norm(everything - centre, axis=1)))
        emitters.append(Emitter(
            object_index=index, position=position, normal=normals[triangles[chosen]],
            area=area, radiance=emission[material[triangles[chosen]]],
            centre=centre, radius=radius))
    return emitters


def _stratified(areas: np.ndarray, count: int) -> np.ndarray:
    """(count,) int64: the triangles (indices into ``areas`` (t,)) of ``count`` points stratified by
    area: the i-th falls where the cumulative area reaches (i + 1/2) / count."""
    cumulative = np.cumsum(areas) / areas.sum()
    return np.minimum(np.searchsorted(cumulative, (np.arange(count) + 0.5) / count), len(areas) - 1)


def _flat_faces(normals: np.ndarray, material: np.ndarray) -> np.ndarray:
    """(t,) int64: a label per triangle, the same for triangles of one material whose unit
    ``normals`` (t, 3) agree to about a degree (a flat face of the emitter)."""
    keys = np.concatenate([np.round(np.asarray(normals, np.float64) * 64.0), material[:, None]], axis=1)
    return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)


def _apportion(weights: np.ndarray, count: int) -> np.ndarray:
    """(g,) int64 summing to ``count`` (at least g): one each, the rest in proportion to ``weights``
    (g,) by largest remainders."""
    share = (count - len(weights)) * weights / weights.sum()
    whole = np.floor(share).astype(np.int64)
    rest = count - len(weights) - int(whole.sum())
    whole[np.argsort(-(share - whole), kind="stable")[:rest]] += 1
    return whole + 1


def sampled_directly(emitter: Emitter, positions: np.ndarray, direction_count: int) -> np.ndarray:
    """Which samples take ``emitter`` by direct sampling instead of the gather.

    Returns
    -------
    mask : (K,) bool, True where the emitter's bounding sphere subtends less than
        EMITTER_DIRECT_CELLS direction cells and the sample lies outside it
    """
    distance = np.linalg.norm(positions - emitter.centre, axis=1)
    outside = distance > emitter.radius * (1.0 + 1e-6)
    ratio = np.divide(emitter.radius, distance, out=np.ones_like(distance), where=outside)
    solid_angle = 2.0 * np.pi * (1.0 - np.sqrt(np.clip(1.0 - ratio * ratio, 0.0, 1.0)))
    return outside & (solid_angle < tol.EMITTER_DIRECT_CELLS * 4.0 * np.pi / max(direction_count, 1))


def emitter_irradiance(emitter: Emitter, positions: np.ndarray, normals: np.ndarray, geometric: np.ndarray,
                       origins: np.ndarray, ray_scene) -> tuple[np.ndarray, int]:
    """Irradiance from ``emitter`` at the given samples, shadowed by exact rays.

    Through the compiled kernels where they load (core.kernels.light_kernels.emitter_patch,
    emitter_rays, emitter_add), bitwise what the numpy code below computes: its dozen passes
    over the samples per patch cost twice embree's queries (docs/benchmarks.md, "Speed,
    part 13").

    Parameters
    ----------
    positions, normals, geometric : (k, 3) float64 samples, shading and geometric normals
    origins : (k, 3) ray origins already offset off the surface (float32, or float64 where
        the ray scene is centred)

    Returns
    -------
    irradiance : (k, 3) float64
    rays : int, shadow rays traced
    """
    module = kernels.compiled()
    if module is not None:
        return _emitter_irradiance_compiled(module, emitter, positions, normals, geometric, origins, ray_scene)
    irradiance = np.zeros((len(positions), 3))
    rays = 0
    for point, normal, area, radiance in zip(emitter.position, emitter.normal, emitter.area, emitter.radiance):
        to_point, distance, transfer = surface_to_point(positions, normals, point, normal)
        lit = (transfer > 0) & (np.einsum("kd,kd->k", geometric, to_point) > 0)
        index = np.nonzero(lit)[0]
        if len(index):
            limit = (distance[index] * (1.0 - tol.SHADOW_RAY_SHORTEN)).astype(np.float32)
            rays += len(index)
            index = index[~ray_scene.occluded(origins[index], to_point[index], limit)]
        irradiance[index] += (area * transfer[index])[:, None] * radiance
    return irradiance, rays


def _emitter_irradiance_compiled(module, emitter: Emitter, positions, normals, geometric, origins, ray_scene
                                 ) -> tuple[np.ndarray, int]:
    """:func:`emitter_irradiance` through the compiled kernels (arguments as there)."""
    count = len(positions)
    positions, normals, geometric = (np.ascontiguousarray(a, np.float64) for a in (positions, normals, geometric))
    origins = np.ascontiguousarray(origins)
    irradiance = np.zeros((count, 3))
    to_point, distance, transfer = np.empty((count, 3)), np.empty(count), np.empty(count)
    lit = np.empty(count, bool)
    threads = getattr(ray_scene, "threads", 0) or 0  # the Threads preference (0: all cores)
    keep = 1.0 - tol.SHADOW_RAY_SHORTEN
    rays = 0
    for point, normal, area, radiance in zip(emitter.position, emitter.normal, emitter.area, emitter.radiance):
        kernels.run(module.emitter_patch, threads, positions, normals, geometric, np.asarray(point, np.float64),
                    np.asarray(normal, np.float64), to_point, distance, transfer, lit)
        index = np.flatnonzero(lit)
        if not len(index):
            continue
        ray_origins = np.empty((len(index), 3), origins.dtype)
        directions, limits = np.empty((len(index), 3)), np.empty(len(index), np.float32)
        kernels.run(module.emitter_rays, threads, index, origins, to_point, distance, keep, ray_origins,
                    directions, limits)
        rays += len(index)
        occluded = np.ascontiguousarray(ray_scene.occluded(ray_origins, directions, limits), bool)
        kernels.run(module.emitter_add, threads, index, occluded, transfer, float(area),
                    np.ascontiguousarray(radiance, np.float64), irradiance)
    return irradiance, rays


@dataclass
class EmissiveTriangles:
    """Every emissive triangle of a bake, for the exact light of emitters close by.

    corners : (T, 3, 3) float64 world space; normal : (T, 3) float64 unit (front side emits);
    radiance : (T, 3) float64 emitted radiance; object_index : (T,) int64 the mesh it belongs to
    """

    corners: np.ndarray
    normal: np.ndarray
    radiance: np.ndarray
    object_index: np.ndarray

    def __len__(self) -> int:
        return len(self.corners)

    def of_objects(self, emitting: np.ndarray) -> "EmissiveTriangles":
        """The triangles of the meshes where ``emitting`` (O,) bool is set."""
        keep = np.asarray(emitting, bool)[self.object_index]
        return EmissiveTriangles(self.corners[keep], self.normal[keep], self.radiance[keep], self.object_index[keep])


def emissive_triangles(meshes: list[Mesh]) -> EmissiveTriangles:
    """The emissive, non-degenerate triangles of ``meshes`` (as :func:`find_emitters` finds them)."""
    corners, normal, radiance = [np.zeros((0, 3, 3))], [np.zeros((0, 3))], [np.zeros((0, 3))]
    owner = [np.zeros(0, np.int64)]
    for index, mesh in enumerate(meshes):
        if not mesh.materials or len(mesh.triangles) == 0:
            continue
        emission = np.array([np.clip(np.nan_to_num(m.emission[:3]), 0.0, None) for m in mesh.materials])
        if not np.any(emission > 0):
            continue
        material = np.clip(mesh.material_index, 0, len(mesh.materials) - 1)
        normals, valid = mesh_face_normals(mesh)
        chosen = np.nonzero(valid & np.any(emission[material] > 0, axis=1))[0]
        corners.append(mesh.positions[mesh.triangles[chosen]].astype(np.float64))
        normal.append(np.asarray(normals[chosen], np.float64))
        radiance.append(emission[material[chosen]])
        owner.append(np.full(len(chosen), index, np.int64))
    return EmissiveTriangles(np.concatenate(corners), np.concatenate(normal), np.concatenate(radiance),
                             np.concatenate(owner))


def near_triangles(triangles: EmissiveTriangles, positions: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(k,) bool: which ``positions`` (k, 3) lie within ``reach`` (k,) of the bounding box of some
    emissive mesh among ``triangles``."""
    near = np.zeros(len(positions), bool)
    for index in np.unique(triangles.object_index):
        corners = triangles.corners[triangles.object_index == index].reshape(-1, 3)
        outside = np.maximum(np.maximum(corners.min(axis=0) - positions, positions - corners.max(axis=0)), 0.0)
        near |= np.linalg.norm(outside, axis=1) < reach
    return near


# (landing, triangle) pairs :func:`triangle_irradiance` works on at a time: 2^16 pairs keep its
# (pairs, 6, 3) temporaries near 6 MB each, in the CPU's caches.
TRIANGLE_PAIR_CHUNK = 1 << 16


def triangle_irradiance(triangles: EmissiveTriangles, positions: np.ndarray, normals: np.ndarray,
                        origins: np.ndarray, ray_scene) -> np.ndarray:
    """(k, 3) float64 irradiance from ``triangles`` at ``positions`` (k, 3) with unit ``normals``
    (k, 3), each triangle's shadow tested by one exact ray from ``origins`` (k, 3; offset off the
    surface, RayScene.ray_origins) to the middle of its part above the receiver's horizon.

    Each triangle's light is integrated in closed form (Lambert's polygon formula: E = L / 2 *
    |sum over edges of angle * n . edge-plane normal|) over its part above the horizon, so a
    receiver a centimetre from an emitter gets its light exactly, where points spread over the
    emitter (:func:`emitter_irradiance`) would be centimetres apart and their 1 / d^2 would
    blow up. Shadows are per triangle: a triangle is wholly seen or wholly hidden.
    """
    count, total = len(positions), len(triangles)
    irradiance = np.zeros((count, 3))
    if count == 0 or total == 0:
        return irradiance
    per_chunk = max(1, TRIANGLE_PAIR_CHUNK // total)
    for first in range(0, count, per_chunk):
        rows = slice(first, min(count, first + per_chunk))
        corner = triangles.corners[None] - positions[rows, None, None, :]  # (k, T, 3, 3) from the receiver
        height = np.einsum("ktcd,kd->ktc", corner, normals[rows])
        # Only triangles facing the receiver with a corner above its horizon light it.
        front = np.einsum("ktd,td->kt", corner[:, :, 0], triangles.normal) < 0
        receiver, triangle = np.nonzero(front & np.any(height > 0, axis=2))
        if not len(receiver):
            continue
        polygon, corners_kept = corner[receiver, triangle], np.full(len(receiver), 3)
        # Most lie wholly above it; only those across it are clipped.
        across = np.nonzero(~np.all(height[receiver, triangle] > 0, axis=1))[0]
        if len(across):
            clipped, corners_kept[across] = clip_above(polygon[across], height[receiver[across], triangle[across]])
            polygon = np.concatenate([polygon, np.repeat(polygon[:, :1], 3, axis=1)], axis=1)
            polygon[across] = clipped
        del corner, height
        form = polygon_form_factor(polygon, normals[rows][receiver])
        lit = np.nonzero(form > 0)[0]
        receiver, triangle, polygon, corners_kept, form = (a[lit] for a in (receiver, triangle, polygon,
                                                                            corners_kept, form))
        # Its shadow ray aims at the polygon's point nearest the receiver, a twentieth of the way to
        # its middle (that of its distinct corners; slots past them repeat corner 0): most of the
        # light comes from there. Aimed at the middle, the ray from a ceiling 5 cm over an 8 m strip
        # crossed the column the strip passes through, and the ceiling above the strip's far part
        # was dark, and so the strip's top face (seed 19 of ../shared/tools/scenegen.py).
        slots = np.arange(polygon.shape[1])[None, :] < corners_kept[:, None]
        middle = (polygon * slots[..., None]).sum(axis=1) / slots.sum(axis=1)[:, None]
        nearest = _nearest_points(polygon, triangles.normal[triangle])
        target = nearest + 0.05 * (middle - nearest)
        start = np.asarray(origins[rows][receiver])
        offset = target + positions[rows][receiver] - start
        distance = np.linalg.norm(offset, axis=1)
        direction = offset / np.maximum(distance, 1e-12)[:, None]
        seen = ~np.asarray(ray_scene.occluded(start, direction,
                                              (distance * (1.0 - tol.SHADOW_RAY_SHORTEN)).astype(np.float32)), bool)
        light = form[:, None] * triangles.radiance[triangle] * seen[:, None]
        for channel in range(3):
            irradiance[rows, channel] += np.bincount(receiver, weights=light[:, channel], minlength=rows.stop - first)
    return irradiance


def _nearest_points(polygon: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(n, 3) float64: the point of each convex polygon nearest the origin. ``polygon`` (n, m, 3)
    holds its corners in order, relative to the origin, slots past its last corner repeating
    corner 0; ``normal`` (n, 3) the unit normal of its plane."""
    plane = np.einsum("nd,nd->n", polygon[:, 0], normal)[:, None] * normal  # the origin's foot
    following = np.roll(polygon, -1, axis=1)
    edge = following - polygon
    side = np.einsum("nmd,nd->nm", np.cross(edge, plane[:, None, :] - polygon), normal)
    scale = np.einsum("nmd,nmd->nm", edge, edge).max(axis=1, keepdims=True)
    inside = np.all(side >= -1e-9 * scale, axis=1) | np.all(side <= 1e-9 * scale, axis=1)
    length = np.einsum("nmd,nmd->nm", edge, edge)
    along = np.clip(-np.einsum("nmd,nmd->nm", polygon, edge) / np.maximum(length, 1e-300), 0.0, 1.0)
    on_edge = polygon + along[..., None] * edge
    closest = np.argmin(np.einsum("nmd,nmd->nm", on_edge, on_edge), axis=1)
    return np.where(inside[:, None], plane, on_edge[np.arange(len(polygon)), closest])

