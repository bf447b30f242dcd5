"""Work on a range of sample rows, as a worker does it (docs/scaleout.md: the bake splits by
sample rows, so that every sample's sums run in the same order as in one process).

A worker is given a scene package (core.distributed.package) and a row range [start, stop)
of the bake's samples (every object's samples concatenated, in object order). It reads the
package once (:class:`PackagedBake`: the meshes, the ray scene, the atlas layout and where
each object's samples start, counted by the raster alone), builds the samples of the objects
the range covers only, as the one-process bake builds them (deterministic: the same bits),
and traces the range's table (:func:`keep_rows`). A worker's memory is then its rows' table
and samples, not the whole scene's samples.

What a worker read, and the samples, tables (and gather normalisations) of the rows it
traced, are kept in its process, keyed by the package's checksum, so the next task of the
same bake (a lamp's direct light, a bounce's gather of the same rows) neither reads, builds
nor traces again (:func:`run_task` runs any task of core.distributed.row_tasks on them).
"""
from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field, replace

import numpy as np

from ..kernels import blas_on_one_thread
from ..pipeline.prepare import (
    Prepared,
    dense_footprint_of,
    direction_rotations,
    footprint_box,
    footprint_point_normals,
    footprint_points,
    meshes_with_faces,
    rotation_group,
    table_request,
    terminator_cutoffs,
    terminator_lifts,
    trace_frame,
)
from ..sampling.samples import ObjectSamples, TexelSummary, build_samples, build_vertex_samples, texel_summary
from ..settings import BakeSettings
from ..transport.contract import SampleSet, direction_chunks
from ..transport.gather import AtlasLayout, gather_normalisation, open_hemisphere_weight
from ..visibility.directions import direction_set
from ..visibility.rays import RayScene
from ..visibility.table import TraceRequest, VisibilityTable, frame_vectors, trace_table
from .package import DAMAGED_ARCHIVE_ERRORS, MANIFEST_NAME, read_package

# checksum -> PackagedBake: one entry per bake this worker process takes part in.
_bakes: dict[str, PackagedBake] = {}
# (checksum, start, stop) -> those rows' table and gather normalisation, made by this worker process.
_rows: dict[tuple[str, int, int], KeptRows] = {}
# The most bakes a worker keeps at once; the oldest is forgotten first, with its rows.
KEPT_BAKES = 2


@dataclass(frozen=True)
class RowsPreparation:
    """A bake narrowed to sample rows [start, stop): what tracing and reading them needs.

    samples : the bake's sample count K (every object's, concatenated)
    request : the rows' TraceRequest (k = stop - start samples)
    frame_normal : (k, 3) float64 the rows' shading normals in their frames of the direction set
    group : (k,) int64 the rows' interleaved rotations, or None (one set)
    open_weight : (k,) float64 what each row's gather weights sum to
        (core.transport.gather.open_hemisphere_weight)
    """

    samples: int
    start: int
    stop: int
    ray_scene: RayScene
    request: TraceRequest
    frame_normal: np.ndarray
    group: np.ndarray | None
    open_weight: np.ndarray


def rows_of(p: Prepared, start: int, stop: int) -> RowsPreparation:
    """Rows [start, stop) of a whole preparation (views, no copies): the in-process executor's."""
    if not 0 <= start <= stop <= len(p.position):
        raise ValueError(f"rows [{start}, {stop}) outside the bake's {len(p.position)} samples")
    return RowsPreparation(len(p.position), start, stop, p.ray_scene, p.trace_request().rows(start, stop),
                           p.frame_normal[start:stop], None if p.group is None else p.group[start:stop],
                           open_hemisphere_weight(p.normal[start:stop], p.geometric[start:stop]))


