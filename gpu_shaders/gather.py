"""The gather on the GPU: the twin of :func:`core.transport.gather.gather`, same contract.

The table is streamed in batches of directions as 2D texture arrays (one layer per
direction), sized so the batch plus the fixed textures stay within the GPU memory
budget; every texture is freed when the call returns, also on an error.

Vertex-mode objects (``layout.is_vertex``) are looked up as
:meth:`core.transport.gather.AtlasLayout.vertex_lookup` does: the batch also carries the hit
triangles, and the layout's corner table and per-object corner bases are uploaded once.
"""
from __future__ import annotations

import numpy as np

from ..core.errors import DeviceError
from ..core.transport.gather import vertex_cells_of
from ..core.visibility.table import decode_uv
from . import runtime

# Channel layers (4 channels each) one dispatch accumulates: 12 x 4 = 48 channels,
# 16 light groups (core.transport.groups.MAX_GROUPS_PER_GATHER); the shader's sums[] size.
MAX_CHANNEL_LAYERS = 12
GROUP_SIZE = 16  # local work group: 16 x 16 samples
RADIANCE_WIDTH = 4096
# GPU memory the gather may use: the fixed textures plus one batch of the table.
# 1 GiB fits every discrete card of the last decade and leaves room for Blender.
DEFAULT_BUDGET_BYTES = 1 << 30
TABLE_BYTES_PER_ENTRY = 4 + 8  # hit object (R32F) and hit uv (RG32F)
VERTEX_BYTES_PER_ENTRY = 4  # hit triangle (R32F), when the layout has vertex-mode objects
# Integers travel as exact floats: below 2^24 whole (a triangle within its object: vertex mode
# takes at most core.visibility.table.MAX_VERTEX_TRIANGLES = 2^24), larger ones (offsets, flat
# indices, corner rows) split into index // SPLIT and index % SPLIT.
SPLIT = 4096  # the shader's split_index
CORNER_WIDTH = 4096  # texels per row of the corner texture (two texels per triangle)


def _build_gather(info) -> None:
    info.image(0, "RGBA32F", "FLOAT_2D_ARRAY", "accumulated", qualifiers={"READ", "WRITE"})
    info.sampler(0, "FLOAT_2D_ARRAY", "hit_object")
    info.sampler(1, "FLOAT_2D_ARRAY", "hit_uv")
    info.sampler(2, "FLOAT_2D", "normals")
    info.sampler(3, "FLOAT_2D_ARRAY", "radiance")
    info.sampler(4, "FLOAT_2D", "objects")
    info.sampler(5, "FLOAT_2D", "directions")
    info.sampler(6, "FLOAT_2D_ARRAY", "excluded")
    info.sampler(7, "FLOAT_2D_ARRAY", "hit_triangle")
    info.sampler(8, "FLOAT_2D", "corners")
    for name in ("sample_width", "sample_count", "batch_start", "batch_count", "channel_layers",
                 "radiance_width", "use_exclude", "has_world", "has_vertex", "nearest_vertex", "corner_width"):
        info.push_constant("INT", name)
    info.local_group_size(GROUP_SIZE, GROUP_SIZE)


