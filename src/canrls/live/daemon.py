"""The live service (``canrls run``): frames in from the bus, estimates out on the bus.

:class:`Daemon` wires small parts, each with one job::

    bus --BusReader--> FrameQueue --------------> estimator thread (this module):
          BusLink: open/reopen, send, faults         blocks of frames through the
                                                     FrameProcessor (make_processor)
        CommandHandler   command frames -> pipeline actions -> RlsCommandAck
        Publisher        parameter and status frames every publish_interval
        Checkpointer     resume at start, save every checkpoint_interval and at stop
    supervisor thread: reopens a vanished bus (BusLink.reopen), pings systemd's watchdog

The threads and the flow of frames, the ``[daemon]`` keys, commands, checkpoints and
systemd: docs/daemon.md.
"""

from __future__ import annotations

import collections
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np

from canrls.can.estimator_frames import ParameterReport, StatusReport
from canrls.can.frameblock import FrameBlock
from canrls.can.protocol import Protocol
from canrls.can.writers import open_writer
from canrls.core.errors import CommandError, ConfigError
from canrls.estimation.estimates import Estimates
from canrls.estimation.model import Model
from canrls.estimation.pipeline import Pipeline
from canrls.estimation.settings import EstimatorSettings
from canrls.live.bus_link import (
    COMMAND_ID,
    BusLink,
    FrameQueue,
    SharedBus,
    command_id,
    command_rows,
    messages_to_block,
    open_bus,
)
from canrls.live.checkpoint import Checkpointer
from canrls.live.commands import CommandHandler, TokenBucket
from canrls.live.daemon_settings import DaemonSettings
from canrls.live.history_hook import HistoryHook
from canrls.live.journal import JOURNAL, Journal
from canrls.live.publisher import FixedPath, Publisher, check_publishable
from canrls.live.recorder import Recorder
from canrls.live.sdnotify import SystemdNotifier
from canrls.live.signals import SignalRelay
from canrls.live.tuning import interpreter
from canrls.processor import FrameProcessor
from canrls.processor.config import AppConfig

__all__ = ["Daemon", "DaemonStats", "make_processor", "serve", "wait_until"]

log = logging.getLogger(__name__)

#: the longest the supervisor sleeps without a watchdog ping due [s] (a bus failure and
#: the stop wake it at once)
_SUPERVISOR_IDLE_S = 1.0
#: the supervisor's tick [s]: a watchdog ping goes out on the first tick at or after its
#: time (the cadence of the 50 ms poll the supervisor once was)
_SUPERVISOR_TICK_S = 0.05


def make_processor(config: DaemonSettings, protocol: Protocol, model: Model,
                   settings: EstimatorSettings) -> FrameProcessor:
    """The daemon's front end: the one place it builds a :class:`FrameProcessor`
    (at start, when resuming from a checkpoint, and for the warm-up)."""
    return FrameProcessor(protocol, model, settings)


