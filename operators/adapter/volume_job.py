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
from ...core.outputs.ownership import StagedWrites, refuse_foreign, write_record
from ...core.visibility.directions import direction_set
from ...core.volume import cache as volume_cache
from ...core.volume import tables as volume_tables
from ...core.volume import transport
from ...core.volume.occluders import Occluders, SurfaceMesh
from . import compat, device, extract, volume_io
from .job import visibility_cache
from .modal import SteppedJob

COMBINED_FILE = "volume.vdb"
# One file per grid (the names core.volume's light gives them), then COMBINED_FILE.
GRID_FILES = ("scattered", "direct", "indirect", "emission", "density")
# The folder record (core.outputs.ownership) that makes a volume's grids VisiBake's to replace.
RECORD_FORMAT = "visibake-volume"
RECORD_FILE = "visibake-volume.json"


@dataclass
class VolumeOutcome:
    """What a volume bake made: the report, and how to take it all back."""

    report: dict
    created: list = field(default_factory=list)
    files: StagedWrites = field(default_factory=StagedWrites)

    def rollback(self) -> None:
        for obj in self.created:
            if obj.name in bpy.data.objects:
                volume_io.remove_baked_object(obj)
        self.files.rollback()
        self.created.clear()


def preferred_threads() -> int:
    """The Threads preference (0: all cores), or 0 where VisiBake is not an enabled add-on."""
    return int(getattr(device.preferences(), "threads", 0) or 0)


def _surface(mesh, casts_shadow: bool, seen_by_scattering: bool) -> SurfaceMesh:
    """A core.scene.Mesh as the volume sees it: its triangles' albedo and emission from their
    materials (an image texture's mean colour where the material has one)."""
    albedo = np.array([np.asarray(m.base_color_texture, np.float64).reshape(-1, 3).mean(axis=0)
                       if m.base_color_texture is not None and np.size(m.base_color_texture) else m.base_color
                       for m in mesh.materials] or [np.full(3, 0.8)], np.float32)
    emission = np.array([m.emission for m in mesh.materials] or [np.zeros(3)], np.float32)
    index = np.clip(mesh.material_index, 0, len(albedo) - 1)
    return SurfaceMesh(mesh.positions, mesh.triangles, casts_shadow, seen_by_scattering,
                       np.clip(albedo[index], 0.0, 1.0), emission[index] if emission.any() else None)


def occluder_meshes(scene, volumes: list) -> list[SurfaceMesh]:
    """The meshes Cycles renders around ``volumes`` (core.volume.occluders.SurfaceMesh): mesh
    objects and the instances and curves the depsgraph makes (extract.scene_geometry), less
    the meshes that are themselves media and the objects whose ray visibility hides them
    from volume scattering and shadows."""
    ignored: list[str] = []  # the surface bake's own warnings about these meshes do not apply here
    depsgraph = bpy.context.evaluated_depsgraph_get()
    media = {o.as_pointer() for o in volumes}
    meshes = []
    for obj in extract.scene_meshes(scene):
        if obj.as_pointer() in media or volume_io.is_mesh_volume(obj):
            continue
        scatter = bool(getattr(obj, "visible_volume_scatter", True))
        shadow = bool(getattr(obj, "visible_shadow", True))
        if not (scatter or shadow):
            continue
        meshes.append(_surface(extract.read_mesh(obj, depsgraph, "", (1, 1), False, ignored), shadow, scatter))
    for mesh in extract.scene_geometry(depsgraph, scene, ignored).meshes:
        meshes.append(_surface(mesh, mesh.casts_shadow, True))
    return meshes


def scene_volumes(scene) -> list:
    """The media Cycles renders, that VisiBake did not make: Volume objects, and meshes whose
    material fills them with a Principled Volume (voxelised)."""
    visible = extract.render_visible(scene)
    return [o for o in scene.objects
            if (volume_io.is_volume_target(o) or volume_io.is_mesh_volume(o)) and o.as_pointer() in visible]


@dataclass
class _Volume:
    """One volume through the steps: its medium, then its light."""

    obj: object
    entry: dict
    medium: object = None
    index_to_local: np.ndarray | None = None
    light: object = None
    folder: str = ""


