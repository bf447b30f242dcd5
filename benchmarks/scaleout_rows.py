"""Scale-out (issue 20): what one worker does for its ranges of the demo, in this process.

    export NUMBA_CACHE_DIR=/tmp/numba-cache
    PYTHONPATH=. .venv/bin/python benchmarks/scaleout_rows.py [--ranges 2] [--threads 2]
    MALLOC_TRIM_THRESHOLD_=65536 PYTHONPATH=. .venv/bin/python benchmarks/scaleout_rows.py

The demo is extracted in bpy and packaged (as benchmarks/scaleout.py does), then, without
Blender: the package read as a worker reads it (core.distributed.rows.PackagedBake), and per
range the samples of the objects it covers built (``sample_rows``) and its table traced and
normalised (``keep_rows``), against the whole preparation's samples (``prepare`` without a
table). The second command runs it under the malloc trimming a Dask nanny sets by default,
which local clusters now turn off (core.distributed.engine.NANNY_ENVIRONMENT).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ranges", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    from benchmarks.scaleout import write_demo_package

    folder = tempfile.mkdtemp(prefix="visibake-rows-")
    path = os.path.join(folder, "demo.vbpkg")
    write_demo_package(path)
    from core import kernels
    from core.distributed import rows
    from core.distributed.package import read_package
    from core.pipeline.prepare import prepare

    kernels.status()
    read = read_package(path)
    settings = replace(read.settings, threads=args.threads)
    started = time.perf_counter()
    whole = prepare(read.scene, settings, table_needed=False)
    whole_s = time.perf_counter() - started
    started = time.perf_counter()
    bake = rows.PackagedBake.read(read.scene, settings)
    read_s = time.perf_counter() - started
    print(f"MALLOC_TRIM_THRESHOLD_={os.environ.get('MALLOC_TRIM_THRESHOLD_', 'unset')}, {args.threads} threads: "
          f"whole preparation {whole_s:.2f} s; the package read as a worker {read_s:.2f} s", flush=True)
    for r in rows.row_ranges(len(whole.position), args.ranges):
        started = time.perf_counter()
        prepared = bake.rows(r.start, r.stop)
        built_s = time.perf_counter() - started
        started = time.perf_counter()
        rows.keep_rows(prepared, args.threads)
        traced_s = time.perf_counter() - started
        print(f"rows {r.start}-{r.stop}: samples built {built_s:.2f} s, traced and normalised {traced_s:.2f} s",
              flush=True)
    os.remove(path)
    os.rmdir(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
