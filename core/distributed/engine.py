"""The Dask engine: a cluster to run row tasks on, and the rules for reaching one safely.

Dask moves pickles over the network: whoever can reach a scheduler can run code on every one
of its workers. So a scheduler off loopback is only joined over TLS (``tls://``, with
distributed's Security and the user's certificates); a plain ``tcp://`` address off loopback
is refused unless the user says ``insecure``. ``workers=N`` starts a local cluster of N
processes on loopback instead (one thread each: the cores are used through processes,
without the GIL).

dask and distributed are imported here only, and only when a cluster is asked for: a bake
in one process never needs them.
"""
from __future__ import annotations

import ipaddress
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np

from ..errors import BakeRefused
from .part_tasks import run_part
from .rows import row_ranges, run_task
from .split import SplitTable

# How often the scheduler runs a task again after the worker running it died.
TASK_RETRIES = 3


class ClusterRefused(BakeRefused):
    """A scheduler address or security setting that cannot be used (the message says why)."""


@dataclass(frozen=True)
class TLSFiles:
    """The certificates of a TLS connection to a scheduler (PEM files)."""

    ca_file: str
    certificate: str
    key: str


def is_loopback(host: str) -> bool:
    """True where ``host`` (a name or an address) resolves to loopback addresses only."""
    try:
        return ipaddress.ip_address(host).is_loopback  # a literal address needs no resolver
    except ValueError:
        pass
    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except OSError:
        return False
    return bool(addresses) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)


def check_scheduler_address(address: str, tls: TLSFiles | None = None, insecure: bool = False) -> str:
    """``address`` if it may be joined, else ClusterRefused saying why.

    tcp:// is allowed on loopback, or anywhere with ``insecure``; tls:// needs ``tls``.
    """
    parts = urlsplit(address)
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or parts.port is None:
        raise ClusterRefused(f"--scheduler {address!r}: give tcp://HOST:PORT or tls://HOST:PORT")
    if parts.scheme == "tls" and tls is None:
        raise ClusterRefused(f"--scheduler {address!r}: a tls:// scheduler needs the certificates "
                             "(--tls-ca-file, --tls-cert, --tls-key)")
    if parts.scheme == "tcp" and not insecure and not is_loopback(parts.hostname):
        raise ClusterRefused(
            f"--scheduler {address!r} is not on this machine and tcp:// is not encrypted: anyone who can reach "
            "the scheduler can run code on its workers. Use tls:// with certificates, or pass --insecure on a "
            "network you trust")
    return address


# A local worker is one process of one thread: past one per core they only contend for the
# cores, each with its own copy of numpy, embree and its ranges' tables (--workers 1000 on two
# cores started 760 processes and a load of 390). Twice the cores leaves room for a worker
# waiting on its scheduler or disk.
WORKERS_PER_CORE = 2


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the system tells it)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def max_local_workers() -> int:
    """The most worker processes ``workers=N`` starts on this machine."""
    return WORKERS_PER_CORE * usable_cores()


@dataclass(frozen=True)
class ClusterOptions:
    """Where a split bake runs: a new local cluster of ``workers`` processes, or the existing
    scheduler at ``scheduler`` (with ``tls`` certificates, or ``insecure``); ``parts`` row
    ranges (None: two per worker, so that a slow or lost worker's share is small)."""

    workers: int | None = None
    scheduler: str | None = None
    tls: TLSFiles | None = None
    insecure: bool = False
    parts: int | None = None

    def validate(self) -> None:
        """ClusterRefused for a combination that cannot run."""
        if (self.workers is None) == (self.scheduler is None):
            raise ClusterRefused("give either --workers N (a local cluster) or --scheduler ADDRESS, not both")
        if self.workers is not None and self.workers < 1:
            raise ClusterRefused(f"--workers {self.workers}: give at least 1 worker process")
        if self.workers is not None and self.workers > max_local_workers():
            raise ClusterRefused(
                f"--workers {self.workers}: at most {max_local_workers()} on this machine ({usable_cores()} cores, "
                f"{WORKERS_PER_CORE} worker processes per core); more only share the same cores, each with its "
                "own memory")
        if self.parts is not None and self.parts < 1:
            raise ClusterRefused(f"--parts {self.parts}: give at least 1 row range")
        if self.scheduler is not None:
            check_scheduler_address(self.scheduler, self.tls, self.insecure)

    def describe(self) -> dict:
        """What the report says of the cluster."""
        return {"workers": self.workers, "scheduler": self.scheduler, "tls": self.tls is not None,
                "insecure": self.insecure}


