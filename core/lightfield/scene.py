"""What a light field's view shows, and Cycles' pixel filter, shared by its two renderers.

A baked scene is drawn as triangles carrying the bake's result: each object's lighting image
looked up through its UV map (atlas mode) and per-corner radiance (vertex-mode lighting, the
emission the lighting pass leaves out). The renderers, gpu_shaders.lightfield.ViewRenderer
(rasterised) and core.lightfield.raycast.RaycastRenderer (embree, its CPU twin), agree on:

- A camera ray shows the nearest surface between the clip planes (both faces of every
  triangle): the image's bilinear sample at the interpolated UV (:func:`sample_bilinear_clamp`)
  plus the interpolated per-corner radiance; where it hits nothing, the world in the ray's
  direction (:func:`world_lookup`: bilinear, Cycles' Environment Texture).
- Each pixel is Cycles' pixel filter applied to s x s supersamples per pixel, stratified at the
  sub-pixel centres; the filter reaches beyond the pixel, so the supersample grid extends past
  the image by :func:`filter_margin` supersamples on every side (the rays there continue the
  frustum, as Cycles' filtered rays do), and :func:`resolve` weights them.

The filter, from Cycles' source (``intern/cycles/scene/film.cpp``, ``filter_func_blackman_harris``
and ``filter_table``; ``intern/cycles/util/math_cdf.cpp``, ``util_cdf_invert``;
``intern/cycles/kernel/camera/camera.h``, ``camera_sample``): the Blackman-Harris window

    f(v, W) = 0.35875 - 0.48829 cos(x) + 0.14128 cos(2x) - 0.01168 cos(3x),  x = 2 pi (v / W + 1/2)

is tabulated with ``W = 2 * filter_width`` (``filter_table`` doubles the width for this filter)
over ``v`` in [0, W / 2] and mirrored, and each camera ray's raster position is the pixel's
corner plus ``0.5 +- v`` drawn independently in x and y with density ``f``. So the filter is
separable, f(dx) f(dy), and spans +-filter_width pixels from the pixel's centre: Blender's
default 1.5 px reaches 1.5 px to each side (not 0.75 px): to the far edge of each
neighbouring pixel. f is 1 at the centre and 6e-5 at the support's edge. Supersampling
turns Cycles' importance-sampled filter into a quadrature: pixel = sum of f-weighted
supersamples / sum of the weights (:func:`pixel_filter_weights`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..lights.environment import direction_to_equirectangular
from ..outputs.images import bilinear_wrap
from .cameras import positive_number, whole_count

# The Blackman-Harris coefficients of Cycles' filter_func_blackman_harris.
_BH = (0.35875, -0.48829, 0.14128, -0.01168)


def _float_array(name: str, values, columns: int | None, allow_none: bool = False) -> np.ndarray | None:
    if values is None:
        if allow_none:
            return None
        raise ValueError(f"{name} is required")
    array = np.ascontiguousarray(values, dtype=np.float32)
    if columns is not None and (array.ndim != 2 or array.shape[1] != columns):
        raise ValueError(f"{name} must have shape (n, {columns}), got {np.shape(values)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return array


def _image_array(name: str, values) -> np.ndarray:
    array = np.ascontiguousarray(values, dtype=np.float32)
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1 or array.shape[1] < 1:
        raise ValueError(f"{name} must have shape (h, w, 3), got {np.shape(values)}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return array


@dataclass
class DrawMesh:
    """The triangles of one object as the bake left it.

    positions : (n, 3) float32 world positions, metres; n = 3 * triangles, corners unshared, in
        any winding (no face is culled).
    radiance : (n, 3) float32 linear radiance per corner, added to the image's (vertex-mode
        lighting, emission); zeros where there is none.
    uv : (n, 2) float32 UVs of the lighting image (atlas mode), or None.
    image : (h, w, 3) float32 linear radiance, row 0 at the bottom (Blender's pixel order),
        sampled bilinearly with clamp-to-edge (:func:`sample_bilinear_clamp`), or None.

    The arrays are converted to contiguous float32 (a copy only where they are not already);
    ValueError for wrong shapes, non-finite values, or an image without UVs.
    """
    positions: np.ndarray
    radiance: np.ndarray
    uv: np.ndarray | None = None
    image: np.ndarray | None = None

    def __post_init__(self):
        self.positions = _float_array("positions", self.positions, 3)
        if len(self.positions) % 3:
            raise ValueError(f"positions must hold 3 corners per triangle, got {len(self.positions)} rows")
        self.radiance = _float_array("radiance", self.radiance, 3)
        if len(self.radiance) != len(self.positions):
            raise ValueError(f"radiance has {len(self.radiance)} rows for {len(self.positions)} corners")
        self.uv = _float_array("uv", self.uv, 2, allow_none=True)
        if self.uv is not None and len(self.uv) != len(self.positions):
            raise ValueError(f"uv has {len(self.uv)} rows for {len(self.positions)} corners")
        if self.image is not None:
            if self.uv is None:
                raise ValueError("an image needs uv")
            self.image = _image_array("image", self.image)

    @property
    def triangle_count(self) -> int:
        return len(self.positions) // 3

    @property
    def textured(self) -> bool:
        return self.image is not None


@dataclass
class DrawScene:
    """The meshes and the world.

    world : (H, W, 3) float32 linear equirectangular radiance in core.lights.environment's layout
        (row 0 at the bottom, the nadir), looked up with :func:`world_lookup`; (1, 1, 3) for a
        uniform world.
    """
    meshes: list
    world: np.ndarray

    def __post_init__(self):
        self.meshes = list(self.meshes)
        for mesh in self.meshes:
            if not isinstance(mesh, DrawMesh):
                raise TypeError(f"meshes must be DrawMesh, got {type(mesh).__name__}")
        self.world = _image_array("world", self.world)

    @property
    def uniform_world(self) -> np.ndarray | None:
        """(3,) float32 radiance of a world that is the same in every direction, else None."""
        flat = self.world.reshape(-1, 3)
        if np.all(flat == flat[0]):
            return flat[0].copy()
        return None


def sample_bilinear_clamp(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with clamp-to-edge, as Cycles' Linear interpolation with Extend.

    image : (h, w, C) float, row 0 at v = 0; uv : (n, 2) float texture coordinates.
    Texel (i, j)'s centre is at uv ((i + 0.5) / w, (j + 0.5) / h); outside the centres of the
    border texels the border is held. Returns (n, C) float32.
    """
    height, width = image.shape[:2]
    uv = np.asarray(uv, np.float32)
    x = uv[:, 0] * np.float32(width) - np.float32(0.5)
    y = uv[:, 1] * np.float32(height) - np.float32(0.5)
    x0 = np.floor(x)
    y0 = np.floor(y)
    tx = (x - x0)[:, None]
    ty = (y - y0)[:, None]
    # Clip the float before the cast: a huge UV must not overflow the integer.
    x0 = np.clip(x0, -1, width).astype(np.int64)
    y0 = np.clip(y0, -1, height).astype(np.int64)
    xa, xb = np.clip(x0, 0, width - 1), np.clip(x0 + 1, 0, width - 1)
    ya, yb = np.clip(y0, 0, height - 1), np.clip(y0 + 1, 0, height - 1)
    bottom = image[ya, xa] * (1.0 - tx) + image[ya, xb] * tx
    top = image[yb, xa] * (1.0 - tx) + image[yb, xb] * tx
    return (bottom * (1.0 - ty) + top * ty).astype(np.float32)


def world_lookup(world: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The world's radiance along ``directions`` (n, 3) (any length): (n, 3) float32.

    Cycles' Environment Texture with Linear interpolation: bilinear at
    ``core.lights.environment.direction_to_equirectangular``'s (u, v), periodic in both axes
    (core.outputs.images.bilinear_wrap).
    """
    if world.shape[0] == 1 and world.shape[1] == 1:
        return np.broadcast_to(world[0, 0].astype(np.float32), (len(directions), 3)).copy()
    u, v = direction_to_equirectangular(directions)
    return bilinear_wrap(world, u, v).astype(np.float32)


def blackman_harris(offset_px, filter_width: float) -> np.ndarray:
    """Cycles' pixel filter at ``offset_px`` pixels from a pixel's centre (any shape, float64).

    ``filter_func_blackman_harris(v, 2 * filter_width)``: 1 at 0, zero beyond +-filter_width.
    """
    v = np.asarray(offset_px, np.float64)
    x = 2.0 * np.pi * (v / (2.0 * filter_width) + 0.5)
    value = _BH[0] + _BH[1] * np.cos(x) + _BH[2] * np.cos(2.0 * x) + _BH[3] * np.cos(3.0 * x)
    return np.where(np.abs(v) <= filter_width, value, 0.0)


def _check_filter(supersampling, filter_width) -> tuple[int, float]:
    return whole_count("supersampling", supersampling), positive_number("filter_width", filter_width)


def filter_margin(supersampling: int, filter_width: float) -> int:
    """r: supersamples the filter reaches past a pixel's own s on each side (>= 0).

    The taps are the supersamples strictly within +-filter_width pixels of the pixel's centre;
    supersample t of a pixel (t = 0..s-1 inside it) is ``(t + 0.5) / s - 0.5`` pixels from it.
    """
    s, width = _check_filter(supersampling, filter_width)
    # The farthest tap -r satisfies (r - 0.5) / s + 0.5 < width.
    return max(0, math.ceil(s * (width - 0.5) + 0.5) - 1)


def pixel_filter_offsets(supersampling: int, filter_width: float) -> np.ndarray:
    """(k,) float64 offsets, in pixels, of a pixel's taps from its centre; k = s + 2 r."""
    s, _ = _check_filter(supersampling, filter_width)
    r = filter_margin(s, filter_width)
    t = np.arange(-r, s + r)
    return (t + 0.5) / s - 0.5


def pixel_filter_weights(supersampling: int, filter_width: float) -> np.ndarray:
    """(k,) float32 separable weights of a pixel's taps (:func:`pixel_filter_offsets`).

    The 2D weight of tap (ty, tx) is ``w[ty] * w[tx]``; ``w`` is symmetric and sums to 1 (so the
    2D weights do too). A filter narrower than half a supersample (no tap within its support)
    falls back to the mean of the pixel's own central supersample(s).
    """
    s, width = _check_filter(supersampling, filter_width)
    offsets = pixel_filter_offsets(s, width)
    weights = blackman_harris(offsets, width)
    if not np.any(weights > 0.0):
        nearest = np.abs(offsets) <= np.abs(offsets).min() + 1e-12
        weights = nearest.astype(np.float64)
    # Normalise in float64; symmetrise against rounding so that w[i] == w[-1 - i] exactly.
    weights = weights / weights.sum()
    weights = 0.5 * (weights + weights[::-1])
    return weights.astype(np.float32)


def extended_size(width: int, height: int, supersampling: int, filter_width: float) -> tuple[int, int, int]:
    """(columns, rows, r) of the supersample grid: s per pixel plus the margin r on every side."""
    r = filter_margin(supersampling, filter_width)
    return width * supersampling + 2 * r, height * supersampling + 2 * r, r


def supersample_ndc(width: int, height: int, supersampling: int, filter_width: float) -> tuple[np.ndarray, np.ndarray]:
    """NDC of the extended supersample grid's centres, row 0 at the top of the image.

    Returns (x (columns,), y (rows,)) float64: supersample column i is at pixel
    ``x_px = (i - r + 0.5) / s`` (0 at the image's left edge), NDC ``2 x_px / width - 1``; row j
    at ``y_px = (j - r + 0.5) / s`` from the top edge, NDC ``1 - 2 y_px / height``.
    """
    columns, rows, r = extended_size(width, height, supersampling, filter_width)
    x_px = (np.arange(columns) - r + 0.5) / supersampling
    y_px = (np.arange(rows) - r + 0.5) / supersampling
    return 2.0 * x_px / width - 1.0, 1.0 - 2.0 * y_px / height


def resolve(supersamples: np.ndarray, supersampling: int, weights: np.ndarray) -> np.ndarray:
    """The filtered image of an extended supersample grid (the CPU twin of the GPU's resolve).

    supersamples : (height * s + 2 r, width * s + 2 r, C) float32, row 0 at the top
    weights : (k,) float32 from :func:`pixel_filter_weights`, k = s + 2 r
    Returns (height, width, C) float32: pixel (y, x) = sum over ty, tx of
    ``w[ty] w[tx] supersamples[y s + ty, x s + tx]``, summed first along x, then along y, each
    in tap order (as the GPU's two passes do).
    """
    s = int(supersampling)
    k = len(weights)
    rows, columns = supersamples.shape[:2]
    width, height = (columns - k + s) // s, (rows - k + s) // s
    data = np.asarray(supersamples, np.float32)
    weights = np.asarray(weights, np.float32)
    across = np.zeros((rows, width) + data.shape[2:], np.float32)
    for t in range(k):
        across += weights[t] * data[:, t:t + (width - 1) * s + 1:s]
    out = np.zeros((height, width) + data.shape[2:], np.float32)
    for t in range(k):
        out += weights[t] * across[t:t + (height - 1) * s + 1:s]
    return out


def camera_position(view_matrix: np.ndarray) -> np.ndarray:
    """(3,) float64 world position of the camera of a (4, 4) world-to-camera matrix."""
    return np.linalg.inv(np.asarray(view_matrix, np.float64))[:3, 3]


def direction_matrix(view_matrix: np.ndarray, projection_matrix: np.ndarray) -> np.ndarray:
    """(3, 3) float64 M: the world direction of the ray through NDC (x, y) is along M @ (x, y, 1).

    It is the unprojection through ``inverse(projection @ view)`` of the far-plane point
    (x, y, 1, 1), less the camera's position, folded into one linear map: with
    q = inverse @ (x, y, 1, 1), ``q.xyz - eye * q.w`` is ``q.w`` times the direction, linear in
    (x, y, 1). The sign is set so that M points away from the camera, into the frustum.
    """
    inverse = np.linalg.inv(np.asarray(projection_matrix, np.float64) @ np.asarray(view_matrix, np.float64))
    # Columns for x, y, and the constant (NDC z = 1 and w = 1 folded together).
    folded = np.stack([inverse[:, 0], inverse[:, 1], inverse[:, 2] + inverse[:, 3]], axis=1)
    eye = camera_position(view_matrix)
    matrix = folded[:3] - eye[:, None] * folded[3][None, :]
    # q.w has one sign over the far plane; a negative one flips every direction.
    if folded[3, 2] < 0.0:
        matrix = -matrix
    return matrix


def check_view(view_matrix, projection_matrix, clip_start: float, clip_end: float) -> tuple[np.ndarray, np.ndarray]:
    """The view's (4, 4) float64 matrices, checked (ValueError for a bad shape, a non-finite
    value or clip planes out of order)."""
    view = np.asarray(view_matrix, np.float64)
    projection = np.asarray(projection_matrix, np.float64)
    for name, matrix in (("view_matrix", view), ("projection_matrix", projection)):
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"{name} must be a finite (4, 4) matrix, got shape {matrix.shape}")
    near, far = float(clip_start), float(clip_end)
    if not (math.isfinite(near) and math.isfinite(far) and 0.0 < near < far):
        raise ValueError(f"clip planes must satisfy 0 < clip_start < clip_end, got {clip_start!r}, {clip_end!r}")
    return view, projection


def check_size(width, height) -> tuple[int, int]:
    """(width, height) as ints >= 1 (ValueError otherwise)."""
    sizes = []
    for name, value in (("width", width), ("height", height)):
        try:
            whole = int(value)
            valid = not isinstance(value, (bool, str)) and whole == value and whole >= 1
        except (TypeError, ValueError, OverflowError):
            valid = False
        if not valid:
            raise ValueError(f"{name} must be a whole number of pixels >= 1, got {value!r}")
        sizes.append(whole)
    return sizes[0], sizes[1]


def scene_centre(scene: DrawScene) -> np.ndarray:
    """(3,) float64 middle of the bounding box of every mesh's positions (zeros if none): the
    renderers trace and draw relative to it, so a scene far from the origin keeps its precision."""
    lows = [mesh.positions.min(axis=0) for mesh in scene.meshes if len(mesh.positions)]
    if not lows:
        return np.zeros(3)
    highs = [mesh.positions.max(axis=0) for mesh in scene.meshes if len(mesh.positions)]
    return 0.5 * (np.min(lows, axis=0).astype(np.float64) + np.max(highs, axis=0).astype(np.float64))
