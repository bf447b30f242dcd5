"""One volume bake: read each Volume object's medium, build its scattering tables, light it,
write its grids and the Volume object that renders them (core.volume does the work).

Everything written or created is undone if the bake fails or is cancelled part way.
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import bpy

import numpy as np

from ...core import kernels
from ...core.errors import VolumeRefused
from ...core.outputs.names import inside_folder, unique_components
from ...core.visibility.directions import direction_set
from ...core.volume import tables as volume_tables
from ...core.volume import transport
from . import compat, extract, volume_io

COMBINED_FILE = "volume.vdb"


@dataclass
class VolumeOutcome:
    """What a volume bake made: the report, and how to take it all back."""

    report: dict
    created: list = field(default_factory=list)
    written: list = field(default_factory=list)
    folders: list = field(default_factory=list)

    def rollback(self) -> None:
        for obj in self.created:
            if obj.name in bpy.data.objects:
                volume_io.remove_baked_object(obj)
        for path in self.written:
            if os.path.isfile(path):
                os.remove(path)
        for folder in reversed(self.folders):
            if os.path.isdir(folder) and not os.listdir(folder):
                os.rmdir(folder)
        self.created.clear()
        self.written.clear()


def scene_volumes(scene) -> list:
    """The Volume objects Cycles renders, that VisiBake did not make."""
    visible = extract.render_visible(scene)
    return [o for o in scene.objects if volume_io.is_volume_target(o) and o.as_pointer() in visible]


def run_volume_bake(scene, objects: list, out_dir: str, resolution: int = 64, directions: int = 64,
                    bounces: int = 1, points: int = 2, seed: int = 0, threads: int = 0,
                    progress: Callable[[str, float], None] | None = None) -> VolumeOutcome:
    """Bake every Volume object of ``objects`` into ``out_dir``/<object>/ and add its baked object."""
    if not objects:
        raise VolumeRefused("no Volume object to bake: the scene has none visible (or --objects named none)")
    vdb = compat.openvdb()  # refuses a Blender without the module before any work
    warnings: list[str] = []
    started = time.perf_counter()
    lights = [extract.read_light(lamp, warnings) for lamp in extract.scene_lights(scene)]
    world = extract.read_world(scene, warnings)
    if extract.scene_meshes(scene):
        warnings.append("meshes do not shadow or hide volumes yet: each volume is lit as if alone with the lamps "
                        "and the world")
    report = {"command": "volume", "directions": int(directions), "bounces": int(bounces), "points_per_ray": points,
              "resolution": int(resolution), "kernels": kernels.status().describe(), "volumes": [], "files": [],
              "warnings": warnings}
    outcome = VolumeOutcome(report)
    components = unique_components([o.name for o in objects], reserved=("report.json",))
    set_of_directions = direction_set(int(directions), rotate=True, seed=int(seed))
    try:
        for number, obj in enumerate(objects):
            entry = _bake_one(vdb, obj, os.path.join(out_dir, components[obj.name]), out_dir, resolution,
                              set_of_directions, lights, world, bounces, points, seed, threads, warnings, outcome,
                              _share(progress, obj.name, number, len(objects)))
            report["volumes"].append(entry)
    except BaseException:
        outcome.rollback()
        raise
    report["volume_kernel_load_s"] = round(kernels.volume_load_seconds(), 3)
    report["seconds"] = round(time.perf_counter() - started, 3)
    return outcome


def _share(progress, name: str, number: int, count: int):
    if progress is None:
        return None
    return lambda stage, fraction: progress(f"{name}: {stage}", (number + fraction) / count)


def _bake_one(vdb, obj, folder: str, out_dir: str, resolution, directions, lights, world, bounces, points, seed,
              threads, warnings, outcome: VolumeOutcome, progress) -> dict:
    seconds = {}
    started = time.perf_counter()
    medium, index_to_local = volume_io.read_medium(obj, resolution, warnings)
    seconds["read"] = time.perf_counter() - started
    warnings.extend(w for w in medium.warnings if w not in warnings)
    entry = {"name": obj.name, "grid": list(medium.shape), "active_voxels": 0, "output": None, "seconds": seconds}
    active = int(np.count_nonzero(medium.density))
    entry["active_voxels"] = active
    if active == 0 or medium.extinction == 0:
        warnings.append(f"volume {obj.name!r}: its density is zero everywhere; it was skipped")
        return entry
    if progress:
        progress("scattering tables", 0.0)
    started = time.perf_counter()
    table = volume_tables.build_tables(medium, directions, points=points, jitter_seed=seed, threads=threads)
    seconds["tables"] = time.perf_counter() - started
    entry["table_mib"] = round(table.nbytes / 2 ** 20, 2)
    started = time.perf_counter()
    light = transport.light_medium(medium, table, lights, world, bounces, threads=threads,
                                   progress=(lambda stage, f: progress(stage, 0.3 + 0.6 * f)) if progress else None)
    seconds["light"] = time.perf_counter() - started
    for line in light.warnings:
        if line not in warnings:
            warnings.append(line)
    total = light.total
    emission = (medium.extinction * medium.density[..., None] * medium.albedo) * total
    if medium.emission is not None:
        emission = emission + medium.emission
    grids = {"scattered": total, "direct": light.direct, "indirect": light.indirect,
             "emission": emission.astype(np.float32), "density": medium.density}
    started = time.perf_counter()
    if not os.path.isdir(folder):
        os.makedirs(folder)
        outcome.folders.append(folder)
    for name, values in grids.items():
        path = inside_folder(out_dir, os.path.basename(folder), f"{name}.vdb")
        outcome.written.append(path)
        volume_io.write_grids(vdb, path, {name: values}, index_to_local)
    combined = inside_folder(out_dir, os.path.basename(folder), COMBINED_FILE)
    outcome.written.append(combined)
    volume_io.write_grids(vdb, combined, {"density": medium.density, "emission": grids["emission"]}, index_to_local)
    baked = volume_io.make_baked_object(obj, combined, medium.extinction, warnings)
    outcome.created.append(baked)
    seconds["write"] = time.perf_counter() - started
    outcome.report["files"] += [inside_folder(out_dir, os.path.basename(folder), f"{n}.vdb") for n in grids]
    outcome.report["files"].append(combined)
    entry.update(output=baked.name, bounce_means=[m.tolist() for m in light.bounce_means],
                 max_scattered=float(total.max()))
    entry["seconds"] = {key: round(value, 3) for key, value in seconds.items()}
    return entry
