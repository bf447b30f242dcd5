"""UV atlases: checking a layout for baking, and unwrapping a mesh with xatlas.

UV conventions are those of :mod:`core.raster`: u right, v up, [0, 1]^2, texel
(x, y) centred at ((x + 0.5) / W, (y + 0.5) / H), row 0 at the bottom.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .raster import degenerate_uv_triangles, rasterize

# A UV coordinate this far outside [0, 1] is still "inside": float32 UVs written at
# exactly 0 or 1 may come back a few ULPs off after a round trip through Blender.
UV_RANGE_SLACK = 1e-6

# xatlas tests degeneracy with absolute thresholds (face area <= FLT_EPSILON,
# welding distance FLT_EPSILON), so meshes are rescaled to a median edge length of
# 1 before unwrapping; a triangle whose doubled area is below this (in those units)
# would be ignored by xatlas and is dropped up front instead.
UNWRAP_MIN_DOUBLED_AREA = 8.0 * float(np.finfo(np.float32).eps)

# xatlas's charting dominates the cost (~85 % at 20k triangles); its defaults are
# already the fast ones (max_iterations=1, bruteForce=False). Repacking the cut
# charts is cheap (~0.1 s at 20k triangles), so when the atlas overshoots the
# requested square they are repacked, each try scaled by the overshoot times this.
UNWRAP_REPACK_SHRINK = 0.99
UNWRAP_MAX_REPACKS = 12


@dataclass(frozen=True)
class UVLayoutStats:
    """Counts behind :func:`uv_layout_problems`.

    Attributes
    ----------
    triangles : int
    non_finite_corners : int, corners with a NaN or infinite coordinate
    out_of_range_corners : int, finite corners outside [0, 1] (beyond ``UV_RANGE_SLACK``)
    zero_area_triangles : int, triangles that cover no area (see ``raster.degenerate_uv_triangles``)
    covered_texels : int
    overlap_texels : int, texels covered by more than one triangle
    """

    triangles: int
    non_finite_corners: int
    out_of_range_corners: int
    zero_area_triangles: int
    covered_texels: int
    overlap_texels: int


@dataclass(frozen=True)
class UnwrapResult:
    """A mesh unwrapped into one square atlas.

    Attributes
    ----------
    corner_uv : (m, 3, 2) float32
        UV of each corner of each input triangle, in the input order, in [0, 1].
    width, height : int
        Size of the image the UVs are laid out for (both equal the requested
        resolution); charts are at least ``padding`` texels apart in it.
    degenerate : (m,) bool
        Triangles that got no UV area (non-finite or zero-area in 3D); their three
        corners are all (0, 0), so they cover no texel.
    texels_per_unit : float
        Texels per unit length of the input positions, the same for every chart.
    chart_count : int
    """

    corner_uv: np.ndarray
    width: int
    height: int
    degenerate: np.ndarray
    texels_per_unit: float
    chart_count: int

    @property
    def degenerate_count(self) -> int:
        return int(np.count_nonzero(self.degenerate))


def uv_layout_stats(corner_uv: np.ndarray, width: int, height: int) -> UVLayoutStats:
    """Measure a UV layout at a target resolution (see :func:`uv_layout_problems`).

    Parameters
    ----------
    corner_uv : (m, 3, 2) float
    width, height : int, target image size in texels
    """
    corners = np.asarray(corner_uv, dtype=np.float64)
    if corners.ndim != 3 or corners.shape[1:] != (3, 2):
        raise ValueError(f"corner_uv must have shape (m, 3, 2), got {corners.shape}")
    finite = np.isfinite(corners).all(axis=2)
    with np.errstate(invalid="ignore"):
        outside = ((corners < -UV_RANGE_SLACK) | (corners > 1.0 + UV_RANGE_SLACK)).any(axis=2)
    raster = rasterize(corners, width, height)
    return UVLayoutStats(
        triangles=int(corners.shape[0]),
        non_finite_corners=int(np.count_nonzero(~finite)),
        out_of_range_corners=int(np.count_nonzero(outside & finite)),
        zero_area_triangles=int(np.count_nonzero(degenerate_uv_triangles(corners, width, height))),
        covered_texels=int(raster.pixel.size),
        overlap_texels=int(raster.overlap_count),
    )


def uv_layout_problems(corner_uv: np.ndarray, width: int, height: int) -> list[str]:
    """Why a UV layout cannot be baked at ``width`` x ``height``; empty when it can.

    Problems: non-finite UVs, UVs outside [0, 1], islands overlapping at texel
    centres (rasterised at the target resolution; shared edges do not count), no
    triangle with UV area. Some zero-area triangles are not a problem on their
    own: they cover no texel, and xatlas gives them to degenerate faces.

    Parameters
    ----------
    corner_uv : (m, 3, 2) float
    width, height : int, target image size in texels

    Returns
    -------
    problems : list of str, human-readable, empty when the layout is valid
    """
    stats = uv_layout_stats(corner_uv, width, height)
    corners = 3 * stats.triangles
    problems = []
    if stats.triangles == 0:
        return ["the UV map has no triangles"]
    if stats.non_finite_corners:
        problems.append(f"{stats.non_finite_corners} of {corners} UV coordinates are NaN or infinite")
    if stats.out_of_range_corners:
        problems.append(f"{stats.out_of_range_corners} of {corners} UV coordinates outside [0, 1]")
    if stats.overlap_texels:
        problems.append(f"UV islands overlap ({stats.overlap_texels} texels covered twice)")
    if stats.zero_area_triangles == stats.triangles:
        problems.append(f"all {stats.triangles} triangles have zero UV area")
    elif stats.covered_texels == 0:
        problems.append(f"no texel centre is covered at {width}x{height}; the UV islands are too small")
    return problems


def unwrap(positions: np.ndarray, triangles: np.ndarray, resolution: int, padding_texels: int = 2,
           texels_per_unit: float | None = None) -> UnwrapResult:
    """Unwrap a triangle mesh with xatlas into one ``resolution`` x ``resolution`` atlas.

    Triangles with a non-finite vertex, repeated vertices or (near-)zero area are
    not given to xatlas; they come back with all three corners at (0, 0) and are
    flagged in ``degenerate``.

    Parameters
    ----------
    positions : (n, 3) float
    triangles : (m, 3) int, indices into ``positions``
    resolution : int, side of the square target image in texels
    padding_texels : int, minimum gap between charts, in texels of that image
    texels_per_unit : float, optional
        Texel density per unit length of ``positions``. By default the largest
        density that fits is used; when given and the charts do not fit in one
        atlas, ``ValueError`` is raised.

    Returns
    -------
    UnwrapResult
    """
    import xatlas

    positions = np.asarray(positions)
    triangles = np.asarray(triangles)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"unwrap: positions must have shape (n, 3), got {positions.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"unwrap: triangles must have shape (m, 3), got {triangles.shape}")
    if triangles.shape[0] == 0:
        raise ValueError("unwrap: the mesh has no triangles")
    if not np.issubdtype(triangles.dtype, np.integer):
        raise ValueError(f"unwrap: triangles must be integer indices, got {triangles.dtype}")
    if triangles.min() < 0 or triangles.max() >= positions.shape[0]:
        raise ValueError(f"unwrap: triangle indices must lie in [0, {positions.shape[0]})")
    if int(resolution) != resolution or int(padding_texels) != padding_texels:
        raise ValueError("unwrap: resolution and padding_texels must be integers")
    resolution, padding = int(resolution), int(padding_texels)
    if padding < 0 or resolution < 2 * padding + 2:
        raise ValueError(f"unwrap: resolution {resolution} is too small for {padding} texels of padding")
    if texels_per_unit is not None and not (np.isfinite(texels_per_unit) and texels_per_unit > 0):
        raise ValueError(f"unwrap: texels_per_unit must be positive, got {texels_per_unit!r}")

    m = triangles.shape[0]
    tri = triangles.astype(np.int64)
    pos = positions.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        usable = np.isfinite(pos[tri]).all(axis=(1, 2))
        usable &= (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])
        if usable.any():
            kept_vertices = np.unique(tri[usable])
            lo, hi = pos[kept_vertices].min(axis=0), pos[kept_vertices].max(axis=0)
            centre = 0.5 * (lo + hi)
            corners = pos[tri[usable]] - centre
            edge_lengths = np.linalg.norm(corners[:, [1, 2, 0]] - corners, axis=2)
            positive = edge_lengths[edge_lengths > 0]
            scale = 1.0 / float(np.median(positive)) if positive.size else 1.0
            # Measure area on the float32 coordinates xatlas will see.
            xc = (corners * scale).astype(np.float32).astype(np.float64)
            doubled = np.linalg.norm(np.cross(xc[:, 1] - xc[:, 0], xc[:, 2] - xc[:, 0]), axis=1)
            usable[usable] = np.isfinite(doubled) & (doubled > UNWRAP_MIN_DOUBLED_AREA)
    if not usable.any():
        raise ValueError(f"unwrap: none of the {m} triangles has a finite, non-zero area")

    kept = np.flatnonzero(usable)
    vertices, local = np.unique(tri[kept], return_inverse=True)
    local = local.reshape(-1, 3).astype(np.uint32)
    xpos = np.ascontiguousarray(((pos[vertices] - centre) * scale).astype(np.float32))

    atlas = xatlas.Atlas()
    atlas.add_mesh(xpos, local)
    pack = xatlas.PackOptions()
    pack.padding = padding
    pack.resolution = resolution
    if texels_per_unit is not None:
        # Both set: xatlas packs into fixed resolution^2 atlases, as many as needed.
        pack.texels_per_unit = float(texels_per_unit) / scale
    atlas.generate(xatlas.ChartOptions(), pack)
    chart_count = int(atlas.chart_count)
    _, faces, uv = atlas[0]
    if faces.shape[0] != kept.size:
        raise RuntimeError(f"xatlas returned {faces.shape[0]} faces for {kept.size} input triangles")
    texel_uv = uv.astype(np.float64) * np.array([atlas.width, atlas.height], dtype=np.float64)
    density = float(atlas.texels_per_unit)
    dropped = _outside_charts(atlas, faces)

    if texels_per_unit is not None:
        if atlas.atlas_count != 1:
            raise ValueError(f"unwrap: at {texels_per_unit} texels per unit the charts need {atlas.atlas_count} "
                             f"atlases of {resolution}x{resolution}; lower texels_per_unit or raise the resolution")
    elif max(atlas.width, atlas.height) > resolution:
        # Given only a resolution, xatlas sizes charts assuming 75 % packing
        # efficiency and grows the atlas past the resolution when it packs worse.
        # Repack the finished charts at a smaller scale: cheap, and keeps the padding.
        texel_uv, density, dropped_again = _repack(texel_uv.astype(np.float32), faces, resolution, padding,
                                                   resolution / max(atlas.width, atlas.height), density)
        dropped |= dropped_again

    corner_uv = np.zeros((m, 3, 2), np.float32)
    corner_uv[kept] = np.clip(texel_uv[faces] / resolution, 0.0, 1.0)
    # xatlas may still drop faces it finds degenerate; their UVs are not placed.
    corner_uv[kept[dropped]] = 0.0
    degenerate = degenerate_uv_triangles(corner_uv, resolution, resolution)
    corner_uv[degenerate] = 0.0
    return UnwrapResult(
        corner_uv=corner_uv,
        width=resolution,
        height=resolution,
        degenerate=degenerate,
        texels_per_unit=density * scale,
        chart_count=chart_count,
    )


def _repack(texel_uv: np.ndarray, faces: np.ndarray, resolution: int, padding: int, shrink: float,
            density: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Pack already-cut charts (in texel units) into one resolution^2 atlas, scaled down as needed.

    Parameters
    ----------
    texel_uv : (v, 2) float32, vertex UVs in texels of the first packing
    faces : (f, 3) uint32
    shrink : float, first scale to try
    density : float, texels per (normalised) unit of ``texel_uv``

    Returns
    -------
    texel_uv : (v, 2) float64, vertex UVs in texels of the resolution^2 image
    density : float, texels per (normalised) unit after scaling
    dropped : (f,) bool, faces xatlas left out of every chart
    """
    import xatlas

    scale = shrink
    for _ in range(UNWRAP_MAX_REPACKS):
        atlas = xatlas.Atlas()
        atlas.add_uv_mesh(texel_uv, faces)
        pack = xatlas.PackOptions()
        pack.padding = padding
        # Unbounded packing (resolution 0) fills about as well as the first pass,
        # far better than xatlas's fixed-size mode with random placement; the
        # scale is then corrected from the size it reached. For a UV mesh,
        # texels_per_unit is simply the scale applied to its UVs.
        pack.texels_per_unit = scale
        atlas.generate(xatlas.ChartOptions(), pack)
        size = max(atlas.width, atlas.height)
        if atlas.atlas_count == 1 and size <= resolution:
            _, repacked_faces, uv = atlas[0]
            if not np.array_equal(repacked_faces, faces):
                raise RuntimeError("xatlas reordered faces while repacking")
            placed = uv.astype(np.float64) * np.array([atlas.width, atlas.height], dtype=np.float64)
            return placed, density * scale, _outside_charts(atlas, faces)
        scale *= min(resolution / max(size, 1), 1.0) * UNWRAP_REPACK_SHRINK
    raise RuntimeError(f"xatlas could not fit the charts into one {resolution}x{resolution} atlas")


def _outside_charts(atlas, faces: np.ndarray) -> np.ndarray:
    """Faces with a vertex xatlas put in no chart: xatlas ignored them and never placed their UVs.

    Returns
    -------
    dropped : (f,) bool
    """
    atlas_index, chart_index = atlas.get_mesh_vertex_assignment(0)
    unplaced = (np.asarray(atlas_index) == np.iinfo(np.uint32).max) | (np.asarray(chart_index) == np.iinfo(np.uint32).max)
    return unplaced[faces].any(axis=1)
