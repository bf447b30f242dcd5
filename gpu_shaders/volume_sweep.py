"""The volume slice sweep on the GPU: the twin of
:func:`core.kernels.volume_kernels.sweep_transmittance`, same signature and contract.

:func:`core.volume.direct.transmittance` calls it as its ``sweep_pass``, once for a sun and
up to six times for a lamp at a position; each call writes the transmittance of the
voxels it selects into ``out`` and leaves the others as they were.

How it runs. The sweep is sequential along its axis (each slice reads the one before), so
``volume_sweep.glsl`` does one slice per dispatch, and the dispatch boundary is the global
synchronisation (Blender's ``gpu.compute.dispatch`` puts a texture-fetch and image barrier
after each). Within a slice every voxel is independent.

Layout, and why:

- The padded density goes up once per call as a 2D array texture, one layer per slice
  along the sweep axis: the shader reads a slice with ``texelFetch`` and the existing
  upload helper (:func:`runtime.float_texture`) already checks its limits.
- The carried values (transmittance for a sun, mean extinction for a lamp) of the previous
  and the current slice ping-pong between two C x B R32F textures that never leave the GPU.
  Only the interior is stored: the kernel's border, never written, holds the outside value,
  which the shader returns for indices beyond the interior.
- The results go into a 2D R32F atlas of slices (each slice a C x B tile), read back with
  one ``read()`` when it is full and at the end. ``read()`` returns layer 0 only of a 3D or
  array texture; an atlas needs no copy pass and one read per atlas instead of one per
  slice, and capping its side at ATLAS_SIDE keeps the GPU memory at the density plus
  64 MiB whatever the grid (a 256^3 grid is one atlas).
- Voxels outside the selection write UNSELECTED, and only the others are copied into
  ``out`` (through a view in the sweep's frame, so no merge across the six sweeps is needed).

The selection and the near-lamp branch are decided on the CPU, in float64, by the kernel's
own expressions: the tests ``|sb| <= 1`` and ``-sa >= |sb|`` sit exactly on their bound for
voxels on a pyramid's diagonal when the lamp is at a voxel centre or on a grid plane, and
float32 would tip some of them into the neighbouring pyramid, whose sweep gives a different
value there. Both tests are monotone in the row (and in the column) and separable, so each
slice's selection is a box of rows and columns, sent as a push constant.

Every dispatch covers the whole slice. The kernel computes a lamp's sweep only over the
pyramid's cross-section and a two-voxel margin; the voxels it selects come out the same
(bit for bit, between that kernel and its earlier whole-slice version, on 48 lamp
positions), and here whole slices keep the shader free of window bounds and of stale
texels: every texel of both ping-pong images and of the atlas tile is written before it
is read. The window would save about two thirds of a lamp's invocations; that is left
until it can be timed on a real GPU (on llvmpipe, where the dispatches take three quarters
of this pass's time, the device choice picks the CPU kernel anyway).

Precision: the GPU carries everything in float32 (the lamp's position and the frame's
linear map are rounded to float32 too), the kernel in float64 with float32 densities and
output. Each slice adds a few float32 roundings to the carried value (the segment, exp,
the bilinear read, the product or the mean extinction) and the bilinear read does not
amplify them (its weights sum to one), so the difference grows at most linearly with the
slices swept: about 1e-7 per slice relative to the transmittance, a few 1e-6 for tens of
slices and below 1e-4 for a few hundred. GLSL's exp may be less exact on real GPUs than on
llvmpipe (a few ulp); the decisions (which voxels, which branch) are the kernel's exactly.
"""
from __future__ import annotations

import numpy as np

from ..core.errors import DeviceError
from . import runtime

GROUP_SIZE = 16  # local work group: 16 x 16 voxels of a slice
# What the shader writes for a voxel this sweep does not select (volume_sweep.glsl's
# UNSELECTED): never a transmittance, which lies in [0, 1].
UNSELECTED = -1.0
# Largest side of the result atlas: 4096^2 R32F is 64 MiB, and holds all 256 slices of 256^2.
ATLAS_SIDE = 4096


