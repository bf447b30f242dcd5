"""A mesh handed to embree as it lies in memory, without embreex's copy.

embreex's ``TriangleMesh`` copies vertices and triangles into embree's buffers one element at
a time through Python indexing: 0.2 s of a 200k-triangle mesh, the largest fixed cost of a bake
of a dense mesh (docs/benchmarks.md, speed parts 14 and 17). Embree itself can read a mesh from
the caller's arrays (``rtcSetSharedGeometryBuffer``), but embreex does not expose it, nor its
scene's handle. This module calls the embree library embreex loaded (through ctypes) to attach
such a geometry to an embreex scene, whose queries then run as before.

The scene's handle is read from the embreex object's fields, which is only done where the
layout is the one expected (embreex is pinned) and proves itself: the object's device field must
be the device this module made the scene with, embree must name that device as the scene's, and
once per process a one-triangle scene built this way must answer a ray as embree should.
Anything else (another embreex, a library not found, an embree error) falls back to embreex's
copy, which gives the same hits: embree reads the same float32 values either way.
"""
from __future__ import annotations

import ctypes
import glob
import os
import threading

import numpy as np

# embree 4's rtcore_common.h and rtcore_geometry.h
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_ERROR_NONE = 0
# embreex 4.4's objects: PyObject's two words, then EmbreeScene's scene handle, its
# is_committed flag (an int padded to a word) and its EmbreeDevice; EmbreeDevice's handle.
_SCENE_BASICSIZE, _SCENE_HANDLE_WORD, _SCENE_DEVICE_WORD = 40, 2, 4
_DEVICE_BASICSIZE, _DEVICE_HANDLE_WORD = 24, 2

_lock = threading.Lock()
_state: dict = {}  # "library": the ctypes library or None; "proven": bool, once checked


def _library():
    """The embree 4 library embreex loaded, its calls typed; None where it is not found."""
    if "library" in _state:
        return _state["library"]
    library = None
    try:
        import embreex

        package = os.path.dirname(os.path.abspath(embreex.__file__))
        # Where the wheels' repair tools put it: auditwheel (Linux), delvewheel (Windows), delocate (macOS).
        patterns = (os.path.join(package, os.pardir, "embreex.libs", "*embree4*"),
                    os.path.join(package, ".dylibs", "*embree4*"), os.path.join(package, "*embree4*"))
        found = sorted(path for pattern in patterns for path in glob.glob(pattern))
        if found:
            library = ctypes.CDLL(os.path.abspath(found[0]))
            pointer, size, unsigned = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint
            for name, restype, argtypes in (
                    ("rtcNewGeometry", pointer, [pointer, ctypes.c_int]),
                    ("rtcSetSharedGeometryBuffer", None, [pointer, ctypes.c_int, unsigned, ctypes.c_int, pointer,
                                                          size, size, size]),
                    ("rtcCommitGeometry", None, [pointer]),
                    ("rtcAttachGeometry", unsigned, [pointer, pointer]),
                    ("rtcReleaseGeometry", None, [pointer]),
                    ("rtcGetDeviceError", ctypes.c_int, [pointer]),
                    ("rtcGetSceneDevice", pointer, [pointer]),
                    ("rtcReleaseDevice", None, [pointer])):
                function = getattr(library, name)
                function.restype, function.argtypes = restype, argtypes
    except (ImportError, OSError, AttributeError):
        library = None
    _state["library"] = library
    return library


def new_scene():
    """(an embreex EmbreeScene, its EmbreeDevice): the device made here, so that the scene's
    fields can be checked against it (:func:`attach`)."""
    from embreex.rtcore import EmbreeDevice
    from embreex.rtcore_scene import EmbreeScene

    device = EmbreeDevice()
    return EmbreeScene(device), device


