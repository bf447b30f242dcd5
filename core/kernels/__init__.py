"""Compiled CPU kernels (numba) for the table lookups, loaded once per process.

The kernels (:mod:`core.kernels.transport_kernels`) are the CPU twin of the GLSL passes.
Where numba cannot load (no wheel for the platform, a broken install, or
``VISIBAKE_KERNELS=numpy`` in the environment) the numpy passes of :mod:`core.transport`
run instead, and :func:`status` says so for the report.

Compiled code is cached on disk, in the folder given to :func:`configure` (Blender: the
extension's user folder; elsewhere the user's cache folder), never beside the sources:
an installed extension's folder may be read-only and is replaced on update. The first
load in a fresh cache compiles (seconds); later loads read the cache.

numba's portable threading layer (workqueue) is used on every platform: it needs no
OpenMP or TBB runtime beside Blender's own, but it must not be entered from two threads
at once, so every call goes through :func:`run`, which holds one lock. The bake calls the
kernels from its worker thread; the lock also covers a script calling from another.
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

# Which implementation runs the lookups: 'numba' (default) or 'numpy' (the fallback).
ENVIRONMENT_SWITCH = "VISIBAKE_KERNELS"
# How every kernel is compiled: in parallel, cached on disk, without the GIL; numpy's
# semantics for division, no bounds checks (the callers pass arrays of checked shapes).
KERNEL_OPTIONS = {"parallel": True, "cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}
# A kernel that runs on one thread: one whose loop is too short to share, or one that
# several Python threads call at once (outside :func:`run` and its lock, which only the
# parallel kernels need: numba's workqueue layer must not be entered twice at once).
SERIAL_OPTIONS = {**KERNEL_OPTIONS, "parallel": False}

_lock = threading.RLock()
_cache_dir: str | None = None
_root: str | None = None  # the cache root the kernels were loaded with (cache_root)
_status: KernelStatus | None = None
_module = None
_volume_module = None
_volume_seconds = 0.0
_appearance_module = None
_blas_lock = threading.Lock()
_blas_depth = 0
_blas_limits = None


@dataclass(frozen=True)
class KernelStatus:
    """How the CPU lookups run in this process.

    backend : 'numba' or 'numpy'
    version : numba's version, or None
    load_seconds : time the first use spent compiling or reading the compiled cache
    compiled : True when that first use compiled (nothing usable was cached)
    cache_dir : where compiled kernels are cached, or None
    reason : why the numpy fallback runs, or None
    """

    backend: str
    version: str | None = None
    load_seconds: float = 0.0
    compiled: bool = False
    cache_dir: str | None = None
    reason: str | None = None
    helpers: int = 0

    def describe(self) -> str:
        """One line for the report and the terminal."""
        if self.backend != "numba":
            return f"numpy lookups (compiled kernels unavailable: {self.reason})"
        how = "compiled on first use" if self.compiled else "loaded from the kernel cache"
        shared = f" ({self.helpers + 1} processes)" if self.helpers else ""
        return f"numba {self.version} kernels, {how} in {self.load_seconds:.1f} s{shared}"

    def as_dict(self) -> dict:
        return {"backend": self.backend, "version": self.version, "load_seconds": round(self.load_seconds, 3),
                "compiled": self.compiled, "cache_dir": self.cache_dir, "reason": self.reason,
                "helpers": self.helpers}


def default_cache_dir() -> str:
    """The user's cache folder for compiled kernels, outside any install folder."""
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA") or os.path.expanduser("~")
    elif sys.platform == "darwin":
        base = os.path.expanduser("~/Library/Caches")
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
    return os.path.join(base, "visibake", "kernels")


def configure(cache_dir: str | None) -> None:
    """Cache compiled kernels in ``cache_dir`` (None: :func:`default_cache_dir`). Takes
    effect at the first load; once the kernels are loaded their cache stays where it is."""
    global _cache_dir
    with _lock:
        if _module is None:
            _cache_dir = cache_dir


