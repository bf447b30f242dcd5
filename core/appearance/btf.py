"""BTF image folders in the UTIA layout (the Bonn UBO2003 sampling), written and read back.

A bidirectional texture function is one image of a tile per (light, view) direction pair.
VisiBake writes it as the UTIA BTF database lays its data out, which itself follows the Bonn
database (UBO2003) for compatibility:

- ``tv{θv:03d}_pv{φv:03d}/tl{θl:03d}_pl{φl:03d}_tv{θv:03d}_pv{φv:03d}.{png|exr}``: one folder
  per view direction, one image per light direction in it; angles in whole degrees, three digits.
- 81 light × 81 view directions over the hemisphere, in rings of constant θ (from the normal):
  θ = 0, 15, 30, 45, 60, 75° with 1, 6, 12, 18, 20, 24 azimuths. In a ring of ``n`` azimuths
  φ = 0, 360/n, 2·360/n, ... degrees: the steps are 60, 30, 20, 18 and 15°, all whole degrees,
  so the names hold the angles exactly. The database's order is ring by ring, azimuth rising
  (which is also the order of sorting by (θ, φ)). UBO2003's archive names agree with it: they
  number each image ``81·light + view`` in this order (``00008 tl000 pl000 tv030 pv030.jpg``:
  light 0, view 8 = (30°, 30°); ``00162 tl015 pl060 tv000 pv000.jpg``: light 2 = (15°, 60°)).
- PNG images hold 8-bit sRGB; EXR images hold linear values (UTIA's are half-float XYZ;
  VisiBake's are 32-bit float linear Rec.709 RGB with alpha 1, through
  :func:`core.outputs.images.write_exr`).

Directions: z is the surface normal, θ is measured from it, φ from the tile's +x axis (its
u direction) towards +y (v). Images are held as the rest of the core holds them: (H, W, 3)
float, row 0 at the bottom (v = 0); files store the top row first.

Light equal to view. A measuring rig cannot put the lamp where the camera is, so UTIA moves
the light slightly for the 81 pairs whose light and view directions coincide (its direction
list gives the moved angles). A simulation has no such obstacle: by default VisiBake lights
those pairs from exactly the direction the file name states (the retro-reflection hot spot
is part of the appearance, and an interpolating renderer expects the image to match its
name). A writer made with ``light_shift_deg > 0`` emulates a rig instead: :func:`light_for`
moves the light that many degrees towards the horizon (θ + shift, same φ). The rule used is
recorded in ``btf.json``.

Every folder VisiBake writes holds a ``btf.json`` manifest (format ``visibake-btf``): the
sampling, the image size and encoding, the tile's period, the light shift and the list of
files written. The writer replaces only files a previous manifest lists (core.outputs.ownership):
told to overwrite, it writes beside other files, and still refuses one of the same name.
"""
from __future__ import annotations

import json
import os
import re
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import OutputRefused
from ..outputs.images import srgb_to_linear, write_exr
from ..outputs.names import inside_folder
from ..outputs.ownership import StagedWrites, is_leftover, read_record, refuse_foreign, remove_leftovers

RING_THETAS_DEG = (0, 15, 30, 45, 60, 75)
RING_COUNTS = (1, 6, 12, 18, 20, 24)

MANIFEST = "btf.json"
FORMAT_NAME = "visibake-btf"
FORMAT_VERSION = 1
IMAGE_FORMATS = ("exr", "png")
COLOR_SPACES = {"exr": "linear Rec.709 / sRGB primaries", "png": "sRGB"}
NAME_PATTERN = "tv{tv:03d}_pv{pv:03d}/tl{tl:03d}_pl{pl:03d}_tv{tv:03d}_pv{pv:03d}.{ext}"
# Half the ring spacing: a larger shift would put the moved light nearer the next ring than its own.
MAX_LIGHT_SHIFT_DEG = 7.5

