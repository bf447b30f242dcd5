"""Ray tracing through embreex: robust origins, batched threaded queries.

Embree's ``tnear`` is fixed at 0 in embreex, so every origin is pushed off its
surface here with the integer-ULP offset of Waechter & Binder (Ray Tracing Gems,
ch. 6), which stays robust at any distance from the world origin where a fixed
epsilon does not.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import tolerances as tol
from . import embree_shared


def offset_ray_origins(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Move points off their surface along ``normals`` by a few float ULPs.

    Parameters
    ----------
    points : (n, 3) float
        Points on the surface (world space).
    normals : (n, 3) float
        Unit geometric normals on the side the rays leave from.

    Returns
    -------
    origins : (n, 3) float32
    """
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    int_offset = (tol.RAY_OFFSET_INT_SCALE * n).astype(np.int32)
    bits = p.view(np.int32)
    stepped = np.where(p < 0, bits - int_offset, bits + int_offset).astype(np.int32).view(np.float32)
    near_origin = p + np.float32(tol.RAY_OFFSET_FLOAT_SCALE) * n
    return np.where(np.abs(p) < tol.RAY_OFFSET_ORIGIN, near_origin, stepped).astype(np.float32)


def default_threads() -> int:
    return max(1, os.cpu_count() or 1)


