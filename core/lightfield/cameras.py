"""The camera grid of a light field, as the HCI 4D light field benchmark defines it.

The benchmark's Blender add-on (lightfield-analysis/blender-addon, ``lightfield_simulator.py``)
builds the grid this way, and this module reproduces it without Blender:

- Every view is a copy of the centre camera (same rotation, focal length, sensor), translated in
  the centre camera's image plane by whole baselines: the optical axes stay parallel.
- Row 0 is the top row and column 0 the left column, as the centre camera sees them; view
  ``index = row * num_cams_x + column`` (the add-on's ``LF_CamNNN`` names, ``input_CamNNN`` files).
- Each view's lens is shifted (off-axis frustum) so that the focus plane, at ``focus_distance_m``
  along the optical axis, projects to the same pixels in every view: zero disparity there.
- Disparity, in pixels between adjacent views, is
  ``d = baseline_m * focal_length_mm * max(res_x, res_y) / sensor_size_mm * (1 / depth_m - 1 / focus_m)``
  (the add-on's ``render_depth_and_disp_maps`` and the evaluation toolkit's ``depth2disp``), with
  depth the distance along the optical axis (Blender Internal's Z pass), not along the ray.
  Positive disparity is nearer than the focus plane. A point of disparity ``d`` seen at pixel
  ``(x, y)`` (x right, y down) in view ``(row, column)`` is at ``(x - d, y)`` in ``(row, column + 1)``
  and at ``(x, y - d)`` in ``(row + 1, column)``.

The sensor: ``sensor_size_mm`` spans the larger image dimension, square pixels. That is Blender's
``sensor_fit = 'AUTO'`` (the add-on sets ``sensor_width = sensor_height = sensor_size``), and it is
why the disparity uses ``max(res_x, res_y)``. Blender's lens shift is in the same unit: a fraction of
the fitted (larger) dimension (``BKE_camera_params_compute_viewplane``: ``dx = shiftx * viewfac``).

Camera frames follow Blender: a camera looks along its local -Z with +Y up and +X right; a rotation
is camera-to-world. Lengths are in metres except the lens, sensor and baseline (millimetres, as HCI).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

_ROTATION_TOLERANCE = 1e-6


def positive_number(name: str, value) -> float:
    """``value`` as a float; ValueError naming ``name`` unless it is a finite number > 0."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, (bool, str)) or not (math.isfinite(number) and number > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return number


def whole_count(name: str, value) -> int:
    try:
        whole = int(value)
        valid = not isinstance(value, (bool, str)) and whole == value and whole >= 1
    except (TypeError, ValueError, OverflowError):
        valid = False
    if not valid:
        raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")
    return whole