_NAME = re.compile(r"^tv(\d{3})_pv(\d{3})/tl(\d{3})_pl(\d{3})_tv(\d{3})_pv(\d{3})\.(exr|png)$")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def ubo_directions() -> tuple[np.ndarray, np.ndarray]:
    """The 81 directions of the UBO2003 / UTIA sampling, in the database's order.

    Returns
    -------
    thetas_deg : (81,) int64, angle from the normal in degrees (0, 15, ..., 75)
    phis_deg : (81,) int64, azimuth in degrees, ``k * 360 // n`` in a ring of ``n``
    """
    thetas, phis = [], []
    for theta, count in zip(RING_THETAS_DEG, RING_COUNTS):
        for k in range(count):
            thetas.append(theta)
            # 360 is a multiple of every ring count: the integer division is exact.
            phis.append(k * 360 // count)
    return np.array(thetas, np.int64), np.array(phis, np.int64)


def unit_vector(theta_deg, phi_deg) -> np.ndarray:
    """Unit vectors of directions given in degrees (z up: the surface normal).

    Parameters
    ----------
    theta_deg, phi_deg : scalars or (K,) arrays of the same length, degrees

    Returns
    -------
    vectors : (K, 3) float64, ``(sin θ cos φ, sin θ sin φ, cos θ)``
    """
    theta = np.radians(np.atleast_1d(np.asarray(theta_deg, np.float64)))
    phi = np.radians(np.atleast_1d(np.asarray(phi_deg, np.float64)))
    theta, phi = np.broadcast_arrays(theta, phi)
    sin_theta = np.sin(theta)
    return np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), np.cos(theta)], axis=-1)


def _whole_degrees(value, label: str, upper: int) -> int:
    """``value`` as an int in [0, upper); refused if it is not a whole number of degrees there."""
    number = float(value)
    if not np.isfinite(number) or number != round(number) or not 0 <= number < upper:
        raise ValueError(f"{label} must be a whole number of degrees in [0, {upper}), got {value!r}")
    return int(round(number))


def image_name(theta_l, phi_l, theta_v, phi_v, ext: str) -> str:
    """The UTIA path of one image, relative to the BTF folder, ``/``-separated.

    ``tv{θv:03d}_pv{φv:03d}/tl{θl:03d}_pl{φl:03d}_tv{θv:03d}_pv{φv:03d}.{ext}``; angles are
    whole degrees (θ in [0, 90], φ in [0, 360)), ``ext`` is ``"exr"`` or ``"png"``.
    """
    if ext not in IMAGE_FORMATS:
        raise ValueError(f"image format must be one of {IMAGE_FORMATS}, got {ext!r}")
    return NAME_PATTERN.format(tl=_whole_degrees(theta_l, "theta_l", 91), pl=_whole_degrees(phi_l, "phi_l", 360),
                               tv=_whole_degrees(theta_v, "theta_v", 91), pv=_whole_degrees(phi_v, "phi_v", 360),
                               ext=ext)


def parse_image_name(name: str) -> tuple[int, int, int, int, str]:
    """``(theta_l, phi_l, theta_v, phi_v, ext)`` of a UTIA relative path; ValueError if it is not one."""
    match = _NAME.match(name.replace(os.sep, "/"))
    if not match or match.group(1, 2) != match.group(5, 6):
        raise ValueError(f"{name!r} is not a UTIA BTF image name (tvXXX_pvXXX/tlXXX_plXXX_tvXXX_pvXXX.exr|png)")
    tv, pv, tl, pl = (int(match.group(i)) for i in (1, 2, 3, 4))
    return tl, pl, tv, pv, match.group(7)