class VolumeJob(SteppedJob):
    """Bake every Volume object of ``objects`` into ``out_dir``/<object>/ and add its baked object.

    ``progress(stage, fraction)`` may raise core.errors.Cancelled; it is called between passes.
    """

    def __init__(self, scene, objects: list, out_dir: str, resolution: int = 64, directions: int = 64,
                 bounces: int = 1, points: int = 2, seed: int = 0, threads: int = 0,
                 progress: Callable[[str, float], None] | None = None, device_name: str | None = None,
                 cluster=None):
        """device_name : 'auto', 'gpu' or 'cpu' for the lamps' slice sweeps (the GPU twin,
        gpu_shaders.volume_sweep); None: the preference. The tables and the bounces run on the
        CPU kernels. cluster : core.distributed.engine.ClusterOptions, or None: each medium's
        tables are built and read by ranges of voxels on a Dask cluster (the same grids, bit
        for bit; not cached)."""
        self.cluster = cluster
        self.scene, self.objects, self.out_dir = scene, list(objects), out_dir
        self.device_name = device_name
        self.sweep_pass = None
        self.resolution, self.directions, self.bounces, self.points = resolution, directions, bounces, points
        self.seed, self.threads = int(seed), int(threads)
        self.progress = progress or (lambda stage, fraction: None)
        self.warnings: list[str] = []
        self.report = {"command": "volume", "directions": int(directions), "bounces": int(bounces),
                       "points_per_ray": int(points), "resolution": int(resolution), "volumes": [], "files": [],
                       "grids": dict(volume_io.OUTPUT_GRIDS), "warnings": self.warnings}
        # A full disk's message names the output folder the user chose.
        self.outcome = VolumeOutcome(self.report, files=StagedWrites(os.path.abspath(out_dir) if out_dir else None))
        self.volumes: list[_Volume] = []
        self.occluders = None
        self.meshes: list = []
        self.cache = None
        self.started = time.perf_counter()

    @property
    def needs_main_thread(self) -> bool:
        """The GPU sweep needs Blender's GPU context, which only the main thread holds."""
        return self.sweep_pass is not None

    def modal_steps(self) -> list:
        """(name, step, on a worker thread; None: unless :attr:`needs_main_thread`) for ModalBake."""
        return [("read", self.read, False), ("compute", self.compute, None), ("finish", self.finish, False)]

    def read(self) -> None:
        """Main thread: the lamps, the world and each volume's medium."""
        if not self.objects:
            raise VolumeRefused("no Volume object to bake: the scene has none visible (or none was chosen)")
        if not self.out_dir:
            raise VolumeRefused("set an Output Folder (or save the .blend): the baked grids are .vdb files written "
                                "there")
        self.vdb = compat.openvdb()  # refuses a Blender without the module before any work
        self.cache = visibility_cache(self.scene)
        requested = self.device_name or getattr(device.preferences(), "device", "auto") or "auto"
        choice = device.choose(bpy.context, requested)
        self.report["device"] = {**choice.report, "passes": "the lamps' slice sweeps" if choice.name == "gpu"
                                 else "none (every pass on the CPU kernels)"}
        if choice.name == "gpu":
            from ...gpu_shaders import volume_sweep
            self.sweep_pass = volume_sweep.sweep_transmittance
        self.report["cache"] = self.cache.folder if self.cache is not None else None
        self.lights = [extract.read_light(lamp, self.warnings) for lamp in extract.scene_lights(self.scene)]
        self.world = extract.read_world(self.scene, self.warnings)
        self.meshes = meshes = occluder_meshes(self.scene, self.objects)
        self.occluders = Occluders.from_meshes(meshes, self.threads)
        self.report["occluders"] = {"meshes": len(meshes),
                                    "triangles": self.occluders.triangles if self.occluders else 0}
        if self.occluders is not None:
            self.warnings.append("meshes light the volumes with their emission and the lamp light they reflect "
                                 "(diffuse, each triangle's base colour, first order); the world light and the "
                                 "volume's light they reflect are left out, and the volumes do not shadow the "
                                 "meshes' own bake")
        for number, obj in enumerate(self.objects):
            self.progress("read", number / len(self.objects))
            started = time.perf_counter()
            read = volume_io.read_mesh_medium if obj.type == "MESH" else volume_io.read_medium
            medium, index_to_local = read(obj, self.resolution, self.warnings)
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
        # Before any work: a file of the user's where a grid would go is refused, not replaced.
        refuse_foreign(path for files in self._planned_files().values() for path in files)

    def _planned_files(self) -> dict:
        """{volume's folder: [the paths its bake writes, its record last]} (absolute)."""
        components = unique_components([v.obj.name for v in self.volumes], reserved=("report.json",))
        planned = {}
        for volume in self.volumes:
            component = components[volume.obj.name]
            names = [f"{name}.vdb" for name in GRID_FILES] + [COMBINED_FILE, RECORD_FILE]
            planned[inside_folder(self.out_dir, component)] = [inside_folder(self.out_dir, component, name)
                                                               for name in names]
            volume.folder = inside_folder(self.out_dir, component)
        return planned

    def compute(self) -> None:
        """Any thread (no bpy): the tables and the light of each volume."""
        if self.cluster is None:
            self._compute(None)
            return
        from ...core.distributed.engine import cluster_parts

        self.progress("starting the cluster", 0.0)
        with cluster_parts(self.cluster, self.threads) as cluster:
            self._compute(cluster)
        self.report["split"] = {"parts": cluster[1], "cluster": self.cluster.describe()}

    def _tables_on(self, cluster, volume, directions):
        """A medium's tables by ranges of voxels on ``cluster`` (client, parts, threads)."""
        from ...core.distributed.engine import ClusterRows
        from ...core.distributed.volume_rows import VolumeSetup, split_tables, volume_task

        client, parts, threads = cluster
        setup = VolumeSetup.of(volume.medium, directions, self.points, volume_tables.STEP, self.seed, self.meshes)
        return split_tables(ClusterRows(client, setup, parts, threads, function=volume_task), setup)

    def _compute(self, cluster) -> None:
        directions = direction_set(int(self.directions), rotate=True, seed=self.seed)
        for number, volume in enumerate(self.volumes):
            def share(stage, fraction, number=number, name=volume.obj.name):
                self.progress(f"{name}: {stage}", (number + 0.3 + 0.7 * fraction) / len(self.volumes))

            share("scattering tables", 0.0)
            started = time.perf_counter()
            def build(volume=volume, share=share):
                return volume_tables.build_tables(
                    volume.medium, directions, points=self.points, step=volume_tables.STEP, jitter_seed=self.seed,
                    threads=self.threads, occluders=self.occluders,
                    progress=lambda fraction: share("scattering tables", 0.5 * fraction))

            if cluster is not None:
                table, volume.entry["tables"] = self._tables_on(cluster, volume, directions), "built on the cluster"
            else:
                table, volume.entry["tables"] = volume_cache.cached_tables(
                    self.cache, volume.obj.name, volume.medium, directions, self.points, volume_tables.STEP,
                    self.seed, self.meshes, build, self.warnings)
            volume.entry["seconds"]["tables"] = round(time.perf_counter() - started, 3)
            volume.entry["table_mib"] = round(table.nbytes / 2 ** 20, 2)
            started = time.perf_counter()
            volume.light = transport.light_medium(
                volume.medium, table, self.lights, self.world, self.bounces, threads=self.threads,
                progress=lambda stage, fraction: share(stage, 0.5 + 0.5 * fraction), occluders=self.occluders,
                sweep_pass=self.sweep_pass)
            volume.entry["seconds"]["light"] = round(time.perf_counter() - started, 3)
            for line in volume.light.warnings:
                if line not in self.warnings:
                    self.warnings.append(line)

    def finish(self) -> VolumeOutcome:
        """Main thread: the grids into the output folder, and the baked Volume objects."""
        planned = self._planned_files()
        refuse_foreign(path for files in planned.values() for path in files)  # a file made while it computed
        for volume in self.volumes:
            started = time.perf_counter()
            self._write(volume, planned[volume.folder])
            volume.entry["seconds"]["write"] = round(time.perf_counter() - started, 3)
        self.report["kernels"] = kernels.status().describe()
        self.report["volume_kernel_load_s"] = round(kernels.volume_load_seconds(), 3)
        self.report["seconds"] = round(time.perf_counter() - self.started, 3)
        return self.outcome

    def abort(self) -> None:
        """Take back what was written and created."""
        self.outcome.rollback()

    def _write(self, volume: _Volume, paths: list) -> None:
        medium, light, outcome = volume.medium, volume.light, self.outcome
        total = light.total
        emission = (medium.extinction * medium.density[..., None] * medium.albedo) * total
        if medium.emission is not None:
            emission = emission + medium.emission
        grids = {"scattered": total, "direct": light.direct, "indirect": light.indirect,
                 "emission": emission.astype(np.float32), "density": medium.density}
        staged = outcome.files
        staged.make_folder(volume.folder)
        *grid_paths, combined, record = paths
        # The record first, listing every file: a run killed part way leaves files that stay VisiBake's.
        with staged.staged(record) as temporary:
            write_record(temporary, RECORD_FORMAT, [os.path.basename(p) for p in paths[:-1]],
                         {"object": volume.obj.name})
        self.report["files"].append(record)  # a file it wrote, as the CLI's count says

        def whole(path):
            volume_io.check_grids(self.vdb, path)

        for name, path in zip(GRID_FILES, grid_paths):
            with staged.staged(path, whole) as temporary:
                volume_io.write_grids(self.vdb, temporary, {name: grids[name]}, volume.index_to_local)
            self.report["files"].append(path)
        with staged.staged(combined, whole) as temporary:
            volume_io.write_grids(self.vdb, temporary, {"density": medium.density, "emission": grids["emission"]},
                                  volume.index_to_local)
        self.report["files"].append(combined)
        baked = volume_io.make_baked_object(volume.obj, combined, medium.extinction)
        outcome.created.append(baked)
        volume.entry.update(output=baked.name, bounce_means=[m.tolist() for m in light.bounce_means],
                            max_scattered=float(total.max()))