def cache_root() -> str:
    """The folder whose subfolders (one per import name) hold the compiled kernels: the one
    chosen at the first load (which then points NUMBA_CACHE_DIR at its subfolder), else the
    one a load would choose. Processes started from this one (a cluster's workers) take it as
    their NUMBA_CACHE_DIR, to find the kernels compiled here."""
    return _root or _cache_dir or os.environ.get("NUMBA_CACHE_DIR") or default_cache_dir()


def _load() -> KernelStatus:
    global _module
    wanted = os.environ.get(ENVIRONMENT_SWITCH, "numba").strip().lower() or "numba"
    if wanted == "numpy":
        return KernelStatus("numpy", reason=f"{ENVIRONMENT_SWITCH}=numpy")
    if wanted != "numba":
        return KernelStatus("numpy", reason=f"{ENVIRONMENT_SWITCH}={wanted!r} is neither 'numba' nor 'numpy'")
    # numba's cache records the kernels' module by its import name, and a cached kernel read
    # under another name fails to load (ModuleNotFoundError) instead of compiling again: the
    # same sources imported as `visibake.core` (tools/visibake.py) and as `core` (tests,
    # benchmarks) keep their kernels apart, one folder per name.
    global _root
    package = __name__.rpartition(".")[0] or "core"
    _root = cache_root()
    cache_dir = os.path.join(_root, re.sub(r"[^A-Za-z0-9._-]+", "_", package))
    started = time.perf_counter()
    try:
        os.makedirs(cache_dir, exist_ok=True)
        numba, modules = _import_kernels(cache_dir)
        misses, helpers = _warm_up_shared(modules, package, cache_dir)
    except Exception as error:  # noqa: BLE001 - any failure to load means: use numpy, and say why
        return KernelStatus("numpy", cache_dir=cache_dir, reason=f"{type(error).__name__}: {error}")
    _module = _Kernels(*modules)
    return KernelStatus("numba", numba.__version__, time.perf_counter() - started, misses > 0, cache_dir,
                        helpers=helpers)


def _import_kernels(cache_dir: str) -> tuple:
    """numba, set to cache in ``cache_dir``, and the kernel modules (transport, table, sample,
    image, light, raster, prep)."""
    # numba reads these when it is first imported; set them for an import still to come.
    os.environ["NUMBA_CACHE_DIR"] = cache_dir
    os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
    import numba
    numba.config.CACHE_DIR = cache_dir
    numba.config.THREADING_LAYER = "workqueue"
    from . import (
        image_kernels,
        light_kernels,
        prep_kernels,
        raster_kernels,
        sample_kernels,
        table_kernels,
        transport_kernels,
    )
    return numba, (transport_kernels, table_kernels, sample_kernels, image_kernels, light_kernels, raster_kernels,
                   prep_kernels)


# A first load with an empty kernel cache compiles about 40 kernels one after the other,
# 100-200 s on one core of a 2-core machine (docs/benchmarks.md, speed part 14), while the other
# cores wait. Helper processes compile some of them into the same cache at the same time.
# Each holds numba's compiler (about 230 MiB), so there are at most this many.
MAX_COMPILE_HELPERS = 3
HELPERS_SWITCH = "VISIBAKE_COMPILE_HELPERS"  # how many helpers at most (0: compile alone)
_HELPER_BOOTSTRAP = """
import importlib, importlib.util, os, sys, types
core_dir, package, cache_dir, claims = sys.argv[1:5]
# The kernels' package under the parent's import name (numba's cache records it), without the
# packages above it (the extension's __init__ needs bpy): empty ones stand in for them.
parts = package.split(".")
for depth in range(1, len(parts)):
    name = ".".join(parts[:depth])
    if name not in sys.modules:
        stand_in = types.ModuleType(name)
        stand_in.__path__ = []
        sys.modules[name] = stand_in
spec = importlib.util.spec_from_file_location(package, os.path.join(core_dir, "__init__.py"),
                                              submodule_search_locations=[core_dir])
module = importlib.util.module_from_spec(spec)
sys.modules[package] = module
spec.loader.exec_module(module)
importlib.import_module(package + ".kernels")._helper_main(cache_dir, claims)
"""


def _helper_count() -> int:
    if not sys.executable:  # an embedded interpreter that cannot start another
        return 0
    wanted = os.environ.get(HELPERS_SWITCH, "").strip()
    most = int(wanted) if wanted.isdigit() else MAX_COMPILE_HELPERS
    return max(0, min(most, (os.cpu_count() or 1) - 1))