def light_for(theta_l, phi_l, theta_v, phi_v, shift_deg: float = 0.0) -> np.ndarray:
    """The direction the simulation lights the image ``(θl, φl, θv, φv)`` from.

    The nominal light direction, except where light and view coincide and ``shift_deg > 0``:
    then θl + ``shift_deg`` (towards the horizon), same φ, as a measuring rig would have to.
    VisiBake's default is no shift (see the module's docstring).

    Parameters
    ----------
    theta_l, phi_l, theta_v, phi_v : degrees (scalars)
    shift_deg : in [0, MAX_LIGHT_SHIFT_DEG]

    Returns
    -------
    light : (3,) float64 unit vector, z up
    """
    shift = float(shift_deg)
    if not 0.0 <= shift <= MAX_LIGHT_SHIFT_DEG:
        raise ValueError(f"light shift must be in [0, {MAX_LIGHT_SHIFT_DEG}] degrees, got {shift_deg!r}")
    same = np.allclose(unit_vector(theta_l, phi_l)[0], unit_vector(theta_v, phi_v)[0], rtol=0.0, atol=1e-12)
    theta = float(theta_l) + (shift if same else 0.0)
    if theta >= 90.0:
        raise ValueError(f"light at theta {theta} degrees would be at or below the horizon")
    return unit_vector(theta, phi_l)[0]


def _angles(angles, label: str) -> tuple[np.ndarray, np.ndarray]:
    """A (thetas, phis) pair of whole-degree int64 arrays, checked."""
    if angles is None:
        return ubo_directions()
    thetas, phis = (np.atleast_1d(np.asarray(a)) for a in angles)
    if thetas.ndim != 1 or thetas.shape != phis.shape or thetas.size == 0:
        raise ValueError(f"{label} directions must be two (N,) arrays of the same length, N > 0")
    thetas = np.array([_whole_degrees(t, f"{label} theta", 90) for t in thetas], np.int64)
    phis = np.array([_whole_degrees(p, f"{label} phi", 360) for p in phis], np.int64)
    pairs = set(zip(thetas.tolist(), np.where(thetas == 0, 0, phis).tolist()))
    if len(pairs) != thetas.size:
        raise ValueError(f"{label} directions repeat a direction (two names would be one image)")
    return thetas, phis


# --- PNG, 8-bit sRGB ---------------------------------------------------------------------
# Written by hand with zlib and struct: the core runs inside Blender, whose Python has no
# image library the core could rely on (bpy's own image saving lives in operators/).

def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear values to 8-bit sRGB codes: clipped to [0, 1], the sRGB curve, rounded.

    Parameters
    ----------
    rgb : (..., 3) float, linear

    Returns
    -------
    codes : (..., 3) uint8
    """
    linear = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)
    return np.clip(np.rint(encoded * 255.0), 0, 255).astype(np.uint8)


def write_png(path: str, image: np.ndarray) -> None:
    """Write an (H, W, 3) bottom-up linear float image as an 8-bit sRGB PNG (top row first).

    Values are clipped to [0, 1] (8 bits hold no more); the file carries an sRGB chunk.
    Raises :class:`core.errors.OutputRefused` for non-finite values (nothing is written).
    """
    if not np.all(np.isfinite(image)):
        raise OutputRefused(f"refusing to write non-finite values to {path}")
    codes = linear_to_srgb8(image)[::-1]
    height, width = codes.shape[:2]
    # Filter type 0 (none) on every row: the data is noisy renders, where PNG's predictors gain little.
    rows = np.zeros((height, 1 + 3 * width), np.uint8)
    rows[:, 1:] = codes.reshape(height, 3 * width)
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    data = (_PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"sRGB", b"\x00")
            # gAMA 1/2.2 for decoders that ignore sRGB, as the PNG specification recommends.
            + _png_chunk(b"gAMA", struct.pack(">I", 45455)) + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
            + _png_chunk(b"IEND", b""))
    with open(path, "wb") as handle:
        handle.write(data)


def _unfilter(raw: bytes, height: int, width: int, channels: int) -> np.ndarray:
    """Undo PNG's per-row filters (types 0-4) on 8-bit samples; (H, W*channels) uint8."""
    stride = width * channels
    if len(raw) != height * (stride + 1):
        raise ValueError("PNG image data has the wrong length")
    rows = np.frombuffer(raw, np.uint8).reshape(height, stride + 1)
    out = np.zeros((height, stride), np.uint8)
    previous = np.zeros(stride, np.int64)
    for y in range(height):
        kind, line = rows[y, 0], rows[y, 1:].astype(np.int64)
        if kind == 0:
            current = line
        elif kind == 2:
            current = (line + previous) & 0xFF
        elif kind in (1, 3, 4):
            # Sub, Average and Paeth depend on the byte just decoded: one pass along the row.
            current = np.zeros(stride, np.int64)
            for x in range(stride):
                left = current[x - channels] if x >= channels else 0
                up = previous[x]
                up_left = previous[x - channels] if x >= channels else 0
                if kind == 1:
                    predictor = left
                elif kind == 3:
                    predictor = (left + up) >> 1
                else:
                    p = left + up - up_left
                    pa, pb, pc = abs(p - left), abs(p - up), abs(p - up_left)
                    predictor = left if pa <= pb and pa <= pc else (up if pb <= pc else up_left)
                current[x] = (line[x] + predictor) & 0xFF
        else:
            raise ValueError(f"PNG row filter {kind} is not defined")
        out[y] = current
        previous = current
    return out


