"""One volume bake: read each Volume object's medium, build its scattering tables, light it,
write its grids and the Volume object that renders them (core.volume does the work).

The steps are split as Blender needs them: :meth:`VolumeJob.read` and :meth:`VolumeJob.finish`
touch bpy (the main thread), :meth:`VolumeJob.compute` does not (the panel runs it on a worker
thread, core.kernels releasing the GIL). Everything written or created is undone if the bake
fails or is cancelled part way (:meth:`VolumeJob.abort`).
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


def preferred_threads() -> int:
    """The Threads preference (0: all cores), or 0 where VisiBake is not an enabled add-on."""
    from . import device
    return int(getattr(device.preferences(), "threads", 0) or 0)


def scene_volumes(scene) -> list:
    """The Volume objects Cycles renders, that VisiBake did not make."""
    visible = extract.render_visible(scene)
    return [o for o in scene.objects if volume_io.is_volume_target(o) and o.as_pointer() in visible]


@dataclass
class _Volume:
    """One volume through the steps: its medium, then its light."""

    obj: object
    entry: dict
    medium: object = None
    index_to_local: np.ndarray | None = None
    light: object = None


class VolumeJob:
    """Bake every Volume object of ``objects`` into ``out_dir``/<object>/ and add its baked object.

    ``progress(stage, fraction)`` may raise core.errors.Cancelled; it is called between passes.
    """

    needs_main_thread = False

    def __init__(self, scene, objects: list, out_dir: str, resolution: int = 64, directions: int = 64,
                 bounces: int = 1, points: int = 2, seed: int = 0, threads: int = 0,
                 progress: Callable[[str, float], None] | None = None):
        self.scene, self.objects, self.out_dir = scene, list(objects), out_dir
        self.resolution, self.directions, self.bounces, self.points = resolution, directions, bounces, points
        self.seed, self.threads = int(seed), int(threads)
        self.progress = progress or (lambda stage, fraction: None)
        self.warnings: list[str] = []
        self.report = {"command": "volume", "directions": int(directions), "bounces": int(bounces),
                       "points_per_ray": int(points), "resolution": int(resolution), "volumes": [], "files": [],
                       "grids": dict(volume_io.OUTPUT_GRIDS), "warnings": self.warnings}
        self.outcome = VolumeOutcome(self.report)
        self.volumes: list[_Volume] = []
        self.started = time.perf_counter()

    def run(self) -> VolumeOutcome:
        """All steps in turn (the command line, scripts)."""
        try:
            self.read()
            self.compute()
            return self.finish()
        except BaseException:
            self.abort()
            raise

    def modal_steps(self) -> list:
        """(name, step, on a worker thread) for core ModalBake."""
        return [("read", self.read, False), ("compute", self.compute, True), ("finish", self.finish, False)]

    def expected_work(self) -> dict:
        return {}

    def read(self) -> None:
        """Main thread: the lamps, the world and each volume's medium."""
        if not self.objects:
            raise VolumeRefused("no Volume object to bake: the scene has none visible (or none was chosen)")
        if not self.out_dir:
            raise VolumeRefused("set an Output Folder (or save the .blend): the baked grids are .vdb files written "
                                "there")
        self.vdb = compat.openvdb()  # refuses a Blender without the module before any work
        self.lights = [extract.read_light(lamp, self.warnings) for lamp in extract.scene_lights(self.scene)]
        self.world = extract.read_world(self.scene, self.warnings)
        if extract.scene_meshes(self.scene):
            self.warnings.append("meshes do not shadow or hide volumes yet: each volume is lit as if alone with "
                                 "the lamps and the world")
        for number, obj in enumerate(self.objects):
            self.progress("read", number / len(self.objects))
            started = time.perf_counter()
            medium, index_to_local = volume_io.read_medium(obj, self.resolution, self.warnings)
            for line in medium.warnings:
                if line not in self.warnings:
                    self.warnings.append(line)
            entry = {"name": obj.name, "grid": list(medium.shape),
                     "active_voxels": int(np.count_nonzero(medium.density)), "output": None,
                     "seconds": {"read": round(time.perf_counter() - started, 3)}}
            self.report["volumes"].append(entry)
            if entry["active_voxels"] == 0:
                self.warnings.append(f"volume {obj.name!r}: its density is zero everywhere; it was skipped")
                continue
            if medium.extinction == 0:
                self.warnings.append(f"volume {obj.name!r}: its material's Density is 0 (nothing scatters); it was "
                                     "skipped")
                continue
            self.volumes.append(_Volume(obj, entry, medium, index_to_local))

    def compute(self) -> None:
        """Any thread (no bpy): the tables and the light of each volume."""
        directions = direction_set(int(self.directions), rotate=True, seed=self.seed)
        for number, volume in enumerate(self.volumes):
            def share(stage, fraction, number=number, name=volume.obj.name):
                self.progress(f"{name}: {stage}", (number + 0.3 + 0.7 * fraction) / len(self.volumes))

            share("scattering tables", 0.0)
            started = time.perf_counter()
            table = volume_tables.build_tables(volume.medium, directions, points=self.points,
                                               jitter_seed=self.seed, threads=self.threads)
            volume.entry["seconds"]["tables"] = round(time.perf_counter() - started, 3)
            volume.entry["table_mib"] = round(table.nbytes / 2 ** 20, 2)
            started = time.perf_counter()
            volume.light = transport.light_medium(volume.medium, table, self.lights, self.world, self.bounces,
                                                  threads=self.threads, progress=share)
            volume.entry["seconds"]["light"] = round(time.perf_counter() - started, 3)
            for line in volume.light.warnings:
                if line not in self.warnings:
                    self.warnings.append(line)

    def finish(self) -> VolumeOutcome:
        """Main thread: the grids into the output folder, and the baked Volume objects."""
        components = unique_components([v.obj.name for v in self.volumes], reserved=("report.json",))
        for volume in self.volumes:
            started = time.perf_counter()
            self._write(volume, components[volume.obj.name])
            volume.entry["seconds"]["write"] = round(time.perf_counter() - started, 3)
        self.report["kernels"] = kernels.status().describe()
        self.report["volume_kernel_load_s"] = round(kernels.volume_load_seconds(), 3)
        self.report["seconds"] = round(time.perf_counter() - self.started, 3)
        return self.outcome

    def abort(self) -> None:
        """Take back what was written and created."""
        self.outcome.rollback()

    def _write(self, volume: _Volume, component: str) -> None:
        medium, light, outcome = volume.medium, volume.light, self.outcome
        total = light.total
        emission = (medium.extinction * medium.density[..., None] * medium.albedo) * total
        if medium.emission is not None:
            emission = emission + medium.emission
        grids = {"scattered": total, "direct": light.direct, "indirect": light.indirect,
                 "emission": emission.astype(np.float32), "density": medium.density}
        folder = inside_folder(self.out_dir, component)
        if not os.path.isdir(folder):
            missing = []
            parent = folder
            while not os.path.exists(parent):
                missing.append(parent)
                parent = os.path.dirname(parent)
            os.makedirs(folder)
            outcome.folders += reversed(missing)
        for name, values in grids.items():
            path = inside_folder(self.out_dir, component, f"{name}.vdb")
            outcome.written.append(path)
            volume_io.write_grids(self.vdb, path, {name: values}, volume.index_to_local)
            self.report["files"].append(path)
        combined = inside_folder(self.out_dir, component, COMBINED_FILE)
        outcome.written.append(combined)
        volume_io.write_grids(self.vdb, combined, {"density": medium.density, "emission": grids["emission"]},
                              volume.index_to_local)
        self.report["files"].append(combined)
        baked = volume_io.make_baked_object(volume.obj, combined, medium.extinction)
        outcome.created.append(baked)
        volume.entry.update(output=baked.name, bounce_means=[m.tolist() for m in light.bounce_means],
                            max_scattered=float(total.max()))
