"""Work on a range of sample rows, as a worker does it (docs/scaleout.md: the bake splits by
sample rows, so that every sample's sums run in the same order as in one process).

A worker is given a scene package (core.distributed.package) and a row range [start, stop)
of the bake's samples (every object's samples concatenated, in object order). It prepares
the samples as the one-process bake does (deterministic: every worker builds the same ones),
then traces only its rows' table (:func:`keep_rows`).

What a worker prepared, and the tables (and gather normalisations) of the rows it traced, are
kept in its process, keyed by the package's checksum, so the next task of the same bake (a
bounce's gather of the same rows) neither prepares nor traces again (:func:`run_task` runs
any task of core.distributed.row_tasks on them).
"""
from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, replace

import numpy as np

from ..pipeline.prepare import Prepared, prepare
from ..transport.contract import direction_chunks
from ..transport.gather import gather_normalisation
from ..visibility.table import VisibilityTable, trace_table
from .package import MANIFEST_NAME, read_package

# checksum -> Prepared (no table): one entry per bake this worker process takes part in.
_prepared: dict[str, Prepared] = {}
# (checksum, start, stop) -> those rows' table and gather normalisation, made by this worker process.
_rows: dict[tuple[str, int, int], KeptRows] = {}
# The most bakes a worker keeps prepared at once; the oldest is forgotten first, with its rows.
KEPT_PREPARATIONS = 2


@dataclass(frozen=True)
class KeptRows:
    """What is kept of a range of rows [start, stop): table (VisibilityTable over N directions
    and the rows) and scale ((rows,) float64 gather normalisation, which every bounce's gather
    reuses)."""

    start: int
    stop: int
    table: VisibilityTable
    scale: np.ndarray


def keep_rows(p: Prepared, start: int, stop: int, threads: int = 0) -> KeptRows:
    """Trace rows [start, stop) of preparation ``p`` (made without its table) and normalise them."""
    if not 0 <= start <= stop <= len(p.position):
        raise ValueError(f"rows [{start}, {stop}) outside the bake's {len(p.position)} samples")
    table = trace_table(p.ray_scene, p.trace_request().rows(start, stop))
    return KeptRows(start, stop, table, gather_normalisation(table, p.frame_normal[start:stop], threads))


def row_ranges(samples: int, parts: int) -> list[range]:
    """``parts`` contiguous ranges of nearly equal size covering ``range(samples)``; they
    depend on (samples, parts) alone, so a retried task gets exactly the same rows."""
    return direction_chunks(samples, parts)


def _claimed_checksum(package: str | bytes) -> str | None:
    """The checksum a package's manifest states, unverified (None if it cannot be read): it
    only finds a preparation this process made from a package it verified in full."""
    try:
        with zipfile.ZipFile(io.BytesIO(package) if isinstance(package, bytes) else package) as archive:
            return json.loads(archive.read(MANIFEST_NAME)).get("checksum")
    except (OSError, zipfile.BadZipFile, KeyError, ValueError):
        return None


def prepared_from_package(package: str | bytes, threads: int = 0) -> tuple[str, Prepared]:
    """(checksum, the package's preparation without its table), read, verified and prepared
    once per worker process; a later task of the same package reads only its manifest.

    package : the package's path on this machine, or its bytes (a worker on another machine
        need not share the driver's disk)
    threads : this machine's worker threads (0: all cores); the package's own setting belongs
        to the machine that wrote it and may exceed this one's cores
    """
    claimed = _claimed_checksum(package)
    if claimed in _prepared:
        return claimed, _prepared[claimed]
    if isinstance(package, bytes):
        handle, path = tempfile.mkstemp(suffix=".vbpkg")
        try:
            with os.fdopen(handle, "wb") as stream:
                stream.write(package)
            read = read_package(path)
        finally:
            os.remove(path)
    else:
        read = read_package(package)
    kept = _prepared.get(read.checksum)
    if kept is None:
        kept = prepare(read.scene, replace(read.settings, threads=threads), table_needed=False)
        while len(_prepared) >= KEPT_PREPARATIONS:
            forgotten = next(iter(_prepared))
            _prepared.pop(forgotten)
            for key in [key for key in _rows if key[0] == forgotten]:
                _rows.pop(key)
        _prepared[read.checksum] = kept
    return read.checksum, kept


def _kept_rows(package: str | bytes, start: int, stop: int, threads: int) -> tuple[Prepared, KeptRows]:
    """The preparation and rows [start, stop)'s table and normalisation, made here once and
    kept: a retried or moved task makes them again, to the same bits."""
    checksum, p = prepared_from_package(package, threads)
    key = (checksum, start, stop)
    if key not in _rows:
        _rows[key] = keep_rows(p, start, stop, threads)
    return p, _rows[key]


def run_task(package: str | bytes, start: int, stop: int, task: str, *arguments, threads: int = 0):
    """``core.distributed.row_tasks.<task>`` on rows [start, stop) of a packaged bake, in this
    (worker) process: the rows are prepared and traced on the first task, then kept."""
    from . import row_tasks

    p, kept = _kept_rows(package, start, stop, threads)
    return getattr(row_tasks, task)(p, kept, *arguments, threads=threads)