def read_png(path: str) -> np.ndarray:
    """Read an 8-bit RGB or RGBA non-interlaced PNG as (H, W, 3) bottom-up linear float32.

    The sRGB curve is undone (alpha, if any, is dropped). Other PNG kinds raise ValueError.
    """
    with open(path, "rb") as handle:
        data = handle.read()
    if not data.startswith(_PNG_SIGNATURE):
        raise ValueError(f"{path} is not a PNG file")
    position, header, compressed = len(_PNG_SIGNATURE), None, []
    while position + 12 <= len(data):
        (length,) = struct.unpack(">I", data[position:position + 4])
        tag = data[position + 4:position + 8]
        body = data[position + 8:position + 8 + length]
        (crc,) = struct.unpack(">I", data[position + 8 + length:position + 12 + length])
        if len(body) != length or zlib.crc32(tag + body) & 0xFFFFFFFF != crc:
            raise ValueError(f"{path}: PNG chunk {tag!r} is damaged")
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            compressed.append(body)
        elif tag == b"IEND":
            break
        position += 12 + length
    if header is None or not compressed:
        raise ValueError(f"{path}: PNG file has no IHDR or no image data")
    width, height, depth, color_type, _, _, interlace = header
    if depth != 8 or color_type not in (2, 6) or interlace != 0:
        raise ValueError(f"{path}: only 8-bit RGB or RGBA non-interlaced PNGs are read "
                         f"(bit depth {depth}, colour type {color_type}, interlace {interlace})")
    channels = 3 if color_type == 2 else 4
    samples = _unfilter(zlib.decompress(b"".join(compressed)), height, width, channels)
    codes = samples.reshape(height, width, channels)[::-1, :, :3]
    return srgb_to_linear(codes.astype(np.float32) / 255.0)


def read_exr_rgb(path: str) -> np.ndarray:
    """Read an EXR's R, G, B channels as (H, W, 3) bottom-up float32."""
    import OpenEXR

    with OpenEXR.File(path) as exr:
        channels = exr.channels()
        if "RGBA" in channels or "RGB" in channels:
            pixels = np.asarray(channels["RGBA" if "RGBA" in channels else "RGB"].pixels)[..., :3]
        elif all(name in channels for name in "RGB"):
            pixels = np.stack([np.asarray(channels[name].pixels) for name in "RGB"], axis=-1)
        else:
            raise ValueError(f"{path} has no R, G, B channels (it has {sorted(channels)})")
    return np.ascontiguousarray(pixels[::-1], np.float32)


# --- The folder --------------------------------------------------------------------------

def _files_under(folder: str) -> list[str]:
    """Every file and link below ``folder``, as ``/``-separated relative paths (links not followed)."""
    found = []
    for root, dirs, files in os.walk(folder):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            found.append(os.path.relpath(os.path.join(root, name), folder).replace(os.sep, "/"))
    return sorted(found)


