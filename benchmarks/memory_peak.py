"""Where a bake's memory goes: ``python benchmarks/memory_peak.py demo --out DIR`` (any arguments of
``tools/visibake.py``).

Prints the process's resident memory once bpy, the extension and the compiled kernels are
loaded (before any scene), then runs the command under ``tracemalloc`` and prints the largest
allocations alive at its highest traced moment, grouped by where they were made. tracemalloc
sees numpy's arrays; its own bookkeeping makes the run slower and its peak RSS higher than a
plain run's.
"""
from __future__ import annotations

import os
import sys
import threading
import time
import tracemalloc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Snapshots are taken each time the traced total has grown by this much since the last one.
SNAPSHOT_STEP_BYTES = 64 << 20
POLL_SECONDS = 0.05


def resident_mib() -> float:
    """This process's resident memory now (Linux), in MiB."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def main(argv: list[str]) -> int:
    sys.path.insert(0, ROOT)
    from tools import visibake

    extension = visibake.load_extension()
    extension.core.kernels.status()
    print(f"before any scene (bpy, the extension, the kernels): {resident_mib():.0f} MiB")
    tracemalloc.start(6)
    highest = {"bytes": 0, "snapshot": None}
    done = threading.Event()

    def watch():
        while not done.is_set():
            current, _ = tracemalloc.get_traced_memory()
            if current > highest["bytes"] + SNAPSHOT_STEP_BYTES:
                highest["bytes"], highest["snapshot"] = current, tracemalloc.take_snapshot()
            time.sleep(POLL_SECONDS)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    status = extension.cli.main(argv)
    done.set()
    watcher.join()
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