def _build(info) -> None:
    info.image(0, "R32F", "FLOAT_2D", "next_carried", qualifiers={"WRITE"})
    info.image(1, "R32F", "FLOAT_2D", "transmittance_atlas", qualifiers={"WRITE"})
    info.sampler(0, "FLOAT_2D_ARRAY", "density")
    info.sampler(1, "FLOAT_2D", "previous_carried")
    # In this order they take 112 bytes as Vulkan lays them out (std430), and 128 as Blender
    # estimates it (it warns beyond 128 bytes, the push constants every device has).
    info.push_constant("IVEC4", "select_box")
    for name in ("light", "linear_row_x", "linear_row_y", "linear_row_z"):
        info.push_constant("VEC3", name)
    for name in ("extinction", "lamp_density"):
        info.push_constant("FLOAT", name)
    for name in ("slice_index", "first_slice", "flip", "is_point", "lamp_within_slice"):
        info.push_constant("INT", name)
    info.push_constant("IVEC2", "tile_origin")
    info.local_group_size(GROUP_SIZE, GROUP_SIZE)


def _first_slice(is_point: bool, light: np.ndarray) -> int:
    """The first slice the kernel sweeps: a lamp's sweep starts at the slice past it."""
    return max(0, int(np.floor(light[0])) + 1) if is_point else 0


def _selection_boxes(is_point: bool, light: np.ndarray, select: bool, slices: np.ndarray, near: np.ndarray,
                     count_b: int, count_c: int) -> np.ndarray:
    """(S, 4) int64 per swept slice: the first and last row, the first and last column it
    writes (inclusive; first > last when none), by the kernel's float64 tests.

    slices : (S,) the swept slices; near : (S,) bool the lamp lies within one slice of them
    """
    if not select:
        return np.tile(np.array([0, count_b - 1, 0, count_c - 1], np.int64), (len(slices), 1))
    along = slices.astype(np.float64)

    def allowed(coordinate: float, count: int) -> np.ndarray:
        """(S, count) bool: the kernel's pyramid test along one in-slice axis."""
        offsets = coordinate - np.arange(count, dtype=np.float64)  # the kernel's sb = light[1] - b
        if not is_point:
            return np.broadcast_to(np.abs(coordinate) <= 1.0, (len(slices), count))
        with np.errstate(divide="ignore", invalid="ignore"):
            per_slice = 1.0 / (along - light[0])  # the kernel's step (unused on near slices)
            far = np.abs(offsets[None, :] * per_slice[:, None]) <= 1.0
        close = -(light[0] - along)[:, None] >= np.abs(offsets)[None, :]
        return np.where(near[:, None], close, far)

    boxes = np.empty((len(slices), 4), np.int64)
    for in_slice_axis, (coordinate, count) in enumerate(((light[1], count_b), (light[2], count_c))):
        mask = allowed(coordinate, count)
        # Both tests are monotone in the index on each side of the lamp, so the allowed
        # indices of a slice are one run: its first and last are the box's sides.
        any_allowed = mask.any(axis=1)
        boxes[:, 2 * in_slice_axis] = np.where(any_allowed, mask.argmax(axis=1), 0)
        boxes[:, 2 * in_slice_axis + 1] = np.where(any_allowed, count - 1 - mask[:, ::-1].argmax(axis=1), -1)
    return boxes