def _previous_manifest(folder: str) -> dict | None:
    """The folder's VisiBake manifest, or None if there is none or it is not VisiBake's."""
    return read_record(os.path.join(folder, MANIFEST), FORMAT_NAME)


def _direction_list(thetas: np.ndarray, phis: np.ndarray) -> list[dict]:
    return [{"theta_deg": int(t), "phi_deg": int(p)} for t, p in zip(thetas, phis)]


class BTFImages:
    """Writes BTF images into a folder by their UTIA names, and nothing else (no manifest, no
    claim on the folder): what a part of a BTF run split across workers writes into the folder
    a :class:`BTFWriter` claimed (core.distributed.part_tasks.btf_part). Parameters as BTFWriter's.
    """

    def __init__(self, folder: str, image_format: str, width: int, height: int, light_angles=None,
                 view_angles=None):
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image format must be one of {IMAGE_FORMATS}, got {image_format!r}")
        if int(width) != width or int(height) != height or width < 1 or height < 1:
            raise ValueError(f"image size must be positive whole pixels, got {width} x {height}")
        self.folder = os.path.abspath(folder)
        self.image_format = image_format
        self.width, self.height = int(width), int(height)
        self.light_thetas, self.light_phis = _angles(light_angles, "light")
        self.view_thetas, self.view_phis = _angles(view_angles, "view")
        self._written: set[str] = set()
        # Each image goes to a temporary name, recorded before it is written, then into place.
        self.staged = StagedWrites(self.folder)

    @property
    def written(self) -> list[str]:
        """The relative paths written so far, sorted."""
        return sorted(self._written)

    @property
    def planned(self) -> list[str]:
        """The relative paths of all L × V images, light-major."""
        return [self.name(li, vi) for li in range(len(self.light_thetas)) for vi in range(len(self.view_thetas))]

    def name(self, light_index: int, view_index: int) -> str:
        """The relative path of image (light_index, view_index)."""
        return image_name(self.light_thetas[light_index], self.light_phis[light_index],
                          self.view_thetas[view_index], self.view_phis[view_index], self.image_format)

    def write(self, light_index: int, view_index: int, image: np.ndarray) -> str:
        """Write image (light_index, view_index); returns its path.

        Parameters
        ----------
        image : (height, width, 3) float, linear RGB, row 0 at the bottom; finite
        """
        image = np.asarray(image)
        if image.shape != (self.height, self.width, 3):
            raise ValueError(f"BTF image must have shape {(self.height, self.width, 3)}, got {image.shape}")
        relative = self.name(light_index, view_index)
        if not np.all(np.isfinite(image)):
            raise OutputRefused(f"refusing to write non-finite values to BTF image {relative}")
        path = inside_folder(self.folder, *relative.split("/"))
        self.staged.make_folder(os.path.dirname(path))
        # Checked again now that the view's folder exists: a link made in its place would move it.
        inside_folder(self.folder, *relative.split("/"))
        with self.staged.staged(path) as temporary:
            if self.image_format == "exr":
                rgba = np.ones((self.height, self.width, 4), np.float32)
                rgba[..., :3] = image
                write_exr(temporary, rgba)
            else:
                write_png(temporary, image)
        self._written.add(relative)
        return path


