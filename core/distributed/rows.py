"""Work on a range of sample rows, as a worker does it (docs/scaleout.md: the bake splits by
sample rows, so that every sample's sums run in the same order as in one process).

A worker is given a scene package (core.distributed.package) and a row range [start, stop)
of the bake's samples (every object's samples concatenated, in object order). It prepares
the samples as the one-process bake does (deterministic: every worker builds the same ones),
then traces only its rows' table. The driver joins the rows' tables with
core.visibility.table.concatenate_columns: the result equals the one-process table bit for bit.

What a worker prepared is kept in its process, keyed by the package's checksum, so the next
task of the same bake (another range, or a bounce) does not read or prepare it again.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import replace

from ..pipeline.prepare import Prepared, prepare, scene_hit_geometry
from ..transport.contract import direction_chunks
from ..visibility.table import TraceRequest, VisibilityTable, trace_table
from .package import read_package

# checksum -> Prepared (no table): one entry per bake this worker process takes part in.
_prepared: dict[str, Prepared] = {}
# The most bakes a worker keeps prepared at once; the oldest is forgotten first.
KEPT_PREPARATIONS = 2


def row_ranges(samples: int, parts: int) -> list[range]:
    """``parts`` contiguous ranges of nearly equal size covering ``range(samples)``; they
    depend on (samples, parts) alone, so a retried task gets exactly the same rows."""
    return direction_chunks(samples, parts)


def trace_request(p: Prepared) -> TraceRequest:
    """The table request of preparation ``p``, as :func:`core.pipeline.prepare.prepare` makes it."""
    return TraceRequest(p.directions, p.position, p.geometric, scene_hit_geometry(p.meshes), p.settings.chunk_rays,
                        None if p.footprint is None else p.footprint[0], p.rotations, p.group)


def prepared_from_package(path: str, threads: int = 0) -> tuple[str, Prepared]:
    """(checksum, the package's preparation without its table), read once per worker process.

    ``threads``: this machine's worker threads (0: all cores); the package's own setting
    belongs to the machine that wrote it and may exceed this one's cores.
    """
    package = read_package(path)
    kept = _prepared.get(package.checksum)
    if kept is None:
        settings = replace(package.settings, threads=threads)
        kept = prepare(package.scene, settings, table_needed=False)
        while len(_prepared) >= KEPT_PREPARATIONS:
            _prepared.pop(next(iter(_prepared)))
        _prepared[package.checksum] = kept
    return package.checksum, kept


def trace_rows(package: str | bytes, start: int, stop: int, threads: int = 0) -> VisibilityTable:
    """The visibility table of sample rows [start, stop) of a packaged bake.

    package : the package's path on this machine, or its bytes (written to a temporary file
        here: a worker on another machine need not share the driver's disk)
    Returns a VisibilityTable over all N directions and stop - start samples.
    """
    if isinstance(package, bytes):
        handle, path = tempfile.mkstemp(suffix=".vbpkg")
        try:
            with os.fdopen(handle, "wb") as stream:
                stream.write(package)
            _, p = prepared_from_package(path, threads)
        finally:
            os.remove(path)
    else:
        _, p = prepared_from_package(package, threads)
    if not 0 <= start <= stop <= len(p.position):
        raise ValueError(f"rows [{start}, {stop}) outside the bake's {len(p.position)} samples")
    return trace_table(p.ray_scene, trace_request(p).rows(start, stop))