def _frozen_array(values, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be a finite array of shape {shape}, got {np.shape(values)}")
    array.setflags(write=False)
    return array


def rotation_from_euler_xyz(rx_rad: float, ry_rad: float, rz_rad: float) -> np.ndarray:
    """The (3, 3) float64 rotation of Blender's ``rotation_mode = 'XYZ'`` Euler angles (radians):
    about world X first, then Y, then Z, i.e. ``Rz @ Ry @ Rx``. HCI's ``center_cam_r*_rad`` are
    the add-on's container object's ``rotation_euler`` in that (default) mode."""
    cx, sx = math.cos(rx_rad), math.sin(rx_rad)
    cy, sy = math.cos(ry_rad), math.sin(ry_rad)
    cz, sz = math.cos(rz_rad), math.sin(rz_rad)
    about_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    about_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    about_z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return about_z @ about_y @ about_x


def euler_xyz_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """(rx, ry, rz) radians, Blender 'XYZ' order, of a (3, 3) rotation; ry in [-pi/2, pi/2].
    At gimbal lock (ry = +-pi/2) rz is set to 0 and rx carries the remaining turn."""
    r = np.asarray(rotation, dtype=np.float64)
    ry = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        return math.atan2(r[2, 1], r[2, 2]), ry, math.atan2(r[1, 0], r[0, 0])
    # Only rx -+ rz is defined here; the columns' second row gives it with rz = 0.
    return math.atan2(-r[1, 2], r[1, 1]), ry, 0.0


@dataclass(frozen=True)
class CentreCamera:
    """The user's camera, at the centre of the grid.

    position_m : (3,) float64 world position, metres.
    rotation : (3, 3) float64 camera-to-world rotation (Blender camera: looks along local -Z, up is
        local +Y); orthonormal, determinant +1 (strip the object's scale first).
    focal_length_mm, sensor_size_mm : the lens and the sensor extent along the *larger* image
        dimension (Blender's sensor fit 'AUTO'; HCI's ``sensor_size_mm``). A Blender camera with another
        fit converts first, e.g. 'VERTICAL' on a landscape image: ``sensor_height * res_x / res_y``.
    resolution_x_px, resolution_y_px : the views' size in pixels (square pixels).
    fstop : HCI's ``fstop``; metadata only (the add-on's Cycles aperture; 100 is its default).
    """
    position_m: np.ndarray
    rotation: np.ndarray
    focal_length_mm: float
    sensor_size_mm: float
    resolution_x_px: int
    resolution_y_px: int
    fstop: float = 100.0

    def __post_init__(self):
        set_ = functools.partial(object.__setattr__, self)
        set_("position_m", _frozen_array(self.position_m, (3,), "position_m"))
        rotation = _frozen_array(self.rotation, (3, 3), "rotation")
        if (not np.allclose(rotation.T @ rotation, np.eye(3), atol=_ROTATION_TOLERANCE)
                or np.linalg.det(rotation) < 0.0):
            raise ValueError("rotation must be a proper rotation matrix (orthonormal, determinant +1); "
                             "remove the camera object's scale first")
        set_("rotation", rotation)
        set_("focal_length_mm", positive_number("focal_length_mm", self.focal_length_mm))
        set_("sensor_size_mm", positive_number("sensor_size_mm", self.sensor_size_mm))
        set_("resolution_x_px", whole_count("resolution_x_px", self.resolution_x_px))
        set_("resolution_y_px", whole_count("resolution_y_px", self.resolution_y_px))
        set_("fstop", positive_number("fstop", self.fstop))

    @property
    def pixel_size_at_unit_distance(self) -> float:
        """The side of one pixel on the plane 1 m in front of the camera, metres."""
        return self.sensor_size_mm / (self.focal_length_mm * max(self.resolution_x_px, self.resolution_y_px))


@dataclass(frozen=True)
class LightFieldGrid:
    """The grid: ``num_cams_x`` columns by ``num_cams_y`` rows of views, ``baseline_mm`` apart in both
    directions, focused (zero disparity) at ``focus_distance_m`` along the optical axis. 1 x 1 is allowed."""
    num_cams_x: int
    num_cams_y: int
    baseline_mm: float
    focus_distance_m: float

    def __post_init__(self):
        set_ = functools.partial(object.__setattr__, self)
        set_("num_cams_x", whole_count("num_cams_x", self.num_cams_x))
        set_("num_cams_y", whole_count("num_cams_y", self.num_cams_y))
        set_("baseline_mm", positive_number("baseline_mm", self.baseline_mm))
        # HCI's add-on takes 0 as "focused at infinity", but its disparity formula divides by it.
        set_("focus_distance_m", positive_number("focus_distance_m", self.focus_distance_m))

    @property
    def view_count(self) -> int:
        return self.num_cams_x * self.num_cams_y

    @property
    def centre_index(self) -> int:
        """The view the ground truth belongs to: the evaluation toolkit's ``int(nx * ny / 2)``. It is
        the centre camera itself on an odd grid; an even grid has no view there."""
        return self.view_count // 2


@dataclass(frozen=True)
class GridView:
    """One view of the grid.

    index, row, column : ``index = row * num_cams_x + column``; row 0 at the top, column 0 at the left.
    offset_m : (2,) float64 (right, up) translation from the centre camera in its image plane, metres.
    position_m : (3,) float64 world position; rotation : (3, 3) the centre camera's rotation.
    shift_x, shift_y : Blender ``Camera.shift_x/shift_y`` giving this view's off-axis frustum, in
        fractions of the larger image dimension; valid with ``sensor_fit = 'AUTO'`` and
        ``sensor_width = sensor_size_mm`` (Blender's own unit for shift is the fitted dimension).
    view_matrix : (4, 4) float64 world-to-camera (eye space: looks along -Z, +Y up).
    projection_matrix : (4, 4) float64 OpenGL ``glFrustum`` matrix: column vectors
        (``clip = P @ V @ [x, y, z, 1]``), NDC in [-1, 1]^3 with x right, y up, z = -1 at the near and
        +1 at the far clip plane, and ``clip.w`` = depth along the optical axis. NDC (-1, +1) is the
        image's top-left corner: pixel ``x = (ndc_x + 1) * res_x / 2``, ``y = (1 - ndc_y) * res_y / 2``,
        pixel centres at +0.5. Blender's gpu module takes it as ``mathutils.Matrix(matrix.tolist())``.
    """
    index: int
    row: int
    column: int
    offset_m: np.ndarray
    position_m: np.ndarray
    rotation: np.ndarray
    shift_x: float
    shift_y: float
    view_matrix: np.ndarray
    projection_matrix: np.ndarray = field(repr=False)

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) float64 matrix_world of a Blender camera object placed at this view."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation
        matrix[:3, 3] = self.position_m
        return matrix


def _check_clip(clip_start_m: float, clip_end_m: float) -> tuple[float, float]:
    near = positive_number("clip_start_m", clip_start_m)
    far = positive_number("clip_end_m", clip_end_m)
    if far <= near:
        raise ValueError(f"clip_end_m ({far}) must be greater than clip_start_m ({near})")
    return near, far