class RayScene:
    """An embree scene of several meshes; geometry ids are the mesh order.

    Parameters
    ----------
    meshes : list of ((n, 3) float, (m, 3) int) pairs
        World-space positions and triangles of each mesh.
    threads : int
        Worker threads (embree releases the GIL during a query).
    centre : (3,) float or None
        Embree traces in float32, which far from the world origin cannot resolve a
        small object (1e5 units: steps of 0.008). The scene is held relative to
        ``centre``, and every query's origins are moved into that frame in float64, so
        precision depends on the scene's extent, not on where it lies. Queries still
        take world-space origins; :meth:`ray_origins` makes ones that keep that precision.
    """

    def __init__(self, meshes, threads: int = 0, centre=None):
        from embreex.mesh_construction import TriangleMesh

        self._scene, self._device = embree_shared.new_scene()
        self._meshes = []
        self._positions = []
        self._triangles = []
        self.centre = np.zeros(3) if centre is None else np.asarray(centre, np.float64).reshape(3)
        for positions, triangles in meshes:
            indices = np.ascontiguousarray(triangles, dtype=np.int32)
            if len(indices) == 0:
                # embree rejects empty buffers; a single degenerate triangle keeps
                # geometry ids aligned with mesh indices and is never hit.
                vertices = embree_shared.padded_vertices(np.zeros((3, 3)))
                indices = np.array([[0, 1, 2]], np.int32)
            else:
                vertices = embree_shared.padded_vertices(self.local(positions))
            # Embree reads the arrays kept below where they lie (embree_shared); else embreex copies them.
            if embree_shared.attach(self._scene, self._device, vertices, indices) is None:
                self._meshes.append(_triangle_mesh(TriangleMesh, self._scene, vertices, indices))
            self._positions.append(vertices)
            self._triangles.append(indices)
        self.threads = threads or default_threads()
        # embreex builds the BVH on a scene's first query: build it now, so that it is timed
        # where the scene is made (a bake's "bvh" stage), not in whichever pass traces first,
        # and so that threads starting queries at once never race to build it.
        self._scene.run(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))

    def subset(self, indices) -> RayScene | None:
        """A scene of only the geometries ``indices`` (a lamp's shadow blockers); None if empty.

        embreex exposes neither ray masks nor filter callbacks, so a lamp whose shadows only
        some objects may cast gets a scene of its own. Geometry ids are renumbered.
        """
        indices = [int(i) for i in indices]
        if not indices:
            return None
        # Back to world space in float64 (exact for float32 vertices) so the subset keeps this scene's frame.
        return RayScene([(self._positions[i].astype(np.float64) + self.centre, self._triangles[i]) for i in indices],
                        self.threads, self.centre)

    def positions(self, index: int) -> np.ndarray:
        """(n, 3) float32 vertices of geometry ``index`` as embree holds them (relative to :attr:`centre`)."""
        return self._positions[index]

    def local(self, points) -> np.ndarray:
        """World-space ``points`` in the frame embree traces in (float64 until the caller casts)."""
        if not self.centre.any():
            return points
        with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices stay so; never hit
            return np.asarray(points, np.float64) - self.centre

    def ray_origins(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """:func:`offset_ray_origins` of world-space ``points``, offset in the traced frame.

        Returns (n, 3) float32 when the scene is not recentred (``centre`` zero), else
        float64 world positions that this scene's queries turn back into the exact
        float32 origins of its frame.
        """
        if not self.centre.any():
            return offset_ray_origins(points, normals)
        return offset_ray_origins(self.local(points), normals).astype(np.float64) + self.centre

    def intersect(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray | None = None):
        """Nearest hit of each ray (before ``distances`` (n,) when given; default: infinity).

        Returns
        -------
        geometry : (n,) int32, -1 for a miss
        triangle : (n,) int32
        barycentric_uv : (n, 2) float32, embree's (u, v): hit = (1-u-v) p0 + u p1 + v p2
        distance : (n,) float32 along the (unit) direction, inf for a miss
        """
        return self.intersect_local(np.ascontiguousarray(self.local(origins), np.float32),
                                    np.ascontiguousarray(directions, np.float32), distances)

    def intersect_local(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray | None = None,
                        out: tuple | None = None):
        """:meth:`intersect` of rays whose ``origins`` (n, 3) float32 are in this scene's frame
        already (core.visibility.table.TraceRequest.rays). ``out``: the four result arrays
        to write into (core.visibility.table.RayBuffers.hits), else new ones."""
        count = len(origins)
        if out is None:
            out = (np.empty(count, np.int32), np.empty(count, np.int32), np.empty((count, 2), np.float32),
                   np.empty(count, np.float32))
        geometry, triangle, bary, distance = out

        def run(a, b):
            found = self.intersect_here(origins[a:b], directions[a:b],
                                        None if distances is None else distances[a:b])
            geometry[a:b] = found["geomID"]
            triangle[a:b] = found["primID"]
            bary[a:b, 0] = found["u"]
            bary[a:b, 1] = found["v"]
            distance[a:b] = found["tfar"]
            np.copyto(distance[a:b], np.float32(np.inf), where=found["geomID"] < 0)

        run_in_spans(run, count, self.threads)
        return geometry, triangle, bary, distance

    def intersect_here(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray | None = None
                       ) -> dict:
        """Embree's nearest hits of the rays ``origins``, ``directions`` (n, 3) float32 (in this
        scene's frame) on the calling thread, as embreex returns them: a dict of (n,) arrays
        ``geomID`` (int32, -1 for a miss), ``primID`` (int32), ``u``, ``v`` (float32 barycentrics:
        hit = (1-u-v) p0 + u p1 + v p2) and ``tfar`` (float32, the distance; undefined for a miss)."""
        kwargs = {} if distances is None else {"dists": np.ascontiguousarray(distances, np.float32)}
        return self._scene.run(origins, directions, output=1, **kwargs)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray | None = None) -> np.ndarray:
        """Whether anything lies on each ray before ``distances`` (default: infinity).

        Returns
        -------
        occluded : (n,) bool
        """
        count = len(origins)
        result = np.empty(count, bool)

        def run(a, b):
            kwargs = {}
            if distances is not None:
                kwargs["dists"] = np.ascontiguousarray(distances[a:b], np.float32)
            hits = self._scene.run(np.ascontiguousarray(self.local(origins[a:b]), np.float32),
                                   np.ascontiguousarray(directions[a:b], np.float32),
                                   query="OCCLUDED", **kwargs)
            result[a:b] = hits >= 0

        run_in_spans(run, count, self.threads)
        return result


