"""Gutter dilation on the GPU: the twin of :func:`core.outputs.dilation.dilate`, same contract.

One compute dispatch per pass, ping-ponging between two pairs of textures (the values
as RGBA32F array layers, 4 channels a layer, and the filled mask as R32F). Channels
are independent, so when all layers do not fit the memory budget they are dilated a
few layers at a time. Every texture is freed when the call returns, also on an error.

Agreement with numpy: the shader adds the filled neighbours in the order numpy's
einsum does (numpy 1.26 on x86-64; the one-channel order comes from its SIMD lanes and
may differ on other builds), forbids the compiler to reorder them (``precise``) and
divides with correct rounding, so on llvmpipe the results are bit-identical (the twin
test compares them exactly). GLSL allows a division of up to 2.5 ulp, so a real GPU
may differ by a few float32 ulp; devices that flush subnormals to zero differ on
subnormal values.
"""
from __future__ import annotations

import numpy as np

from ..core.errors import DeviceError
from ..core.outputs.dilation import check_dilate_arguments
from . import runtime

GROUP_SIZE = 16  # local work group: 16 x 16 texels of one channel layer
# GPU memory one call may use; the same default as the gather's.
DEFAULT_BUDGET_BYTES = 1 << 30
LAYER_BYTES_PER_TEXEL = 2 * 16  # source and target RGBA32F
FIXED_BYTES_PER_TEXEL = 2 * 4 + 16  # source and target mask (R32F), the read-back target


def _build_dilate(info) -> None:
    info.image(0, "RGBA32F", "FLOAT_2D_ARRAY", "target_values", qualifiers={"WRITE"})
    info.image(1, "R32F", "FLOAT_2D", "target_known", qualifiers={"WRITE"})
    info.sampler(0, "FLOAT_2D_ARRAY", "source_values")
    info.sampler(1, "FLOAT_2D", "source_known")
    info.push_constant("INT", "single_channel")
    info.local_group_size(GROUP_SIZE, GROUP_SIZE)


def layers_per_chunk(width: int, height: int, layers: int, budget_bytes: int) -> int:
    """Channel layers dilated at once so their textures and the masks fit ``budget_bytes``."""
    texels = width * height
    available = budget_bytes - texels * FIXED_BYTES_PER_TEXEL
    per_layer = texels * LAYER_BYTES_PER_TEXEL
    if available < per_layer:
        needed = (per_layer + texels * FIXED_BYTES_PER_TEXEL) / 2**20
        raise MemoryError(f"the GPU budget of {budget_bytes / 2**20:.0f} MiB cannot hold one channel layer "
                          f"of a {width}x{height} dilation ({needed:.0f} MiB)")
    return int(min(layers, runtime.MAX_LAYERS, available // per_layer))


def dilate(image: np.ndarray, coverage: np.ndarray, margin: int,
           budget_bytes: int = DEFAULT_BUDGET_BYTES) -> tuple[np.ndarray, np.ndarray]:
    """Fill the gutter on the GPU. Parameters and results as :func:`core.outputs.dilation.dilate`.

    Parameters
    ----------
    image : (H, W, C) or (H, W) float
        Values on covered texels; values elsewhere are ignored.
    coverage : (H, W) bool
    margin : int >= 0
    budget_bytes : GPU memory the textures may take; more channels than fit are
        dilated in several rounds. MemoryError if one layer (4 channels) does not fit.

    Returns
    -------
    image : same shape as the input, float32; covered texels are unchanged
    filled : (H, W) bool, texels filled by dilation (disjoint from ``coverage``)

    Raises ValueError for images wider or taller than the GPU texture limit (16384).
    """
    # The same checks and messages as the numpy twin, so callers can swap them.
    image, coverage, margin = check_dilate_arguments(image, coverage, margin)
    flat_channels = image.ndim == 2
    height, width = coverage.shape
    if width > runtime.MAX_TEXTURE_SIZE or height > runtime.MAX_TEXTURE_SIZE:
        raise DeviceError(f"dilate: a {width}x{height} image exceeds the GPU texture limit of "
                          f"{runtime.MAX_TEXTURE_SIZE} texels a side; use core.outputs.dilation.dilate")
    channels = 1 if flat_channels else image.shape[2]
    values = np.zeros((height, width, channels), np.float32)
    values[coverage] = image.reshape(height, width, channels)[coverage]

    # A texel's distance to the coverage is below the image's longer side, so passes
    # beyond that change nothing (numpy stops there as its frontier runs empty).
    passes = min(margin, max(height, width) - 1) if coverage.any() else 0
    if passes > 0 and channels > 0:
        layers = -(-channels // 4)
        chunk = layers_per_chunk(width, height, layers, budget_bytes)
        padded = np.zeros((height, width, 4 * layers), np.float32)
        padded[..., :channels] = values
        stacked = padded.reshape(height, width, layers, 4).transpose(2, 0, 1, 3)
        known = None
        for first in range(0, layers, chunk):
            part, known = _dilate_layers(stacked[first:first + chunk], coverage, passes, channels == 1)
            padded[..., 4 * first:4 * first + 4 * len(part)] = part.transpose(1, 2, 0, 3).reshape(height, width, -1)
        values = padded[..., :channels]
        filled = known & ~coverage
    else:
        filled = np.zeros((height, width), bool)
    return (values[..., 0] if flat_channels else values), filled


def _dilate_layers(stacked: np.ndarray, coverage: np.ndarray, passes: int,
                   single_channel: bool) -> tuple[np.ndarray, np.ndarray]:
    """``passes`` passes over channel layers.

    stacked : (L, H, W, 4) float32, zero on uncovered texels
    Returns ((L, H, W, 4) float32 values, (H, W) bool covered-or-filled mask).
    """
    runtime.ensure_context()
    import gpu

    layers, height, width, _ = stacked.shape
    with runtime.TextureSet() as resident:
        values = [resident.upload(stacked, layers=True), resident.empty(width, height, layers)]
        masks = [resident.upload(coverage.astype(np.float32)[..., None]), resident.empty(width, height, fmt="R32F")]
        program = runtime.shader("dilate", _build_dilate)
        groups = (-(-width // GROUP_SIZE), -(-height // GROUP_SIZE), layers)
        for step in range(passes):
            source, target = step % 2, (step + 1) % 2
            program.bind()
            program.uniform_sampler("source_values", values[source])
            program.uniform_sampler("source_known", masks[source])
            program.image("target_values", values[target])
            program.image("target_known", masks[target])
            program.uniform_int("single_channel", int(single_channel))
            gpu.compute.dispatch(program, *groups)
        final = passes % 2
        out = np.empty((layers, height, width, 4), np.float32)
        for layer in range(layers):
            out[layer] = runtime.read_layer(resident, values[final], layer, width, height)
        # A one-channel texture reads back as (H, W), without a channel axis.
        known = runtime.read_texture(masks[final]).reshape(height, width) > 0.5
        return out, known
