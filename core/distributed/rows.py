"""Work on a range of sample rows, as a worker does it (docs/scaleout.md: the bake splits by
sample rows, so that every sample's sums run in the same order as in one process).

A worker is given a scene package (core.distributed.package) and a row range [start, stop)
of the bake's samples (every object's samples concatenated, in object order). It prepares
the samples as the one-process bake does (deterministic: every worker builds the same ones),
then traces only its rows' table. The driver joins the rows' tables with
core.visibility.table.concatenate_columns: the result equals the one-process table bit for bit.

What a worker prepared, and the tables (and gather normalisations) of the rows it traced, are
kept in its process, keyed by the package's checksum, so the next task of the same bake (a bounce's gather of the same
rows) neither prepares nor traces again. Each bounce sends the whole radiance atlas out and
gets each range's rows back (:func:`gather_rows`).
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
from ..transport.contacts import exposed_share
from ..transport.contract import GatherGeometry, GatherSource, direction_chunks
from ..transport.gather import gather, gather_normalisation
from ..visibility.table import VisibilityTable, trace_table
from .package import MANIFEST_NAME, read_package

# checksum -> Prepared (no table): one entry per bake this worker process takes part in.
_prepared: dict[str, Prepared] = {}
# (checksum, start, stop) -> those rows' table and gather normalisation, made by this worker process.
_rows: dict[tuple[str, int, int], _Rows] = {}
# The most bakes a worker keeps prepared at once; the oldest is forgotten first, with its rows.
KEPT_PREPARATIONS = 2


@dataclass(frozen=True)
class _Rows:
    """What a worker keeps of its rows: table (VisibilityTable over N directions and the rows)
    and scale ((rows,) float64 gather normalisation, which every bounce's gather reuses)."""

    table: VisibilityTable
    scale: np.ndarray


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


def _kept_rows(package: str | bytes, start: int, stop: int, threads: int) -> tuple[Prepared, _Rows]:
    """The preparation and rows [start, stop)'s table and normalisation, made here once and
    kept: a retried or moved task makes them again, to the same bits."""
    checksum, p = prepared_from_package(package, threads)
    if not 0 <= start <= stop <= len(p.position):
        raise ValueError(f"rows [{start}, {stop}) outside the bake's {len(p.position)} samples")
    key = (checksum, start, stop)
    if key not in _rows:
        table = trace_table(p.ray_scene, p.trace_request().rows(start, stop))
        _rows[key] = _Rows(table, gather_normalisation(table, p.frame_normal[start:stop], threads))
    return p, _rows[key]


def trace_rows(package: str | bytes, start: int, stop: int, threads: int = 0) -> VisibilityTable:
    """The visibility table of sample rows [start, stop) of a packaged bake (kept in this
    process for the rows' gathers). Returns a VisibilityTable over all N directions and
    stop - start samples."""
    return _kept_rows(package, start, stop, threads)[1].table


def gather_rows(package: str | bytes, start: int, stop: int, radiance: np.ndarray, world: np.ndarray,
                exclude: np.ndarray | None = None, threads: int = 0) -> np.ndarray:
    """The gather (core.transport.gather.gather) of sample rows [start, stop): (stop - start, C)
    float64, equal bit for bit to those rows of the gather over every sample.

    radiance : (layout.size, C) float32, the whole packed radiance atlas; world : (N, C) or (C,)
    exclude : (stop - start, O) bool rows of the exclusion mask, or None
    """
    p, rows = _kept_rows(package, start, stop, threads)
    geometry = GatherGeometry(rows.table, p.frame_normal[start:stop], rows.scale, p.layout, threads)
    return gather(geometry, GatherSource(radiance, world, exclude))


def row_summaries(package: str | bytes, start: int, stop: int, threads: int = 0) -> dict:
    """What the driver needs of rows [start, stop)'s table besides their gathers, per sample,
    equal bit for bit to those rows of the whole preparation's (core.pipeline.prepare.Prepared):

    gather_scale : (k,) float64 each sample's gather normalisation (Prepared.gather_scale)
    exposed : (k,) float64 its share of footprint points not buried (Prepared.exposed)
    buried : (k,) bool whether its texel lies inside other geometry (VisibilityTable.buried)
    """
    p, rows = _kept_rows(package, start, stop, threads)
    slots = 1 if p.footprint is None else p.footprint[0].shape[1]
    return {"gather_scale": rows.scale, "exposed": exposed_share(rows.table, slots, threads),
            "buried": rows.table.buried()}
