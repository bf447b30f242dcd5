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
from ..visibility.table import VisibilityTable, concatenate_columns
from .rows import gather_rows, row_ranges, row_summaries, trace_rows

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


class RowWork:
    """One packaged bake's sample rows on a cluster: ``parts`` row ranges, each traced by a
    worker that keeps its table, then gathered there every bounce.

    Results come back in row order and are joined, so they equal the one-process bake's bit
    for bit, whichever worker ran which range, and after a worker died (its ranges are traced
    again elsewhere, to the same bits).

    client : a dask.distributed Client; package : the package file's bytes (sent to every
    worker once); samples : the bake's K; parts : row ranges (at least the worker count, so
    that every worker has rows); threads : each task's worker threads (0: all the cores of
    its machine; with several worker processes on one machine, its share)
    """

    def __init__(self, client, package: bytes, samples: int, parts: int, threads: int = 0):
        self.client = client
        self.threads = int(threads)
        self.ranges = row_ranges(samples, parts)
        self.package = client.scatter(package, broadcast=True)
        self.placement: dict[range, str] = {}  # the worker that traced each range (and keeps its table)

    def _run(self, function, arguments, progress=None) -> list:
        """``function(package, start, stop, *arguments)`` per range, on the worker that holds the
        range's table where it is still alive; results in row order."""
        from distributed import as_completed

        futures = []
        for r in self.ranges:
            # A range goes back to the worker keeping its table; if that one died, anywhere.
            where = {"workers": [self.placement[r]], "allow_other_workers": True} if r in self.placement else {}
            futures.append(self.client.submit(function, self.package, r.start, r.stop, *arguments, pure=False,
                                              retries=TASK_RETRIES, threads=self.threads, **where))
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

    def trace(self, progress=None) -> VisibilityTable:
        """The whole table, traced by ranges (each kept where it was traced) and joined.

        It brings every range's table back to this process, which a bake split for memory
        must not do: it is for checks and for small bakes; :meth:`summaries` and
        :meth:`gather` are what the driver of a split bake needs.
        progress : callable(fraction) after each finished range, or None
        """
        return concatenate_columns(self._run(trace_rows, (), progress))

    def gather(self, radiance: np.ndarray, world: np.ndarray, progress=None) -> np.ndarray:
        """(K, C) float64: the gather of every sample from ``radiance`` (layout.size, C) float32
        and ``world`` (N, C) or (C,), by ranges on the workers (the atlas is sent to each once)."""
        shared = self.client.scatter(np.asarray(radiance), broadcast=True)
        return np.concatenate(self._run(gather_rows, (shared, np.asarray(world)), progress))

    def summaries(self) -> dict:
        """The rows' per-sample summaries (core.distributed.rows.row_summaries), joined: each (K,)."""
        parts = self._run(row_summaries, ())
        return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}
