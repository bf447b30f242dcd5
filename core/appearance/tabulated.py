"""Tabulated BSDFs: a micro-geometry's scattering sampled on light × view direction sets.

For BSDFs no analytic model or isotropic table holds (anisotropic reflection, transmission
through thin layers), VisiBake stores the simulated values on two direction sets over the
whole sphere, in one ``.npz`` file (``np.savez_compressed``, readable with ``np.load`` and
``allow_pickle=False``). Format ``visibake-bsdf``, version 1; its arrays:

==============  =============  ============================================================
key             shape, dtype   meaning
==============  =============  ============================================================
format          () str         ``"visibake-bsdf"``
version         () int64       1
light           (L, 3) <f4     unit vectors towards the light; z is the surface normal
view            (V, 3) <f4     unit vectors towards the viewer; z < 0 is transmission
values          (L, V, 3) <f4  BSDF in 1/sr, linear Rec.709 RGB, >= 0
transparency    (L, 3) <f4     the fraction of light passing straight through (thin layers), in [0, 1]
period          (2,) <f8       the tile's period along x and y, in ``units``
units           () str         the length unit of ``period`` (e.g. ``"m"``)
settings        () str         the simulation's settings, a JSON object
checksum        () str         SHA-256, hex, of the content (below)
==============  =============  ============================================================

The checksum covers, in this order: ``format`` and ``version`` as text; then for each of
light, view, values, transparency, period: the key, the dtype (``<f4``/``<f8``) and the
shape as text, then the array's bytes (C order, little-endian); then ``units`` and
``settings`` as UTF-8. Each text piece ends with a NUL byte. It catches damage and partial
copies, not forgery.

Files are written atomically (a temporary file in the same folder, then ``os.replace``):
a reader never sees half a table. Non-finite values are refused on writing and reading.

Interpolation (:meth:`TabulatedBSDF.evaluate`): a query direction is weighted onto its 3
nearest table directions (by angle) with modified Shepard weights
``w_i = ((R - d_i) / (R d_i))^2``, R the angle to the 4th nearest, normalised to sum 1.
Every weight falls to 0 as its direction stops being among the 3 nearest, so the result is
continuous over the sphere (plain k-nearest inverse-distance weighting jumps wherever the
3rd and 4th nearest swap); at a table direction it is that direction's value exactly. Light
and view are weighted independently: 3 × 3 = 9 table values per query. (Barycentric
weights on a spherical triangulation would need a convex hull, i.e. scipy or a hand-written
hull; a hemisphere-only set would also leave the bottom unfenced.)
"""
from __future__ import annotations

import hashlib
import json
import os
import zipfile
import zlib
from dataclasses import dataclass

import numpy as np

from ..outputs.atomic import atomic_file

FORMAT_NAME = "visibake-bsdf"
FORMAT_VERSION = 1
NEIGHBOURS = 3
# How far from 1 a stored float32 direction's length may be: float32 rounding is ~1e-7.
UNIT_TOLERANCE = 1e-5
# A query this close (radians) to a table direction takes that direction's value alone.
SNAP_ANGLE = 1e-9
_ARRAY_KEYS = ("light", "view", "values", "transparency", "period")
_KEYS = ("format", "version") + _ARRAY_KEYS + ("units", "settings", "checksum")
# Queries per block: bounds the (block, table size) matrices of dot products.
_BLOCK_ENTRIES = 1 << 21


def checksum(light, view, values, transparency, period, units: str, settings: str) -> str:
    """The SHA-256 (hex) of a table's content, as the module's docstring defines it.

    Parameters
    ----------
    light : (L, 3) float32; view : (V, 3) float32; values : (L, V, 3) float32
    transparency : (L, 3) float32; period : (2,) float64; units, settings : str
    """
    digest = hashlib.sha256()
    digest.update(f"{FORMAT_NAME}\0{FORMAT_VERSION}\0".encode())
    for key, array, dtype in zip(_ARRAY_KEYS, (light, view, values, transparency, period),
                                 ("<f4", "<f4", "<f4", "<f4", "<f8")):
        array = np.ascontiguousarray(array, dtype=dtype)
        digest.update(f"{key}\0{dtype}\0{array.shape}\0".encode())
        digest.update(array.tobytes())
    digest.update(units.encode("utf-8") + b"\0" + settings.encode("utf-8") + b"\0")
    return digest.hexdigest()