def _exclusion_masks(exclude: np.ndarray) -> np.ndarray:
    """(K, O) bool as (K, layers, 4) float32: 16 objects per channel, exact integer bit masks."""
    samples, objects = exclude.shape
    layers = -(-objects // 64)
    padded = np.zeros((samples, layers * 64), bool)
    padded[:, :objects] = exclude
    bits = padded.reshape(samples, layers * 4, 16).astype(np.uint32) << np.arange(16, dtype=np.uint32)
    return bits.sum(axis=2).astype(np.float32).reshape(samples, layers, 4)


def _split(values) -> tuple[np.ndarray, np.ndarray]:
    values = np.asarray(values, np.int64)
    return values // SPLIT, values % SPLIT


def _has_vertex(layout) -> bool:
    return layout.is_vertex is not None and bool(np.any(layout.is_vertex))


def _corner_texture(layout) -> tuple[np.ndarray, int]:
    """The corner table as an RGBA image, two texels per row; and the image's width."""
    corners = np.asarray(layout.corner_flat, np.int64).reshape(-1, 3)
    texels = np.zeros((len(corners), 2, 4), np.float32)
    high, low = _split(corners)
    texels[:, 0, 0], texels[:, 0, 1] = high[:, 0], low[:, 0]
    texels[:, 0, 2], texels[:, 0, 3] = high[:, 1], low[:, 1]
    texels[:, 1, 0], texels[:, 1, 1] = high[:, 2], low[:, 2]
    texels = texels.reshape(-1, 4)
    width = max(1, min(CORNER_WIDTH, len(texels)))
    height = max(1, -(-len(texels) // width))
    if height > runtime.MAX_TEXTURE_SIZE:
        raise DeviceError(f"{len(corners)} vertex-mode triangles exceed the GPU gather's corner table "
                          f"({CORNER_WIDTH * runtime.MAX_TEXTURE_SIZE // 2} triangles); use the CPU device")
    image = np.zeros((height * width, 4), np.float32)
    image[:len(texels)] = texels
    return image.reshape(height, width, 4), width


def _object_texture(layout) -> np.ndarray:
    """(2, O, 4): row 0 width, height, split offset; row 1 vertex flag, split corner base."""
    objects = np.zeros((2, len(layout.widths), 4), np.float32)
    high, low = _split(layout.offsets)
    objects[0] = np.stack([layout.widths, layout.heights, high, low], axis=1)
    if _has_vertex(layout):
        vertex = np.asarray(layout.is_vertex, bool)
        high, low = _split(np.where(vertex, layout.corner_base, 0))
        objects[1, :, 0] = vertex
        objects[1, :, 1] = high
        objects[1, :, 2] = low
    return objects


def batch_directions(samples: int, budget_bytes: int, fixed_bytes: int, vertex: bool = False) -> int:
    """Directions per batch so the batch and the fixed textures fit ``budget_bytes``.

    ``vertex``: the layout has vertex-mode objects, so each entry also carries its hit triangle.
    """
    per_direction = samples * (TABLE_BYTES_PER_ENTRY + (VERTEX_BYTES_PER_ENTRY if vertex else 0))
    available = budget_bytes - fixed_bytes
    if available < per_direction:
        raise MemoryError(f"the GPU budget of {budget_bytes / 2**20:.0f} MiB cannot hold the fixed textures "
                          f"({fixed_bytes / 2**20:.0f} MiB) and one direction of the table "
                          f"({per_direction / 2**20:.0f} MiB)")
    return int(min(runtime.MAX_LAYERS, available // per_direction))


def gather(geometry, source, progress=None, samples: np.ndarray | None = None, directions: range | None = None,
           budget_bytes: int = DEFAULT_BUDGET_BYTES) -> np.ndarray:
    """E(p) = sum_i w_i(p) L(S_i[p]) on the GPU. Parameters as :func:`core.transport.gather.gather`
    (``geometry`` a GatherGeometry, ``source`` a GatherSource).

    ``geometry.threads`` is unused; ``samples`` only zeroes the others (the GPU computes all).
    Returns (K, C) float64.
    """
    table, normals, scale, layout = geometry.table, geometry.normals, geometry.scale, geometry.layout
    radiance, world, exclude = source.radiance, source.world, source.exclude
    chosen = range(len(table.directions)) if directions is None else directions
    if chosen.step != 1 or chosen.start < 0 or chosen.stop > len(table.directions):
        raise ValueError(f"gather: directions must be a contiguous range within 0..{len(table.directions)}, "
                         f"got {directions!r}")
    radiance = np.asarray(radiance, np.float32)
    count = len(table.directions)
    if _has_vertex(layout):
        vertex_cells_of(table, layout)  # raises where table and layout disagree
    total_samples = len(normals)
    channels = radiance.shape[1]
    result = np.zeros((total_samples, channels))
    if total_samples == 0 or count == 0:
        return result
    for first in range(0, channels, 4 * MAX_CHANNEL_LAYERS):
        part = slice(first, min(channels, first + 4 * MAX_CHANNEL_LAYERS))
        world_part = np.broadcast_to(np.asarray(world, np.float64), (count, channels))[:, part]
        result[:, part] = _gather_channels(table, normals, scale, layout, radiance[:, part], world_part, progress,
                                           exclude, budget_bytes, chosen)
    if samples is not None:
        keep = np.zeros(total_samples, bool)
        keep[samples] = True
        result[~keep] = 0.0
    return result


def _gather_channels(table, normals, scale, layout, radiance, world, progress, exclude, budget_bytes, chosen):
    runtime.ensure_context()
    import gpu

    count = len(table.directions)
    total_samples = len(normals)
    channels = radiance.shape[1]
    layers = -(-channels // 4)
    width, height = runtime.sample_grid(total_samples)
    with runtime.TextureSet() as resident:
        normals_grid = runtime.to_grid(np.concatenate([np.asarray(normals, np.float32),
                                                       np.asarray(scale, np.float32)[:, None]], axis=1),
                                       width, height)
        normals_texture = resident.upload(normals_grid)
        padded = np.zeros((len(radiance), 4 * layers), np.float32)
        padded[:, :channels] = radiance
        radiance_width = min(RADIANCE_WIDTH, len(padded))
        radiance_height = -(-len(padded) // radiance_width)
        flat = np.zeros((radiance_height * radiance_width, 4 * layers), np.float32)
        flat[:len(padded)] = padded
        radiance_layers = flat.reshape(radiance_height, radiance_width, layers, 4).transpose(2, 0, 1, 3)
        radiance_texture = resident.upload(radiance_layers, layers=True)
        objects_texture = resident.upload(_object_texture(layout))
        has_vertex = _has_vertex(layout)
        if has_vertex:
            corner_image, corner_width = _corner_texture(layout)
        else:
            corner_image, corner_width = np.zeros((1, 1, 4), np.float32), 1
        corners_texture = resident.upload(corner_image)
        no_triangles = resident.upload(np.zeros((1, 1, 1, 1), np.float32), layers=True)
        rows = np.zeros((1 + layers, count, 4), np.float32)
        rows[0, :, :3] = table.directions
        world_padded = np.zeros((count, 4 * layers), np.float32)
        world_padded[:, :channels] = world
        rows[1:] = world_padded.reshape(count, layers, 4).transpose(1, 0, 2)
        directions_texture = resident.upload(rows)
        if exclude is not None and np.any(exclude):
            masks = _exclusion_masks(np.asarray(exclude, bool))
            grid = np.zeros((height * width, masks.shape[1], 4), np.float32)
            grid[:total_samples] = masks
            excluded_texture = resident.upload(grid.reshape(height, width, masks.shape[1], 4).transpose(2, 0, 1, 3),
                                       layers=True)
            use_exclude = 1
        else:
            excluded_texture = resident.upload(np.zeros((1, 1, 1, 4), np.float32), layers=True)
            use_exclude = 0
        accumulated = resident.upload(np.zeros((layers, height, width, 4), np.float32), layers=True)
        fixed_bytes = resident.uploaded_bytes
        batch = batch_directions(width * height, budget_bytes, fixed_bytes, vertex=has_vertex)

        program = runtime.shader("gather", _build_gather)
        groups = (-(-width // GROUP_SIZE), -(-height // GROUP_SIZE), 1)
        for start in range(chosen.start, chosen.stop, batch):
            stop = min(chosen.stop, start + batch)
            codes = np.full((stop - start, height * width), -2.0, np.float32)
            # The batch's rows of the table, dense: the shader reads entry (direction, sample)
            # as a texel.
            objects = table.entries.dense("hit_object", start, stop)
            codes[:, :total_samples] = objects
            uvs = np.zeros((stop - start, height * width, 2), np.float32)
            uvs[:, :total_samples] = decode_uv(table.entries.dense("hit_uv_code", start, stop))
            if has_vertex:
                # The shader takes a vertex-mode hit's triangle and barycentrics apart.
                triangles = np.zeros((stop - start, height * width), np.float32)
                rows, columns = np.nonzero((objects >= 0) & layout.is_vertex[np.maximum(objects, 0)])
                triangles[rows, columns], uvs[rows, columns] = table.entry_vertex(
                    table.entries.index(rows + start, columns))
            table.entries.release()
            codes_texture, codes_data = runtime.float_texture(codes.reshape(-1, height, width, 1), True)
            uvs_texture, uvs_data = runtime.float_texture(uvs.reshape(-1, height, width, 2), True)
            if has_vertex:
                triangles_texture, triangles_data = runtime.float_texture(triangles.reshape(-1, height, width, 1),
                                                                          True)
            else:
                triangles_texture, triangles_data = no_triangles, None
            program.bind()
            program.image("accumulated", accumulated)
            program.uniform_sampler("hit_object", codes_texture)
            program.uniform_sampler("hit_uv", uvs_texture)
            program.uniform_sampler("normals", normals_texture)
            program.uniform_sampler("radiance", radiance_texture)
            program.uniform_sampler("objects", objects_texture)
            program.uniform_sampler("directions", directions_texture)
            program.uniform_sampler("excluded", excluded_texture)
            program.uniform_sampler("hit_triangle", triangles_texture)
            program.uniform_sampler("corners", corners_texture)
            for name, value in (("sample_width", width), ("sample_count", total_samples), ("batch_start", start),
                                ("batch_count", stop - start), ("channel_layers", layers),
                                ("radiance_width", radiance_width), ("use_exclude", use_exclude),
                                ("has_world", int(np.any(world != 0))), ("has_vertex", int(has_vertex)),
                                ("nearest_vertex", int(bool(layout.nearest_vertex))),
                                ("corner_width", corner_width)):
                program.uniform_int(name, value)
            gpu.compute.dispatch(program, *groups)
            del codes_texture, uvs_texture, codes_data, uvs_data, triangles_texture, triangles_data
            if progress is not None:
                progress((stop - chosen.start) / max(len(chosen), 1))
        out = np.zeros((total_samples, 4 * layers))
        for layer in range(layers):
            values = runtime.read_layer(resident, accumulated, layer, width, height)
            out[:, 4 * layer:4 * layer + 4] = values.reshape(-1, 4)[:total_samples]
        return out[:, :channels]
