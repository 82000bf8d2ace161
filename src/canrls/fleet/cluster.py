"""The Dask cluster an ingest runs on: a :class:`distributed.LocalCluster` of worker
processes (one per core, one thread each: the replay holds the GIL between its C
loops), or an existing scheduler's cluster (``--scheduler tcp://HOST:PORT``)."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from canrls.core.errors import ConfigError

__all__ = ["dask_client", "require_dask"]


def require_dask() -> Any:
    """The ``distributed`` module.

    :raises ConfigError: dask[distributed] (the ``fleet`` extra) is not installed.
    """
    try:
        import distributed
    except ImportError as e:
        raise ConfigError("ingesting on Dask needs dask[distributed], which is not "
                          "installed: pip install 'canrls[fleet]' (or --workers 0 to "
                          "ingest in this process)") from e
    return distributed


@contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, *,
                memory_limit: str | int = "auto", timeout: float = 30.0) -> Iterator[Any]:
    """A Dask client: of the cluster at ``scheduler``, else of a new
    :class:`~distributed.LocalCluster` with ``workers`` processes (default: one per
    core) on 127.0.0.1 (its HTTP server on a free port). The local cluster is closed on
    exit.

    :raises ConfigError: the scheduler cannot be reached.
    """
    distributed = require_dask()
    # the scheduler and nannies of a local cluster log every start and stop at INFO
    quiet = logging.getLogger("distributed")
    level = quiet.level
    quiet.setLevel(max(level, logging.WARNING))
    try:
        with _client(distributed, scheduler, workers, memory_limit, timeout) as client:
            yield client
    finally:
        quiet.setLevel(level)


@contextmanager
def _client(distributed: Any, scheduler: str | None, workers: int | None,
            memory_limit: str | int, timeout: float) -> Iterator[Any]:
    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout=timeout)
        except (OSError, TimeoutError) as e:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect ({e})") from e
        try:
            yield client
        finally:
            client.close()
        return
    n = workers if workers is not None else (os.cpu_count() or 1)
    if n < 1:
        raise ConfigError(f"--workers {n}: must be at least 1 (0: in this process)")
    import dask

    # the workers' statistical profiler samples the task's stack every 10 ms: on a log's
    # fit (a C loop called from Python, many short calls) it cost a third of the
    # wall time; the nannies hand this configuration to their workers. Dask's
    # MALLOC_TRIM_THRESHOLD_ (glibc hands freed memory back at 64 KiB) made each fit's
    # block buffers fresh pages again: a third slower; None leaves glibc's own rule
    with dask.config.set({"distributed.worker.profile.enabled": False,
                          "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_":
                          None}):
        cluster = distributed.LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
            # the scheduler's HTTP server starts anyway (8787 unless told): a free port
            # on the loopback, so that clusters side by side do not collide
            dashboard_address="127.0.0.1:0", memory_limit=memory_limit,
            silence_logs=logging.ERROR)
    try:
        client = distributed.Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()