def _helper_environment(cache_dir: str) -> dict:
    """A helper process's environment: this one's, caching in ``cache_dir``, with this
    process's module path (Blender adds the extensions' wheels, numba among them, to sys.path
    at run time, where a bare interpreter would not look)."""
    paths = [path for path in sys.path if path and os.path.isdir(path)]
    return {**os.environ, "NUMBA_CACHE_DIR": cache_dir, "PYTHONPATH": os.pathsep.join(paths)}


def _claim(claims: str, number: int) -> bool:
    """Take warm-up step ``number`` for this process, unless another has taken it."""
    try:
        os.close(os.open(os.path.join(claims, f"{number}.claimed"), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        return True
    except FileExistsError:
        return False


def _done_path(claims: str, number: int) -> str:
    return os.path.join(claims, f"{number}.done")


def _helper_main(cache_dir: str, claims: str) -> None:
    """A helper process: compile into ``cache_dir`` every warm-up step no other process has
    claimed in the folder ``claims``, saying each one done there."""
    _, modules = _import_kernels(cache_dir)
    for number, step in enumerate(_warm_up_steps(*modules)):
        if _claim(claims, number):
            step()
            open(_done_path(claims, number), "w").close()


def _warm_up_shared(modules, package: str, cache_dir: str) -> tuple[int, int]:
    """Run every warm-up step (:func:`_warm_up_steps`), shared with helper processes when its
    first kernel was not in the cache (a first load after an install or an update): each process claims steps in turn
    (:func:`_claim`), and this one then runs the helpers' steps once they are done, which
    reads what they compiled (or compiles it, where a helper stopped). Returns (kernels
    compiled, helper processes that finished their share)."""
    steps = _warm_up_steps(*modules)
    steps[0]()
    first_kernel = steps[0].func
    count = _helper_count()
    helpers, claims = [], None
    if sum(first_kernel.stats.cache_misses.values()) > 0 and count > 0:
        claims = tempfile.mkdtemp(prefix="visibake-compile-")
        _claim(claims, 0)
        core_dir = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        environment = _helper_environment(cache_dir)
        flags = getattr(subprocess, "CREATE_NO_WINDOW", 0)  # no console window on Windows
        for _ in range(count):
            try:
                helpers.append(subprocess.Popen([sys.executable, "-c", _HELPER_BOOTSTRAP, core_dir, package,
                                                 cache_dir, claims], env=environment, stdin=subprocess.DEVNULL,
                                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                                creationflags=flags))
            except OSError:
                break  # no interpreter to start: the steps not taken are this process's
    finished = False
    try:
        theirs = []
        for number, step in enumerate(steps[1:], 1):
            if claims is None or _claim(claims, number):
                step()
            else:
                theirs.append((number, step))
        for number, step in theirs:
            while not os.path.exists(_done_path(claims, number)) and any(h.poll() is None for h in helpers):
                time.sleep(0.05)
            step()
        finished = True
    finally:
        for helper in helpers:
            try:
                # Every step is done: a helper still running is only exiting.
                helper.wait(timeout=10.0 if finished else 0.0)
            except subprocess.TimeoutExpired:
                helper.kill()
                helper.wait()
        if claims is not None:
            shutil.rmtree(claims, ignore_errors=True)
    return _compiled_count(modules), sum(1 for helper in helpers if helper.returncode == 0)


def _compiled_count(modules) -> int:
    return sum(1 for kernel in _kernel_functions(*modules) if sum(kernel.stats.cache_misses.values()) > 0)


class _Kernels:
    """Every compiled kernel under one name (``kernels.compiled().gather``)."""

    def __init__(self, *modules):
        for module in modules:
            for name, value in vars(module).items():
                if hasattr(value, "stats") and not name.startswith("_"):
                    setattr(self, name, value)


def _warm_up_steps(module, table_module, sample_module, image_module, light_module, raster_module,
                   prep_module) -> list:
    """Every kernel's first call on a tiny input, in the one signature the callers use: one
    callable per kernel (the raster's three in one, each feeding the next), in the order a
    load runs them. Running them compiles each kernel, or reads it from the cache."""
    # One stored entry (direction 0, sample 0) of a one-sample table.
    words = np.ones((1, 1), np.uint64)
    base = np.zeros((1, 1), np.int64)
    objects = np.zeros(1, np.int16)
    uv_codes = np.zeros((1, 2), np.uint16)
    cells = np.zeros(1, np.int64)
    directions = np.zeros((1, 3), np.float32)
    normals = np.zeros((1, 3), np.float32)
    one32 = np.ones(1, np.float32)
    samples = np.zeros(1, np.int64)
    radiance = np.zeros((4, 3), np.float32)
    sizes = np.ones(1, np.int64)
    index = np.zeros(1, np.int64)
    three = np.zeros((1, 3))
    one = np.ones((1, 1), bool)
    uv = np.zeros((1, 3, 2))
    centre = np.zeros((1, 2))
    corners = np.zeros((1, 3, 3))
    int32 = np.zeros(1, np.int32)
    footprint = np.zeros((1, 1, 3), np.float32)
    flags = np.zeros(1, bool)
    points = np.zeros((1, 3))
    from ..visibility.table import DISTANCE_SPLITS, DISTANCE_VALUES

    def raster():
        corner_uv = np.array([[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]])
        offsets = np.zeros(2, np.int64)
        no_claims = np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, bool), np.zeros((0, 3), np.float32)
        raster_module.triangle_claims(corner_uv, 1, 1, 1e-7, 1e-6, 1e-12, offsets, *no_claims, False)
        claims = np.zeros(offsets[1], np.int32), np.zeros(offsets[1], np.int32), np.zeros(offsets[1], bool)
        weights = np.zeros((offsets[1], 3), np.float32)
        raster_module.triangle_claims(corner_uv, 1, 1, 1e-7, 1e-6, 1e-12, offsets, *claims, weights, True)
        chosen = np.zeros(1, np.int64)
        raster_module.resolve_claims(claims[0], claims[2], chosen, np.zeros(1, np.int8), np.zeros(2, np.int64))
        raster_module.gather_claims(chosen, claims[1], weights, np.zeros(1, np.int64), np.zeros(1, np.int32),
                                    np.zeros((1, 3), np.float32), np.zeros(1, bool))

    steps = [
        partial(table_module.rays_where, one, index, 0, np.zeros(1, np.int64), np.zeros(1, np.int64)),
        partial(module.gather, words, base, objects, uv_codes, cells, directions, normals, one32, samples, 0, 1,
                radiance, sizes, sizes, np.zeros(1, np.int64), np.zeros(1, bool), np.zeros((1, 3), np.int32),
                np.zeros(1, np.int64), False, np.zeros((0, 3), np.float32), np.zeros((0, 0), bool),
                np.ones(1, bool), np.zeros((1, 3))),
        partial(module.cosine_sum, words, base, objects, directions, normals, one32, np.int16(-2), False,
                np.zeros(1)),
        partial(module.cosine_sum, words, base, objects, directions.astype(np.float64), normals.astype(np.float64),
                np.ones(1), np.int16(-1), True, np.zeros(1)),
        partial(module.bare_lookup, words, base, objects, uv_codes, samples, 0, 1, radiance, sizes, sizes,
                np.zeros(1, np.int64), np.zeros((1, 3))),
        partial(table_module.record, objects, uv_codes, np.zeros(1, np.uint16), index, np.zeros(1, np.int32),
                np.zeros(1, np.int32), np.zeros((1, 2), np.float32), np.ones(1, np.float32),
                np.ones((1, 3), np.float32), index, np.zeros((1, 3)), np.zeros((1, 3, 2), np.float32), cells,
                np.zeros(0, bool), DISTANCE_SPLITS, index, np.int64(0), np.zeros(1, np.int32)),
        partial(table_module.ray_setup, index, index, three, np.zeros((1, 0, 3), np.float32), index, three,
                np.zeros((1, 1, 3), np.float32), index, np.zeros(3), np.float32(256.0), np.float32(1.0),
                np.float32(1.0), np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32)),
        partial(table_module.rays_of_span, words, base, np.int64(0), np.int64(1), index, np.int64(0),
                np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64)),
        partial(table_module.horizon_bits, three, three, np.zeros((1, 1), np.uint64), np.zeros(1, np.int32)),
        partial(table_module.entries_at, words, base, index, index, np.zeros(1, np.int64)),
        partial(table_module.count_per_sample, words, base, objects, np.int16(-3), np.zeros(1, np.int32)),
        # Each entry array's type.
        *(partial(table_module.copy_runs, index, index, index, values, values.copy())
          for values in (objects, np.zeros(1, np.uint16), np.zeros(1, np.uint32))),
        *(partial(table_module.entry_columns, words, base, values, np.int64(0), np.int64(1),
                  np.zeros((1, 1), values.dtype)) for values in (objects, np.zeros(1, np.uint16))),
        partial(sample_module.footprint_first_draw, uv, centre, np.zeros(1), np.ones(1, bool), np.zeros((1, 1, 2)),
                corners, 0.5, 1e-4, np.zeros((1, 1, 3)), np.zeros((1, 1), bool)),
        partial(sample_module.footprint_redraws, uv, centre, np.zeros(1), np.ones(1, bool), np.zeros((1, 1, 2)),
                corners, 0.5, 1e-4, 10, np.zeros((1, 1, 3)), np.zeros((1, 1), bool)),
        partial(sample_module.footprint_corners, uv, centre, np.zeros(1), corners, np.zeros((1, 3)),
                np.zeros((1, 1, 3), np.float32), 0.25, 1e-4, np.zeros((1, 4, 3), np.float32)),
        partial(sample_module.footprint_jitter, np.zeros(1, np.int64), np.zeros(1, np.int32),
                np.zeros((1, 2), np.uint32), np.zeros((1, 1, 2))),
        partial(sample_module.footprint_offsets_of, np.zeros((1, 1, 3)), np.zeros((1, 3)),
                np.zeros((1, 1, 3), np.float32)),
        partial(sample_module.footprint_point_normals, np.zeros((1, 1, 3), np.float32), np.zeros((1, 3)),
                np.zeros(1, np.int64), np.zeros(1, np.int64), corners, np.zeros((1, 3, 3), np.float32),
                np.zeros((1, 3)), np.zeros((1, 1, 3), np.float32)),
        partial(sample_module.face_frames, corners[0], np.array([[0, 1, 2]], np.int32), 1e-12, np.zeros((1, 3)),
                np.zeros(1, bool), np.zeros(1)),
        partial(image_module.bilinear_points, np.zeros((4, 3), np.float32), int32 + 1, int32 + 1, int32, int32,
                np.zeros((1, 2), np.float32), np.zeros((1, 3))),
        partial(image_module.seam_product, np.zeros((1, 8)), np.zeros((1, 8), np.int64), np.ones(1), 1.0,
                np.zeros((1, 3)), np.zeros((1, 3))),
        partial(image_module.seam_solve, np.zeros((1, 8)), np.zeros((1, 8), np.int64), np.ones(1), 1.0, np.ones(1),
                np.zeros((1, 3)), np.ones(3), 4, np.zeros((1, 3))),
        partial(image_module.dilate_rings, np.zeros((1, 3), np.float32), np.ones(1, bool), np.zeros(0, np.int64),
                1, 1, 1),
        partial(image_module.sum_rows, np.zeros(1, np.int64), np.zeros((1, 3)), np.zeros(0, np.int64),
                np.zeros((1, 3))),
        partial(image_module.sum_rows, int32, np.zeros((1, 3)), int32, np.zeros((1, 3))),  # the filter's int32 pairs
        partial(image_module.contact_sums, np.zeros((4, 3), np.float32), np.zeros((4, 3), np.float32), int32 + 1,
                int32 + 1, int32, int32, np.zeros((1, 2), np.float32), np.zeros(1, np.float32), np.zeros((1, 3)),
                np.zeros(1, np.int64), np.zeros((1, 3))),
        partial(light_module.hard_lamp_point, light_module.POINT, np.ones(3), np.array([0.0, 0.0, -1.0]), 0.5, 0.1,
                three, three, footprint, 0, footprint, 0, np.ones(3), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1),
                np.zeros((1, 3)), np.zeros(1, bool)),
        partial(light_module.hard_lamp_decided, light_module.POINT, np.ones(3), np.array([0.0, 0.0, -1.0]), 0.5,
                0.1, three, three, footprint, np.zeros((1, 0, 3), np.float32), np.ones(3), np.zeros(1, np.int64),
                flags, flags, 1, flags, 4, 1.0, np.zeros((1, 3)), np.zeros(1, bool)),
    ]
    for sample_origins in (np.zeros((1, 3), np.float32), np.zeros((1, 3))):  # a ray scene at the origin, and centred
        steps.append(partial(light_module.shadow_ray_setup, index, index, np.ones(1), three, np.zeros((0, 3)), three,
                             three, three, three, np.zeros(1), sample_origins, np.zeros(3), False, 1.0,
                             np.float32(256.0), np.float32(1.0), np.float32(1.0), sample_origins.copy(),
                             np.zeros((1, 3)), np.zeros(1, np.float32), np.zeros((1, 3))))
        steps.append(partial(light_module.emitter_rays, index, sample_origins, three, np.ones(1), 1.0,
                             sample_origins.copy(), np.zeros((1, 3)), np.zeros(1, np.float32)))
        steps.append(partial(light_module.corner_probe_rays, False, np.ones(3), np.array([0.0, 0.0, -1.0]), three,
                             three, three, three, np.zeros(1), np.zeros((1, 4, 3), np.float32), 0, np.ones(1, bool),
                             1.0, np.zeros(3), False, np.float32(256.0), np.float32(1.0), np.float32(1.0),
                             np.zeros(1, bool), sample_origins.copy(), np.zeros((1, 3)), np.zeros(1, np.float32)))
        steps.append(partial(light_module.hard_lamp_edge_rays, light_module.POINT, np.ones(3),
                             np.array([0.0, 0.0, -1.0]), 0.5, 0.1, three, three, three, three, np.zeros(1), footprint,
                             np.zeros((1, 0, 3), np.float32), 0, np.ones(1, bool), np.ones(3), 1.0, np.zeros(3), False,
                             np.float32(256.0), np.float32(1.0), np.float32(1.0), np.zeros((1, 1, 3)),
                             np.zeros((1, 1), bool), sample_origins[None].copy(), np.zeros((1, 1, 3)),
                             np.zeros((1, 1), np.float32)))
    first = np.zeros(1, np.int64)
    steps += [
        partial(light_module.emitter_patch, three, three, three, np.ones(3), np.ones(3), np.zeros((1, 3)), np.zeros(1),
                np.zeros(1), np.zeros(1, bool)),
        partial(light_module.emitter_add, index, np.zeros(1, bool), np.ones(1), 1.0, np.ones(3), np.zeros((1, 3))),
        partial(light_module.footprint_curvature, footprint, three, 0.5, np.zeros(1, bool)),
        partial(light_module.edge_light_add, np.zeros((1, 1, 3)), np.zeros((1, 1), bool), np.zeros((1, 3))),
        raster,
        partial(raster_module.uv_checks, np.zeros((1, 3, 2)), 1, 1, 1e-6, 1e-12, np.zeros(1, bool),
                np.zeros(1, np.int8), np.zeros(1, np.int8)),
        partial(prep_module.close_entries, words, base, objects, np.zeros(1, np.uint16), DISTANCE_VALUES,
                np.ones(1, np.float32), np.zeros(0), np.zeros(2, np.int64), np.zeros(0, np.int64),
                np.zeros(0, np.int64), False),
        partial(prep_module.exposed_share, words, base, objects, 1, 0.9, 0, np.zeros(1)),
        partial(prep_module.texel_owners, first, np.zeros((1, 2), np.float32), first + 1, first + 1, first, first,
                np.zeros((1, 2), np.int64), np.zeros(1, np.int64)),
        partial(prep_module.filter_candidates, first, np.ones(1, bool), first, 0, 1, 1, np.zeros((1, 2), np.int64), 1,
                points, points, points, 0.5, 1.0, np.zeros(2, np.int64), np.zeros(2, np.int64), first, first,
                np.zeros((1, 3), np.float32), np.zeros(1, np.float32), False),
    ]
    return steps


