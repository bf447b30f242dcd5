"""One period of a micro-geometry surface that repeats in X and Y, and its samples.

The tile is what the virtual gonioreflectometer (core.appearance.gonio) lights and views:
the paper's section 7.1 periodic micro-geometry. Its samples are the vertices of the mesh
refined until no edge is longer than two cells of period / resolution (the paper's
per-vertex tables), so that a shadow edge or an inter-reflection is resolved as finely as a 64x64 texture
would at resolution 64, on any mesh, UV-mapped or not.

A sample is shared by the faces around a point that shade it with one normal (smooth faces
through their interpolated corner normals, flat ones in one plane) and one material; a
crease or a material border splits it, so that a V-groove's two walls keep their own light
at the bottom of the groove.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import AppearanceRefused
from ..geometry import face_normals, triangle_areas

# Most triangles the refinement may make: 4 M triangles hold about 2 M samples, whose tables
# at 256 directions are ~20 GB; a bigger request is a mistake, refused with a message.
MAX_REFINED_TRIANGLES = 4_000_000
# Faces whose unit normals differ by less than this (about 0.06 degrees) count as one plane.
COPLANAR = 1e-3
# A border point further than this share of the period from its opposite border's points
# makes the tile "not periodic" (a warning, not a refusal: the user may know better).
BORDER_MISMATCH = 1e-3


@dataclass
class Tile:
    """One period of a periodic micro-geometry.

    positions : (P, 3) float64 scene units, z up (the macro surface's normal)
    triangles : (T, 3) int32
    period : (2,) float64 the repeat in X and Y
    origin : (2,) float64 the footprint's lower corner: the period is
        [origin, origin + period) in X and Y
    albedo : (T, 3) float32 linear base colour of each triangle's material
    specular : (T,) float32 weight of the glossy lobe (0: Lambert only)
    roughness : (T,) float32 the glossy lobe's GGX roughness (Principled BSDF), or < 0 for
        the paper's Phong lobe whose exponent is ``phong_exponent``
    smooth : (T,) bool smooth-shaded faces share their samples' normals
    material : (T,) int32 the triangle's material slot (a border between two splits samples)
    phong_exponent : float
    corner_normals : (T, 3, 3) float64 unit shading normals at each triangle's corners (as
        the renderer shades: Blender's corner normals), or None for smooth_corner_normals
    transmission : (T,) float32 in [0, 1] the share of the diffuse light a face passes to its
        other side (a thin translucent sheet, as a fibre's wall; 0: opaque)
    warnings : what was noticed about the tile (for the report)
    """

    positions: np.ndarray
    triangles: np.ndarray
    period: np.ndarray
    origin: np.ndarray
    albedo: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    smooth: np.ndarray
    material: np.ndarray
    phong_exponent: float = 8.0
    corner_normals: np.ndarray | None = None
    transmission: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)

    @classmethod
    def of(cls, positions, triangles, period=None, origin=None, albedo=(0.8, 0.8, 0.8), specular=0.0,
           roughness=-1.0, smooth=False, material=0, phong_exponent: float = 8.0, corner_normals=None,
           transmission=0.0) -> Tile:
        """A tile with per-triangle properties broadcast from scalars; the period defaults to
        the bounding box in XY. Refuses (core.errors.AppearanceRefused) what cannot be simulated."""
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        triangles = np.asarray(triangles, np.int32).reshape(-1, 3)
        if len(triangles) == 0:
            raise AppearanceRefused("the tile has no faces: give it a mesh with at least one face")
        if not np.all(np.isfinite(positions)):
            raise AppearanceRefused("the tile has vertices at infinite or undefined positions")
        if triangles.min() < 0 or triangles.max() >= len(positions):
            raise AppearanceRefused("the tile's faces refer to vertices it does not have")
        low = positions[np.unique(triangles)].min(axis=0)
        high = positions[np.unique(triangles)].max(axis=0)
        period = high[:2] - low[:2] if period is None else np.asarray(period, np.float64).reshape(2)
        origin = low[:2] if origin is None else np.asarray(origin, np.float64).reshape(2)
        if not np.all(np.isfinite(period)) or np.any(period <= 0):
            raise AppearanceRefused(f"the tile's period must be positive in X and Y, got {tuple(period)} (a tile "
                                    "flat in X or Y has no footprint: give its period)")
        count = len(triangles)
        tile = cls(positions, triangles, period, origin,
                   np.broadcast_to(np.asarray(albedo, np.float32), (count, 3)).copy(),
                   np.broadcast_to(np.asarray(specular, np.float32), (count,)).copy(),
                   np.broadcast_to(np.asarray(roughness, np.float32), (count,)).copy(),
                   np.broadcast_to(np.asarray(smooth, bool), (count,)).copy(),
                   np.broadcast_to(np.asarray(material, np.int32), (count,)).copy(), float(phong_exponent),
                   transmission=np.broadcast_to(np.asarray(transmission, np.float32), (count,)).copy())
        if corner_normals is None:
            tile.corner_normals = smooth_corner_normals(positions, triangles, tile.smooth)
        else:
            corner_normals = np.asarray(corner_normals, np.float64).reshape(count, 3, 3)
            if not np.all(np.isfinite(corner_normals)):
                raise AppearanceRefused("the tile's normals are not finite")
            tile.corner_normals = corner_normals
        if not np.any(face_normals(positions, triangles)[1]):
            raise AppearanceRefused("the tile's faces all have zero area")
        if np.any(tile.albedo < 0) or np.any(tile.albedo > 1) or np.any(tile.specular < 0) or np.any(tile.specular > 1):
            raise AppearanceRefused("the tile's base colours and specular weights must lie in [0, 1]")
        if not np.all((tile.transmission >= 0) & (tile.transmission <= 1)):
            raise AppearanceRefused("the tile's transmission weights must lie in [0, 1]")
        tile.warnings.extend(border_mismatch(tile))
        return tile

    @property
    def glossy(self) -> bool:
        """Whether any face has a glossy lobe (the transport is view-dependent only then)."""
        return bool(np.any(self.specular > 0))

    @property
    def translucent(self) -> bool:
        """Whether any face passes light to its other side (its samples then have twins)."""
        return self.transmission is not None and bool(np.any(self.transmission > 0))


def border_mismatch(tile: Tile) -> list[str]:
    """Warnings when the tile's surface does not continue across its borders: for each axis,
    the profile where the tile meets its lower border must reappear at its upper border.

    Checks the edges lying on each border (vertices within a tolerance of it): their points,
    shifted by one period, must lie on the opposite border's edges. A tile with no geometry
    on a border (threads that stop short of it) is periodic by gaps, which is fine.
    """
    warnings = []
    tolerance = BORDER_MISMATCH * float(tile.period.max())
    for axis, name in ((0, "X"), (1, "Y")):
        low = tile.origin[axis]
        high = low + tile.period[axis]
        coordinate = tile.positions[:, axis]
        on_low = np.abs(coordinate - low) < tolerance
        on_high = np.abs(coordinate - high) < tolerance
        other = 1 - axis
        low_points = tile.positions[on_low][:, [other, 2]]
        high_points = tile.positions[on_high][:, [other, 2]]
        if len(low_points) == 0 and len(high_points) == 0:
            continue
        if len(low_points) == 0 or len(high_points) == 0:
            warnings.append(f"the tile is not periodic in {name}: it has vertices on one {name} border and none on "
                            "the other, so the repeated surface has a step there")
            continue
        missing = _unmatched(low_points, high_points, tolerance) + _unmatched(high_points, low_points, tolerance)
        if missing:
            warnings.append(f"the tile is not periodic in {name}: {missing} border vertices have no partner on the "
                            f"opposite border (a step or a gap in the repeated surface)")
    return warnings


def _unmatched(points: np.ndarray, others: np.ndarray, tolerance: float) -> int:
    """How many of ``points`` (k, 2) lie further than ``tolerance`` from the polyline through
    ``others`` (m, 2) sorted along its first coordinate (the opposite border's profile)."""
    order = np.argsort(others[:, 0], kind="stable")
    along = others[order, 0]
    height = others[order, 1]
    if len(along) == 1:
        return int(np.sum(np.hypot(points[:, 0] - along[0], points[:, 1] - height[0]) > tolerance))
    # The profile's height at each point's position (vertical walls: any height between the
    # wall's ends matches, so compare with the nearest profile vertex as well).
    interpolated = np.interp(points[:, 0], along, height)
    nearest = np.min(np.hypot(points[:, None, 0] - along[None], points[:, None, 1] - height[None]), axis=1)
    inside = (points[:, 0] >= along[0] - tolerance) & (points[:, 0] <= along[-1] + tolerance)
    fits = inside & ((np.abs(interpolated - points[:, 1]) < tolerance) | (nearest < tolerance))
    return int(np.sum(~fits))


def refine(positions: np.ndarray, triangles: np.ndarray, longest: float):
    """Split every triangle into four at its edges' midpoints until no edge is longer than
    ``longest``. Midpoints are shared between neighbours, so the mesh stays watertight.

    Returns (positions (P', 3) float64, triangles (T', 3) int32, parent (T',) int64: the
    original triangle each came from, corner_bary (T', 3, 3) float64: each corner's
    barycentric weights in its parent).
    """
    parent = np.arange(len(triangles), dtype=np.int64)
    corner_bary = np.tile(np.eye(3), (len(triangles), 1, 1))
    while True:
        corners = positions[triangles]
        edges = np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)
        if len(triangles) == 0 or edges.max() <= longest:
            return positions, triangles, parent, corner_bary
        if len(triangles) * 4 > MAX_REFINED_TRIANGLES:
            raise AppearanceRefused(f"the tile at this resolution needs more than {MAX_REFINED_TRIANGLES:,} "
                                    "triangles; lower the resolution or simplify the tile")
        pairs = np.sort(np.stack([triangles, triangles[:, [1, 2, 0]]], axis=2).reshape(-1, 2), axis=1)
        unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
        middle = len(positions) + inverse.reshape(-1, 3)
        positions = np.concatenate([positions, 0.5 * (positions[unique[:, 0]] + positions[unique[:, 1]])])
        a, b, c = triangles.T
        ab, bc, ca = middle.T
        triangles = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                                    np.stack([ab, bc, ca], 1)]).astype(np.int32)
        ba, bb, bcc = corner_bary[:, 0], corner_bary[:, 1], corner_bary[:, 2]
        mab, mbc, mca = 0.5 * (ba + bb), 0.5 * (bb + bcc), 0.5 * (bcc + ba)
        corner_bary = np.concatenate([np.stack([ba, mab, mca], 1), np.stack([mab, bb, mbc], 1),
                                      np.stack([mca, mbc, bcc], 1), np.stack([mab, mbc, mca], 1)])
        parent = np.concatenate([parent] * 4)