def _triangle_mesh(triangle_mesh, scene, vertices: np.ndarray, indices: np.ndarray):
    """embreex's ``TriangleMesh(scene, vertices, indices)`` of (n, 3) float32 ``vertices`` and
    (m, 3) int32 ``indices``, with the same buffers, built 1.7x faster: where a mesh cannot be
    handed to embree without a copy (core.visibility.embree_shared).

    embreex copies both arrays into embree's buffers element by element through untyped
    indexing: ``indices[i][0]`` makes a numpy view of row ``i`` before reading it, 1.2 us a
    triangle (0.24 s of a 200k-triangle mesh's 0.31 s). Rows that are Python lists in a 1-D
    object array are read without one, and vertices as Python floats (exact: they are float32
    values) without a numpy scalar each. Making those objects costs less than the views they
    save, once the cyclic garbage collector, which every few hundred new containers would walk
    the whole process's objects, is held off while they live (docs/benchmarks.md, part 14)."""
    import gc

    collecting = gc.isenabled()
    gc.disable()
    try:
        return triangle_mesh(scene, vertices.astype(object),
                             np.fromiter(indices.tolist(), dtype=object, count=len(indices)))
    finally:
        if collecting:
            gc.enable()


def run_in_spans(function, count: int, threads: int) -> None:
    """``function(a, b)`` on consecutive spans [a, b) covering [0, count), at most one per
    thread of ``threads`` (0: all cores), each at least 4096 items long, at once
    (:func:`run_together`): for work that releases the GIL (embree's queries, the serial kernels)."""
    threads = threads or default_threads()
    parts = min(threads, max(1, count // 4096))
    bounds = np.linspace(0, count, parts + 1).astype(np.int64)
    spans = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    run_together([lambda a=a, b=b: function(a, b) for a, b in spans])


# The helper threads run_together keeps. A bake calls it about a hundred times (every shadow-ray
# batch, every span of the trace), and a pool made and joined per call cost 0.2 ms of thread
# starts each time (docs/benchmarks.md, speed part 20).
_helpers_lock = threading.Lock()
_helpers: ThreadPoolExecutor | None = None
_helper_count = 0
_this_thread = threading.local()


def _mark_helper() -> None:
    _this_thread.is_helper = True


def run_together(calls: list) -> list:
    """Each of ``calls`` (callables without arguments) at once: the first on the calling thread,
    the others on kept helper threads. Returns their results in order; once every call has
    ended, raises the first call's error, if any. A call made on a helper thread runs its
    calls one after the other there, so a helper never waits for another helper."""
    if len(calls) <= 1 or getattr(_this_thread, "is_helper", False):
        return [call() for call in calls]
    futures = _on_helpers(calls[1:])
    first, error = None, None
    try:
        first = calls[0]()
    except BaseException as raised:  # the helpers' calls read buffers the caller owns: let them end first
        error = raised
    results = [first]
    for future in futures:
        try:
            results.append(future.result())
        except BaseException as raised:
            error = error or raised
            results.append(None)
    if error is not None:
        raise error
    return results


def _on_helpers(calls: list) -> list:
    """Futures of ``calls`` submitted to the kept helper threads, at least as many as calls.
    Under the lock, so that no other thread lets the pool go between choosing and submitting."""
    global _helpers, _helper_count
    with _helpers_lock:
        if _helpers is None or _helper_count < len(calls):
            if _helpers is not None:
                _helpers.shutdown(wait=False)  # its threads end once idle; what it was given still runs
            _helpers = ThreadPoolExecutor(len(calls), thread_name_prefix="visibake-helper", initializer=_mark_helper)
            _helper_count = len(calls)
        return [_helpers.submit(call) for call in calls]


def stop_helpers() -> None:
    """End the kept helper threads (the extension unregistering); the next call starts new ones."""
    global _helpers, _helper_count
    with _helpers_lock:
        if _helpers is not None:
            _helpers.shutdown(wait=False)
        _helpers, _helper_count = None, 0
