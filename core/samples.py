"""Surface samples of one object: texels of its atlas mapped to world space."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import tolerances as tol
from .images import bilinear_wrap
from .raster import rasterize
from .scene import Mesh


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

    def __len__(self) -> int:
        return len(self.pixel)


def face_normals(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals and a validity mask.

    Returns
    -------
    normals : (m, 3) float64, zero where the triangle is degenerate or not finite
    valid : (m,) bool
    """
    if len(triangles) == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    corners = positions[triangles].astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(cross, axis=1)
        longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
        valid = np.isfinite(length) & (length > tol.DEGENERATE_TRIANGLE_RATIO * longest * longest) & (length > 0)
    normals = np.zeros_like(cross)
    normals[valid] = cross[valid] / length[valid, None]
    return normals, valid


def _normalise(vectors: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(vectors, axis=1)
    good = np.isfinite(length) & (length > 1e-12)
    out = fallback.copy()
    out[good] = vectors[good] / length[good, None]
    return out


def build_samples(mesh: Mesh) -> ObjectSamples:
    """Rasterise the mesh's bake UV map and evaluate geometry and materials per texel."""
    width, height = mesh.resolution
    corner_uv = mesh.uv_maps[mesh.bake_uv_map]
    normals, valid = face_normals(mesh.positions, mesh.triangles)
    # Degenerate or non-finite triangles get no samples: they have no normal to shade with.
    raster_uv = np.where(valid[:, None, None], corner_uv, 0.0).astype(np.float64)
    raster = rasterize(raster_uv, width, height)
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
    np.clip(albedo, 0.0, 1.0, out=albedo)
    np.nan_to_num(albedo, copy=False, nan=0.0)
    np.nan_to_num(emission, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.clip(emission, 0.0, None, out=emission)

    return ObjectSamples(
        width=width, height=height, pixel=raster.pixel, triangle=tri,
        barycentric=raster.barycentric, position=position, normal=shading,
        geometric_normal=geometric, albedo=albedo, emission=emission,
        coverage=raster.coverage, uv_overlap_texels=int(raster.overlap_count),
    )