def smooth_corner_normals(positions: np.ndarray, triangles: np.ndarray, smooth: np.ndarray) -> np.ndarray:
    """(T, 3, 3) float64 unit normals at each triangle's corners: where the face is smooth, the
    vertex normal weighted by the corner angles of the smooth faces around it (as Blender
    computes a mesh's normals); where it is flat, the face's own normal."""
    normals, _ = face_normals(positions, triangles)
    corners = positions[triangles]
    vertex = np.zeros((len(positions), 3))
    for corner in range(3):
        one = corners[:, (corner + 1) % 3] - corners[:, corner]
        other = corners[:, (corner + 2) % 3] - corners[:, corner]
        cosine = np.einsum("fx,fx->f", one, other) / np.maximum(
            np.linalg.norm(one, axis=1) * np.linalg.norm(other, axis=1), 1e-300)
        angle = np.arccos(np.clip(cosine, -1.0, 1.0))
        np.add.at(vertex, triangles[smooth, corner], (normals * angle[:, None])[smooth])
    vertex /= np.maximum(np.linalg.norm(vertex, axis=1, keepdims=True), 1e-300)
    result = np.repeat(normals[:, None, :], 3, axis=1)
    result[smooth] = vertex[triangles[smooth]]
    return result


@dataclass
class TileSamples:
    """The tile's samples: vertices of its refined mesh (see the module's docstring).

    position : (S, 3) float64; normal : (S, 3) float64 unit; area : (S,) float64 (a third
        of the faces around it), scene units squared
    albedo : (S, 3) float32; specular : (S,) float32; roughness : (S,) float32
    triangles : (F, 3) int32 the refined faces, indexing samples (their fronts)
    face_normal : (F, 3) float64 unit; face_area : (F,) float64
    transmission : (S,) float32 the share of diffuse light passed to the twin's side
    twin : (S,) int64 the sample on the other side of a translucent face (-1: none)
    back_triangles : (F, 3) int32 the samples of each face's back (-1 rows: the face is
        opaque, its back black)
    """

    position: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    albedo: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    triangles: np.ndarray
    face_normal: np.ndarray
    face_area: np.ndarray
    transmission: np.ndarray
    twin: np.ndarray
    back_triangles: np.ndarray

    def __len__(self) -> int:
        return len(self.position)