def visibake_package() -> tuple[str, str]:
    """(the dotted package VisiBake's core is imported under here, without ``.core``; its
    folder): what a worker must import the tasks under (core/distributed/worker_preload.py)."""
    core = __name__.rsplit(".distributed.engine", 1)[0]
    package = core.rsplit(".", 1)[0] if "." in core else ""
    folder = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return package, folder


# The nanny's default MALLOC_TRIM_THRESHOLD_ (Dask's "trim memory") turns off glibc's
# adaptive mmap threshold, so every large numpy temporary is mapped and unmapped afresh:
# building and tracing a range ran 1.3-2.5x slower with it (docs/benchmarks.md, "Scale-out,
# part 3"). The nanny leaves a variable unset when its value is None.
NANNY_ENVIRONMENT = '{"MALLOC_TRIM_THRESHOLD_": None}'


def worker_environment() -> dict:
    """The environment of a worker process started here: this interpreter's module path (its
    numpy, embree and kernels), and VisiBake's package for the preload."""
    from .. import kernels

    package, folder = visibake_package()
    paths = [folder] + [p for p in sys.path if p and os.path.isdir(p)]
    # The kernels compiled here serve the workers too (same sources, same import name).
    return dict(os.environ, PYTHONPATH=os.pathsep.join(dict.fromkeys(paths)), VISIBAKE_PACKAGE=package,
                VISIBAKE_PACKAGE_DIR=folder, NUMBA_CACHE_DIR=kernels.cache_root(),
                DASK_DISTRIBUTED__WORKER__DAEMON="False",
                DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON=NANNY_ENVIRONMENT)


PRELOAD = os.path.join(os.path.dirname(os.path.abspath(__file__)), "worker_preload.py")
# Each process of a local cluster is started through this, so that it dies with this process.
DIE_WITH_PARENT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "die_with_parent.py")
# How long a local cluster may take to start (a worker imports numpy, embree and the kernels).
START_SECONDS = 120


