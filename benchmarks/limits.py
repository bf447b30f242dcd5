"""What the libraries underneath can do, measured on the same data as a bake.

Each VisiBake stage is reported as a fraction of these: embreex tracing rays from
prebuilt arrays with no VisiBake code around it, and numpy gathering table entries.
"""
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np


def embree_rays_per_second(meshes, count: int = 4_000_000, threads: int = 2) -> float:
    """embreex alone: rays from random surface points into their upper hemisphere, traced on a
    scene whose BVH is built first (untimed, as a bake builds it in its "bvh" stage).

    Parameters
    ----------
    meshes : objects with ``positions`` (n, 3) and ``triangles`` (m, 3), world space
    """
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    scene = EmbreeScene()
    for mesh in meshes:
        TriangleMesh(scene, np.ascontiguousarray(mesh.positions, np.float32),
                     np.ascontiguousarray(mesh.triangles, np.int32))
    rng = np.random.default_rng(0)
    corners = np.concatenate([m.positions[m.triangles] for m in meshes])
    with np.errstate(invalid="ignore"):
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        length = np.linalg.norm(normals, axis=1)
    usable = np.nonzero(np.isfinite(length) & (length > 0))[0]
    pick = usable[rng.integers(0, len(usable), count)]
    a, b = rng.random((2, count, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    c = corners[pick]
    n = normals[pick] / length[pick, None]
    origins = (c[:, 0] + a * (c[:, 1] - c[:, 0]) + b * (c[:, 2] - c[:, 0]) + 1e-4 * n).astype(np.float32)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    directions = np.where(np.sum(directions * n, axis=1, keepdims=True) < 0, -directions, directions)
    directions = directions.astype(np.float32)
    spans = np.array_split(np.arange(count), threads)
    scene.run(origins[:0], directions[:0])  # the BVH: embreex builds it on the first query
    started = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(lambda span: scene.run(origins[span], directions[span], output=1), spans))
    return count / (time.perf_counter() - started)


def numpy_gather_lookups_per_second(texels: int, directions: int, atlas_texels: int, repeats: int = 3) -> float:
    """numpy alone: one RGB float32 fetch per (direction, texel), random addresses.

    The same number of lookups as one gather over a table of ``directions`` x
    ``texels`` entries into atlases of ``atlas_texels`` texels, with no weights, no
    bilinear filter and no bookkeeping: the ceiling for the gather stage. The best
    of ``repeats`` runs of one direction's worth of lookups is scaled up.
    """
    rng = np.random.default_rng(0)
    flat = rng.random((max(atlas_texels, 1), 3), dtype=np.float32)
    index = rng.integers(0, len(flat), texels)
    accumulator = np.zeros((texels, 3), np.float32)
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        accumulator += np.take(flat, index, axis=0)
        best = min(best, time.perf_counter() - started)
    return texels / best


def bare_lookup_call(kernels, table, geometry, radiance: np.ndarray, threads: int = 0):
    """A call of the same table walk as the compiled gather (same blocks, threads and table
    reads) with one nearest-texel read per hit entry and no weights, filter or bookkeeping
    (core.kernels.transport_kernels.bare_lookup); None where the kernels cannot load.

    kernels : the extension's core.kernels module
    radiance : (layout.size, C) float32, the atlas the gather reads
    threads : 0 for the gather's own (geometry.threads)
    """
    module = kernels.compiled()
    if module is None:
        return None
    layout = geometry.layout
    radiance = np.ascontiguousarray(radiance, np.float32)
    samples = np.arange(len(geometry.normals), dtype=np.int64)
    out = np.zeros((len(samples), radiance.shape[1]))
    entries = table.entries
    arguments = (entries.above_words, entries.word_base, entries.hit_object, entries.hit_uv_code, samples, 0,
                 len(table.directions), radiance, layout.widths.astype(np.int64),
                 layout.heights.astype(np.int64), layout.offsets.astype(np.int64), out)
    return lambda: kernels.run(module.bare_lookup, threads or geometry.threads, *arguments)


def reset_peak_memory() -> bool:
    """Start a new resident-memory high-water mark (Linux: /proc/self/clear_refs).

    Without it, a sweep in one process could only report the peak of every run so far.
    Returns False where the mark cannot be reset.
    """
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


def peak_memory_bytes() -> int:
    """Resident-memory high-water mark since :func:`reset_peak_memory` (VmHWM), else 0."""
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0