def tile_samples(tile: Tile, resolution: int) -> TileSamples:
    """The tile's samples at ``resolution``: the faces are split until no edge is longer than
    two cells of the period's longer side over ``resolution``."""
    if resolution < 1:
        raise AppearanceRefused(f"the resolution must be at least 1, got {resolution}")
    # A grid of resolution x resolution cells has diagonals of sqrt(2) cells, and a sloped
    # one longer: two cells lets a 64 x 64 heightfield at resolution 64 be its own samples.
    spacing = float(tile.period.max()) / resolution
    positions, triangles, parent, corner_bary = refine(tile.positions, tile.triangles, 2.0 * spacing)
    normals, keep = face_normals(positions, triangles)
    positions_used, triangles, parent, normals = positions, triangles[keep], parent[keep], normals[keep]
    # Smooth faces shade with their parent's corner normals, interpolated as the renderer does
    # (measured: averaging the refined faces' own normals drifted towards flat shading, 2% too
    # bright on a woven tile against Cycles).
    shading = np.einsum("fcb,fbx->fcx", corner_bary[keep], tile.corner_normals[parent]).reshape(-1, 3)
    areas = triangle_areas(positions[triangles])
    corner_point = triangles.reshape(-1)
    corner_face = np.repeat(np.arange(len(triangles)), 3)
    smooth = tile.smooth[parent][corner_face]
    # Corners share a sample when they sit at one point, with one material, and the same
    # normal: their faces' planes where flat, their shading normals where smooth (a sharp edge
    # in a smooth surface splits its samples).
    corner_normal = np.where(smooth[:, None], shading, normals[corner_face])
    # A translucent face's back is a surface of its own: its corners again, facing the other
    # way, whose samples are the twins of the front's (the light one side receives, the other
    # sends on).
    transmission = np.zeros(len(tile.triangles), np.float32) if tile.transmission is None else tile.transmission
    translucent = transmission[parent] > 0
    back = np.nonzero(translucent[corner_face])[0]
    front_count = len(corner_point)
    all_point = np.concatenate([corner_point, corner_point[back]])
    all_face = np.concatenate([corner_face, corner_face[back]])
    all_normal = np.concatenate([corner_normal, -corner_normal[back]])
    side = np.concatenate([np.zeros(front_count, np.int64), np.ones(len(back), np.int64)])
    plane = np.round(all_normal / COPLANAR).astype(np.int64)
    keys = np.column_stack([all_point, tile.material[parent][all_face], tile.smooth[parent][all_face],
                            translucent[all_face], side, plane]).astype(np.int64)
    _, sample_of = np.unique(keys, axis=0, return_inverse=True)
    sample_of = sample_of.reshape(-1)
    count = int(sample_of.max()) + 1
    weighted = np.zeros((count, 3))
    np.add.at(weighted, sample_of, all_normal * areas[all_face, None])
    length = np.linalg.norm(weighted, axis=1, keepdims=True)
    normal = weighted / np.maximum(length, 1e-300)
    area = np.zeros(count)
    np.add.at(area, sample_of, areas[all_face] / 3.0)
    position = np.zeros((count, 3))
    position[sample_of] = positions_used[all_point]
    front = sample_of[:front_count]
    twin = np.full(count, -1, np.int64)
    twin[sample_of[front_count:]] = front[back]
    twin[front[back]] = sample_of[front_count:]
    back_triangles = np.full(front_count, -1, np.int32)
    back_triangles[back] = sample_of[front_count:]

    def per_sample(values: np.ndarray) -> np.ndarray:
        out = np.zeros((count, *values.shape[1:]), values.dtype)
        out[sample_of] = values[parent][all_face]
        return out

    return TileSamples(position, normal, area, per_sample(tile.albedo), per_sample(tile.specular),
                       per_sample(tile.roughness), front.reshape(-1, 3).astype(np.int32), normals, areas,
                       per_sample(transmission), twin, back_triangles.reshape(-1, 3))
