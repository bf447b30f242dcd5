"""A local Dask cluster under hostile use (issue 51, item 3): a worker count far beyond the
cores is refused before any process starts, through the command and the panel's preference;
and a bake killed with SIGKILL takes every process of its cluster with it."""
import importlib
import os
import signal
import subprocess
import sys
import time

import bpy

import distributed  # noqa: F401 - pinned (requirements.txt): a broken install fails, not skips
import psutil  # a dependency of distributed: lists the processes
import pytest

from blender_support import REPO_ROOT, extension_module_name
from bpy_scenes import black_world, cube, grid, material, mesh_object, sun


@pytest.fixture
def engine(visibake):
    return importlib.import_module(f"{extension_module_name()}.core.distributed.engine")


def _room():
    black_world()
    ground = mesh_object("Ground", grid(1.0, segments=4), material("White", (0.8, 0.8, 0.8)))
    block = mesh_object("Block", cube(0.5), material("Grey", (0.5, 0.5, 0.5)), location=(0, 0, 0.5), uv_map=None)
    sun(3.0, tilt_degrees=20.0)
    return [ground, block]


@pytest.fixture
def room_blend(clean_scene, tmp_path):
    _room()
    path = tmp_path / "room.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    return path


def _descendants() -> set[int]:
    return {child.pid for child in psutil.Process().children(recursive=True)}


def test_more_workers_than_the_cores_take_are_refused_before_any_process_starts(visibake, engine, room_blend,
                                                                                tmp_path, capfd):
    limit = engine.max_local_workers()
    assert limit == engine.WORKERS_PER_CORE * len(os.sched_getaffinity(0))
    before = _descendants()
    for workers in (limit + 1, 1000):
        assert visibake.cli.main(["bake", str(room_blend), "--out", str(tmp_path / "out"), "--workers", str(workers),
                                  "--no-progress", "--no-cache"]) == 2
        said = capfd.readouterr().err.strip().splitlines()
        assert said and f"--workers {workers}: at most {limit} on this machine" in said[-1], said
    assert _descendants() <= before  # not one scheduler or worker was started
    assert not (tmp_path / "out").exists()


def test_the_panel_refuses_a_cluster_workers_preference_beyond_the_cores(visibake, engine, clean_scene):
    limit = engine.max_local_workers()
    prefs = visibake.operators.adapter.device.preferences()
    if limit + 1 > type(prefs).bl_rna.properties["cluster_workers"].hard_max:
        pytest.skip(f"this machine's {limit} workers are more than the preference offers")
    objects = _room()
    for obj in objects:
        obj.select_set(True)
    uv_maps = {obj.name: list(obj.data.uv_layers.keys()) for obj in objects}
    before = _descendants()
    prefs.cluster_workers = limit + 1
    try:
        with pytest.raises(RuntimeError, match=f"{limit + 1}: at most {limit} on this machine"):
            bpy.ops.visibake.bake()  # an error report raises in scripts
    finally:
        prefs.cluster_workers = 0
    assert _descendants() <= before
    assert {obj.name: list(obj.data.uv_layers.keys()) for obj in objects} == uv_maps  # nothing was unwrapped
    assert not [name for name in bpy.data.images.keys() if name.startswith("VB_")]


def _cluster_processes(parent) -> tuple[list, int]:
    """(every process below ``parent``, how many of them are Dask workers' own worker processes)."""
    found, working = [], 0
    for child in parent.children(recursive=True):
        try:
            line = " ".join(child.cmdline())
            above = child.parent()
            above_line = " ".join(above.cmdline()) if above is not None else ""
        except psutil.Error:
            continue  # gone already
        found.append(child)
        # A `dask worker` (a nanny) runs its worker as a child of its own (multiprocessing's spawn).
        if "spawn_main" in line and "distributed.cli.dask_worker" in above_line:
            working += 1
    return found, working


def test_a_bake_killed_with_sigkill_takes_every_process_of_its_cluster_with_it(room_blend, tmp_path):
    command = subprocess.Popen(
        [sys.executable, str(REPO_ROOT / "tools" / "visibake.py"), "bake", str(room_blend), "--out",
         str(tmp_path / "out"), "--workers", "2", "--resolution", "64", "--directions", "256", "--bounces", "2",
         "--no-progress", "--no-cache"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=str(REPO_ROOT))
    started = []
    try:
        parent = psutil.Process(command.pid)
        deadline = time.monotonic() + 300  # the workers import numpy, embree and the kernels
        while True:
            assert command.poll() is None, f"the bake ended before its workers ran: {command.stderr.read()}"
            assert time.monotonic() < deadline, "the cluster's workers never started"
            processes, working = _cluster_processes(parent)
            if working >= 2:
                started = processes
                break
            time.sleep(0.1)  # polling the process table
        os.kill(command.pid, signal.SIGKILL)
        command.wait(timeout=60)
        assert command.returncode == -signal.SIGKILL  # it was still baking
        # Every process the bake started: its scheduler, both nannies, their workers and helpers.
        _, alive = psutil.wait_procs(started, timeout=60)
        assert not alive, [" ".join(p.cmdline())[:120] for p in alive]
    finally:
        if command.poll() is None:
            command.kill()
            command.wait()
        for process in started:
            try:
                process.kill()
            except psutil.Error:
                pass
        command.stderr.close()