def _kernel_functions(*modules) -> list:
    """Every compiled kernel of ``modules`` (numba dispatchers), in a fixed order."""
    return [value for module in modules for name, value in sorted(vars(module).items())
            if hasattr(value, "stats") and hasattr(value, "py_func") and not name.startswith("_")]


@contextlib.contextmanager
def blas_on_one_thread():
    """numpy's BLAS held to one thread while the block runs (nested blocks: until the outermost
    ends), then as it was; wrapped around every bake, relight and worker task.

    OpenBLAS, which numpy's wheels link, keeps its threads spinning (``sched_yield``) for a
    while after every call it ran on them, even a (N, 3) x (3, K) product: each spinning thread
    takes a core from the kernels and embree's queries that follow. With two cores, a
    visibility trace took as long on two threads as on one (docs/benchmarks.md, speed part 11).
    The bake's products are too thin to gain from BLAS threads. Done through threadpoolctl,
    which finds whichever BLAS this process loaded; where it finds none, or cannot load,
    nothing changes."""
    global _blas_depth, _blas_limits
    with _blas_lock:
        if _blas_depth == 0:
            try:
                from threadpoolctl import threadpool_limits
                _blas_limits = threadpool_limits(limits=1, user_api="blas")
            except Exception:  # noqa: BLE001 - a missing or failing limiter only costs speed
                _blas_limits = None
        _blas_depth += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_depth -= 1
            if _blas_depth == 0 and _blas_limits is not None:
                _blas_limits.restore_original_limits()
                _blas_limits = None


