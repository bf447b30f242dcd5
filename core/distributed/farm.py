"""A split bake on a render farm (Flamenco): steps that exchange files in a job folder on the
farm's shared storage, instead of a cluster's messages.

A farm runs separate commands, each a process of its own, in an order fixed before the job
starts (tasks with dependencies), so the driver cannot wait for its row tasks in memory. It
is run again instead, once per step, and replays: :class:`FarmRows` is the executor of the
driver's split table (core.distributed.split), and numbers the executor calls it meets. A
call whose parts' results are in the folder is answered from them; the first call without
them is written to the folder, and the driver stops (:class:`PartsPending`). Then one part
command per row range answers it (:func:`run_part`), and the next step runs the driver again,
which now gets one call further. The driver is deterministic (the bake's preparation and
direct light are the same bits every time), so every replay asks the same calls with the same
arguments, and the finished bake equals the one-process bake bit for bit.

The job folder (one bake; never shared by two)::

    package.vbpkg            the scene package (core.distributed.package), written by the first step
    pending.json             {"call": n} the call the parts answer next, or {"done": true}
    calls/NNNN/call.vbv      call n: its task, ranges and arguments (core.distributed.package.write_values)
    calls/NNNN/part-RRRR.vbv range r's result of call n
    rows/part-RRRR.vbv       range r's table and normalisation, traced by its first part command
                             and read by its later ones

Every file is a checksummed package of values (no pickle); a part command refuses a folder
written by another VisiBake.
"""
from __future__ import annotations

import inspect
import json
import os
import tempfile
from dataclasses import dataclass

from ..errors import BakeRefused
from ..kernels import blas_on_one_thread
from ..outputs.atomic import atomic_file
from ..visibility.table import TableEntries, VisibilityTable
from .package import read_package, read_values, write_values
from .rows import KeptRows, keep_rows, row_ranges
from .split import SplitTable

PACKAGE_NAME = "package.vbpkg"
PENDING_NAME = "pending.json"
TABLE_FIELDS = ("directions", "vertex_cells", "rays_cast", "rays_below_horizon", "backface_hits",
                "backface_per_sample", "traced_per_sample")
ENTRY_FIELDS = ("samples", "above_words", "word_base", "hit_object", "hit_uv_code", "hit_distance_code")


@dataclass(frozen=True)
class FarmOptions:
    """A bake run as farm steps: the job folder on shared storage and the row ranges (one part
    task per range per step)."""

    folder: str
    parts: int

    def validate(self) -> None:
        if self.parts < 1:
            raise BakeRefused(f"--parts {self.parts}: give at least 1 part")
        if not self.folder:
            raise BakeRefused("--job: give the job's folder on the farm's shared storage")

    def describe(self) -> dict:
        return {"farm": os.path.abspath(self.folder), "parts": self.parts}


class PartsPending(Exception):
    """The driver stopped at call ``call``: the parts must answer it before the next step."""

    def __init__(self, call: int, folder: str):
        super().__init__(f"step waits for the parts of call {call} in {folder}")
        self.call = call
        self.folder = folder


def _call_folder(folder: str, call: int) -> str:
    return os.path.join(folder, "calls", f"{call:04d}")


def _part_path(folder: str, call: int, index: int) -> str:
    return os.path.join(_call_folder(folder, call), f"part-{index:04d}.vbv")


def _write_pending(folder: str, state: dict) -> None:
    with atomic_file(os.path.join(folder, PENDING_NAME), "w", encoding="utf-8") as stream:
        json.dump(state, stream)


def read_pending(folder: str) -> dict:
    """The job folder's state: {"call": n} (parts to run), {"done": true}, or {} (not started)."""
    path = os.path.join(folder, PENDING_NAME)
    try:
        with open(path, encoding="utf-8") as stream:
            state = json.load(stream)
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as error:
        raise BakeRefused(f"the farm job's {path} cannot be read ({error})") from None
    if type(state) is not dict:
        raise BakeRefused(f"the farm job is damaged: {path} is not an object")
    # What the steps wrote: {"call": n} or {"done": true}; anything else is a damaged file.
    call = state.get("call")
    if not (state == {"done": True} or (state.keys() == {"call"} and type(call) is int and call >= 0)):
        raise BakeRefused(f"the farm job is damaged: {path} holds {json.dumps(state)[:200]}, not "
                          '{"call": N} (N >= 0) or {"done": true}; submit the job again with a new job folder')
    return state