@dataclass
class PackagedBake:
    """What a worker keeps of a packaged bake between its tasks: everything but most samples.

    The row tasks (core.distributed.row_tasks) read it as they read a whole
    core.pipeline.prepare.Prepared in process: its settings, meshes, ray_scene, directions,
    rotations and layout, and :meth:`sample_rows`.

    meshes : the meshes with faces, in object order (as core.pipeline.prepare.prepare keeps them)
    sample_offset : (objects + 1,) int64 where each object's samples start among all K
    vertex_samples : object index -> its VertexSamples (built up front: the layout needs them)
    rotations : (G, 3, 3) float64 interleaved rotations of the direction set, or None
    footprint_normals, terminator : whether the whole bake's samples have footprint normals and
        terminator lifts (some object has them: core.sampling.samples.TexelSummary): the rows
        then have them too, as core.pipeline.prepare.concatenated_footprint and
        concatenated_terminator give them
    """

    settings: BakeSettings
    meshes: list
    sample_offset: np.ndarray
    vertex_samples: dict
    layout: AtlasLayout
    directions: np.ndarray
    rotations: np.ndarray | None
    ray_scene: RayScene
    footprint_normals: bool
    terminator: bool
    # (start, stop) -> those rows' (SampleSet, (k,) int64 rotations or None), built on their first task
    _sample_sets: dict = field(default_factory=dict, repr=False)

    @classmethod
    def read(cls, scene, settings: BakeSettings) -> PackagedBake:
        """The bake of ``scene`` (core.scene.Scene) at ``settings``; reads each atlas object
        with one raster of its UV map, without evaluating its samples."""
        meshes = meshes_with_faces(scene.meshes)
        centre, _ = trace_frame(meshes)
        vertex = {index: build_vertex_samples(mesh, centre) for index, mesh in enumerate(meshes)
                  if mesh.mode == "vertex"}
        summaries = []
        for index, mesh in enumerate(meshes):
            if index in vertex:
                built = vertex[index]
                summaries.append(TexelSummary(len(built), built.footprint_normals is not None,
                                              built.terminator is not None))
            else:
                summaries.append(texel_summary(mesh, settings.footprint_samples, settings.threads))
        sizes = [(vertex[index].width, vertex[index].height) if index in vertex else tuple(mesh.resolution)
                 for index, mesh in enumerate(meshes)]
        layout = AtlasLayout.from_sizes(sizes, [vertex[index].corner_sample if index in vertex else None
                                                for index in range(len(meshes))],
                                        settings.vertex_lookup == "nearest")
        return cls(settings, meshes, np.concatenate([[0], np.cumsum([s.count for s in summaries])]).astype(np.int64),
                   vertex, layout, direction_set(settings.directions, settings.rotate, settings.seed),
                   direction_rotations(settings.interleave, settings.seed),
                   RayScene([(m.positions, m.triangles) for m in meshes], settings.threads, centre),
                   any(s.footprint_normals for s in summaries), any(s.terminator for s in summaries))

    @property
    def samples(self) -> int:
        return int(self.sample_offset[-1])

    def object_samples(self, index: int) -> ObjectSamples:
        """Object ``index``'s samples, as core.pipeline.prepare.prepare builds them."""
        if index in self.vertex_samples:
            return self.vertex_samples[index]
        built = build_samples(self.meshes[index], self.settings.footprint_samples, self.settings.threads,
                              self.settings.footprint_width)
        expected = int(self.sample_offset[index + 1] - self.sample_offset[index])
        if len(built) != expected:
            raise RuntimeError(f"object {self.meshes[index].name!r} made {len(built)} samples where its raster "
                               f"counted {expected}")
        return built

    def _pieces(self, start: int, stop: int) -> list[tuple[int, ObjectSamples, slice]]:
        """(object index, its samples, the rows' slice of them) of each object rows [start, stop) cover."""
        if not 0 <= start <= stop <= self.samples:
            raise ValueError(f"rows [{start}, {stop}) outside the bake's {self.samples} samples")
        pieces = []
        for index in range(len(self.meshes)):
            first, last = int(self.sample_offset[index]), int(self.sample_offset[index + 1])
            if max(start, first) < min(stop, last):
                pieces.append((index, self.object_samples(index),
                               slice(max(start, first) - first, min(stop, last) - first)))
        return pieces

    def sample_rows(self, start: int, stop: int) -> SampleSet:
        """Samples [start, stop) of the bake, built from the objects they cover and kept for the
        range's later tasks (its trace, the lamps' direct light): bitwise the rows of the whole
        preparation's SampleSet (core.pipeline.prepare.Prepared.sample_rows), ids and dense
        footprints included. The covered objects' own footprints are not kept (the joined
        arrays hold the rows'), nor are the samples of the objects the rows do not cover."""
        return self._built(start, stop)[0]

    def _built(self, start: int, stop: int) -> tuple[SampleSet, np.ndarray | None]:
        """(:meth:`sample_rows`, the rows' (k,) int64 rotations or None), built once per range."""
        if (start, stop) in self._sample_sets:
            return self._sample_sets[start, stop]
        pieces = self._pieces(start, stop)
        position = _joined(pieces, lambda i, s: s.position, (3,), np.float64)
        normal = _joined(pieces, lambda i, s: s.normal, (3,), np.float64)
        geometric = _joined(pieces, lambda i, s: s.geometric_normal, (3,), np.float64)
        owner = _joined(pieces, lambda i, s: np.full(len(s), i, np.int64), (), np.int64)
        count = self.settings.footprint_samples
        points = corners = point_normals = None
        if count > 1:
            points = _joined(pieces, lambda i, s: footprint_points(s, count), (count, 3), np.float32)
            corners = _joined(pieces, lambda i, s: footprint_box(s), (4, 3), np.float32)
            if self.footprint_normals:
                point_normals = _joined(pieces, lambda i, s: footprint_point_normals(s, count), (count, 3),
                                        np.float32)
        lifts = cutoffs = None
        if self.terminator:
            lifts = _joined(pieces, lambda i, s: terminator_lifts(s), (3,), np.float64)
            cutoffs = _joined(pieces, lambda i, s: terminator_cutoffs(self.meshes[i], s), (), np.float64)
        group = None
        if self.rotations is not None:
            group = _joined(pieces, lambda i, s: rotation_group(s, self.settings.interleave), (), np.int64)
        # What a dense footprint reads of each covered object; its footprint arrays are in the joined ones.
        covered = {index: replace(s, footprint=None, footprint_corners=None, footprint_normals=None, terminator=None,
                                  albedo=None, emission=None) for index, s, _ in pieces}

        def dense(rows, count):
            return dense_footprint_of(self.meshes, covered.__getitem__, self.sample_offset,
                                      lambda chosen: normal[np.asarray(chosen) - start], rows, count,
                                      self.settings.threads, self.settings.footprint_width)

        built = SampleSet(position, normal, geometric, self.ray_scene.ray_origins(position, geometric), owner,
                          points, corners, lifts, cutoffs, footprint_normals=point_normals,
                          dense_footprint=None if points is None else dense, ids=np.arange(start, stop, dtype=np.int64))
        self._sample_sets[start, stop] = (built, group)
        return built, group

    def rows(self, start: int, stop: int) -> RowsPreparation:
        """Rows [start, stop) of the bake, to trace: their samples are built once, by
        :meth:`sample_rows`, and kept for the lamps' direct light."""
        samples, group = self._built(start, stop)
        request = table_request(self.meshes, self.settings, self.directions, samples.position, samples.geometric,
                                None if samples.footprint is None else (samples.footprint,), self.rotations, group)
        return RowsPreparation(self.samples, start, stop, self.ray_scene, request,
                               frame_vectors(samples.normal, self.rotations, group), group,
                               open_hemisphere_weight(samples.normal, samples.geometric))