def _atlas_layout(slices: int, count_b: int, count_c: int) -> tuple[int, int]:
    """(columns, rows) of C x B tiles in one atlas of at most ATLAS_SIDE a side."""
    columns = max(1, min(slices, ATLAS_SIDE // count_c))
    rows = max(1, min(-(-slices // columns), ATLAS_SIDE // count_b))
    if columns * count_c > runtime.MAX_TEXTURE_SIZE or rows * count_b > runtime.MAX_TEXTURE_SIZE:
        raise DeviceError(f"a {count_c}x{count_b} slice exceeds the GPU texture limit; use the CPU device")
    return columns, rows


def sweep_transmittance(density, extinction, is_point, light, linear, select, flip, order, lamp_density, out):
    """Transmittance from every voxel to a lamp by front-to-back slices, on the GPU.

    Arguments and result as :func:`core.kernels.volume_kernels.sweep_transmittance`:

    density : (A + 3, B + 3, C + 3) float32 padded density, permuted (not flipped)
    extinction : sigma_t per unit density per world unit
    is_point : True for a lamp at a position, False for a sun
    light : (3,) a point lamp's position in the frame's index space, or a sun's direction
        towards it scaled so that its first component is -1
    linear : (3, 3) the frame's index-to-world linear map
    select : write only the voxels of the lamp's pyramid along this axis; False: every voxel
    flip : the sweep axis is read backwards; order : (3,) the grid axes in frame order
    lamp_density : the density at a point lamp (0 for a sun)
    out : (nx, ny, nz) float32 in the grid's own layout, written where selected, other
        voxels left as they are
    """
    density = np.ascontiguousarray(density, np.float32)
    light = np.asarray(light, np.float64)
    linear = np.asarray(linear, np.float64)
    order = [int(axis) for axis in order]
    count_a, count_b, count_c = (int(n) - 3 for n in density.shape)
    first = _first_slice(bool(is_point), light)
    slices = np.arange(first, count_a)
    if not len(slices) or count_b < 1 or count_c < 1:
        return
    # The kernel's branch for a lamp within one slice, decided in float64 as it decides it.
    near = (slices - light[0] <= 1.0) if is_point else np.zeros(len(slices), bool)
    boxes = _selection_boxes(bool(is_point), light, bool(select), slices, near, count_b, count_c)
    columns, rows = _atlas_layout(len(slices), count_b, count_c)
    per_atlas = columns * rows

    # ``out`` seen in the sweep's frame: frame voxel (a, b, c) is out[...] at grid index
    # (order[0]: a, or A - 1 - a when flipped; order[1]: b; order[2]: c), as _grid_index.
    in_frame = out.transpose(order)
    if flip:
        in_frame = in_frame[::-1]

    runtime.ensure_context()
    import gpu

    with runtime.TextureSet() as resident:
        density_texture = resident.upload(density[..., None], layers=True)
        carried = [resident.empty(count_c, count_b, fmt="R32F") for _ in range(2)]
        atlas = resident.empty(columns * count_c, rows * count_b, fmt="R32F")
        program = runtime.shader("volume_sweep", _build)
        groups = (-(-count_c // GROUP_SIZE), -(-count_b // GROUP_SIZE), 1)

        def copy_out(start: int, stop: int) -> None:
            """Slices ``slices[start:stop]``, in the atlas from tile 0, into ``out`` where selected."""
            tiles = runtime.read_texture(atlas).reshape(rows, count_b, columns, count_c)
            tiles = tiles.transpose(0, 2, 1, 3).reshape(per_atlas, count_b, count_c)[:stop - start]
            target = in_frame[slices[start]:slices[start] + stop - start]
            np.copyto(target, tiles, where=tiles != UNSELECTED)

        start = 0
        for index, slice_index in enumerate(slices):
            tile = index - start
            program.bind()
            program.uniform_sampler("density", density_texture)
            # Ping-pong: the previous slice's image is read, the other one written.
            program.uniform_sampler("previous_carried", carried[index % 2])
            program.image("next_carried", carried[(index + 1) % 2])
            program.image("transmittance_atlas", atlas)
            for name, value in (("slice_index", int(slice_index)), ("first_slice", first), ("flip", int(bool(flip))),
                                ("is_point", int(bool(is_point))), ("lamp_within_slice", int(near[index]))):
                program.uniform_int(name, value)
            program.uniform_int("select_box", [int(v) for v in boxes[index]])
            program.uniform_int("tile_origin", [(tile % columns) * count_c, (tile // columns) * count_b])
            program.uniform_float("light", [float(v) for v in light])
            for row, name in enumerate(("linear_row_x", "linear_row_y", "linear_row_z")):
                program.uniform_float(name, [float(v) for v in linear[row]])
            program.uniform_float("extinction", float(extinction))
            program.uniform_float("lamp_density", float(lamp_density))
            gpu.compute.dispatch(program, *groups)
            if tile + 1 == per_atlas or index + 1 == len(slices):
                copy_out(start, index + 1)
                start = index + 1
