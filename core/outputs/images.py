"""Output images: assembling pass images from samples, EXR files, tone mapping.

Images in the core are stored as Blender stores pixels: (H, W, C) float32 with row 0
at the bottom (v = 0). EXR files are written top row first, as Blender saves them.
"""
from __future__ import annotations

import errno
import os

import numpy as np

from ..errors import OutputRefused
from .dilation import dilate


def bilinear_wrap(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cycles' linear image lookup with periodic wrapping in both axes (EXTENSION_REPEAT).

    Parameters
    ----------
    image : (h, w, C) float, row 0 at v = 0
    u, v : (n,) float texture coordinates

    Returns
    -------
    values : (n, C) float64
    """
    height, width = image.shape[:2]
    x = np.asarray(u, np.float64) * width - 0.5
    y = np.asarray(v, np.float64) * height - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    tx = (x - x0)[:, None]
    ty = (y - y0)[:, None]
    x0 = x0.astype(np.int64) % width
    y0 = y0.astype(np.int64) % height
    x1 = (x0 + 1) % width
    y1 = (y0 + 1) % height
    image = np.asarray(image, np.float64)
    bottom = image[y0, x0] * (1.0 - tx) + image[y0, x1] * tx
    top = image[y1, x0] * (1.0 - tx) + image[y1, x1] * tx
    return bottom * (1.0 - ty) + top * ty


def sample_image(values: np.ndarray, pixel: np.ndarray, coverage: np.ndarray, margin: int,
                 dilate_function=dilate) -> np.ndarray:
    """Scatter per-sample RGB values into an RGBA image and dilate into the gutter.

    Parameters
    ----------
    values : (k, 3) float per-sample values
    pixel : (k,) int64 flat pixel index
    coverage : (H, W) bool
    margin : gutter width in texels
    dilate_function : :func:`core.outputs.dilation.dilate` or a twin with its contract

    Returns
    -------
    image : (H, W, 4) float32, alpha 1 on covered texels and 0 elsewhere; finite
    """
    height, width = coverage.shape
    rgb = np.zeros((height * width, 3), np.float32)
    rgb[pixel] = np.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)
    rgb = rgb.reshape(height, width, 3)
    if margin > 0:
        rgb, _ = dilate_function(rgb, coverage, margin)
    image = np.empty((height, width, 4), np.float32)
    image[..., :3] = rgb
    image[..., 3] = coverage
    return image


def write_exr(path: str, image: np.ndarray) -> None:
    """Write an (H, W, 4) bottom-up float image as a 32-bit float RGBA EXR (top row first)."""
    import OpenEXR

    if not np.all(np.isfinite(image)):
        raise OutputRefused(f"refusing to write non-finite values to {path}")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    top_down = np.ascontiguousarray(image[::-1], dtype=np.float32)
    with OpenEXR.File(header, {"RGBA": top_down}) as exr:
        try:
            exr.write(path)
        except RuntimeError as error:
            # OpenEXR says a file cannot be written (a full disk, a folder in its place) with a
            # RuntimeError; it is a file system's error, and callers tell those from bugs by OSError.
            raise OSError(errno.EIO, str(error).strip(), path) from error


def tonemap(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear radiance to display sRGB in [0, 1] (Reinhard on luminance, then the sRGB curve).

    Parameters
    ----------
    image : (H, W, 3 or 4) float; alpha, if present, is kept

    Returns
    -------
    display : same shape, float32
    """
    rgb = np.clip(np.nan_to_num(image[..., :3] * exposure), 0.0, None)
    luminance = rgb @ np.array([0.2126, 0.7152, 0.0722])
    scale = np.divide(1.0, 1.0 + luminance, out=np.ones_like(luminance), where=np.isfinite(luminance))
    mapped = np.clip(rgb * scale[..., None], 0.0, 1.0)
    encoded = np.where(mapped <= 0.0031308, 12.92 * mapped, 1.055 * np.power(mapped, 1 / 2.4) - 0.055)
    out = np.array(image, dtype=np.float32, copy=True)
    out[..., :3] = encoded
    return out


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve inverted, for 8-bit colour textures read as stored."""
    values = np.asarray(values, np.float32)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4).astype(np.float32)