def _joined(pieces, values, shape: tuple, dtype) -> np.ndarray:
    """``values(object index, samples)`` of each piece (see PackagedBake._pieces), cut to its
    rows and joined; (0, *shape) ``dtype`` without pieces."""
    if not pieces:
        return np.zeros((0, *shape), dtype)
    return np.concatenate([np.asarray(values(index, samples))[cut] for index, samples, cut in pieces])


@dataclass(frozen=True)
class KeptRows:
    """What is kept of a range of rows [start, stop) of a bake of ``samples`` samples: table
    (VisibilityTable over N directions and the rows), scale ((k,) float64 gather normalisation,
    which every bounce's gather reuses), frame_normal ((k, 3) float64) and group ((k,) int64 or
    None), as in :class:`RowsPreparation`."""

    start: int
    stop: int
    samples: int
    table: VisibilityTable
    scale: np.ndarray
    frame_normal: np.ndarray
    group: np.ndarray | None


def keep_rows(rows: RowsPreparation, threads: int = 0) -> KeptRows:
    """Trace ``rows``' table and normalise it."""
    table = trace_table(rows.ray_scene, rows.request)
    return KeptRows(rows.start, rows.stop, rows.samples, table,
                    gather_normalisation(table, rows.frame_normal, rows.open_weight, threads), rows.frame_normal,
                    rows.group)