def grid_views(camera: CentreCamera, grid: LightFieldGrid, clip_start_m: float = 0.1,
               clip_end_m: float = 1000.0) -> list[GridView]:
    """Every view of ``grid`` around ``camera``, in HCI order (index = row * num_cams_x + column)."""
    near, far = _check_clip(clip_start_m, clip_end_m)
    baseline_m = grid.baseline_mm / 1000.0
    focus = grid.focus_distance_m
    pixel = camera.pixel_size_at_unit_distance
    half_width = 0.5 * camera.resolution_x_px * pixel
    half_height = 0.5 * camera.resolution_y_px * pixel
    shift_unit = camera.sensor_size_mm / camera.focal_length_mm  # the window's move for shift 1, at 1 m
    world_to_camera = camera.rotation.T
    views = []
    for row in range(grid.num_cams_y):
        for column in range(grid.num_cams_x):
            offset = np.array([(column - 0.5 * (grid.num_cams_x - 1)) * baseline_m,
                               (0.5 * (grid.num_cams_y - 1) - row) * baseline_m])
            position = camera.position_m + camera.rotation @ np.array([offset[0], offset[1], 0.0])
            # The window (on the plane 1 m ahead) moves against the camera, by what the offset
            # subtends at the focus distance: the focus plane then lands on the same pixels in every view.
            window_x, window_y = -offset / focus
            view = np.eye(4)
            view[:3, :3] = world_to_camera
            view[:3, 3] = -world_to_camera @ position
            projection = _frustum(near * (window_x - half_width), near * (window_x + half_width),
                                  near * (window_y - half_height), near * (window_y + half_height), near, far)
            for array in (offset, position, view, projection):
                array.setflags(write=False)
            # `+ 0.0`: the centre view's shift reads 0.0, not -0.0.
            views.append(GridView(index=row * grid.num_cams_x + column, row=row, column=column,
                                  offset_m=offset, position_m=position, rotation=camera.rotation,
                                  shift_x=float(window_x / shift_unit) + 0.0,
                                  shift_y=float(window_y / shift_unit) + 0.0,
                                  view_matrix=view, projection_matrix=projection))
    return views


def _frustum(left: float, right: float, bottom: float, top: float, near: float, far: float) -> np.ndarray:
    return np.array([
        [2.0 * near / (right - left), 0.0, (right + left) / (right - left), 0.0],
        [0.0, 2.0 * near / (top - bottom), (top + bottom) / (top - bottom), 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2.0 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def disparity_per_inverse_depth(camera: CentreCamera, grid: LightFieldGrid) -> float:
    """HCI's ``baseline_m * focal_length_mm * max(res) / sensor_size_mm``: pixels of disparity per
    1/m of inverse depth (the disparity of depth ``z`` is this times ``1/z - 1/focus``)."""
    return (grid.baseline_mm / 1000.0) * camera.focal_length_mm * max(
        camera.resolution_x_px, camera.resolution_y_px) / camera.sensor_size_mm


def depth_to_disparity(depth_m, camera: CentreCamera, grid: LightFieldGrid) -> np.ndarray:
    """Disparity (float64 pixels between adjacent views, any shape) of depths along the optical axis
    (metres, > 0; inf allowed: the most negative disparity). 0 at the focus distance, > 0 nearer."""
    depth = np.asarray(depth_m, dtype=np.float64)
    if np.any(depth <= 0.0):
        raise ValueError("depth_m must be positive (metres along the optical axis)")
    return disparity_per_inverse_depth(camera, grid) * (1.0 / depth - 1.0 / grid.focus_distance_m)


def disparity_to_depth(disparity_px, camera: CentreCamera, grid: LightFieldGrid) -> np.ndarray:
    """Depth along the optical axis (float64 metres, any shape) of disparities (pixels between
    adjacent views); the inverse of :func:`depth_to_disparity`. Disparities at or below the one of
    infinity (``-disparity_per_inverse_depth / focus``) map to inf."""
    inverse_depth = (np.asarray(disparity_px, dtype=np.float64) / disparity_per_inverse_depth(camera, grid)
                     + 1.0 / grid.focus_distance_m)
    with np.errstate(divide="ignore"):
        depth = 1.0 / inverse_depth
    return np.where(inverse_depth > 0.0, depth, np.inf)


def depth_from_depth_buffer(buffer, clip_start_m: float, clip_end_m: float) -> np.ndarray:
    """Depth along the optical axis (float64 metres) of OpenGL depth-buffer values in [0, 1] written
    with a :class:`GridView` projection of the same clip planes (default depth range, 0 = near)."""
    near, far = _check_clip(clip_start_m, clip_end_m)
    ndc_z = 2.0 * np.asarray(buffer, dtype=np.float64) - 1.0
    return 2.0 * far * near / ((far + near) - ndc_z * (far - near))