def mark_done(folder: str) -> None:
    """Say in the job folder that the bake finished (later part steps have nothing to do)."""
    _write_pending(folder, {"done": True})


class FarmRows:
    """Row ranges answered by part commands through the job folder ``folder``: the executor of
    a split table on a farm (see the module's docstring). parts : the row ranges."""

    name = "farm"
    local_bytes = 0  # the driver holds none of the table

    def __init__(self, folder: str, parts: int):
        self.folder = os.path.abspath(folder)
        self.parts = int(parts)
        self.ranges: list[range] = []
        self.calls = 0

    def start(self, prepared, progress=None) -> SplitTable:
        self.ranges = row_ranges(len(prepared.position), self.parts)
        return SplitTable(self, self.run("table_stats", [()] * len(self.ranges), (), progress))

    def run(self, task: str, per_range: list[tuple], shared: tuple, progress=None) -> list:
        """The parts' results of this call, read from the folder; PartsPending (the call written
        to the folder) where they are not all there yet."""
        call = self.calls
        self.calls += 1
        paths = [_part_path(self.folder, call, index) for index in range(len(self.ranges))]
        if all(os.path.exists(path) for path in paths):
            results = []
            for number, path in enumerate(paths):
                results.append(_read_job_file(path, ("result",))["result"])
                if progress is not None:
                    progress((number + 1) / len(paths))
            return results
        os.makedirs(_call_folder(self.folder, call), exist_ok=True)
        write_values(os.path.join(_call_folder(self.folder, call), "call.vbv"),
                     {"task": task, "parts": self.parts, "ranges": [[r.start, r.stop] for r in self.ranges],
                      "per_range": [list(own) for own in per_range], "shared": list(shared)})
        _write_pending(self.folder, {"call": call})
        raise PartsPending(call, self.folder)


def _read_job_file(path: str, keys: tuple[str, ...]) -> dict:
    """The values of the job folder's file ``path``, which must hold ``keys``; BakeRefused
    (core.distributed.package.PackageRefused) naming the file where it is damaged."""
    values = read_values(path)
    missing = [key for key in keys if key not in values]
    if missing:
        raise BakeRefused(f"the farm job is damaged: {path} lacks {', '.join(missing)}")
    return values


def _read_call(path: str) -> dict:
    """The call file ``path`` (its task, ranges and arguments), its shape checked: a task of
    core.distributed.row_tasks, ranges of row numbers and one argument tuple per range."""
    from . import row_tasks

    asked = _read_job_file(path, ("task", "parts", "ranges", "per_range", "shared"))
    task, parts, ranges, per_range = asked["task"], asked["parts"], asked["ranges"], asked["per_range"]
    function = getattr(row_tasks, task, None) if type(task) is str else None
    # Only a function of row_tasks itself, not a name it imported.
    if not (inspect.isfunction(function) and function.__module__ == row_tasks.__name__):
        raise BakeRefused(f"the farm job is damaged: {path} asks for an unknown task {task!r}")
    if (type(parts) is not int or type(ranges) is not list or type(per_range) is not list
            or type(asked["shared"]) is not list or not 1 <= len(ranges) <= parts or len(per_range) != len(ranges)
            or not all(type(r) is list and len(r) == 2 and all(type(n) is int for n in r) and 0 <= r[0] <= r[1]
                       for r in ranges)
            or not all(type(own) is list for own in per_range)):
        raise BakeRefused(f"the farm job is damaged: {path} does not hold {parts!r} parts' ranges of rows and "
                          "their arguments")
    return asked


def _save_rows(path: str, checksum: str, kept: KeptRows) -> None:
    table = {name: getattr(kept.table, name) for name in TABLE_FIELDS}
    table["entries"] = {name: getattr(kept.table.entries, name) for name in ENTRY_FIELDS}
    write_values(path, {"package": checksum, "start": kept.start, "stop": kept.stop, "samples": kept.samples,
                        "table": table, "scale": kept.scale, "frame_normal": kept.frame_normal,
                        "group": kept.group})