def _handles(scene, device) -> tuple[int, int] | None:
    """(scene handle, device handle) of the embreex ``scene`` made with ``device``; None unless
    the objects' layout is the one expected and embree agrees that the scene is the device's."""
    library = _library()
    if library is None or type(scene).__basicsize__ != _SCENE_BASICSIZE \
            or type(device).__basicsize__ != _DEVICE_BASICSIZE:
        return None
    scene_words = (ctypes.c_void_p * (_SCENE_BASICSIZE // 8)).from_address(id(scene))
    if scene_words[_SCENE_DEVICE_WORD] != id(device):
        return None
    device_handle = (ctypes.c_void_p * (_DEVICE_BASICSIZE // 8)).from_address(id(device))[_DEVICE_HANDLE_WORD]
    scene_handle = scene_words[_SCENE_HANDLE_WORD]
    if not scene_handle or not device_handle:
        return None
    named = library.rtcGetSceneDevice(scene_handle)  # a new reference to the device
    if named:
        library.rtcReleaseDevice(named)
    return (scene_handle, device_handle) if named == device_handle else None


def padded_vertices(vertices: np.ndarray) -> np.ndarray:
    """(n, 3) ``vertices`` (any float dtype, rounded to float32 as ``astype`` rounds) in a float32
    array with one float more after them: embree reads a shared vertex buffer with 16-byte loads,
    so its last vertex needs 4 bytes of padding. Returns the (n, 3) view; its base holds the padding."""
    padded = np.zeros(3 * len(vertices) + 1, np.float32)
    view = padded[:3 * len(vertices)].reshape(-1, 3)
    view[...] = vertices
    return view


def _padded(vertices: np.ndarray) -> bool:
    """Whether 4 bytes of the array owning ``vertices`` follow its last vertex."""
    owner = vertices
    while isinstance(owner.base, np.ndarray):
        owner = owner.base
    return vertices.ctypes.data + vertices.nbytes + 4 <= owner.ctypes.data + owner.nbytes


def _attach_unchecked(scene, device, vertices: np.ndarray, indices: np.ndarray) -> int | None:
    handles = _handles(scene, device)
    if handles is None:
        return None
    library = _library()
    scene_handle, device_handle = handles
    geometry = library.rtcNewGeometry(device_handle, _GEOMETRY_TYPE_TRIANGLE)
    if not geometry:
        return None
    try:
        library.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_VERTEX, 0, _FORMAT_FLOAT3,
                                           vertices.ctypes.data, 0, 12, len(vertices))
        library.rtcSetSharedGeometryBuffer(geometry, _BUFFER_TYPE_INDEX, 0, _FORMAT_UINT3,
                                           indices.ctypes.data, 0, 12, len(indices))
        library.rtcCommitGeometry(geometry)
        if library.rtcGetDeviceError(device_handle) != _ERROR_NONE:
            return None
        geometry_id = library.rtcAttachGeometry(scene_handle, geometry)
        if library.rtcGetDeviceError(device_handle) != _ERROR_NONE:
            raise RuntimeError("bug: embree failed to attach a committed geometry; the scene's geometry ids "
                               "no longer follow its meshes")
        return int(geometry_id)
    finally:
        library.rtcReleaseGeometry(geometry)  # the scene holds its own reference once attached


def _proven() -> bool:
    """Whether a one-triangle scene built by :func:`_attach_unchecked` answers a ray as embree
    should (checked once per process)."""
    if "proven" not in _state:
        proven = False
        try:
            scene, device = new_scene()
            vertices = padded_vertices(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32))
            indices = np.array([[0, 1, 2]], np.int32)
            if _attach_unchecked(scene, device, vertices, indices) == 0:
                found = scene.run(np.array([[0.25, 0.25, 1.0], [2.0, 2.0, 1.0]], np.float32),
                                  np.array([[0, 0, -1.0], [0, 0, -1.0]], np.float32), output=1)
                proven = (found["geomID"].tolist() == [0, -1] and int(found["primID"][0]) == 0
                          and abs(float(found["tfar"][0]) - 1.0) < 1e-6 and abs(float(found["u"][0]) - 0.25) < 1e-6
                          and abs(float(found["v"][0]) - 0.25) < 1e-6)
            del scene, device, vertices, indices
        except Exception:  # noqa: BLE001  (whatever went wrong, embreex's own copy still works)
            proven = False
        _state["proven"] = proven
    return _state["proven"]


def attach(scene, device, vertices: np.ndarray, indices: np.ndarray) -> int | None:
    """Attach the mesh ``vertices`` (n, 3) float32 (from :func:`padded_vertices`) and ``indices``
    (m, 3) int32 (C-contiguous) to the embreex ``scene`` made by :func:`new_scene` with ``device``,
    embree reading both arrays where they are: the caller keeps them alive, unchanged, for as
    long as the scene lives. Returns the geometry id, or None where this cannot be done here
    (then nothing was attached: use embreex's TriangleMesh)."""
    if vertices.dtype != np.float32 or indices.dtype != np.int32 or not indices.flags.c_contiguous \
            or not vertices.flags.c_contiguous or not _padded(vertices):
        return None
    with _lock:
        if not _proven():
            return None
        return _attach_unchecked(scene, device, vertices, indices)


def available() -> bool:
    """Whether meshes are attached without embreex's copy in this process."""
    with _lock:
        return _proven()
