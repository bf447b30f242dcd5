"""Files of the HCI 4D light field benchmark layout: ``parameters.cfg``, PFM ground truth, view names.

What the benchmark's tools expect (lightfield-analysis/python-tools ``file_io.py``, the evaluation
toolkit's ``toolkit/utils/file_io.py`` and ``scenes/base_scene.py``, the Blender add-on's
``import_export.py``), and so what this module writes:

- Views: ``input_Cam000.png`` ... (``%03d``), index = row * num_cams_x + column from the top left.
  VisiBake also writes ``input_CamNNN.exr`` (linear radiance) beside each PNG. HCI's reader sorts the
  names as strings, which misorders grids of more than 1000 views; :func:`read_light_field` parses them.
- ``parameters.cfg``: INI sections ``[intrinsics]``, ``[extrinsics]``, ``[meta]``, ``key = value``
  lines (Python's configparser, ``str()`` of each value). The readers call ``int()`` on the resolutions
  and camera counts (so they must be written without a decimal point), ``float()`` on the rest,
  and also require ``scene, category, date, version, authors, contact`` in ``[meta]`` (``authors``
  split on ", "); the add-on's loader also requires ``cycles_seed``. configparser interpolation is on
  in their readers, so no value may contain '%'. ``center_cam_r*_rad`` are Blender 'XYZ' Euler angles
  of the centre camera (the add-on's grid container object's ``rotation_euler``).
- ``[meta]`` ``disp_min/disp_max``: the centre view's disparity range rounded outward to 0.1 px and
  widened by 0.1 px (:func:`disparity_range`); ``frustum_disp_min/max``: the range the add-on's
  frustum preview shows (a user setting there); ``depth_map_scale``: the high-resolution ground
  truth's size over the views' (10 in the dataset).
- ``gt_disp_lowres.pfm``, ``gt_depth_lowres.pfm``: the centre view's disparity (pixels) and depth
  (metres along the optical axis) at the views' resolution. HCI renders them ``depth_map_scale``
  times larger (the ``*_highres.pfm`` files) and takes each tile's median for ``lowres``. Where
  the view sees no surface (the world), the depth is the camera's far clip distance and the
  disparity the one of that depth: HCI's scenes have a surface in every pixel and its tools
  expect finite maps, so neither file holds an infinity (nothing nearer than the far clip is
  there, as a depth buffer says).
- PFM: ``Pf`` (1 channel) or ``PF`` (3), ``width height``, a scale whose sign is the byte order
  (negative: little-endian; the tools write ``-1``), then float32 rows from the bottom row up. Their
  ``read_pfm`` flips the rows back (``np.flipud``) and multiplies by ``abs(scale)``, as ours does.

Every file is written whole or not at all (:func:`core.outputs.atomic.atomic_file`).
"""
from __future__ import annotations

import configparser
import datetime
import math
import os
import re

import numpy as np

from ..outputs.atomic import atomic_file
from .cameras import CentreCamera, LightFieldGrid, depth_to_disparity, euler_xyz_from_rotation, rotation_from_euler_xyz

PARAMETERS_FILE = "parameters.cfg"
DISPARITY_FILE = "gt_disp_lowres.pfm"
DEPTH_FILE = "gt_depth_lowres.pfm"
VIEW_EXTENSIONS = (".png", ".exr")
_VIEW_NAME = re.compile(r"input_Cam(\d+)(\.png|\.exr)$")

# (section, key, type) in the order of the dataset's own files; `str` values are free text.
_FIELDS = (
    ("intrinsics", "focal_length_mm", float), ("intrinsics", "image_resolution_x_px", int),
    ("intrinsics", "image_resolution_y_px", int), ("intrinsics", "sensor_size_mm", float),
    ("intrinsics", "fstop", float),
    ("extrinsics", "num_cams_x", int), ("extrinsics", "num_cams_y", int), ("extrinsics", "baseline_mm", float),
    ("extrinsics", "focus_distance_m", float), ("extrinsics", "center_cam_x_m", float),
    ("extrinsics", "center_cam_y_m", float), ("extrinsics", "center_cam_z_m", float),
    ("extrinsics", "center_cam_rx_rad", float), ("extrinsics", "center_cam_ry_rad", float),
    ("extrinsics", "center_cam_rz_rad", float),
    ("meta", "scene", str), ("meta", "category", str), ("meta", "date", str), ("meta", "version", str),
    ("meta", "authors", str), ("meta", "contact", str), ("meta", "cycles_seed", int),
    ("meta", "disp_min", float), ("meta", "disp_max", float), ("meta", "frustum_disp_min", float),
    ("meta", "frustum_disp_max", float), ("meta", "depth_map_scale", float),
)


