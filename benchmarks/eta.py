"""How good is the time left the status bar shows? The demo baked as the panel bakes it.

    .venv/bin/python benchmarks/eta.py [--directions 128] [--resolution 256]

Drives ``operators.adapter.modal.ModalBake`` exactly as the modal operator does (a tick every
0.1 s on the main thread, long steps on workers, unwraps in child processes) and
records, at every tick, the estimate of the time left (``Progress.seconds_left``).
Once the bake has ended, the true time left at each tick is known; the error of the
estimate is reported at 10, 25, 50, 75 and 90 % of the run, and as the mean absolute
error over the run in seconds and as a share of the bake's length.

Four runs of the same scene: cold (nothing cached, the UV maps unwrapped), warm (the
visibility and the lighting in the cache), relight-like (the cache valid, a lamp
changed, so the transport runs) and moved (an object moved: the table is updated).

Writes ``benchmarks/results/eta.json`` with the machine, settings and date.
"""
import argparse
import importlib
import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

TICK_SECONDS = 0.1
MARKS = (0.10, 0.25, 0.50, 0.75, 0.90)


def timed_bake(progress_module, modal_module, job_module, bpy, objects) -> dict:
    """One bake driven tick by tick; the estimates and the truth."""
    progress = progress_module.Progress()
    modal = modal_module.ModalBake(job_module.BakeJob(bpy.context, objects, progress=progress), progress)
    started = time.perf_counter()
    samples = []
    trace = []
    while not modal.tick():
        left = progress.seconds_left()
        samples.append((time.perf_counter() - started, left, progress.stage))
        trace.append((round(samples[-1][0], 2), progress.stage, round(progress.fraction, 3),
                      None if left is None else round(left, 2)))
        time.sleep(TICK_SECONDS)
    total = time.perf_counter() - started
    if modal.error is not None:
        raise modal.error
    errors = [(elapsed, left - (total - elapsed), stage) for elapsed, left, stage in samples if left is not None]
    at_marks = {}
    for mark in MARKS:
        near = min(samples, key=lambda sample: abs(sample[0] - mark * total)) if samples else None
        if near is not None and near[1] is not None:
            at_marks[f"{int(mark * 100)}%"] = {"elapsed": round(near[0], 2), "estimate": round(near[1], 2),
                                                "true": round(total - near[0], 2), "stage": near[2]}
    absolute = [abs(error) for _, error, _ in errors]
    mean_absolute = sum(absolute) / len(absolute) if absolute else None
    return {"seconds": round(total, 2), "ticks": len(samples),
            "cache": modal.outcome.report["cache"]["state"],
            "stage_seconds": modal.outcome.report["stage_seconds"],
            "lighting_reused": bool(modal.outcome.report["cache"].get("lighting_reused")),
            "planned_work": {k: float(v) for k, v in progress.work.items()},
            "mean_absolute_error_seconds": round(mean_absolute, 2) if mean_absolute is not None else None,
            "mean_absolute_error_share": round(mean_absolute / total, 3) if mean_absolute is not None else None,
            "first_estimate": round(samples[0][1], 2) if samples and samples[0][1] is not None else None,
            "at": at_marks, "trace": trace}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--directions", type=int, default=128)
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--bounces", type=int, default=2)
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "eta.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import write_results
    from tools.visibake import load_extension

    extension = load_extension()
    import bpy

    demo_scene = importlib.import_module(f"{extension.__name__}.operators.adapter.demo_scene")
    progress = importlib.import_module(f"{extension.__name__}.core.pipeline.progress")
    modal = importlib.import_module(f"{extension.__name__}.operators.adapter.modal")
    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")

    bpy.ops.wm.read_homefile(use_empty=True)
    objects = demo_scene.build_demo_scene(bpy.context.scene)
    props = bpy.context.scene.visibake
    props.directions, props.resolution, props.bounces = args.directions, args.resolution, args.bounces
    props.passes = {"lighting"}
    runs = {}
    with tempfile.TemporaryDirectory(prefix="visibake-eta-") as cache:
        props.cache_dir = cache
        runs["cold"] = timed_bake(progress, modal, job, bpy, objects)
        print("cold", json.dumps(runs["cold"]), flush=True)
        if os.environ.get("ETA_COLD_ONLY"):
            return 0
        runs["warm"] = timed_bake(progress, modal, job, bpy, objects)
        print("warm", json.dumps(runs["warm"]), flush=True)
        lamp = next(o for o in bpy.context.scene.objects if o.type == "LIGHT" and o.data.type == "POINT")
        lamp.data.energy *= 2.0
        runs["lamp_changed"] = timed_bake(progress, modal, job, bpy, objects)
        print("lamp_changed", json.dumps(runs["lamp_changed"]), flush=True)
        torus = bpy.data.objects["Torus"]
        torus.location.x += 0.3
        runs["moved"] = timed_bake(progress, modal, job, bpy, objects)
        print("moved", json.dumps(runs["moved"]), flush=True)
    write_results(args.out, {
        "settings": {"directions": args.directions, "resolution": args.resolution, "bounces": args.bounces,
                     "tick_seconds": TICK_SECONDS, "scene": "demo"},
        "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