class BTFWriter(BTFImages):
    """Writes one BTF image per (light, view) pair into a folder, in the UTIA layout.

    Parameters
    ----------
    folder : the BTF's folder (created if missing)
    image_format : ``"exr"`` (32-bit float linear RGB) or ``"png"`` (8-bit sRGB, clipped to [0, 1])
    width, height : the images' size in pixels
    period : (2,) the tile's period in scene units along x and y (what one image spans)
    light_angles, view_angles : ``(thetas_deg (L,), phis_deg (L,))`` whole degrees, in the
        order images are indexed; default :func:`ubo_directions` for both
    light_shift_deg : see :func:`light_for` (0: light equal to view is lit as named)
    overwrite : write into a folder that also holds files no VisiBake manifest lists (they are
        kept; one with the name of a file this run writes is refused all the same)
    settings : JSON-serialisable dict of the simulation's settings, kept in the manifest

    Refuses (:class:`core.errors.OutputRefused`, a ValueError) a folder that holds files no
    previous VisiBake manifest lists (unless ``overwrite``; never one named as a file it
    writes), a path that would resolve outside the folder, and non-finite pixels. A manifest
    listing every file the run will write is written at once, so an interrupted run's files
    stay VisiBake's; :meth:`finish` completes it and removes the files of an earlier run that
    this one did not write again.
    """

    def __init__(self, folder: str, image_format: str, width: int, height: int, period, light_angles=None,
                 view_angles=None, light_shift_deg: float = 0.0, overwrite: bool = False, settings: dict | None = None):
        super().__init__(folder, image_format, width, height, light_angles, view_angles)
        period = np.asarray(period, np.float64)
        if period.shape != (2,) or not np.all(np.isfinite(period)) or np.any(period <= 0):
            raise ValueError(f"period must be two positive finite lengths, got {period.tolist()}")
        light_for(0, 0, 0, 0, light_shift_deg)  # checks the shift's range
        self.period = period
        self.light_shift_deg = float(light_shift_deg)
        self.settings = dict(settings or {})
        json.dumps(self.settings)  # refuses what the manifest could not hold, before anything is written

        if os.path.lexists(self.folder) and not os.path.isdir(self.folder):
            raise OutputRefused(f"BTF folder {self.folder} is a file, not a folder; nothing was written")
        previous = _previous_manifest(self.folder) if os.path.isdir(self.folder) else None
        self._previous_files = set(previous["files"]) if previous else set()
        # The manifest's temporary name too: a run stopped while replacing the manifest leaves it.
        owned = self._previous_files | ({MANIFEST, MANIFEST + ".tmp"} if previous else set())
        # A killed run's temporaries are VisiBake's: neither a refusal nor kept (removed below).
        foreign = [f for f in _files_under(self.folder) if f not in owned
                   and not is_leftover(os.path.join(self.folder, *f.split("/")))] if os.path.isdir(self.folder) else []
        if foreign and not overwrite:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise OutputRefused(f"BTF folder {self.folder} holds files VisiBake did not write ({shown}); "
                                "choose an empty folder or allow overwriting (they are kept); nothing was written")
        if os.path.lexists(os.path.join(self.folder, MANIFEST)) and not os.path.isfile(
                os.path.join(self.folder, MANIFEST)):
            raise OutputRefused(f"{os.path.join(self.folder, MANIFEST)} is not a file; nothing was written")
        # Even with overwrite: a file of the user's never gives way to one of the same name.
        refuse_foreign([os.path.join(self.folder, *name.split("/")) for name in [MANIFEST, *self.planned]],
                       "overwriting writes beside your files, never over one; choose another folder")
        remove_leftovers(self.folder)
        try:
            self.staged.make_folder(self.folder)
            self._write_manifest(complete=False)
        except BaseException:
            self.staged.rollback()  # no writer is returned to abort: take back the folder here
            raise

    def adopt(self, relative_paths) -> None:
        """Count images written into the folder by parts of this run (:class:`BTFImages` on
        workers) as written by this writer: their names must be planned ones."""
        planned = set(self.planned)
        for relative in relative_paths:
            if relative not in planned:
                raise ValueError(f"BTF image {relative!r} is not one of this run's")
            if relative not in self._previous_files:
                # Planned, not an earlier run's: the refusal above says no file of that name was here.
                self.staged.created.append(os.path.join(self.folder, *relative.split("/")))
            self._written.add(relative)

    def light_direction(self, light_index: int, view_index: int) -> np.ndarray:
        """(3,) float64: the direction the simulation lights image (light_index, view_index) from."""
        return light_for(self.light_thetas[light_index], self.light_phis[light_index],
                         self.view_thetas[view_index], self.view_phis[view_index], self.light_shift_deg)

    def view_direction(self, view_index: int) -> np.ndarray:
        """(3,) float64: the direction image column ``view_index`` is seen from."""
        return unit_vector(self.view_thetas[view_index], self.view_phis[view_index])[0]

    def finish(self) -> str:
        """Complete the manifest once every image is written; returns its path.

        Raises ValueError if images are missing (the provisional manifest stays, so the files
        written remain VisiBake's). Files of an earlier run this one did not write again go.
        """
        planned = self.planned
        missing = [p for p in planned if p not in self._written]
        if missing:
            raise ValueError(f"BTF folder {self.folder} is missing {len(missing)} of {len(planned)} images "
                             f"(first: {missing[0]})")
        for stale in sorted(self._previous_files - set(planned)):
            path = os.path.join(self.folder, *stale.split("/"))
            if os.path.isfile(path) and not os.path.islink(path):
                os.remove(path)
                folder = os.path.dirname(path)
                if folder != self.folder and not os.listdir(folder):
                    os.rmdir(folder)
        return self._write_manifest(complete=True)

    def abort(self) -> None:
        """Take back a run that did not finish: its temporaries, and the images, manifest and
        folders it created (core.outputs.ownership.StagedWrites). Over an earlier BTF the
        provisional manifest (complete: false) stays, listing both runs' files, so the folder
        stays VisiBake's to write again; a file that was there before the run always stays."""
        self.staged.rollback()
        self._written.clear()

    def _write_manifest(self, complete: bool) -> str:
        files = self.planned if complete else sorted(set(self.planned) | self._previous_files)
        manifest = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "complete": complete,
            "layout": "UTIA (Bonn UBO2003 sampling)",
            "name_pattern": NAME_PATTERN,
            "image_format": self.image_format,
            "pixel_type": "float32" if self.image_format == "exr" else "uint8",
            "color_space": COLOR_SPACES[self.image_format],
            "row_order": "top row first in the files",
            "image_size": {"width": self.width, "height": self.height},
            "period": self.period.tolist(),
            "period_units": "scene units",
            "angle_convention": "degrees; theta from the surface normal (z), phi from the tile's +x (u) towards +y (v)",
            "light_directions": _direction_list(self.light_thetas, self.light_phis),
            "view_directions": _direction_list(self.view_thetas, self.view_phis),
            "light_shift": {
                "shift_deg": self.light_shift_deg,
                "rule": ("none: light equal to view is lit from the named direction" if self.light_shift_deg == 0 else
                         "where light equals view, the light is moved shift_deg towards the horizon "
                         "(theta + shift_deg, same phi)"),
            },
            "settings": self.settings,
            "files": files,
        }
        path = os.path.join(self.folder, MANIFEST)
        with self.staged.staged(path) as temporary:
            with open(temporary, "w", encoding="utf-8") as handle:
                json.dump(manifest, handle, indent=1)
                handle.write("\n")
        return path


