"""The Dask cluster a study runs on: an embedded ``LocalCluster`` sized to this machine, or an
existing scheduler (``--scheduler tcp://HOST:PORT``), unchanged.

The embedded one listens on 127.0.0.1 only (its HTTP routes too) and starts no dashboard; its
workers are processes with one thread each (a point is CPU-bound Python: threads would share
one interpreter lock).
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
from collections.abc import Iterator
from typing import Any

from ballbeam.errors import ClusterError, ConfigError

CONNECT_TIMEOUT_S = 20
PROBE_TIMEOUT_S = 5


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def import_studies_extra() -> None:
    """One clear line instead of an ImportError when the ``studies`` extra is missing."""
    try:
        import distributed  # noqa: F401
        import pandas  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError as error:
        raise ConfigError(
            f"sweeps need the 'studies' extra ({error.name} is missing): "
            "pip install 'ballbeam-hil[studies]'"
        ) from error


def _probe(address: str) -> None:
    """Refused at once instead of after the client's whole retry timeout: a TCP scheduler that
    nothing listens on."""
    scheme, _, rest = address.partition("://")
    host, _, port = rest.rpartition(":")
    if scheme != "tcp" or not port.isdigit():
        return  # other transports: the client says
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=PROBE_TIMEOUT_S).close()
    except OSError as error:
        raise ClusterError(
            f"cannot reach the Dask scheduler {address}: {error.strerror or error}"
        ) from error


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int | None = None) -> Iterator[Any]:
    """A connected ``distributed.Client``; an embedded cluster is closed on the way out."""
    import_studies_extra()
    from distributed import Client, LocalCluster

    if scheduler is not None:
        if workers is not None:
            raise ConfigError("--workers sizes the embedded cluster; with --scheduler the "
                              "cluster's own workers run the points")
        _probe(scheduler)
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as error:
            raise ClusterError(f"cannot reach the Dask scheduler {scheduler}: {error}") from error
        try:
            yield client
        finally:
            client.close()
        return
    try:
        cluster = LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            # The scheduler's HTTP server (health and metrics routes; no dashboard) on a free
            # loopback port rather than 8787, which another cluster may hold.
            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.ERROR,
        )
    except (OSError, TimeoutError) as error:
        raise ClusterError(f"cannot start a local Dask cluster: {error}") from error
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()


def worker_count(client: Any) -> int:
    return len(client.scheduler_info(n_workers=-1)["workers"])
