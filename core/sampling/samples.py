"""Surface samples of one object: texels of its atlas mapped to world space."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import tolerances as tol
from ..geometry import mesh_face_normals
from ..outputs.images import bilinear_wrap
from ..scene import Mesh
from .footprint import BOX_WIDTH, footprint_corners, footprint_normals, footprint_offsets
from .raster import rasterize
from .terminator import smooth_surface_offsets


@dataclass
class ObjectSamples:
    """The covered texels of one object's atlas.

    pixel : (k,) int64 flat index y * width + x (row 0 at v = 0)
    triangle : (k,) int32
    barycentric : (k, 3) float32
    position : (k, 3) float64 world space
    normal : (k, 3) float64 unit shading normal
    geometric_normal : (k, 3) float64 unit face normal
    albedo : (k, 3) float32
    emission : (k, 3) float32
    coverage : (height, width) bool
    footprint : (k, P, 3) float32 offsets from ``position`` of the points spread over each
        texel's footprint (:func:`core.sampling.footprint.footprint_offsets`), or None: the
        samples stand for their own position only (vertex samples, or one point per texel)
    footprint_corners : (k, 4, 3) float32 offsets to the corners of each texel's box, where
        exact shadows probe for an edge (core.sampling.footprint.footprint_corners), or None
    terminator : (k, 3) float64 lift towards the smooth surface for shadow rays
        (:func:`core.sampling.terminator.smooth_surface_offsets`), or None where no face is smooth
    footprint_normals : (k, P, 3) float32 the shading normal at each footprint point
        (:func:`core.sampling.footprint.footprint_normals`), or None where no face is smooth
    """

    width: int
    height: int
    pixel: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    geometric_normal: np.ndarray
    albedo: np.ndarray
    emission: np.ndarray
    coverage: np.ndarray
    uv_overlap_texels: int = 0
    footprint: np.ndarray | None = None
    footprint_corners: np.ndarray | None = None
    terminator: np.ndarray | None = None
    footprint_normals: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.pixel)


def _normalise(vectors: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(vectors, axis=1)
    good = np.isfinite(length) & (length > 1e-12)
    out = fallback.copy()
    out[good] = vectors[good] / length[good, None]
    return out


def _on_smooth_faces(mesh: Mesh, triangle: np.ndarray, geometric: np.ndarray) -> np.ndarray:
    """(k,) bool: samples on triangles ``triangle`` (k,) whose corner normals differ from the
    face normal ``geometric`` (k, 3). A flat-shaded face has no smooth surface to lift shadow
    rays to, and one normal over the whole footprint."""
    if not len(triangle):
        return np.zeros(0, bool)
    cosines = np.einsum("kcd,kd->kc", mesh.corner_normals[triangle].astype(np.float64), geometric)
    return cosines.min(axis=1) < 1.0 - tol.FLAT_NORMAL_SLACK


def _texel_raster(mesh: Mesh, threads: int):
    """The raster of ``mesh``'s bake UV map that :func:`build_samples` evaluates: the UVs it
    rasterised (T, 3, 2) float64 (zero for triangles that hold no texel), the face normals
    (T, 3) float64 (zero likewise) and core.sampling.raster.rasterize's result."""
    width, height = mesh.resolution
    # Only triangles with UV area can hold texels (an occluder whose UVs are all one point,
    # extract's past-the-budget instances, holds none). The normals are the mesh's kept ones,
    # which the table's hit geometry needs for every triangle anyway.
    uv = np.asarray(mesh.uv_maps[mesh.bake_uv_map], np.float64)
    uv_area = (uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1]) \
        - (uv[:, 1, 1] - uv[:, 0, 1]) * (uv[:, 2, 0] - uv[:, 0, 0])
    with_area = uv_area != 0  # NaN counts: the raster skips it
    all_normals, all_valid = mesh_face_normals(mesh, threads)
    if with_area.all():
        # The common case, without copies of every triangle's arrays (read-only, as kept).
        normals, valid = all_normals, all_valid
    else:
        normals, valid = np.zeros((len(mesh.triangles), 3)), np.zeros(len(mesh.triangles), bool)
        normals[with_area], valid[with_area] = all_normals[with_area], all_valid[with_area]
    # Degenerate or non-finite triangles get no samples: they have no normal to shade with.
    raster_uv = uv if valid.all() else np.where(valid[:, None, None], uv, 0.0)
    return raster_uv, normals, rasterize(raster_uv, width, height, threads)


@dataclass(frozen=True)
class TexelSummary:
    """What :func:`build_samples` would make of a mesh, found by the raster alone: how many
    samples, and whether they get footprint normals and terminator lifts (some sample lies on
    a smooth face). A worker that bakes a range of samples reads the objects outside it this
    way: whether the bake's samples have those arrays depends on every object."""

    count: int
    footprint_normals: bool
    terminator: bool