def row_ranges(samples: int, parts: int) -> list[range]:
    """``parts`` contiguous ranges of nearly equal size covering ``range(samples)``; they
    depend on (samples, parts) alone, so a retried task gets exactly the same rows."""
    return direction_chunks(samples, parts)


def _claimed_checksum(package: str | bytes) -> str | None:
    """The checksum a package's manifest states, unverified (None if it cannot be read): it
    only finds a preparation this process made from a package it verified in full."""
    try:
        with zipfile.ZipFile(io.BytesIO(package) if isinstance(package, bytes) else package) as archive:
            manifest = json.loads(archive.read(MANIFEST_NAME))
    except (*DAMAGED_ARCHIVE_ERRORS, KeyError, ValueError):
        return None  # read_package says what is wrong with it
    return manifest.get("checksum") if type(manifest) is dict else None


def packaged_bake(package: str | bytes, threads: int = 0) -> tuple[str, PackagedBake]:
    """(checksum, the package's :class:`PackagedBake`), read and verified once per worker
    process; a later task of the same package reads only its manifest.

    package : the package's path on this machine, or its bytes (a worker on another machine
        need not share the driver's disk)
    threads : this machine's worker threads (0: all cores); the package's own setting belongs
        to the machine that wrote it and may exceed this one's cores
    """
    claimed = _claimed_checksum(package)
    if claimed in _bakes:
        return claimed, _bakes[claimed]
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
    kept = _bakes.get(read.checksum)
    if kept is None:
        kept = PackagedBake.read(read.scene, replace(read.settings, threads=threads))
        while len(_bakes) >= KEPT_BAKES:
            forgotten = next(iter(_bakes))
            _bakes.pop(forgotten)
            for key in [key for key in _rows if key[0] == forgotten]:
                _rows.pop(key)
        _bakes[read.checksum] = kept
    return read.checksum, kept


def _kept_rows(package: str | bytes, start: int, stop: int, threads: int) -> tuple[PackagedBake, KeptRows]:
    """The packaged bake and rows [start, stop)'s table and normalisation, made here once and
    kept: a retried or moved task makes them again, to the same bits."""
    checksum, bake = packaged_bake(package, threads)
    key = (checksum, start, stop)
    if key not in _rows:
        _rows[key] = keep_rows(bake.rows(start, stop), threads)
    return bake, _rows[key]


def run_task(package: str | bytes, start: int, stop: int, task: str, *arguments, threads: int = 0):
    """``core.distributed.row_tasks.<task>`` on rows [start, stop) of a packaged bake, in this
    (worker) process: the rows are built and traced on the first task, then kept."""
    from . import row_tasks

    with blas_on_one_thread():
        bake, kept = _kept_rows(package, start, stop, threads)
        return getattr(row_tasks, task)(bake, kept, *arguments, threads=threads)
