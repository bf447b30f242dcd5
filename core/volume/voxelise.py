"""A closed mesh's interior as a voxel grid: what Cycles renders for a mesh whose material has
a volume shader (the medium fills the mesh's inside), as a density grid for core.volume.

:func:`fitted_grid` makes a grid around a bounding box; :func:`inside_fraction` gives each
voxel the fraction of its stratified sub-samples that lie inside the mesh.

The inside test
---------------
Rays parallel to the grid's three axes, one per column of sub-samples, each collecting every
surface crossing along its line (embree finds the nearest hit; the ray is cast again from
just past it until it leaves the mesh). A sample's inside/outside follows from the parity of
the crossings before it. Each of the three axes votes:

- a column with an odd number of crossings (its line went through a hole of an open mesh, or
  grazed a silhouette edge or vertex and met one triangle where it should have met two or
  none) says nothing: its parity from one end contradicts its parity from the other, so it
  abstains;
- the sample is inside when most of the axes that did not abstain say so. Where they tie (or
  all abstain), the plain majority of the three axes' parities counted from the axes' low
  ends decides.

So a hole only misleads the samples whose three lines all cross holes: a mesh with one face
missing still voxelises to its closed interior (the lines through the missing face abstain,
the two other axes agree). Crossing parity is exact for a closed mesh and ignores the faces'
winding: it fills the geometric inside. (Cycles enters a mesh's volume through a front face
and leaves it through a back face, so a mesh with flipped normals renders otherwise there.)

Measured on a 10 k-triangle mesh, 64^3 voxels of 2^3 samples (2 cores): about 0.2 s. Against
the plain majority of the three parities (no abstaining), the abstaining vote gives the
same answer for a closed mesh and keeps a cube with two adjacent faces missing whole (the
plain majority empties it); a single axis's parity (the usual scanline voxeliser) empties
a cube with its bottom missing. With a fifth of a sphere's triangles missing no parity
scheme is good (about 10 % of the volume off either way).

A generalized winding number (Jacobson et al. 2013) is the more robust test for badly broken
meshes, but it sums over every triangle per sample: 2 M samples times 10 k triangles is 2e10
solid angles, about two hours in numpy (measured: 3e6 triangle-samples a second), against
the fraction of a second of the rays; its fast hierarchical form (Barill et al. 2018) is far
more code than the holes it would fix.
"""
from __future__ import annotations

import numpy as np

from ..visibility.rays import RayScene

# Sub-samples per chunk of the grid (bounds the memory of the votes: about 8 bytes each).
_CHUNK_SAMPLES = 1 << 22
# A line crossing more surfaces than this is given up as unreliable (abstains).
_MAX_LAYERS = 4096


