"""Logs of many drives into the history: each log through the same pipeline as
``canrls fit``, on a Dask cluster (or in this process), each recording stored once.

:func:`ingest_one` is what a worker runs for one log: the log's SHA-256 first (a log
whose hash the history already holds for this model is skipped), then
:func:`canrls.processor.replay.fit_logs`, and where asked the diagnosis's candidate ranking
(handed in as a ``ranker``: this layer does not import the diagnosis). A log that
cannot be fitted becomes an error :class:`~canrls.fleet.records.Recording` naming the
file and the reason. On a cluster :func:`ingest` sends every log once (a path listed
twice once), short logs several to a task (:func:`task_groups`), each task hashing its
logs and fitting them, and takes the results in the listed order (:class:`_InOrder`):
the first listed log of each content is stored, the others are named as duplicates.
In this process it hashes each log first, so a log listed again is not fitted again,
and hands that hash to the fit. Results are stored in batches with the history's
insert-or-ignore: a worker killed mid-log (Dask runs its task again elsewhere), a run
interrupted, or two runs at once still leave every recording stored exactly once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from canrls import __version__
from canrls.core.errors import CanrlsError, ConfigError, StallError
from canrls.core.files import ContentHash
from canrls.fleet import cluster
from canrls.fleet.detect import DetectionSettings, assess, to_rank
from canrls.fleet.history import History
from canrls.fleet.records import (
    SOURCE_LOG,
    STATUS_ERROR,
    CandidateValue,
    ParameterValue,
    Recording,
)
from canrls.fleet.sources import LogSource, check_name
from canrls.processor.config import AppConfig, Overrides, load_config, prepare

__all__ = ["JobConfig", "IngestJob", "IngestSummary", "Duplicate", "Ranker", "content_hash",
           "ingest", "ingest_one", "ingest_many", "task_groups", "hash_or_none", "model_key",
           "model_key_of", "RANK_MODES"]

log = logging.getLogger(__name__)

#: ``rank`` of :func:`ingest`: ``none``; ``all`` (every log); ``auto`` (after the fits,
#: the recordings around each residual change the detection finds, to name the effect)
RANK_MODES = ("none", "auto", "all")

#: ``ranker(path, protocol, model, settings, max_order)``: the candidate effects of one
#: log, best first (the command line hands in the diagnosis's ranking)
Ranker = Callable[[str, Any, Any, Any, int], Sequence[CandidateValue]]

#: results stored per transaction at most, and the longest a result waits to be stored [s]
BATCH = 64
BATCH_S = 1.0
#: bytes of logs a task takes on a cluster: short logs go several to a task (a task
#: costs the scheduler, the client and the worker some milliseconds beside its fits);
#: a log of this size or more goes alone
TASK_BYTES = 2 * 1024 * 1024
#: tasks per worker at least, where there are logs enough: a small ingest still spreads
#: over every worker, and its progress still moves
TASKS_PER_WORKER = 4


@dataclass(frozen=True)
class JobConfig(Overrides):
    """The configuration of a log's fit: a TOML file and the command line's
    :class:`~canrls.processor.config.Overrides` of ``canrls fit``. Hashable and picklable: a worker
    builds the protocol and model from it once (:meth:`prepared`)."""

    config: str | None = None

    @classmethod
    def from_overrides(cls, config: str | None, over: Overrides) -> JobConfig:
        """``over`` with the configuration file ``config``; numbers as plain floats (a
        worker unpickles them without the command line's types)."""
        kw = {f.name: getattr(over, f.name) for f in dataclasses.fields(Overrides)}
        for k, v in kw.items():
            if isinstance(v, float):
                kw[k] = float(v)
        return cls(config=config, **kw)

    def for_source(self, src: LogSource) -> JobConfig:
        """This configuration with a manifest row's overrides."""
        kw: dict[str, Any] = {}
        if src.config:
            kw["config"] = src.config
        if src.dbc:
            kw["dbc"] = src.dbc
        if src.signals:
            kw["signals"] = src.signals
        if src.kt is not None:
            kw["kt"] = src.kt
        if src.effects:
            kw["effects"] = src.effects
        return dataclasses.replace(self, **kw) if kw else self

    def app_config(self) -> AppConfig:
        return load_config(self.config, self)

    def prepared(self) -> tuple[Any, Any, Any]:
        """``(protocol, model, settings)`` as ``canrls fit`` builds them (cached per
        process: a worker builds each configuration once)."""
        got = _PREPARED.get(self)
        if got is None:
            got = _PREPARED[self] = prepare(self.app_config())
        return got


_PREPARED: dict[JobConfig, tuple[Any, Any, Any]] = {}


def hash_or_none(path: str) -> str | None:
    """:func:`content_hash`, None for a file that cannot be read (a worker's task)."""
    try:
        return content_hash(path)
    except OSError:
        return None


def model_key(cfg: JobConfig) -> tuple[str, str]:
    """``(key, description)`` of the model a configuration fits (of the axis it picks):
    :func:`model_key_of` its configuration."""
    return model_key_of(cfg.app_config().one_axis())


def model_key_of(app: AppConfig) -> tuple[str, str]:
    """``(key, description)`` of the model the configuration of one axis fits: the key is
    a SHA-256 (hex, 64) of everything that changes the parameters (the model and
    estimator tables, the fixed-point settings, the decoding options, the signal mapping
    and the DBC's bytes); the description is what a reader needs
    (``inertia,viscous,coulomb kt=0.1``)."""
    model = dict(app.model)
    effects = model.get("effects") or ["inertia", "viscous", "coulomb"]
    can = {k: v for k, v in app.can.items()
           if k not in ("interface", "channel", "bitrate", "fd", "data_bitrate", "dbc")}
    if "ids" in can and _moves_nothing(app):
        del can["ids"]  # one [[axes]] table of the DBC's own IDs: the key of no rule
    dbc = app.dbc_path()
    doc = {"model": model, "estimator": app.estimator, "fixed": app.fixed, "can": can,
           "signals": app.signals, "signal_overrides": list(app.signal_overrides),
           "dbc": None if dbc is None else hash_or_none(str(dbc))}
    key = hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()
    desc = ",".join(str(e) for e in effects)
    if model.get("kt") is not None:
        desc += f" kt={model['kt']:g}"
    if dbc is not None:
        desc += f" dbc={Path(dbc).name}"
    return key, desc


def _moves_nothing(app: AppConfig) -> bool:
    """The ID rule ``[can] ids`` leaves every mapped message on its DBC's ID
    (``offset:0``, ``cia402:1`` on a DBC written for node 1)."""
    moved = app.protocol().messages
    return [m.frame_id for m in moved] == [m.frame_id for m in
                                           app.protocol(with_rule=False).messages]


def content_hash(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = ContentHash()
    with open(path, "rb") as f:
        h.finish(f.fileno())
    return h.hexdigest()


@dataclass(frozen=True)
class IngestJob:
    """One log for a worker: where, whose, how to fit it."""

    source: LogSource
    config: JobConfig
    key: str
    model: str
    rank: bool = False
    max_order: int = 64


def _finite(x: Any) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return math.nan
    return v


def _recording(job: IngestJob, digest: str, res: Any,
               candidates: tuple[CandidateValue, ...] | None,
               rank_error: str | None) -> Recording:
    est = res.estimates
    period = res.period.value
    paired = int(res.frames.pairing.get("samples", 0))
    t0 = _finite(res.start.t0)
    t1 = t0 + paired * period if period and math.isfinite(t0) else math.nan
    eqs = {e.equation: {"fit_percent": e.fit_percent, "r2": e.r2,
                        "divergence": e.divergence, "saturations": int(sum(
                            e.saturations.values())), "low_excitation": e.low_excitation,
                        "sigma_inflation": e.sigma_inflation, "samples": e.samples}
           for e in est.equations}
    verdicts: dict[str, Any] = {
        "equations": eqs,
        "not_identifiable": [p.name for p in est.parameters if not p.identifiable],
        "rejected_frames": int(sum(res.frames.rejected.values())),
        "lost_frames": int(sum(res.frames.lost.values())),
        "period": period,
        "start_date": res.start.date,
    }
    if rank_error:
        verdicts["rank_error"] = rank_error
    params = tuple(ParameterValue(name=p.name, value=float(p.value), sigma=float(p.sigma),
                                  unit=p.unit, fixed=float(p.fixed),
                                  identifiable=bool(p.identifiable),
                                  prior_share=float(p.prior_share))
                   for p in est.parameters)
    unit = est.equations[0].unit if est.equations else ""
    return Recording(drive=job.source.drive, drive_type=job.source.drive_type,
                     content_hash=digest, model_key=job.key, model=job.model,
                     source=SOURCE_LOG, path=job.source.path, t_start=t0, t_end=t1,
                     samples=int(est.samples), frames=int(res.frames.total),
                     residual_rms=float(est.residual_rms), fit_percent=float(est.fit_percent),
                     unit=unit, verdicts=verdicts, parameters=params, candidates=candidates,
                     canrls_version=__version__)


def ingest_one(job: IngestJob, known: frozenset[str] | set[str] | None = None,
               ranker: Ranker | None = None, *, digest: str | None = None
               ) -> Recording | None:
    """One log (a worker's task): None when the history holds its hash for this model
    (``known``), else a :class:`Recording` (an error row when it cannot be fitted).
    ``digest``: the log's :func:`content_hash` when the caller has taken it already.
    Without it the log is read once, its hash taken as the fit reads it; only when
    ``known`` holds hashes (a rerun) is it hashed before, so a stored log is not fitted.
    """
    from canrls.processor.replay import fit_logs

    path = job.source.path
    if digest is None and known:
        try:
            digest = content_hash(path)
        except OSError as e:
            return _unreadable(job, known, e)
    if known is not None and digest in known:
        return None
    stream = ContentHash() if digest is None else None
    try:
        protocol, model, settings = job.config.prepared()
        res = fit_logs([path], protocol, model, settings,
                       digests=None if stream is None else [stream])
    except (CanrlsError, OSError, MemoryError) as e:
        return _failed(job, digest, known, e)
    except Exception as e:  # a bug: the row says so, the fleet goes on
        log.debug("internal error on %s", path, exc_info=True)
        return _failed(job, digest, known, e)
    if stream is not None:
        digest = stream.hexdigest()
    assert digest is not None
    candidates: tuple[CandidateValue, ...] | None = None
    rank_error = None
    if job.rank and ranker is not None:
        try:
            candidates = tuple(ranker(path, protocol, model, settings, job.max_order))
        except Exception as e:  # the fit stands without its ranking
            rank_error = f"{type(e).__name__}: {e}"
    return _recording(job, digest, res, candidates, rank_error)


def ingest_many(jobs: Sequence[IngestJob], known: frozenset[str] | set[str] | None = None,
                ranker: Ranker | None = None) -> list[Recording | None]:
    """Several short logs (a worker's task, :func:`task_groups`): :func:`ingest_one` of
    each, in order."""
    return [ingest_one(job, known, ranker) for job in jobs]


def task_groups(sizes: Sequence[int], workers: int) -> list[range]:
    """The logs of a cluster's tasks, in the listed order: consecutive logs (their
    ``sizes`` in bytes) until a task holds :data:`TASK_BYTES`, and no more logs than
    leave :data:`TASKS_PER_WORKER` tasks to each of ``workers`` (a worker: one thread).
    """
    most = max(1, len(sizes) // (TASKS_PER_WORKER * max(1, workers)))
    groups: list[range] = []
    start = total = 0
    for i, size in enumerate(sizes):
        if i > start and (total + size > TASK_BYTES or i - start >= most):
            groups.append(range(start, i))
            start, total = i, 0
        total += size
    if start < len(sizes):
        groups.append(range(start, len(sizes)))
    return groups


def _size(path: str) -> int:
    """A log's size in bytes (0 when it cannot be read: its task says why)."""
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def _unreadable_key(path: str) -> str:
    """The hash under which the error row of a log without content to hash is stored
    (keyed by the path, so a rerun does not repeat it)."""
    return hashlib.sha256(f"unreadable:{path}".encode()).hexdigest()


def _unreadable(job: IngestJob, known: frozenset[str] | set[str] | None,
                e: OSError) -> Recording | None:
    """The error row of a log that cannot be read; None when the history holds it."""
    digest = _unreadable_key(job.source.path)
    if known is not None and digest in known:
        return None
    return _error(job, digest, f"{job.source.path}: cannot read the log ({e.strerror or e})")


def _failed(job: IngestJob, digest: str | None, known: frozenset[str] | set[str] | None,
            e: BaseException) -> Recording | None:
    """The error row of a log whose fit failed with ``e``, under its hash (taken now
    when the fit did not read the log to its end; a file that is not a regular one is
    never opened again); None when the history holds that row."""
    path = job.source.path
    if digest is None:
        try:
            digest = content_hash(path) if os.path.isfile(path) else _unreadable_key(path)
        except OSError as oe:
            return _unreadable(job, known, oe)
        if known is not None and digest in known:
            return None
    if isinstance(e, CanrlsError):
        msg = str(e)
        return _error(job, digest, msg if path in msg else f"{path}: {msg}")
    if isinstance(e, (OSError, MemoryError)):
        return _error(job, digest, f"{path}: {type(e).__name__}: {e}")
    return _error(job, digest, f"{path}: internal error: {type(e).__name__}: {e} "
                               f"({traceback.extract_tb(e.__traceback__)[-1].name})")


def _error(job: IngestJob, digest: str, message: str) -> Recording:
    return Recording(drive=job.source.drive, drive_type=job.source.drive_type,
                     content_hash=digest, model_key=job.key, model=job.model,
                     status=STATUS_ERROR, source=SOURCE_LOG, path=job.source.path,
                     error=" | ".join(s.strip() for s in message.splitlines() if s.strip()),
                     canrls_version=__version__)


def rank_one(path: str, config: JobConfig, max_order: int,
             ranker: Ranker) -> tuple[CandidateValue, ...]:
    """The candidate ranking of one log (a worker's task of ``rank="auto"``)."""
    protocol, model, settings = config.prepared()
    return tuple(ranker(path, protocol, model, settings, max_order))


@dataclass(frozen=True)
class Duplicate:
    """A log listed again, under ``drive``, with the content of one listed before it
    (``owner_path`` of ``owner``): stored once, under the first listed."""

    path: str
    drive: str
    owner_path: str
    owner: str

    def format(self) -> str:
        under = (f"listed again for drive {self.owner}" if self.drive == self.owner else
                 f"listed for drive {self.drive}")
        return (f"{self.path} ({under}) is the same log as {self.owner_path}: stored once, "
                f"under drive {self.owner}")


@dataclass(frozen=True)
class IngestSummary:
    """What an ingest did."""

    total: int
    stored: int
    skipped: int
    errors: int
    #: stored meanwhile by another run (the insert found it there)
    already: int = 0
    #: logs whose task did not finish (a worker lost too often): a rerun takes them
    failed: tuple[tuple[str, str], ...] = ()
    #: recordings ranked after the fits (``rank="auto"``)
    ranked: int = 0
    elapsed_s: float = 0.0
    workers: int = 0
    #: each worker's peak resident memory [bytes] (Dask only)
    worker_peak_rss: Mapping[str, int] = field(default_factory=dict)
    error_rows: tuple[tuple[str, str], ...] = ()
    #: logs whose content another listed log has (stored once, under the first listed)
    duplicates: tuple[Duplicate, ...] = ()
    #: the recordings the logs give, one per axis of a machine's log (0: one per log)
    recordings: int = 0

    def format(self) -> str:
        rate = self.total / self.elapsed_s * 60.0 if self.elapsed_s > 0 else math.nan
        axes = (f" ({self.recordings} recordings, one per axis)"
                if self.recordings and self.recordings != self.total else "")
        lines = [f"{self.total} logs{axes}: {self.stored} stored, {self.skipped} already in the "
                 f"history, {self.errors} errors"
                 + (f", {len(self.duplicates)} duplicates" if self.duplicates else "")
                 + (f", {self.already} stored meanwhile by another run" if self.already else "")
                 + (f", {len(self.failed)} not finished (rerun to take them)"
                    if self.failed else "")
                 + f" ({self.elapsed_s:.1f} s, {rate:.0f} logs/min"
                 + (f", {self.workers} workers" if self.workers else ", in this process")
                 + ")"]
        if self.ranked:
            lines.append(f"candidate effects ranked on {self.ranked} recordings around "
                         f"residual changes")
        for d in self.duplicates[:20]:
            lines.append(f"  duplicate: {d.format()}")
        if len(self.duplicates) > 20:
            lines.append(f"  ... and {len(self.duplicates) - 20} more duplicates")
        for _, why in self.error_rows[:20]:
            lines.append(f"  error: {why}")
        if len(self.error_rows) > 20:
            lines.append(f"  ... and {len(self.error_rows) - 20} more errors")
        for path, why in self.failed[:20]:
            lines.append(f"  not finished: {path}: {why}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"total": self.total, "stored": self.stored, "skipped": self.skipped,
                "errors": self.errors, "already": self.already,
                "failed": [{"path": p, "reason": r} for p, r in self.failed],
                "error_rows": [{"path": p, "error": r} for p, r in self.error_rows],
                "duplicates": [dataclasses.asdict(d) for d in self.duplicates],
                "recordings": self.recordings or self.total,
                "ranked": self.ranked, "elapsed_s": self.elapsed_s, "workers": self.workers,
                "worker_peak_rss": dict(self.worker_peak_rss)}


class _Store:
    """Results into the history in batches (at most :data:`BATCH` per transaction, none
    waiting longer than :data:`BATCH_S`)."""

    def __init__(self, history: History) -> None:
        self.history = history
        self.pending: list[Recording] = []
        self.since = time.monotonic()
        self.stored = self.errors = self.already = 0
        self.error_rows: list[tuple[str, str]] = []

    def add(self, rec: Recording) -> None:
        if not self.pending:
            self.since = time.monotonic()
        self.pending.append(rec)
        if len(self.pending) >= BATCH or time.monotonic() - self.since >= BATCH_S:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        batch, self.pending = self.pending, []
        for rec, rid in zip(batch, self.history.store(batch), strict=True):
            if rid is None:
                self.already += 1
            elif rec.ok:
                self.stored += 1
            else:
                self.errors += 1
                self.error_rows.append((rec.path, rec.error or ""))


def ingest(sources: Sequence[LogSource], config: JobConfig, history: History, *,
           client: Any = None, rank: str = "none", ranker: Ranker | None = None,
           max_order: int = 64, progress: Callable[[int, int], None] | None = None,
           retry_errors: bool = False, stall_timeout: float | None = None,
           settings: DetectionSettings | None = None) -> IngestSummary:
    """Ingest ``sources`` into ``history``: on the Dask ``client``'s cluster, or in this
    process (``client=None``). ``rank``: one of :data:`RANK_MODES` (needs ``ranker``).
    ``progress(done, total)`` after each log. ``retry_errors``: forget the error rows of
    this model first, so their logs are tried again. ``stall_timeout``: the longest the
    cluster may go without any result (default :data:`~canrls.fleet.cluster.STALL_TIMEOUT`).
    ``settings``: the detection that picks the recordings ``rank="auto"`` ranks (default:
    the ``[fleet]`` table of ``config``'s file, as ``fleet report --config`` reads it).

    :raises StallError: the cluster stopped answering; what arrived is stored, and the
        message says how much.
    """
    if rank not in RANK_MODES:
        raise ValueError(f"rank {rank!r} not one of {RANK_MODES}")
    if rank == "auto" and settings is None:
        settings = DetectionSettings.from_file(config.config)  # a bad table: before any log
    stall = cluster.STALL_TIMEOUT if stall_timeout is None else stall_timeout
    t0 = time.monotonic()
    rejected = [(src.path, src.error) for src in sources if src.error]
    jobs: list[IngestJob] = []
    keys: dict[JobConfig, tuple[str, str]] = {}
    axes: dict[JobConfig, tuple[str, ...]] = {}
    recordings = 0
    for whole in sources:
        if whole.error:
            recordings += 1
            continue
        own = config.for_source(whole)
        try:
            for src, cfg in per_axis(whole, own, axes):
                recordings += 1
                if src.error:
                    rejected.append((src.path, src.error))
                    continue
                if cfg not in keys:
                    keys[cfg] = model_key(cfg)
                    cfg.prepared()  # a bad configuration fails here, once, before any log
                key, desc = keys[cfg]
                jobs.append(IngestJob(source=src, config=cfg, key=key, model=desc,
                                      rank=rank == "all", max_order=max_order))
        except ConfigError as e:
            if own is config or not whole.row:
                raise
            # the manifest row's dbc, config, kt, effects or signals: name the row
            raise type(e)(f"{whole.row}: {e}") from e
    if retry_errors:
        for key, _ in set(keys.values()):
            history.forget_errors(key)
    known = {key: frozenset(history.known_hashes(key)) for key, _ in set(keys.values())}
    store = _Store(history)
    failed: list[tuple[str, str]] = []
    use_ranker = ranker if rank == "all" else None
    skipped = done = 0
    duplicates: list[Duplicate] = []
    try:
        if client is None:
            # each log hashed first: a log the history holds or listed again is not fitted
            todo, duplicates = _plan(jobs, [hash_or_none(j.source.path) for j in jobs],
                                     known)
            skipped = done = len(jobs) - len(todo) - len(duplicates)
            done += len(duplicates)
            if progress is not None and done:
                progress(done, len(jobs))
            for job, digest in todo:
                rec = ingest_one(job, known[job.key], use_ranker, digest=digest)
                if rec is None:
                    skipped += 1
                else:
                    store.add(rec)
                done += 1
                if progress is not None:
                    progress(done, len(jobs))
        else:
            # each log read once, by its task (hash and fit): the history's hashes are
            # sent to every worker once, a log it holds comes back as None
            order = _InOrder(jobs, store)
            duplicates = order.duplicates
            sent: dict[tuple[str, str], int] = {}
            again: dict[int, list[int]] = {}  # a path listed again: not sent again
            for i, job in enumerate(jobs):
                first = sent.setdefault((job.key, job.source.path), i)
                if first != i:
                    again.setdefault(first, []).append(i)
            shared = {k: _scatter(client, v, stall) if v else None for k, v in known.items()}
            # one graph per model, not a message per log; short logs several to a task
            by_key: dict[str, list[int]] = {}
            for i in sent.values():
                by_key.setdefault(jobs[i].key, []).append(i)
            slots = _slots(client, stall)
            futures: dict[Any, list[int]] = {}
            for key, idx in by_key.items():
                tasks = [[idx[k] for k in g] for g in
                         task_groups([_size(jobs[i].source.path) for i in idx], slots)]
                futures.update(zip(client.map(ingest_many, [[jobs[i] for i in t] for t in tasks],
                                              known=shared[key], ranker=use_ranker,
                                              pure=False), tasks, strict=True))
            try:
                for fut, got in cluster.finished(futures, _address(client), stall):
                    task = futures[fut]
                    if fut.status != "finished":
                        why = f"{type(got).__name__}: {got}"
                        failed.extend((jobs[k].source.path, why) for i in task
                                      for k in (i, *again.get(i, ())))
                        got = [_LOST] * len(task)
                    fut.release()
                    for i, rec in zip(task, got, strict=True):
                        for k in (i, *again.get(i, ())):
                            order.arrive(k, rec)
                            done += 1
                            if progress is not None:
                                progress(done, len(jobs))
            finally:
                client.cancel(list(futures))  # sent, not awaited: never blocks
            skipped = order.skipped
        store.flush()
    except StallError as e:
        store.flush()
        raise _stall(e, store.stored + store.errors, len(jobs)) from None
    finally:
        store.flush()  # what arrived before an interruption is kept
    ranked = 0
    if rank == "auto" and ranker is not None:
        try:
            ranked = _rank_changes(history, {k for k, _ in keys.values()},
                                   {j.source.path: j.config for j in jobs}, client, ranker,
                                   max_order, stall, settings)
        except StallError as e:
            raise StallError(f"{e}; every log stored, not the candidate ranking: run again "
                             f"for it") from None
    peaks: dict[str, int] = {}
    workers = 0
    if client is not None:
        peaks = worker_peak_rss(client)
        workers = len(peaks)
    return IngestSummary(total=len(sources), stored=store.stored, skipped=skipped,
                         errors=store.errors + len(rejected), already=store.already,
                         failed=tuple(failed), ranked=ranked,
                         elapsed_s=time.monotonic() - t0, workers=workers,
                         worker_peak_rss=peaks,
                         error_rows=tuple(rejected) + tuple(store.error_rows),
                         duplicates=tuple(duplicates), recordings=recordings)


def per_axis(src: LogSource, cfg: JobConfig, cache: dict[JobConfig, tuple[str, ...]]
             ) -> list[tuple[LogSource, JobConfig]]:
    """The recordings one log of a machine gives: one per axis its configuration declares
    (``[[axes]]`` or ``--axes``; ``--axis NAME`` only that one), each under the drive
    ``MACHINE.AXIS`` with that axis's configuration; a log of one drive as it is.
    ``cache``: the axis names of each configuration, read once."""
    if cfg not in cache:
        app = cfg.app_config()
        cache[cfg] = (() if not app.axes else (cfg.axis_name,) if cfg.axis_name
                      else tuple(app.axis_configs()))
    out = []
    for name in cache[cfg]:
        drive = f"{src.drive}.{name}"
        try:
            drive = check_name(drive, "drive", src.path)
        except ConfigError as e:
            out.append((dataclasses.replace(src, drive=drive, error=str(e)), cfg))
            continue
        out.append((dataclasses.replace(src, drive=drive),
                    dataclasses.replace(cfg, axis_name=name)))
    return out or [(src, cfg)]


#: a task that did not finish (its worker lost too often)
_LOST = object()


class _InOrder:
    """The cluster's results taken in the listed order (a task's order on the cluster is
    not the listed order): of the logs with one content the first listed is stored, the
    others become :class:`Duplicate`. A result waits for those listed before it; when a
    run is interrupted, the waiting ones are not stored (a rerun fits them), so the owner
    of a content never depends on which task finished first."""

    def __init__(self, jobs: Sequence[IngestJob], store: _Store) -> None:
        self.jobs = jobs
        self.store = store
        self.waiting: dict[int, Any] = {}
        self.next = 0
        self.skipped = 0
        self.first: dict[tuple[str, str], IngestJob] = {}
        self.duplicates: list[Duplicate] = []

    def arrive(self, i: int, rec: Any) -> None:
        """The result of listed log ``i``: a :class:`Recording`, None (the history holds
        it) or :data:`_LOST`."""
        self.waiting[i] = rec
        while self.next in self.waiting:
            job, got = self.jobs[self.next], self.waiting.pop(self.next)
            self.next += 1
            if got is None:
                self.skipped += 1
            elif got is not _LOST:
                owner = self.first.setdefault((job.key, got.content_hash), job)
                if owner is job:
                    self.store.add(got)
                else:
                    self.duplicates.append(_duplicate(job, owner))


def _duplicate(job: IngestJob, owner: IngestJob) -> Duplicate:
    return Duplicate(path=job.source.path, drive=job.source.drive,
                     owner_path=owner.source.path, owner=owner.source.drive)


def _scatter(client: Any, data: Any, stall: float) -> Any:
    """``data`` on every worker once (a future the tasks take), within ``stall`` s."""
    try:
        # in a list: a set given alone is scattered element by element
        return client.scatter([data], broadcast=True, hash=False, timeout=stall)[0]
    except (TimeoutError, OSError) as e:
        raise StallError(f"the cluster at {_address(client)} did not take the history's "
                         f"hashes within {stall:g} s ({e})") from None


def _slots(client: Any, stall: float) -> int:
    """How many tasks the cluster runs at once (its workers' threads), asked within
    ``stall`` s."""
    try:
        return max(1, sum(client.nthreads(callback_timeout=stall).values()))
    except (TimeoutError, OSError) as e:
        raise StallError(f"the Dask scheduler at {_address(client)}: no answer within "
                         f"{stall:g} s when asked for its workers ({e or type(e).__name__})"
                         ) from None


def _plan(jobs: Sequence[IngestJob], hashes: Sequence[str | None],
          known: Mapping[str, frozenset[str]]
          ) -> tuple[list[tuple[IngestJob, str | None]], list[Duplicate]]:
    """The jobs to run, each with its hash (None: unreadable): not those whose content
    the history holds for their model, and of the logs with one content (a log listed
    twice, a copy under another name) only the first listed; the others are returned
    as :class:`Duplicate`."""
    todo: list[tuple[IngestJob, str | None]] = []
    duplicates: list[Duplicate] = []
    first: dict[tuple[str, str], IngestJob] = {}
    for job, digest in zip(jobs, hashes, strict=True):
        if digest is not None and digest in known[job.key]:
            continue
        if digest is not None:
            owner = first.setdefault((job.key, digest), job)
            if owner is not job:
                duplicates.append(_duplicate(job, owner))
                continue
        todo.append((job, digest))
    return todo, duplicates


def _address(client: Any) -> str:
    return str(getattr(client.scheduler, "address", None) or "?")


def _stall(e: StallError, stored: int, total: int) -> StallError:
    """``e`` with what the ingest kept."""
    return StallError(f"{e}; {stored} of the {total} logs to fit stored, each kept: run "
                      f"again for the rest")


def _peak_rss() -> int:
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def worker_peak_rss(client: Any) -> dict[str, int]:
    """Each worker process's peak resident memory [bytes]."""
    try:
        # Client.run has no timeout of its own; Client.sync takes this one
        got = client.run(_peak_rss, callback_timeout=cluster.SCHEDULER_TIMEOUT)
        return {str(k): int(v) for k, v in got.items()}
    except Exception as e:  # a worker gone: no figure rather than no summary
        log.debug("worker memory not read: %s", e)
        return {}


def _rank_changes(history: History, model_keys: Iterable[str],
                  configs: Mapping[str, JobConfig], client: Any, ranker: Ranker,
                  max_order: int, stall: float, settings: DetectionSettings | None) -> int:
    """Rank the candidate effects of the recordings around each residual change (as
    ``settings`` find them) that has no ranking yet (``rank="auto"``); returns how many
    were ranked."""
    todo: list[tuple[int, str, JobConfig]] = []
    for key in model_keys:
        recs = history.recordings(model_key=key)
        for rid, path in to_rank(assess(recs, settings=settings)):
            cfg = configs.get(path)
            if cfg is not None and Path(path).is_file():
                todo.append((rid, path, cfg))
    if not todo:
        return 0
    if client is None:
        results = [rank_one(p, c, max_order, ranker) for _, p, c in todo]
    else:
        futs = [client.submit(rank_one, p, c, max_order, ranker, pure=False)
                for _, p, c in todo]
        # a task lost: those go without a ranking
        got = {f: v if f.status == "finished" else ()
               for f, v in cluster.finished(futs, _address(client), stall)}
        results = [got[f] for f in futs]
    n = 0
    for (rid, _, _), cands in zip(todo, results, strict=True):
        if cands:
            history.add_candidates(rid, cands)
            n += 1
    return n
