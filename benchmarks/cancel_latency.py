"""How soon a cancel stops a long unwrap in its child process.

    .venv/bin/python benchmarks/cancel_latency.py [--after 0.5] [--runs 3]

The sphere of ``tests/core/test_unwrap_child.py`` (~65k triangles, about 12 s of
xatlas on 2 cores) is unwrapped with ``core.sampling.unwrap_child.unwrap_in_child``;
the cancel is asked for ``--after`` seconds in, and the time from then until
``Cancelled`` reaches the caller (the child killed and its folder removed) is the
latency. The test checks that the cancel takes effect; this measures how fast.

Writes ``benchmarks/results/cancel_latency.json`` with the machine and the date.
"""
import argparse
import importlib.util
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
TEST_MODULE = os.path.join(ROOT, "tests", "core", "test_unwrap_child.py")


def _sphere(segments: int, rings: int):
    spec = importlib.util.spec_from_file_location("cancel_latency_cases", TEST_MODULE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module._sphere(segments, rings)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--after", type=float, default=0.5, help="seconds into the unwrap to cancel")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--poll", type=float, default=0.05, help="seconds between cancel checks")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "cancel_latency.json"))
    args = parser.parse_args(argv)

    from benchmarks.run import write_results
    from core.errors import Cancelled
    from core.sampling.unwrap_child import unwrap_in_child

    positions, triangles = _sphere(256, 128)
    latencies = []
    for _ in range(args.runs):
        cancel_at = time.perf_counter() + args.after
        try:
            unwrap_in_child(positions, triangles, 1024, cancelled=lambda: time.perf_counter() >= cancel_at,
                            poll_seconds=args.poll)
        except Cancelled:
            latencies.append(time.perf_counter() - cancel_at)
        else:
            print("the unwrap finished before the cancel: raise the sphere's size or lower --after", file=sys.stderr)
            return 1
        print(f"cancel to Cancelled: {latencies[-1]:.3f} s", flush=True)
    write_results(args.out, {
        "settings": {"triangles": int(len(triangles)), "resolution": 1024, "after_seconds": args.after,
                     "poll_seconds": args.poll, "runs": args.runs},
        "latency_seconds": [round(value, 4) for value in latencies],
        "worst_seconds": round(max(latencies), 4)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