class LocalProcesses:
    """A ``dask scheduler`` and ``workers`` ``dask worker`` processes on 127.0.0.1, started
    with this interpreter and stopped by :meth:`close`: what ``--workers N`` runs on. Plain
    processes (not multiprocessing), so that they start the same from Blender as from Python."""

    def __init__(self, workers: int):
        self.folder = tempfile.mkdtemp(prefix="visibake-cluster-")
        self.scheduler_file = os.path.join(self.folder, "scheduler.json")
        self.environment = worker_environment()
        self.processes: list = []
        self.logs: list = []
        self._start("scheduler", ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                                  "--no-dashboard", "--scheduler-file", self.scheduler_file, "--preload", PRELOAD])
        deadline = time.monotonic() + START_SECONDS
        while not os.path.exists(self.scheduler_file):
            if time.monotonic() > deadline or self.processes[0].poll() is not None:
                said = self.log_tail()
                self.close()
                raise RuntimeError(f"the local Dask scheduler did not start:\n{said}")
            time.sleep(0.1)
        for number in range(workers):
            self._start(f"worker-{number}", ["distributed.cli.dask_worker", "--scheduler-file", self.scheduler_file,
                                             "--nworkers", "1", "--nthreads", "1", "--no-dashboard", "--name",
                                             f"visibake-{number}", "--preload", PRELOAD, "--local-directory",
                                             os.path.join(self.folder, f"worker-{number}")])

    def _start(self, name: str, arguments: list[str]) -> None:
        log = open(os.path.join(self.folder, f"{name}.log"), "wb")  # noqa: SIM115 (closed in close())
        self.logs.append(log)
        self.processes.append(subprocess.Popen([sys.executable, DIE_WITH_PARENT, str(os.getpid()), *arguments],
                                               stdout=log, stderr=subprocess.STDOUT, env=self.environment))

    def log_tail(self, lines: int = 20) -> str:
        """The last lines each process wrote (what to show when the cluster fails to start)."""
        said = []
        for log in self.logs:
            log.flush()
            with open(log.name, encoding="utf-8", errors="replace") as stream:
                said += [f"{os.path.basename(log.name)}: {line.rstrip()}" for line in stream.readlines()[-lines:]]
        return "\n".join(said)

    def close(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.terminate()
        for process in self.processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
        for log in self.logs:
            log.close()
        shutil.rmtree(self.folder, ignore_errors=True)


@contextmanager
def cluster_client(scheduler: str | None = None, workers: int | None = None, tls: TLSFiles | None = None,
                   insecure: bool = False):
    """A dask.distributed Client, closed on leaving: of the scheduler at ``scheduler``, or of
    a new local cluster of ``workers`` processes on loopback (closed with it)."""
    ClusterOptions(workers, scheduler, tls, insecure).validate()
    try:
        from distributed import Client
        from distributed.security import Security
    except ImportError as error:
        raise ClusterRefused(f"the Dask engine is not installed here ({error}): install dask and distributed "
                             "to bake on a cluster") from None

    if scheduler:
        security = None
        if tls is not None:
            security = Security(tls_ca_file=tls.ca_file, tls_client_cert=tls.certificate, tls_client_key=tls.key,
                                require_encryption=True)
        with Client(scheduler, security=security, timeout=START_SECONDS) as client:
            yield client
        return
    processes = LocalProcesses(int(workers))
    try:
        with Client(scheduler_file=processes.scheduler_file, timeout=START_SECONDS) as client:
            try:
                client.wait_for_workers(int(workers), timeout=START_SECONDS)
            except TimeoutError:
                raise RuntimeError(f"the local Dask workers did not start:\n{processes.log_tail()}") from None
            yield client
    finally:
        processes.close()


def worker_addresses(client) -> list[str]:
    """The addresses of the cluster's workers, sorted, asked of the scheduler now.

    Not ``client.scheduler_info()["workers"]``: that returns the client's cached identity, which
    its periodic refresh (asking for no workers) can overwrite between the fetch and the read,
    so a cluster of two live workers read as none (CI, stop 35)."""
    return sorted(client.nthreads())


@contextmanager
def cluster_rows(options: ClusterOptions, package: bytes, threads: int = 0):
    """A :class:`ClusterRows` executor of the packaged bake on the cluster ``options`` names,
    closed (with a local cluster) on leaving. threads : the cores this machine's workers share
    (0: all): each local worker's tasks use its share; a remote worker's use all of its machine."""
    with cluster_parts(options, threads) as (client, parts, share):
        yield ClusterRows(client, package, parts, share)


class ClusterRows:
    """Row ranges of one packaged bake kept on a cluster's workers: the executor of a split
    table (core.distributed.split.SplitTable) whose tasks run where each range's table is;
    also of a medium's tables by ranges of voxels (core.distributed.volume_rows, with its
    ``function`` and state).

    Each range is traced by one worker, which keeps its table; every later task of the range
    goes back to that worker while it lives. Results come back in row order and are joined,
    so they equal the one-process bake's bit for bit, whichever worker ran which range, and
    after a worker died (its ranges are traced again elsewhere, to the same bits).

    client : a dask.distributed Client; package : the package file's bytes (sent to every
    worker once), or the state ``function`` takes; parts : row ranges (at least the worker
    count, so that every worker has rows); threads : each task's worker threads (0: all the
    cores of its machine; with several worker processes on one machine, its share);
    function : ``function(state, start, stop, task, *arguments, threads)`` runs a task on a
    worker (core.distributed.rows.run_task for a bake)
    """

    name = "dask"
    # Arrays larger than this go to the workers once (scattered), not inside every task.
    SCATTER_BYTES = 1 << 16
    local_bytes = 0  # the driver holds none of the table

    def __init__(self, client, package, parts: int, threads: int = 0, function=run_task):
        self.client = client
        self.parts = int(parts)
        self.threads = int(threads)
        self.function = function
        self.ranges: list[range] = []
        self.package = client.scatter(package, broadcast=True)
        self.placement: dict[range, str] = {}  # the worker that traced each range (and keeps its table)

    def start(self, prepared, progress=None) -> SplitTable:
        """Trace every range of the package's bake on the workers (``prepared`` is the driver's
        preparation of the same scene, without its table)."""
        self.ranges = row_ranges(len(prepared.position), self.parts)
        stats = self.run("table_stats", [()] * len(self.ranges), (), progress)
        differing = {s["samples"] for s in stats} - {len(prepared.position)}
        if differing:
            raise RuntimeError(f"the workers prepared {sorted(differing)} samples where this bake has "
                               f"{len(prepared.position)}: they did not prepare the same package")
        return SplitTable(self, stats)

    def run(self, task: str, per_range: list[tuple], shared: tuple, progress=None) -> list:
        """``core.distributed.row_tasks.<task>(prepared, kept rows, *per_range[i], *shared,
        threads)`` for each range i on the worker holding it where it is still alive; results
        in row order. progress : callable(fraction) after each finished range, or None."""
        shared = tuple(self.client.scatter(value, broadcast=True)
                       if isinstance(value, np.ndarray) and value.nbytes > self.SCATTER_BYTES else value
                       for value in shared)
        futures = []
        # A range not placed yet is dealt to the workers in turn: left to itself, the scheduler
        # gave three of four ranges to one of two idle workers (docs/benchmarks.md, "Scale-out, part 3").
        workers = worker_addresses(self.client)
        for number, (r, own) in enumerate(zip(self.ranges, per_range)):
            # A range goes back to the worker keeping its table; if that one died, anywhere.
            chosen = self.placement.get(r) or (workers[number % len(workers)] if workers else None)
            where = {"workers": [chosen], "allow_other_workers": True} if chosen else {}
            futures.append(self.client.submit(self.function, self.package, r.start, r.stop, task, *own, *shared,
                                              pure=False, retries=TASK_RETRIES, threads=self.threads, **where))
        results = gathered(self.client, futures, progress)
        holders = self.client.who_has(futures)
        for r, future in zip(self.ranges, futures):
            if holders.get(future.key):
                self.placement[r] = holders[future.key][0]
        return results


def run_parts(client, task: str, arguments: list[tuple], progress=None) -> list:
    """``core.distributed.part_tasks.<task>(*arguments[i])`` for every part i on the cluster,
    retried where a worker dies; results in part order. progress : callable(fraction) after
    each finished part, or None."""
    futures = [client.submit(run_part, task, *own, pure=False, retries=TASK_RETRIES) for own in arguments]
    return gathered(client, futures, progress)


def gathered(client, futures: list, progress=None) -> list:
    """The futures' results in their order, ``progress(fraction)`` after each finished one;
    ClusterRefused, saying how to start it, where the cluster cannot import VisiBake."""
    from distributed import as_completed

    try:
        for done, _ in enumerate(as_completed(futures), 1):
            if progress is not None:
                progress(done / len(futures))
        return client.gather(futures)
    except (ImportError, RuntimeError) as error:
        # A task's function is unpickled by the scheduler and by the worker: both must import
        # VisiBake's core under this process's module name.
        if not isinstance(error, ImportError) and "deserialization" not in str(error):
            raise
        package, folder = visibake_package()
        raise ClusterRefused(
            f"the cluster cannot import VisiBake ({str(error).splitlines()[0]}): start its scheduler and each "
            f"worker with `--preload {PRELOAD}` (workers also with --nthreads 1) and, in their environment, "
            f"VISIBAKE_PACKAGE={package} VISIBAKE_PACKAGE_DIR={folder} (a copy of this VisiBake on that "
            "machine) and this Python's packages") from None


@contextmanager
def cluster_parts(options: ClusterOptions, threads: int = 0):
    """(client, parts, each part's threads) of the cluster ``options`` names, closed (with a
    local cluster) on leaving: ``parts`` is options.parts, else two per worker."""
    options.validate()
    cores = threads or os.cpu_count() or 1
    with cluster_client(options.scheduler, options.workers, options.tls, options.insecure) as client:
        count = len(worker_addresses(client))
        if count < 1:
            raise ClusterRefused(f"the scheduler at {options.scheduler} has no workers")
        yield client, options.parts or 2 * count, max(1, cores // count) if options.workers else 0


def run_in_parts(options: ClusterOptions, task: str, make_arguments, threads: int = 0, progress=None,
                 stage: str = "parts") -> tuple[list, int]:
    """``core.distributed.part_tasks.<task>`` on the cluster ``options`` names, closed on
    leaving: the parts are ``make_arguments(parts, threads)`` (a list of argument tuples, from
    the cluster's part count and each part's threads; this VisiBake's version is put first).
    progress : callable(stage, fraction) or None. Returns (the results in part order, the
    number of parts)."""
    from ..version import visibake_version

    if progress is not None:
        progress("starting the cluster", 0.0)
    with cluster_parts(options, threads) as (client, parts, share):
        arguments = [(visibake_version(), *own) for own in make_arguments(parts, share)]
        report = None if progress is None else (lambda fraction: progress(stage, fraction))
        return run_parts(client, task, arguments, report), len(arguments)