def view_file_name(index: int, extension: str = ".png") -> str:
    """``input_Cam007.png``: the file of view ``index`` (row * num_cams_x + column)."""
    if extension not in VIEW_EXTENSIONS:
        raise ValueError(f"extension must be one of {VIEW_EXTENSIONS}, got {extension!r}")
    return f"input_Cam{index:03d}{extension}"


def disparity_range(disparity_px) -> tuple[float, float]:
    """HCI's ``disp_min, disp_max`` of a disparity map (pixels): the finite values' extremes rounded
    outward to a tenth of a pixel, then widened by another tenth."""
    values = np.asarray(disparity_px, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise ValueError("the disparity map has no finite value")
    low = math.floor(round(values.min() * 10.0, 9)) / 10.0 - 0.1
    high = math.ceil(round(values.max() * 10.0, 9)) / 10.0 + 0.1
    return round(low, 10), round(high, 10)


def _text(name: str, value: str) -> str:
    value = str(value)
    if "%" in value or "\n" in value or "\r" in value or value != value.strip():
        raise ValueError(f"{name} must be one line without '%' or surrounding spaces "
                         f"(HCI's configparser would misread it), got {value!r}")
    return value


def _finite(name: str, value) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


def write_parameters(path: str, camera: CentreCamera, grid: LightFieldGrid, *, disp_min: float,
                     disp_max: float, frustum_disp_min: float | None = None, frustum_disp_max: float | None = None,
                     depth_map_scale: float = 1.0, scene: str = "scene", category: str = "other",
                     date: str | None = None, version: str = "v0", authors: tuple[str, ...] = ("VisiBake",),
                     contact: str = "") -> None:
    """Write ``parameters.cfg`` for ``camera`` and ``grid``, readable by HCI's tools.

    disp_min, disp_max : the centre view's disparity range in pixels (see :func:`disparity_range`).
    frustum_disp_min, frustum_disp_max : default to ``disp_min, disp_max``.
    depth_map_scale : the ground truth's size over the views' (1: only ``*_lowres`` files exist).
    date : ISO date, default today. ``cycles_seed`` is written 0 (no Cycles here; the add-on's loader
    needs the key).
    """
    if float(disp_min) > float(disp_max):
        raise ValueError(f"disp_min ({disp_min}) must not exceed disp_max ({disp_max})")
    authors = tuple(authors)
    if not authors or any(", " in author for author in authors):
        raise ValueError("authors must be one or more names, none containing ', ' (HCI splits on it)")
    rx, ry, rz = euler_xyz_from_rotation(camera.rotation)
    values = {
        "focal_length_mm": camera.focal_length_mm, "image_resolution_x_px": camera.resolution_x_px,
        "image_resolution_y_px": camera.resolution_y_px, "sensor_size_mm": camera.sensor_size_mm,
        "fstop": camera.fstop, "num_cams_x": grid.num_cams_x, "num_cams_y": grid.num_cams_y,
        "baseline_mm": grid.baseline_mm, "focus_distance_m": grid.focus_distance_m,
        "center_cam_x_m": camera.position_m[0], "center_cam_y_m": camera.position_m[1],
        "center_cam_z_m": camera.position_m[2], "center_cam_rx_rad": rx, "center_cam_ry_rad": ry,
        "center_cam_rz_rad": rz, "scene": scene, "category": category,
        "date": datetime.date.today().isoformat() if date is None else date, "version": version,
        "authors": ", ".join(authors), "contact": contact, "cycles_seed": 0, "disp_min": disp_min,
        "disp_max": disp_max, "frustum_disp_min": disp_min if frustum_disp_min is None else frustum_disp_min,
        "frustum_disp_max": disp_max if frustum_disp_max is None else frustum_disp_max,
        "depth_map_scale": depth_map_scale,
    }
    parser = configparser.ConfigParser(delimiters=("=",), interpolation=None)
    for section, key, kind in _FIELDS:
        if not parser.has_section(section):
            parser.add_section(section)
        value = values[key]
        if kind is float:
            text = repr(_finite(key, value))  # repr: the shortest text that reads back exactly
        elif kind is int:
            text = str(int(value))
        else:
            text = _text(key, value)
        parser.set(section, key, text)
    with atomic_file(path, "w", encoding="utf-8") as stream:
        parser.write(stream)


def read_parameters(path: str) -> dict:
    """The fields of a ``parameters.cfg`` as a flat dict keyed by the file's own names, typed as HCI
    reads them (int, float, str; ``authors`` a list of names). ``cycles_seed`` may be absent; keys
    beyond HCI's (the add-on's ``offset``) are ignored. Raises ValueError naming a missing or
    malformed field."""
    parser = configparser.ConfigParser(delimiters=("=",), interpolation=None)
    try:
        with open(path, encoding="utf-8") as stream:
            parser.read_file(stream)
    except configparser.Error as error:
        raise ValueError(f"{path} is not an INI file: {error}") from error
    params = {}
    for section, key, kind in _FIELDS:
        if not parser.has_option(section, key):
            if key == "cycles_seed":
                continue
            raise ValueError(f"{path} lacks [{section}] {key}")
        text = parser.get(section, key)
        try:
            # The add-on's loader reads the seed with float(); so do we, to accept what it accepts.
            params[key] = float(text) if key == "cycles_seed" else kind(text)
        except ValueError as error:
            raise ValueError(f"{path}: [{section}] {key} = {text!r} is not {kind.__name__}") from error
    params["authors"] = params["authors"].split(", ")
    return params


def camera_and_grid(params: dict) -> tuple[CentreCamera, LightFieldGrid]:
    """The centre camera and grid of a :func:`read_parameters` dict (ValueError if invalid)."""
    camera = CentreCamera(
        position_m=[params["center_cam_x_m"], params["center_cam_y_m"], params["center_cam_z_m"]],
        rotation=rotation_from_euler_xyz(params["center_cam_rx_rad"], params["center_cam_ry_rad"],
                                         params["center_cam_rz_rad"]),
        focal_length_mm=params["focal_length_mm"], sensor_size_mm=params["sensor_size_mm"],
        resolution_x_px=params["image_resolution_x_px"], resolution_y_px=params["image_resolution_y_px"],
        fstop=params["fstop"])
    grid = LightFieldGrid(num_cams_x=params["num_cams_x"], num_cams_y=params["num_cams_y"],
                          baseline_mm=params["baseline_mm"], focus_distance_m=params["focus_distance_m"])
    return camera, grid


def write_pfm(path: str, data) -> None:
    """Write a (h, w), (h, w, 1) or (h, w, 3) real array as a little-endian float32 PFM, HCI's way:
    header ``Pf``/``PF``, ``w h``, ``-1``; rows from the bottom of the image up."""
    array = np.asarray(data)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)) or 0 in array.shape:
        raise ValueError(f"a PFM holds a non-empty (h, w) or (h, w, 3) array, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.floating) and not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"a PFM holds real numbers, got dtype {array.dtype}")
    with np.errstate(over="ignore"):
        values = array.astype("<f4")
    if np.any(np.isfinite(array) & ~np.isfinite(values)):
        raise ValueError("values beyond float32's range cannot be stored in a PFM")
    height, width = array.shape[:2]
    header = f"{'Pf' if array.ndim == 2 else 'PF'}\n{width} {height}\n-1\n".encode("ascii")
    with atomic_file(path, "wb") as stream:
        stream.write(header)
        stream.write(np.ascontiguousarray(values[::-1]).tobytes())


def _header_line(stream, path: str) -> str:
    line = stream.readline()
    while line.startswith(b"#"):  # HCI's reader skips comment lines
        line = stream.readline()
    if not line:
        raise ValueError(f"{path}: the PFM header ends early")
    return line.decode("ascii", errors="replace").strip()


def read_pfm(path: str) -> np.ndarray:
    """A PFM file as float32, (h, w) for ``Pf`` or (h, w, 3) for ``PF``, top row first; either byte
    order; values multiplied by the header's ``abs(scale)`` as HCI's reader does."""
    with open(path, "rb") as stream:
        identifier = _header_line(stream, path)
        if identifier not in ("Pf", "PF"):
            raise ValueError(f"{path}: not a PFM file (identifier {identifier[:20]!r}, expected 'Pf' or 'PF')")
        dimensions = _header_line(stream, path).split()
        try:
            width, height = (int(text) for text in dimensions)
        except ValueError:
            width = height = 0
        if width < 1 or height < 1:
            raise ValueError(f"{path}: bad PFM dimensions {' '.join(dimensions)[:40]!r}, expected 'width height'")
        scale_text = _header_line(stream, path)
        try:
            scale = float(scale_text)
        except ValueError:
            scale = 0.0
        if scale == 0.0 or not math.isfinite(scale):
            raise ValueError(f"{path}: bad PFM scale {scale_text[:40]!r}, expected a non-zero number")
        payload = stream.read()
    shape = (height, width) if identifier == "Pf" else (height, width, 3)
    expected = int(np.prod(shape)) * 4
    if len(payload) != expected:
        raise ValueError(f"{path}: {len(payload)} bytes of pixels for a {width}x{height} {identifier} PFM, "
                         f"expected {expected}")
    data = np.frombuffer(payload, dtype="<f4" if scale < 0 else ">f4").reshape(shape)[::-1].astype(np.float32)
    if abs(scale) != 1.0:
        data *= np.float32(abs(scale))
    return data


def write_ground_truth(folder: str, depth_m, camera: CentreCamera, grid: LightFieldGrid, *,
                       far_m: float) -> tuple[float, float]:
    """Write the centre view's ``gt_depth_lowres.pfm`` (depth ``(res_y, res_x)`` metres along the optical
    axis, top row first; inf where no surface) and the ``gt_disp_lowres.pfm`` computed from it. Returns
    :func:`disparity_range` of the disparity, for ``parameters.cfg``.

    far_m : the camera's far clip distance (metres), written where no surface is seen (the sky):
        both files hold finite values only, as HCI's tools expect (its scenes have no sky)."""
    depth = np.asarray(depth_m, dtype=np.float64)
    expected = (camera.resolution_y_px, camera.resolution_x_px)
    if depth.shape != expected:
        raise ValueError(f"depth_m must have the views' shape {expected} (rows, columns), got {depth.shape}")
    if not (math.isfinite(far_m) and far_m > 0):
        raise ValueError(f"far_m must be a positive finite distance, got {far_m}")
    depth = np.where(depth == np.inf, far_m, depth)
    if not np.all(np.isfinite(depth)):
        raise ValueError("depth_m holds NaN or -inf (a renderer's bug)")
    disparity = depth_to_disparity(depth, camera, grid)
    write_pfm(os.path.join(folder, DEPTH_FILE), depth)
    write_pfm(os.path.join(folder, DISPARITY_FILE), disparity)
    return disparity_range(disparity)


def read_light_field(folder: str) -> dict:
    """Read an HCI folder.

    Returns a dict: ``parameters`` (:func:`read_parameters`), ``views`` ({extension: [path of view 0,
    1, ...]} for each of ``.png``/``.exr`` present), ``disparity`` and ``depth`` (float32 (h, w) arrays
    of the centre view's ``*_lowres.pfm``, or None where the file is absent, as in HCI's test scenes).
    Raises ValueError when a view is missing, numbered beyond the grid, misnamed, or a map's shape
    is not the views'.
    """
    parameters_path = os.path.join(folder, PARAMETERS_FILE)
    if not os.path.isfile(parameters_path):
        raise ValueError(f"{folder} is not an HCI light field: it has no {PARAMETERS_FILE}")
    params = read_parameters(parameters_path)
    count = params["num_cams_x"] * params["num_cams_y"]
    found: dict[str, dict[int, str]] = {}
    for name in sorted(os.listdir(folder)):
        if not name.startswith("input_"):
            continue
        match = _VIEW_NAME.match(name)
        if match is None or name != view_file_name(int(match.group(1)), match.group(2)):
            raise ValueError(f"{folder}: unexpected view file {name!r} (views are input_CamNNN.png/.exr)")
        index = int(match.group(1))
        if index >= count:
            raise ValueError(f"{folder}: view file {name!r} is beyond the {params['num_cams_x']}x"
                             f"{params['num_cams_y']} grid of parameters.cfg (views 0 to {count - 1})")
        found.setdefault(match.group(2), {})[index] = os.path.join(folder, name)
    if not found:
        raise ValueError(f"{folder} has no views (input_CamNNN.png or .exr)")
    views = {}
    for extension in VIEW_EXTENSIONS:
        if extension not in found:
            continue
        missing = [view_file_name(index, extension) for index in range(count) if index not in found[extension]]
        if missing:
            shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
            raise ValueError(f"{folder}: {len(missing)} of {count} views missing: {shown}")
        views[extension] = [found[extension][index] for index in range(count)]
    maps = {}
    for key, name in (("disparity", DISPARITY_FILE), ("depth", DEPTH_FILE)):
        path = os.path.join(folder, name)
        maps[key] = read_pfm(path) if os.path.isfile(path) else None
        expected = (params["image_resolution_y_px"], params["image_resolution_x_px"])
        if maps[key] is not None and maps[key].shape != expected:
            raise ValueError(f"{path}: shape {maps[key].shape}, expected the views' {expected}")
    return {"parameters": params, "views": views, **maps}