def status() -> KernelStatus:
    """Load the kernels if that was not tried yet (compiling on first use), and say how
    the lookups run. Thread-safe; the load happens once per process."""
    global _status
    with _lock:
        if _status is None:
            _status = _load()
        return _status


def volume():
    """The volume kernels (:mod:`core.kernels.volume_kernels`), compiled or read from the cache
    on first use; None where numba cannot load (:func:`status` says why). Kept apart from
    the surface kernels so that a surface bake never compiles them."""
    global _volume_module, _volume_seconds
    if compiled() is None:
        return None
    with _lock:
        if _volume_module is None:
            started = time.perf_counter()
            from . import volume_kernels
            volume_kernels.warm_up()
            _volume_seconds = time.perf_counter() - started
            _volume_module = volume_kernels
        return _volume_module


def appearance():
    """The appearance kernels (:mod:`core.kernels.appearance_kernels`), compiled or read from
    the cache on first use; None where numba cannot load (:func:`status` says why)."""
    global _appearance_module
    if compiled() is None:
        return None
    with _lock:
        if _appearance_module is None:
            from . import appearance_kernels
            appearance_kernels.warm_up()
            _appearance_module = appearance_kernels
        return _appearance_module


def volume_load_seconds() -> float:
    """Seconds the first :func:`volume` call spent compiling or reading the volume kernels."""
    return _volume_seconds


def tried() -> bool:
    """Whether this process has loaded the kernels already (or found it cannot)."""
    return _status is not None


def compiled():
    """The kernels module, or None when the numpy fallback runs."""
    status()
    return _module


# Asked once: a bake runs about a thousand kernels on a scene of many small objects, and each
# os.cpu_count() and numba.set_num_threads cost 10-20 us here (docs/benchmarks.md, speed part 14).
_CORES = os.cpu_count() or 1
_threads_set = threading.local()  # the count this thread last gave numba.set_num_threads


def thread_count(threads: int) -> int:
    """The kernels' thread count for the Threads preference ``threads`` (0: all cores)."""
    import numba
    return max(1, min(int(threads) or _CORES, numba.config.NUMBA_NUM_THREADS))


def run(kernel, threads: int, *arguments) -> None:
    """Call ``kernel(*arguments)`` on ``threads`` threads (0: all cores), one call at a time."""
    import numba
    count = thread_count(threads)
    with _lock:
        # numba's count is the calling thread's own: set it where it differs from the last one set.
        if getattr(_threads_set, "count", None) != count:
            numba.set_num_threads(count)
            _threads_set.count = count
        kernel(*arguments)
