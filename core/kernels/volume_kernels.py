"""Compiled (numba) kernels of the volume passes (core.volume): the direct light's slice
sweep, the scattering tables' ray march, the 3D gather and the world's light through the
tables.

Imported only through :func:`core.kernels.volume`, the first time a volume is lit: a
surface bake never compiles them.

Every grid a kernel reads is zero-padded (:func:`core.volume.medium.padded`): voxel
(i, j, k) is stored at (i + 1, j + 1, k + 1), with one layer of zeros below and two above.
The medium's density is the trilinear interpolation of its voxel centres with zeros outside
the grid, so it fades to zero over the half voxel beyond the grid's faces, which integrates
as a hard face at -0.5 and n - 0.5 (the closed forms of the tests use that). A point
anywhere in [-1, n] then reads its eight neighbours without a bounds test.

Each parallel loop writes disjoint outputs and sums in a fixed order, so the results do
not depend on the thread count.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from . import KERNEL_OPTIONS, SERIAL_OPTIONS

# Distances and escape fractions are stored as 16-bit codes (core.volume.tables).
CODE_MAX = 65535.0
# A ray this optically deep lets less than 1/65535 through (exp(-11.1)): its escape code is 0.
ESCAPE_BEYOND = 11.1
# Voxels per task of the table march and the gather.
BLOCK = 512


@nb.njit(**SERIAL_OPTIONS)
def trilinear(grid, x, y, z):
    """The padded scalar ``grid`` (X, Y, Z) float32 at index-space point (x, y, z): zero
    outside [-1, n] on any axis."""
    px = x + 1.0
    py = y + 1.0
    pz = z + 1.0
    limit_x = grid.shape[0] - 2
    limit_y = grid.shape[1] - 2
    limit_z = grid.shape[2] - 2
    if px < 0.0 or py < 0.0 or pz < 0.0 or px > limit_x or py > limit_y or pz > limit_z:
        return 0.0
    i = int(px)
    j = int(py)
    k = int(pz)
    fx = px - i
    fy = py - j
    fz = pz - k
    c00 = grid[i, j, k] + (grid[i + 1, j, k] - grid[i, j, k]) * fx
    c10 = grid[i, j + 1, k] + (grid[i + 1, j + 1, k] - grid[i, j + 1, k]) * fx
    c01 = grid[i, j, k + 1] + (grid[i + 1, j, k + 1] - grid[i, j, k + 1]) * fx
    c11 = grid[i, j + 1, k + 1] + (grid[i + 1, j + 1, k + 1] - grid[i, j + 1, k + 1]) * fx
    c0 = c00 + (c10 - c00) * fy
    c1 = c01 + (c11 - c01) * fy
    return c0 + (c1 - c0) * fz


@nb.njit(**SERIAL_OPTIONS)
def _bilinear_slice(grid, k, b, c, outside):
    """Slice ``k`` (padded index) of the padded ``grid`` (X, Y, Z) at in-slice index point
    (b, c); ``outside`` beyond [-1, n] on either axis."""
    pb = b + 1.0
    pc = c + 1.0
    if pb < 0.0 or pc < 0.0 or pb > grid.shape[1] - 2 or pc > grid.shape[2] - 2:
        return outside
    j = int(pb)
    m = int(pc)
    fb = pb - j
    fc = pc - m
    low = grid[k, j, m] + (grid[k, j + 1, m] - grid[k, j, m]) * fb
    high = grid[k, j, m + 1] + (grid[k, j + 1, m + 1] - grid[k, j, m + 1]) * fb
    return low + (high - low) * fc


@nb.njit(**SERIAL_OPTIONS)
def _grid_index(axis, order, along, row, column):
    """The index along the grid's axis ``axis`` of a sweep frame's voxel (along, row, column),
    the frame's axes being the grid's axes ``order``."""
    if order[0] == axis:
        return along
    if order[1] == axis:
        return row
    return column


@nb.njit(**KERNEL_OPTIONS)
def sweep_transmittance(density, extinction, is_point, light, linear, select, flip, order, lamp_density, out):
    """Transmittance from every voxel to a lamp, by front-to-back slices from the lamp (the
    paper's section 6.1): each voxel continues the value of the previous slice, read
    bilinearly where its ray towards the lamp crosses that slice, over the segment between
    (trapezoidal in density).

    What a slice carries is chosen so that the bilinear read is exact in a homogeneous
    medium: for a sun the transmittance (constant across a slab's slice), for a lamp at a
    position the mean extinction along the ray to the lamp (constant in any homogeneous
    medium, where the transmittance falls off radially and a bilinear read of it would
    darken every slice a little more).

    The sweep runs in a frame (core.volume.direct.SweepFrame): the grid's axes permuted so
    that the sweep axis is first, and that axis read backwards when ``flip``, so that the
    sweep's index increases away from the lamp. The results go straight into the grid's own
    layout, so the six sweeps of a lamp need no merge.

    density : (A + 3, B + 3, C + 3) float32 padded density, permuted (not flipped)
    extinction : float64, sigma_t per unit density per world unit
    is_point : True for a lamp at a position, False for a direction (a sun)
    light : (3,) float64 a point lamp's position in the frame's index space, or a sun's
        direction towards it, scaled so that its first component is -1 (one slice back)
    linear : (3, 3) float64 the frame's index-to-world linear map (segment lengths)
    select : True: write only the voxels whose ray to the lamp leaves through the slice
        behind them (the lamp's pyramid along this axis); False: every voxel
    flip : the sweep axis is read backwards; order : (3,) int64 the grid axes in frame order
    lamp_density : float64 the density at a point lamp (0 for a sun)
    out : (nx, ny, nz) float32 in the grid's own layout, written where selected (the caller
        pre-fills it)
    """
    count_a = density.shape[0] - 3
    count_b = density.shape[1] - 3
    count_c = density.shape[2] - 3
    # Outside the grid nothing attenuates: transmittance 1 (a sun), mean extinction 0 (a lamp).
    outside = 0.0 if is_point else 1.0
    previous = np.full((count_b + 3, count_c + 3), outside)
    current = np.full((count_b + 3, count_c + 3), outside)
    first = 0
    if is_point:
        first = max(0, int(np.floor(light[0])) + 1)
    for a in range(first, count_a):
        # Padded indices of this slice and the one behind it (-1: the pad before the grid).
        slice_here = count_a - a if flip else a + 1
        slice_behind = count_a - a + 1 if flip else a
        grid_a = np.int64(count_a - 1 - a) if flip else np.int64(a)
        # A lamp's pyramid widens by a voxel per slice: only its cross-section, and a margin that
        # the next slice's bilinear reads reach, needs computing (a sixth of the grid, not half).
        low_b, high_b, low_c, high_c = 0, count_b, 0, count_c
        if is_point and select:
            reach_out = a - light[0] + 2.0
            low_b = max(0, int(np.floor(light[1] - reach_out)))
            high_b = min(count_b, int(np.ceil(light[1] + reach_out)) + 1)
            low_c = max(0, int(np.floor(light[2] - reach_out)))
            high_c = min(count_c, int(np.ceil(light[2] + reach_out)) + 1)
        for b in nb.prange(low_b, high_b):
            for c in range(low_c, high_c):
                here = density[slice_here, b + 1, c + 1]
                # This voxel's index in the grid's own layout (prange's index may be unsigned:
                # cast, or numba unifies int64 with it as float).
                row = np.int64(b)
                column = np.int64(c)
                i0 = _grid_index(0, order, grid_a, row, column)
                i1 = _grid_index(1, order, grid_a, row, column)
                i2 = _grid_index(2, order, grid_a, row, column)
                if is_point:
                    sa = light[0] - a
                    sb = light[1] - b
                    sc = light[2] - c
                    wx = linear[0, 0] * sa + linear[0, 1] * sb + linear[0, 2] * sc
                    wy = linear[1, 0] * sa + linear[1, 1] * sb + linear[1, 2] * sc
                    wz = linear[2, 0] * sa + linear[2, 1] * sb + linear[2, 2] * sc
                    reach = np.sqrt(wx * wx + wy * wy + wz * wz)
                    if a - light[0] <= 1.0:
                        # The lamp lies within one slice: integrate straight to it.
                        depth = extinction * reach * 0.5 * (here + lamp_density)
                        current[b + 1, c + 1] = depth / reach if reach > 0.0 else extinction * lamp_density
                        if not select or (-sa >= abs(sb) and -sa >= abs(sc)):
                            out[i0, i1, i2] = np.exp(-depth)
                        continue
                    step = 1.0 / (a - light[0])
                    sa *= step
                    sb *= step
                    sc *= step
                else:
                    sa = light[0]
                    sb = light[1]
                    sc = light[2]
                    reach = 0.0
                wx = linear[0, 0] * sa + linear[0, 1] * sb + linear[0, 2] * sc
                wy = linear[1, 0] * sa + linear[1, 1] * sb + linear[1, 2] * sc
                wz = linear[2, 0] * sa + linear[2, 1] * sb + linear[2, 2] * sc
                length = np.sqrt(wx * wx + wy * wy + wz * wz)
                qb = b + sb
                qc = c + sc
                behind = _bilinear_slice(density, slice_behind, qb, qc, 0.0)
                carried = outside
                if a > first or (not is_point and a > 0):
                    pb = qb + 1.0
                    pc = qc + 1.0
                    if pb >= 0.0 and pc >= 0.0 and pb <= count_b + 1 and pc <= count_c + 1:
                        j = int(pb)
                        m = int(pc)
                        fb = pb - j
                        fc = pc - m
                        low = previous[j, m] + (previous[j + 1, m] - previous[j, m]) * fb
                        high = previous[j, m + 1] + (previous[j + 1, m + 1] - previous[j, m + 1]) * fb
                        carried = low + (high - low) * fc
                segment = extinction * length * 0.5 * (here + behind)
                if is_point:
                    depth = carried * (reach - length) + segment
                    current[b + 1, c + 1] = depth / reach
                    value = np.exp(-depth)
                else:
                    value = carried * np.exp(-segment)
                    current[b + 1, c + 1] = value
                # The step is one slice back (sa = -1): the lamp's pyramid is where it moves
                # at most one voxel sideways.
                if not select or (abs(sb) <= 1.0 and abs(sc) <= 1.0):
                    out[i0, i1, i2] = value
        previous, current = current, previous


@nb.njit(**SERIAL_OPTIONS)
def _hash_unit(a, b, c):
    """A uniform number in [0, 1) from three non-negative integers (a PCG-style hash)."""
    h = np.uint64(a) * np.uint64(0x9E3779B97F4A7C15) ^ np.uint64(b) * np.uint64(0xBF58476D1CE4E5B9) \
        ^ np.uint64(c) * np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(31)
    h *= np.uint64(0xD6E8FEB86659FD93)
    h ^= h >> np.uint64(32)
    return (h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@nb.njit(**KERNEL_OPTIONS)
def scatter_table(density, active, directions, world_per_index, extinction, step, points, seed, code_scale,
                  block, blocked, first_direction, first_voxel, distance_codes, escape_codes):
    """For every direction and active voxel, march the ray through the medium and store where
    it scatters (section 6.2 of the paper): ``points`` quantiles (j + u) / points of the
    free-flight distribution within the grid, u a hashed uniform per voxel, direction and
    point when ``seed`` >= 0 (the paper's random point for points = 1), u = 1/2 otherwise;
    and the fraction that escapes the grid, or reaches a mesh that blocks the ray first.

    Work goes in tasks of one direction and ``block`` consecutive voxels, so that the rays a
    thread marches together are parallel neighbours reading the same cells.

    density : (X, Y, Z) float32 padded density
    active : (V, 3) int32 voxel indices (C order)
    directions : (N, 3) float64 unit directions in index space
    world_per_index : (N,) float64 world length of one index unit along each direction
    extinction : float64 sigma_t per unit density per world unit; step : float64 index units
    points : int M; seed : int64 (< 0: deterministic midpoints); code_scale : float64
        distance codes per index unit; block : int voxels per task
    blocked : (N, V) float32 index-space distance at which a mesh stops each ray (inf: none),
        or (0, 0) when no mesh is near; the ray's free flight ends there
    first_direction : int64 the index of ``directions[0]`` in the whole set (the points'
        hash uses it, so that a table built in chunks of directions is the same table)
    first_voxel : int64 the index of ``active[0]`` among the medium's active voxels (likewise,
        for a table built by ranges of voxels)
    Outputs distance_codes (N, V, M) uint16 (index-space distance times code_scale) and
    escape_codes (N, V) uint16 (escaping fraction times 65535).
    """
    limit_x = float(density.shape[0] - 3)
    limit_y = float(density.shape[1] - 3)
    limit_z = float(density.shape[2] - 3)
    diagonal = np.sqrt((limit_x + 1.0) ** 2 + (limit_y + 1.0) ** 2 + (limit_z + 1.0) ** 2)
    max_steps = int(diagonal / step) + 3
    count_v = active.shape[0]
    blocks = (count_v + block - 1) // block
    for task in nb.prange(directions.shape[0] * blocks):
        d = task // blocks
        first = (task % blocks) * block
        depth = np.empty(max_steps + 1, np.float64)
        sampled = np.empty(max_steps + 1, np.float64)
        along = np.empty(max_steps + 1, np.float64)
        ux = directions[d, 0]
        uy = directions[d, 1]
        uz = directions[d, 2]
        scale = extinction * world_per_index[d] * 0.5
        for v in range(first, min(first + block, count_v)):
            x = float(active[v, 0])
            y = float(active[v, 1])
            z = float(active[v, 2])
            # The ray's last step ends where it leaves the box [-1, n] (the density is zero
            # there and beyond), so that no stored point lies outside the medium.
            exit_distance = 1e300
            for start, unit, limit in ((x, ux, limit_x), (y, uy, limit_y), (z, uz, limit_z)):
                if unit > 0.0:
                    exit_distance = min(exit_distance, (limit - start) / unit)
                elif unit < 0.0:
                    exit_distance = min(exit_distance, (-1.0 - start) / unit)
            if blocked.shape[0] > 0:
                exit_distance = min(exit_distance, max(float(blocked[d, v]), 0.0))
            before = trilinear(density, x, y, z)
            total = 0.0
            depth[0] = 0.0
            sampled[0] = before
            along[0] = 0.0
            count = 0
            travelled = 0.0
            while count < max_steps:
                length = min(step, exit_distance - travelled)
                if length <= 0.0:
                    break
                travelled += length
                after = trilinear(density, x + ux * travelled, y + uy * travelled, z + uz * travelled)
                total += scale * length * (before + after)
                count += 1
                depth[count] = total
                sampled[count] = after
                along[count] = travelled
                before = after
                if total > ESCAPE_BEYOND:
                    break
            escaping = np.exp(-total)
            escape_codes[d, v] = np.uint16(min(escaping * CODE_MAX + 0.5, CODE_MAX))
            scattered = 1.0 - escaping
            k = 0
            for j in range(points):
                if seed >= 0:
                    u = _hash_unit(v + first_voxel + np.int64(seed) * 1000003, np.int64(d) + first_direction, j)
                else:
                    u = 0.5
                target = -np.log(1.0 - (j + u) / points * scattered)
                while k < count and depth[k + 1] < target:
                    k += 1
                if k >= count:
                    distance = along[count]
                else:
                    rise = depth[k + 1] - depth[k]
                    share = min(max((target - depth[k]) / rise, 0.0), 1.0) if rise > 0.0 else 0.0
                    # The density is linear along the step, so the depth within it is
                    # quadratic: solve it, so that the point lands where there is medium
                    # (a linear guess puts it past a falling edge, even outside the grid).
                    low = sampled[k]
                    high = sampled[k + 1]
                    wanted = share * 0.5 * (low + high)
                    root = low * low + 2.0 * (high - low) * wanted
                    fraction = 2.0 * wanted / (low + np.sqrt(max(root, 0.0))) if wanted > 0.0 else 0.0
                    distance = along[k] + min(fraction, 1.0) * (along[k + 1] - along[k])
                distance_codes[d, v, j] = np.uint16(min(distance * code_scale + 0.5, CODE_MAX))


@nb.njit(**KERNEL_OPTIONS)
def gather_volume(source, active, directions, distance_codes, escape_codes, distance_per_code, block, result):
    """One bounce of the 3D transport: for every active voxel, the mean over directions of
    the light scattered at each stored point towards it.

    Each task takes ``block`` consecutive voxels through every direction in order, so a
    direction's lookups are neighbours in the source grid and each voxel's sum runs in the
    same order whatever the thread count.

    source : (X, Y, Z, 3) float32 padded: what a scattering point sends (albedo times
        in-scattered radiance, or emission over extinction), dilated one voxel beyond the
        medium (core.volume.transport.dilated_source), so that a plain trilinear read near
        the medium's edge does not mix in the zeros outside it
    active : (V, 3) int32; directions : (N, 3) float64 unit, index space
    distance_codes : (N, V, M) uint16; escape_codes : (N, V) uint16; distance_per_code :
        float64 index units per code; block : int voxels per task
    Output result (V, 3) float64: in-scattered radiance (the phase is isotropic).
    """
    count = directions.shape[0]
    points = distance_codes.shape[2]
    count_v = active.shape[0]
    limit_x = np.float32(source.shape[0] - 2)
    limit_y = np.float32(source.shape[1] - 2)
    limit_z = np.float32(source.shape[2] - 2)
    # Flat, unsigned offsets: the eight corners of a cell are fixed strides apart, and
    # unsigned indices spare the negative-index wrap test on each of the 24 reads.
    flat = source.ravel()
    step_z = np.uint64(3)
    step_y = np.uint64(3 * source.shape[2])
    step_x = np.uint64(3 * source.shape[2] * source.shape[1])
    zero = np.float32(0.0)
    one = np.float32(1.0)
    blocks = (count_v + block - 1) // block
    for task in nb.prange(blocks):
        first = task * block
        last = min(first + block, count_v)
        sums = np.zeros((last - first, 3), np.float64)
        for d in range(count):
            ex = np.float32(directions[d, 0] * distance_per_code)
            ey = np.float32(directions[d, 1] * distance_per_code)
            ez = np.float32(directions[d, 2] * distance_per_code)
            for v in range(first, last):
                weight = np.float32(CODE_MAX - escape_codes[d, v])
                if weight <= zero:
                    continue
                ox = np.float32(active[v, 0] + 1)
                oy = np.float32(active[v, 1] + 1)
                oz = np.float32(active[v, 2] + 1)
                r = zero
                g = zero
                b = zero
                for j in range(points):
                    code = np.float32(distance_codes[d, v, j])
                    px = ox + ex * code
                    py = oy + ey * code
                    pz = oz + ez * code
                    if px < zero or py < zero or pz < zero or px > limit_x or py > limit_y or pz > limit_z:
                        continue
                    i = np.uint64(px)
                    jj = np.uint64(py)
                    k = np.uint64(pz)
                    fx = px - np.float32(i)
                    fy = py - np.float32(jj)
                    fz = pz - np.float32(k)
                    gx = one - fx
                    gy = one - fy
                    gz = one - fz
                    w000 = gx * gy * gz
                    w100 = fx * gy * gz
                    w010 = gx * fy * gz
                    w110 = fx * fy * gz
                    w001 = gx * gy * fz
                    w101 = fx * gy * fz
                    w011 = gx * fy * fz
                    w111 = fx * fy * fz
                    a000 = i * step_x + jj * step_y + k * step_z
                    a100 = a000 + step_x
                    a010 = a000 + step_y
                    a110 = a100 + step_y
                    a001 = a000 + step_z
                    a101 = a100 + step_z
                    a011 = a010 + step_z
                    a111 = a110 + step_z
                    r += (w000 * flat[a000] + w100 * flat[a100] + w010 * flat[a010] + w110 * flat[a110]
                          + w001 * flat[a001] + w101 * flat[a101] + w011 * flat[a011] + w111 * flat[a111])
                    a000 += np.uint64(1)
                    a100 += np.uint64(1)
                    a010 += np.uint64(1)
                    a110 += np.uint64(1)
                    a001 += np.uint64(1)
                    a101 += np.uint64(1)
                    a011 += np.uint64(1)
                    a111 += np.uint64(1)
                    g += (w000 * flat[a000] + w100 * flat[a100] + w010 * flat[a010] + w110 * flat[a110]
                          + w001 * flat[a001] + w101 * flat[a101] + w011 * flat[a011] + w111 * flat[a111])
                    a000 += np.uint64(1)
                    a100 += np.uint64(1)
                    a010 += np.uint64(1)
                    a110 += np.uint64(1)
                    a001 += np.uint64(1)
                    a101 += np.uint64(1)
                    a011 += np.uint64(1)
                    a111 += np.uint64(1)
                    b += (w000 * flat[a000] + w100 * flat[a100] + w010 * flat[a010] + w110 * flat[a110]
                          + w001 * flat[a001] + w101 * flat[a101] + w011 * flat[a011] + w111 * flat[a111])
                row = v - first
                sums[row, 0] += weight * r
                sums[row, 1] += weight * g
                sums[row, 2] += weight * b
        # The weights were escape codes' complements, summed in float64: scale once.
        scale = 1.0 / (CODE_MAX * points * count)
        for v in range(first, last):
            result[v, 0] = sums[v - first, 0] * scale
            result[v, 1] = sums[v - first, 1] * scale
            result[v, 2] = sums[v - first, 2] * scale


@nb.njit(**KERNEL_OPTIONS)
def march_transmittance(density, points, directions, lengths, world_per_index, extinction, step, out):
    """Transmittance through the medium along K index-space segments, marched in ``step``
    index units with the trapezoid rule, from where each enters the box [-1, n] (the density
    is zero outside it) to where it leaves it or ends.

    density : (X, Y, Z) float32 padded; points : (K, 3) float64 starts; directions : (K, 3)
    float64 unit; lengths : (K,) float64 index units (inf: unbounded, a sun);
    world_per_index : (K,) float64 world length of an index unit along each; extinction,
    step : float64. Output out (K,) float64.
    """
    limit_x = float(density.shape[0] - 3)
    limit_y = float(density.shape[1] - 3)
    limit_z = float(density.shape[2] - 3)
    for q in nb.prange(points.shape[0]):
        x = points[q, 0]
        y = points[q, 1]
        z = points[q, 2]
        ux = directions[q, 0]
        uy = directions[q, 1]
        uz = directions[q, 2]
        near = 0.0
        far = lengths[q]
        for start, unit, limit in ((x, ux, limit_x), (y, uy, limit_y), (z, uz, limit_z)):
            if unit != 0.0:
                a = (-1.0 - start) / unit
                b = (limit - start) / unit
                near = max(near, min(a, b))
                far = min(far, max(a, b))
            elif start < -1.0 or start > limit:
                far = -1.0
        depth = 0.0
        if far > near:
            travelled = near
            before = trilinear(density, x + ux * near, y + uy * near, z + uz * near)
            while travelled < far:
                length = min(step, far - travelled)
                travelled += length
                after = trilinear(density, x + ux * travelled, y + uy * travelled, z + uz * travelled)
                depth += 0.5 * length * (before + after)
                before = after
                if depth * extinction * world_per_index[q] > ESCAPE_BEYOND:
                    break
        out[q] = np.exp(-depth * extinction * world_per_index[q])


@nb.njit(**KERNEL_OPTIONS)
def world_light(radiance, escape, out):
    """The world's radiance arriving at each table voxel: out[v] = the mean over the N
    directions of radiance[n] * escape[n, v], summed in float64 in the directions' order, so
    that a range of voxels gets bitwise the whole tables' values (a BLAS product's order
    depends on the CPU's kernel and the matrix's width: on an AMD EPYC, ranges of a float32
    sgemm differed in the last bit). In parallel over voxels.

    radiance : (N, 3) float64; escape : (N, V) float32 (core.volume.tables.ScatteringTables.
    world_escape); out : (V, 3) float64.
    """
    count = escape.shape[0]
    for v in nb.prange(escape.shape[1]):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for n in range(count):
            fraction = np.float64(escape[n, v])
            s0 += radiance[n, 0] * fraction
            s1 += radiance[n, 1] * fraction
            s2 += radiance[n, 2] * fraction
        out[v, 0] = s0 / count
        out[v, 1] = s1 / count
        out[v, 2] = s2 / count


def warm_up() -> None:
    """Compile (or read from the cache) each kernel for the dtypes its callers pass, so that
    no call during a bake compiles (core.kernels.volume times this)."""
    density = np.zeros((4, 4, 4), np.float32)
    linear = np.eye(3)
    out = np.ones((1, 1, 1), np.float32)
    order = np.arange(3, dtype=np.int64)
    sweep_transmittance(density, 1.0, True, np.zeros(3), linear, True, True, order, 0.0, out)
    sweep_transmittance(density, 1.0, False, np.array([-1.0, 0.0, 0.0]), linear, False, False, order, 0.0, out)
    trilinear(density, np.float64(0.0), np.float64(0.0), np.float64(0.0))  # a lamp's own density (core.volume.direct)
    active = np.zeros((1, 3), np.int32)
    directions = np.array([[1.0, 0.0, 0.0]])
    codes = np.zeros((1, 1, 1), np.uint16)
    escape = np.zeros((1, 1), np.uint16)
    for blocked in (np.zeros((0, 0), np.float32), np.full((1, 1), np.inf, np.float32)):
        scatter_table(density, active, directions, np.ones(1), 1.0, 1.0, 1, np.int64(-1), 1.0, BLOCK, blocked,
                      np.int64(0), np.int64(0), codes, escape)
    march_transmittance(density, np.zeros((1, 3)), directions, np.full(1, np.inf), np.ones(1), 1.0, 0.5,
                        np.zeros(1))
    gather_volume(np.zeros((4, 4, 4, 3), np.float32), active, directions, codes, escape, 1.0, BLOCK,
                  np.zeros((1, 3)))
    world_light(np.zeros((1, 3)), np.zeros((1, 1), np.float32), np.zeros((1, 3)))
