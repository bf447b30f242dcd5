"""A volume's scattering tables in the visibility cache (core.visibility.cache), so that a
bake after a change of lamps, world, colour or emission reads them instead of marching
them again (the paper's point: visibility once, then lighting by lookups).

Each volume has a slot of its own, named after the scene's label, the volume's name and
the table settings (direction count and seed, points per ray, march step). The slot holds
the tables of its last bake and the key they were built for: a hash of everything an
entry depends on (the density grid and its placement, the material's Density, the
directions, the occluding meshes, the format). A bake whose key differs marches the tables
again and replaces the file.
"""
from __future__ import annotations

import hashlib
import json

import numpy as np

from ..visibility.cache import CacheFull, CorruptCache, arrays_key
from .medium import Medium
from .occluders import SurfaceMesh
from .tables import ScatteringTables

# Bump whenever a stored array's meaning changes (the kernels' codes, the hash of points).
FORMAT = 1
_ARRAYS = ("directions", "index_directions", "world_per_index", "voxels", "distance_codes", "escape_codes")


def slot_key(volume: str, directions: int, seed: int, points: int, step: float) -> str:
    """Hex name of a volume's slot (one per volume and table settings)."""
    text = json.dumps([volume, int(directions), int(seed), int(points), float(step)])
    return hashlib.blake2b(text.encode("utf-8", "surrogatepass"), digest_size=8).hexdigest()


def table_key(medium: Medium, directions: np.ndarray, points: int, step: float, jitter_seed: int | None,
              meshes: list) -> str:
    """Hash of what every table entry depends on.

    meshes : the occluders as Occluders.from_meshes takes them; only the geometry that ends
        table rays is hashed, since a mesh's shadows and colours do not enter the tables
    """
    seen = [m for m in map(SurfaceMesh.of, meshes) if m.seen_by_scattering]
    geometry = [part for m in seen for part in (np.asarray(m.positions, np.float64), np.asarray(m.triangles, np.int32))]
    return arrays_key(FORMAT, medium.density, medium.index_to_world, float(medium.extinction),
                      np.asarray(directions, np.float64), int(points), float(step), jitter_seed, len(seen),
                      *geometry)


def to_arrays(tables: ScatteringTables) -> dict:
    """The arrays of ``tables`` as the cache stores them."""
    arrays = {name: getattr(tables, name) for name in _ARRAYS}
    arrays["scalars"] = np.array([tables.distance_per_code, tables.step], np.float64)
    arrays["jitter_seed"] = np.array([-1 if tables.jitter_seed is None else tables.jitter_seed], np.int64)
    if tables.sees_world is not None:
        arrays["sees_world"] = np.packbits(tables.sees_world, axis=1)
    return arrays


def from_arrays(arrays: dict, medium: Medium, directions: np.ndarray, points: int) -> ScatteringTables:
    """The tables of a cache file, checked against what the bake expects (raises CorruptCache)."""
    try:
        voxels = np.asarray(arrays["voxels"])
        count = len(directions)
        codes = np.asarray(arrays["distance_codes"])
        escape = np.asarray(arrays["escape_codes"])
        distance_per_code, step = (float(v) for v in arrays["scalars"])
        seed = int(arrays["jitter_seed"][0])
        sees_world = None
        if "sees_world" in arrays:
            sees_world = np.unpackbits(arrays["sees_world"], axis=1, count=len(voxels)).astype(bool)
    except (KeyError, ValueError, TypeError, IndexError) as error:
        raise CorruptCache(f"its arrays are malformed ({error})") from None
    if voxels.dtype != np.int32 or not np.array_equal(voxels, medium.active()) \
            or codes.dtype != np.uint16 or codes.shape != (count, len(voxels), points) \
            or escape.dtype != np.uint16 or escape.shape != (count, len(voxels)) \
            or not np.array_equal(arrays["directions"], directions) \
            or (sees_world is not None and sees_world.shape != escape.shape):
        raise CorruptCache("its arrays do not match its key")
    return ScatteringTables(np.asarray(arrays["directions"]), np.asarray(arrays["index_directions"]),
                            np.asarray(arrays["world_per_index"]), voxels, codes, escape, distance_per_code, step,
                            None if seed < 0 else seed, sees_world)


def cached_tables(cache, volume_name: str, medium: Medium, directions: np.ndarray, points: int,
                  step: float, jitter_seed: int | None, meshes: list, build, warnings: list[str]):
    """The tables of ``medium`` from ``cache`` (a core.visibility.cache.VisibilityCache, or
    None) when they were stored for the same key, else ``build()`` and stored.

    volume_name : the volume's name (its slot is named after it and the table settings)
    build : () -> ScatteringTables
    Returns (tables, how) with how 'cached', 'built' or 'built, not cached'.
    """
    if cache is None:
        return build(), "built"
    seed = -1 if jitter_seed is None else int(jitter_seed)
    slot = cache.volume_slot(slot_key(volume_name, len(directions), seed, points, step))
    key = table_key(medium, directions, points, step, jitter_seed, meshes)
    try:
        found = cache.load_volume_tables(slot, key)
        if found is not None:
            return from_arrays(found[1], medium, directions, points), "cached"
    except CorruptCache as error:
        warnings.append(f"volume {medium.name!r}: its cached scattering tables were not used ({error}); "
                        "they were built again")
    tables = build()
    try:
        cache.save_volume_tables(slot, key, volume_name, to_arrays(tables))
    except (CacheFull, OSError) as error:
        warnings.append(f"volume {medium.name!r}: its scattering tables were not cached ({error})")
        return tables, "built, not cached"
    return tables, "built"
