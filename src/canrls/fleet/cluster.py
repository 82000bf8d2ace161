"""The Dask cluster an ingest runs on: a :class:`distributed.LocalCluster` of worker
processes (one per core, one thread each: the replay holds the GIL between its C
loops), or an existing scheduler's cluster (``--scheduler tcp://HOST:PORT``).

Every wait on a scheduler is bounded: the address is checked before any connection,
the scheduler must answer Dask's ``identity`` within the timeout (a port that accepts
and never answers, or answers something else, is named), the client's own handshake
must end within it too, and the scheduler must have a worker. Results are awaited
with :func:`finished`: a stall of :data:`STALL_TIMEOUT` without any result raises
:class:`~canrls.core.errors.StallError` naming the address.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import re
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from canrls.core.errors import ConfigError, StallError

__all__ = ["dask_client", "require_dask", "scheduler_address", "max_workers",
           "local_workers", "finished", "SCHEDULER_TIMEOUT", "STALL_TIMEOUT",
           "WORKERS_PER_CORE", "FILES_PER_WORKER"]

log = logging.getLogger(__name__)

#: the longest any one wait on a scheduler takes (connect, answer, a worker) [s]
SCHEDULER_TIMEOUT = 30.0
#: the longest a cluster may work without any result (a log fitted or ranked)
#: before the wait ends as a stall [s]: far beyond one log's fit
STALL_TIMEOUT = 300.0
#: worker processes of a local cluster per core, at most (each fits one log at a time;
#: more than a few per core only adds memory and start-up)
WORKERS_PER_CORE = 4
#: how often a wait for results looks for one [s]
_POLL = 0.01
#: files this process holds open per worker of a local cluster (its nanny, the comms
#: to the worker and the scheduler, their pipes; about 10 measured)
FILES_PER_WORKER = 16
#: files kept for this process itself (the history, the logs, Python's own)
FILES_RESERVED = 64

_HOST_PORT = re.compile(r"^(?:\[(?P<v6>[^\]]*)\]|(?P<host>[^:/\[\]]+)):(?P<port>[0-9]{1,5})$")
_HOSTNAME = re.compile(r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
                       r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")


def scheduler_address(text: str) -> str:
    """The address of a Dask scheduler: ``tcp://HOST:PORT`` (``HOST:PORT`` means the
    same), HOST a name, an IPv4 address or ``[IPv6]``.

    :raises ConfigError: anything else, naming what is wrong.
    """
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    where = f"--scheduler {text[:200]!r}"
    if scheme.lower() != "tcp":
        raise ConfigError(f"{where}: scheme {scheme[:20]!r} is not a Dask scheduler's "
                          f"(tcp://HOST:PORT)")
    m = _HOST_PORT.match(rest)
    if m is None:
        raise ConfigError(f"{where}: not HOST:PORT (e.g. tcp://127.0.0.1:8786, "
                          f"tcp://[::1]:8786)")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ConfigError(f"{where}: port {port} is not in 1..65535")
    if m["v6"] is not None:
        try:
            ipaddress.IPv6Address(m["v6"])
        except ValueError:
            raise ConfigError(f"{where}: [{m['v6'][:60]}] is not an IPv6 address") from None
    elif not _HOSTNAME.match(m["host"]):
        raise ConfigError(f"{where}: {m['host'][:60]!r} is not a host name or address")
    return f"{scheme.lower()}://{rest}"


def max_workers(cores: int | None = None, open_files: int | None = None) -> int:
    """The most worker processes a local cluster may have here: :data:`WORKERS_PER_CORE`
    per core, and no more than the open-file limit (``RLIMIT_NOFILE``, soft) leaves
    room for at :data:`FILES_PER_WORKER` each."""
    if cores is None:
        cores = os.cpu_count() or 1
    if open_files is None:
        import resource

        open_files = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        if open_files == resource.RLIM_INFINITY:
            open_files = 1 << 20
    by_files = (open_files - FILES_RESERVED) // FILES_PER_WORKER
    return max(1, min(WORKERS_PER_CORE * cores, by_files))


def local_workers(workers: int | None) -> int:
    """How many worker processes a local cluster gets: ``workers``, or one per core
    (within :func:`max_workers`).

    :raises ConfigError: fewer than 1, or more than :func:`max_workers`.
    """
    top = max_workers()
    n = workers if workers is not None else min(os.cpu_count() or 1, top)
    if n < 1:
        raise ConfigError(f"--workers {n}: must be at least 1 (0: in this process)")
    if n > top:
        raise ConfigError(f"--workers {n}: at most {top} here ({WORKERS_PER_CORE} per "
                          f"core of {os.cpu_count() or 1}, within the open-file limit)")
    return n


async def _identity(address: str, timeout: float) -> Any:
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def _probe(address: str, timeout: float) -> None:
    """Ask the scheduler at ``address`` who it is, within ``timeout`` seconds in all.

    :raises ConfigError: no connection, no answer in time, or not a Dask scheduler's.
    """
    import asyncio

    try:
        got = asyncio.run(asyncio.wait_for(_identity(address, timeout), timeout))
    except TimeoutError:
        raise ConfigError(f"--scheduler {address}: no answer within {timeout:g} s (not a "
                          f"Dask scheduler, or one that does not respond)") from None
    except OSError as e:
        raise ConfigError(f"--scheduler {address}: cannot connect "
                          f"({_short(e) or type(e).__name__})") from e
    except Exception as e:  # whatever bytes it sent: not a Dask scheduler
        raise ConfigError(f"--scheduler {address}: does not answer as a Dask scheduler "
                          f"({type(e).__name__})") from e
    if not isinstance(got, dict) or got.get("type") != "Scheduler":
        raise ConfigError(f"--scheduler {address}: does not answer as a Dask scheduler")


def _short(e: BaseException) -> str:
    return " ".join(str(e).split())[:200]


def _connect(distributed: Any, address: str, timeout: float) -> Any:
    """A :class:`distributed.Client` of the scheduler at ``address``, within ``timeout``
    seconds: Dask bounds its TCP connect and its requests, not the handshake between
    them, so the client is made in a thread that is abandoned if it takes longer (a
    client it makes later is closed there).

    :raises ConfigError: no connection, or no handshake within ``timeout``.
    """
    box: list[Any] = []
    lock = threading.Lock()
    abandoned = False

    def make() -> None:
        client = distributed.Client.__new__(distributed.Client)
        try:
            client.__init__(address, timeout=timeout)
        except Exception as e:
            # a client that failed to start keeps its event-loop thread: stop it
            runner = getattr(client, "_loop_runner", None)
            if runner is not None:
                runner.stop()
            with lock:
                box.append(e)
            return
        with lock:
            if not abandoned:
                box.append(client)
                return
        _close(client, timeout)

    thread = threading.Thread(target=make, name="canrls-dask-connect", daemon=True)
    thread.start()
    thread.join(timeout)
    with lock:
        if not box:
            abandoned = True
            raise ConfigError(f"--scheduler {address}: no handshake within {timeout:g} s "
                              f"(a scheduler that answered, then stopped)")
        got = box[0]
    if isinstance(got, (OSError, TimeoutError)):
        raise ConfigError(f"--scheduler {address}: cannot connect "
                          f"({_short(got) or type(got).__name__})") from got
    if isinstance(got, Exception):
        raise got
    return got


def _close(client: Any, timeout: float) -> None:
    """Close ``client`` within ``timeout`` seconds; a scheduler that does not answer is
    left (it forgets the client when the connection ends)."""
    try:
        client.close(timeout=timeout)
    except (OSError, TimeoutError) as e:  # TimeoutError is an OSError; both said once
        log.debug("client not closed cleanly: %s", e)


def finished(futures: Iterable[Any], address: str, stall: float
             ) -> Iterator[tuple[Any, Any]]:
    """``(future, value)`` of each of ``futures`` as it finishes, in that order: its
    result, or for a task that failed or was cancelled its exception. The results are
    fetched by the client's event loop as the tasks end, not one round trip at a time
    from this thread.

    :raises StallError: ``stall`` seconds without any of them finishing, naming the
        scheduler's ``address``.
    """
    from distributed import as_completed

    pending = as_completed(futures, with_results=True, raise_errors=False)
    since = time.monotonic()
    while not pending.is_empty():
        ready = pending.next_batch(block=False)
        for fut, value in ready:
            # an erred task's value is Dask's (type, exception, traceback)
            yield fut, value[1] if fut.status == "error" else value
        if ready:
            since = time.monotonic()
        elif time.monotonic() - since > stall:
            raise _stalled(address, stall)
        else:
            time.sleep(_POLL)


def _stalled(address: str, stall: float) -> StallError:
    return StallError(f"the Dask scheduler at {address}: no result within {stall:g} s "
                      f"(it or its workers stopped answering)")



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
                memory_limit: str | int = "auto",
                timeout: float | None = None) -> Iterator[Any]:
    """A Dask client: of the cluster at ``scheduler``, else of a new
    :class:`~distributed.LocalCluster` with ``workers`` processes (default: one per
    core, at most :func:`max_workers`) on 127.0.0.1 (its HTTP server on a free port).
    The local cluster is closed on exit. ``timeout`` bounds each wait on the scheduler
    (default :data:`SCHEDULER_TIMEOUT`).

    :raises ConfigError: a bad address, a scheduler that cannot be reached, does not
        answer within ``timeout``, is not Dask's or has no worker; too many workers.
    """
    distributed = require_dask()
    if timeout is None:
        timeout = SCHEDULER_TIMEOUT
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
        address = scheduler_address(scheduler)
        _probe(address, timeout)
        client = _connect(distributed, address, timeout)
        try:
            try:
                client.wait_for_workers(1, timeout=timeout)
            except TimeoutError:
                raise ConfigError(f"--scheduler {address}: no worker joined its cluster "
                                  f"within {timeout:g} s") from None
            yield client
        finally:
            _close(client, timeout)
        return
    n = local_workers(workers)
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
