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

from ..errors import BakeRefused
from ..visibility.table import VisibilityTable, concatenate_columns
from .rows import row_ranges, trace_rows

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


def trace_table_on(client, package: bytes, samples: int, parts: int, progress=None) -> VisibilityTable:
    """The whole table of a packaged bake, traced as ``parts`` row ranges on ``client``'s
    workers and joined in row order: bit-identical to tracing it in one process.

    package : the package file's bytes (sent to every worker once); samples : the bake's K
    progress : callable(fraction) after each finished part, or None
    """
    from distributed import as_completed

    shared = client.scatter(package, broadcast=True)
    ranges = row_ranges(samples, parts)
    futures = [client.submit(trace_rows, shared, r.start, r.stop, pure=False, retries=TASK_RETRIES,
                             key=f"visibake-trace-rows-{r.start}-{r.stop}-{id(shared)}") for r in ranges]
    done = 0
    for _ in as_completed(futures):
        done += 1
        if progress is not None:
            progress(done / len(futures))
    return concatenate_columns(client.gather(futures))