def texel_summary(mesh: Mesh, footprint_samples: int = 1, threads: int = 0) -> TexelSummary:
    """:class:`TexelSummary` of ``build_samples(mesh, footprint_samples, threads)``."""
    _, normals, raster = _texel_raster(mesh, threads)
    smooth = bool(np.any(_on_smooth_faces(mesh, raster.triangle, normals[raster.triangle])))
    return TexelSummary(len(raster.triangle), _has_footprint_normals(footprint_samples, smooth),
                        _has_terminator(mesh, smooth))


def _has_footprint_normals(footprint_samples: int, smooth: bool) -> bool:
    return footprint_samples > 1 and smooth


def _has_terminator(mesh: Mesh, smooth: bool) -> bool:
    return mesh.terminator_offset > 0 and smooth


def build_samples(mesh: Mesh, footprint_samples: int = 1, threads: int = 0,
                  footprint_width: float = BOX_WIDTH) -> ObjectSamples:
    """Rasterise the mesh's bake UV map and evaluate geometry and materials per texel, with
    ``footprint_samples`` points over each texel's footprint (above 1; see ObjectSamples), a
    box ``footprint_width`` texels wide (core.sampling.footprint).
    ``threads``: the compiled kernels' thread count (0: all cores); the samples do not depend on it."""
    width, height = mesh.resolution
    raster_uv, normals, raster = _texel_raster(mesh, threads)
    tri = raster.triangle
    bary = np.clip(raster.barycentric.astype(np.float64), tol.SAMPLE_BARYCENTRIC_INSET, None)
    bary /= bary.sum(axis=1, keepdims=True)
    corners = mesh.positions[mesh.triangles[tri]].astype(np.float64)
    position = np.einsum("kc,kcd->kd", bary, corners)
    geometric = normals[tri]
    shading = np.einsum("kc,kcd->kd", bary, mesh.corner_normals[tri].astype(np.float64))
    shading = _normalise(shading, geometric)
    # A shading normal on the far side of the surface would shade nothing; fall back.
    backwards = np.einsum("kd,kd->k", shading, geometric) <= 0
    shading[backwards] = geometric[backwards]

    albedo = np.empty((len(tri), 3), np.float32)
    emission = np.empty((len(tri), 3), np.float32)
    materials = mesh.materials or []
    material_of_sample = mesh.material_index[tri] if len(mesh.material_index) else np.zeros(len(tri), np.int32)
    material_of_sample = np.clip(material_of_sample, 0, max(len(materials) - 1, 0))
    for index, material in enumerate(materials or [None]):
        chosen = material_of_sample == index
        if not np.any(chosen):
            continue
        if material is None:
            albedo[chosen] = 0.8
            emission[chosen] = 0.0
            continue
        texture = material.base_color_texture
        uv_name = material.texture_uv_map
        if texture is not None and uv_name in mesh.uv_maps:
            tex_uv = np.einsum("kc,kcd->kd", bary[chosen], mesh.uv_maps[uv_name][tri[chosen]].astype(np.float64))
            albedo[chosen] = bilinear_wrap(texture[..., :3], tex_uv[:, 0], tex_uv[:, 1])
        else:
            albedo[chosen] = material.base_color[:3]
        emission[chosen] = material.emission[:3]
    # Cycles keeps a base colour above 1 (its diffuse closures clamp at 0 only), so such a
    # surface reflects more than it receives there too; the adapter warns about it.
    np.clip(albedo, 0.0, None, out=albedo)
    np.nan_to_num(albedo, copy=False, nan=0.0, posinf=0.0)
    np.nan_to_num(emission, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.clip(emission, 0.0, None, out=emission)

    smooth = _on_smooth_faces(mesh, tri, geometric)
    footprint = box_corners = point_normals = None
    if footprint_samples > 1:
        # Each sample's own triangle's corners: a dense mesh's few texels touch few of its
        # triangles, and gathering every triangle's took 7 ms of 200k (docs/benchmarks.md, part 20).
        own = np.arange(len(tri))
        own_uv = raster_uv[tri]
        footprint = footprint_offsets(raster.pixel, own, width, height, own_uv, corners, position,
                                      footprint_samples, threads, seed_triangle=tri, box_width=footprint_width)
        box_corners = footprint_corners(raster.pixel, own, width, height, own_uv, corners, position, footprint,
                                        threads, box_width=footprint_width)
        if _has_footprint_normals(footprint_samples, bool(np.any(smooth))):
            point_normals = footprint_normals(footprint, position, own, corners, mesh.corner_normals[tri], shading,
                                              smooth, threads)
    terminator = None
    if _has_terminator(mesh, bool(np.any(smooth))):
        terminator = np.zeros((len(tri), 3))
        terminator[smooth] = smooth_surface_offsets(mesh.positions, mesh.triangles, mesh.corner_normals,
                                                    geometric[smooth], tri[smooth], bary[smooth])
        terminator = np.nan_to_num(terminator, nan=0.0, posinf=0.0, neginf=0.0)
    return ObjectSamples(
        width=width, height=height, pixel=raster.pixel, triangle=tri,
        barycentric=raster.barycentric, position=position, normal=shading,
        geometric_normal=geometric, albedo=albedo, emission=emission,
        coverage=raster.coverage, uv_overlap_texels=int(raster.overlap_count), footprint=footprint,
        footprint_corners=box_corners, terminator=terminator, footprint_normals=point_normals,
    )


@dataclass
class VertexSamples(ObjectSamples):
    """Samples at the vertices of one object (the paper's section 5), as a 1 x k "atlas".

    A vertex is one sample where all its corners share a shading normal, and one
    sample per distinct normal where the mesh has split normals (sharp edges), so a
    cube's corner is lit three ways, as its faces are. Laid out as a one-row image of
    k texels (``pixel`` = 0..k-1, full coverage), the transport treats the object like
    any other; only a ray landing on it reads its light differently (the triangle's
    three samples, not a bilinear texel lookup).

    corner_sample : (m, 3) int32 the sample of each triangle corner
    domain : 'POINT' (one value per vertex) or 'CORNER' (per face corner, where
        split normals made several samples at one vertex)
    element_sample : (vertex_count or loop_count,) int64 the sample of each output
        element, -1 for elements no valid triangle uses
    """

    corner_sample: np.ndarray | None = None
    domain: str = "POINT"
    element_sample: np.ndarray | None = None


def _corner_albedo_emission(mesh: Mesh, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and emission at every corner of ``triangles``: (t, 3, 3) float64 each."""
    count = len(triangles)
    albedo = np.full((count, 3, 3), 0.8)
    emission = np.zeros((count, 3, 3))
    materials = mesh.materials or []
    material_of = mesh.material_index[triangles] if len(mesh.material_index) else np.zeros(count, np.int32)
    material_of = np.clip(material_of, 0, max(len(materials) - 1, 0))
    for index, material in enumerate(materials):
        chosen = np.nonzero(material_of == index)[0]
        if material is None or len(chosen) == 0:
            continue
        texture = material.base_color_texture
        uv_name = material.texture_uv_map
        if texture is not None and uv_name in mesh.uv_maps:
            uv = mesh.uv_maps[uv_name][triangles[chosen]].astype(np.float64)  # (c, 3, 2)
            flat = uv.reshape(-1, 2)
            albedo[chosen] = bilinear_wrap(texture[..., :3], flat[:, 0], flat[:, 1]).reshape(-1, 3, 3)
        else:
            albedo[chosen] = np.asarray(material.base_color, np.float64)[:3]
        emission[chosen] = np.asarray(material.emission, np.float64)[:3]
    albedo = np.clip(np.nan_to_num(albedo, nan=0.0, posinf=0.0), 0.0, None)  # no upper bound, as in Cycles
    emission = np.clip(np.nan_to_num(emission, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
    return albedo, emission


def build_vertex_samples(mesh: Mesh, centre: np.ndarray | None = None) -> VertexSamples:
    """One sample per vertex (per distinct shading normal where normals are split).

    ``centre`` (3,): where the rays are traced around (core.pipeline.prepare.trace_frame);
    the inset into the triangle scales with the float32 step there, not at the world origin.

    Corners of degenerate or non-finite triangles make no sample. Albedo and emission
    of a sample are the mean over its corners (a vertex between two materials gets
    their mix, as an interpolated vertex colour would show it).
    """
    normals, valid = mesh_face_normals(mesh)
    used = np.nonzero(valid)[0]
    corner_vertex = mesh.triangles[used].astype(np.int64)  # (t, 3)
    corner_normal = np.asarray(mesh.corner_normals[used], np.float64).reshape(-1, 3)
    corner_normal = _normalise(corner_normal, np.repeat(normals[used], 3, axis=0))
    vertex_of_corner = corner_vertex.ravel()
    # Corners of one vertex whose normals agree to float32 rounding share a sample.
    rounded = np.round(corner_normal / tol.SPLIT_NORMAL_TOLERANCE).astype(np.int64)
    keys = np.concatenate([vertex_of_corner[:, None], rounded], axis=1)
    unique_keys, sample_of_corner = np.unique(keys, axis=0, return_inverse=True)
    sample_of_corner = sample_of_corner.ravel()
    count = len(unique_keys)
    split = count > len(np.unique(vertex_of_corner))

    normal = np.zeros((count, 3))
    np.add.at(normal, sample_of_corner, corner_normal)
    face_sum = np.zeros((count, 3))
    np.add.at(face_sum, sample_of_corner, np.repeat(normals[used], 3, axis=0))
    normal = _normalise(normal, _normalise(face_sum, np.tile([0.0, 0.0, 1.0], (count, 1))))
    position = mesh.positions[unique_keys[:, 0]].astype(np.float64)
    # A vertex where two objects meet (a floor's edge under a wall) lies on the other
    # object's surface, and its rays would hit it at t = 0. Like Cycles' vertex bake
    # (which moves each corner towards its triangle's middle), move the sample a hair
    # into one of its triangles, the one facing most like its normal: it then lies on
    # that face, in front of which its rays start. (The mean of several triangles'
    # middles would lie behind the faces of a convex or concave vertex.)
    facing = np.einsum("kd,kd->k", np.repeat(normals[used], 3, axis=0), normal[sample_of_corner])
    order = np.lexsort((-facing, sample_of_corner))
    first = order[np.r_[True, np.diff(sample_of_corner[order]) != 0]]
    chosen_triangle = used[first // 3]
    towards = mesh.positions[mesh.triangles[chosen_triangle]].mean(axis=1) - position
    length = np.linalg.norm(towards, axis=1)
    local = position if centre is None else position - np.asarray(centre, np.float64)
    scale = tol.VERTEX_SAMPLE_INSET * np.maximum(1.0, np.abs(local).max(axis=1))
    step = np.divide(np.minimum(length, scale), length, out=np.zeros_like(length), where=length > 0)
    position = position + towards * step[:, None]
    corners_per_sample = np.bincount(sample_of_corner, minlength=count).astype(np.float64)[:, None]
    corner_albedo, corner_emission = _corner_albedo_emission(mesh, used)
    albedo = np.zeros((count, 3))
    emission = np.zeros((count, 3))
    np.add.at(albedo, sample_of_corner, corner_albedo.reshape(-1, 3))
    np.add.at(emission, sample_of_corner, corner_emission.reshape(-1, 3))
    albedo /= corners_per_sample
    emission /= corners_per_sample

    corner_sample = np.full((len(mesh.triangles), 3), -1, np.int32)
    corner_sample[used] = sample_of_corner.reshape(-1, 3)
    if split and mesh.corner_loops is not None:
        domain = "CORNER"
        element_sample = np.full(max(mesh.loop_count, 0), -1, np.int64)
        element_sample[np.asarray(mesh.corner_loops)[used].ravel()] = sample_of_corner
    else:
        domain = "POINT"
        element_sample = np.full(max(mesh.vertex_count, len(mesh.positions)), -1, np.int64)
        element_sample[unique_keys[:, 0]] = np.arange(count)
    return VertexSamples(
        width=count, height=1, pixel=np.arange(count, dtype=np.int64), triangle=np.zeros(count, np.int32),
        barycentric=np.zeros((count, 3), np.float32), position=position, normal=normal,
        geometric_normal=normal.copy(), albedo=albedo.astype(np.float32), emission=emission.astype(np.float32),
        coverage=np.ones((1, count), bool), corner_sample=corner_sample, domain=domain,
        element_sample=element_sample)


def dense_footprint(mesh: Mesh, samples: ObjectSamples, rows: np.ndarray, count: int, threads: int = 0,
                    footprint_width: float = BOX_WIDTH):
    """``count`` footprint points of samples ``rows`` (r,) of ``samples`` (built from ``mesh``),
    drawn as build_samples draws them (the same ``footprint_width``), so that the first
    footprint_samples of them are the samples' own (the same scrambled Sobol sequence, longer).
    ``threads``: the kernels' (0: all cores).

    Returns (offsets (r, count, 3) float32, normals (r, count, 3) float32 or None where no
    face of ``rows`` is smooth).
    """
    width, height = samples.width, samples.height
    triangle = samples.triangle[rows]
    # Each row's own triangle's corners, as build_samples gives them.
    own = np.arange(len(triangle))
    corners = mesh.positions[mesh.triangles[triangle]].astype(np.float64)
    position = samples.position[rows]
    offsets = footprint_offsets(samples.pixel[rows], own, width, height,
                                np.asarray(mesh.uv_maps[mesh.bake_uv_map][triangle], np.float64), corners, position,
                                count, threads, seed_triangle=triangle, box_width=footprint_width)
    smooth = _on_smooth_faces(mesh, triangle, samples.geometric_normal[rows])
    if not smooth.any():
        return offsets, None
    return offsets, footprint_normals(offsets, position, own, corners, mesh.corner_normals[triangle],
                                      samples.normal[rows], smooth, threads)