def _load_rows(path: str, checksum: str, start: int, stop: int) -> KeptRows | None:
    if not os.path.exists(path):
        return None
    values = _read_job_file(path, ("package", "start", "stop", "samples", "table", "scale", "frame_normal", "group"))
    if values["package"] != checksum or (values["start"], values["stop"]) != (start, stop):
        return None  # another bake's rows: traced again
    table = dict(values["table"])
    table["entries"] = TableEntries(**table["entries"])
    return KeptRows(start, stop, values["samples"], VisibilityTable(**table), values["scale"],
                    values["frame_normal"], values["group"])


def run_part(folder: str, index: int, threads: int = 0) -> str:
    """Answer range ``index`` of the job folder's pending call (a part command's work): trace
    and keep the range's table the first time, then run the call's task on it. Returns what
    was done, in words; nothing when the bake is done, the range does not exist (fewer
    samples than parts) or its result is already there (a task run again). BakeRefused for a
    part beyond the job's parts, or a damaged file of the job folder (naming it)."""
    from . import row_tasks
    from .rows import packaged_bake

    folder = os.path.abspath(folder)
    state = read_pending(folder)
    if state.get("done"):
        return "nothing to do: the bake is finished"
    if "call" not in state:
        return "nothing to do: the driver has not asked for anything yet"
    call = state["call"]
    result_path = _part_path(folder, call, index)
    asked = _read_call(os.path.join(_call_folder(folder, call), "call.vbv"))
    if index >= asked["parts"]:
        raise BakeRefused(f"--part {index}: the farm job in {folder} has parts 0 to {asked['parts'] - 1}")
    if index >= len(asked["ranges"]):
        # Fewer sample rows than parts: this part's task has nothing to do.
        return f"call {call}: part {index} has no rows (the bake has {len(asked['ranges'])} ranges)"
    if os.path.exists(result_path):
        return f"call {call}, part {index}: already answered"
    start, stop = asked["ranges"][index]
    package_path = os.path.join(folder, PACKAGE_NAME)
    with blas_on_one_thread():
        checksum, bake = packaged_bake(package_path, threads)
        rows_path = os.path.join(folder, "rows", f"part-{index:04d}.vbv")
        kept = _load_rows(rows_path, checksum, start, stop)
        if kept is None:
            kept = keep_rows(bake.rows(start, stop), threads)
            os.makedirs(os.path.dirname(rows_path), exist_ok=True)
            _save_rows(rows_path, checksum, kept)
        result = getattr(row_tasks, asked["task"])(bake, kept, *asked["per_range"][index], *asked["shared"],
                                                   threads=threads)
    write_values(result_path, {"result": result})
    return f"call {call} ({asked['task']}), part {index}: rows {start} to {stop} answered"


def write_job_package(folder: str, scene, settings) -> None:
    """The first step writes the scene package; a later step checks that the folder's package
    is this bake's (a folder holds one bake: another's results must not be mixed in)."""
    from .package import write_package

    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, PACKAGE_NAME)
    if not os.path.exists(path):
        write_package(path, scene, settings)
        return
    with tempfile.TemporaryDirectory(prefix="visibake-farm-") as scratch:
        mine = write_package(os.path.join(scratch, PACKAGE_NAME), scene, settings)
    if read_package(path).checksum != mine:
        raise BakeRefused(f"the farm job folder {folder} holds another bake (its scene or settings differ): give "
                          "each job a folder of its own")


def estimated_steps(settings, lights: int, world_rotations: int) -> int:
    """About how many driver steps a bake takes (one per executor call, plus the last): the
    trace, the normalisation and exposed shares, near and short hits, one per lamp's direct
    light, the emitted gather (one per interleaved rotation under a world image), one per
    bounce and AO; two spare. A job type with fewer steps fails its last task, saying so."""
    steps = 1 + 2 + 2 + lights + max(world_rotations, 1) + settings.bounces + 1
    return steps + 2 + 1
