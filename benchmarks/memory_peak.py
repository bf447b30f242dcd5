"""Where a bake's memory goes: ``python benchmarks/memory_peak.py [--resident-only | --window NAME]
demo --out DIR`` (then any arguments of ``tools/visibake.py``).

Prints the process's resident memory once bpy, the extension and the compiled kernels are
loaded (before any scene), then runs the command under ``tracemalloc`` and prints the highest
resident and traced memory in each stage and pass of the bake (the resident figure split into its
anonymous and file-backed parts at that moment: a table in a scratch file's mapping, and the
libraries' code, are the latter; and glibc's heap in use and free then, where glibc runs), and
the largest allocations alive at its highest traced moment, grouped by where they were made
(``--window NAME``: its highest traced moment inside the windows whose name contains NAME, such
as ``transport``). ``--resident-only`` leaves tracemalloc off (the resident figures are then a
plain run's). tracemalloc sees numpy's arrays; its own bookkeeping makes the run slower and its
peak RSS higher than a plain run's.
"""
from __future__ import annotations

import importlib
import os
import sys
import threading
import time
import tracemalloc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Snapshots are taken each time the traced total has grown by this much since the last one.
SNAPSHOT_STEP_BYTES = 64 << 20
# The same inside a ``--window``, finer: the window's peak is usually not far above its start.
WINDOW_STEP_BYTES = 8 << 20
POLL_SECONDS = 0.05


def resident_mib() -> float:
    """This process's resident memory now (Linux), in MiB."""
    return resident_parts()[0]


def resident_parts() -> tuple[float, float, float]:
    """This process's resident memory now (Linux), in MiB: the whole, and its anonymous and
    file-backed parts (a table held in a scratch file's mapping is the latter)."""
    found = {}
    with open("/proc/self/status") as status:
        for line in status:
            name = line.split(":")[0]
            if name in ("VmRSS", "RssAnon", "RssFile"):
                found[name] = int(line.split()[1]) / 1024
    return found.get("VmRSS", float("nan")), found.get("RssAnon", float("nan")), found.get("RssFile", float("nan"))


def main(argv: list[str]) -> int:
    sys.path.insert(0, ROOT)
    from tools import visibake

    resident_only = bool(argv) and argv[0] == "--resident-only"
    if resident_only:
        argv = argv[1:]
    window_wanted = ""
    if len(argv) > 1 and argv[0] == "--window":
        window_wanted, argv = argv[1], argv[2:]
    extension = visibake.load_extension()
    extension.core.kernels.status()
    print(f"before any scene (bpy, the extension, the kernels): {resident_mib():.0f} MiB")
    if not resident_only:
        tracemalloc.start(6)
    # The highest resident and traced memory of each window of the bake: a window closes when a
    # stage starts (it was the stage before's) or a pass is recorded (it was that pass's).
    windows = []
    window = {"resident": 0.0, "anon": 0.0, "file": 0.0, "heap": (float("nan"), float("nan"))}
    libc = importlib.import_module(f"{extension.__name__}.core.pipeline.budget")._libc()

    def heap_parts() -> tuple[float, float]:
        """glibc's heap in use and free, in MiB (NaN elsewhere): the anonymous memory that
        holds nothing shows as the latter."""
        if libc is None:
            return float("nan"), float("nan")
        info = libc.mallinfo2()
        return info.uordblks / 2**20, info.fordblks / 2**20

    def watch_resident():
        resident, anon, file = resident_parts()
        if resident > window["resident"]:
            window.update(resident=resident, anon=anon, file=file, heap=heap_parts())
    progress = importlib.import_module(f"{extension.__name__}.core.pipeline.progress")
    start_stage, record_pass = progress.Stages.start, progress.Stages.record_pass

    def close(name):
        traced = tracemalloc.get_traced_memory()[1] / 2**20 if tracemalloc.is_tracing() else 0.0
        watch_resident()
        windows.append((name, window["resident"], window["anon"], window["file"], *window["heap"], traced))
        window.update(resident=0.0, anon=0.0, file=0.0)
        if tracemalloc.is_tracing():
            tracemalloc.reset_peak()

    # Which window the bake is in now (a pass's window is named when it closes, so a pass inside
    # the wanted stage counts as that stage's).
    current = {"name": "(start)"}

    def start_and_note(stages, name):
        close(f"stage {getattr(stages, '_noted_stage', '(start)')}")
        stages._noted_stage = current["name"] = name
        return start_stage(stages, name)

    def record_and_note(stages, name, *arguments):
        close(f"  pass {name}")
        return record_pass(stages, name, *arguments)

    progress.Stages.start, progress.Stages.record_pass = start_and_note, record_and_note
    highest = {"bytes": 0, "snapshot": None}
    done = threading.Event()

    def watch():
        while not done.is_set():
            watch_resident()
            if not resident_only and window_wanted in current["name"]:
                traced, _ = tracemalloc.get_traced_memory()
                step = SNAPSHOT_STEP_BYTES if not window_wanted else WINDOW_STEP_BYTES
                if traced > highest["bytes"] + step:
                    highest["bytes"], highest["snapshot"] = traced, tracemalloc.take_snapshot()
            time.sleep(POLL_SECONDS)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    status = extension.cli.main(argv)
    done.set()
    watcher.join()
    close("the rest")
    print("highest memory in each window of the bake (MiB: resident, its anonymous and file-backed parts "
          "then, glibc's heap in use and free then, and traced):")
    for name, resident, anon, file, in_use, free, traced in windows:
        print(f"  {resident:7.0f} {anon:7.0f} {file:7.0f} {in_use:7.0f} {free:7.0f} {traced:7.0f}  {name}")
    if resident_only:
        return status
    print(f"exit status {status}; traced peak {tracemalloc.get_traced_memory()[1] / 2**20:.0f} MiB; "
          f"snapshot at {highest['bytes'] / 2**20:.0f} MiB")
    if highest["snapshot"] is not None:
        for statistic in highest["snapshot"].statistics("traceback")[:20]:
            print(f"{statistic.size / 2**20:8.1f} MiB in {statistic.count} blocks")
            for line in statistic.traceback.format()[-6:]:
                print("        " + line)
    return status


if __name__ == "__main__":
    exit_status = main(sys.argv[1:])
    from tools.blender_compat import compat

    compat.end_module_process(exit_status)