def fitted_grid(bounds_min, bounds_max, resolution: int, margin_voxels: int = 1):
    """A grid of cubic voxels around an axis-aligned box.

    bounds_min, bounds_max : (3,) real, the box's corners (any space: world or object)
    resolution : int >= 1, the grid's voxels along its longest side, margins included
    margin_voxels : int >= 0, empty voxels on each side of the box (fewer where ``resolution``
        leaves no room: at most (resolution - 1) // 2, so at least one voxel spans the box)

    The box's longest side spans ``resolution - 2 * margin`` voxels exactly; each other side
    the fewest voxels of that size that cover it (at least one; a side longer than a whole
    number of voxels by under 1e-4 voxel counts as that number), plus the margins. The box is
    centred in the grid.

    Returns
    -------
    shape : tuple of 3 int
    index_to_world : (4, 4) float64, voxel (i, j, k)'s centre at ``index_to_world @ (i, j, k, 1)``
        in the box's space (a diagonal scale by the voxel size and a translation)

    Raises ValueError for non-finite bounds, a box with no extent, or a resolution below 1.
    """
    low = np.asarray(bounds_min, np.float64).reshape(3)
    high = np.asarray(bounds_max, np.float64).reshape(3)
    resolution = int(resolution)
    if resolution < 1:
        raise ValueError(f"resolution {resolution} is below 1")
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise ValueError("the bounds are not finite")
    extent = high - low
    longest = float(extent.max())
    if not longest > 0:
        raise ValueError(f"the bounds {low.tolist()} .. {high.tolist()} enclose nothing")
    margin = max(0, min(int(margin_voxels), (resolution - 1) // 2))
    inner = resolution - 2 * margin
    voxel = longest / inner
    # A side a hair over a whole number of voxels (float32 vertices: 4/9 is 4.0000001 voxels of
    # 1/9) gets that number: the box pokes under 1e-4 voxel into the margin, centred. The
    # longest side gets exactly ``inner``.
    cover = np.clip(np.ceil(extent / voxel - 1e-4), 1, inner).astype(np.int64)
    shape = tuple(int(n) + 2 * margin for n in cover)
    centre = 0.5 * (low + high)
    matrix = np.eye(4)
    matrix[:3, :3] *= voxel
    matrix[:3, 3] = centre - voxel * (np.array(shape, np.float64) - 1.0) / 2.0
    return shape, matrix


def inside_fraction(vertices, triangles, index_to_world, shape, samples_per_axis: int = 2,
                    threads: int = 0) -> np.ndarray:
    """The fraction of each voxel inside a closed triangle mesh.

    vertices : (n, 3) real, in the space ``index_to_world`` maps to (non-finite ones drop
        their triangles)
    triangles : (m, 3) int, indices into ``vertices``
    index_to_world : (4, 4) (or (3, 4)) real, invertible: voxel (i, j, k)'s centre is at
        ``index_to_world @ (i, j, k, 1)``; a voxel is the unit cell around its centre in index
        space (any affine map: rotated, sheared, non-uniformly scaled)
    shape : three ints >= 1, the grid's voxels per axis
    samples_per_axis : int >= 1; each voxel is sampled on a stratified ``s x s x s`` grid
        (sample j of an axis at offset (j + 0.5) / s - 0.5 from the centre)
    threads : embree query threads (0: all cores)

    Returns
    -------
    (nx, ny, nz) float32 in [0, 1], multiples of 1 / s^3. All zeros for a mesh without
    triangles. See the module docstring for the inside test.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid shape {shape} is not three sides >= 1")
    s = int(samples_per_axis)
    if s < 1:
        raise ValueError(f"samples_per_axis {samples_per_axis} is below 1")
    result = np.zeros(shape, np.float32)
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(triangles) == 0:
        return result
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ValueError(f"triangle indices reach {int(triangles.max())} (or below 0) with {len(vertices)} vertices")
    matrix = np.asarray(index_to_world, np.float64)
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError("index_to_world is not a finite 4 x 4 matrix")
    to_index = np.linalg.inv(matrix)
    with np.errstate(invalid="ignore", over="ignore"):
        points = vertices @ to_index[:3, :3].T + to_index[:3, 3]
    finite = np.all(np.isfinite(points), axis=1)
    triangles = triangles[np.all(finite[triangles], axis=1)]
    if len(triangles) == 0:
        return result
    used = points[np.unique(triangles)]
    low, high = used.min(axis=0), used.max(axis=0)
    # Only voxels whose cell meets the mesh's box can hold a sample inside it.
    first = np.clip(np.floor(low + 0.5), 0, shape).astype(np.int64)
    last = np.clip(np.ceil(high + 0.5), 0, shape).astype(np.int64)
    if np.any(last <= first):
        return result
    box = tuple(int(n) for n in last - first)
    # Trace in a frame centred on the box (embree's float32 then resolves the box's extent).
    centre = 0.5 * (low + high)
    scene = RayScene([(points, triangles.astype(np.int32))], threads, centre=centre)
    # Sample coordinates per axis, in the traced frame: sample m of the box lies in voxel
    # first + m // s, at offset (m % s + 0.5) / s - 0.5.
    coords = [first[a] + (np.arange(box[a] * s) + 0.5) / s - 0.5 - centre[a] for a in range(3)]
    start = low - centre - 1.0  # rays start a voxel before the mesh: they see every crossing
    lines = [_crossings(scene, coords, axis, start[axis]) for axis in range(3)]
    sides = [n * s for n in box]
    chunk = max(1, _CHUNK_SAMPLES // (sides[1] * sides[2] * s))
    block = np.zeros(box, np.float32)
    for x0 in range(0, box[0], chunk):
        x1 = min(box[0], x0 + chunk)
        inside = _vote(lines, coords, sides, x0 * s, x1 * s)
        count = x1 - x0
        inside = inside.reshape(count, s, box[1], s, box[2], s)
        total = np.zeros((count, box[1], box[2]), np.uint16)
        for i in range(s):  # s^3 strided adds: much faster than numpy's reduction over split axes
            for j in range(s):
                for k in range(s):
                    total += inside[:, i, :, j, :, k]
        block[x0:x1] = total * np.float32(1.0 / s ** 3)
    result[first[0]:last[0], first[1]:last[1], first[2]:last[2]] = block
    return result


def _crossings(scene: RayScene, coords, axis: int, start: float):
    """Every crossing of the lines along ``axis`` through the sample columns.

    Columns are the sample coordinates of the two other axes (in increasing axis order), in
    C order. Returns (column (N,) int64 ascending, position (N,) float64 along ``axis`` in the
    traced frame, ascending within a column; valid (C,) bool: the column crossed an even
    number of times). Held sparsely: one line through many layers costs only its own hits.
    """
    other = [a for a in range(3) if a != axis]
    grid = np.meshgrid(coords[other[0]], coords[other[1]], indexing="ij")
    count = grid[0].size
    origins = np.empty((count, 3), np.float32)
    origins[:, other[0]] = grid[0].ravel()
    origins[:, other[1]] = grid[1].ravel()
    direction = np.zeros(3, np.float32)
    direction[axis] = 1.0
    position = np.full(count, start, np.float64)
    active = np.arange(count)
    columns, positions = [], []
    for _ in range(_MAX_LAYERS):
        if len(active) == 0:
            break
        origins[active, axis] = position[active]
        directions = np.ascontiguousarray(np.broadcast_to(direction, (len(active), 3)))
        geometry, _, _, distance = scene.intersect_local(origins[active], directions)
        hit = geometry >= 0
        active = active[hit]
        # The hit as embree measured it: from the float32 origin actually traced.
        found = origins[active, axis].astype(np.float64) + distance[hit].astype(np.float64)
        columns.append(active)
        positions.append(found)
        # Cast again from just past the hit (embreex has no tnear): a few float32 steps, at
        # least 1e-4 voxel, so the same triangle is not met twice.
        step = np.maximum(1e-4, 16.0 * np.spacing(np.abs(found).astype(np.float32)).astype(np.float64))
        position[active] = found + step
    column = np.concatenate(columns) if columns else np.zeros(0, np.int64)
    found = np.concatenate(positions) if positions else np.zeros(0)
    order = np.argsort(column, kind="stable")  # layers were appended in order along each line
    column, found = column[order], found[order]
    valid = np.bincount(column, minlength=count) % 2 == 0
    if len(active):  # lines still crossing after _MAX_LAYERS: give them up
        valid[active] = False
    return column, found, valid


def _parity(line, first: int, last: int, coords: np.ndarray) -> np.ndarray:
    """(last - first, L) uint8: per column of ``first`` .. ``last`` - 1 of ``line`` (what
    :func:`_crossings` returns), the parity of its crossings before each of ``coords`` (L,),
    sorted. Crossings before ``coords[0]`` count for all, after the last for none."""
    column, found, _ = line
    width = len(coords)
    lo, hi = np.searchsorted(column, [first, last])
    slot = np.searchsorted(coords, found[lo:hi], side="right")
    toggles = np.zeros((last - first, width + 1), np.uint8)
    # Sums in uint8 wrap at 256, which keeps their parity.
    np.add.at(toggles, (column[lo:hi] - first, slot), np.uint8(1))
    return np.cumsum(toggles[:, :width], axis=1, dtype=np.uint8) & np.uint8(1)


def _vote(lines, coords, sides, x0: int, x1: int) -> np.ndarray:
    """(x1 - x0, Y, Z) bool: the samples of x range [x0, x1) inside the mesh, by the three axes'
    votes (the module docstring)."""
    _, ny, nz = sides
    width = x1 - x0
    # Axis 0: columns (y, z), all of them, crossings counted along x within the range.
    along_x = _parity(lines[0], 0, ny * nz, coords[0][x0:x1]).reshape(ny, nz, width).transpose(2, 0, 1)
    valid_x = lines[0][2].reshape(1, ny, nz)
    # Axis 1: columns (x, z), those with x in the range.
    along_y = _parity(lines[1], x0 * nz, x1 * nz, coords[1]).reshape(width, nz, ny).transpose(0, 2, 1)
    valid_y = lines[1][2][x0 * nz:x1 * nz].reshape(width, 1, nz)
    # Axis 2: columns (x, y), those with x in the range.
    along_z = _parity(lines[2], x0 * ny, x1 * ny, coords[2]).reshape(width, ny, nz)
    valid_z = lines[2][2][x0 * ny:x1 * ny].reshape(width, ny, 1)

    # Each sample's parities and its lines' validity as a 6-bit code, decided by the table.
    code = along_z + (along_y << 1)
    code += along_x << 2
    code += (valid_z.astype(np.uint8) << 3) + (valid_y.astype(np.uint8) << 4)
    code += valid_x.astype(np.uint8) << 5
    return _DECISION[code]


def _decide(code: int) -> bool:
    """The vote of one sample: ``code`` holds bits (z, y, x parity; z, y, x line valid)."""
    parity = [(code >> bit) & 1 for bit in range(3)]
    valid = [(code >> bit) & 1 for bit in range(3, 6)]
    voters = sum(valid)
    yes = sum(p * v for p, v in zip(parity, valid))
    if voters and 2 * yes != voters:
        return 2 * yes > voters
    return sum(parity) >= 2


_DECISION = np.array([_decide(code) for code in range(64)], bool)
