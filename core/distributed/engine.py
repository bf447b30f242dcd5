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
import socket
from contextlib import contextmanager
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np

from ..errors import BakeRefused
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


@contextmanager
def cluster_client(scheduler: str | None = None, workers: int | None = None, tls: TLSFiles | None = None,
                   insecure: bool = False):
    """A dask.distributed Client, closed on leaving: of the scheduler at ``scheduler``, or of
    a new local cluster of ``workers`` processes on loopback (closed with it)."""
    from distributed import Client, LocalCluster
    from distributed.security import Security

    if scheduler:
        check_scheduler_address(scheduler, tls, insecure)
        security = None
        if tls is not None:
            security = Security(tls_ca_file=tls.ca_file, tls_client_cert=tls.certificate, tls_client_key=tls.key,
                                require_encryption=True)
        with Client(scheduler, security=security) as client:
            yield client
        return
    if not workers or workers < 1:
        raise ClusterRefused(f"--workers {workers}: give at least 1 worker process")
    with LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


class ClusterRows:
    """Row ranges of one packaged bake kept on a cluster's workers: the executor of a split
    table (core.distributed.split.SplitTable) whose tasks run where each range's table is.

    Each range is traced by one worker, which keeps its table; every later task of the range
    goes back to that worker while it lives. Results come back in row order and are joined,
    so they equal the one-process bake's bit for bit, whichever worker ran which range, and
    after a worker died (its ranges are traced again elsewhere, to the same bits).

    client : a dask.distributed Client; package : the package file's bytes (sent to every
    worker once); parts : row ranges (at least the worker count, so that every worker has
    rows); threads : each task's worker threads (0: all the cores of its machine; with several
    worker processes on one machine, its share)
    """

    # Arrays larger than this go to the workers once (scattered), not inside every task.
    SCATTER_BYTES = 1 << 16
    local_bytes = 0  # the driver holds none of the table

    def __init__(self, client, package: bytes, parts: int, threads: int = 0):
        self.client = client
        self.parts = int(parts)
        self.threads = int(threads)
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
        from distributed import as_completed

        shared = tuple(self.client.scatter(value, broadcast=True)
                       if isinstance(value, np.ndarray) and value.nbytes > self.SCATTER_BYTES else value
                       for value in shared)
        futures = []
        for r, own in zip(self.ranges, per_range):
            # A range goes back to the worker keeping its table; if that one died, anywhere.
            where = {"workers": [self.placement[r]], "allow_other_workers": True} if r in self.placement else {}
            futures.append(self.client.submit(run_task, self.package, r.start, r.stop, task, *own, *shared,
                                              pure=False, retries=TASK_RETRIES, threads=self.threads, **where))
        done = 0
        for _ in as_completed(futures):
            done += 1
            if progress is not None:
                progress(done / len(futures))
        results = self.client.gather(futures)
        holders = self.client.who_has(futures)
        for r, future in zip(self.ranges, futures):
            if holders.get(future.key):
                self.placement[r] = holders[future.key][0]
        return results
