"""A span of the table's rays set up, traced by embree and recorded in one compiled loop.

Imported only through :func:`core.kernels.embree`, once :mod:`core.visibility.embree_shared`
has bound embree's ``rtcIntersect1`` to :data:`INTERSECT_SYMBOL` (llvmlite's symbol table,
so that the cached kernel links to this process's library). Each ray is set up and recorded
by the very helpers of :func:`core.kernels.table_kernels.ray_setup` and ``record``, and embree
gets the ray embreex's query gives it (origin, direction, tnear 0, tfar 1e37, every mask bit):
the entries are bitwise those of the span tracer's three steps, without embreex's arrays per
span or the rays' round trip through memory between the steps.
"""
from __future__ import annotations

import numba as nb
import numpy as np
from numba import types

from . import SERIAL_OPTIONS
from .table_kernels import record_hit, record_miss, set_up_ray

INTERSECT_SYMBOL = "visibake_rtcIntersect1"
# void rtcIntersect1(RTCScene scene, RTCRayHit* rayhit, RTCIntersectArguments* args)
_intersect = types.ExternalFunction(INTERSECT_SYMBOL, types.void(types.voidptr, types.voidptr, types.voidptr))

# embree 4's RTCRayHit as 20 four-byte words (16-byte aligned): the ray's origin, tnear,
# direction, time, tfar, mask, id, flags; the hit's normal, u, v, primID, geomID, instID.
RAYHIT_WORDS = 20
_TNEAR, _TIME, _TFAR, _MASK, _ID, _FLAGS = 3, 7, 8, 9, 10, 11
_U, _V, _PRIM, _GEOM, _INST = 15, 16, 17, 18, 19
# embreex's default tfar (its query's "no distance")
_FAR = np.float32(1e37)


@nb.njit(**SERIAL_OPTIONS)
def trace_span(scene, rayhit, direction_index, sample_index, entry, positions, footprint, point_of_direction,
               geometric, frame_directions, group, centre, recentred, int_scale, float_scale, origin_limit,
               hit_object, hit_uv_code, hit_distance_code, triangle_offset, face_normals, corner_uv, vertex_cells,
               distance_splits, first_sample, backfaces):
    """Set up, trace and record the rays (direction_index[r], sample_index[r]) (n,) int64 into
    the entries ``entry`` (n,) int64, one ray at a time on the calling thread (the GIL let go).

    scene : embree's RTCScene handle (an integer), its BVH built
    rayhit : (RAYHIT_WORDS,) float32, 16-byte aligned, the thread's own
    positions ... origin_limit : table_kernels.ray_setup's arguments, and ``recentred`` (bool):
        whether the scene's frame is away from the world origin (set_up_ray)
    hit_object ... distance_splits : table_kernels.record's arguments
    first_sample : int64; backfaces : (m,) int32, in and out, or (0,) to count nothing
    """
    words = rayhit.view(np.int32)
    address = rayhit.ctypes.data
    counting = backfaces.shape[0] > 0
    for r in range(entry.shape[0]):
        s = sample_index[r]
        set_up_ray(direction_index[r], s, positions, footprint, point_of_direction, geometric, frame_directions,
                   group, centre, recentred, int_scale, float_scale, origin_limit, rayhit[0:3], rayhit[4:7])
        rayhit[_TNEAR] = 0.0
        rayhit[_TIME] = 0.0
        rayhit[_TFAR] = _FAR
        words[_MASK] = -1
        words[_ID] = 0
        words[_FLAGS] = 0
        words[_PRIM] = -1
        words[_GEOM] = -1
        words[_INST] = -1
        _intersect(scene, address, 0)
        e = entry[r]
        geometry = words[_GEOM]
        if geometry < 0:
            record_miss(hit_object, hit_uv_code, hit_distance_code, e)
            continue
        back = record_hit(hit_object, hit_uv_code, hit_distance_code, e, geometry, words[_PRIM], rayhit[_U],
                          rayhit[_V], rayhit[_TFAR], rayhit[4], rayhit[5], rayhit[6], triangle_offset, face_normals,
                          corner_uv, vertex_cells, distance_splits)
        if back and counting:
            backfaces[s - first_sample] += 1


def rayhit_buffer() -> np.ndarray:
    """A (RAYHIT_WORDS,) float32 array at a 16-byte aligned address (embree's RTCRayHit)."""
    raw = np.zeros(RAYHIT_WORDS + 4, np.float32)
    skip = (-raw.ctypes.data % 16) // 4
    return raw[skip:skip + RAYHIT_WORDS]


def warm_up(scene: int) -> None:
    """Compile (or read from the cache) :func:`trace_span` for the table's argument types by
    tracing one ray of ``scene`` (an RTCScene handle) into a throwaway entry."""
    from ..visibility.table import DISTANCE_SPLITS

    one = np.zeros(1, np.int64)
    trace_span(scene, rayhit_buffer(), one, one, one, np.zeros((1, 3)), np.zeros((1, 0, 3), np.float32), one,
               np.array([[0.0, 0.0, 1.0]]), np.array([[[0.0, 0.0, -1.0]]], np.float32), one, np.zeros(3), False,
               np.float32(256.0), np.float32(1.0 / 65536.0), np.float32(1.0 / 32.0), np.zeros(1, np.int16),
               np.zeros((1, 2), np.uint16), np.zeros(1, np.uint16), one, np.zeros((1, 3)),
               np.zeros((1, 3, 2), np.float32), one, DISTANCE_SPLITS, np.int64(0), np.zeros(0, np.int32))