@dataclass(frozen=True)
class DaemonStats:
    """Counters of a running daemon (all totals since start, or resume)."""

    frames: int = 0
    samples: int = 0
    blocks: int = 0
    publications: int = 0
    frames_sent: int = 0
    tx_dropped: int = 0
    tx_paused: int = 0
    rx_overflow: int = 0
    error_frames: int = 0
    bus_reopens: int = 0
    commands: int = 0
    commands_rejected: int = 0
    #: acknowledgements sent, by result (``ok``, ``rate_limited``, ``too_large``, ...)
    command_results: dict[str, int] = field(default_factory=dict)
    reloads: int = 0
    checkpoints: int = 0
    backlog: int = 0
    estimator_cpu_s: float = 0.0
    #: the bus reader's thread CPU time (0 for an axis on a machine's one bus: the
    #: machine's :attr:`~canrls.live.machine_daemon.MachineDaemon.reader_cpu_s`)
    listener_cpu_s: float = 0.0
    resumed_from: str | None = None
    counters: dict[str, int] = field(default_factory=dict)
    #: the recording (``[daemon] record``): path, frames written, frames not written
    #: after an error, errors, the first error (None: no recording)
    record: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def wait_until(check: Callable[[], bool], timeout: float) -> bool:
    """Poll ``check()`` every 5 ms until true or ``timeout`` seconds; its last answer."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(0.005)
    return check()


def serve(served: Any, stopping: threading.Event, duration: float | None,
          ready: Callable[[], object] | None = None,
          each: Callable[[], None] | None = None) -> int:
    """Start ``served`` (a :class:`Daemon` or a machine's), call ``ready``, serve until
    ``stopping`` is set (SIGTERM/SIGINT request it), ``duration`` s have passed or
    ``served.failure`` is set, then stop it; SIGHUP requests a reload; ``each`` is called
    at every wake-up (at least every 0.2 s). Signal handlers only from the main thread,
    restored after; they act from a thread of their own (:class:`SignalRelay`), never
    inside the code a signal interrupts. Returns the exit status (0, or 1 after a failure)."""
    def stop(_: int) -> None:
        served.request_stop()

    def reload(_: int) -> None:
        served.request_reload()

    with SignalRelay({signal.SIGTERM: stop, signal.SIGINT: stop, signal.SIGHUP: reload}):
        try:
            served.start()
            if ready is not None:
                ready()
            end = None if duration is None else time.monotonic() + duration
            while not stopping.is_set() and served.failure is None:
                left = 0.2 if end is None else min(0.2, end - time.monotonic())
                if left <= 0:
                    break
                stopping.wait(left)
                if each is not None:
                    each()
        finally:
            served.stop()
    return 0 if served.failure is None else 1


class Daemon:
    """The live estimator on a CAN bus.

    :param protocol: DBC and signal mapping of the drive's feedback.
    :param model: the configured model (a checkpoint may resume with effects added to it).
    :param settings: estimator settings (as ``canrls fit``).
    :param daemon: the ``[daemon]`` settings.
    :param bus: bus arguments for :func:`~canrls.live.bus_link.open_bus` (from
        :func:`~canrls.live.bus_link.bus_config`).
    :param bus_factory: opens the bus instead (tests: a faulty bus); called again to reopen.
    :param reload: returns the configured model again (SIGHUP); None: reload does nothing.
    :param notifier: systemd notifications (default: from ``$NOTIFY_SOCKET``).
    :param backpressure: when the queue is full, make the bus reader wait instead of
        dropping frames (only for simulated buses, whose drive then waits too).
    :param on_publish: called in the estimator thread after each publication with
        ``(frames processed so far, time.monotonic() when its parameter frames had
        been sent)`` (benchmarks).
    :param history: offered the estimates after each publication, closed at stop
        (``[history]``: :class:`~canrls.live.history_hook.HistoryHook`).
    :param configuration: what produced the model, kept in the file the command
        ``save_model`` writes to ``[daemon] saved_model`` (default: none recorded).
    :param fixed_path: computes the published fixed column from the frames (``canrls
        run`` and ``canrls demo``: the target's integer path, where ``[daemon] fixed``
        says so: :func:`canrls.cli.run.fixed_path_for`); None: the pipeline's kernel
        (with a warning when ``fixed = "target"`` asked for the target's path).
    """

    def __init__(self, protocol: Protocol, model: Model,
                 settings: EstimatorSettings | None = None,
                 daemon: DaemonSettings | None = None, *,
                 bus: Mapping[str, Any] | None = None,
                 bus_factory: Callable[[], can.BusABC] | None = None,
                 reload: Callable[[], Model] | None = None,
                 notifier: SystemdNotifier | None = None,
                 backpressure: bool = False,
                 on_publish: Callable[[int, float], None] | None = None,
                 history: HistoryHook | None = None,
                 configuration: AppConfig | None = None,
                 fixed_path: FixedPath | None = None) -> None:
        if bus is None and bus_factory is None:
            raise ConfigError("Daemon: give the bus arguments (bus=...) or a bus_factory")
        self.protocol = protocol
        self.settings = settings or EstimatorSettings()
        self.config = cfg = daemon or DaemonSettings()
        bus_args = dict(bus or {})
        self._bus_args = bus_args if bus_factory is None else None
        self._reload_fn = reload
        self.sd = notifier if notifier is not None else SystemdNotifier()
        # a model the frames cannot carry never runs (nor is it checkpointed)
        check_publishable(model, cfg.max_parameters, "the configured model")
        self.config_model = model
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        #: wakes the supervisor: the bus failed, or the daemon stops
        self._attention = threading.Event()
        self._stopped = threading.Event()
        self._rx_closed = threading.Event()
        self._reload_requested = threading.Event()
        self._threads: list[threading.Thread] = []
        self._recorder: Recorder | None = None
        self._record_stats: dict[str, Any] | None = None
        self._started = False
        self._tuned = False
        self._heartbeat = time.monotonic()
        self._c: collections.Counter[str] = collections.Counter()  # blocks, reloads
        #: the exception that ended the estimator or supervisor thread (None: none)
        self.failure: BaseException | None = None
        self._est_cpu = 0.0
        # the estimator, from a checkpoint if there is one that fits
        proc = make_processor(cfg, protocol, model, self.settings)
        #: the stated control period [s] (None: measured from the frames, not known yet)
        self.dt = proc.period
        self._checkpoints = Checkpointer(cfg.checkpoint, model, self.settings, self.dt,
                                         cfg.checkpoint_interval,
                                         max_parameters=cfg.max_parameters)
        self._base: dict[str, int] = {}
        self.resumed_from: str | None = None
        resumed = self._checkpoints.resume(self._restored)
        if resumed is not None:
            proc, cp = resumed
            self._base = dict(cp.counters)
            self.resumed_from = str(cfg.checkpoint)
        self._proc = proc
        # the parts
        self._queue = FrameQueue(cfg.queue_size, backpressure, self._stopping,
                                 on_error=self._recv_failed, full=cfg.max_block)
        # an axis's RlsCommand: the shipped ID + its own offset ([daemon] own_ids)
        self._command_id = self._queue.command_id = command_id(cfg.own_offset)
        # an axis of a machine takes its own frames only (the bus's filters; the
        # others never reach its queue)
        own = [(m.frame_id, m.is_extended) for m in protocol.messages] + [
            (self._command_id, False)]
        self._link = BusLink(self._queue, bus_factory or (lambda: open_bus(bus_args)), cfg,
                             describe=str(bus_args or "bus"),
                             rx_ids=own if cfg.rx_filter else ())
        if fixed_path is None and cfg.fixed == "target":
            log.warning("daemon.fixed = 'target' but no target path was given "
                        "(canrls.cli.run.fixed_path_for builds it): the published fixed "
                        "column is the kernel's on the float front end")
        self._fixed_path = fixed_path
        #: why the target's path starts again after the resume (None: it continues)
        self._fixed_resume: str | None = None
        if resumed is not None and fixed_path is not None:
            self._fixed_resume = fixed_path.resume(resumed[1].state.get("target"), proc)
        self._publisher = Publisher(proc, cfg, self._link, self._wire_counters, on_publish,
                                    fixed_path)
        self._history = history
        self._configuration = configuration or AppConfig(source="<canrls run>")
        self._journal = Journal()
        self._commands = CommandHandler(
            proc, cfg.commands, self._link.send, self._set_model, self._reset_done,
            max_parameters=cfg.max_parameters, check_model=self._check_model,
            bucket=TokenBucket(cfg.command_rate, cfg.command_burst),
            save_model=None if cfg.saved_model is None else self._save_model)

    def _reset_done(self) -> None:
        """After the command ``reset``: no online RMS yet, and the target's integer path
        (the fixed column) starts again from its prior, as the estimators did."""
        self._publisher.clear_rms()
        if self._fixed_path is not None:
            self._fixed_path.restart()
            self._journal.fixed_restarted("reset")

    def shared_bus(self) -> dict[str, Any] | None:
        """The bus arguments with which this axis may take a machine's one bus
        (:meth:`join`): its own frames only, nothing recorded, no factory of its own;
        None: it opens its own."""
        cfg = self.config
        if self._bus_args is None or not cfg.rx_filter or cfg.record is not None:
            return None
        return dict(self._bus_args)

    def join(self, hub: SharedBus) -> None:
        """Take frames from, and send on, a machine's one bus (before :meth:`start`)."""
        if self._started:
            raise RuntimeError("a running daemon cannot change its bus")
        self._link.hub = hub

    def _save_model(self) -> Path:
        """The command ``save_model``: the running model and its estimates written to
        ``[daemon] saved_model`` as ``canrls fit --save-model`` writes them (in the
        estimator thread, under its lock)."""
        from canrls.processor.modelfile import SavedModel

        proc, path = self._proc, self.config.saved_model
        assert path is not None
        if proc.calibration is None:
            raise CommandError("the calibration window has not ended: nothing is "
                               "estimated yet")
        saved = SavedModel.from_parts(proc.model, self.estimates(), proc.calibration,
                                      self._configuration, ["<canrls run>"])
        period = proc.period_info().value
        if saved.calibration is not None and period:
            saved.calibration["period"] = float(period)
        out = saved.save(path)
        log.info("save_model: the running model written to %s", out)
        return out

    def _check_model(self, model: Model, what: str = "the model") -> None:
        """:func:`~canrls.live.publisher.check_publishable` with ``[daemon] max_parameters``."""
        check_publishable(model, self.config.max_parameters, what)

    def _restored(self, model: Model, state: dict[str, Any]) -> FrameProcessor:
        # a checkpoint whose model cannot be published is set aside, not resumed
        self._check_model(model, "the checkpoint's model")
        proc = make_processor(self.config, self.protocol, model, self.settings)
        proc.restore(state, model)
        return proc

    def _stop_flag(self) -> None:
        """Mark the daemon stopping and wake the supervisor to see it."""
        self._stopping.set()
        self._attention.set()

    def _recv_failed(self, exc: BaseException) -> None:
        self._link.recv_failed(exc)
        self._attention.set()

    # ------------------------------------------------------------------ properties
    @property
    def model(self) -> Model:
        """The running model (effects added by commands included)."""
        return self._proc.model

    @property
    def pipeline(self) -> Pipeline:
        return self._proc.pipeline

    @property
    def processor(self) -> FrameProcessor:
        return self._proc

    @property
    def bus(self) -> can.BusABC | None:
        return self._link.bus

    @property
    def publisher(self) -> Publisher:
        """The parameter and status frames (published by the estimator thread)."""
        return self._publisher

    @property
    def last_status(self) -> StatusReport | None:
        """The status of the last publication."""
        return self._publisher.last_status

    def estimates(self) -> Estimates:
        """The current estimates (taken under the estimator's lock), the fixed column as
        published: the target's integer path's where it runs (NaN until it does)."""
        with self._lock:
            est = self._proc.pipeline.estimates()
            path = self._fixed_path.fixed() if self._fixed_path is not None else None
        if path is None:
            return est
        return est.with_fixed({name: v for name, (v, _) in path.items()})

    def _wire_counters(self) -> dict[str, int]:
        p, b = self._proc, self._base
        return {
            "frames_rejected": p.frames_rejected() + b.get("frames_rejected", 0),
            "frames_lost": p.frames_lost() + self._queue.overflow + b.get("frames_lost", 0),
            "saturations": int(self._proc.pipeline.saturations.total) + b.get("saturations", 0),
            "tx_dropped": self._link.counts["tx_dropped"] + b.get("tx_dropped", 0),
        }

    def stats(self) -> DaemonStats:
        c, tx, cmd, q = self._c, self._link.counts, self._commands.counts, self._queue
        with self._lock:
            counters = self._wire_counters()
        return DaemonStats(
            frames=self._proc.frames + self._base.get("frames", 0),
            samples=self._proc.pipeline.samples, blocks=c["blocks"],
            publications=self._publisher.publications, frames_sent=tx["frames_sent"],
            tx_dropped=counters["tx_dropped"], tx_paused=tx["tx_paused"],
            rx_overflow=q.overflow, error_frames=tx["error_frames"],
            bus_reopens=tx["bus_reopens"], commands=cmd["commands"],
            commands_rejected=cmd["commands_rejected"],
            command_results={k: v for k, v in cmd.items()
                             if k not in ("commands", "commands_rejected")},
            reloads=c["reloads"],
            checkpoints=self._checkpoints.saved, backlog=q.held,
            estimator_cpu_s=self._est_cpu, listener_cpu_s=q.cpu,
            resumed_from=self.resumed_from, counters=counters,
            record=self._recorder.stats() if self._recorder is not None
            else self._record_stats)

    def frame_counts(self) -> dict[str, Any]:
        """The frames the processor saw, as ``canrls fit --json`` has them under
        ``frames`` (total, rejected by reason, lost, foreign, pairing; since the start,
        a checkpoint's counters aside)."""
        with self._lock:
            return self._proc.frame_counts().to_dict()

    def status(self) -> StatusReport:
        """The status as the next RlsStatus/RlsHealth/RlsCounters would carry it."""
        with self._lock:
            return self._publisher.status(time.monotonic())

    def parameter_reports(self) -> list[ParameterReport]:
        with self._lock:
            return self._publisher.reports()[0]

    def checkpoint(self) -> Path | None:
        """Save a checkpoint now (no-op without ``[daemon] checkpoint``). A model that
        cannot be published is never saved (logged): it would stop the next start."""
        if self.config.checkpoint is None:
            return None
        with self._lock:
            try:
                self._check_model(self.model, "the running model")
            except ConfigError as e:
                log.error("checkpoint not written: %s", e)
                return None
            counters = self._wire_counters()
            counters["frames"] = self._proc.frames + self._base.get("frames", 0)
            model, state = self.model, self._proc.state()
            if self._fixed_path is not None:
                state["target"] = self._fixed_path.state()
        return self._checkpoints.save(model, state, counters)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Open the bus and start the threads (``BusError`` if the bus cannot be opened)."""
        if self._started:
            raise RuntimeError("daemon already started")
        self._started = True
        if self.config.record is not None:
            # never through a link planted at the path (python-can opens by name)
            writer = open_writer(self.config.record, f"daemon.record = {self.config.record}")
            self._recorder = Recorder(writer, self.config.record)
            self._queue.recorder = self._recorder
        try:
            self._link.open()
        except BaseException:
            self._close_recorder()
            raise
        self._heartbeat = time.monotonic()
        interpreter.tune(self.config.switch_interval)
        self._tuned = True
        if self.resumed_from is not None and self._fixed_path is not None:
            self._journal.fixed_resumed(self.resumed_from, self._fixed_resume)
        for loop, name in ((self._estimator_loop, "canrls estimator"),
                             (self._supervisor_loop, "canrls supervisor")):
            t = threading.Thread(target=loop, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("canrls daemon running on %s: effects %s, %d parameters", self._link.info(),
                 ",".join(self.model.effect_names), len(self.model.parameters))
        if self.model.per_ampere:
            log.warning("%s", self.model.per_ampere_text)

    def stop(self) -> None:
        """Stop reading, process what was queued, publish that state, checkpoint, close
        the bus. Idempotent."""
        if self._stopped.is_set() or not self._started:
            self._stop_flag()
            if not self._started:  # never to run: the checkpoint is another's to take
                self._checkpoints.close()
            return
        self.sd.stopping()
        self._stop_flag()
        self._queue.space.set()
        for t in self._threads:  # the supervisor first: no reopening from now on
            if t.name == "canrls supervisor":
                t.join()
        self._link.close_reader()
        self._rx_closed.set()  # the estimator drains the queue, then ends
        self._queue.wake_all()
        for t in self._threads:
            t.join()
        self._threads.clear()
        if self.failure is None:
            self.checkpoint()
        else:  # the state that failed is not saved: the last periodic checkpoint stays
            log.error("no checkpoint at stop: the daemon failed (%s: %s)",
                      type(self.failure).__name__, self.failure)
        self._checkpoints.close()  # the lock: another daemon may take the file now
        self._link.close()
        self._close_recorder()
        if self._history is not None:
            self._history.close()
        if self._tuned:
            self._tuned = False
            interpreter.restore()
        self._stopped.set()
        log.info("canrls daemon stopped: %s", self.stats().to_dict())

    def _close_recorder(self) -> None:
        r, self._recorder = self._recorder, None
        self._queue.recorder = None
        if r is not None:
            r.stop()  # errors logged and counted, never raised
            self._record_stats = r.stats()

    def __enter__(self) -> Daemon:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def request_stop(self) -> None:
        self._stop_flag()
        self._queue.wake.set()

    def request_reload(self) -> None:
        self._reload_requested.set()
        self._queue.wake.set()

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (or ``duration`` s), stop; SIGHUP reloads.

        Returns the exit status: 0 after a requested stop, 1 when an exception ended the
        estimator or supervisor thread (:attr:`failure`, logged with its traceback; the
        daemon then stops at once, without a final checkpoint). Signal handlers are
        installed only when called from the main thread.
        """
        return serve(self, self._stopping, duration, ready=lambda: self.sd.ready(
            f"estimating {','.join(self.model.effect_names)} on {self._link.info()}"))

    def wait_for(self, predicate: Callable[[Daemon], bool], timeout: float) -> bool:
        """Poll ``predicate(self)`` until true or ``timeout`` seconds (tests, the demo)."""
        return wait_until(lambda: predicate(self), timeout)

    def hold_input(self, hold: bool) -> None:
        """Stop (``True``) or restart taking frames from the bus listener.

        The bus reader's thread waits while the input is held, so a simulated drive with
        ``realtime=False`` (frames made as they are read) pauses with it: the demo
        holds the drive while it computes the diagnosis. On a real bus frames would
        pile up in the interface's buffer: do not hold a live bus for long.
        """
        self._queue.hold(hold)

    # ------------------------------------------------------------------ supervisor thread
    def _failed(self, where: str, exc: BaseException) -> None:
        """An exception ended a thread: logged, kept (:attr:`failure`), the daemon stops."""
        log.critical("%s thread failed; stopping the daemon (exit status 1)", where,
                     exc_info=exc)
        JOURNAL.error("fault: the %s thread failed (%s: %s); stopping", where,
                      type(exc).__name__, exc)
        if self.failure is None:
            self.failure = exc
        self._stop_flag()
        self._queue.wake.set()

    def _supervisor_loop(self) -> None:
        try:
            self._supervise()
        except Exception as e:
            self._failed("supervisor", e)

    def _supervise(self) -> None:
        """Sleeps until the next watchdog ping, a failure of the bus or the stop (not a
        poll: every wake-up of a thread costs CPU)."""
        wd = self.sd.watchdog_interval
        next_ping = 0.0
        while True:
            self._attention.clear()  # before the checks: a later set() cuts the sleep
            if self._stopping.is_set():
                return
            if self._link.failed.is_set():
                self._link.reopen(self._stopping)
                continue
            now = time.monotonic()
            if wd is not None and now >= next_ping:
                # alive = the estimator loop went round recently
                if now - self._heartbeat < wd / 2:
                    self.sd.watchdog()
                next_ping = now + wd / 4
            if wd is None:
                sleep = _SUPERVISOR_IDLE_S
            else:  # whole ticks up to the next ping
                ticks = max(1, math.ceil((next_ping - now) / _SUPERVISOR_TICK_S))
                sleep = min(ticks * _SUPERVISOR_TICK_S, _SUPERVISOR_IDLE_S)
            self._attention.wait(sleep)

    # ------------------------------------------------------------------ estimator thread
    def _estimator_loop(self) -> None:
        cfg = self.config
        pub, ckpt, q = self._publisher, self._checkpoints, self._queue
        now = time.monotonic()
        pub.start(now)
        ckpt.next_at = now + cfg.checkpoint_interval
        last_block = 0.0
        cpu0 = time.thread_time()
        try:
            while True:
                closed = self._rx_closed.is_set()
                now = time.monotonic()
                self._heartbeat = now
                if not q.queue and not closed:
                    deadline = min(pub.deadline(now), ckpt.next_at, now + 0.25)
                    q.wake.wait(max(0.0, deadline - now))
                    q.wake.clear()
                if q.queue and not closed and cfg.block_s > 0 and q.held < cfg.max_block:
                    # let frames gather, but not past a publication: it carries them (a
                    # whole block waiting, a backlog, is taken at once: FrameQueue.full)
                    until = last_block + cfg.block_s
                    if cfg.publish_interval > 0:
                        until = min(until, pub.next_at)
                    wait = until - time.monotonic()
                    if wait > 0 and not q.hurry.is_set():
                        q.hurry.wait(wait)  # a command or the end cuts it short
                q.hurry.clear()
                if q.queue:
                    last_block = time.monotonic()
                    self._drain(closed)
                if self._reload_requested.is_set():
                    self._reload_requested.clear()
                    self._reload()
                now = time.monotonic()
                last = closed and not q.queue
                if pub.due(now) or last:  # the last: the state the daemon stops in
                    pub.publish(now)
                    self._journal.published(self._link.info(), self.model, pub.last_status)
                    if self._history is not None:
                        self._history.offer(now, self.estimates, final=last)
                if ckpt.due(now):
                    self.checkpoint()
                    ckpt.next_at = now + cfg.checkpoint_interval
                self._est_cpu = time.thread_time() - cpu0
                if last:
                    break
        except Exception as e:  # never silently, never exit status 0
            self._failed("estimator", e)
        finally:
            self._est_cpu = time.thread_time() - cpu0

    def _drain(self, everything: bool) -> None:
        q = self._queue
        while q.queue:
            self.process(q.take(self.config.max_block))
            if not everything:
                break

    def process(self, frames: FrameBlock | Sequence[can.Message]) -> None:
        """Handle frames as the estimator thread does: feedback frames through the
        processor, command and error frames in stream order between them."""
        block = frames if isinstance(frames, FrameBlock) else messages_to_block(frames)
        with self._lock:
            err = block.is_error
            start = 0
            for i in np.flatnonzero(err | command_rows(block, self._command_id)).tolist():
                if err[i]:
                    self._link.error_frame(int(block.arbitration_id[i]))
                else:
                    self._estimate(block.take(slice(start, i + 1)))
                    start = i + 1
                    cmd = block.take(slice(i, i + 1)).to_messages()[0]
                    # decoded as the shipped DBC's RlsCommand (its ID moved back)
                    cmd.arbitration_id = COMMAND_ID
                    self._commands.handle(cmd)
            self._estimate(block if start == 0 else block.take(slice(start, None)))

    def _estimate(self, block: FrameBlock) -> None:
        if not len(block):
            return
        out = self._proc.process(block)
        if self._fixed_path is not None:
            self._fixed_path.feed(block, self._proc)
        self._c["blocks"] += 1
        self._publisher.absorb(out)

    # ------------------------------------------------------------------ model changes
    def _set_model(self, model: Model, why: str) -> None:
        self._proc.with_model(model)
        if self._fixed_path is not None:
            # the journal's model line says estimation restarts; the float keeps its values
            self._fixed_path.restart(float_kept=True)
        self._publisher.model_changed()
        self._journal.model_changed(model, why)

    def _reload(self) -> None:
        self._c["reloads"] += 1
        if self._reload_fn is None:
            log.info("SIGHUP: nothing to reload")
            return
        self.sd.reloading()
        try:
            new = self._reload_fn()
        except Exception as e:  # a bad file must not stop the service
            log.error("reload failed, keeping the running model: %s", e)
            self.sd.ready()
            return
        if new != self.model:
            try:
                self._check_model(new, "the reloaded model")
            except ConfigError as e:
                log.error("reload refused, keeping the running model: %s", e)
                self.sd.ready()
                return
        with self._lock:
            self.config_model = new
            self._checkpoints.config_model = new
            if new != self.model:
                self._set_model(new, "reload")
            else:
                log.info("reload: model unchanged (%s)", ",".join(new.effect_names))
        self.sd.ready()