def _unit_rows(array: np.ndarray, label: str) -> None:
    lengths = np.linalg.norm(array.astype(np.float64), axis=-1)
    worst = float(np.max(np.abs(lengths - 1.0))) if lengths.size else 0.0
    if worst > UNIT_TOLERANCE:
        raise ValueError(f"tabulated BSDF: {label} directions must be unit vectors "
                         f"(one has length {lengths[np.argmax(np.abs(lengths - 1.0))]:.6g})")


def sphere_weights(table: np.ndarray, query: np.ndarray, k: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:
    """Interpolation weights of query directions on a table of directions (see the module's docstring).

    Parameters
    ----------
    table : (N, 3) float, unit vectors
    query : (K, 3) float, unit vectors
    k : neighbours per query (at most N)

    Returns
    -------
    indices : (K, k) int64 into ``table``, nearest first
    weights : (K, k) float64, each row sums to 1
    """
    table = np.asarray(table, np.float64)
    query = np.asarray(query, np.float64)
    count = table.shape[0]
    k = min(k, count)
    indices = np.empty((query.shape[0], k), np.int64)
    weights = np.empty((query.shape[0], k), np.float64)
    block = max(1, _BLOCK_ENTRIES // max(count, 1))
    candidates = min(k + 1, count)
    for start in range(0, query.shape[0], block):
        q = query[start:start + block]
        dots = q @ table.T
        # Ranked by dot product (cheap), then the few candidates' angles measured precisely:
        # atan2(|q x t|, q . t) keeps its accuracy near 0, where arccos(q . t) loses it.
        if candidates < count:
            near = np.argpartition(-dots, candidates - 1, axis=1)[:, :candidates]
        else:
            near = np.broadcast_to(np.arange(count), (q.shape[0], count)).copy()
        t = table[near]
        angles = np.arctan2(np.linalg.norm(np.cross(q[:, None, :], t), axis=-1), np.einsum("kj,knj->kn", q, t))
        order = np.argsort(angles, axis=1, kind="stable")
        near = np.take_along_axis(near, order, axis=1)
        angles = np.take_along_axis(angles, order, axis=1)
        d = angles[:, :k]
        with np.errstate(divide="ignore", invalid="ignore"):
            if candidates > k:
                radius = angles[:, k:k + 1]
                w = (np.clip(radius - d, 0.0, None) / (radius * d)) ** 2
            else:
                # The table has no (k+1)-th direction: the neighbour set never changes, plain Shepard.
                w = 1.0 / d ** 2
        snapped = d[:, 0] <= SNAP_ANGLE
        w[snapped] = 0.0
        w[snapped, 0] = 1.0
        total = w.sum(axis=1)
        # A query equally far from its 3rd and 4th nearest and from all of the first 3 at once
        # (a point of symmetry) leaves no weight: share it equally.
        empty = ~(total > 0.0) | ~np.isfinite(total)
        w[empty] = 1.0
        total[empty] = k
        indices[start:start + block] = near[:, :k]
        weights[start:start + block] = w / total[:, None]
    return indices, weights


def _unit_queries(directions, label: str) -> np.ndarray:
    directions = np.asarray(directions, np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"{label} directions must have shape (K, 3), got {directions.shape}")
    lengths = np.linalg.norm(directions, axis=1)
    if not np.all(np.isfinite(lengths)) or np.any(lengths == 0.0):
        raise ValueError(f"{label} directions must be finite and non-zero")
    return directions / lengths[:, None]


@dataclass(frozen=True, eq=False)
class TabulatedBSDF:
    """A BSDF sampled on a light direction set × a view direction set over the sphere.

    Attributes
    ----------
    light : (L, 3) float32 unit vectors towards the light (z: the surface normal)
    view : (V, 3) float32 unit vectors towards the viewer (z < 0: transmission)
    values : (L, V, 3) float32 BSDF in 1/sr, linear Rec.709 RGB, >= 0
    transparency : (L, 3) float32 straight-through fraction per light direction, in [0, 1]
    period : (2,) float64 tile period along x and y, in ``units``
    units : the length unit of ``period``
    settings : the simulation's settings, a JSON object as text (a dict is encoded)
    """

    light: np.ndarray
    view: np.ndarray
    values: np.ndarray
    transparency: np.ndarray
    period: np.ndarray
    units: str = "m"
    settings: str = "{}"

    def __post_init__(self):
        convert = {key: np.ascontiguousarray(getattr(self, key), np.float32)
                   for key in ("light", "view", "values", "transparency")}
        convert["period"] = np.ascontiguousarray(self.period, np.float64)
        for key, array in convert.items():
            object.__setattr__(self, key, array)
        settings = self.settings
        if isinstance(settings, dict):
            settings = json.dumps(settings, sort_keys=True)
        object.__setattr__(self, "settings", settings)
        _validate(self.light, self.view, self.values, self.transparency, self.period, self.units, self.settings)

    @property
    def settings_dict(self) -> dict:
        """The simulation's settings, decoded."""
        return json.loads(self.settings)

    def evaluate(self, light, view) -> np.ndarray:
        """The BSDF for pairs of directions, interpolated on the sphere (module's docstring).

        Parameters
        ----------
        light : (K, 3) float, towards the light (normalised here)
        view : (K, 3) float, towards the viewer (normalised here)

        Returns
        -------
        bsdf : (K, 3) float64 in 1/sr; equal to ``values[i, j]`` where light is ``light[i]``
            and view is ``view[j]``
        """
        light = _unit_queries(light, "light")
        view = _unit_queries(view, "view")
        if light.shape != view.shape:
            raise ValueError(f"light and view must have the same shape, got {light.shape} and {view.shape}")
        light_index, light_weight = sphere_weights(self.light, light)
        view_index, view_weight = sphere_weights(self.view, view)
        result = np.zeros((light.shape[0], 3), np.float64)
        for a in range(light_index.shape[1]):
            for b in range(view_index.shape[1]):
                weight = (light_weight[:, a] * view_weight[:, b])[:, None]
                result += weight * self.values[light_index[:, a], view_index[:, b]]
        return result

    def evaluate_transparency(self, light) -> np.ndarray:
        """The straight-through fraction for light directions, interpolated as :meth:`evaluate`.

        Parameters
        ----------
        light : (K, 3) float

        Returns
        -------
        transparency : (K, 3) float64
        """
        light = _unit_queries(light, "light")
        index, weight = sphere_weights(self.light, light)
        return np.einsum("kn,knc->kc", weight, self.transparency[index].astype(np.float64))


def _validate(light, view, values, transparency, period, units, settings) -> None:
    """ValueError with the reason unless the arrays form a valid table (any dtype)."""
    if light.ndim != 2 or light.shape[1] != 3 or light.shape[0] == 0:
        raise ValueError(f"tabulated BSDF: light must have shape (L, 3), L > 0; got {light.shape}")
    if view.ndim != 2 or view.shape[1] != 3 or view.shape[0] == 0:
        raise ValueError(f"tabulated BSDF: view must have shape (V, 3), V > 0; got {view.shape}")
    expected = (light.shape[0], view.shape[0], 3)
    if values.shape != expected:
        raise ValueError(f"tabulated BSDF: values must have shape {expected}, got {values.shape}")
    if transparency.shape != (light.shape[0], 3):
        raise ValueError(f"tabulated BSDF: transparency must have shape {(light.shape[0], 3)}, "
                         f"got {transparency.shape}")
    if period.shape != (2,):
        raise ValueError(f"tabulated BSDF: period must have shape (2,), got {period.shape}")
    for key, array in (("light", light), ("view", view), ("values", values), ("transparency", transparency),
                       ("period", period)):
        if not np.all(np.isfinite(array)):
            raise ValueError(f"tabulated BSDF: {key} holds NaN or infinite values")
    _unit_rows(light, "light")
    _unit_rows(view, "view")
    if np.any(values < 0):
        raise ValueError("tabulated BSDF: values must be >= 0 (a BSDF is never negative)")
    if np.any(transparency < 0) or np.any(transparency > 1):
        raise ValueError("tabulated BSDF: transparency must be in [0, 1]")
    if np.any(period <= 0):
        raise ValueError(f"tabulated BSDF: period must be positive, got {period.tolist()}")
    if not isinstance(units, str) or not units:
        raise ValueError("tabulated BSDF: units must be a non-empty string")
    try:
        decoded = json.loads(settings)
    except (TypeError, ValueError) as error:
        raise ValueError(f"tabulated BSDF: settings must be a JSON object ({error})") from error
    if not isinstance(decoded, dict):
        raise ValueError("tabulated BSDF: settings must be a JSON object")


def save_tabulated(path: str, bsdf: TabulatedBSDF) -> str:
    """Write ``bsdf`` to ``path`` (``.npz``) atomically; returns the path.

    Refuses (ValueError) non-finite values, which :class:`TabulatedBSDF` already refuses.
    """
    arrays = {key: getattr(bsdf, key) for key in _ARRAY_KEYS}
    _validate(*arrays.values(), bsdf.units, bsdf.settings)
    content = {
        "format": np.array(FORMAT_NAME),
        "version": np.array(FORMAT_VERSION, np.int64),
        **{key: array.astype(array.dtype.newbyteorder("<")) for key, array in arrays.items()},
        "units": np.array(bsdf.units),
        "settings": np.array(bsdf.settings),
        "checksum": np.array(checksum(*arrays.values(), bsdf.units, bsdf.settings)),
    }
    path = os.path.abspath(path)
    # A stream, not a name: np.savez_compressed would append ".npz" to a temporary name.
    with atomic_file(path) as stream:
        np.savez_compressed(stream, **content)
    return path


class _Refused(ValueError):
    """A reason already worded for the user (as opposed to a damaged archive's exception)."""


def _scalar(archive, key: str, kind: str, path: str):
    array = archive[key]
    if array.shape != () or array.dtype.kind != kind:
        raise _Refused(f"{path}: {key!r} must be a single {'string' if kind == 'U' else 'integer'}")
    return array.item()


def load_tabulated(path: str) -> TabulatedBSDF:
    """Read and check a ``visibake-bsdf`` file.

    Raises ValueError, naming the file and the reason, for: not an npz archive, another
    format or version, missing keys, wrong shapes or dtypes, non-unit directions, NaN or
    infinite values, a checksum that does not match.

    Returns
    -------
    bsdf : :class:`TabulatedBSDF`
    """
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"{path} is not a readable .npz archive ({error})") from error
    if not hasattr(archive, "files"):
        raise ValueError(f"{path} holds a single array, not a {FORMAT_NAME} archive")
    with archive:
        if "format" not in archive.files:
            raise ValueError(f"{path} is not a {FORMAT_NAME} file (it has no 'format' entry)")
        try:
            name = _scalar(archive, "format", "U", path)
            if name != FORMAT_NAME:
                raise _Refused(f"{path} is a {name!r} file, not {FORMAT_NAME!r}")
            missing = [key for key in _KEYS if key not in archive.files]
            if missing:
                raise _Refused(f"{path} lacks the entries {missing}")
            version = _scalar(archive, "version", "i", path)
            if version != FORMAT_VERSION:
                raise _Refused(f"{path} is {FORMAT_NAME} version {version}; this VisiBake reads version "
                               f"{FORMAT_VERSION}")
            arrays = {key: archive[key] for key in _ARRAY_KEYS}
            units = _scalar(archive, "units", "U", path)
            settings = _scalar(archive, "settings", "U", path)
            stored = _scalar(archive, "checksum", "U", path)
        except _Refused:
            raise
        except (ValueError, KeyError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
            # Entries are decompressed as they are read: a damaged archive shows only here.
            raise ValueError(f"{path}: damaged {FORMAT_NAME} archive ({error})") from error
    for key, array in arrays.items():
        wanted = np.float64 if key == "period" else np.float32
        if array.dtype != np.dtype(wanted):
            raise ValueError(f"{path}: {key!r} must be {np.dtype(wanted).name}, got {array.dtype}")
    try:
        _validate(*arrays.values(), units, settings)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from error
    if checksum(*arrays.values(), units, settings) != stored:
        raise ValueError(f"{path}: checksum does not match its content (the file is damaged or was edited)")
    return TabulatedBSDF(**arrays, units=units, settings=settings)