def write_btf_folder(folder: str, images: np.ndarray, image_format: str, period, light_angles=None,
                     view_angles=None, **options) -> str:
    """Write a whole BTF at once; returns the manifest's path.

    Parameters
    ----------
    images : (L, V, H, W, 3) float, linear RGB, rows bottom-up; finite
    image_format, period, light_angles, view_angles, options : as :class:`BTFWriter`
    """
    images = np.asarray(images)
    if images.ndim != 5 or images.shape[-1] != 3:
        raise ValueError(f"images must have shape (L, V, H, W, 3), got {images.shape}")
    if not np.all(np.isfinite(images)):
        raise OutputRefused(f"refusing to write non-finite values to the BTF folder {folder}")
    writer = BTFWriter(folder, image_format, images.shape[3], images.shape[2], period, light_angles, view_angles,
                       **options)
    if images.shape[:2] != (len(writer.light_thetas), len(writer.view_thetas)):
        raise ValueError(f"images hold {images.shape[:2]} (light, view) pairs; the directions give "
                         f"{(len(writer.light_thetas), len(writer.view_thetas))}")
    for li in range(images.shape[0]):
        for vi in range(images.shape[1]):
            writer.write(li, vi, images[li, vi])
    return writer.finish()


@dataclass(frozen=True, eq=False)
class BTFDirections:
    """The sampling of a BTF folder, in its image order.

    light_thetas, light_phis : (L,) int64 degrees
    view_thetas, view_phis : (V,) int64 degrees
    """

    light_thetas: np.ndarray
    light_phis: np.ndarray
    view_thetas: np.ndarray
    view_phis: np.ndarray

    @property
    def light(self) -> np.ndarray:
        """(L, 3) float64 unit vectors."""
        return unit_vector(self.light_thetas, self.light_phis)

    @property
    def view(self) -> np.ndarray:
        """(V, 3) float64 unit vectors."""
        return unit_vector(self.view_thetas, self.view_phis)


