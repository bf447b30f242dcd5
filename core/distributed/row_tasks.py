"""The passes over a range of sample rows' table, as a split bake runs them
(core.distributed.split): the same functions one process runs on the whole table, given
the rows' table and returning the rows' results.

Each task is ``task(bake, kept, *arguments, threads=...)``: ``bake`` is the bake's
core.pipeline.prepare.Prepared in process, or a worker's core.distributed.rows.PackagedBake
of the same package (of either, a task reads the same bits: settings, meshes, ray scene,
directions, rotations, layout, and the rows' samples by ``sample_rows``),
``kept`` the range's core.distributed.rows.KeptRows. Executors name tasks by their function's name.
"""
from __future__ import annotations

import numpy as np

from ..pipeline.prepare import shadowing_of
from ..transport.contacts import exposed_share as _exposed_share
from ..transport.contacts import table_close_entries
from ..transport.contract import GatherGeometry, GatherSource
from ..transport.direct import lamp_irradiance
from ..transport.gather import ambient_occlusion as _ambient_occlusion
from ..transport.gather import gather
from ..visibility.directions import ShadowRegions
from ..visibility.shadows import shadow_fractions as _shadow_fractions


def table_stats(p, kept, threads: int = 0) -> dict:
    """What the driver keeps of the rows' table (core.distributed.split.SplitTable): its
    directions (N, 3) float64, vertex_cells, per-sample counts (k,) int32, ray counters and
    bytes, and the bake's sample count (the driver checks the worker prepared the same bake)."""
    table = kept.table
    return {"samples": kept.samples, "start": kept.start, "stop": kept.stop, "directions": table.directions,
            "vertex_cells": table.vertex_cells, "traced_per_sample": table.traced_per_sample,
            "backface_per_sample": table.backface_per_sample, "rays_cast": table.rays_cast,
            "rays_below_horizon": table.rays_below_horizon, "backface_hits": table.backface_hits,
            "nbytes": table.nbytes}


def table(p, kept, threads: int = 0):
    """The rows' VisibilityTable itself (for checks: a split bake never moves it)."""
    return kept.table


def gather_rows(p, kept, exclude, samples, radiance, world, threads: int = 0) -> np.ndarray:
    """(k, C) float64 the rows' gather (core.transport.gather.gather) of ``radiance`` (size, C)
    float32 and ``world`` (N, C) or (C,); exclude : (k, O) bool rows or None; samples : the
    rows' own indices (into the range) to gather, or None for all."""
    geometry = GatherGeometry(kept.table, kept.frame_normal, kept.scale, p.layout, threads)
    return gather(geometry, GatherSource(radiance, world, exclude), None, samples)


def normalisation(p, kept, threads: int = 0) -> np.ndarray:
    """(k,) float64 the rows' gather normalisation (made with the rows' table, kept with it)."""
    return kept.scale


def exposed_share(p, kept, slots: int, threads: int = 0) -> np.ndarray:
    """(k,) float64 core.transport.contacts.exposed_share of the rows."""
    return _exposed_share(kept.table, slots, threads)


def ambient_occlusion(p, kept, threads: int = 0) -> np.ndarray:
    """(k,) float64 core.transport.gather.ambient_occlusion of the rows."""
    return _ambient_occlusion(kept.table, kept.frame_normal, kept.scale, threads)


def close_entries(p, kept, sample_reach, target_reach, threads: int = 0) -> tuple[np.ndarray, ...]:
    """core.transport.contacts.table_close_entries of the rows, with the bake's sample indices;
    sample_reach : (k,) the rows' reaches, or None."""
    sample, direction, obj, uv, floor = table_close_entries(kept.table, target_reach, sample_reach, threads)
    return sample + kept.start, direction, obj, uv, floor


def shadow_fractions(p, kept, light_distance, region_count: int, threads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(lit, traced) (k, M) uint16 core.visibility.shadows.shadow_fractions of the rows over
    ``region_count`` regions of the table's directions (as core.transport.contract.Shadowing
    makes them); light_distance : (k,) the rows' distances to a local lamp, or None (a distant one)."""
    regions = ShadowRegions(kept.table.directions, region_count)
    fractions = _shadow_fractions(kept.table, regions, light_distance, p.rotations, kept.group)
    return fractions.lit, fractions.traced


def direct_light(p, kept, lights, threads: int = 0) -> tuple[np.ndarray, int]:
    """((k, 3) float64 irradiance, shadow rays traced) of ``lights`` (core.scene.Light) at the
    rows: core.transport.direct.lamp_irradiance of the rows' samples (their ids in the bake
    seed the sampler), shadow fractions looked up in the rows' own table."""
    return lamp_irradiance(p.sample_rows(kept.start, kept.stop), shadowing_of(p, kept.table, kept.group), lights)
