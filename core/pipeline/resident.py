"""The last preparation kept in memory between bakes of one session (a running Blender, a script).

Relighting changes only lights and world. A preparation (samples, footprints, the table and
what is derived from it: gather weights, contacts, near hits) depends on neither, so a
Relight that finds the same geometry, materials and settings as the last bake reuses it:
no table is read from disk, no sample placed again. One preparation is kept, and only while
it fits the memory bound the user sets (the preference Resident Memory).
"""
from __future__ import annotations

import gc
import threading
from dataclasses import asdict, fields

import numpy as np

from ..scene import Scene
from ..settings import BakeSettings
from ..visibility.cache import CacheStatus, arrays_key, object_key
from .prepare import Prepared, prepare

# Settings that do not change what a preparation holds: how many threads computed it.
_NOT_IN_KEY = {"threads"}

_lock = threading.Lock()
_kept: tuple[str, Prepared, int] | None = None  # (key, preparation, bytes)


def preparation_key(scene: Scene, settings: BakeSettings, table_needed: bool | None, cache) -> str:
    """Hash of everything :func:`core.pipeline.prepare.prepare` reads besides the lights and
    the world: every mesh's geometry, layout, materials and flags, the settings, and where the
    cache is (a relight writes its lighting cache there)."""
    values = asdict(settings)
    parts = [repr(sorted((k, repr(v)) for k, v in values.items() if k not in _NOT_IN_KEY)), repr(table_needed),
             "" if cache is None else str(cache.folder)]
    for mesh in scene.meshes:
        parts += [object_key(mesh), mesh.name, mesh.output, mesh.light_group, mesh.mode, mesh.casts_shadow,
                  float(mesh.terminator_offset), mesh.vertex_count, mesh.loop_count, mesh.bake_uv_map,
                  np.asarray(mesh.corner_normals, np.float32), np.asarray(mesh.material_index, np.int64)]
        if mesh.corner_loops is not None:
            parts.append(np.asarray(mesh.corner_loops, np.int64))
        for name in sorted(mesh.uv_maps):
            parts += [name, np.asarray(mesh.uv_maps[name], np.float32)]
        for material in mesh.materials:
            if material is None:
                parts.append(None)
                continue
            parts += [material.name, np.asarray(material.base_color, np.float64), material.texture_uv_map,
                      np.asarray(material.emission, np.float64)]
            if material.base_color_texture is not None:
                parts.append(np.asarray(material.base_color_texture, np.float32))
    if settings.shadows == "fractions":
        # Its warnings name the lamps that shadow fractions cannot treat as linked.
        parts += [(light.name, light.casts_shadows, light.blockers) for light in scene.lights]
    return arrays_key(*parts)


def prepared_bytes(p: Prepared) -> int:
    """Memory a preparation holds in arrays (a cached table counted as loaded: the relight reads it)."""
    arrays = []
    for spec in fields(p):
        value = getattr(p, spec.name)
        arrays.extend(value if isinstance(value, tuple) else (value,))
    for samples in p.object_samples:
        arrays.extend(vars(samples).values())
    # Each buffer once: the objects' footprints are views into the concatenated ones.
    owners = {}
    for array in arrays:
        if isinstance(array, np.ndarray):
            while isinstance(array.base, np.ndarray):
                array = array.base
            owners[id(array)] = array.nbytes
    return int((p.table.nbytes if p.table is not None else 0) + sum(owners.values()))


def prepare_or_reuse(scene: Scene, settings: BakeSettings, progress=None, table_needed: bool | None = None,
                     cache=None, require_cached_table: bool = False, keep_bytes: int = 0,
                     reuse: bool = True) -> Prepared:
    """:func:`core.pipeline.prepare.prepare`, or the preparation kept from the last bake of
    this session when nothing it depends on has changed.

    keep_bytes : the memory bound: the new preparation is kept for the next bake if it holds
        at most this many bytes (0: nothing is kept, and what was kept is let go)
    reuse : whether a kept preparation may serve this bake (a Relight); False prepares anew
        (a Bake checks the cache and the geometry again) and keeps the result

    A reused preparation reports no stage times and no rays, says in ``skipped`` what it
    spared, and its cache state is 'resident'.
    """
    global _kept
    # Without a bound nothing is reused or kept, so no key is needed: it hashes every mesh's
    # arrays (54 ms of a 200k-triangle mesh's 0.5 s bake; docs/benchmarks.md, speed part 17).
    key = preparation_key(scene, settings, table_needed, cache) if keep_bytes > 0 else None
    with _lock:
        kept = _kept
        if keep_bytes <= 0:
            _kept = None
    if (reuse and kept is not None and kept[0] == key and keep_bytes > 0
            and (kept[1].table is not None or not table_needed)):
        _, p, size = kept
        original = p.cache_status
        p.stage_seconds = {}
        p.visibility_rays = 0
        p.skipped = [s for s in p.skipped if not s.startswith("samples and visibility:")] + [
            f"samples and visibility: geometry, materials and settings unchanged since the last bake in this "
            f"session; its preparation was kept in memory ({size / 2**20:.0f} MiB)"]
        p.cache_status = CacheStatus(state="resident", path=original.path if original else "",
                                     message="the table was kept in memory since the last bake",
                                     bytes_on_disk=original.bytes_on_disk if original else 0)
        return p
    # Let the old one go before a new preparation needs the memory.
    with _lock:
        _kept = None
    if kept is not None:
        del kept
        _collect_cycles()
    p = prepare(scene, settings, progress, table_needed=table_needed, cache=cache,
                require_cached_table=require_cached_table)
    if keep_bytes > 0:
        size = prepared_bytes(p)
        if size <= keep_bytes:
            p.resident = True
            # What relights keep (core.pipeline.light_memo) stays within the same bound.
            p.light_memo.limit_bytes = min(p.light_memo.limit_bytes, keep_bytes - size)
            with _lock:
                _kept = (key, p, size)
        else:
            p.skipped.append(f"keeping this preparation in memory for the next relight: it holds "
                             f"{size / 2**20:.0f} MiB, more than Resident Memory allows "
                             f"({keep_bytes / 2**20:.0f} MiB)")
    return p


def forget() -> None:
    """Let the kept preparation go (unregistering, or a test that wants a cold bake)."""
    global _kept
    with _lock:
        kept, _kept = _kept, None
    if kept is not None:
        del kept
        _collect_cycles()


def _collect_cycles() -> None:
    """Free a preparation let go now, not at the garbage collector's next full pass: it refers
    to itself (its sample set holds its bound dense_footprint), so dropping the last outside
    reference frees nothing, and the next bake, which makes few Python objects, may run for
    long before the collector does. A second Bake held both (docs/benchmarks.md, speed part 21)."""
    gc.collect()