def _sorted_unique(pairs) -> tuple[np.ndarray, np.ndarray]:
    ordered = sorted(set(pairs))
    return np.array([p[0] for p in ordered], np.int64), np.array([p[1] for p in ordered], np.int64)


def read_btf_folder(path: str) -> tuple[BTFDirections, np.ndarray]:
    """Read a BTF folder in the UTIA layout.

    The directions and their order come from a VisiBake ``btf.json`` where there is one;
    otherwise from the file names, sorted by (θ, φ) (which is the UBO2003 order).

    Returns
    -------
    directions : :class:`BTFDirections`
    images : (L, V, H, W, 3) float32 linear RGB, rows bottom-up (PNGs decoded from sRGB)
    """
    folder = os.path.abspath(path)
    if not os.path.isdir(folder):
        raise ValueError(f"{folder} is not a folder")
    manifest = _previous_manifest(folder)
    if manifest is not None:
        ext = manifest.get("image_format")
        if ext not in IMAGE_FORMATS:
            raise ValueError(f"{folder}/{MANIFEST} names no known image format ({ext!r})")
        try:
            light = [(int(d["theta_deg"]), int(d["phi_deg"])) for d in manifest["light_directions"]]
            view = [(int(d["theta_deg"]), int(d["phi_deg"])) for d in manifest["view_directions"]]
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"{folder}/{MANIFEST} has no usable direction lists") from error
        directions = BTFDirections(*(np.array(v, np.int64) for v in zip(*light)),
                                   *(np.array(v, np.int64) for v in zip(*view)))
    else:
        parsed = []
        for name in _files_under(folder):
            try:
                parsed.append(parse_image_name(name))
            except ValueError:
                continue
        if not parsed:
            raise ValueError(f"{folder} holds no BTF images (tvXXX_pvXXX/tlXXX_plXXX_tvXXX_pvXXX.exr|png)")
        kinds = {p[4] for p in parsed}
        if len(kinds) > 1:
            raise ValueError(f"{folder} mixes image formats {sorted(kinds)}")
        ext = kinds.pop()
        directions = BTFDirections(*_sorted_unique((p[0], p[1]) for p in parsed),
                                   *_sorted_unique((p[2], p[3]) for p in parsed))
    reader = read_exr_rgb if ext == "exr" else read_png
    rows = []
    for tl, pl in zip(directions.light_thetas, directions.light_phis):
        row = []
        for tv, pv in zip(directions.view_thetas, directions.view_phis):
            relative = image_name(tl, pl, tv, pv, ext)
            file = os.path.join(folder, *relative.split("/"))
            if not os.path.isfile(file):
                raise ValueError(f"BTF folder {folder} lacks the image {relative}")
            row.append(reader(file))
        rows.append(row)
    shapes = {image.shape for row in rows for image in row}
    if len(shapes) != 1:
        raise ValueError(f"BTF folder {folder} holds images of different sizes {sorted(shapes)}")
    return directions, np.array(rows, np.float32)
