"""A medium's scattering tables held by ranges of its active voxels (docs/scaleout.md): the
volume's counterpart of core.distributed.split.

Each range's tables are built where the range runs (core.volume.tables.build_tables with
``voxel_range``: a point's hash takes its voxel's index among all the active ones) and kept
there. Every pass that reads the tables runs per range and the rows come back joined: the
bounces' gathers (from the dilated source grid, built once on the driver), the world's light
and the light the meshes reflect (each hit point's lamp sampler seeded by its voxel's index).
A voxel's sums run in the same order as in one process, so the light is the same bits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..version import visibake_version

# Ranges a process keeps built at once; the oldest goes first.
KEPT_RANGES = 16
# (setup key, start, stop) -> (ScatteringTables of the range, its Occluders or None), in this process.
_kept: dict = {}


@dataclass(frozen=True)
class VolumeSetup:
    """What a range's tables are built from. key : core.volume.cache.table_key of the rest (it
    names the kept ranges); medium : core.volume.medium.Medium; directions (N, 3) float64;
    points, step, seed as build_tables takes them; meshes : the occluders as
    core.volume.occluders.Occluders.from_meshes takes them; version : the driver's VisiBake
    (a worker of another refuses the setup)."""

    key: str
    medium: object
    directions: np.ndarray
    points: int
    step: float
    seed: int | None
    meshes: list
    version: str = ""

    @classmethod
    def of(cls, medium, directions, points: int, step: float, seed: int | None, meshes: list) -> VolumeSetup:
        from ..volume.cache import table_key

        return cls(table_key(medium, directions, points, step, seed, meshes), medium,
                   np.asarray(directions, np.float64), int(points), float(step), seed, list(meshes),
                   visibake_version())


def _range_tables(setup: VolumeSetup, start: int, stop: int, threads: int):
    from ..volume.occluders import Occluders
    from ..volume.tables import build_tables

    found = _kept.get((setup.key, start, stop))
    if found is None:
        occluders = Occluders.from_meshes(setup.meshes, threads) if setup.meshes else None
        tables = build_tables(setup.medium, setup.directions, setup.points, setup.step, setup.seed, threads,
                              occluders, voxel_range=range(start, stop))
        while len(_kept) >= KEPT_RANGES:
            _kept.pop(next(iter(_kept)))
        found = _kept[setup.key, start, stop] = (tables, occluders)
    return found


def volume_task(setup: VolumeSetup, start: int, stop: int, task: str, *arguments, threads: int = 0):
    """Task ``task`` on active voxels [start, stop) of ``setup``, in this (worker) process:
    "stats", "gather" (source grid), "world_light" (radiance (N, 3)), "reflected_light"
    (lights, area light samples)."""
    from ..volume.occluders import reflected_light
    from ..volume.transport import gather_source, world_light
    from .part_tasks import check_version

    check_version(setup.version)
    tables, occluders = _range_tables(setup, start, stop, threads)
    if task == "stats":
        return {"nbytes": tables.nbytes, "with_meshes": tables.sees_world is not None}
    if task == "gather":
        return gather_source(tables, *arguments, threads)
    if task == "world_light":
        return world_light(tables, *arguments, threads=threads)
    if task == "reflected_light":
        return reflected_light(setup.medium, tables, occluders, *arguments, threads=threads, first_voxel=start)
    raise ValueError(f"no volume task {task!r}")


class SplitVolumeTables:
    """The driver's handle on a medium's tables held by ranges of active voxels.

    voxels (V, 3) int32 and directions (N, 3) float64 as ScatteringTables'; sees_world is
    True where the tables were built with meshes (its per-ray flags stay with the ranges),
    else None; nbytes : the tables' bytes, all held by the ranges.
    """

    def __init__(self, executor, voxels: np.ndarray, directions: np.ndarray, stats: list[dict]):
        self.executor = executor
        self.voxels = voxels
        self.directions = directions
        self.sees_world = True if stats and stats[0]["with_meshes"] else None
        self.nbytes = sum(int(s["nbytes"]) for s in stats)

    def _joined(self, task: str, *arguments) -> np.ndarray:
        parts = self.executor.run(task, [()] * len(self.executor.ranges), arguments)
        return np.concatenate(parts) if parts else np.zeros((0, 3))

    def gather(self, source: np.ndarray) -> np.ndarray:
        """(V, 3) float64 core.volume.transport.gather_source of every range."""
        return self._joined("gather", source)

    def world_light(self, radiance: np.ndarray) -> np.ndarray:
        """(V, 3) float64 core.volume.transport.world_light of every range."""
        return self._joined("world_light", np.asarray(radiance, np.float64))

    def reflected_light(self, lights: list, area_light_samples: int) -> np.ndarray:
        """(V, 3) float64 core.volume.occluders.reflected_light of every range."""
        return self._joined("reflected_light", list(lights), int(area_light_samples))


class InProcessVolumeRows:
    """A medium's ranges built and run one after another in this process: the reference."""

    name = "in process"

    def __init__(self, setup: VolumeSetup, parts: int, threads: int = 0):
        self.state = setup
        self.parts, self.threads = int(parts), int(threads)
        self.ranges: list[range] = []

    def run(self, task: str, per_range: list[tuple], shared: tuple, progress=None) -> list:
        """volume_task per range, in order (per_range : each range's own arguments, before ``shared``)."""
        results = []
        for number, (r, own) in enumerate(zip(self.ranges, per_range)):
            results.append(volume_task(self.state, r.start, r.stop, task, *own, *shared, threads=self.threads))
            if progress is not None:
                progress((number + 1) / len(self.ranges))
        return results


def split_tables(executor, setup: VolumeSetup) -> SplitVolumeTables:
    """Build ``setup``'s tables by ``executor.parts`` ranges of active voxels on ``executor``
    (InProcessVolumeRows, or core.distributed.engine.ClusterRows given ``setup`` as its state
    and volume_task as its function)."""
    from .rows import row_ranges

    voxels = setup.medium.active()
    executor.ranges = row_ranges(len(voxels), executor.parts)
    return SplitVolumeTables(executor, voxels, np.asarray(setup.directions, np.float64),
                             executor.run("stats", [()] * len(executor.ranges), ()))
