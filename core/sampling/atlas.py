"""UV atlases: checking a layout for baking, and unwrapping a mesh with xatlas.

UV conventions are those of :mod:`core.sampling.raster`: u right, v up, [0, 1]^2, texel
(x, y) centred at ((x + 0.5) / W, (y + 0.5) / H), row 0 at the bottom.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kernels
from .. import tolerances as tol
from ..errors import UnwrapFailed
from ..geometry import edge_cross, triangle_areas
from .raster import degenerate_uv_triangles, rasterize

# xatlas (0.0.11 and upstream, jpcy/xatlas#146) grows "planar" regions across any
# two neighbouring faces whose normals' dot product is within 1e-4 of 1 (0.81
# degrees), transitively, then projects each region flat. On a finely tessellated
# smooth surface (e.g. an 80k-face icosphere) such a region wraps round the whole
# surface: projected flat it overlaps itself, and when closed xatlas segfaults.
# Regions whose normals stray further than this from their mean are broken up
# before unwrapping by nudging their vertices along the normal...
PLANAR_CHAIN_MAX_ANGLE_DEG = 15.0
# ...by this fraction of the median edge length (tilting neighbouring faces by
# about a degree, past xatlas's threshold), doubling on each retry.
PLANAR_CHAIN_NUDGE = 0.02
PLANAR_CHAIN_TRIES = 4

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
    out_of_range_corners : int, finite corners outside [0, 1] (beyond ``tol.UV_RANGE_SLACK``)
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
        Texels per unit length of the input positions that every chart is scaled
        to; xatlas then stretches each chart by under one texel per axis so that
        its extents are whole texels, so small charts come out a little denser.
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
    raster = rasterize(corners, width, height, load_kernels=False)
    # As the raster: the kernels only where this process has loaded them (this check runs on
    # Blender's main thread, before a bake's kernels stage).
    module = kernels.compiled() if kernels.tried() else None
    if module is not None:
        count = corners.shape[0]
        degenerate, non_finite, outside = np.empty(count, bool), np.empty(count, np.int8), np.empty(count, np.int8)
        kernels.run(module.uv_checks, 0, np.ascontiguousarray(corners), int(width), int(height), tol.UV_RANGE_SLACK,
                    tol.DEGENERATE_TRIANGLE_RATIO, degenerate, non_finite, outside)
        non_finite_corners, out_of_range_corners = int(non_finite.sum()), int(outside.sum())
    else:
        finite = np.isfinite(corners).all(axis=2)
        with np.errstate(invalid="ignore"):
            away = ((corners < -tol.UV_RANGE_SLACK) | (corners > 1.0 + tol.UV_RANGE_SLACK)).any(axis=2)
        degenerate = degenerate_uv_triangles(corners, width, height)
        non_finite_corners, out_of_range_corners = int(np.count_nonzero(~finite)), int(np.count_nonzero(away & finite))
    return UVLayoutStats(
        triangles=int(corners.shape[0]),
        non_finite_corners=non_finite_corners,
        out_of_range_corners=out_of_range_corners,
        zero_area_triangles=int(np.count_nonzero(degenerate)),
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
        atlas, ``ValueError`` is raised (xatlas itself shrinks any single chart
        larger than the atlas).

    Returns
    -------
    UnwrapResult
    """
    # Imported here so layout checks keep working where the xatlas wheel is missing.
    import xatlas

    positions = np.asarray(positions)
    triangles = np.asarray(triangles)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise UnwrapFailed(f"unwrap: positions must have shape (n, 3), got {positions.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise UnwrapFailed(f"unwrap: triangles must have shape (m, 3), got {triangles.shape}")
    if triangles.shape[0] == 0:
        raise UnwrapFailed("unwrap: the mesh has no triangles")
    if not np.issubdtype(triangles.dtype, np.integer):
        raise UnwrapFailed(f"unwrap: triangles must be integer indices, got {triangles.dtype}")
    if triangles.min() < 0 or triangles.max() >= positions.shape[0]:
        raise UnwrapFailed(f"unwrap: triangle indices must lie in [0, {positions.shape[0]})")
    if int(resolution) != resolution or int(padding_texels) != padding_texels:
        raise UnwrapFailed("unwrap: resolution and padding_texels must be integers")
    resolution, padding = int(resolution), int(padding_texels)
    if padding < 0 or resolution < 2 * padding + 2:
        raise UnwrapFailed(f"unwrap: resolution {resolution} is too small for {padding} texels of padding")
    if texels_per_unit is not None and not (np.isfinite(texels_per_unit) and texels_per_unit > 0):
        raise UnwrapFailed(f"unwrap: texels_per_unit must be positive, got {texels_per_unit!r}")

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
            doubled = np.linalg.norm(edge_cross(xc), axis=1)
            usable[usable] = np.isfinite(doubled) & (doubled > tol.UNWRAP_MIN_DOUBLED_AREA)
    if not usable.any():
        raise UnwrapFailed(f"unwrap: none of the {m} triangles has a finite, non-zero area")

    kept = np.flatnonzero(usable)
    vertices, local = np.unique(tri[kept], return_inverse=True)
    local = local.reshape(-1, 3).astype(np.uint32)
    xpos = np.ascontiguousarray(((pos[vertices] - centre) * scale).astype(np.float32))
    xpos = _break_planar_chains(xpos, local)

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
    if atlas.width == 0 or atlas.height == 0:
        raise UnwrapFailed(f"unwrap: xatlas found no usable face among the {kept.size} triangles")
    _, faces, uv = atlas[0]
    if faces.shape[0] != kept.size:
        raise RuntimeError(f"xatlas returned {faces.shape[0]} faces for {kept.size} input triangles")
    texel_uv = uv.astype(np.float64) * np.array([atlas.width, atlas.height], dtype=np.float64)
    density = float(atlas.texels_per_unit)
    dropped = _outside_charts(atlas, faces)

    if texels_per_unit is not None:
        if atlas.atlas_count != 1:
            raise UnwrapFailed(f"unwrap: at {texels_per_unit} texels per unit the charts need {atlas.atlas_count} "
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


def _break_planar_chains(xpos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Nudge the vertices of curved near-coplanar face chains so xatlas cannot make them one planar chart.

    Parameters
    ----------
    xpos : (v, 3) float32, normalised positions (median edge length 1)
    faces : (f, 3) uint32

    Returns
    -------
    xpos : (v, 3) float32, the input itself when nothing needed breaking
    """
    # Colocated vertices are one vertex to xatlas; nudging them apart would tear the mesh.
    _, weld = np.unique(xpos, axis=0, return_inverse=True)
    weld = weld.ravel()
    welded = weld[faces.astype(np.int64)]
    rng = np.random.default_rng(0)
    nudge = PLANAR_CHAIN_NUDGE
    for _ in range(PLANAR_CHAIN_TRIES):
        hazard = _curved_planar_regions(xpos, faces, welded)
        if not hazard.any():
            return xpos
        corners = xpos[faces[hazard]].astype(np.float64)
        face_normal = edge_cross(corners)
        vertex_normal = np.zeros((weld.max() + 1, 3))
        for k in range(3):
            np.add.at(vertex_normal, welded[hazard, k], face_normal)
        length = np.linalg.norm(vertex_normal, axis=1, keepdims=True)
        vertex_normal = np.divide(vertex_normal, length, out=np.zeros_like(vertex_normal), where=length > 0)
        sign = rng.choice([-1.0, 1.0], size=len(vertex_normal))
        offset = (nudge * sign)[:, None] * vertex_normal
        xpos = (xpos + offset[weld]).astype(np.float32)
        nudge *= 2.0
    if _curved_planar_regions(xpos, faces, welded).any():
        raise RuntimeError("unwrap: the mesh has smooth curved regions xatlas would flatten into one "
                           "overlapping (or crashing) planar chart, and nudging them did not help")
    return xpos


def _curved_planar_regions(xpos: np.ndarray, faces: np.ndarray, welded: np.ndarray) -> np.ndarray:
    """Faces in a chain xatlas would take as planar whose normals stray past PLANAR_CHAIN_MAX_ANGLE_DEG.

    Parameters
    ----------
    xpos : (v, 3) float32
    faces : (f, 3) uint32
    welded : (f, 3) int64, corner vertices with colocated vertices merged

    Returns
    -------
    hazard : (f,) bool
    """
    corners = xpos[faces].astype(np.float64)
    normal = edge_cross(corners)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    f = faces.shape[0]
    # Faces sharing an edge are adjacent in the sorted edge list.
    a = welded.ravel()
    b = welded[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * (int(welded.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    same = key[order[1:]] == key[order[:-1]]
    f0 = order[:-1][same] // 3
    f1 = order[1:][same] // 3
    dot = np.einsum("ij,ij->i", normal[f0], normal[f1])
    near = np.abs(dot - 1.0) <= tol.PLANAR_CHAIN_DOT_SLACK
    label = _components(f, f0[near], f1[near])
    mean = np.zeros((f, 3))
    np.add.at(mean, label, normal)
    length = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = np.divide(mean, length, out=np.zeros_like(mean), where=length > 0)
    spread = np.einsum("ij,ij->i", normal, mean[label])
    lowest = np.full(f, np.inf)
    np.minimum.at(lowest, label, spread)
    return lowest[label] < np.cos(np.radians(PLANAR_CHAIN_MAX_ANGLE_DEG))


def _components(count: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component label (the smallest member) of each of ``count`` nodes joined by edges a-b."""
    parent = np.arange(count)
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            return parent
        np.minimum.at(parent, np.maximum(ra[differ], rb[differ]), np.minimum(ra[differ], rb[differ]))
        while True:
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up


def _outside_charts(atlas, faces: np.ndarray) -> np.ndarray:
    """Faces with a vertex xatlas put in no chart: xatlas ignored them and never placed their UVs.

    Returns
    -------
    dropped : (f,) bool
    """
    unassigned = np.iinfo(np.uint32).max
    atlas_index, chart_index = atlas.get_mesh_vertex_assignment(0)
    unplaced = (np.asarray(atlas_index) == unassigned) | (np.asarray(chart_index) == unassigned)
    return unplaced[faces].any(axis=1)


def loop_uvs(positions, triangles, loops, corner_uv, loop_count):
    """One UV per mesh loop from per-triangle-corner UVs.

    A loop is shared by the triangles of one polygon; when an unwrapper put those
    triangles into different charts, the polygon is remapped into the chart of its
    largest triangle through that triangle's affine map from 3D to UV, so the
    polygon stays one piece instead of stretching across the atlas.

    Returns
    -------
    per_loop : (loop_count, 2) float32
    remapped : int, polygons that had to be remapped
    """
    corner_uv = np.asarray(corner_uv, np.float64)
    flat_loops = loops.ravel()
    flat_uv = corner_uv.reshape(-1, 2)
    per_loop = np.zeros((loop_count, 2))
    per_loop[flat_loops] = flat_uv
    disagree = np.any(np.abs(per_loop[flat_loops] - flat_uv) > 1e-7, axis=1).reshape(-1, 3).any(axis=1)
    if not np.any(disagree):
        return per_loop.astype(np.float32), 0
    # Triangles sharing a loop belong to one polygon: union them.
    parent = np.arange(len(triangles))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    first_triangle = np.full(loop_count, -1)
    for t, corner_loops in enumerate(loops):
        for loop in corner_loops:
            if first_triangle[loop] < 0:
                first_triangle[loop] = t
            else:
                ra, rb = find(first_triangle[loop]), find(t)
                if ra != rb:
                    parent[rb] = ra
    roots = np.array([find(t) for t in range(len(triangles))])
    bad_roots = np.unique(roots[disagree])
    uv_area = triangle_areas(corner_uv)
    for root in bad_roots:
        members = np.nonzero(roots == root)[0]
        reference = members[np.argmax(uv_area[members])]
        p = positions[triangles[reference]].astype(np.float64)
        e1, e2 = p[1] - p[0], p[2] - p[0]
        gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        if abs(np.linalg.det(gram)) < 1e-30:
            continue
        inverse = np.linalg.inv(gram)
        uv0, uv1, uv2 = corner_uv[reference]
        for t in members:
            for corner, loop in enumerate(loops[t]):
                d = positions[triangles[t][corner]] - p[0]
                s, u = inverse @ np.array([d @ e1, d @ e2])
                per_loop[loop] = uv0 + s * (uv1 - uv0) + u * (uv2 - uv0)
    return np.clip(per_loop, 0.0, 1.0).astype(np.float32), len(bad_roots)
