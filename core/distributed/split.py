"""A visibility table held by ranges of sample rows (docs/scaleout.md), and the executor that
holds them in this process (the reference); the others hold them on a cluster's workers
(core.distributed.engine.ClusterRows) or answer through a farm's job folder
(core.distributed.farm.FarmRows).

The driver of a split bake prepares the scene as one process would, except that its
``Prepared.table`` is a :class:`SplitTable`: every pass that reads the table (the gathers,
their normalisation, the exposed shares, close entries, shadow fractions, ambient
occlusion) runs one task per row range where that range's table is kept, with the same
function one process runs on the whole table, and the rows come back joined in row order.
Each sample's sums run in the same order as in one process, so a split bake equals the
one-process bake bit for bit, whichever executor runs it and however many ranges it has.

The tasks are the functions of core.distributed.row_tasks, named in a task by their name
alone (a worker imports them under its own module path).
"""
from __future__ import annotations

import numpy as np

from ..visibility.table import VisibilityTable


class SplitTable:
    """The driver's handle on a table traced and kept by ranges of sample rows.

    Has what the bake reads of a table without its large arrays: directions (N, 3)
    float64, the per-sample counts (K,) int32 (so :meth:`buried` is local), the ray
    counters and vertex_cells; every pass over the entries is a method that runs a task
    per range (``executor.run``) and joins the rows.

    executor : an executor holding the ranges (:class:`InProcessRows`,
        core.distributed.engine.ClusterRows or core.distributed.farm.FarmRows); stats : each range's
        core.distributed.row_tasks.table_stats, in row order
    """

    def __init__(self, executor, stats: list[dict]):
        self.executor = executor
        first = stats[0]
        self.directions = first["directions"]
        self.vertex_cells = first["vertex_cells"]
        self.traced_per_sample = np.concatenate([s["traced_per_sample"] for s in stats])
        self.backface_per_sample = np.concatenate([s["backface_per_sample"] for s in stats])
        self.rays_cast = sum(int(s["rays_cast"]) for s in stats)
        self.rays_below_horizon = sum(int(s["rays_below_horizon"]) for s in stats)
        self.backface_hits = sum(int(s["backface_hits"]) for s in stats)
        self.remote_bytes = sum(int(s["nbytes"]) for s in stats)

    @property
    def ranges(self) -> list[range]:
        return self.executor.ranges

    @property
    def nbytes(self) -> int:
        """The bytes this process holds of the table (all of it in process, none on a cluster)."""
        return self.executor.local_bytes

    def describe(self) -> dict:
        """What the bake report says of the split (Report.split)."""
        return {"ranges": len(self.ranges), "executor": self.executor.name,
                "table_bytes_held_by_ranges": int(self.remote_bytes)}

    def buried(self) -> np.ndarray:
        """(K,) bool, VisibilityTable.buried's rule on the joined per-sample counts."""
        return 2 * self.backface_per_sample > self.traced_per_sample

    def _per_range(self, *arrays) -> list[tuple]:
        """Each range's rows of ``arrays`` ((K, ...) arrays, or None), as task arguments."""
        return [tuple(None if a is None else a[r.start:r.stop] for a in arrays) for r in self.ranges]

    def gather(self, radiance: np.ndarray, world: np.ndarray, exclude: np.ndarray | None,
               samples: np.ndarray | None, progress=None) -> np.ndarray:
        """(K, C) float64 core.transport.gather.gather of every range, joined; samples not in
        ``samples`` (k,) int64 (if given) get 0. radiance : (layout.size, C) float32;
        world : (N, C) or (C,); exclude : (K, O) bool or None."""
        per_range = []
        for r, (rows_exclude,) in zip(self.ranges, self._per_range(exclude)):
            chosen = None
            if samples is not None:
                chosen = np.asarray(samples, np.int64)
                chosen = chosen[(chosen >= r.start) & (chosen < r.stop)] - r.start
            per_range.append((rows_exclude, chosen))
        parts = self.executor.run("gather_rows", per_range, (np.ascontiguousarray(radiance, np.float32),
                                                              np.asarray(world, np.float64)), progress)
        return np.concatenate(parts)

    def gather_normalisation(self) -> np.ndarray:
        """(K,) float64 core.transport.gather.gather_normalisation, joined."""
        return np.concatenate(self.executor.run("normalisation", [()] * len(self.ranges), ()))

    def exposed_share(self, slots: int) -> np.ndarray:
        """(K,) float64 core.transport.contacts.exposed_share, joined."""
        return np.concatenate(self.executor.run("exposed_share", [()] * len(self.ranges), (int(slots),)))

    def ambient_occlusion(self) -> np.ndarray:
        """(K,) float64 core.transport.gather.ambient_occlusion, joined."""
        return np.concatenate(self.executor.run("ambient_occlusion", [()] * len(self.ranges), ()))

    def close_entries(self, target_reach: np.ndarray, sample_reach: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """core.transport.contacts.table_close_entries over every range, with global sample
        indices, in the whole table's order (by direction, then sample)."""
        parts = self.executor.run("close_entries", self._per_range(sample_reach),
                                  (np.asarray(target_reach, np.float32),))
        joined = [np.concatenate([part[i] for part in parts]) for i in range(5)]
        # Ranges come in row order and each lists its entries by direction, then sample: a
        # stable sort by direction restores the one table's order.
        order = np.argsort(joined[1], kind="stable")
        return tuple(values[order] for values in joined)

    def shadow_fractions(self, regions, light_distance: np.ndarray | None):
        """core.visibility.shadows.ShadowFractions over every range, joined."""
        from ..visibility.shadows import ShadowFractions

        parts = self.executor.run("shadow_fractions", self._per_range(light_distance), (int(regions.count),))
        return ShadowFractions(regions, np.concatenate([lit for lit, _ in parts]),
                               np.concatenate([traced for _, traced in parts]))

    def lamp_irradiance(self, lights, progress=None) -> tuple[np.ndarray, int]:
        """((K, 3) float64, shadow rays) core.transport.direct.lamp_irradiance of ``lights`` at
        every sample, by the ranges where they are kept, joined (the split bake's direct light:
        its shadow fractions come from each range's own table)."""
        parts = self.executor.run("direct_light", [()] * len(self.ranges), (list(lights),), progress)
        return np.concatenate([irradiance for irradiance, _ in parts]), sum(int(rays) for _, rays in parts)

    def whole(self) -> VisibilityTable:
        """The whole table, joined here (for checks and small bakes: a split bake never needs it)."""
        from ..visibility.table import concatenate_columns

        return concatenate_columns(self.executor.run("table", [()] * len(self.ranges), ()))


class InProcessRows:
    """Row ranges traced and kept in this process, their tasks run one after another: the
    executor the cluster's results are checked against.

    parts : the number of row ranges; threads : each task's worker threads (0: all cores)
    """

    name = "in process"

    def __init__(self, parts: int, threads: int = 0):
        self.parts = int(parts)
        self.threads = int(threads)
        self.ranges: list[range] = []
        self.kept: list = []  # per range: core.distributed.rows.KeptRows
        self.prepared = None

    @property
    def local_bytes(self) -> int:
        return sum(int(kept.table.nbytes) for kept in self.kept)

    def start(self, prepared, progress=None) -> SplitTable:
        """Trace every range of ``prepared`` (core.pipeline.prepare.Prepared, without a table)."""
        from . import row_tasks
        from .rows import keep_rows, row_ranges, rows_of

        self.prepared = prepared
        self.ranges = row_ranges(len(prepared.position), self.parts)
        self.kept = []
        for number, r in enumerate(self.ranges):
            self.kept.append(keep_rows(rows_of(prepared, r.start, r.stop), self.threads))
            if progress is not None:
                progress((number + 1) / len(self.ranges))
        return SplitTable(self, [row_tasks.table_stats(prepared, kept, self.threads) for kept in self.kept])

    def run(self, task: str, per_range: list[tuple], shared: tuple, progress=None) -> list:
        """``core.distributed.row_tasks.<task>(prepared, kept rows, *per_range[i], *shared,
        threads)`` for each range i, in row order."""
        from . import row_tasks

        function = getattr(row_tasks, task)
        results = []
        for number, (kept, own) in enumerate(zip(self.kept, per_range)):
            results.append(function(self.prepared, kept, *own, *shared, threads=self.threads))
            if progress is not None:
                progress((number + 1) / len(self.kept))
        return results
